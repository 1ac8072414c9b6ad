//! Set-up the integration tests share: loopback ports, service configurations, the service run
//! in this process or as a child (each waited for until it is ready, not for a guessed time),
//! replays, and the resources a test may lack (the shared recordings, Chromium, the Python peers
//! that `scripts/test` installs), each skipped alike: SKIPPED said plainly, or a failure under its
//! `IMUCALD_REQUIRE_*=1` ([`testdata::absent`]).

// Each test file uses a part of this module.
#![allow(dead_code)]

use imucald::app::daemon::{Ready, RunSummary};
use imucald::app::replay::{replay, ReplayOptions, ReplayOutcome};
use imucald::config::{Config, SourceConfig};
use imucald::types::Sample;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::time::Duration;

mod python;
/// The library's test set-up: the recordings, the skip policy, pings, a passing calibration.
#[path = "../../src/testdata.rs"]
pub mod testdata;
mod untuned;
mod wait;
pub use python::python_path;
#[allow(unused_imports)]
pub use untuned::untuned_fusion;
pub use wait::*;

/// A UDP port on the loopback that was free a moment ago.
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A TCP port on the loopback that was free a moment ago.
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A service configuration file `dir/live.toml`: one source `sim:SCENARIO` (`tumble?speed=2`),
/// the calibration directory under `dir`, and `extra` TOML after it (`[ui]` ...).
pub fn sim_service_toml(dir: &Path, scenario: &str, extra: &str) -> PathBuf {
    let cfg = dir.join("live.toml");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\nsources = [{{ address = \"sim:{scenario}\" }}]\ncalibration_dir = \"{}\"\n\n{extra}",
            dir.join("cal").display()
        ),
    )
    .unwrap();
    cfg
}

/// A MAVLink source at `address` (`udpin:IP:PORT`, `file:LOG`, `sim:SCENARIO` ...).
pub fn mavlink_source(address: impl Into<String>) -> SourceConfig {
    SourceConfig {
        address: address.into(),
        payload: imucald::config::PayloadKind::Mavlink,
        fields: vec![],
        scales: Default::default(),
    }
}

/// A symmetric soft iron a compass near ferrous parts might have (the `M` of calibrated =
/// M (raw - offset)), hidden in simulated flights.
pub const SOFT_IRON: [[f64; 3]; 3] = [
    [1.04, 0.03, -0.02],
    [0.03, 0.95, 0.025],
    [-0.02, 0.025, 1.02],
];

/// The largest difference between two matrices, element by element.
pub fn matrix_dist(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> f64 {
    (0..3)
        .flat_map(|i| (0..3).map(move |j| (a[i][j] - b[i][j]).abs()))
        .fold(0.0, f64::max)
}

/// The distance between two vectors.
pub fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

/// A simulated flight streamed to a live service over UDP as a flight controller sends it
/// (HIGHRES_IMU with the vehicle's state: `io::samplelog::VehicleStateStream`), paced like a fast
/// link (2 ms per 200 samples: the service's queue is bounded); the service (`cfg`, from
/// [`udpin_config`] with its `port`) publishes its JSON lines to a socket of ours and is stopped
/// once it took everything sent. Returns those lines.
pub async fn stream_flight(samples: &[Sample], port: u16, mut cfg: Config) -> Vec<String> {
    use imucald::io::mavout::MavEncoder;
    let sink = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    cfg.daemon.publish = vec![format!("udp:{}", sink.local_addr().unwrap())];
    let daemon = Daemon::ready(cfg).await;
    let peer = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut enc = MavEncoder::new(1, 1);
    let mut state = imucald::io::samplelog::VehicleStateStream::default();
    let mut lines = Vec::new();
    let mut buf = vec![0u8; 65536];
    let mut read = |lines: &mut Vec<String>| {
        while let Ok(n) = sink.try_recv(&mut buf) {
            lines.extend(
                String::from_utf8_lossy(&buf[..n])
                    .lines()
                    .map(str::to_string),
            );
        }
    };
    for (k, s) in samples.iter().enumerate() {
        let boot_us = 10_000_000 + (s.t_s * 1e6).round() as u64;
        let mut msgs = state.messages(s, boot_us);
        msgs.push(imucald::io::samplelog::highres_imu(s, boot_us));
        for m in msgs {
            peer.send_to(&enc.encode(&m), ("127.0.0.1", port))
                .await
                .unwrap();
        }
        if k % 200 == 199 {
            tokio::time::sleep(Duration::from_millis(2)).await;
            read(&mut lines);
        }
    }
    let to = testdata::SERVICE_IDS;
    testdata::taken(&peer, port, to, Duration::from_secs(20), |_| {}).await;
    daemon.stop(Duration::from_secs(5)).await;
    read(&mut lines);
    lines
}

/// A service config with one `udpin:` MAVLink source on a free loopback port (returned) and its
/// calibration directory under `dir`.
pub fn udpin_config(dir: &Path) -> (u16, Config) {
    let port = free_udp_port();
    let mut cfg = Config::default();
    cfg.daemon.sources = vec![mavlink_source(format!("udpin:127.0.0.1:{port}"))];
    cfg.daemon.calibration_dir = dir.join("cal").display().to_string();
    (port, cfg)
}

/// Environment variable that turns "no Python with the test peers" into a test failure when set
/// to `1` (`scripts/test` sets it).
pub const REQUIRE_PYTHON_ENV: &str = "IMUCALD_REQUIRE_PYTHON";

/// [`python_path`] when it imports `modules` (`"pymavlink"`, `"vqf, numpy"`, `"MAVProxy"`), or
/// `None` with SKIPPED said (a failure under `IMUCALD_REQUIRE_PYTHON=1`).
pub fn python(modules: &str) -> Option<String> {
    python::python_importing(modules).or_else(|| {
        testdata::absent(
            &format!("a Python importing {modules} ({})", python_path()),
            REQUIRE_PYTHON_ENV,
            "run ./scripts/test (it installs them into .venv) or set IMUCALD_PYTHON",
        )
    })
}

/// [`python`], failing the test without it whatever the switch says: for a caller that cannot
/// skip.
pub fn python_with(module: &str) -> String {
    python::python_importing(module).unwrap_or_else(|| {
        panic!(
            "no Python with {module} at {}: run ./scripts/test (it installs a venv) or set IMUCALD_PYTHON",
            python_path()
        )
    })
}

/// Chromium's path, or `None` with SKIPPED said (a failure under `IMUCALD_REQUIRE_BROWSER=1`).
pub fn chromium() -> Option<&'static str> {
    const CHROMIUM: &str = "/usr/bin/chromium";
    if Path::new(CHROMIUM).exists() {
        return Some(CHROMIUM);
    }
    testdata::absent(
        CHROMIUM,
        "IMUCALD_REQUIRE_BROWSER",
        "apt-get install chromium; scripts/test does",
    )
}

/// `imucald run` as a child process: its stdout and stderr read as lines, started and waited for
/// until it said it is ready (its links open). Killed when dropped.
pub struct Service {
    /// `None` once handed out ([`Service::into_child`]).
    child: Option<Child>,
    pub stdout: Lines,
    pub stderr: Lines,
    /// Its `ready` log line.
    pub ready: String,
}

impl Service {
    /// `imucald run` with `args`, once its `ready` line came (within [`READY_WITHIN`]).
    pub fn start<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> Service {
        let mut child = Command::new(env!("CARGO_BIN_EXE_imucald"))
            .arg("run")
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stdout = Lines::read(child.stdout.take().unwrap());
        let mut stderr = Lines::read(child.stderr.take().unwrap());
        let ready = wait_for_line(&mut stderr, "ready line", is_ready_log, READY_WITHIN);
        Service {
            child: Some(child),
            stdout,
            stderr,
            ready,
        }
    }

    pub fn child(&mut self) -> &mut Child {
        self.child.as_mut().expect("the child was handed out")
    }

    /// The JSON `ready` line on stdout (with `--publish stdout`).
    pub fn ready_json(&mut self) -> serde_json::Value {
        let l = wait_for_line(
            &mut self.stdout,
            "JSON ready line",
            is_ready_json,
            READY_WITHIN,
        );
        serde_json::from_str(&l).unwrap()
    }

    /// SIGTERM; its exit status (`None`: still running `within` after, then killed) and all it
    /// logged.
    pub fn stop(&mut self, within: Duration) -> (Option<ExitStatus>, String) {
        let child = self.child();
        sigterm(child);
        let status = wait_exit(child, within);
        if status.is_none() {
            let _ = child.kill();
            let _ = child.wait();
        }
        (status, self.stderr.until_end())
    }

    /// The child alone, its output still drained (and dropped) so that it never blocks on a pipe.
    pub fn into_child(mut self) -> Child {
        self.stdout.drain_in_background();
        self.stderr.drain_in_background();
        self.child.take().expect("the child was handed out")
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        if let Some(c) = self.child.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// `imucald run --config CONFIG`, once it is ready; its output drained and dropped.
pub fn spawn_service(config: &Path) -> Child {
    Service::start(&["--config".as_ref(), config.as_os_str()]).into_child()
}

/// The service with `mag_cal = "on_command"` (nothing installs a calibration unless commanded),
/// no publication, its calibration directory (returned) under `dir` and `sources` (the TOML of each
/// source table, as `{ address = "..." }`), started as a child process.
pub fn spawn_on_command_service(dir: &Path, sources: &[String]) -> (PathBuf, Child) {
    let cal = dir.join("cal");
    let cfg = dir.join("svc.toml");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\ncalibration_dir = \"{}\"\npublish = []\nmag_cal = \"on_command\"\n\
             sources = [{}]\n",
            cal.display(),
            sources.join(", ")
        ),
    )
    .unwrap();
    (cal, spawn_service(&cfg))
}

/// Fails the test with the command's stderr unless it exited successfully.
#[track_caller]
pub fn assert_success(out: &Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `replay` of the log at `path` with `cfg` and the default options; a failure names the log.
pub fn replay_log(path: &Path, cfg: &Config) -> ReplayOutcome {
    replay(path, cfg, &ReplayOptions::default(), &mut |_, _| {})
        .unwrap_or_else(|e| panic!("replay {}: {e}", path.display()))
}

/// `samples` written as a CSV log in a temporary directory and replayed with `cfg`.
pub fn replay_samples(samples: &[Sample], cfg: &Config) -> ReplayOutcome {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("log.csv");
    imucald::io::samplelog::write_csv(&log, samples).unwrap();
    replay_log(&log, cfg)
}

/// HIGHRES_IMU for a simulated sample, stamped with its time since a boot
/// [`imucald::io::samplelog::TLOG_BOOT_OFFSET_US`] before the simulation's start (as the `.tlog` writer does).
pub fn highres_imu_at(s: &Sample) -> mavlink::dialects::ardupilotmega::MavMessage {
    imucald::io::samplelog::highres_imu(
        s,
        imucald::io::samplelog::TLOG_BOOT_OFFSET_US + (s.t_s * 1e6).round() as u64,
    )
}

/// Paces a stream in real time: sleeps, every 50th sample (`i`), until the time of a sample at
/// `t_s` played `speed` times faster than recorded from `t0`.
pub async fn pace(i: usize, t0: tokio::time::Instant, t_s: f64, speed: f64) {
    if i.is_multiple_of(50) {
        tokio::time::sleep_until(t0 + Duration::from_secs_f64(t_s / speed)).await;
    }
}

/// The live service running in this process.
pub struct Daemon {
    stop: tokio::sync::watch::Sender<bool>,
    task: tokio::task::JoinHandle<Result<RunSummary, imucald::error::Error>>,
    /// What its `ready` line said: each link's bound address.
    pub ready: Ready,
}

impl Daemon {
    /// The service on `cfg`, once every link has opened (or failed to: see [`Ready`]). Needs no
    /// deadline: the service is ready or stopped within its first connection attempt.
    pub async fn ready(cfg: Config) -> Daemon {
        let (stop, stop_rx) = tokio::sync::watch::channel(false);
        let (tx, rx) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(imucald::app::daemon::run_reporting_ready(
            cfg,
            stop_rx,
            Some(tx),
        ));
        match rx.await {
            Ok(ready) => Daemon { stop, task, ready },
            Err(_) => panic!("the service stopped before it was ready: {:?}", task.await),
        }
    }

    /// [`Daemon::ready`], then `play` more of the tokio clock: under a paused clock, the time a
    /// replay is given to play, at no cost.
    pub async fn start(cfg: Config, play: Duration) -> Daemon {
        let d = Daemon::ready(cfg).await;
        tokio::time::sleep(play).await;
        d
    }

    /// The address link `i` is bound to (a udpin source asked for port 0 learns its port).
    pub fn local(&self, i: usize) -> std::net::SocketAddr {
        match &self.ready.links[i].opening {
            imucald::io::link::LinkOpening::Open { local: Some(a), .. } => *a,
            other => panic!("link {i} has no bound address: {other:?}"),
        }
    }

    /// Asks it to stop; its summary, once it stopped (however long it takes: for tokio's paused
    /// clock, where a timeout would fire while the service idles).
    pub async fn stopped(self) -> RunSummary {
        self.stop.send(true).unwrap();
        self.task.await.unwrap().unwrap()
    }

    /// Asks it to stop; its summary, once it stopped (within `within`).
    pub async fn stop(self, within: Duration) -> RunSummary {
        self.stop.send(true).unwrap();
        tokio::time::timeout(within, self.task)
            .await
            .expect("stops")
            .unwrap()
            .unwrap()
    }
}

/// A JSON-lines consumer over UDP on the loopback, for a service in this process. A task of its
/// own reads the socket as lines come (a socket left unread for seconds fills and drops them), and
/// keeps them for the test: a test's service sends a few MB at most.
pub struct JsonSink {
    addr: std::net::SocketAddr,
    rx: tokio::sync::mpsc::UnboundedReceiver<serde_json::Value>,
    reader: tokio::task::JoinHandle<()>,
    /// Every line taken so far, in order.
    pub lines: Vec<serde_json::Value>,
}

impl JsonSink {
    pub async fn bind() -> JsonSink {
        let sock = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = sock.local_addr().unwrap();
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        let reader = tokio::spawn(async move {
            let mut buf = vec![0u8; 65_536];
            while let Ok(n) = sock.recv(&mut buf).await {
                for l in String::from_utf8_lossy(&buf[..n]).lines() {
                    if tx.send(serde_json::from_str(l).unwrap()).is_err() {
                        return;
                    }
                }
            }
        });
        JsonSink {
            addr,
            rx,
            reader,
            lines: vec![],
        }
    }

    /// Its `daemon.publish` entry.
    pub fn publish(&self) -> String {
        format!("udp:{}", self.addr)
    }

    /// Every line received, once those still on their way arrived: for after the service stopped
    /// (its writers passed on what was queued), read until 20 ms pass without one.
    pub async fn drain(&mut self) -> &[serde_json::Value] {
        while let Ok(Some(v)) =
            tokio::time::timeout(Duration::from_millis(20), self.rx.recv()).await
        {
            self.lines.push(v);
        }
        &self.lines
    }

    /// The next line `want` accepts, once it came (it and those before it are kept in
    /// `lines`); fails the test, naming what was `awaited`, when it does not come `within`.
    pub async fn wait_for(
        &mut self,
        awaited: &str,
        mut want: impl FnMut(&serde_json::Value) -> bool,
        within: Duration,
    ) -> serde_json::Value {
        let until = tokio::time::Instant::now() + within;
        loop {
            let Ok(Some(v)) = tokio::time::timeout_at(until, self.rx.recv()).await else {
                let said: Vec<String> = (self.lines.iter())
                    .filter(|v| v["type"] == "status")
                    .map(|v| v["text"].to_string())
                    .collect();
                panic!(
                    "no {awaited} within {within:?} among {} lines; the status lines: {said:?}",
                    self.lines.len()
                );
            };
            self.lines.push(v.clone());
            if want(&v) {
                return v;
            }
        }
    }
}

impl Drop for JsonSink {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

/// The tumble (seed 4), and the tumble with other hard and soft iron simulated with `seed_b`: two
/// compasses or two vehicles, each with its own truth.
pub fn tumble_and_other_iron(seed_b: u64) -> (imucald::sim::SimOutput, imucald::sim::SimOutput) {
    use imucald::sim::{simulate, Scenario};
    let sc = Scenario::named("tumble").unwrap();
    let a = simulate(&sc, 4);
    (a, simulate(&with_other_iron(&sc), seed_b))
}

/// `sc` with a second compass's hard and soft iron in place of its own.
pub fn with_other_iron(sc: &imucald::sim::Scenario) -> imucald::sim::Scenario {
    let mut sc2 = sc.clone();
    sc2.truth.mag.offset = [-31.0, 12.5, 44.0];
    sc2.truth.mag.matrix = [
        [0.97, 0.03, -0.02],
        [0.03, 1.04, 0.015],
        [-0.02, 0.015, 0.99],
    ];
    sc2
}

/// Appends one `.tlog` record to `bytes`: the big-endian time stamp `stamp_us`, then `msg` as a
/// MAVLink 2 frame from system 1, component 1 (sequence 0).
pub fn push_tlog_record(
    bytes: &mut Vec<u8>,
    stamp_us: u64,
    msg: &mavlink::dialects::ardupilotmega::MavMessage,
) {
    let header = mavlink::MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: 0,
    };
    bytes.extend_from_slice(&stamp_us.to_be_bytes());
    mavlink::write_versioned_msg(bytes, mavlink::MavlinkVersion::V2, header, msg).unwrap();
}

/// Largest offset error and largest normalised-matrix element error of a calibration against the
/// simulated truth.
pub fn errors_against_truth(
    fit: &imucald::report::SensorCalibration,
    truth: &imucald::sim::SensorTruth,
) -> (f64, f64) {
    let normalised = |m: &[[f64; 3]; 3]| {
        imucald::calib::model::Calibration {
            model: imucald::calib::model::ModelKind::Full12,
            offset: [0.0; 3],
            matrix: *m,
        }
        .normalised_matrix()
    };
    let off = (0..3)
        .map(|k| (fit.offset[k] - truth.offset[k]).abs())
        .fold(0.0, f64::max);
    let mat = (normalised(&fit.matrix) - normalised(&truth.matrix))
        .abs()
        .max();
    (off, mat)
}

/// `imucald run` as a child on the `file:` source `log` at `speed` times its pace (0: as fast as
/// possible), publishing to `publish` (a TOML list), with `extra` (TOML tables) before the
/// `[daemon]` table; configuration, calibration directory (`cal`) and report
/// (`live-report.json`) beside `log`. Its output, asserted successful, and its report.
pub fn run_on_file(
    log: &Path,
    speed: u32,
    publish: &str,
    extra: &str,
) -> (Output, imucald::report::Report) {
    let dir = log.parent().unwrap();
    let cfg = dir.join("live.toml");
    std::fs::write(
        &cfg,
        format!(
            "{extra}[daemon]\ncalibration_dir = \"{}\"\npublish = {publish}\nsources = [{{ address = \"file:{}?speed={speed}\" }}]\n",
            dir.join("cal").display(),
            log.display()
        ),
    )
    .unwrap();
    let report = dir.join("live-report.json");
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["run", "--config"])
        .arg(&cfg)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert_success(&out);
    let r = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    (out, r)
}

/// `samples` as a `.tlog` in `dir` written by pymavlink (`tests/interop/pymavlink_flight_tlog.py`:
/// HIGHRES_IMU, ATTITUDE when the reference attitude changes, GPS_RAW_INT and SYS_STATUS at
/// 5 Hz), through a CSV beside it; `None` (SKIPPED said) without pymavlink ([`python`]).
pub fn pymavlink_flight_tlog(samples: &[Sample], dir: &Path) -> Option<PathBuf> {
    let py = python("pymavlink")?;
    let csv = dir.join("flight.csv");
    imucald::io::samplelog::write_csv(&csv, samples).unwrap();
    let tlog = dir.join("flight.tlog");
    let st = Command::new(py)
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/interop/pymavlink_flight_tlog.py"
        ))
        .arg(&csv)
        .arg(&tlog)
        .status()
        .unwrap();
    assert!(st.success(), "pymavlink_flight_tlog.py");
    Some(tlog)
}

/// `NAME VALUE` lines of an ArduPilot `.parm` file by name, comments left out.
pub fn parm_values(text: &str) -> std::collections::BTreeMap<String, f64> {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let mut it = l.split_whitespace();
            Some((it.next()?.to_string(), it.next()?.parse().ok()?))
        })
        .collect()
}
