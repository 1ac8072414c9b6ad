//! The live service (`imucald run`): links in, the shared pipeline, fits off the async executor,
//! heading/progress/reports published back. Thin glue: every decision lives in a pure module.
//!
//! ```text
//! link tasks ──(bounded mpsc, drops counted)──> run loop ──> Pipeline::push
//!                                                  │  Calibrator ─> OrientationFilter (fused attitude)
//!                                                  │  refit due: snapshot ─> spawn_blocking(fit_all)
//!                                                  │  result: accept if checks pass and not worse on held-out points
//!                                                  ├─> MAVLink back to the links (progress, report, heading,
//!                                                  │   ATTITUDE_QUATERNION / ATTITUDE)
//!                                                  ├─> JSON lines: a bounded queue per consumer
//!                                                  │   (try_send, drops counted) -> its writer
//!                                                  └─> calibration files (atomic), report
//! ```

use crate::clock::{ClockSettings, SourceClock};
use crate::config::{Config, SourceConfig};
use crate::coverage::Progress;
use crate::decode::{InstanceChoice, MessageConverter};
use crate::error::Error;
use crate::fusion::OrientationFilter;
use crate::link::{spawn_link, Address, Inbound, LinkHandle, LinkOptions, LinkStatus, Payload};
use crate::mavout::{
    self, ApCompassParams, LiveEvent, MagCalEffect, MagCalEvent, MagCalRun, MavEncoder, ParamWriter,
};
use crate::model::Calibration;
use crate::pipeline::{fit_all, Calibrated, Calibrator, FitResults, Pipeline, SensorResult};
use crate::report::{GyroCalibration, SensorCalibration};
use crate::types::{norm, Sample, Unit, Vec3};
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavMessage, MavResult, COMMAND_LONG_DATA,
};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// What is kept on disk between runs (`calibration.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredCalibration {
    pub schema: String,
    /// The primary instance's compass id (the index its flight-stack parameters are named for:
    /// COMPASS_OFS / CAL_MAG0 for 0, COMPASS_OFS2 / CAL_MAG1 for 1 ...).
    #[serde(default)]
    pub compass_id: u8,
    pub mag: Option<SensorCalibration>,
    pub accel: Option<SensorCalibration>,
    pub gyro: Option<GyroCalibration>,
    /// The stream's other IMU instances, each calibrated on its own (a vehicle with several
    /// compasses).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub instances: Vec<StoredInstance>,
}

/// The calibration in use of an IMU instance other than the primary.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredInstance {
    /// `highres_imu:1`, `scaled_imu2`, ...
    pub instance: String,
    /// MAG_CAL_* `compass_id`, and the index of its flight-stack parameters.
    pub compass_id: u8,
    pub mag: Option<SensorCalibration>,
    pub accel: Option<SensorCalibration>,
}

pub const STORE_SCHEMA: &str = "imucald.calibration/1";
pub const STORE_FILE: &str = "calibration.json";

impl StoredCalibration {
    fn empty() -> Self {
        StoredCalibration {
            schema: STORE_SCHEMA.into(),
            compass_id: 0,
            mag: None,
            accel: None,
            gyro: None,
            instances: Vec::new(),
        }
    }
    pub fn mag_cal(&self) -> Option<Calibration> {
        self.mag.as_ref()?.calibration()
    }
    pub fn accel_cal(&self) -> Option<Calibration> {
        self.accel.as_ref()?.calibration()
    }
    /// Every compass's magnetometer calibration in uT with its compass id (what parameters hold).
    pub fn mags_ut(&self) -> Vec<(usize, Calibration)> {
        let primary = self.mag.as_ref().and_then(|m| m.calibration_ut());
        let others = self.instances.iter().filter_map(|i| {
            let c = i.mag.as_ref()?.calibration_ut()?;
            Some((i.compass_id as usize, c))
        });
        primary
            .map(|c| (self.compass_id as usize, c))
            .into_iter()
            .chain(others)
            .collect()
    }
    /// The stored entry of the instance with compass id `compass_id` (made when missing).
    fn instance_mut(&mut self, name: &str, compass_id: u8) -> &mut StoredInstance {
        let k = match self
            .instances
            .iter()
            .position(|i| i.compass_id == compass_id)
        {
            Some(k) => k,
            None => {
                self.instances.push(StoredInstance {
                    instance: name.to_string(),
                    compass_id,
                    mag: None,
                    accel: None,
                });
                self.instances.len() - 1
            }
        };
        &mut self.instances[k]
    }
}

/// Load the last good calibration; a missing file is no calibration, a damaged one is an error that
/// says which file.
pub fn load_store(dir: &Path) -> Result<Option<StoredCalibration>, Error> {
    let p = dir.join(STORE_FILE);
    match std::fs::read_to_string(&p) {
        Ok(text) => serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| Error::Format {
                path: p,
                message: format!("not a calibration file ({e}); move it away to start fresh"),
            }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(Error::Read { path: p, source }),
    }
}

/// Write the calibration and its exports atomically into `dir`.
pub fn save_store(dir: &Path, store: &StoredCalibration) -> Result<(), Error> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let (m, a) = (store.mag_cal(), store.accel_cal());
    let mags = store.mags_ut();
    crate::publish::write_atomic(
        &dir.join("ardupilot.parm"),
        crate::export::ardupilot_file(&mags, a.as_ref()).as_bytes(),
    )?;
    crate::publish::write_atomic(
        &dir.join("px4.params"),
        crate::export::px4_file(&mags, a.as_ref()).as_bytes(),
    )?;
    crate::publish::write_atomic(
        &dir.join("fusion.h"),
        crate::export::fusion_file(m.as_ref(), a.as_ref()).as_bytes(),
    )?;
    // The JSON last: it is what a restart loads.
    crate::publish::write_json(&dir.join(STORE_FILE), store)
}

/// RMS of |calibrated| - radius over points (calibrated units).
fn rms_on(cal: &Calibration, radius: f64, pts: &[Vec3]) -> f64 {
    if pts.is_empty() {
        return f64::INFINITY;
    }
    (pts.iter()
        .map(|p| (norm(&cal.apply(p)) - radius).powi(2))
        .sum::<f64>()
        / pts.len() as f64)
        .sqrt()
}

/// The live service holds every this-many-th kept magnetometer point and pose out of its fits
/// ([`crate::pipeline::hold_out`]): a new calibration is judged on those against the current one.
pub const HOLD_OUT_EVERY: usize = 5;

/// How much worse (relative RMS) on the held-out points than the current calibration a new one may
/// be and still replace it (two fits of the same field differ by noise).
pub const ACCEPT_MARGIN: f64 = 0.02;

/// Whether a failed magnetometer fit is reported (MAG_CAL_REPORT with a failure status), as
/// ArduPilot's calibrator does: only once the run's completion reached 100 % (the data covered the
/// sphere, about a known centre) and the fit still failed for a reason other than still collecting.
pub fn failure_report_due(mag: &SensorCalibration, completion_pct: u8) -> bool {
    let collecting = matches!(
        mag.failure.as_deref(),
        Some("coverage") | Some("not_enough_samples")
    );
    mag.status != "ok" && !collecting && completion_pct >= 100
}

/// Why a new calibration did not replace the current one.
#[derive(Debug, Clone, PartialEq)]
pub enum NotReplaced {
    /// The fit failed a check (`failure`: the report's reason).
    Failed { failure: String, detail: String },
    /// A calibration is in use and the new fit had no points held out to compare them on.
    NothingHeldOut,
    /// Worse than the current calibration on the held-out points (RMS of |calibrated| - radius).
    WorseOnHeldOut {
        points: usize,
        rms_new: f64,
        rms_current: f64,
    },
}

impl std::fmt::Display for NotReplaced {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NotReplaced::Failed { failure, detail } => write!(f, "failed {failure}: {detail}"),
            NotReplaced::NothingHeldOut => {
                write!(f, "too few points to hold out a comparison with the current calibration")
            }
            NotReplaced::WorseOnHeldOut {
                points,
                rms_new,
                rms_current,
            } => write!(
                f,
                "worse than the current calibration on {points} points held out of the fit (rms {rms_new:.4} vs {rms_current:.4})"
            ),
        }
    }
}

/// Whether a new fit replaces the current calibration: it passed its checks, and (when there is a
/// current one) it is better on the points held out of its fit, or worse by at most
/// [`ACCEPT_MARGIN`].
pub fn accept(new: &SensorResult, current: Option<&SensorCalibration>) -> Result<(), NotReplaced> {
    let Some(nc) = new.calibration else {
        return Err(NotReplaced::Failed {
            failure: new.report.failure.clone().unwrap_or_else(|| "?".into()),
            detail: new.report.detail.clone().unwrap_or_default(),
        });
    };
    let Some((cur, cc)) = current.and_then(|c| c.calibration().map(|cc| (c, cc))) else {
        return Ok(());
    };
    let held = &new.held_out;
    if held.is_empty() {
        return Err(NotReplaced::NothingHeldOut);
    }
    let rms_new = rms_on(&nc, new.report.radius, held);
    let rms_current = rms_on(&cc, cur.radius, held);
    if rms_new > rms_current * (1.0 + ACCEPT_MARGIN) + 1e-12 {
        return Err(NotReplaced::WorseOnHeldOut {
            points: held.len(),
            rms_new,
            rms_current,
        });
    }
    Ok(())
}

fn payload_of(s: &SourceConfig) -> Payload {
    match s.payload.as_str() {
        "motioncal" => Payload::MotionCal,
        "csv" => Payload::Csv {
            fields: s.fields.clone(),
            scales: s.scales.clone(),
        },
        _ => Payload::Mavlink,
    }
}

/// Lines a JSON consumer's queue holds; more while it is not taking them are dropped and counted.
const SINK_QUEUE_LINES: usize = 1024;
/// How long the JSON writers get at shutdown to pass on what is queued, before they are dropped.
const SINK_DRAIN_AT_EXIT: Duration = Duration::from_millis(150);
/// A TCP JSON consumer that refused or did not answer is tried again after this long.
const SINK_TCP_RETRY: Duration = Duration::from_secs(1);
/// Lost JSON lines and MAVLink datagrams are reported (JSON `status`, log) at most this often, s.
const DROPS_REPORT_S: f64 = 5.0;
/// Lines a writer takes from its queue per wake-up.
const SINK_BATCH: usize = 64;

/// What became of the lines for one JSON consumer (shared with its writer).
#[derive(Debug, Default)]
struct SinkCounters {
    /// Handed to the consumer (written to stdout or the socket).
    sent: std::sync::atomic::AtomicU64,
    /// Dropped by the run loop: the consumer's queue was full (it is not taking lines).
    queue_full: std::sync::atomic::AtomicU64,
    /// Taken by the writer but not delivered: no connection, the socket refused it.
    not_delivered: std::sync::atomic::AtomicU64,
}

impl SinkCounters {
    fn add(c: &std::sync::atomic::AtomicU64, n: u64) {
        c.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
    }
    fn get(c: &std::sync::atomic::AtomicU64) -> u64 {
        c.load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Where a JSON consumer's writer runs.
enum SinkWriter {
    /// A tokio task (UDP, TCP): aborted at shutdown when it has not finished.
    Task(tokio::task::JoinHandle<()>),
    /// A thread of its own (stdout, whose writes block): the receiver resolves when it ends; a
    /// thread still blocked at shutdown is left behind (it ends with the process).
    Thread(tokio::sync::oneshot::Receiver<()>),
}

/// A JSON-lines consumer: a writer of its own fed through a bounded queue, so that a consumer that
/// stops reading (a full pipe, a TCP peer that does not read) loses lines, counted, and never holds
/// the run loop.
struct Sink {
    /// The address as configured (`stdout`, `udp:IP:PORT`, `tcp:IP:PORT`).
    label: String,
    tx: Option<mpsc::Sender<std::sync::Arc<str>>>,
    counters: std::sync::Arc<SinkCounters>,
    writer: Option<SinkWriter>,
    /// Lines lost (queue full + not delivered) when they were last reported.
    lost_reported: u64,
}

impl Sink {
    fn open(spec: &str) -> Result<Sink, Error> {
        let bad = || Error::Config {
            key: "publish".into(),
            message: format!("`{spec}` is not stdout, udp:IP:PORT or tcp:IP:PORT"),
        };
        let (tx, rx) = mpsc::channel::<std::sync::Arc<str>>(SINK_QUEUE_LINES);
        let counters = std::sync::Arc::new(SinkCounters::default());
        let c = counters.clone();
        let writer = if spec == "stdout" {
            let (done_tx, done_rx) = tokio::sync::oneshot::channel();
            std::thread::Builder::new()
                .name("imucald-stdout".into())
                .spawn(move || {
                    stdout_writer(rx, &c);
                    let _ = done_tx.send(());
                })
                .map_err(|e| Error::Other(format!("publish {spec}: {e}")))?;
            SinkWriter::Thread(done_rx)
        } else if let Some(a) = spec.strip_prefix("udp:") {
            let addr: std::net::SocketAddr = a.parse().map_err(|_| bad())?;
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
        } else if let Some(a) = spec.strip_prefix("tcp:") {
            let addr: std::net::SocketAddr = a.parse().map_err(|_| bad())?;
            SinkWriter::Task(tokio::spawn(tcp_writer(addr, rx, c)))
        } else {
            return Err(bad());
        };
        Ok(Sink {
            label: spec.to_string(),
            tx: Some(tx),
            counters,
            writer: Some(writer),
            lost_reported: 0,
        })
    }

    /// Queue a line; never waits. A full queue drops it (counted).
    fn send(&self, line: &std::sync::Arc<str>) {
        if let Some(tx) = &self.tx {
            if tx.try_send(line.clone()).is_err() {
                SinkCounters::add(&self.counters.queue_full, 1);
            }
        }
    }

    /// Lines that did not reach the consumer so far.
    fn lost(&self) -> u64 {
        SinkCounters::get(&self.counters.queue_full)
            + SinkCounters::get(&self.counters.not_delivered)
    }

    fn report(&self) -> crate::report::SinkReport {
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
async fn close_sinks(sinks: &mut [Sink], deadline: tokio::time::Instant) {
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
fn stdout_writer(mut rx: mpsc::Receiver<std::sync::Arc<str>>, c: &SinkCounters) {
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
async fn udp_writer(
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
async fn tcp_writer(
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

/// A periodic output: served at the ticks of the run loop's clock when its period is a whole number
/// of clock periods, else by a timer of its own. Both are on the time grid from `epoch`.
struct Output {
    cadence: Cadence,
    own: Option<tokio::time::Interval>,
}

impl Output {
    fn new(epoch: tokio::time::Instant, rate_hz: f64) -> Output {
        Output {
            cadence: Cadence::new(epoch, rate_hz),
            own: None,
        }
    }

    /// Keep to the clock of period `clock`, or take a timer of its own.
    fn use_clock(&mut self, epoch: tokio::time::Instant, clock: Duration) {
        let (p, c) = (self.cadence.period.as_nanos(), clock.as_nanos());
        if c == 0 || p % c != 0 {
            let mut t = tokio::time::interval_at(epoch, self.cadence.period);
            t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            self.own = Some(t);
        }
    }

    /// Whether the output is due at clock tick `t` (never, when it has a timer of its own).
    fn due_at_clock(&mut self, t: tokio::time::Instant) -> bool {
        self.own.is_none() && self.cadence.due(t)
    }

    /// The next tick of its own timer (polled only when it has one).
    async fn own_tick(&mut self) {
        match self.own.as_mut() {
            Some(t) => {
                t.tick().await;
            }
            None => std::future::pending().await,
        }
    }
}

/// A periodic output on the shared time grid: due at `epoch + k * period`. Asked at the ticks of a
/// clock on the same grid, at least as fast; ticks missed while busy are skipped, not made up.
#[derive(Debug, Clone, Copy)]
struct Cadence {
    period: Duration,
    next: tokio::time::Instant,
}

impl Cadence {
    fn new(epoch: tokio::time::Instant, rate_hz: f64) -> Cadence {
        Cadence {
            // (Rates are validated: finite, positive and at most 1 kHz.)
            period: Duration::from_secs_f64(1.0 / rate_hz).max(Duration::from_micros(1)),
            next: epoch,
        }
    }

    /// Whether the output is due at clock tick `t`; if so, the next time is set after `t`.
    fn due(&mut self, t: tokio::time::Instant) -> bool {
        if t < self.next {
            return false;
        }
        let behind = (t - self.next).as_nanos() / self.period.as_nanos();
        self.next = u32::try_from(behind + 1)
            .ok()
            .and_then(|k| self.period.checked_mul(k))
            .and_then(|d| self.next.checked_add(d))
            .unwrap_or(t + self.period);
        true
    }
}

/// Largest datagram of MAVLink frames sent to a link, bytes: under a 1500-byte Ethernet MTU less
/// IP and UDP headers, so a datagram is never fragmented.
const MAV_DATAGRAM_MAX: usize = 1400;

/// What `run` did, for the caller's last words.
#[derive(Debug, Clone, Default)]
pub struct RunSummary {
    pub samples: u64,
    pub accepted: usize,
    pub inbound_dropped: u64,
}

/// A vehicle heard on the links: its converter (instances, clocks) and its ArduPilot state (whether
/// its magnetometer data comes calibrated, and the calibration to undo).
struct Vehicle {
    /// Link index and system id; (0, 0) for every link with `daemon.links = "merged"`.
    key: (usize, u8),
    conv: MessageConverter,
    ardupilot: bool,
    ap_params: ApCompassParams,
    /// Told the user it is not calibrated.
    announced: bool,
}

struct LinkEntry {
    handle: LinkHandle,
    mavlink: bool,
    /// A UDP link, read by polling on the time grid.
    polled: bool,
    ended: bool,
    replay: bool,
    label: String,
    /// Datagrams of MAVLink frames dropped because its outbound queue was full (also in the link's
    /// `outbound_dropped`, with those it could not send: no peer yet, link down).
    outbound_queue_full: u64,
    /// `outbound_queue_full` when it was last reported.
    queue_full_reported: u64,
}

/// One IMU instance calibrated live: its pipeline, its magnetometer calibration run and progress,
/// its latest fit. Track 0 is the primary instance, whose calibration also gives the heading and
/// the attitude; every further compass of the calibrated vehicle gets a track of its own
/// (at most [`crate::decode::MAX_INSTANCES`]), calibrated, reported (MAG_CAL_* with its compass id,
/// JSON with its `instance`), stored and written under its own parameter names.
struct Track {
    /// The instance's index in the calibrated vehicle's converter; `None` for track 0 until the
    /// converter picked its primary (and for samples of text-line links, which have no instances).
    instance: Option<usize>,
    /// `highres_imu:1`, `scaled_imu2`, ...
    name: String,
    /// MAG_CAL_* `compass_id`.
    compass_id: u8,
    pipe: Pipeline,
    /// Magnetometer samples pushed (a track without any reports no magnetometer progress).
    mag_samples: u64,
    /// Counts calibration-run restarts: a fit started before the latest one is disregarded.
    generation: u64,
    /// Completion of the calibration run, for the progress reports.
    progress: Progress,
    /// The magnetometer calibration run (ground-station commands, continuous calibration).
    mag_run: MagCalRun,
    /// The failed magnetometer fit to report, while its event is handled.
    mag_failed: Option<SensorCalibration>,
    /// The last magnetometer calibration sent in MAG_CAL_REPORT (reports only when it moved).
    reported_mag: Option<SensorCalibration>,
    last_results: Option<FitResults>,
    /// A refit is due (its pipeline said so since the last fit started).
    refit_wanted: bool,
}

impl Track {
    fn new(
        cfg: &Config,
        instance: Option<usize>,
        name: String,
        compass_id: u8,
    ) -> Result<Track, Error> {
        Ok(Track {
            instance,
            name,
            compass_id,
            pipe: Pipeline::new(cfg)?.with_hold_out(HOLD_OUT_EVERY),
            mag_samples: 0,
            generation: 0,
            progress: Progress::new(cfg.daemon.progress_full_regions),
            mag_run: MagCalRun::Idle,
            mag_failed: None,
            reported_mag: None,
            last_results: None,
            refit_wanted: false,
        })
    }

    /// Push a sample (raw, sensor axes); true when a refit is due.
    fn push(&mut self, s: &Sample) -> bool {
        if s.mag_ut.is_some() {
            self.mag_samples += 1;
        }
        let due = self.pipe.push(s);
        self.refit_wanted |= due;
        due
    }
}

/// Which tracks a fit job fitted: (track, its generation when the job started, time, results).
type TrackFits = Vec<(usize, u64, f64, FitResults)>;

struct State {
    cfg: Config,
    /// The instances calibrated; track 0 is the primary.
    tracks: Vec<Track>,
    /// Clocks of the links that deliver samples rather than MAVLink frames, by link index.
    sample_clocks: Vec<SourceClock>,
    store: StoredCalibration,
    calibrator: Calibrator,
    latest: Option<Calibrated>,
    enc: MavEncoder,
    /// Our MAVLink ids: inbound frames carrying them are our own echo.
    own: mavout::OwnIds,
    /// Inbound frames dropped as our own echo.
    own_echo: u64,
    /// MAVLink frames encoded in this turn of the run loop, sent to the links as one datagram (or
    /// write) at its end: one `sendto` for all the messages of a tick, not one per message.
    mav_out: Vec<u8>,
    /// The calibration store and the report, written off the run loop.
    store_writes: Writes,
    report_writes: Writes,
    links: Vec<LinkEntry>,
    sinks: Vec<Sink>,
    /// The vehicles heard (a link and a system id each, or one for all with
    /// `daemon.links = "merged"`): their converters and ArduPilot state.
    vehicles: Vec<Vehicle>,
    /// The vehicle calibrated: the first whose IMU data arrived.
    primary_vehicle: Option<usize>,
    /// IMU samples of other vehicles, not calibrated.
    other_vehicle_samples: u64,
    /// IMU samples of instances past the tracks the service keeps, not calibrated.
    other_instance_samples: u64,
    /// A converter as new, for the next vehicle heard.
    new_converter: MessageConverter,
    /// Counts of the samples from text-line and simulator links.
    line_stats: crate::decode::DecodeStats,
    writer: Option<ParamWriter>,
    accepted: usize,
    cal_dir: PathBuf,
    report: Option<PathBuf>,
    start: tokio::time::Instant,
    declination: Option<f64>,
    mag_awaiting_params: u64,
    /// Calibrated vectors since the last heading publication.
    window: Averager,
    /// Fused attitude (body FRD -> NED, true north when the place is known) from every calibrated sample.
    fusion: OrientationFilter,
    /// Calibrated gyro since the last attitude publication (the body rates sent with it).
    attitude_rates: RateMean,
    /// `daemon.attitude_every_samples`: samples since the last attitude, and whether one is due now.
    samples_since_attitude: u32,
    attitude_due: bool,
    /// The latest magnetometer reading in body axes before calibration (to tell how far a new
    /// calibration moves the field the filter sees).
    last_body_mag: Option<Vec3>,
}

/// Time step of the orientation filter's first sample and of samples whose clock jumps, s.
const FUSION_DEFAULT_DT_S: f64 = 0.01;

/// Whether a new magnetometer calibration moves the calibrated field of `raw` (body axes, before
/// calibration) by more than 2 % in norm or 2 degrees in direction: the orientation filter would take
/// such a step for a magnetic disturbance (and distrust the field for a while), so it restarts instead.
fn mag_cal_moved(old: Option<&Calibration>, new: Option<&Calibration>, raw: &Vec3) -> bool {
    let f = |c: Option<&Calibration>| c.map_or(*raw, |c| c.apply(raw));
    let (a, b) = (f(old), f(new));
    let (na, nb) = (norm(&a), norm(&b));
    if !(na > 0.0 && nb > 0.0 && na.is_finite() && nb.is_finite()) {
        return false;
    }
    let cos = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (na * nb);
    (nb / na - 1.0).abs() > 0.02 || cos.clamp(-1.0, 1.0).acos().to_degrees() > 2.0
}

/// Mean of the calibrated body rates between two attitude publications; keeps the last mean when
/// no gyro sample came in between.
#[derive(Debug, Default, Clone, Copy)]
struct RateMean {
    sum: Vec3,
    n: u32,
    last: Option<Vec3>,
}

impl RateMean {
    fn add(&mut self, g: &Vec3) {
        for k in 0..3 {
            self.sum[k] += g[k];
        }
        self.n += 1;
    }

    fn take(&mut self) -> Option<Vec3> {
        if self.n > 0 {
            let n = self.n as f64;
            self.last = Some(self.sum.map(|v| v / n));
            self.sum = [0.0; 3];
            self.n = 0;
        }
        self.last
    }
}

impl State {
    fn calibrator_from_store(store: &StoredCalibration, declination: Option<f64>) -> Calibrator {
        let mut c = Calibrator::empty(declination);
        c.mag = store.mag_cal();
        c.accel = store.accel_cal();
        c.gyro_bias = store
            .gyro
            .as_ref()
            .filter(|g| g.status == "ok")
            .map(|g| g.bias);
        c
    }

    fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// Queue MAVLink messages for the live links; [`State::flush_mav`] sends them.
    async fn send_mav(&mut self, msgs: &[MavMessage]) {
        for m in msgs {
            let bytes = self.enc.encode(m);
            if !self.mav_out.is_empty() && self.mav_out.len() + bytes.len() > MAV_DATAGRAM_MAX {
                self.flush_mav();
            }
            self.mav_out.extend_from_slice(&bytes);
        }
    }

    /// Send the queued MAVLink frames to each live link as one datagram (or write). A link whose
    /// queue is full loses it, counted in `outbound_dropped`.
    fn flush_mav(&mut self) {
        if self.mav_out.is_empty() {
            return;
        }
        for l in self.links.iter_mut().filter(|l| l.mavlink && !l.replay) {
            if l.handle.outbound.try_send(self.mav_out.clone()).is_err() {
                l.outbound_queue_full += 1;
                l.handle
                    .counters
                    .outbound_dropped
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
        self.mav_out.clear();
    }

    /// Our HEARTBEAT on every live MAVLink link.
    async fn send_heartbeat(&mut self) {
        if self.links.iter().any(|l| l.mavlink && !l.replay) {
            self.send_mav(&[mavout::heartbeat()]).await;
        }
    }

    /// Queue a JSON line for every consumer (never waits: a full queue drops it, counted).
    async fn send_json(&mut self, ev: &LiveEvent) {
        if self.sinks.is_empty() {
            return;
        }
        let line: std::sync::Arc<str> = mavout::json_line(ev).into();
        for s in &self.sinks {
            s.send(&line);
        }
    }

    /// A JSON `status` line (and a log line) for each consumer that lost lines since the last
    /// time, and for each link whose outbound queue was full (not for datagrams a link could not
    /// send: a udpin link has no peer until one sends, and the HEARTBEAT goes out regardless).
    async fn report_drops(&mut self) {
        let mut said = vec![];
        for s in self.sinks.iter_mut() {
            let lost = s.lost();
            if lost > s.lost_reported {
                let r = s.report();
                said.push(format!(
                    "JSON consumer {}: {} lines dropped since the last report, {} in all ({} with its queue full, {} not delivered), {} sent",
                    s.label,
                    lost - s.lost_reported,
                    lost,
                    r.queue_full,
                    r.not_delivered,
                    r.sent
                ));
                s.lost_reported = lost;
            }
        }
        for l in self.links.iter_mut() {
            let n = l.outbound_queue_full;
            if n > l.queue_full_reported {
                said.push(format!(
                    "{}: {} MAVLink datagrams dropped with its outbound queue full since the last report ({} in all)",
                    l.label,
                    n - l.queue_full_reported,
                    n
                ));
                l.queue_full_reported = n;
            }
        }
        for text in said {
            tracing::warn!("{text}");
            self.send_json(&LiveEvent::Status {
                level: severity_name(4).into(),
                text,
            })
            .await;
        }
    }

    /// What the outputs could not deliver, for the report.
    fn outputs_report(&self) -> crate::report::OutputsReport {
        crate::report::OutputsReport {
            json_sinks: self.sinks.iter().map(Sink::report).collect(),
            links: self
                .links
                .iter()
                .map(|l| crate::report::LinkOutputReport {
                    link: l.label.clone(),
                    outbound_dropped: l
                        .handle
                        .counters
                        .outbound_dropped
                        .load(std::sync::atomic::Ordering::Relaxed),
                    outbound_queue_full: l.outbound_queue_full,
                })
                .collect(),
        }
    }

    async fn status(&mut self, severity: u8, text: String) {
        tracing::info!("{text}");
        let msgs = mavout::statustext(severity, &text);
        self.send_mav(&msgs).await;
        self.send_json(&LiveEvent::Status {
            level: severity_name(severity).into(),
            text,
        })
        .await;
    }

    /// A sample of the primary instance: calibrated for the heading and attitude, and pushed.
    fn on_sample(&mut self, s: Sample) -> bool {
        let due = self.tracks[0].push(&s);
        let body = self.tracks[0].pipe.to_body(&s);
        if body.mag_ut.is_some() {
            self.last_body_mag = body.mag_ut;
        }
        // The angles are taken of the means at the heading rate (`publish_heading`), not per sample.
        let c = self.calibrator.apply_vectors(&body);
        self.window.add(&c);
        self.fuse(&c);
        self.latest = Some(c);
        let every = self.cfg.daemon.attitude_every_samples;
        if every > 0 {
            self.samples_since_attitude += 1;
            if self.samples_since_attitude >= every {
                self.samples_since_attitude = 0;
                self.attitude_due = true;
            }
        }
        due
    }

    /// A sample from a link that times its own samples (text lines: the time they were read, or
    /// their own `t` column), through that link's clock, taken as a receive clock (lines read
    /// together share a time, and a still sensor's lines can repeat: none is dropped).
    fn stamp(&mut self, link: usize, mut s: Sample) -> Sample {
        if self.links.get(link).is_some_and(|l| l.replay) {
            // Already timed: a file's samples by its reader's clock; the simulator's are ours.
            return s;
        }
        if self.sample_clocks.len() <= link {
            let fresh = SourceClock::new(ClockSettings::default());
            self.sample_clocks.resize(link + 1, fresh);
        }
        let c = self.sample_clocks[link].stamp(None, Some(crate::clock::us_from_s(s.t_s)), None);
        (s.t_s, s.segment) = (c.t_s, c.segment);
        s
    }

    /// Feed a calibrated sample (body axes, stored gyro bias removed) to the orientation filter.
    /// A gyro still in counts (no scale known) is left out: the filter then runs on accel and mag.
    fn fuse(&mut self, c: &Calibrated) {
        let gyro = c
            .gyro_rad_s
            .filter(|_| self.tracks[0].pipe.gyro_units == Unit::Si);
        if c.accel_mps2.is_none() && gyro.is_none() && c.mag_ut.is_none() {
            return;
        }
        let s = Sample {
            gyro_rad_s: gyro,
            ..c.as_sample()
        };
        self.fusion.update_sample(&s, FUSION_DEFAULT_DT_S);
        if let Some(g) = gyro.filter(crate::types::is_finite3) {
            self.attitude_rates.add(&g);
        }
    }

    /// The fused attitude as ATTITUDE_QUATERNION and/or ATTITUDE (per `daemon.attitude_message`) and a
    /// JSON `attitude` line, once the filter has its tilt and its heading.
    async fn publish_attitude(&mut self) {
        let mean_rates = self.attitude_rates.take();
        if !(self.fusion.initialized() && self.fusion.mag_reference().is_some()) {
            return;
        }
        let o = self.fusion.orientation();
        let q = [o.q.w, o.q.i, o.q.j, o.q.k];
        if !q.iter().all(|c| c.is_finite()) {
            return;
        }
        // Body rates: the calibrated gyro less the filter's residual bias estimate.
        let residual_bias = self.fusion.bias();
        let rates_rad_s = mean_rates.map_or([0.0; 3], |r| {
            [
                r[0] - residual_bias[0],
                r[1] - residual_bias[1],
                r[2] - residual_bias[2],
            ]
        });
        let t_ms = (self.now_s() * 1000.0) as u32;
        let mut msgs = vec![];
        let which = self.cfg.daemon.attitude_message.as_str();
        if which == "attitude_quaternion" || which == "both" {
            msgs.extend(mavout::attitude_quaternion(t_ms, q, rates_rad_s));
        }
        if which == "attitude" || which == "both" {
            msgs.extend(mavout::attitude_from_quaternion(t_ms, q, rates_rad_s));
        }
        self.send_mav(&msgs).await;
        let stored_bias = self.calibrator.gyro_bias.unwrap_or([0.0; 3]);
        let ev = LiveEvent::Attitude {
            t: self.latest.map_or(self.tracks[0].pipe.last_t, |c| c.t_s),
            q,
            roll_deg: o.roll_deg,
            pitch_deg: o.pitch_deg,
            heading_deg: o.heading_deg,
            true_heading: self.declination.is_some(),
            gyro_bias_rad_s: [
                stored_bias[0] + residual_bias[0],
                stored_bias[1] + residual_bias[1],
                stored_bias[2] + residual_bias[2],
            ],
            mag_disturbed: self.fusion.mag_disturbed(),
        };
        self.send_json(&ev).await;
    }

    /// The vehicle a frame comes from: its link and system id (every link is one vehicle with
    /// `daemon.links = "merged"`), taken on when first heard.
    fn vehicle(&mut self, link: usize, system_id: u8) -> usize {
        let key = if self.cfg.daemon.links == "merged" {
            (0, 0)
        } else {
            (link, system_id)
        };
        if let Some(v) = self.vehicles.iter().position(|v| v.key == key) {
            return v;
        }
        self.vehicles.push(Vehicle {
            key,
            conv: self.new_converter.clone(),
            ardupilot: false,
            ap_params: ApCompassParams::default(),
            announced: false,
        });
        self.vehicles.len() - 1
    }

    /// A frame from a MAVLink link: heartbeats and parameters steer, IMU messages become samples.
    /// Our own frames echoed back (a router, a looped link) are dropped and counted.
    async fn on_frame(&mut self, link: usize, frame: &crate::decode::Frame, time_us: u64) -> bool {
        if self.own.is_own(frame.system_id, frame.component_id) {
            self.own_echo += 1;
            return false;
        }
        match &frame.message {
            MavMessage::HEARTBEAT(h) => {
                let v = self.vehicle(link, frame.system_id);
                if h.autopilot == MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA
                    && !self.vehicles[v].ardupilot
                    && frame.component_id != 191
                {
                    self.vehicles[v].ardupilot = true;
                    if self.cfg.daemon.ardupilot_corrected_mag == "undo" {
                        self.status(6, "ArduPilot link: reading COMPASS_* to undo its calibration before fitting".into()).await;
                        let reqs = mavout::param_request_reads(frame.system_id, frame.component_id);
                        self.send_mav(&reqs).await;
                    } else {
                        self.status(4, "ArduPilot link: its magnetometer data is already calibrated; set daemon.ardupilot_corrected_mag = \"undo\" to fit it".into()).await;
                    }
                }
                false
            }
            MavMessage::COMMAND_LONG(c) => {
                self.on_command(frame, c).await;
                false
            }
            MavMessage::PARAM_VALUE(_) => {
                let v = self.vehicle(link, frame.system_id);
                self.vehicles[v].ap_params.absorb(&frame.message);
                if let Some(w) = self.writer.as_mut() {
                    w.absorb(&frame.message);
                }
                false
            }
            _ => {
                let v = self.vehicle(link, frame.system_id);
                let Some((k, mut s)) = self.vehicles[v].conv.convert_any(&frame.message, time_us)
                else {
                    return false;
                };
                if *self.primary_vehicle.get_or_insert(v) != v {
                    self.other_vehicle_samples += 1;
                    if !std::mem::replace(&mut self.vehicles[v].announced, true) {
                        let (l, sys) = self.vehicles[v].key;
                        let label = self
                            .links
                            .get(l)
                            .map(|x| x.label.clone())
                            .unwrap_or_default();
                        self.status(4, format!("{label}: IMU data of a second vehicle (system {sys}): not calibrated; one vehicle is, the first heard (daemon.links = \"merged\" takes every link as one vehicle)")).await;
                    }
                    return false;
                }
                let Some(track) = self.track_of(k).await else {
                    return false;
                };
                let vh = &self.vehicles[v];
                if vh.ardupilot {
                    if let Some(m) = s.mag_ut {
                        s.mag_ut = if self.cfg.daemon.ardupilot_corrected_mag == "undo" {
                            vh.ap_params.undo(self.tracks[track].compass_id, m)
                        } else {
                            None
                        };
                        if s.mag_ut.is_none() {
                            self.mag_awaiting_params += 1;
                        }
                    }
                }
                if track == 0 {
                    self.on_sample(s)
                } else {
                    self.tracks[track].push(&s)
                }
            }
        }
    }

    /// The track of instance `k` of the calibrated vehicle: track 0 for its primary (named on its
    /// first sample), a new track for a further instance. `None` (counted) past
    /// [`crate::decode::MAX_INSTANCES`] tracks or when a pipeline cannot be made.
    async fn track_of(&mut self, k: usize) -> Option<usize> {
        if let Some(t) = self.tracks.iter().position(|t| t.instance == Some(k)) {
            return Some(t);
        }
        let v = self.primary_vehicle?;
        let conv = &self.vehicles[v].conv;
        let info = conv.instances().get(k).cloned()?;
        if conv.primary_index() == Some(k) {
            let t0 = &mut self.tracks[0];
            (t0.instance, t0.name, t0.compass_id) = (Some(k), info.name, info.compass_id);
            self.store.compass_id = info.compass_id;
            return Some(0);
        }
        if self.tracks.len() >= crate::decode::MAX_INSTANCES {
            self.other_instance_samples += 1;
            return None;
        }
        let mut t = match Track::new(&self.cfg, Some(k), info.name.clone(), info.compass_id) {
            Ok(t) => t,
            Err(e) => {
                tracing::error!("instance {} not calibrated: {e}", info.name);
                self.other_instance_samples += 1;
                return None;
            }
        };
        t.pipe.mag_units = info.units.mag;
        t.pipe.gyro_units = info.units.gyro;
        self.tracks.push(t);
        let text = format!(
            "{}: a further IMU instance (compass {}), calibrated on its own",
            info.name, info.compass_id
        );
        self.status(6, text).await;
        Some(self.tracks.len() - 1)
    }

    /// The heading cadence: the heading, and the next messages of a parameter write in progress.
    async fn on_heading_tick(&mut self) {
        self.publish_heading().await;
        if let Some(w) = self.writer.as_mut() {
            let now = self.start.elapsed().as_secs_f64();
            let msgs = w.next_messages(now);
            let done = w.done();
            let failed = w.failed();
            self.send_mav(&msgs).await;
            if done {
                self.writer = None;
                if failed.is_empty() {
                    self.status(
                        6,
                        "parameters written and confirmed by the flight controller".into(),
                    )
                    .await;
                } else {
                    self.status(
                        3,
                        format!("parameters not confirmed: {}", failed.join(", ")),
                    )
                    .await;
                }
            }
        }
    }

    async fn publish_heading(&mut self) {
        // The mean of the calibrated vectors since the last publication (decimation with averaging).
        let Some(mut c) = self.latest else { return };
        match self.window.take(self.declination) {
            Some(m) => c = Calibrated { t_s: c.t_s, ..m },
            // Nothing new since the last time: the latest sample again, with its angles.
            None => self.calibrator.add_attitude(&mut c),
        }
        let t_ms = (self.now_s() * 1000.0) as u32;
        let mut msgs = vec![];
        if let (Some(r), Some(p)) = (c.roll_deg, c.pitch_deg) {
            match (self.cfg.daemon.heading_message.as_str(), c.heading_deg) {
                ("named_value_float", Some(h)) => {
                    msgs.push(mavout::named_float("HEADING", t_ms, h as f32))
                }
                ("attitude", Some(h)) => msgs.push(mavout::attitude(t_ms, r, p, h)),
                _ => {}
            }
        }
        if self.cfg.daemon.debug_vect {
            let f = |v: Vec3| [v[0] as f32, v[1] as f32, v[2] as f32];
            if let Some(m) = c.mag_ut {
                msgs.push(mavout::debug_vect(
                    "MAG_UT",
                    (self.now_s() * 1e6) as u64,
                    f(m),
                ));
            }
            if let Some(a) = c.accel_mps2 {
                msgs.push(mavout::debug_vect(
                    "ACC_MPS2",
                    (self.now_s() * 1e6) as u64,
                    f(a),
                ));
            }
        }
        self.send_mav(&msgs).await;
        if let (Some(r), Some(p), Some(h)) = (c.roll_deg, c.pitch_deg, c.heading_deg) {
            let ev = LiveEvent::Heading {
                t: c.t_s,
                roll_deg: r,
                pitch_deg: p,
                heading_deg: h,
                true_heading: self.declination.is_some(),
            };
            self.send_json(&ev).await;
        }
        let ev = LiveEvent::Calibrated {
            t: c.t_s,
            accel_mps2: c.accel_mps2,
            gyro_rad_s: c.gyro_rad_s,
            mag_ut: c.mag_ut,
        };
        self.send_json(&ev).await;
    }

    /// MAG_CAL_PROGRESS and a JSON `progress` line for each compass whose calibration run
    /// reports progress (track 0 always; a further instance once it has magnetometer data).
    async fn publish_progress(&mut self) {
        let continuous = self.cfg.daemon.mag_cal == "continuous";
        for i in 0..self.tracks.len() {
            let centre = self
                .mag_in_use(i)
                .and_then(|m| m.calibration())
                .map(|c| c.offset);
            let t = &mut self.tracks[i];
            if (i > 0 && t.mag_samples == 0) || !t.mag_run.reports_progress(continuous) {
                continue;
            }
            let p = t.pipe.progress(&mut t.progress, centre);
            let dir = p.direction.map(|v| v as f32);
            let msg = mavout::mag_cal_progress(t.compass_id, p.completion_pct, p.mask, dir, 1);
            let ev = LiveEvent::Progress {
                sensor: "mag".into(),
                instance: t.compass_id,
                completion_pct: p.completion_pct as f64,
                filled_regions: p.filled_regions,
            };
            self.send_mav(&[msg]).await;
            self.send_json(&ev).await;
        }
    }

    /// The magnetometer calibration in use of track `i`.
    fn mag_in_use(&self, i: usize) -> Option<&SensorCalibration> {
        if i == 0 {
            return self.store.mag.as_ref();
        }
        let id = self.tracks[i].compass_id;
        let s = self.store.instances.iter().find(|s| s.compass_id == id)?;
        s.mag.as_ref()
    }

    /// The accelerometer calibration in use of track `i`.
    fn accel_in_use(&self, i: usize) -> Option<&SensorCalibration> {
        if i == 0 {
            return self.store.accel.as_ref();
        }
        let id = self.tracks[i].compass_id;
        let s = self.store.instances.iter().find(|s| s.compass_id == id)?;
        s.accel.as_ref()
    }

    /// A compass's name in messages to the user: empty with one compass.
    fn compass_label(&self, i: usize) -> String {
        if self.tracks.len() > 1 {
            format!(" (compass {})", self.tracks[i].compass_id)
        } else {
            String::new()
        }
    }

    /// A refit of track `i` came back: decide, store, publish.
    async fn on_fit(&mut self, i: usize, t: f64, results: FitResults) {
        let mut changed = false;
        let id = self.tracks[i].compass_id;
        // A commanded run is judged on its own, as ArduPilot's calibrator judges a run: its
        // result is reported whatever the calibration in use (accepting it is the ground
        // station's call). The magnetometer's result goes to the calibration run (`mag_event`),
        // which installs it or holds it for the ground station.
        let commanded = matches!(self.tracks[i].mag_run, MagCalRun::Running { .. });
        let current_mag = self.mag_in_use(i).filter(|_| !commanded).cloned();
        let mag_passed = match accept(&results.mag, current_mag.as_ref()) {
            Ok(()) => true,
            Err(why) => {
                tracing::info!(
                    sensor = "mag",
                    compass = id,
                    "calibration not replaced: {why}"
                );
                false
            }
        };
        match accept(&results.accel, self.accel_in_use(i)) {
            Ok(()) => {
                let r = &results.accel.report;
                tracing::info!(sensor = "accel", compass = id, model = %r.model, rms = r.rms_residual, "calibration accepted");
                if i == 0 {
                    self.store.accel = Some(r.clone());
                    self.calibrator.accel = results.accel.calibration;
                } else {
                    let name = self.tracks[i].name.clone();
                    self.store.instance_mut(&name, id).accel = Some(r.clone());
                }
                changed = true;
            }
            Err(why) => tracing::info!(
                sensor = "accel",
                compass = id,
                "calibration not replaced: {why}"
            ),
        }
        if i == 0 && results.gyro.status == "ok" {
            self.store.gyro = Some(results.gyro.clone());
            self.calibrator.gyro_bias = Some(results.gyro.bias);
        }
        // The magnetometer like ArduPilot's calibrator: success when accepted, failure once the
        // data covered the sphere and the fit still failed (not while still collecting).
        let mag = &results.mag.report;
        let completion = self.tracks[i].progress.completion_pct();
        if mag_passed {
            let ev = MagCalEvent::FitPassed {
                cal: Box::new(mag.clone()),
                complete: completion >= 100,
            };
            changed |= self.mag_event(i, ev).await.0;
        } else if failure_report_due(mag, completion) {
            self.tracks[i].mag_failed = Some(mag.clone());
            self.mag_event(i, MagCalEvent::FitFailed).await;
        }
        for (name, r) in [
            ("mag", &results.mag.report),
            ("accel", &results.accel.report),
        ] {
            self.send_json(&LiveEvent::calibration(name, id, r)).await;
        }
        self.tracks[i].pipe.install(t, results.clone());
        self.tracks[i].last_results = Some(results);
        if changed {
            self.store_changed();
        }
        if let Some(job) = self.report_job() {
            self.report_writes.want(job);
        }
    }

    /// A new calibration in the store: counted, and written off the run loop.
    fn store_changed(&mut self) {
        self.accepted += 1;
        let store = Box::new(self.store.clone());
        self.store_writes
            .want(WriteJob::Store(self.cal_dir.clone(), store));
    }

    /// Feed track `i`'s magnetometer calibration run an event and carry out what its transition
    /// says. Returns whether a calibration was installed (the caller has the store written) and
    /// the COMMAND_ACK results the transition gave (the caller answers the command once).
    async fn mag_event(&mut self, i: usize, ev: MagCalEvent) -> (bool, Vec<MavResult>) {
        let accepting = matches!(ev, MagCalEvent::Accept { .. });
        let continuous = self.cfg.daemon.mag_cal == "continuous";
        let id = self.tracks[i].compass_id;
        let run = std::mem::replace(&mut self.tracks[i].mag_run, MagCalRun::Idle);
        let (next, effects) = run.on(ev, continuous, id);
        self.tracks[i].mag_run = next;
        let (mut installed, mut reported, mut acks) = (false, false, vec![]);
        for fx in effects {
            match fx {
                MagCalEffect::Ack(result) => acks.push(result),
                MagCalEffect::Restart => self.restart_mag_run(i).await,
                MagCalEffect::Install(cal) => {
                    self.install_mag(i, *cal);
                    installed = true;
                }
                MagCalEffect::ReportSuccess {
                    cal,
                    autosaved,
                    commanded,
                } => {
                    let moved = self.tracks[i].reported_mag.as_ref().is_none_or(|prev| {
                        prev.model != cal.model
                            || (0..3).any(|k| (prev.offset[k] - cal.offset[k]).abs() > 0.05)
                    });
                    if commanded || moved {
                        reported = autosaved;
                        let msg = mavout::mag_cal_report_autosaved(id, &cal, autosaved);
                        self.send_mav(&[msg]).await;
                        let what = if autosaved {
                            "mag calibrated"
                        } else {
                            "mag calibration ready (accept to install it, cancel to discard it)"
                        };
                        let text = format!(
                            "{what}{}: {} offset [{:.2}, {:.2}, {:.2}] uT, rms {:.3}",
                            self.compass_label(i),
                            cal.model,
                            cal.offset[0],
                            cal.offset[1],
                            cal.offset[2],
                            cal.rms_residual
                        );
                        self.status(6, text).await;
                        self.tracks[i].reported_mag = Some(*cal);
                    }
                }
                MagCalEffect::ReportFailure => {
                    if let Some(mag) = self.tracks[i].mag_failed.take() {
                        self.send_mav(&[mavout::mag_cal_report(id, &mag)]).await;
                    }
                }
            }
        }
        if installed && (reported || accepting) && self.cfg.daemon.write_params {
            self.start_param_write();
        }
        (installed, acks)
    }

    /// A magnetometer calibration of track `i` in use from now on (the store is written by the
    /// caller). The primary's also goes to the heading and attitude.
    fn install_mag(&mut self, i: usize, cal: SensorCalibration) {
        tracing::info!(sensor = "mag", compass = self.tracks[i].compass_id, model = %cal.model, rms = cal.rms_residual, "calibration accepted");
        if i > 0 {
            let (name, id) = (self.tracks[i].name.clone(), self.tracks[i].compass_id);
            self.store.instance_mut(&name, id).mag = Some(cal);
            return;
        }
        let before = self.calibrator.mag;
        self.store.mag = Some(cal);
        self.calibrator.mag = self.store.mag_cal();
        if let Some(m) = self.last_body_mag {
            if mag_cal_moved(before.as_ref(), self.calibrator.mag.as_ref(), &m) {
                tracing::info!(
                    "magnetometer calibration moved the field: orientation filter restarted"
                );
                self.fusion = OrientationFilter::new(*self.fusion.config());
            }
        }
    }

    /// A new calibration run of track `i` from zero coverage: what was collected goes, a fit in
    /// flight is disregarded (it saw the old data); the calibration in use stays.
    async fn restart_mag_run(&mut self, i: usize) {
        let t = &mut self.tracks[i];
        match Pipeline::new(&self.cfg) {
            Ok(p) => {
                let (mag_units, gyro_units) = (t.pipe.mag_units, t.pipe.gyro_units);
                t.pipe = p.with_hold_out(HOLD_OUT_EVERY);
                (t.pipe.mag_units, t.pipe.gyro_units) = (mag_units, gyro_units);
            }
            Err(e) => tracing::error!("calibration run not restarted: {e}"),
        }
        t.generation += 1;
        t.refit_wanted = false;
        t.progress.restart();
        let text = format!("mag calibration run started{}", self.compass_label(i));
        self.status(6, text).await;
    }

    /// COMMAND_LONG: the ground station's calibration commands when addressed to us (or to all).
    /// Like ArduPilot, each compass has its own run and the command's compass mask says which
    /// take it (0: all); one COMMAND_ACK answers: accepted when a compass took it.
    async fn on_command(&mut self, frame: &crate::decode::Frame, c: &COMMAND_LONG_DATA) {
        let to_us = |target: u8, own: u8| target == 0 || target == own;
        if !(to_us(c.target_system, self.own.system_id)
            && to_us(c.target_component, self.own.component_id))
        {
            return;
        }
        let ev = match c.command {
            MavCmd::MAV_CMD_DO_START_MAG_CAL => MagCalEvent::Start {
                opts: mavout::MagCalStart::from_command(c),
                now_s: self.now_s(),
            },
            MavCmd::MAV_CMD_DO_ACCEPT_MAG_CAL => MagCalEvent::Accept {
                mask: mavout::mask_param(c.param1),
            },
            MavCmd::MAV_CMD_DO_CANCEL_MAG_CAL => MagCalEvent::Cancel {
                mask: mavout::mask_param(c.param1),
            },
            other => {
                // Another command meant for us alone gets an answer; broadcast ones are for others.
                if c.target_system != 0 && c.target_component != 0 {
                    let ack = mavout::command_ack(
                        other,
                        MavResult::MAV_RESULT_UNSUPPORTED,
                        frame.system_id,
                        frame.component_id,
                    );
                    self.send_mav(&[ack]).await;
                }
                return;
            }
        };
        tracing::info!(
            "{:?} from {}/{}",
            c.command,
            frame.system_id,
            frame.component_id
        );
        let (mut installed, mut acks) = (false, vec![]);
        for i in 0..self.tracks.len() {
            if i == 0 || self.tracks[i].mag_samples > 0 {
                let (inst, a) = self.mag_event(i, ev.clone()).await;
                installed |= inst;
                acks.extend(a);
            }
        }
        let result = if acks.contains(&MavResult::MAV_RESULT_ACCEPTED) {
            MavResult::MAV_RESULT_ACCEPTED
        } else {
            acks.first()
                .copied()
                .unwrap_or(MavResult::MAV_RESULT_FAILED)
        };
        let ack = mavout::command_ack(c.command, result, frame.system_id, frame.component_id);
        self.send_mav(&[ack]).await;
        if installed {
            self.store_changed();
        }
    }

    /// Write every compass's calibration in use to the flight controller (`daemon.write_params`).
    fn start_param_write(&mut self) {
        let params: Vec<_> = self
            .store
            .mags_ut()
            .iter()
            .flat_map(|(k, m)| {
                if self.cfg.daemon.param_target == "px4" {
                    crate::export::px4_mag(m, *k).0
                } else {
                    crate::export::ardupilot_mag(m, *k).0
                }
            })
            .collect();
        if params.is_empty() {
            return;
        }
        self.writer = Some(ParamWriter::new(
            params,
            self.cfg.daemon.target_system,
            self.cfg.daemon.target_component,
        ));
    }

    /// Write the calibration store now (at shutdown; while running, `store_writes` does it).
    async fn save(&mut self) {
        let job = WriteJob::Store(self.cal_dir.clone(), Box::new(self.store.clone()));
        let r = tokio::task::spawn_blocking(move || job.run()).await;
        self.written(r).await;
    }

    /// Say what came of a background write: a calibration that could not be written is reported
    /// (the previous file is kept: writes are atomic), a report only logged.
    async fn written(&mut self, r: Result<(Written, Result<(), Error>), tokio::task::JoinError>) {
        match r {
            Ok((Written::Calibration, Ok(()))) => {
                tracing::info!("calibration written to {}", self.cal_dir.display())
            }
            Ok((Written::Calibration, Err(e))) => {
                self.status(
                    3,
                    format!("calibration not written (the previous file is kept): {e}"),
                )
                .await
            }
            Ok((Written::Report, Ok(()))) => {}
            Ok((Written::Report, Err(e))) => tracing::warn!("report not written: {e}"),
            Err(e) => tracing::error!("file write task failed: {e}"),
        }
    }

    /// Write the report now (at shutdown).
    async fn write_report(&mut self) {
        if let Some(job) = self.report_job() {
            let r = tokio::task::spawn_blocking(move || job.run()).await;
            self.written(r).await;
        }
    }

    /// The report as it stands, ready to be written (none without `--report` or before a fit).
    fn report_job(&self) -> Option<WriteJob> {
        let (Some(path), Some(results)) =
            (self.report.clone(), self.tracks[0].last_results.clone())
        else {
            return None;
        };
        let mut stats = self
            .primary_vehicle
            .map(|v| self.vehicles[v].conv.stats.clone())
            .unwrap_or_default();
        stats.records += self.line_stats.records;
        stats.counts.add(&self.line_stats.counts);
        stats.skip_n("other_vehicle", self.other_vehicle_samples);
        stats.skip_n("too_many_instances", self.other_instance_samples);
        for l in &self.links {
            if let Ok(d) = l.handle.decode_stats.lock() {
                for (k, v) in &d.skipped {
                    *stats.skipped.entry(k.clone()).or_insert(0) += v;
                }
                stats.time.add(&d.time);
            }
            let dropped = l
                .handle
                .counters
                .inbound_dropped
                .load(std::sync::atomic::Ordering::Relaxed);
            stats.skip_n("queue_full", dropped);
        }
        stats.skip_n("mag_awaiting_params", self.mag_awaiting_params);
        for c in &self.sample_clocks {
            stats.time.add(&c.stats);
        }
        stats.skip_n("own_echo", self.own_echo);
        let label = self
            .links
            .iter()
            .map(|l| l.label.clone())
            .collect::<Vec<_>>()
            .join(",");
        let input = crate::report::InputReport::new(
            "live",
            Some(label),
            self.primary_vehicle
                .and_then(|v| self.vehicles[v].conv.instance())
                .map(String::from),
            &stats,
            self.tracks[0].pipe.samples,
            self.tracks[0].pipe.last_t,
        );
        let pipe = &self.tracks[0].pipe;
        let mut report = crate::replay::make_report(input, pipe, &results, self.declination);
        report.instances = self.instance_reports(&report.calibration);
        report.outputs = Some(self.outputs_report());
        Some(WriteJob::Report(path, Box::new(report)))
    }
}

impl State {
    /// Start a fit of every track whose refit is due (`all`: of every track, with its last poses
    /// closed: the end of a replay), off the executor.
    fn start_fits(&mut self, all: bool) -> tokio::task::JoinHandle<TrackFits> {
        let mut inputs = vec![];
        for (i, t) in self.tracks.iter_mut().enumerate() {
            if all {
                t.pipe.finish_poses();
            } else if !t.refit_wanted {
                continue;
            }
            t.refit_wanted = false;
            inputs.push((i, t.generation, t.pipe.last_t, t.pipe.snapshot()));
        }
        let cfg = self.cfg.clone();
        tokio::task::spawn_blocking(move || {
            inputs
                .into_iter()
                .map(|(i, generation, t, input)| (i, generation, t, fit_all(&input, &cfg)))
                .collect()
        })
    }

    /// Fits came back: each goes to its track unless that track's run restarted meanwhile.
    async fn fits_done(&mut self, r: Result<TrackFits, tokio::task::JoinError>) {
        match r {
            Ok(fits) => {
                for (i, generation, t, res) in fits {
                    if generation == self.tracks[i].generation {
                        self.on_fit(i, t, res).await;
                    } else {
                        tracing::info!(
                            "a fit from before the calibration run restarted: disregarded"
                        );
                    }
                }
            }
            Err(e) => tracing::error!("fit task failed: {e}"),
        }
    }
}

/// A block per calibrated instance for the report (empty with one): the primary's calibration is
/// the report's own (`primary`), the others' their latest fits.
impl State {
    fn instance_reports(
        &self,
        primary: &crate::report::CalibrationReport,
    ) -> Vec<crate::report::InstanceReport> {
        if self.tracks.len() < 2 {
            return Vec::new();
        }
        let infos = self
            .primary_vehicle
            .map(|v| self.vehicles[v].conv.instances())
            .unwrap_or_default();
        self.tracks
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let calibration = if i == 0 {
                    primary.clone()
                } else {
                    let r = t.last_results.as_ref()?;
                    crate::report::CalibrationReport {
                        mag: r.mag.report.clone(),
                        accel: r.accel.report.clone(),
                        gyro: r.gyro.clone(),
                    }
                };
                let info = t.instance.and_then(|k| infos.get(k));
                Some(crate::report::InstanceReport {
                    instance: t.name.clone(),
                    compass_id: t.compass_id,
                    primary: i == 0,
                    samples: info.map_or(t.pipe.samples, |x| x.samples),
                    time: info.map(|x| x.time.clone()).unwrap_or_default(),
                    calibration,
                })
            })
            .collect()
    }
}

/// A file the service writes: the calibration store, or the report.
enum WriteJob {
    Store(PathBuf, Box<StoredCalibration>),
    Report(PathBuf, Box<crate::report::Report>),
}

/// Which file a finished write was.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Written {
    Calibration,
    Report,
}

impl WriteJob {
    /// Write it (blocking: temp file, fsync, rename). Returns which file it was, and how it went.
    fn run(self) -> (Written, Result<(), Error>) {
        match self {
            WriteJob::Store(dir, store) => (Written::Calibration, save_store(&dir, &store)),
            WriteJob::Report(path, report) => {
                (Written::Report, crate::publish::write_json(&path, &report))
            }
        }
    }
}

/// One file kept up to date off the run loop: at most one write in flight on the blocking pool;
/// content asked for meanwhile waits, and newer content replaces it (only the latest is written).
/// An fsync on a slow card can take a good part of a second; the live outputs must not wait for it.
#[derive(Default)]
struct Writes {
    job: Option<tokio::task::JoinHandle<(Written, Result<(), Error>)>>,
    next: Option<WriteJob>,
}

impl Writes {
    fn want(&mut self, job: WriteJob) {
        self.next = Some(job);
    }

    /// Start the waiting write if none is in flight.
    fn start(&mut self) {
        if self.job.is_none() {
            if let Some(job) = self.next.take() {
                self.job = Some(tokio::task::spawn_blocking(move || job.run()));
            }
        }
    }

    /// The write in flight (polled only when there is one).
    async fn done(&mut self) -> Result<(Written, Result<(), Error>), tokio::task::JoinError> {
        match self.job.as_mut() {
            Some(j) => {
                let r = j.await;
                self.job = None;
                r
            }
            None => std::future::pending().await,
        }
    }
}

/// Running means of calibrated vectors between publications.
#[derive(Debug, Default)]
struct Averager {
    a: [f64; 3],
    na: usize,
    g: [f64; 3],
    ng: usize,
    m: [f64; 3],
    nm: usize,
}

impl Averager {
    fn add(&mut self, c: &Calibrated) {
        let acc = |s: &mut [f64; 3], n: &mut usize, v: Option<Vec3>| {
            if let Some(v) = v {
                for k in 0..3 {
                    s[k] += v[k];
                }
                *n += 1;
            }
        };
        acc(&mut self.a, &mut self.na, c.accel_mps2);
        acc(&mut self.g, &mut self.ng, c.gyro_rad_s);
        acc(&mut self.m, &mut self.nm, c.mag_ut);
    }

    /// Means and the attitude from them; resets. None when nothing arrived.
    fn take(&mut self, declination: Option<f64>) -> Option<Calibrated> {
        let mean = |s: [f64; 3], n: usize| (n > 0).then(|| s.map(|v| v / n as f64));
        let out = Calibrated {
            accel_mps2: mean(self.a, self.na),
            gyro_rad_s: mean(self.g, self.ng),
            mag_ut: mean(self.m, self.nm),
            ..Default::default()
        };
        *self = Averager::default();
        if out.accel_mps2.is_none() && out.mag_ut.is_none() {
            return None;
        }
        let mut out = out;
        if let Some(f) = out.accel_mps2 {
            let (r, p) = crate::attitude::roll_pitch_deg(&f);
            out.roll_deg = Some(r);
            out.pitch_deg = Some(p);
            if let Some(m) = out.mag_ut {
                out.heading_deg = Some(crate::attitude::wrap360(
                    crate::attitude::heading_deg(&m, r, p) + declination.unwrap_or(0.0),
                ));
            }
        }
        Some(out)
    }
}

fn severity_name(s: u8) -> &'static str {
    match s {
        0..=3 => "error",
        4 => "warning",
        5 | 6 => "info",
        _ => "debug",
    }
}

/// Run the service until `shutdown` turns true, or until every replay/sim source has ended.
pub async fn run(cfg: Config, mut shutdown: watch::Receiver<bool>) -> Result<RunSummary, Error> {
    // Checked here too (callers may build the config in code): bad rates would stop the timers.
    cfg.validate()?;
    let d = cfg.daemon.clone();
    let sources = if d.sources.is_empty() {
        vec![SourceConfig {
            address: "sim:tumble".into(),
            payload: "mavlink".into(),
            fields: vec![],
            scales: Default::default(),
        }]
    } else {
        d.sources.clone()
    };
    let cal_dir = PathBuf::from(&d.calibration_dir);
    let store = load_store(&cal_dir)?.unwrap_or_else(StoredCalibration::empty);
    if store.mag.is_some() || store.accel.is_some() {
        tracing::info!(
            "resuming from the calibration in {}",
            cal_dir.join(STORE_FILE).display()
        );
    }
    let declination = cfg.declination_deg()?;
    let mut sinks = vec![];
    for p in &d.publish {
        sinks.push(Sink::open(p)?);
    }
    let (tx, mut rx) = mpsc::channel::<Inbound>(d.queue_capacity);
    // The time grid the UDP polls and the periodic outputs share.
    let epoch = tokio::time::Instant::now();
    let (link_stop_tx, link_stop_rx) = watch::channel(false);
    let mut links = vec![];
    for (i, s) in sources.iter().enumerate() {
        let addr = Address::parse(&s.address)?;
        let replay = matches!(addr, Address::File { .. } | Address::Sim { .. });
        let payload = payload_of(s);
        let mavlink = matches!(payload, Payload::Mavlink) && !matches!(addr, Address::Sim { .. });
        let opts = LinkOptions {
            silent_after_s: d.silent_after_s,
            // A consumer of per-sample attitude wants each sample at once.
            udp_poll_s: if d.attitude_every_samples > 0 {
                0.0
            } else {
                d.udp_poll_ms / 1000.0
            },
            poll_epoch: Some(epoch),
            ..LinkOptions::default()
        };
        let polled = matches!(addr, Address::UdpIn(_) | Address::UdpOut(_));
        let handle = spawn_link(i, addr, payload, tx.clone(), link_stop_rx.clone(), opts);
        links.push(LinkEntry {
            handle,
            mavlink,
            polled,
            ended: false,
            replay,
            label: s.address.clone(),
            outbound_queue_full: 0,
            queue_full_reported: 0,
        });
    }
    drop(tx);
    let choice = if cfg.input.instance == "auto" {
        InstanceChoice::Auto
    } else {
        InstanceChoice::Named(cfg.input.instance.clone())
    };
    let mut new_converter = MessageConverter::new(choice.clone(), cfg.input.raw_imu_scale);
    if new_converter.choice == InstanceChoice::Auto {
        // Every compass of the calibrated vehicle, each on its own track.
        new_converter = new_converter.with_other_instances();
    }
    let track0 = Track::new(&cfg, None, String::new(), store.compass_id)?;
    let mut st = State {
        tracks: vec![track0],
        sample_clocks: Vec::new(),
        calibrator: State::calibrator_from_store(&store, declination),
        store,
        latest: None,
        enc: MavEncoder::new(d.system_id, d.component_id),
        own: mavout::OwnIds {
            system_id: d.system_id,
            component_id: d.component_id,
        },
        own_echo: 0,
        mav_out: Vec::with_capacity(MAV_DATAGRAM_MAX),
        store_writes: Writes::default(),
        report_writes: Writes::default(),
        links,
        sinks,
        vehicles: Vec::new(),
        primary_vehicle: None,
        other_vehicle_samples: 0,
        other_instance_samples: 0,
        new_converter,
        line_stats: crate::decode::DecodeStats::default(),
        writer: None,
        accepted: 0,
        cal_dir,
        report: d.report.as_ref().map(PathBuf::from),
        start: tokio::time::Instant::now(),
        declination,
        mag_awaiting_params: 0,
        window: Averager::default(),
        fusion: OrientationFilter::new(cfg.fusion_config(declination)),
        attitude_rates: RateMean::default(),
        samples_since_attitude: 0,
        attitude_due: false,
        last_body_mag: None,
        cfg,
    };
    // The periodic outputs, on the same time grid as the links' UDP polls (`epoch`). Those whose
    // period is a whole number of clock periods are served at the ticks of one clock that ticks
    // with the polls, in the wake-up a poll makes anyway (a timer of its own per output, set 100 ms
    // or more ahead, would cost tokio's timer wheel a wake-up of its own to move it to its finest
    // level). Any other keeps a timer of its own, so every output stays evenly spaced.
    let polled = st.links.iter().any(|l| l.polled);
    let poll = (polled && d.udp_poll_ms > 0.0 && d.attitude_every_samples == 0)
        .then(|| Duration::from_secs_f64(d.udp_poll_ms / 1000.0));
    let mut outputs = [
        Output::new(epoch, d.heading_rate_hz),
        Output::new(epoch, d.progress_rate_hz),
        Output::new(epoch, d.attitude_rate_hz),
    ];
    let clock_period = poll
        .or_else(|| outputs.iter().map(|o| o.cadence.period).min())
        .unwrap_or(Duration::from_millis(100));
    for o in outputs.iter_mut() {
        o.use_clock(epoch, clock_period);
    }
    let [mut heading_out, mut progress_out, mut attitude_out] = outputs;
    let mut drops_out = Output::new(epoch, 1.0 / DROPS_REPORT_S);
    drops_out.use_clock(epoch, clock_period);
    let mut heartbeat_out = (d.heartbeat_rate_hz > 0.0).then(|| {
        let mut o = Output::new(epoch, d.heartbeat_rate_hz);
        o.use_clock(epoch, clock_period);
        o
    });
    let mut clock = tokio::time::interval_at(epoch, clock_period);
    clock.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // One fit job at a time, for every track whose refit was due when it started.
    let mut fit_job: Option<tokio::task::JoinHandle<TrackFits>> = None;
    // Whatever is queued is taken in one go (at most this many), so the select below runs once per
    // batch of samples rather than once per sample.
    const INBOX_BATCH: usize = 256;
    let mut inbox: Vec<Inbound> = Vec::with_capacity(INBOX_BATCH);
    'main: loop {
        // `daemon.attitude_every_samples`: the attitude right after the sample that made it due.
        if st.attitude_due {
            st.attitude_due = false;
            st.publish_attitude().await;
        }
        if fit_job.is_none() && st.tracks.iter().any(|t| t.refit_wanted) {
            fit_job = Some(st.start_fits(false));
        }
        // Whatever this turn queued for the links goes out before the loop waits again.
        st.flush_mav();
        st.store_writes.start();
        st.report_writes.start();
        tokio::select! {
            _ = shutdown.changed() => {
                if *shutdown.borrow() { break; }
            }
            n = rx.recv_many(&mut inbox, INBOX_BATCH) => {
                if n == 0 {
                    break;
                }
                for ev in inbox.drain(..) {
                    if st.attitude_due {
                        st.attitude_due = false;
                        st.publish_attitude().await;
                    }
                    match ev {
                        Inbound::Sample { link, sample } => {
                            let sample = st.stamp(link, sample);
                            st.line_stats.records += 1;
                            st.line_stats.count_sample(&sample);
                            st.on_sample(sample);
                        }
                        Inbound::Frame { link, frame, time_us } => {
                            st.on_frame(link, &frame, time_us).await;
                        }
                        Inbound::Status { link, status } => {
                            let label = st.links.get(link).map(|l| l.label.clone()).unwrap_or_default();
                            match status {
                                LinkStatus::Connected(s) => st.status(6, format!("{label}: connected {s}")).await,
                                LinkStatus::Lost(s) => st.status(4, format!("{label}: lost ({s}); reconnecting, calibration kept")).await,
                                LinkStatus::Silent { for_s } => st.status(4, format!("{label}: silent for {for_s:.1} s")).await,
                                LinkStatus::Ended => {
                                    if let Some(l) = st.links.get_mut(link) { l.ended = true; }
                                    if st.links.iter().all(|l| l.replay && l.ended) {
                                        // Every source was a replay and all have ended: final fit, then stop.
                                        if let Some(j) = fit_job.take() { st.fits_done(j.await).await; }
                                        let last = st.start_fits(true).await;
                                        st.fits_done(last).await;
                                        break 'main;
                                    }
                                }
                            }
                        }
                    }
                }
            }
            r = async { fit_job.as_mut().expect("guarded").await }, if fit_job.is_some() => {
                fit_job = None;
                st.fits_done(r).await;
            }
            t = clock.tick() => {
                if heading_out.due_at_clock(t) {
                    st.on_heading_tick().await;
                }
                if progress_out.due_at_clock(t) {
                    st.publish_progress().await;
                }
                if attitude_out.due_at_clock(t) {
                    st.publish_attitude().await;
                }
                if drops_out.due_at_clock(t) {
                    st.report_drops().await;
                }
                if heartbeat_out.as_mut().is_some_and(|o| o.due_at_clock(t)) {
                    st.send_heartbeat().await;
                }
                for i in 0..st.tracks.len() {
                    if matches!(st.tracks[i].mag_run, MagCalRun::Waiting { .. }) {
                        let now_s = st.now_s();
                        st.mag_event(i, MagCalEvent::Tick { now_s }).await;
                    }
                }
            }
            _ = heading_out.own_tick(), if heading_out.own.is_some() => st.on_heading_tick().await,
            _ = progress_out.own_tick(), if progress_out.own.is_some() => st.publish_progress().await,
            _ = attitude_out.own_tick(), if attitude_out.own.is_some() => st.publish_attitude().await,
            _ = drops_out.own_tick(), if drops_out.own.is_some() => st.report_drops().await,
            _ = async { heartbeat_out.as_mut().expect("guarded").own_tick().await },
                if heartbeat_out.as_ref().is_some_and(|o| o.own.is_some()) => st.send_heartbeat().await,
            r = st.store_writes.done(), if st.store_writes.job.is_some() => st.written(r).await,
            r = st.report_writes.done(), if st.report_writes.job.is_some() => st.written(r).await,
        }
    }
    st.flush_mav();
    // Shutdown: stop the links, keep the last good calibration on disk, write the report.
    let _ = link_stop_tx.send(true);
    if let Some(j) = fit_job.take() {
        if let Ok(r) = tokio::time::timeout(Duration::from_millis(500), j).await {
            st.fits_done(r).await;
        }
    }
    // Writes in flight finish first, so an older file cannot land after the final one.
    for w in [&mut st.store_writes, &mut st.report_writes] {
        w.next = None;
    }
    if st.store_writes.job.is_some() {
        let r = st.store_writes.done().await;
        st.written(r).await;
    }
    if st.report_writes.job.is_some() {
        let r = st.report_writes.done().await;
        st.written(r).await;
    }
    if st.store.mag.is_some() || st.store.accel.is_some() {
        st.save().await;
    }
    st.write_report().await;
    // What is queued for the JSON consumers goes out, briefly: one that does not read cannot hold
    // the exit.
    st.report_drops().await;
    close_sinks(
        &mut st.sinks,
        tokio::time::Instant::now() + SINK_DRAIN_AT_EXIT,
    )
    .await;
    let inbound_dropped = st
        .links
        .iter()
        .map(|l| {
            l.handle
                .counters
                .inbound_dropped
                .load(std::sync::atomic::Ordering::Relaxed)
        })
        .sum();
    for l in &st.links {
        l.handle.task.abort();
    }
    Ok(RunSummary {
        samples: st.tracks[0].pipe.samples,
        accepted: st.accepted,
        inbound_dropped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cal(offset: Vec3, scale: f64) -> Calibration {
        Calibration {
            model: crate::model::ModelKind::Sphere,
            offset,
            matrix: [[scale, 0.0, 0.0], [0.0, scale, 0.0], [0.0, 0.0, scale]],
        }
    }

    #[test]
    fn daemon_restarts_fusion_only_when_the_mag_calibration_moves_the_field() {
        let raw = [30.0, -10.0, 45.0];
        let c = cal([10.0, -20.0, 30.0], 1.0);
        // First calibration after raw data: the field the filter sees jumps.
        assert!(mag_cal_moved(None, Some(&c), &raw));
        // A refit that moves the offset by a fraction of a uT: the filter keeps going.
        let near = cal([10.1, -20.05, 30.0], 1.005);
        assert!(!mag_cal_moved(Some(&c), Some(&near), &raw));
        assert!(!mag_cal_moved(Some(&c), Some(&c), &raw));
        // Norm by 5 %, or direction by several degrees: restart.
        assert!(mag_cal_moved(
            Some(&c),
            Some(&cal([10.0, -20.0, 30.0], 1.05)),
            &raw
        ));
        assert!(mag_cal_moved(
            Some(&c),
            Some(&cal([10.0, -17.0, 30.0], 1.0)),
            &raw
        ));
        // Degenerate or broken readings never restart it.
        assert!(!mag_cal_moved(Some(&c), Some(&near), &[10.0, -20.0, 30.0]));
        assert!(!mag_cal_moved(None, Some(&c), &[f64::NAN, 0.0, 0.0]));
    }

    #[test]
    fn daemon_replaces_a_calibration_only_when_better_on_points_held_out_of_the_fit() {
        let sim = crate::sim::simulate(&crate::sim::Scenario::named("tumble").unwrap(), 5);
        let cfg = Config::default();
        let mut pipe = Pipeline::new(&cfg).unwrap().with_hold_out(HOLD_OUT_EVERY);
        for s in &sim.samples {
            pipe.push(s);
        }
        pipe.finish_poses();
        let input = pipe.snapshot();
        let r = fit_all(&input, &cfg);
        let n = input.mag_points.len();
        // Every 5th kept point held out, the fit made on the rest.
        assert_eq!(r.mag.held_out.len(), n.div_ceil(HOLD_OUT_EVERY));
        assert!(r.mag.report.samples_used <= n - r.mag.held_out.len());
        let every_fifth: Vec<Vec3> = input
            .mag_points
            .iter()
            .step_by(HOLD_OUT_EVERY)
            .copied()
            .collect();
        assert_eq!(r.mag.held_out, every_fifth);
        assert_eq!(r.mag.report.status, "ok", "{:?}", r.mag.report.detail);
        let truth = &sim.truth.mag;
        let current = |offset: Vec3| SensorCalibration {
            offset,
            matrix: truth.matrix,
            ..r.mag.report.clone()
        };
        // Nothing to compare with: its checks decide.
        assert_eq!(accept(&r.mag, None), Ok(()));
        // A current calibration 3 uT off: replaced.
        let off = [truth.offset[0] + 3.0, truth.offset[1], truth.offset[2]];
        assert_eq!(accept(&r.mag, Some(&current(off))), Ok(()));
        // A new one 1 uT off against the true one: worse on the held-out points, kept out.
        let mut worse = r.mag.clone();
        let c = worse.calibration.as_mut().unwrap();
        c.offset[1] += 1.0;
        match accept(&worse, Some(&current(truth.offset))) {
            Err(NotReplaced::WorseOnHeldOut {
                points,
                rms_new,
                rms_current,
            }) => {
                assert_eq!(points, r.mag.held_out.len());
                assert!(
                    rms_new > rms_current * (1.0 + ACCEPT_MARGIN),
                    "{rms_new} {rms_current}"
                );
            }
            other => panic!("{other:?}"),
        }
        // No points held out: no comparison, the current one stays.
        let mut none = r.mag.clone();
        none.held_out.clear();
        assert_eq!(
            accept(&none, Some(&current(off))),
            Err(NotReplaced::NothingHeldOut)
        );
        // A failed fit never replaces anything.
        let mut failed = r.mag.clone();
        failed.calibration = None;
        failed.report.failure = Some("coverage".into());
        assert!(matches!(
            accept(&failed, None),
            Err(NotReplaced::Failed { .. })
        ));
    }

    #[test]
    fn daemon_attitude_rates_are_means_between_publications() {
        let mut r = RateMean::default();
        assert_eq!(r.take(), None);
        r.add(&[0.1, 0.2, 0.3]);
        r.add(&[0.3, 0.0, -0.3]);
        assert_eq!(r.take(), Some([0.2, 0.1, 0.0]));
        // Nothing new: the last mean again.
        assert_eq!(r.take(), Some([0.2, 0.1, 0.0]));
        r.add(&[1.0, 1.0, 1.0]);
        assert_eq!(r.take(), Some([1.0, 1.0, 1.0]));
    }

    /// A TCP consumer that accepts and never reads: queueing lines for it never waits, what its
    /// queue cannot hold is counted, and closing it is bounded by the deadline.
    #[tokio::test]
    async fn daemon_json_sink_for_a_stuck_consumer_drops_counts_and_closes_in_time() {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let held = std::thread::spawn(move || l.accept().map(|(c, _)| c));
        let mut sinks = vec![Sink::open(&format!("tcp:{addr}")).unwrap()];
        // 20 000 lines of 1 kB: far more than the socket buffers and the queue hold.
        let line: std::sync::Arc<str> = format!("{}\n", "x".repeat(1023)).into();
        let t0 = std::time::Instant::now();
        for i in 0..20_000 {
            sinks[0].send(&line);
            if i % 256 == 0 {
                // Let the writer run (connect, fill the socket, block).
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        let queued_s = t0.elapsed().as_secs_f64();
        let r = sinks[0].report();
        // Measured: 3841 sent, 15071 dropped with the queue full.
        assert!(r.queue_full > 5_000, "{r:?}");
        // Every line is accounted for: sent, dropped, or still queued / in the writer's hands.
        let in_flight = (SINK_QUEUE_LINES + SINK_BATCH) as u64;
        assert!(
            r.sent + r.queue_full + r.not_delivered + in_flight >= 20_000,
            "{r:?}"
        );
        assert_eq!(sinks[0].lost(), r.queue_full + r.not_delivered);
        let t1 = tokio::time::Instant::now();
        close_sinks(&mut sinks, t1 + Duration::from_millis(100)).await;
        let closed_s = t1.elapsed().as_secs_f64();
        eprintln!("{r:?}: queued in {queued_s:.3} s, closed in {closed_s:.3} s");
        // Measured: queueing ~0.15 s (mostly the sleeps), closing 0.10 s (the deadline).
        assert!(queued_s < 2.0 && closed_s < 0.5, "{queued_s} {closed_s}");
        drop(held);
    }

    /// Two links, two vehicles: an ArduPilot HEARTBEAT on one does not make the service undo the
    /// other's (PX4) magnetometer data, and the second vehicle's IMU data is counted, not mixed
    /// into the first's calibration. With `daemon.links = "merged"` both are one vehicle.
    #[tokio::test]
    async fn daemon_keeps_links_apart_as_vehicles() {
        use mavlink::dialects::ardupilotmega::{MavType, HEARTBEAT_DATA, HIGHRES_IMU_DATA};
        for merged in [false, true] {
            let dir = tempfile::tempdir().unwrap();
            let ports: Vec<u16> = (0..2)
                .map(|_| {
                    let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
                    s.local_addr().unwrap().port()
                })
                .collect();
            let mut cfg = Config::default();
            cfg.daemon.sources = ports
                .iter()
                .map(|p| SourceConfig {
                    address: format!("udpin:127.0.0.1:{p}"),
                    payload: "mavlink".into(),
                    fields: vec![],
                    scales: Default::default(),
                })
                .collect();
            let report = dir.path().join("report.json");
            cfg.daemon.calibration_dir = dir.path().join("cal").display().to_string();
            cfg.daemon.report = Some(report.display().to_string());
            cfg.daemon.publish = vec![];
            cfg.daemon.links = if merged { "merged" } else { "separate" }.into();
            cfg.daemon.heartbeat_rate_hz = 0.0;
            cfg.fit.refit_every_s = 0.1;
            let (stop_tx, stop_rx) = watch::channel(false);
            let daemon = tokio::spawn(run(cfg, stop_rx));
            tokio::time::sleep(Duration::from_millis(200)).await;
            let imu = |i: u64| {
                MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                    time_usec: 1_000_000 + i * 10_000,
                    zacc: -9.81,
                    xmag: 0.2 + 0.001 * i as f32,
                    zmag: 0.4,
                    ..Default::default()
                })
            };
            let (px4, ap) = (
                tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap(),
                tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap(),
            );
            px4.connect(("127.0.0.1", ports[0])).await.unwrap();
            ap.connect(("127.0.0.1", ports[1])).await.unwrap();
            let (mut px4_enc, mut ap_enc) = (MavEncoder::new(1, 1), MavEncoder::new(7, 1));
            // The PX4 vehicle's IMU data first (it is the one calibrated), then an ArduPilot
            // vehicle on the other link: its HEARTBEAT and IMU data, then more PX4 data.
            for i in 0..30 {
                px4.send(&px4_enc.encode(&imu(i))).await.unwrap();
            }
            tokio::time::sleep(Duration::from_millis(150)).await;
            let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                ..Default::default()
            });
            ap.send(&ap_enc.encode(&hb)).await.unwrap();
            for i in 0..20 {
                ap.send(&ap_enc.encode(&imu(i))).await.unwrap();
            }
            tokio::time::sleep(Duration::from_millis(150)).await;
            for i in 30..60 {
                px4.send(&px4_enc.encode(&imu(i))).await.unwrap();
            }
            tokio::time::sleep(Duration::from_millis(300)).await;
            stop_tx.send(true).unwrap();
            let summary = daemon.await.unwrap().unwrap();
            let r: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
            let skipped = &r["input"]["skipped"];
            if merged {
                // One vehicle: the ArduPilot HEARTBEAT holds back the magnetometer data from then
                // on (its COMPASS_* never come), as it does for a single ArduPilot link.
                assert_eq!(summary.samples, 80, "{r}");
                assert!(
                    skipped["mag_awaiting_params"].as_u64().unwrap_or(0) > 0,
                    "{skipped}"
                );
            } else {
                assert_eq!(summary.samples, 60, "{r}");
                assert_eq!(skipped["other_vehicle"].as_u64(), Some(20), "{skipped}");
                assert!(skipped.get("mag_awaiting_params").is_none(), "{skipped}");
            }
        }
    }

    /// Our own frames echoed back (same system and component id) are dropped and counted, never
    /// samples and never a vehicle's HEARTBEAT; our HEARTBEAT goes out on the link.
    #[tokio::test]
    async fn daemon_drops_its_own_echo_and_sends_heartbeats() {
        use mavlink::dialects::ardupilotmega::{MavType, HEARTBEAT_DATA, HIGHRES_IMU_DATA};
        let dir = tempfile::tempdir().unwrap();
        let port = std::net::UdpSocket::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let json = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut cfg = Config::default();
        cfg.daemon.sources = vec![SourceConfig {
            address: format!("udpin:127.0.0.1:{port}"),
            payload: "mavlink".into(),
            fields: vec![],
            scales: Default::default(),
        }];
        cfg.daemon.calibration_dir = dir.path().join("cal").display().to_string();
        cfg.daemon.report = Some(dir.path().join("report.json").display().to_string());
        cfg.daemon.publish = vec![format!("udp:{}", json.local_addr().unwrap())];
        // Not 191: the ArduPilot detection already passes over component 191, whoever sends it.
        cfg.daemon.system_id = 1;
        cfg.daemon.component_id = 190;
        cfg.fit.refit_every_s = 0.1;
        let (stop_tx, stop_rx) = watch::channel(false);
        let daemon = tokio::spawn(run(cfg, stop_rx));
        tokio::time::sleep(Duration::from_millis(200)).await;
        let peer = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        peer.connect(("127.0.0.1", port)).await.unwrap();
        let imu = |i: u64| {
            MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                time_usec: 1_000_000 + i * 10_000,
                zacc: -9.81,
                xmag: 0.2,
                zmag: 0.4,
                ..Default::default()
            })
        };
        let (mut echo, mut fc) = (MavEncoder::new(1, 190), MavEncoder::new(1, 1));
        // Our own id on an ArduPilot HEARTBEAT and on IMU frames: none of it is taken.
        let ap = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            ..Default::default()
        });
        peer.send(&echo.encode(&ap)).await.unwrap();
        for i in 0..40 {
            peer.send(&echo.encode(&imu(i))).await.unwrap();
        }
        for i in 0..30 {
            peer.send(&fc.encode(&imu(100 + i))).await.unwrap();
        }
        let mut dec = crate::decode::FrameDecoder::new();
        let mut heartbeats = vec![];
        let mut buf = vec![0u8; 65_536];
        let until = tokio::time::Instant::now() + Duration::from_millis(2300);
        while let Ok(Ok(n)) = tokio::time::timeout_at(until, peer.recv(&mut buf)).await {
            for f in dec.push(&buf[..n]) {
                if let MavMessage::HEARTBEAT(h) = f.message {
                    heartbeats.push((f.system_id, f.component_id, h.mavtype, h.autopilot));
                }
            }
        }
        stop_tx.send(true).unwrap();
        let summary = daemon.await.unwrap().unwrap();
        assert_eq!(summary.samples, 30);
        // At 1 s and 2 s (the one at the start went nowhere: no peer had sent anything yet).
        assert!((2..=3).contains(&heartbeats.len()), "{heartbeats:?}");
        for h in &heartbeats {
            assert_eq!(
                *h,
                (
                    1,
                    190,
                    MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                    MavAutopilot::MAV_AUTOPILOT_INVALID
                )
            );
        }
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap())
                .unwrap();
        assert_eq!(
            report["input"]["skipped"]["own_echo"], 41,
            "{}",
            report["input"]
        );
        assert!(report["input"]["skipped"]
            .get("mag_awaiting_params")
            .is_none());
        let mut lines = vec![];
        while let Ok(Ok(n)) =
            tokio::time::timeout(Duration::from_millis(50), json.recv(&mut buf)).await
        {
            lines.push(String::from_utf8_lossy(&buf[..n]).to_string());
        }
        assert!(!lines.is_empty());
        assert!(
            lines.iter().all(|l| !l.contains("ArduPilot")),
            "our own HEARTBEAT was taken for a vehicle's: {lines:?}"
        );
    }

    #[test]
    fn daemon_json_sink_addresses_are_checked() {
        for bad in ["udp:nowhere", "tcp:1.2.3.4", "file:/tmp/x", ""] {
            let e = Sink::open(bad).err().expect(bad).to_string();
            assert!(e.contains("publish"), "{e}");
        }
    }

    #[test]
    fn daemon_cadences_fire_on_their_grid_points_and_skip_what_was_missed() {
        let epoch = tokio::time::Instant::now();
        let ms = |n: u64| epoch + Duration::from_millis(n);
        // 10 Hz asked by a 20 ms clock: every fifth tick, the first at the epoch.
        let mut c = Cadence::new(epoch, 10.0);
        let fired: Vec<u64> = (0..=25u64)
            .map(|k| 20 * k)
            .filter(|&t| c.due(ms(t)))
            .collect();
        assert_eq!(fired, [0, 100, 200, 300, 400, 500]);
        // 30 Hz (33.3 ms) off the 20 ms grid: at the first tick at or after each due time, and the
        // mean rate is kept (6 in 200 ms).
        let mut c = Cadence::new(epoch, 30.0);
        let fired: Vec<u64> = (0..10u64)
            .map(|k| 20 * k)
            .filter(|&t| c.due(ms(t)))
            .collect();
        assert_eq!(fired, [0, 40, 80, 100, 140, 180]);
        // A stall of a second: one output, then back on the grid (no burst making up for it).
        let mut c = Cadence::new(epoch, 10.0);
        assert!(c.due(ms(0)));
        assert!(c.due(ms(1030)));
        assert!(!c.due(ms(1060)) && !c.due(ms(1080)));
        assert!(c.due(ms(1100)));
    }
}
