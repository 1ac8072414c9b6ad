//! Set-up the integration tests share: loopback ports, service configurations, the service run
//! in this process or as a child, replays, and the Python peers that `scripts/test` installs.

// Each test file uses a part of this module.
#![allow(dead_code)]

use imucald::app::daemon::RunSummary;
use imucald::app::replay::{replay, ReplayOptions, ReplayOutcome};
use imucald::config::{Config, SourceConfig};
use imucald::types::Sample;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::Duration;

mod python;
mod untuned;
pub use python::{python_importing, python_path};
#[allow(unused_imports)]
pub use untuned::untuned_fusion;

/// A UDP port on the loopback that was free a moment ago.
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
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

/// A service config with one `udpin:` MAVLink source on a free loopback port (returned) and its
/// calibration directory under `dir`.
pub fn udpin_config(dir: &Path) -> (u16, Config) {
    let port = free_udp_port();
    let mut cfg = Config::default();
    cfg.daemon.sources = vec![mavlink_source(format!("udpin:127.0.0.1:{port}"))];
    cfg.daemon.calibration_dir = dir.join("cal").display().to_string();
    (port, cfg)
}

/// [`python_path`], checked to import `module` (pymavlink, pyulog).
pub fn python_with(module: &str) -> String {
    python_importing(module).unwrap_or_else(|| {
        panic!(
            "no Python with {module} at {}: run ./scripts/test (it installs a venv) or set IMUCALD_PYTHON",
            python_path()
        )
    })
}

/// `imucald run --config CONFIG`, its output discarded (the caller waits for it to bind).
pub fn spawn_service(config: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["run", "--config"])
        .arg(config)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
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

/// Sleeps, every 50th sample (`i`), until the time of a sample at `t_s` played `speed` times
/// faster than recorded from `t0`.
pub async fn pace(i: usize, t0: tokio::time::Instant, t_s: f64, speed: f64) {
    if i.is_multiple_of(50) {
        tokio::time::sleep_until(t0 + Duration::from_secs_f64(t_s / speed)).await;
    }
}

/// The live service running in this process.
pub struct Daemon {
    stop: tokio::sync::watch::Sender<bool>,
    task: tokio::task::JoinHandle<Result<RunSummary, imucald::error::Error>>,
}

impl Daemon {
    /// The service on `cfg`, given `settle` to open its links.
    pub async fn start(cfg: Config, settle: Duration) -> Daemon {
        let (stop, stop_rx) = tokio::sync::watch::channel(false);
        let task = tokio::spawn(imucald::app::daemon::run(cfg, stop_rx));
        tokio::time::sleep(settle).await;
        Daemon { stop, task }
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
/// 5 Hz), through a CSV beside it.
pub fn pymavlink_flight_tlog(samples: &[Sample], dir: &Path) -> PathBuf {
    let csv = dir.join("flight.csv");
    imucald::io::samplelog::write_csv(&csv, samples).unwrap();
    let tlog = dir.join("flight.tlog");
    let st = Command::new(python_with("pymavlink"))
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/interop/pymavlink_flight_tlog.py"
        ))
        .arg(&csv)
        .arg(&tlog)
        .status()
        .unwrap();
    assert!(st.success(), "pymavlink_flight_tlog.py");
    tlog
}
