//! Live transports: the only code that knows sockets, serial ports and the wall clock of a replay.
//!
//! One address per link (`udpin:`, `udpout:`, `tcpout:`, `tcpin:`, `serial:`, `file:`, `sim:`),
//! like rust-mavlink's `connect`, but the bytes are read here and framed by
//! [`crate::io::decode`], so MAVLink v1 and v2 are both accepted and every bad frame is counted.
//!
//! Each link runs as one tokio task started by [`spawn_link`] and reports what it reads as
//! [`Inbound`] items on a shared bounded channel:
//! - live links (udp, tcp, serial) never wait on that channel: when it is full the item is
//!   dropped and counted in [`LinkCounters::inbound_dropped`];
//! - replays (`file:`, `sim:`) wait for room instead (nothing is lost), paced by their own
//!   timestamps divided by `speed` (0 = as fast as possible).
//!
//! A live link that fails (refused, closed, serial port gone, I/O error) reports
//! [`LinkStatus::Lost`] once, then retries with exponential backoff until it is back
//! ([`LinkStatus::Connected`]). Nothing here panics on bad input or a vanished peer, and every
//! loop watches the shutdown flag. How the first opening went (the bound local address, the port
//! the system chose for port 0, or why it failed) is told once, on [`LinkHandle::opening`].

use crate::io::decode::{
    self, DecodeStats, Frame, FrameDecoder, FrameParse, SkipReason, TlogRecords,
};

mod address;
mod grid;
mod live;
mod queue;
mod replay;
mod text;
mod udp;
mod udp_batch;
use crate::error::Error;
use crate::types::Sample;
pub use address::*;
pub(crate) use grid::GridTimer;
use live::{run_dialled, run_tcp_in};
pub(crate) use queue::{inbound_queue, InboundRx, InboundTx, Queued};
use replay::{run_file, run_sim};
use std::collections::BTreeMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
pub use text::*;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use udp::{decode_datagram, merge_stats, POLL_MIN};

// ---------------------------------------------------------------------------------------------
// Public types

/// What the bytes of a link are.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Payload {
    /// MAVLink v1/v2 frames.
    #[default]
    Mavlink,
    /// MotionCal text lines `Raw:ax,ay,az,gx,gy,gz,mx,my,mz` (int16 counts).
    MotionCal,
    /// Comma-separated numbers per line in the order of `fields` (t, ax, ay, az, gx, gy, gz, mx,
    /// my, mz, temp, throttle, current, ref_qw, ref_qx, ref_qy, ref_qz, moving, lat, lon, alt; `_` or an empty
    /// name ignores a column), each multiplied by its scale. No `t` field: arrival time.
    Csv {
        fields: Vec<String>,
        scales: BTreeMap<String, f64>,
    },
}

/// The field names a [`Payload::Csv`] line may carry (those of `decode`'s CSV reader).
pub(crate) const CSV_FIELDS: [&str; crate::io::decode::FIELDS.len()] = crate::io::decode::FIELDS;

impl Payload {
    /// Check a CSV payload's field names and scales (the others are always valid).
    pub fn check(&self) -> Result<(), Error> {
        let Payload::Csv { fields, scales } = self else {
            return Ok(());
        };
        let err = |message: String| Error::Config {
            key: "fields".into(),
            message,
        };
        for f in fields {
            if !(f.is_empty() || f == "_" || CSV_FIELDS.contains(&f.as_str())) {
                return Err(err(format!(
                    "unknown field `{f}` (known: {}; `_` skips a column)",
                    CSV_FIELDS.join(", ")
                )));
            }
        }
        let has = |n: &str| fields.iter().any(|f| f == n);
        let sensors = ["ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz"];
        if !sensors.iter().any(|s| has(s)) {
            return Err(err(
                "no sensor fields: expected ax/ay/az, gx/gy/gz or mx/my/mz".to_string(),
            ));
        }
        for (k, v) in scales {
            if !CSV_FIELDS.contains(&k.as_str()) || !v.is_finite() {
                return Err(Error::Config {
                    key: "scales".into(),
                    message: format!("scale `{k} = {v}` needs a known field and a finite number"),
                });
            }
        }
        Ok(())
    }
}

/// One item from a link to the service.
#[derive(Debug, Clone)]
pub(crate) enum Inbound {
    /// MAVLink frames read together (a UDP poll's datagrams, a stream's read, a replay's records
    /// due at once; at most [`queue::FRAMES_PER_ITEM`]), in the order read.
    Frames {
        link: usize,
        frames: Vec<TimedFrame>,
    },
    /// A sample from a text-line link, a CSV file or `sim:`.
    Sample { link: usize, sample: Sample },
    /// A change of the link's state.
    Status { link: usize, status: LinkStatus },
}

/// A MAVLink frame and its time: the arrival time (Unix microseconds) or, for `file:`, the tlog
/// timestamp.
#[derive(Debug, Clone)]
pub(crate) struct TimedFrame {
    pub time_us: u64,
    pub frame: Frame,
}

/// State changes of a link.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum LinkStatus {
    /// Up (again); the text says with what.
    Connected(String),
    /// Down, with the reason; a live link retries with backoff.
    Lost(String),
    /// No bytes for `for_s` seconds while connected (reported once per silence).
    Silent { for_s: f64 },
    /// A replay reached its end.
    Ended,
}

/// How a link's first opening went: what the live service's `ready` line lists for it. Set once,
/// before the link's first [`LinkStatus`], and never changed after (a link that fails later says
/// so with [`LinkStatus::Lost`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum LinkOpening {
    /// Open: a socket bound (a UDP link, a TCP listener), a connection made, a serial port or a
    /// file opened, a simulation made. `local` is the bound local address when the link has one
    /// (the port the system chose when the address asked for port 0).
    Open {
        local: Option<SocketAddr>,
        detail: String,
    },
    /// The first attempt failed: a live link keeps trying with backoff, a replay never works.
    Failed { detail: String },
}

/// Counters of one link, readable while it runs.
#[derive(Default, Debug)]
pub(crate) struct LinkCounters {
    pub bytes_in: AtomicU64,
    pub frames_in: AtomicU64,
    pub samples_in: AtomicU64,
    /// Text lines that were not samples (MotionCal `Uni:`/`Cal1:` lines, headers, garbage).
    pub lines_skipped: AtomicU64,
    /// Items a live link could not queue because the inbound channel was full.
    pub inbound_dropped: AtomicU64,
    /// Outbound messages not written: link down, no UDP peer yet, send error.
    pub outbound_dropped: AtomicU64,
    /// Connection attempts after the first (and, for tcpin, clients after the first).
    pub reconnects: AtomicU64,
}

impl LinkCounters {
    fn add(c: &AtomicU64, n: u64) {
        c.fetch_add(n, Ordering::Relaxed);
    }
}

/// What [`spawn_link`] returns.
#[derive(Debug)]
pub(crate) struct LinkHandle {
    /// Bytes to write to the link (already-encoded frames or text).
    pub outbound: mpsc::Sender<Vec<u8>>,
    pub counters: Arc<LinkCounters>,
    /// Decode counters of this link (frames/lines decoded, skips by reason).
    pub decode_stats: Arc<Mutex<DecodeStats>>,
    /// `None` until the link first opened or failed to ([`LinkOpening`]); closed without a value
    /// when the link stopped before that.
    pub opening: watch::Receiver<Option<LinkOpening>>,
    pub task: tokio::task::JoinHandle<()>,
}

/// Tuning of a link.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LinkOptions {
    /// Report [`LinkStatus::Silent`] after this many seconds without bytes (0 = never).
    pub silent_after_s: f64,
    /// First reconnect delay, s.
    pub backoff_min_s: f64,
    /// Longest reconnect delay, s.
    pub backoff_max_s: f64,
    /// Capacity of the outbound channel.
    pub outbound_capacity: usize,
    /// UDP: read the socket every this many seconds, taking everything queued, instead of waking
    /// for each datagram (0). The socket is then not watched by the reactor at all, so arriving
    /// datagrams wake nothing: fewer wake-ups for up to this much more latency.
    pub udp_poll_s: f64,
    /// UDP polls fall on the grid `poll_epoch + k * period` (while the period is the configured
    /// one), so that other timers on the same grid, like the service's periodic outputs, fire in
    /// the same wake-up. `None`: the grid starts when the link does.
    pub poll_epoch: Option<tokio::time::Instant>,
}

impl Default for LinkOptions {
    fn default() -> Self {
        LinkOptions {
            silent_after_s: 3.0,
            backoff_min_s: 0.2,
            backoff_max_s: 5.0,
            outbound_capacity: 256,
            udp_poll_s: 0.0,
            poll_epoch: None,
        }
    }
}

/// Longest UDP poll period: a 1 kHz stream queues at most 200 of the 256 datagrams Linux's
/// default receive buffer holds between two reads, so none is lost before the adaptive shortening
/// (see `poll_thresholds`) reacts to a faster one.
pub const UDP_POLL_MAX: Duration = Duration::from_millis(200);

/// A duration from seconds, clamped so that no input (NaN, negative, huge) can panic.
fn secs(x: f64) -> Duration {
    if x.is_finite() && x > 0.0 {
        Duration::from_secs_f64(x.min(1.0e6))
    } else {
        Duration::ZERO
    }
}

/// Options made safe to use.
#[derive(Debug, Clone)]
struct Tuning {
    silent: Option<Duration>,
    udp_poll: Option<Duration>,
    poll_epoch: Option<tokio::time::Instant>,
    backoff_min: Duration,
    backoff_max: Duration,
}

impl Tuning {
    fn from(o: &LinkOptions) -> Tuning {
        let silent = (o.silent_after_s.is_finite() && o.silent_after_s > 0.0)
            .then(|| secs(o.silent_after_s));
        let min = if o.backoff_min_s.is_finite() && o.backoff_min_s > 0.0 {
            secs(o.backoff_min_s).max(Duration::from_millis(1))
        } else {
            Duration::from_millis(200)
        };
        let max = if o.backoff_max_s.is_finite() && o.backoff_max_s > 0.0 {
            secs(o.backoff_max_s).max(min)
        } else {
            Duration::from_secs(5).max(min)
        };
        Tuning {
            silent,
            udp_poll: (o.udp_poll_s.is_finite() && o.udp_poll_s > 0.0)
                .then(|| secs(o.udp_poll_s).clamp(POLL_MIN, UDP_POLL_MAX)),
            poll_epoch: o.poll_epoch,
            backoff_min: min,
            backoff_max: max,
        }
    }
}

use crate::io::clock::now_us;

/// How a connection ended.
enum End {
    Stop,
    Lost(String),
}

/// The link's fixed parts, shared by all its loops.
struct Shared {
    index: usize,
    inbound: InboundTx,
    counters: Arc<LinkCounters>,
    stats: Arc<Mutex<DecodeStats>>,
    tuning: Tuning,
    start: Instant,
    /// Where the link's first opening is told ([`LinkHandle::opening`]).
    opening: watch::Sender<Option<LinkOpening>>,
}

impl Shared {
    /// Queue an item without waiting (live links); when there is no room it is dropped, each of
    /// its frames counted. False when the service is gone.
    fn offer(&self, item: Inbound) -> bool {
        let n = match &item {
            Inbound::Frames { frames, .. } => frames.len() as u64,
            Inbound::Sample { .. } | Inbound::Status { .. } => 1,
        };
        match self.inbound.try_send(item) {
            Ok(()) => true,
            Err(queue::Refused::Full) => {
                LinkCounters::add(&self.counters.inbound_dropped, n);
                true
            }
            Err(queue::Refused::Closed) => false,
        }
    }

    /// Queue a live link's frames read so far, if any (see [`Shared::offer`]).
    fn offer_frames(&self, batch: &mut Vec<TimedFrame>) -> bool {
        if batch.is_empty() {
            return true;
        }
        let frames = std::mem::take(batch);
        self.offer(Inbound::Frames {
            link: self.index,
            frames,
        })
    }

    /// Tell how the first opening went (later ones are not told: the first is the start-up's).
    fn opened(&self, how: LinkOpening) {
        self.opening.send_if_modified(|o| {
            if o.is_some() {
                return false;
            }
            tracing::debug!("link {}: {how:?}", self.index);
            *o = Some(how);
            true
        });
    }

    fn status(&self, status: LinkStatus) -> bool {
        match &status {
            LinkStatus::Lost(r) => tracing::debug!("link {}: lost: {r}", self.index),
            s => tracing::debug!("link {}: {s:?}", self.index),
        }
        self.offer(Inbound::Status {
            link: self.index,
            status,
        })
    }

    fn merge(&self, local: &DecodeStats) {
        if local.records == 0
            && local.skipped.is_empty()
            && local.counts.is_empty()
            && local.time.segments == 0
        {
            return;
        }
        if let Ok(mut s) = self.stats.lock() {
            merge_stats(&mut s, local);
        }
    }

    fn elapsed_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }
}

/// Per-connection receive state.
enum Rx {
    Mavlink(FrameDecoder),
    Text {
        lines: LineBuffer,
        parser: LineParser,
    },
}

impl Rx {
    fn new(payload: &Payload) -> Rx {
        match payload {
            Payload::Mavlink => Rx::Mavlink(FrameDecoder::new()),
            Payload::MotionCal => Rx::Text {
                lines: LineBuffer::new(),
                parser: LineParser::MotionCal,
            },
            Payload::Csv { fields, scales } => Rx::Text {
                lines: LineBuffer::new(),
                parser: LineParser::Csv(CsvLineParser::new(fields, scales)),
            },
        }
    }

    /// Decode bytes and queue what they hold, as one item. False when the service is gone.
    fn on_bytes(&mut self, sh: &Shared, bytes: &[u8], datagram: bool) -> bool {
        let mut local = DecodeStats::default();
        let mut batch = Vec::new();
        let open = self.take_bytes(sh, bytes, datagram, now_us(), &mut local, &mut batch);
        sh.merge(&local);
        open && sh.offer_frames(&mut batch)
    }

    /// [`Rx::on_bytes`] for bytes that arrived at `time_us` (Unix us), counted into `local`, their
    /// frames added to `batch` (queued once full; the caller queues the rest): datagrams read
    /// together share one arrival time, one item and one merge of their counts.
    fn take_bytes(
        &mut self,
        sh: &Shared,
        bytes: &[u8],
        datagram: bool,
        time_us: u64,
        local: &mut DecodeStats,
        batch: &mut Vec<TimedFrame>,
    ) -> bool {
        LinkCounters::add(&sh.counters.bytes_in, bytes.len() as u64);
        let mut open = true;
        match self {
            Rx::Mavlink(dec) => {
                let max = sh.inbound.max_batch();
                let add = |frame: Frame| {
                    batch.push(TimedFrame { time_us, frame });
                    if batch.len() >= max {
                        open &= sh.offer_frames(batch);
                    }
                };
                let n = if datagram {
                    decode_datagram(bytes, local, add)
                } else {
                    let frames = dec.push(bytes);
                    merge_stats(local, &std::mem::take(&mut dec.stats));
                    let n = frames.len() as u64;
                    frames.into_iter().for_each(add);
                    n
                };
                local.records += n;
                LinkCounters::add(&sh.counters.frames_in, n);
            }
            Rx::Text { lines, parser } => {
                let (mut got, overlong) = lines.push(bytes);
                if datagram {
                    got.extend(lines.take_partial());
                }
                let mut skipped = overlong;
                let t = sh.elapsed_s();
                for line in got {
                    if line.trim().is_empty() {
                        continue;
                    }
                    let s = match parser {
                        LineParser::MotionCal => parse_motioncal_line(&line, t),
                        LineParser::Csv(p) => p.parse(&line, t),
                    };
                    match s {
                        Some(sample) => {
                            local.records += 1;
                            local.count_sample(&sample);
                            LinkCounters::add(&sh.counters.samples_in, 1);
                            open &= sh.offer(Inbound::Sample {
                                link: sh.index,
                                sample,
                            });
                        }
                        None => skipped += 1,
                    }
                }
                if skipped > 0 {
                    LinkCounters::add(&sh.counters.lines_skipped, skipped);
                    local.skip_n("bad_line", skipped);
                }
            }
        }
        open
    }
}

// ---------------------------------------------------------------------------------------------
// Task plumbing

/// The link's receivers: shutdown flag and outbound bytes.
struct Control {
    shutdown: watch::Receiver<bool>,
    outbound: mpsc::Receiver<Vec<u8>>,
    /// False once every outbound sender is gone (then the channel is no longer polled).
    outbound_open: bool,
}

/// Resolves when shutdown is requested (or its sender is gone).
async fn wait_stop(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|stop| *stop).await;
}

/// Run `fut` while watching shutdown (-> `None`) and dropping outbound bytes (the link is not
/// writable meanwhile).
async fn guarded<F: Future>(
    ctl: &mut Control,
    counters: &LinkCounters,
    fut: F,
) -> Option<F::Output> {
    tokio::pin!(fut);
    loop {
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return None,
            r = &mut fut => return Some(r),
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                Some(_) => LinkCounters::add(&counters.outbound_dropped, 1),
                None => ctl.outbound_open = false,
            },
        }
    }
}

/// Start a link task. Must be called inside a tokio runtime.
pub(crate) fn spawn_link(
    index: usize,
    addr: Address,
    payload: Payload,
    inbound: InboundTx,
    shutdown: watch::Receiver<bool>,
    opts: LinkOptions,
) -> LinkHandle {
    let (out_tx, out_rx) = mpsc::channel(opts.outbound_capacity.max(1));
    let counters = Arc::new(LinkCounters::default());
    let decode_stats = Arc::new(Mutex::new(DecodeStats::default()));
    let (opening_tx, opening) = watch::channel(None);
    let sh = Shared {
        index,
        inbound,
        counters: counters.clone(),
        stats: decode_stats.clone(),
        tuning: Tuning::from(&opts),
        start: Instant::now(),
        opening: opening_tx,
    };
    let ctl = Control {
        shutdown,
        outbound: out_rx,
        outbound_open: true,
    };
    let task = tokio::spawn(run(sh, ctl, addr, payload));
    LinkHandle {
        outbound: out_tx,
        counters,
        decode_stats,
        opening,
        task,
    }
}

async fn run(sh: Shared, mut ctl: Control, addr: Address, payload: Payload) {
    if *ctl.shutdown.borrow() {
        return;
    }
    match &addr {
        Address::File { path, speed } => run_file(&sh, &mut ctl, path, *speed, &payload).await,
        Address::Sim {
            scenario,
            seed,
            speed,
        } => run_sim(&sh, &mut ctl, scenario, *seed, *speed).await,
        Address::TcpIn(a) => run_tcp_in(&sh, &mut ctl, *a, &payload).await,
        _ => run_dialled(&sh, &mut ctl, &addr, &payload).await,
    }
    tracing::debug!("link {} ({addr}) stopped", sh.index);
}

/// Queue an item, waiting for room (replays). False on shutdown or when the service is gone.
async fn deliver(sh: &Shared, ctl: &mut Control, item: Inbound) -> bool {
    matches!(
        guarded(ctl, &sh.counters, sh.inbound.send(item)).await,
        Some(Ok(()))
    )
}

/// A replay's status, waiting for room; its first says how the opening went (a replay connects
/// once, or fails once).
async fn deliver_status(sh: &Shared, ctl: &mut Control, status: LinkStatus) -> bool {
    match &status {
        LinkStatus::Connected(d) => sh.opened(LinkOpening::Open {
            local: None,
            detail: d.clone(),
        }),
        LinkStatus::Lost(d) => sh.opened(LinkOpening::Failed { detail: d.clone() }),
        LinkStatus::Silent { .. } | LinkStatus::Ended => {}
    }
    let link = sh.index;
    deliver(sh, ctl, Inbound::Status { link, status }).await
}

/// Run blocking work off the executor, watching shutdown.
async fn blocking<T: Send + 'static>(
    sh: &Shared,
    ctl: &mut Control,
    f: impl FnOnce() -> Result<T, String> + Send + 'static,
) -> Option<Result<T, String>> {
    match guarded(ctl, &sh.counters, tokio::task::spawn_blocking(f)).await? {
        Ok(r) => Some(r),
        Err(e) => Some(Err(format!("worker failed: {e}"))),
    }
}

#[cfg(test)]
mod tests;
