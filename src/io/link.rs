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
mod queue;
mod text;
mod udp_batch;
use crate::error::Error;
use crate::types::Sample;
pub use address::*;
pub(crate) use grid::GridTimer;
pub(crate) use queue::{inbound_queue, InboundRx, InboundTx, Queued};
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

// ---------------------------------------------------------------------------------------------
// Decoding bytes of a live link

/// Frames of one UDP datagram. Unlike the stream decoder, a datagram's end is a frame boundary:
/// an unfinished frame there is counted `truncated`; each run of garbage counts one `resync`.
/// Each frame goes to `emit` as it is found; returns how many.
fn decode_datagram(buf: &[u8], stats: &mut DecodeStats, mut emit: impl FnMut(Frame)) -> u64 {
    let mut n_frames = 0;
    let mut pos = 0;
    let mut in_garbage = false;
    while pos < buf.len() {
        match decode::parse_frame(&buf[pos..]) {
            FrameParse::Frame(f, n) => {
                emit(f);
                n_frames += 1;
                pos += n;
                in_garbage = false;
            }
            FrameParse::Incomplete => {
                stats.skip("truncated");
                break;
            }
            FrameParse::Skip(n, why) => {
                if why != SkipReason::Resync || !in_garbage {
                    stats.skip(why.name());
                }
                // The bytes after a damaged frame's first byte are its rest, not new garbage.
                in_garbage = matches!(why, SkipReason::Resync | SkipReason::BadCrc);
                pos += n.max(1);
            }
        }
    }
    n_frames
}

fn merge_stats(dst: &mut DecodeStats, src: &DecodeStats) {
    dst.records += src.records;
    dst.counts.add(&src.counts);
    for (k, v) in &src.skipped {
        *dst.skipped.entry(k.clone()).or_insert(0) += v;
    }
    dst.time.add(&src.time);
}

use crate::io::clock::now_us;

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

/// How a connection ended.
enum End {
    Stop,
    Lost(String),
}

trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

/// An open live connection.
enum Conn {
    Stream {
        io: Box<dyn Io>,
        /// The local end of a TCP connection (none for a serial port).
        local: Option<SocketAddr>,
        desc: String,
        eof: &'static str,
    },
    Udp {
        sock: UdpSocket,
        /// udpout's target; `None` for udpin (reply to the last sender).
        target: Option<SocketAddr>,
        desc: String,
    },
}

impl Conn {
    /// What the link's `ready` entry says of this connection.
    fn opening(&self) -> LinkOpening {
        match self {
            Conn::Stream { local, desc, .. } => LinkOpening::Open {
                local: *local,
                detail: desc.clone(),
            },
            Conn::Udp { sock, desc, .. } => LinkOpening::Open {
                local: sock.local_addr().ok(),
                detail: desc.clone(),
            },
        }
    }
}

const TCP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

async fn open(addr: &Address) -> Result<Conn, String> {
    match addr {
        Address::UdpIn(a) => {
            let sock = UdpSocket::bind(a)
                .await
                .map_err(|e| format!("cannot bind udp {a}: {e}"))?;
            let local = sock
                .local_addr()
                .map(|l| l.to_string())
                .unwrap_or_else(|_| a.to_string());
            Ok(Conn::Udp {
                sock,
                target: None,
                desc: format!("listening on udp {local}"),
            })
        }
        Address::UdpOut(t) => {
            let local: SocketAddr = match (t.is_ipv4(), t.ip().is_loopback()) {
                (true, true) => "127.0.0.1:0",
                (true, false) => "0.0.0.0:0",
                (false, true) => "[::1]:0",
                (false, false) => "[::]:0",
            }
            .parse()
            .expect("literal socket address");
            let sock = UdpSocket::bind(local)
                .await
                .map_err(|e| format!("cannot bind udp {local}: {e}"))?;
            sock.connect(t)
                .await
                .map_err(|e| format!("cannot address udp {t}: {e}"))?;
            let local = sock.local_addr().map(|l| l.to_string()).unwrap_or_default();
            Ok(Conn::Udp {
                sock,
                target: Some(*t),
                desc: format!("udp to {t} from {local}"),
            })
        }
        Address::TcpOut(h) => {
            let s = match tokio::time::timeout(TCP_CONNECT_TIMEOUT, TcpStream::connect(h.as_str()))
                .await
            {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => return Err(format!("cannot connect to tcp {h}: {e}")),
                Err(_) => return Err(format!("cannot connect to tcp {h}: timed out")),
            };
            let _ = s.set_nodelay(true);
            let local = s.local_addr().ok();
            let peer = s
                .peer_addr()
                .map(|p| p.to_string())
                .unwrap_or_else(|_| h.clone());
            Ok(Conn::Stream {
                io: Box::new(s),
                local,
                desc: format!("tcp {peer}"),
                eof: "connection closed by the remote end",
            })
        }
        Address::Serial { path, baud } => {
            use tokio_serial::SerialPortBuilderExt;
            let port = tokio_serial::new(path.as_str(), *baud)
                .open_native_async()
                .map_err(|e| format!("cannot open serial {path}: {e}"))?;
            Ok(Conn::Stream {
                io: Box::new(port),
                local: None,
                desc: format!("serial {path} at {baud} baud"),
                eof: "serial port closed (end of stream)",
            })
        }
        Address::TcpIn(_) | Address::File { .. } | Address::Sim { .. } => {
            Err(format!("{addr} is not a dialled link"))
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

// ---------------------------------------------------------------------------------------------
// Live links

/// udpin, udpout, tcpout, serial: open, serve, and on failure retry with backoff.
async fn run_dialled(sh: &Shared, ctl: &mut Control, addr: &Address, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut first = true;
    let mut lost_reported = false;
    loop {
        if !first {
            LinkCounters::add(&sh.counters.reconnects, 1);
        }
        first = false;
        let Some(res) = guarded(ctl, &sh.counters, open(addr)).await else {
            return;
        };
        match res {
            Ok(conn) => {
                let up = Instant::now();
                let mut rx = Rx::new(payload);
                sh.opened(conn.opening());
                let end = match conn {
                    Conn::Stream { io, desc, eof, .. } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        serve_stream(sh, ctl, io, &mut rx, None, eof).await
                    }
                    Conn::Udp { sock, target, desc } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        match sh.tuning.udp_poll {
                            Some(period) => {
                                serve_udp_polled(sh, ctl, sock, target, &mut rx, period).await
                            }
                            None => serve_udp(sh, ctl, &sock, target, &mut rx).await,
                        }
                    }
                };
                match end {
                    End::Stop => return,
                    End::Lost(r) => {
                        if !sh.status(LinkStatus::Lost(r)) {
                            return;
                        }
                        lost_reported = true;
                    }
                }
                // A connection that lasted resets the backoff; one that flaps keeps growing it.
                if up.elapsed() >= t.backoff_max {
                    backoff = t.backoff_min;
                }
            }
            Err(reason) => {
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                } else {
                    tracing::trace!("link {}: still down: {reason}", sh.index);
                }
            }
        }
        if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
            .await
            .is_none()
        {
            return;
        }
        backoff = (backoff * 2).min(t.backoff_max);
    }
}

/// tcpin: listen on the given address; serve one client at a time (others are closed at once).
async fn run_tcp_in(sh: &Shared, ctl: &mut Control, a: SocketAddr, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut lost_reported = false;
    let mut clients = 0u64;
    loop {
        let listener = match guarded(ctl, &sh.counters, TcpListener::bind(a)).await {
            None => return,
            Some(Ok(l)) => l,
            Some(Err(e)) => {
                let reason = format!("cannot listen on tcp {a}: {e}");
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                }
                if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
                    .await
                    .is_none()
                {
                    return;
                }
                backoff = (backoff * 2).min(t.backoff_max);
                LinkCounters::add(&sh.counters.reconnects, 1);
                continue;
            }
        };
        let local = listener.local_addr().ok();
        let shown = local.map_or_else(|| a.to_string(), |l| l.to_string());
        tracing::info!("link {}: listening on tcp {shown}", sh.index);
        sh.opened(LinkOpening::Open {
            local,
            detail: format!("listening on tcp {shown}"),
        });
        loop {
            let Some(acc) = guarded(ctl, &sh.counters, listener.accept()).await else {
                return;
            };
            let (stream, peer) = match acc {
                Ok(x) => x,
                Err(e) => {
                    // Transient (e.g. out of file descriptors): wait a little and accept again.
                    tracing::debug!("link {}: accept failed: {e}", sh.index);
                    let pause = tokio::time::sleep(Duration::from_millis(100));
                    if guarded(ctl, &sh.counters, pause).await.is_none() {
                        return;
                    }
                    continue;
                }
            };
            clients += 1;
            if clients > 1 {
                LinkCounters::add(&sh.counters.reconnects, 1);
            }
            let _ = stream.set_nodelay(true);
            if !sh.status(LinkStatus::Connected(format!("tcp client {peer}"))) {
                return;
            }
            let mut rx = Rx::new(payload);
            let eof = "client closed the connection";
            match serve_stream(sh, ctl, Box::new(stream), &mut rx, Some(&listener), eof).await {
                End::Stop => return,
                End::Lost(r) => {
                    if !sh.status(LinkStatus::Lost(format!(
                        "{r} ({peer}); waiting for a client"
                    ))) {
                        return;
                    }
                }
            }
        }
    }
}

/// Read a byte stream (TCP, serial) until it fails; write outbound bytes concurrently so a
/// stalled writer never stops the reader.
async fn serve_stream(
    sh: &Shared,
    ctl: &mut Control,
    io: Box<dyn Io>,
    rx: &mut Rx,
    listener: Option<&TcpListener>,
    eof: &str,
) -> End {
    let (mut rd, mut wr) = tokio::io::split(io);
    let Control {
        shutdown,
        outbound,
        outbound_open,
    } = ctl;
    let silent_after = sh.tuning.silent;

    let reader = async {
        let mut buf = vec![0u8; 4096];
        let mut last = Instant::now();
        let mut silent = false;
        loop {
            let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
            tokio::select! {
                r = rd.read(&mut buf) => match r {
                    Ok(0) => return End::Lost(eof.to_string()),
                    Ok(n) => {
                        last = Instant::now();
                        silent = false;
                        if !rx.on_bytes(sh, &buf[..n], false) {
                            return End::Stop;
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => return End::Lost(format!("read failed: {e}")),
                },
                _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                    silent = true;
                    let for_s = last.elapsed().as_secs_f64();
                    if !sh.status(LinkStatus::Silent { for_s }) {
                        return End::Stop;
                    }
                }
            }
        }
    };

    let writer = async {
        loop {
            if !*outbound_open {
                std::future::pending::<()>().await;
            }
            match outbound.recv().await {
                Some(bytes) => {
                    if let Err(e) = wr.write_all(&bytes).await {
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                        return End::Lost(format!("write failed: {e}"));
                    }
                }
                None => *outbound_open = false,
            }
        }
    };

    // tcpin: one client at a time; close the others at once.
    let extra_clients = async {
        match listener {
            Some(l) => loop {
                match l.accept().await {
                    Ok((_s, peer)) => {
                        tracing::info!("link {}: refused a second tcp client {peer}", sh.index)
                    }
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            },
            None => std::future::pending::<()>().await,
        }
    };

    tokio::select! {
        biased;
        _ = wait_stop(shutdown) => End::Stop,
        e = reader => e,
        e = writer => e,
        _ = extra_clients => End::Stop,
    }
}

fn transient_udp_error(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    // ICMP port-unreachable from an earlier send shows up as refused/reset: the peer is not up
    // yet, which is normal for UDP.
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionReset | WouldBlock | Interrupted
    )
}

/// Serve a UDP socket: each datagram is decoded on its own; outbound goes to the target
/// (udpout) or to the last sender (udpin).
async fn serve_udp(
    sh: &Shared,
    ctl: &mut Control,
    sock: &UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
) -> End {
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut buf = vec![0u8; 65_536];
    let mut last = Instant::now();
    let mut silent = false;
    loop {
        let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            r = sock.recv_from(&mut buf) => match r {
                Ok((n, from)) => {
                    if target.is_none() && peer != Some(from) {
                        tracing::debug!("link {}: udp peer {from}", sh.index);
                        peer = Some(from);
                    }
                    last = Instant::now();
                    silent = false;
                    if !rx.on_bytes(sh, &buf[..n], true) {
                        return End::Stop;
                    }
                }
                Err(e) if transient_udp_error(&e) => {}
                Err(e) => return End::Lost(format!("udp receive failed: {e}")),
            },
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).await.map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).await.map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
            _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                silent = true;
                if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                    return End::Stop;
                }
            }
        }
    }
}

/// Receive-buffer bytes one small datagram takes in Linux's accounting (its `truesize`: the
/// payload's allocation and the socket buffer around it), as SO_RCVBUF reads back: Linux's default
/// `rmem_default` of 212992 bytes holds 256 datagrams of a HIGHRES_IMU's size (measured on
/// loopback: 256 queued at the default, 2520 at 2 MiB).
const DATAGRAM_TRUESIZE: usize = 832;

/// Datagrams per poll above which the poll period shrinks (aiming at half this many per read), and
/// below which it doubles back towards the configured one, for a receive buffer of `bytes` (0:
/// not known, taken as Linux's default): a fast sender is read often enough that the buffer never
/// fills between reads, 3/8 of it at most (96 of the default's 256). The grow threshold is under
/// half the shrink one, so doubling the period never overshoots it.
fn poll_thresholds(bytes: usize) -> (usize, usize) {
    let holds = (bytes / DATAGRAM_TRUESIZE).max(256);
    let shrink_above = holds * 3 / 8;
    (shrink_above, shrink_above * 5 / 12)
}
/// Shortest poll period.
const POLL_MIN: Duration = Duration::from_millis(1);
/// How long a shortened poll period is kept after the last busy read before it may grow again, so
/// a sender that pauses briefly does not come back to a long period (and a full buffer).
const POLL_HOLD: Duration = Duration::from_secs(2);
/// Receive buffer asked for on a polled socket, bytes (the kernel caps it at `net.core.rmem_max`).
const POLL_RECEIVE_BUFFER: usize = 1 << 20;

/// As [`serve_udp`], but the socket is taken off the reactor and read every `period` (shorter while
/// datagrams arrive fast, see [`poll_thresholds`]): whatever queued in the kernel meanwhile is
/// taken in one go. Arriving datagrams wake nothing.
async fn serve_udp_polled(
    sh: &Shared,
    ctl: &mut Control,
    sock: UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
    period: Duration,
) -> End {
    let sock = match sock.into_std() {
        Ok(s) => s,
        Err(e) => return End::Lost(format!("udp socket: {e}")),
    };
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut batch = udp_batch::UdpBatch::new();
    let buffer = match udp_batch::grow_receive_buffer(&sock, POLL_RECEIVE_BUFFER) {
        Ok(b) => b,
        Err(e) => {
            tracing::debug!("link {}: udp receive buffer left as it was: {e}", sh.index);
            0
        }
    };
    let (shrink_above, grow_below) = poll_thresholds(buffer);
    let mut fast_until = Instant::now();
    let mut last = Instant::now();
    let mut silent = false;
    let mut every = period;
    let epoch = sh
        .tuning
        .poll_epoch
        .unwrap_or_else(tokio::time::Instant::now);
    // The first poll at once (at the epoch, or on the grid's first point passed).
    let mut polls = GridTimer::new(epoch, every);
    loop {
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            _ = polls.tick() => {
                let mut taken = 0usize;
                let mut local = DecodeStats::default();
                let mut frames = Vec::new();
                loop {
                    let n = match batch.recv(&sock) {
                        Ok(n) => n,
                        Err(e) if transient_udp_error(&e) => break,
                        Err(e) => {
                            sh.merge(&local);
                            if !sh.offer_frames(&mut frames) {
                                return End::Stop;
                            }
                            return End::Lost(format!("udp receive failed: {e}"));
                        }
                    };
                    let time_us = now_us();
                    frames.reserve(n.min(sh.inbound.max_batch()));
                    for i in 0..n {
                        let (bytes, from) = batch.get(i);
                        if let Some(from) = from.filter(|f| target.is_none() && peer != Some(*f)) {
                            tracing::debug!("link {}: udp peer {from}", sh.index);
                            peer = Some(from);
                        }
                        taken += 1;
                        if !rx.take_bytes(sh, bytes, true, time_us, &mut local, &mut frames) {
                            return End::Stop;
                        }
                    }
                    if n < udp_batch::BATCH {
                        break;
                    }
                }
                sh.merge(&local);
                if !sh.offer_frames(&mut frames) {
                    return End::Stop;
                }
                if taken > shrink_above {
                    // Aim at about half the threshold per read at the rate just seen.
                    let aim = (shrink_above / 2) as u32;
                    every = (every * aim / taken as u32).max(POLL_MIN.min(period));
                    fast_until = Instant::now() + POLL_HOLD;
                } else if taken < grow_below && Instant::now() >= fast_until {
                    every = (every * 2).min(period);
                }
                polls.set_period(every);
                let got = taken > 0;
                if got {
                    last = Instant::now();
                    silent = false;
                } else if let Some(after) = silent_after {
                    if !silent && last.elapsed() >= after {
                        silent = true;
                        if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                            return End::Stop;
                        }
                    }
                }
            }
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Replays

/// Longest pause a replay makes for one gap in its timestamps (recorded time), s.
pub(crate) const MAX_REPLAY_GAP_S: f64 = 10.0;

/// Maps recorded times onto the clock at `speed` (0 = no waiting). Backwards steps do not wait;
/// gaps longer than [`MAX_REPLAY_GAP_S`] are shortened to it.
struct Pacer {
    speed: f64,
    start: Instant,
    last: Option<f64>,
    elapsed: f64,
}

impl Pacer {
    fn new(speed: f64) -> Pacer {
        Pacer {
            speed,
            start: Instant::now(),
            last: None,
            elapsed: 0.0,
        }
    }

    fn deadline(&mut self, t_s: f64) -> Option<Instant> {
        if !(self.speed > 0.0) || !t_s.is_finite() {
            return None;
        }
        let Some(last) = self.last.replace(t_s) else {
            self.start = Instant::now();
            return None;
        };
        self.elapsed += (t_s - last).clamp(0.0, MAX_REPLAY_GAP_S);
        Some(self.start + secs(self.elapsed / self.speed))
    }

    /// Wait until `t_s` is due. False on shutdown.
    async fn wait(&mut self, sh: &Shared, ctl: &mut Control, t_s: f64) -> bool {
        let due = self.deadline(t_s);
        self.wait_until(sh, ctl, due).await
    }

    /// Wait until `due` (a [`Pacer::deadline`]; none: no wait). False on shutdown.
    async fn wait_until(&self, sh: &Shared, ctl: &mut Control, due: Option<Instant>) -> bool {
        match due {
            Some(d) if d > Instant::now() => {
                guarded(ctl, &sh.counters, tokio::time::sleep_until(d))
                    .await
                    .is_some()
            }
            _ => true,
        }
    }
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

/// True when a CSV payload's file has no header row (its first line starts with a number).
fn headerless(text: &str) -> bool {
    text.lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split(',').next())
        .is_some_and(|c| c.trim().parse::<f64>().is_ok())
}

async fn run_file(
    sh: &Shared,
    ctl: &mut Control,
    path: &std::path::Path,
    speed: f64,
    payload: &Payload,
) {
    let p = path.to_path_buf();
    let read = blocking(sh, ctl, move || {
        let raw = std::fs::read(&p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
        let data = decode::maybe_gunzip(&raw)
            .map_err(|e| format!("cannot decompress {}: {e}", p.display()))?
            .into_owned();
        Ok((raw.len(), data))
    })
    .await;
    let (size, data) = match read {
        None => return,
        Some(Ok(x)) => x,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    LinkCounters::add(&sh.counters.bytes_in, size as u64);
    let name = path.display().to_string();
    let lower = name.to_ascii_lowercase();
    let format = decode::detect_format(&data).or_else(|| {
        if lower.ends_with(".tlog") {
            Some(decode::Format::Tlog)
        } else if lower.ends_with(".csv") || lower.ends_with(".csv.gz") {
            Some(decode::Format::Csv)
        } else {
            None
        }
    });
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let ok = match format {
        Some(decode::Format::Tlog) => {
            deliver_status(
                sh,
                ctl,
                LinkStatus::Connected(format!("replaying tlog {name} {pace}")),
            )
            .await
                && replay_tlog(sh, ctl, &data, speed).await
        }
        Some(decode::Format::Csv) => {
            let text = String::from_utf8_lossy(&data);
            let mut mapping = decode::CsvMapping::default();
            let owned;
            let text: &str = match payload {
                Payload::Csv { fields, scales } => {
                    mapping.scales = scales.clone();
                    if headerless(&text) {
                        owned = format!("{}\n{text}", fields.join(","));
                        &owned
                    } else {
                        &text
                    }
                }
                _ => &text,
            };
            let mut stats = DecodeStats::default();
            match decode::decode_csv(text, &mapping, &mut stats) {
                Ok(samples) => {
                    sh.merge(&stats);
                    deliver_status(
                        sh,
                        ctl,
                        LinkStatus::Connected(format!("replaying csv {name} {pace}")),
                    )
                    .await
                        && replay_samples(sh, ctl, samples, speed).await
                }
                Err(e) => deliver_status(sh, ctl, LinkStatus::Lost(format!("{name}: {e}"))).await,
            }
        }
        Some(decode::Format::Bin | decode::Format::Ulg) | None => {
            let msg = format!("{name}: neither a .tlog nor a CSV with a header row (flight-controller logs: use `imucald replay`)");
            deliver_status(sh, ctl, LinkStatus::Lost(msg)).await
        }
    };
    if ok {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}

/// Replay a tlog's records paced by their timestamps; the records due together (all of them at
/// speed 0) go as one item, up to the queue's batch size.
async fn replay_tlog(sh: &Shared, ctl: &mut Control, data: &[u8], speed: f64) -> bool {
    let mut records = TlogRecords::new(data);
    let mut pacer = Pacer::new(speed);
    let mut batch: Vec<TimedFrame> = Vec::new();
    let max = sh.inbound.max_batch();
    while let Some((ts, frame)) = records.next() {
        // Publish the records and skips so far.
        sh.merge(&std::mem::take(&mut records.stats));
        let due = pacer.deadline(ts as f64 * 1e-6);
        let wait = due.is_some_and(|d| d > Instant::now());
        if (wait || batch.len() >= max)
            && !(deliver_frames(sh, ctl, &mut batch).await && pacer.wait_until(sh, ctl, due).await)
        {
            sh.merge(&records.stats);
            return false;
        }
        LinkCounters::add(&sh.counters.frames_in, 1);
        batch.push(TimedFrame { time_us: ts, frame });
    }
    sh.merge(&records.stats);
    deliver_frames(sh, ctl, &mut batch).await
}

/// Queue a replay's frames so far, if any, waiting for room. False on shutdown or when the
/// service is gone.
async fn deliver_frames(sh: &Shared, ctl: &mut Control, batch: &mut Vec<TimedFrame>) -> bool {
    if batch.is_empty() {
        return true;
    }
    let frames = std::mem::take(batch);
    let link = sh.index;
    deliver(sh, ctl, Inbound::Frames { link, frames }).await
}

/// Emit samples paced by their `t_s`. False on shutdown.
async fn replay_samples(sh: &Shared, ctl: &mut Control, samples: Vec<Sample>, speed: f64) -> bool {
    let mut pacer = Pacer::new(speed);
    for sample in samples {
        if !pacer.wait(sh, ctl, sample.t_s).await {
            return false;
        }
        LinkCounters::add(&sh.counters.samples_in, 1);
        let item = Inbound::Sample {
            link: sh.index,
            sample,
        };
        if !deliver(sh, ctl, item).await {
            return false;
        }
    }
    true
}

async fn run_sim(sh: &Shared, ctl: &mut Control, scenario: &str, seed: u64, speed: f64) {
    let name = scenario.to_string();
    let made = blocking(sh, ctl, move || {
        let sc = crate::sim::named::scenario(&name).map_err(|e| e.to_string())?;
        Ok(crate::sim::simulate(&sc, seed).samples)
    })
    .await;
    let samples = match made {
        None => return,
        Some(Ok(s)) => s,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    let mut stats = DecodeStats::default();
    for s in &samples {
        stats.records += 1;
        stats.count_sample(s);
    }
    sh.merge(&stats);
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let desc = format!(
        "simulating {scenario} (seed {seed}, {} samples) {pace}",
        samples.len()
    );
    if deliver_status(sh, ctl, LinkStatus::Connected(desc)).await
        && replay_samples(sh, ctl, samples, speed).await
    {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}

#[cfg(test)]
mod tests;
