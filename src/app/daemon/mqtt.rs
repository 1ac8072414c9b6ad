//! The MQTT consumer of the JSON lines (`mqtt://HOST:PORT/PREFIX`, see `docs/mqtt.md`): each
//! line is published to `PREFIX/<vehicle>/<type>` on a broker by a writer task of its own, fed by
//! the sink's bounded queue like every JSON consumer ([`super::sinks`]).
//!
//! QoS 1 (at least once): the broker's PUBACK is what tells a line delivered from a line lost
//! with the connection, so both are counted (`sent`, `not_delivered`). The session is clean and a
//! line not acknowledged when the connection goes is counted, not sent again: a heading or an
//! attitude is stale by the time the broker is back.
//!
//! The writer never waits on the broker while the run loop waits on it: a broker that is down or
//! slow fills the client's own queue ([`MQTT_CLIENT_QUEUE`]) and then the sink's, and lines are
//! dropped and counted. It reconnects with an exponential back-off ([`Backoff`]).

use super::sinks::{SinkCounters, SINK_BATCH};
use crate::config::MqttUrl;
use crate::types::STATUS_TARGET;
use rumqttc::{AsyncClient, ConnectionError, Event, EventLoop, MqttOptions, Outgoing, Packet, QoS};
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::Instant;

/// The first wait before connecting again after the broker refused, went away or did not answer.
pub(super) const MQTT_RETRY_FIRST: Duration = Duration::from_millis(250);
/// The wait doubles after each failed attempt, up to this.
pub(super) const MQTT_RETRY_MAX: Duration = Duration::from_secs(8);
/// Each wait is spread at random by up to this fraction either way, so that a fleet's services do
/// not all knock at a restarted broker at the same instant.
pub(super) const MQTT_RETRY_SPREAD: f64 = 0.2;
/// A connection attempt (TCP connect and the broker's CONNACK) that takes longer has failed, s.
pub(super) const MQTT_CONNECT_TIMEOUT_S: u64 = 5;
/// The client pings a quiet broker after this long; one that has not answered by the next ping is
/// taken as gone (so a silent loss is noticed within twice this).
pub(super) const MQTT_KEEP_ALIVE: Duration = Duration::from_secs(10);
/// Lines published and not yet acknowledged, at most; more wait in the client's queue.
pub(super) const MQTT_INFLIGHT: u16 = 100;
/// Lines the client library holds before it publishes them; a line it cannot take is not
/// delivered (counted).
pub(super) const MQTT_CLIENT_QUEUE: usize = 64;
/// The largest MQTT packet sent or taken, bytes; a longer line is not delivered (counted).
pub(super) const MQTT_MAX_PACKET_BYTES: usize = 64 * 1024;
/// A PUBLISH packet's bytes besides its topic and payload, at most: the fixed header (5), the
/// topic's length (2) and the packet id (2).
const MQTT_PUBLISH_HEADER_BYTES: usize = 9;

/// The topic of a JSON line: `PREFIX/<vehicle>/<type>`, the vehicle being the line's
/// `vehicle.system_id`, or `first_system_id` for a line that names none (the first vehicle's
/// lines and the service's own). `None` for a line without a usable `type`.
pub(super) fn topic_of(prefix: &str, first_system_id: u8, line: &str) -> Option<String> {
    #[derive(serde::Deserialize)]
    struct Tag {
        system_id: u8,
    }
    #[derive(serde::Deserialize)]
    struct Head {
        #[serde(rename = "type")]
        kind: String,
        vehicle: Option<Tag>,
    }
    let head: Head = serde_json::from_str(line).ok()?;
    let level_ok = !head.kind.is_empty()
        && head
            .kind
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
    let vehicle = head.vehicle.map_or(first_system_id, |t| t.system_id);
    level_ok.then(|| format!("{prefix}/{vehicle}/{}", head.kind))
}

/// Exponential reconnection back-off: [`MQTT_RETRY_FIRST`], doubled after each failed attempt up
/// to [`MQTT_RETRY_MAX`], each wait spread by [`MQTT_RETRY_SPREAD`]; the first again once
/// connected.
#[derive(Debug, Clone, Copy)]
pub(super) struct Backoff {
    next: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            next: MQTT_RETRY_FIRST,
        }
    }
}

impl Backoff {
    /// The wait before the next attempt; the one after it is twice as long (capped).
    pub(super) fn wait(&mut self) -> Duration {
        let base = self.next;
        self.next = (base * 2).min(MQTT_RETRY_MAX);
        let spread = 1.0 + MQTT_RETRY_SPREAD * (2.0 * rand::random::<f64>() - 1.0);
        base.mul_f64(spread)
    }

    pub(super) fn reset(&mut self) {
        *self = Backoff::default();
    }
}

/// The client's options: a random client id (two services with one id would push each other
/// off the broker), a clean session, the limits above.
fn options(url: &MqttUrl) -> MqttOptions {
    let id = format!("imucald-{:012x}", rand::random::<u64>() >> 16);
    let mut o = MqttOptions::new(id, url.host.clone(), url.port);
    o.set_keep_alive(MQTT_KEEP_ALIVE)
        .set_clean_session(true)
        .set_inflight(MQTT_INFLIGHT)
        .set_max_packet_size(MQTT_MAX_PACKET_BYTES, MQTT_MAX_PACKET_BYTES);
    o
}

/// One turn of the client's event loop, owning it: polled across the writer's wake-ups and never
/// dropped half-way (a turn cut short can lose a packet it was writing).
type Turn = Pin<Box<dyn Future<Output = (EventLoop, Result<Event, ConnectionError>)> + Send>>;

fn turn(mut events: EventLoop) -> Turn {
    Box::pin(async move {
        let r = events.poll().await;
        (events, r)
    })
}

/// One connection to the broker (from its attempt to its loss) and the lines it holds.
struct Connection {
    client: AsyncClient,
    turn: Turn,
    connected: bool,
    /// Lines handed to the client and not acknowledged yet.
    held: u64,
}

/// How a connection ended.
enum Ended {
    /// The service closed the queue (shutting down).
    QueueClosed,
    /// Refused, lost or timed out: why.
    Lost(String),
}

/// What the writer tells the log about the broker (as a status of the service, like a link's).
struct BrokerLog<'a> {
    label: &'a str,
    /// When the broker was last lost (for "reconnected after"), None while connected or before
    /// the first connection.
    lost_at: Option<Instant>,
    ever_connected: bool,
    /// The current outage was already logged.
    outage_said: bool,
}

impl BrokerLog<'_> {
    fn connected(&mut self) {
        match self.lost_at.take() {
            Some(t) => tracing::info!(
                target: STATUS_TARGET,
                "{}: reconnected to the MQTT broker after {:.1} s",
                self.label,
                t.elapsed().as_secs_f64()
            ),
            None => tracing::info!(
                target: STATUS_TARGET,
                "{}: connected to the MQTT broker",
                self.label
            ),
        }
        self.ever_connected = true;
        self.outage_said = false;
    }

    fn failed(&mut self, e: &str, wait: Duration, lost: u64) {
        self.lost_at.get_or_insert_with(Instant::now);
        let wait_s = wait.as_secs_f64();
        if self.outage_said {
            tracing::debug!(
                target: STATUS_TARGET,
                "{}: MQTT broker still unreachable ({e}); next try in {wait_s:.2} s",
                self.label
            );
            return;
        }
        self.outage_said = true;
        let what = if self.ever_connected {
            "lost the MQTT broker"
        } else {
            "cannot reach the MQTT broker"
        };
        tracing::warn!(
            target: STATUS_TARGET,
            "{}: {what} ({e}), {lost} lines not acknowledged; lines are counted as not delivered until it is back (next try in {wait_s:.2} s, waits doubling to {} s)",
            self.label,
            MQTT_RETRY_MAX.as_secs_f64()
        );
    }
}

impl Connection {
    fn start(url: &MqttUrl) -> Connection {
        let (client, mut events) = AsyncClient::new(options(url), MQTT_CLIENT_QUEUE);
        events
            .network_options
            .set_connection_timeout(MQTT_CONNECT_TIMEOUT_S);
        Connection {
            client,
            turn: turn(events),
            connected: false,
            held: 0,
        }
    }

    /// Queue a line for the broker, never waiting: one the client cannot take now, or that has
    /// no topic or does not fit a packet, is not delivered (counted).
    fn hand(&mut self, line: &str, topic: Option<String>, c: &SinkCounters) {
        let payload = line.trim_end_matches('\n');
        let taken = topic
            .filter(|t| {
                t.len() + payload.len() + MQTT_PUBLISH_HEADER_BYTES <= MQTT_MAX_PACKET_BYTES
            })
            .is_some_and(|t| {
                self.client
                    .try_publish(t, QoS::AtLeastOnce, false, payload.as_bytes())
                    .is_ok()
            });
        if taken {
            self.held += 1;
        } else {
            SinkCounters::add(&c.not_delivered, 1);
        }
    }

    /// What the client's event loop said: the connection made, a line acknowledged; `Err` (why)
    /// when the connection failed.
    fn on_event(
        &mut self,
        r: Result<Event, ConnectionError>,
        c: &SinkCounters,
        log: &mut BrokerLog,
        retry: &mut Backoff,
    ) -> Result<(), String> {
        match r.map_err(|e| e.to_string())? {
            Event::Incoming(Packet::ConnAck(_)) => {
                self.connected = true;
                retry.reset();
                log.connected();
            }
            Event::Incoming(Packet::PubAck(_)) => {
                self.held = self.held.saturating_sub(1);
                SinkCounters::add(&c.sent, 1);
            }
            _ => {}
        }
        Ok(())
    }

    /// Hand the queue's lines to the client and turn its event loop until the queue closes or
    /// the connection fails.
    async fn serve(
        &mut self,
        rx: &mut mpsc::Receiver<Arc<str>>,
        route: &Route,
        c: &SinkCounters,
        log: &mut BrokerLog<'_>,
        retry: &mut Backoff,
    ) -> Ended {
        let mut batch = Vec::with_capacity(SINK_BATCH);
        loop {
            tokio::select! {
                n = rx.recv_many(&mut batch, SINK_BATCH) => {
                    if n == 0 {
                        return Ended::QueueClosed;
                    }
                    for line in batch.drain(..) {
                        self.hand(&line, route.topic(&line), c);
                    }
                }
                (events, r) = &mut self.turn => {
                    self.turn = turn(events);
                    if let Err(e) = self.on_event(r, c, log, retry) {
                        return Ended::Lost(e);
                    }
                }
            }
        }
    }

    /// At shutdown: wait for the acknowledgements of the lines held, then say goodbye to the
    /// broker. The service's exit deadline cuts this short (the task is aborted).
    async fn finish(mut self, c: &SinkCounters, log: &mut BrokerLog<'_>, retry: &mut Backoff) {
        while self.connected && self.held > 0 {
            let (events, r) = (&mut self.turn).await;
            self.turn = turn(events);
            if self.on_event(r, c, log, retry).is_err() {
                break;
            }
        }
        if self.connected && self.held == 0 && self.client.try_disconnect().is_ok() {
            loop {
                let (events, r) = (&mut self.turn).await;
                self.turn = turn(events);
                if matches!(r, Ok(Event::Outgoing(Outgoing::Disconnect)) | Err(_)) {
                    break;
                }
            }
        }
        SinkCounters::add(&c.not_delivered, self.held);
    }
}

/// Where lines go: the prefix and the first vehicle's system id.
struct Route {
    prefix: String,
    first_system_id: u8,
}

impl Route {
    fn topic(&self, line: &str) -> Option<String> {
        topic_of(&self.prefix, self.first_system_id, line)
    }
}

/// Count the queue's lines as not delivered until `until`; false when the queue closed.
async fn drop_until(rx: &mut mpsc::Receiver<Arc<str>>, until: Instant, c: &SinkCounters) -> bool {
    let mut batch = Vec::with_capacity(SINK_BATCH);
    loop {
        tokio::select! {
            n = rx.recv_many(&mut batch, SINK_BATCH) => {
                if n == 0 {
                    return false;
                }
                SinkCounters::add(&c.not_delivered, n as u64);
                batch.clear();
            }
            _ = tokio::time::sleep_until(until) => return true,
        }
    }
}

/// The MQTT consumer's writer task: connect, publish what the queue brings, and after a failure
/// wait (counting the lines that come meanwhile as not delivered) and connect again.
/// `label` is the consumer as configured; lines without a vehicle go under `first_system_id`.
pub(super) async fn mqtt_writer(
    label: String,
    url: MqttUrl,
    first_system_id: u8,
    mut rx: mpsc::Receiver<Arc<str>>,
    c: Arc<SinkCounters>,
) {
    let route = Route {
        prefix: url.prefix.clone(),
        first_system_id,
    };
    let mut log = BrokerLog {
        label: &label,
        lost_at: None,
        ever_connected: false,
        outage_said: false,
    };
    let mut retry = Backoff::default();
    loop {
        let mut conn = Connection::start(&url);
        match conn.serve(&mut rx, &route, &c, &mut log, &mut retry).await {
            Ended::QueueClosed => {
                conn.finish(&c, &mut log, &mut retry).await;
                return;
            }
            Ended::Lost(e) => {
                // Every line the client held is gone with it (a clean session is not resumed).
                SinkCounters::add(&c.not_delivered, conn.held);
                let wait = retry.wait();
                log.failed(&e, wait, conn.held);
                drop(conn);
                if !drop_until(&mut rx, Instant::now() + wait, &c).await {
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::sinks::{close_sinks, Sink};
    use super::*;
    use crate::io::mavout::{json_line, json_line_for, LiveEvent, VehicleTag};

    #[test]
    fn mqtt_topic_is_prefix_vehicle_type() {
        let status = LiveEvent::Status {
            level: "info".into(),
            text: "x".into(),
        };
        assert_eq!(
            topic_of("fleet/a", 3, &json_line(&status)).as_deref(),
            Some("fleet/a/3/status")
        );
        let tag = VehicleTag {
            link: "udpin:0.0.0.0:14550".into(),
            system_id: 42,
        };
        let heading = LiveEvent::Heading {
            t: 1.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            heading_deg: 90.0,
            true_heading: false,
        };
        assert_eq!(
            topic_of("fleet", 1, &json_line_for(&heading, Some(&tag))).as_deref(),
            Some("fleet/42/heading")
        );
        for bad in [
            "",
            "{}",
            "not json",
            r#"{"type":"a/b"}"#,
            r##"{"type":"#"}"##,
            r#"{"type":""}"#,
        ] {
            assert_eq!(topic_of("fleet", 1, bad), None, "{bad}");
        }
    }

    #[test]
    fn mqtt_backoff_doubles_to_its_cap_and_starts_over() {
        let mut b = Backoff::default();
        let near = |d: Duration, base: Duration| {
            let r = d.as_secs_f64() / base.as_secs_f64();
            (1.0 - MQTT_RETRY_SPREAD..=1.0 + MQTT_RETRY_SPREAD).contains(&r)
        };
        let mut base = MQTT_RETRY_FIRST;
        for _ in 0..12 {
            let w = b.wait();
            assert!(near(w, base), "{w:?} for {base:?}");
            base = (base * 2).min(MQTT_RETRY_MAX);
        }
        assert_eq!(base, MQTT_RETRY_MAX);
        b.reset();
        assert!(near(b.wait(), MQTT_RETRY_FIRST));
    }

    /// No broker at the address: every line is counted (as not delivered, or dropped with the
    /// queue full), none as sent, and the consumer closes by the exit deadline.
    #[tokio::test]
    async fn sinks_mqtt_without_a_broker_counts_every_line_and_closes_in_time() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut sinks = vec![Sink::open(&format!("mqtt://127.0.0.1:{port}/t"), 1).unwrap()];
        let line: Arc<str> = json_line(&LiveEvent::Status {
            level: "info".into(),
            text: "x".into(),
        })
        .into();
        for _ in 0..3000 {
            sinks[0].send(&line);
        }
        // Let the writer fail to connect and count (the refusal on loopback is immediate).
        let until = std::time::Instant::now() + Duration::from_secs(5);
        while sinks[0].lost() < 3000 && std::time::Instant::now() < until {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        let r = sinks[0].report();
        assert_eq!(r.sent, 0);
        assert_eq!(r.queue_full + r.not_delivered, 3000, "{r:?}");
        assert!(r.not_delivered > 0, "{r:?}");
        let t1 = tokio::time::Instant::now();
        close_sinks(&mut sinks, t1 + Duration::from_millis(100)).await;
        assert!(t1.elapsed() < Duration::from_millis(500));
    }
}
