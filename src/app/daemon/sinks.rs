//! The JSON-line consumers: one bounded queue and one writer per consumer (stdout on a thread,
//! UDP, TCP and MQTT as tasks); a full queue drops and counts, never waits.

use super::*;
use crate::config::PublishTarget;

/// Lines a JSON consumer's queue holds; more while it is not taking them are dropped and counted.
pub(super) const SINK_QUEUE_LINES: usize = 1024;
/// How long the JSON writers get at shutdown to pass on what is queued, before they are dropped.
pub(super) const SINK_DRAIN_AT_EXIT: Duration = Duration::from_millis(150);
/// A TCP JSON consumer that refused or did not answer is tried again after this long.
pub(super) const SINK_TCP_RETRY: Duration = Duration::from_secs(1);
/// Lost JSON lines and MAVLink datagrams are reported (JSON `status`, log) at most this often, s.
pub(super) const DROPS_REPORT_S: f64 = 5.0;
/// Lines a writer takes from its queue per wake-up.
pub(super) const SINK_BATCH: usize = 64;

/// What became of the lines for one JSON consumer (shared with its writer).
#[derive(Debug, Default)]
pub(super) struct SinkCounters {
    /// Handed to the consumer (written to stdout or the socket).
    pub(super) sent: std::sync::atomic::AtomicU64,
    /// Dropped by the run loop: the consumer's queue was full (it is not taking lines).
    pub(super) queue_full: std::sync::atomic::AtomicU64,
    /// Taken by the writer but not delivered: no connection, the socket refused it.
    pub(super) not_delivered: std::sync::atomic::AtomicU64,
}

impl SinkCounters {
    pub(super) fn add(c: &std::sync::atomic::AtomicU64, n: u64) {
        c.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
    }
    pub(super) fn get(c: &std::sync::atomic::AtomicU64) -> u64 {
        c.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Where a JSON consumer's writer runs.
pub(super) enum SinkWriter {
    /// A tokio task (UDP, TCP): aborted at shutdown when it has not finished.
    Task(tokio::task::JoinHandle<()>),
    /// A thread of its own (stdout, whose writes block): the receiver resolves when it ends; a
    /// thread still blocked at shutdown is left behind (it ends with the process).
    Thread(tokio::sync::oneshot::Receiver<()>),
}

/// A JSON-lines consumer: a writer of its own fed through a bounded queue, so that a consumer that
/// stops reading (a full pipe, a TCP peer that does not read) loses lines, counted, and never holds
/// the run loop.
pub(super) struct Sink {
    /// The address as configured (`stdout`, `udp:IP:PORT`, `tcp:IP:PORT`,
    /// `mqtt://HOST:PORT/PREFIX`).
    pub(super) label: String,
    pub(super) tx: Option<mpsc::Sender<std::sync::Arc<str>>>,
    pub(super) counters: std::sync::Arc<SinkCounters>,
    pub(super) writer: Option<SinkWriter>,
    /// Lines lost (queue full + not delivered) when they were last reported.
    pub(super) lost_reported: u64,
}

impl Sink {
    /// The consumer at `spec`. `first_system_id`: the MAVLink system id of the first vehicle
    /// calibrated (`daemon.target_system`), whose lines name no vehicle; an MQTT consumer puts
    /// them under it.
    pub(super) fn open(spec: &str, first_system_id: u8) -> Result<Sink, Error> {
        let target = PublishTarget::parse(spec).map_err(|message| Error::Config {
            key: "publish".into(),
            message,
        })?;
        let (tx, rx) = mpsc::channel::<std::sync::Arc<str>>(SINK_QUEUE_LINES);
        let counters = std::sync::Arc::new(SinkCounters::default());
        let c = counters.clone();
        let writer = match target {
            PublishTarget::Stdout => {
                let (done_tx, done_rx) = tokio::sync::oneshot::channel();
                std::thread::Builder::new()
                    .name("imucald-stdout".into())
                    .spawn(move || {
                        stdout_writer(rx, &c);
                        let _ = done_tx.send(());
                    })
                    .map_err(|e| Error::Other(format!("publish {spec}: {e}")))?;
                SinkWriter::Thread(done_rx)
            }
            PublishTarget::Udp(addr) => {
                let bind = match (addr.ip().is_loopback(), addr.is_ipv4()) {
                    (true, true) => "127.0.0.1:0",
                    (true, false) => "[::1]:0",
                    (false, true) => "0.0.0.0:0",
                    (false, false) => "[::]:0",
                };
                let sock = std::net::UdpSocket::bind(bind)
                    .and_then(|s| s.set_nonblocking(true).map(|()| s))
                    .map_err(|e| Error::Other(format!("publish {spec}: {e}")))?;
                SinkWriter::Task(tokio::spawn(udp_writer(sock, addr, rx, c)))
            }
            PublishTarget::Tcp(addr) => SinkWriter::Task(tokio::spawn(tcp_writer(addr, rx, c))),
            PublishTarget::Mqtt(url) => {
                let writer = mqtt::mqtt_writer(spec.to_string(), url, first_system_id, rx, c);
                SinkWriter::Task(tokio::spawn(writer))
            }
        };
        Ok(Sink {
            label: spec.to_string(),
            tx: Some(tx),
            counters,
            writer: Some(writer),
            lost_reported: 0,
        })
    }

    /// The live page's consumer: its writer hands the lines to the page's hub (`crate::app::ui`).
    pub(super) fn ui(feed: crate::app::ui::server::Feed) -> Sink {
        let (tx, mut rx) = mpsc::channel::<std::sync::Arc<str>>(SINK_QUEUE_LINES);
        let counters = std::sync::Arc::new(SinkCounters::default());
        let c = counters.clone();
        let task = tokio::spawn(async move {
            let mut batch = Vec::with_capacity(SINK_BATCH);
            while rx.recv_many(&mut batch, SINK_BATCH).await > 0 {
                for line in batch.drain(..) {
                    feed.line(&line);
                    SinkCounters::add(&c.sent, 1);
                }
            }
        });
        Sink {
            label: "ui".into(),
            tx: Some(tx),
            counters,
            writer: Some(SinkWriter::Task(task)),
            lost_reported: 0,
        }
    }

    /// Queue a line; never waits. A full queue drops it (counted).
    pub(super) fn send(&self, line: &std::sync::Arc<str>) {
        if let Some(tx) = &self.tx {
            if tx.try_send(line.clone()).is_err() {
                SinkCounters::add(&self.counters.queue_full, 1);
            }
        }
    }

    /// Lines that did not reach the consumer so far.
    pub(super) fn lost(&self) -> u64 {
        SinkCounters::get(&self.counters.queue_full)
            + SinkCounters::get(&self.counters.not_delivered)
    }

    pub(super) fn report(&self) -> crate::report::SinkReport {
        crate::report::SinkReport {
            sink: self.label.clone(),
            sent: SinkCounters::get(&self.counters.sent),
            queue_full: SinkCounters::get(&self.counters.queue_full),
            not_delivered: SinkCounters::get(&self.counters.not_delivered),
        }
    }
}

/// Close the queues and give the writers until `deadline` to pass on what is queued; then stop
/// those still writing (a consumer that does not read cannot hold the exit).
pub(super) async fn close_sinks(sinks: &mut [Sink], deadline: tokio::time::Instant) {
    for s in sinks.iter_mut() {
        s.tx = None;
    }
    for s in sinks.iter_mut() {
        match s.writer.take() {
            Some(SinkWriter::Task(mut h)) => {
                let finished = tokio::time::timeout_at(deadline, &mut h).await.is_ok();
                if !finished {
                    h.abort();
                }
            }
            Some(SinkWriter::Thread(done)) => {
                let _ = tokio::time::timeout_at(deadline, done).await;
            }
            None => {}
        }
    }
}

/// The stdout consumer's thread: blocking writes (a full pipe blocks this thread only).
pub(super) fn stdout_writer(mut rx: mpsc::Receiver<std::sync::Arc<str>>, c: &SinkCounters) {
    use std::io::Write;
    let mut batch = Vec::with_capacity(SINK_BATCH);
    while rx.blocking_recv_many(&mut batch, SINK_BATCH) > 0 {
        let mut out = std::io::stdout().lock();
        for line in batch.drain(..) {
            match out.write_all(line.as_bytes()) {
                Ok(()) => SinkCounters::add(&c.sent, 1),
                Err(_) => SinkCounters::add(&c.not_delivered, 1),
            }
        }
        let _ = out.flush();
    }
}

/// A UDP consumer's writer: one datagram per line on a plain non-blocking socket, not registered
/// with tokio (a registered one reports write readiness after every datagram sent, a wake-up that
/// nothing waits for). A datagram the kernel cannot take at once is dropped, as UDP may anyway.
pub(super) async fn udp_writer(
    sock: std::net::UdpSocket,
    addr: std::net::SocketAddr,
    mut rx: mpsc::Receiver<std::sync::Arc<str>>,
    c: std::sync::Arc<SinkCounters>,
) {
    let mut batch = Vec::with_capacity(SINK_BATCH);
    while rx.recv_many(&mut batch, SINK_BATCH).await > 0 {
        for line in batch.drain(..) {
            match sock.send_to(line.as_bytes(), addr) {
                Ok(_) => SinkCounters::add(&c.sent, 1),
                Err(_) => SinkCounters::add(&c.not_delivered, 1),
            }
        }
    }
}

/// A TCP consumer's writer: connects when there is something to send (again after
/// [`SINK_TCP_RETRY`] when that failed), writes what is queued in one go; a consumer that stops
/// reading blocks this task only, and its queue fills.
pub(super) async fn tcp_writer(
    addr: std::net::SocketAddr,
    mut rx: mpsc::Receiver<std::sync::Arc<str>>,
    c: std::sync::Arc<SinkCounters>,
) {
    use tokio::io::AsyncWriteExt;
    let mut conn: Option<tokio::net::TcpStream> = None;
    let mut retry_at = tokio::time::Instant::now();
    let mut batch = Vec::with_capacity(SINK_BATCH);
    let mut buf = String::new();
    loop {
        let n = rx.recv_many(&mut batch, SINK_BATCH).await;
        if n == 0 {
            break;
        }
        if conn.is_none() && tokio::time::Instant::now() >= retry_at {
            conn = tokio::time::timeout(SINK_TCP_RETRY, tokio::net::TcpStream::connect(addr))
                .await
                .ok()
                .and_then(|r| r.ok());
            if conn.is_none() {
                retry_at = tokio::time::Instant::now() + SINK_TCP_RETRY;
            }
        }
        buf.clear();
        for line in batch.drain(..) {
            buf.push_str(&line);
        }
        let delivered = match conn.as_mut() {
            Some(s) => s.write_all(buf.as_bytes()).await.is_ok(),
            None => false,
        };
        if delivered {
            SinkCounters::add(&c.sent, n as u64);
        } else {
            conn = None;
            SinkCounters::add(&c.not_delivered, n as u64);
        }
    }
}
