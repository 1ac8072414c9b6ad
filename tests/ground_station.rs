//! MAVProxy (PyPI) as the ground station, as a user drives a compass calibration with it: the
//! service runs with `daemon.mag_cal = "on_command"` on a simulated tumble and listens on UDP;
//! `mavproxy.py --master=udpout:... --target-system=1` connects and sends `magcal start`; its
//! calibration module
//! prints the MAG_CAL_REPORT and answers it with DO_ACCEPT_MAG_CAL (ACCEPTED: the result is
//! already saved), and the service writes the calibration. `./scripts/test` installs MAVProxy into
//! `.venv`; without it these tests say SKIPPED ([`common::python`]).

mod common;

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// `mavproxy.py` beside the Python that imports MAVProxy, or `None` (SKIPPED said).
fn mavproxy() -> Option<PathBuf> {
    let py = common::python("MAVProxy")?;
    Some(PathBuf::from(py).with_file_name("mavproxy.py"))
}

/// MAVProxy (`mavproxy`) on `port` (UDP out) in `dir`, with `args`, its commands from a pipe and
/// its output lines through a channel.
fn mavproxy_session(
    mavproxy: &std::path::Path,
    dir: &std::path::Path,
    port: u16,
    args: &[&str],
) -> (
    std::process::Child,
    std::process::ChildStdin,
    std::sync::mpsc::Receiver<String>,
) {
    let mut gcs = Command::new(mavproxy)
        .arg(format!("--master=udpout:127.0.0.1:{port}"))
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdin = gcs.stdin.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let out = gcs.stdout.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    (gcs, stdin, rx)
}

/// The next of MAVProxy's lines (from `rx`, each kept in `seen`) that `want` accepts; `None` when
/// it does not come `within`.
fn next_line(
    rx: &std::sync::mpsc::Receiver<String>,
    seen: &mut Vec<String>,
    want: impl Fn(&str) -> bool,
    within: Duration,
) -> Option<String> {
    let deadline = Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let l = rx.recv_timeout(left).ok()?;
        seen.push(l.clone());
        if want(&l) {
            return Some(l);
        }
    }
}

/// A ground station and the service it drives: MAVProxy, its output lines (`rx`, each kept in
/// `seen`), the service's calibration folder and process.
struct Linked {
    gcs: std::process::Child,
    stdin: std::process::ChildStdin,
    rx: std::sync::mpsc::Receiver<String>,
    seen: Vec<String>,
    cal: PathBuf,
    svc: std::process::Child,
}

/// MAVProxy first (with `gcs_args`), then, once it waits for a heartbeat, a service on command
/// with `links`; returns when MAVProxy has heard the service (within `within` each), so a run
/// sees the service's whole stream however long MAVProxy takes to start.
fn mavproxy_then_service(
    mavproxy: &std::path::Path,
    dir: &std::path::Path,
    port: u16,
    gcs_args: &[&str],
    links: &[String],
    within: Duration,
) -> Linked {
    let (gcs, stdin, rx) = mavproxy_session(mavproxy, dir, port, gcs_args);
    let mut seen = Vec::new();
    let up = next_line(
        &rx,
        &mut seen,
        |l| l.contains("Waiting for heartbeat"),
        within,
    );
    assert!(up.is_some(), "MAVProxy did not start:\n{}", seen.join("\n"));
    let (cal, svc) = common::spawn_on_command_service(dir, links);
    let heard = next_line(
        &rx,
        &mut seen,
        |l| l.contains("Detected vehicle 1:191"),
        within,
    );
    assert!(
        heard.is_some(),
        "MAVProxy never heard the service:\n{}",
        seen.join("\n")
    );
    Linked {
        gcs,
        stdin,
        rx,
        seen,
        cal,
        svc,
    }
}

/// Send one command line to MAVProxy.
fn send(stdin: &mut std::process::ChildStdin, cmd: &str) {
    use std::io::Write;
    writeln!(stdin, "{cmd}").unwrap();
}

#[test]
fn mavproxy_magcal_start_calibrates_and_accepts() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    // MAVProxy first (the service's system id given: MAVProxy takes a target from autopilot
    // heartbeats only, and the service's says onboard controller), then the service, whose
    // simulated tumble starts with it, and the command once MAVProxy has heard the service: the
    // run sees the whole tumble however long MAVProxy takes to start.
    let within = Duration::from_secs(60);
    let links = [
        "{ address = \"sim:tumble?speed=10\" }".into(),
        format!("{{ address = \"udpin:127.0.0.1:{port}\" }}"),
    ];
    let Linked {
        mut gcs,
        mut stdin,
        rx,
        mut seen,
        cal,
        mut svc,
    } = mavproxy_then_service(
        &mavproxy,
        dir.path(),
        port,
        &["--target-system=1"],
        &links,
        within,
    );
    send(&mut stdin, "magcal start");
    let report = next_line(
        &rx,
        &mut seen,
        |l| l.starts_with("Calibration of compass"),
        Duration::from_secs(90),
    );
    // The accept goes out right after the report (MAVProxy accepts every report); its answer,
    // and the calibration the service writes.
    next_line(
        &rx,
        &mut seen,
        |l| l.contains("DO_ACCEPT_MAG_CAL: "),
        Duration::from_secs(5),
    );
    let written = |text: &str| {
        serde_json::from_str::<serde_json::Value>(text).is_ok_and(|v| v["mag"]["status"] == "ok")
    };
    let stored = common::wait_for_file(
        &cal.join("calibration.json"),
        written,
        Duration::from_secs(20),
    )
    .unwrap_or_default();
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    let acked = seen
        .iter()
        .any(|l| l.contains("DO_START_MAG_CAL: ACCEPTED"));
    assert!(
        acked,
        "no COMMAND_ACK for magcal start; MAVProxy said:\n{}",
        seen.join("\n")
    );
    let report =
        report.unwrap_or_else(|| panic!("no MAG_CAL_REPORT; MAVProxy said:\n{}", seen.join("\n")));
    assert!(report.contains("compass 0 SUCCESS"), "{report}");
    // The run saved its result (autosave): the automatic accept is ACCEPTED, as ArduPilot answers.
    assert!(
        seen.iter()
            .any(|l| l.contains("DO_ACCEPT_MAG_CAL: ACCEPTED")),
        "MAVProxy said:\n{}",
        seen.join("\n")
    );
    let v: serde_json::Value = serde_json::from_str(&stored).expect("calibration.json written");
    assert_eq!(v["mag"]["status"], "ok", "{stored}");
    // The simulated tumble's hard iron (Scenario `tumble`: [12, -25, 40] uT).
    let off: Vec<f64> = v["mag"]["offset"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    let err = [12.0, -25.0, 40.0]
        .iter()
        .zip(&off)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    eprintln!("{report}; stored offset {off:?} uT, {err:.4} uT from the truth");
    // Measured 0.0024 and 0.0055 uT.
    assert!(err < 0.02, "offset {off:?}");
}

/// MAVProxy lists the service's parameters (its settings and the calibration in use) as it lists a
/// flight controller's, and `param set` changes a live setting only where the config allows it:
/// a calibration value stays read only.
#[test]
fn mavproxy_lists_the_service_parameters_and_sets_only_writable_ones() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    let cfg = dir.path().join("svc.toml");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\ncalibration_dir = \"{}\"\npublish = []\nparams_writable = true\n\
             sources = [{{ address = \"sim:tumble?speed=10\" }}, {{ address = \"udpin:127.0.0.1:{port}\" }}]\n",
            dir.path().join("cal").display()
        ),
    )
    .unwrap();
    let mut svc = common::spawn_service(&cfg);
    // Our component: MAVProxy keeps the parameters of each component apart.
    let (mut gcs, mut stdin, rx) = mavproxy_session(
        &mavproxy,
        dir.path(),
        port,
        &[
            "--target-system=1",
            "--target-component=191",
            "--cmd=set param_ftp 0",
        ],
    );
    let mut seen = Vec::new();
    let parm = dir.path().join("mav_1_191.parm");
    // Once a calibration is in use, fetch the list again (MAVProxy fetched it at connection,
    // before there was one); with the compass's values listed, change a setting and then try a
    // calibration value.
    let mut step = 0;
    let deadline = Instant::now() + Duration::from_secs(90);
    while Instant::now() < deadline && step < 5 {
        let Ok(l) = rx.recv_timeout(Duration::from_millis(200)) else {
            continue;
        };
        let listed = std::fs::read_to_string(&parm).unwrap_or_default();
        if step == 0 && l.contains("mag calibrated") {
            send(&mut stdin, "param fetch");
            step = 1;
        } else if step == 1
            && l.starts_with("Saved ")
            && listed.lines().any(|l| {
                let mut w = l.split_whitespace();
                w.next() == Some("MAG0_OK") && w.next().and_then(|v| v.parse().ok()) == Some(1.0)
            })
        {
            send(&mut stdin, "param set CAL_MAG_MODE 1");
            step = 2;
        } else if step == 2 && l.contains("CAL_MAG_MODE set to 1 (on_command)") {
            send(&mut stdin, "param set MAG0_OFS_X 3");
            step = 3;
        } else if step == 3 && l.contains("Failed to set MAG0_OFS_X") {
            // And the list once more: the same count and order as before.
            send(&mut stdin, "param fetch");
            step = 4;
        } else if step == 4 && l.starts_with("Saved ") {
            step = 5;
        }
        seen.push(l);
    }
    let listed = std::fs::read_to_string(&parm).unwrap_or_default();
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    assert_eq!(step, 5, "MAVProxy said:\n{}", seen.join("\n"));
    assert!(
        seen.iter().any(|l| l.contains("MAG0_OFS_X is read only")),
        "MAVProxy said:\n{}",
        seen.join("\n")
    );
    let value = |name: &str| -> f64 {
        let line = listed
            .lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .unwrap_or_else(|| panic!("no {name} in the list:\n{listed}"));
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    };
    assert_eq!(value("CAL_WRITE_PARAMS"), 0.0);
    assert_eq!(value("MAG0_OK"), 1.0);
    // The list has one shape: every fetch (at connection, when nothing may be calibrated yet,
    // after the calibration, after the settings changed) saves the same count, every name listed
    // (no second compass here: its values NaN).
    let saved: Vec<&str> = seen
        .iter()
        .filter(|l| l.starts_with("Saved ") && l.contains("parameters"))
        .filter_map(|l| l.split_whitespace().nth(1))
        .collect();
    assert!(saved.len() >= 2, "MAVProxy said:\n{}", seen.join("\n"));
    assert!(saved.iter().all(|n| *n == saved[0]), "counts {saved:?}");
    assert!(value("MAG1_OFS_X").is_nan());
    assert_eq!(value("MAG1_OK"), 0.0);
    // The simulated tumble's hard iron (Scenario `tumble`: [12, -25, 40] uT); measured within
    // 0.03 uT of it while the fit still refines.
    for (axis, truth) in ["X", "Y", "Z"].iter().zip([12.0, -25.0, 40.0]) {
        let v = value(&format!("MAG0_OFS_{axis}"));
        assert!((v - truth).abs() < 0.5, "MAG0_OFS_{axis} {v}\n{listed}");
    }
}

/// `magcal yaw` from MAVProxy after the data has stopped: refused (FAILED) with the reason, as the
/// vehicle's yaw now is not known; nothing is written.
#[test]
fn mavproxy_magcal_yaw_on_stale_data_is_refused_with_the_reason() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    let cfg = dir.path().join("svc.toml");
    let cal = dir.path().join("cal");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\ncalibration_dir = \"{}\"\npublish = []\nmag_cal = \"on_command\"\n\
             sources = [{{ address = \"sim:tumble?speed=50\" }}, {{ address = \"udpin:127.0.0.1:{port}\" }}]\n\
             [place]\nlatitude_deg = 47.4\nlongitude_deg = 8.5\n",
            cal.display()
        ),
    )
    .unwrap();
    let mut svc = common::spawn_service(&cfg);
    let (mut gcs, mut stdin, rx) =
        mavproxy_session(&mavproxy, dir.path(), port, &["--target-system=1"]);
    let mut seen = Vec::new();
    let mut ended = None;
    let mut answered = false;
    let deadline = Instant::now() + Duration::from_secs(60);
    while Instant::now() < deadline && !answered {
        if let Ok(l) = rx.recv_timeout(Duration::from_millis(200)) {
            if l.contains("sim:tumble?speed=50: ended") {
                ended = Some(Instant::now());
            }
            answered = l.contains("FIXED_MAG_CAL_YAW: ");
            seen.push(l);
        }
        // The data is stale once it is older than the service's 2 s: command 3 s after the end.
        if ended.is_some_and(|e| e.elapsed() > Duration::from_secs(3)) {
            send(&mut stdin, "magcal yaw 90");
            ended = None;
        }
    }
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    let said = seen.join("\n");
    assert!(
        said.contains("FIXED_MAG_CAL_YAW: FAILED"),
        "MAVProxy said:\n{said}"
    );
    assert!(
        said.contains("fixed-yaw calibration refused: the latest samples are"),
        "MAVProxy said:\n{said}"
    );
    // Nothing installed: no store, or one without a magnetometer calibration.
    if let Ok(stored) = std::fs::read_to_string(cal.join("calibration.json")) {
        let v: serde_json::Value = serde_json::from_str(&stored).unwrap();
        assert!(v["mag"].is_null(), "{stored}");
    }
}

/// The number after `name : ` in a pymavlink message as MAVProxy prints it
/// (`MAG_CAL_PROGRESS {compass_id : 0, cal_mask : 1, cal_status : 1, attempt : 1, ...}`).
fn printed_field(line: &str, name: &str) -> Option<u32> {
    let at = line.find(&format!("{name} : "))? + name.len() + 3;
    let digits: String = line[at..]
        .chars()
        .take_while(|c| c.is_ascii_digit())
        .collect();
    digits.parse().ok()
}

/// A run started from MAVProxy with a 3 s delay and retry on (`long DO_START_MAG_CAL 0 1 1 3`), on
/// a magnetometer too noisy to pass ArduPilot's default fitness: MAVProxy's `status
/// MAG_CAL_PROGRESS` shows WAITING_TO_START first, then the run collecting (attempt 1), then,
/// after the fit fails, attempt 2 collecting again, with the reason said and no report.
#[test]
fn mavproxy_delayed_start_waits_then_retries_after_a_failure() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    let scenario = dir.path().join("noisy.toml");
    std::fs::write(&scenario, "name = \"tumble\"\n[mag]\nnoise_sd = 4.0\n").unwrap();
    let within = Duration::from_secs(60);
    let links = [
        format!("{{ address = \"sim:{}?speed=10\" }}", scenario.display()),
        format!("{{ address = \"udpin:127.0.0.1:{port}\" }}"),
    ];
    let Linked {
        mut gcs,
        mut stdin,
        rx,
        mut seen,
        cal: _,
        mut svc,
    } = mavproxy_then_service(
        &mavproxy,
        dir.path(),
        port,
        &["--target-system=1", "--target-component=191"],
        &links,
        within,
    );
    // Every compass, retry, autosave, a 3 s delay.
    send(&mut stdin, "long DO_START_MAG_CAL 0 1 1 3");
    let mut progress: Vec<(u32, u32)> = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut asked = Instant::now();
    while Instant::now() < deadline && !progress.iter().any(|p| p.1 >= 2) {
        if asked.elapsed() > Duration::from_millis(400) {
            send(&mut stdin, "status MAG_CAL_PROGRESS");
            asked = Instant::now();
        }
        let Ok(l) = rx.recv_timeout(Duration::from_millis(100)) else {
            continue;
        };
        if l.contains("MAG_CAL_PROGRESS {") {
            if let (Some(s), Some(a)) = (
                printed_field(&l, "cal_status"),
                printed_field(&l, "attempt"),
            ) {
                if progress.last() != Some(&(s, a)) {
                    progress.push((s, a));
                }
            }
        }
        seen.push(l);
    }
    send(&mut stdin, "magcal cancel");
    std::thread::sleep(Duration::from_millis(500));
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    while let Ok(l) = rx.try_recv() {
        seen.push(l);
    }
    let said = seen.join("\n");
    eprintln!("(cal_status, attempt) in order: {progress:?}");
    assert!(said.contains("DO_START_MAG_CAL: ACCEPTED"), "{said}");
    // WAITING_TO_START (1) first, then collecting (2 or 3) as attempt 1, then attempt 2.
    assert_eq!(progress.first(), Some(&(1, 1)), "{progress:?}\n{said}");
    let collecting = progress.iter().position(|&(s, a)| s >= 2 && a == 1);
    let retried = progress.iter().position(|&(s, a)| s >= 2 && a == 2);
    assert!(
        collecting.is_some() && retried.is_some() && collecting < retried,
        "{progress:?}\n{said}"
    );
    assert!(said.contains("retrying, attempt 2"), "{said}");
    // A retry sends no MAG_CAL_REPORT (ArduPilot's calibrator goes straight back to collecting).
    assert!(!said.contains("Calibration of compass"), "{said}");
}

/// `magcal yaw 90` (latitude and longitude 0) from MAVProxy to a vehicle at rest at yaw 90 that
/// streams GLOBAL_POSITION_INT (a `.tlog` written by `imucald simulate`, played at its pace): the
/// service takes the vehicle's position, as ArduPilot takes its own, and calibrates (said in a
/// STATUSTEXT, written); no `[place]` is configured.
#[test]
fn mavproxy_magcal_yaw_uses_the_vehicle_position() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    let scenario = dir.path().join("rest.toml");
    std::fs::write(
        &scenario,
        "name = \"tumble\"\nattitudes = [[1.0, -2.0, 90.0]]\npause_s = [300.0, 300.0]\n\
         [place]\nlatitude_deg = 47.4\nlongitude_deg = 8.5\n",
    )
    .unwrap();
    let log = dir.path().join("rest.tlog");
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["simulate", "--seed", "3", "--scenario"])
        .arg(&scenario)
        .arg("--out")
        .arg(&log)
        .output()
        .unwrap();
    common::assert_success(&out);
    let within = Duration::from_secs(60);
    let links = [
        format!("{{ address = \"file:{}?speed=1\" }}", log.display()),
        format!("{{ address = \"udpin:127.0.0.1:{port}\" }}"),
    ];
    let Linked {
        mut gcs,
        mut stdin,
        rx,
        mut seen,
        cal,
        mut svc,
    } = mavproxy_then_service(
        &mavproxy,
        dir.path(),
        port,
        &["--target-system=1"],
        &links,
        within,
    );
    // A few seconds of rest (the fixed-yaw window is 1 s), then the command.
    std::thread::sleep(Duration::from_secs(4));
    send(&mut stdin, "magcal yaw 90");
    let answer = next_line(
        &rx,
        &mut seen,
        |l| l.contains("FIXED_MAG_CAL_YAW: "),
        Duration::from_secs(20),
    );
    let written = |text: &str| {
        serde_json::from_str::<serde_json::Value>(text).is_ok_and(|v| v["mag"]["status"] == "ok")
    };
    let stored = common::wait_for_file(
        &cal.join("calibration.json"),
        written,
        Duration::from_secs(20),
    );
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    let said = seen.join("\n");
    let answer = answer.unwrap_or_else(|| panic!("no COMMAND_ACK:\n{said}"));
    assert!(answer.contains("FIXED_MAG_CAL_YAW: ACCEPTED"), "{said}");
    assert!(!said.contains("no position available"), "{said}");
    assert!(
        said.contains("AP: mag calibrated at a fixed yaw of 90.0 deg"),
        "{said}"
    );
    assert!(stored.is_some(), "no calibration written:\n{said}");
}

/// A UDP relay between MAVProxy (which sends to the returned port) and the service on
/// `service_port`, noting the name of every message MAVProxy sends and when (s since the start)
/// until `stop` turns true.
fn counting_relay(
    service_port: u16,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> (u16, std::thread::JoinHandle<Vec<(f64, String)>>) {
    use std::net::UdpSocket;
    let gcs_side = UdpSocket::bind("127.0.0.1:0").unwrap();
    let svc_side = UdpSocket::bind("127.0.0.1:0").unwrap();
    let port = gcs_side.local_addr().unwrap().port();
    let handle = std::thread::spawn(move || {
        let tick = Some(Duration::from_millis(5));
        gcs_side.set_read_timeout(tick).unwrap();
        svc_side.set_read_timeout(tick).unwrap();
        let mut decoder = imucald::io::decode::FrameDecoder::new();
        let (start, mut gcs, mut seen, mut buf) = (Instant::now(), None, Vec::new(), [0u8; 65536]);
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            if let Ok((n, from)) = gcs_side.recv_from(&mut buf) {
                gcs = Some(from);
                let _ = svc_side.send_to(&buf[..n], ("127.0.0.1", service_port));
                for f in decoder.push(&buf[..n]) {
                    let name = format!("{:?}", f.message);
                    let name = name.split('(').next().unwrap_or_default().to_string();
                    seen.push((start.elapsed().as_secs_f64(), name));
                }
            }
            if let (Ok(n), Some(to)) = (svc_side.recv(&mut buf), gcs) {
                let _ = gcs_side.send_to(&buf[..n], to);
            }
        }
        seen
    });
    (port, handle)
}

/// The service with a simulated tumble (at its pace: it lasts the whole test) and a UDP source on
/// a free port (returned), publishing nothing, its files under `dir`.
fn tumbling_service(dir: &std::path::Path) -> (u16, std::process::Child) {
    let port = common::free_udp_port();
    let cfg = dir.join("svc.toml");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\ncalibration_dir = \"{}\"\npublish = []\n\
             sources = [{{ address = \"sim:tumble\" }}, {{ address = \"udpin:127.0.0.1:{port}\" }}]\n",
            dir.join("cal").display()
        ),
    )
    .unwrap();
    (port, common::spawn_service(&cfg))
}

/// MAVProxy's `param fetch` asks for `@PARAM/param.pck` over MAVFTP first: the service serves it at
/// once, so the list arrives in one round trip and a burst, not after MAVProxy's MAVFTP timeout
/// (about 11 s before it falls back to PARAM_REQUEST_LIST).
#[test]
fn mavproxy_param_fetch_is_answered_at_once_over_mavftp() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (port, mut svc) = tumbling_service(dir.path());
    let (mut gcs, mut stdin, rx) = mavproxy_session(
        &mavproxy,
        dir.path(),
        port,
        &["--target-system=1", "--target-component=191"],
    );
    let mut seen = Vec::new();
    let received = |l: &str| l.starts_with("Received ") && l.contains("parameters (ftp)");
    // The fetch MAVProxy makes when it connects, then three asked for.
    let first = next_line(&rx, &mut seen, received, Duration::from_secs(60));
    let mut took = Vec::new();
    for _ in 0..3 {
        let asked = Instant::now();
        send(&mut stdin, "param fetch");
        if next_line(&rx, &mut seen, received, Duration::from_secs(20)).is_none() {
            break;
        }
        took.push(asked.elapsed().as_secs_f64());
    }
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    let said = seen.join("\n");
    let first = first.unwrap_or_else(|| panic!("no parameters over MAVFTP:\n{said}"));
    assert_eq!(first, "Received 71 parameters (ftp)", "{said}");
    assert_eq!(took.len(), 3, "a fetch not answered:\n{said}");
    eprintln!("param fetch took {took:?} s");
    // Measured 0.20 s each (the need: under 2 s). The bound here is what tells an answer from
    // MAVProxy's MAVFTP timeout (about 11 s) on a loaded 2-core machine running the suite, where
    // MAVProxy's own turn can take seconds; the figure itself is printed above.
    assert!(took.iter().all(|&t| t < 6.0), "{took:?}\n{said}");
    let parm = std::fs::read_to_string(dir.path().join("mav_1_191.parm")).unwrap();
    let listed = common::parm_values(&parm);
    assert_eq!(listed.len(), 71, "{parm}");
    assert_eq!(listed["CAL_MAG_MODE"], 0.0, "{parm}");
}

/// MAVProxy started with only `--target-system=1` (as many users start it) keeps its target
/// component 0 and asks for the parameters of (1, 1) until a list arrives there; served over
/// MAVFTP (the service answers a request to every component of its system when no flight
/// controller of that system is heard), the list arrives once and MAVProxy stops asking. Counted
/// over 30 s on a relay between the two; the bound is at most 5 PARAM_REQUEST_LIST in 2 minutes,
/// so at most 1 in 30 s.
#[test]
fn mavproxy_with_only_a_target_system_stops_asking_for_the_list() {
    let Some(mavproxy) = mavproxy() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (svc_port, mut svc) = tumbling_service(dir.path());
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (port, relay) = counting_relay(svc_port, stop.clone());
    let (mut gcs, _stdin, rx) =
        mavproxy_session(&mavproxy, dir.path(), port, &["--target-system=1"]);
    let mut seen = Vec::new();
    let heard = next_line(
        &rx,
        &mut seen,
        |l| l.contains("Detected vehicle 1:191"),
        Duration::from_secs(60),
    );
    let window = Duration::from_secs(30);
    let from = Instant::now();
    while from.elapsed() < window {
        if let Ok(l) = rx.recv_timeout(Duration::from_millis(200)) {
            seen.push(l);
        }
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let sent = relay.join().unwrap();
    let _ = Command::new("kill").arg(svc.id().to_string()).status();
    let _ = gcs.kill();
    let _ = svc.wait();
    let _ = gcs.wait();
    let said = seen.join("\n");
    assert!(heard.is_some(), "MAVProxy never heard the service:\n{said}");
    let lists = sent
        .iter()
        .filter(|(_, n)| n == "PARAM_REQUEST_LIST")
        .count();
    let ftp = sent
        .iter()
        .filter(|(_, n)| n == "FILE_TRANSFER_PROTOCOL")
        .count();
    let span_s = sent.last().map_or(0.0, |s| s.0);
    eprintln!(
        "over {span_s:.1} s MAVProxy sent {lists} PARAM_REQUEST_LIST and {ftp} FILE_TRANSFER_PROTOCOL"
    );
    assert!(span_s >= window.as_secs_f64(), "{sent:?}");
    assert!(said.contains("Received 71 parameters (ftp)"), "{said}");
    // Measured 0 lists (3 MAVFTP requests: open, burst read, close); before, one every 2 s.
    let per_2_min = lists as f64 * 120.0 / span_s;
    assert!(per_2_min <= 5.0, "{lists} lists in {span_s:.0} s:\n{said}");
}
