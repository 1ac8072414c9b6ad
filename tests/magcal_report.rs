//! A commanded compass calibration's MAG_CAL_REPORT as ArduPilot's calibrator sends it: repeated
//! while its result waits (so a report lost on the way arrives again) until the ground station
//! accepts it, and no more after. The service runs in this process on the embedded simulated
//! tumble (10x its pace) with `daemon.mag_cal = "on_command"`; a ground station of ours on UDP
//! starts a run with autosave off, lets the first reports go unanswered, then accepts.

mod common;

use imucald::config::MagCalMode;
use imucald::io::mavout::MavEncoder;
use mavlink::dialects::ardupilotmega::{
    MagCalStatus, MavCmd, MavMessage, MavResult, COMMAND_LONG_DATA,
};
use std::time::Duration;

/// DO_START_MAG_CAL or DO_ACCEPT_MAG_CAL for every compass, to the service's ids.
fn command(command: MavCmd, param3: f32) -> MavMessage {
    let (system, component) = common::testdata::SERVICE_IDS;
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command,
        target_system: system,
        target_component: component,
        param3,
        ..Default::default()
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_report_repeats_until_the_ground_station_accepts_it() {
    let dir = tempfile::tempdir().unwrap();
    let (port, mut cfg) = common::udpin_config(dir.path());
    cfg.daemon.mag_cal = MagCalMode::OnCommand;
    cfg.daemon
        .sources
        .push(common::mavlink_source("sim:tumble?speed=10"));
    let daemon = common::Daemon::ready(cfg).await;
    let gcs = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut enc = MavEncoder::new(255, 190);
    // Autosave off: the result waits for the accept.
    let start = command(MavCmd::MAV_CMD_DO_START_MAG_CAL, 0.0);
    gcs.send_to(&enc.encode(&start), ("127.0.0.1", port))
        .await
        .unwrap();
    let mut dec = imucald::io::decode::FrameDecoder::new();
    let mut buf = vec![0u8; 65536];
    let t0 = tokio::time::Instant::now();
    let mut reports = Vec::new();
    let mut accepted_at = None;
    let mut ack = None;
    let deadline = t0 + Duration::from_secs(90);
    loop {
        let until = match accepted_at {
            // Listen 2.5 s past the accept for a report that should not come.
            Some(at) => at + Duration::from_millis(2500),
            None => deadline,
        };
        let Ok(Ok(n)) = tokio::time::timeout_at(until, gcs.recv(&mut buf)).await else {
            break;
        };
        let now = tokio::time::Instant::now();
        for f in dec.push(&buf[..n]) {
            match f.message {
                MavMessage::MAG_CAL_REPORT(r) => reports.push((now, r)),
                MavMessage::COMMAND_ACK(a) if a.command == MavCmd::MAV_CMD_DO_ACCEPT_MAG_CAL => {
                    ack = Some(a.result)
                }
                _ => {}
            }
        }
        // The first report and two repeats go unanswered (as if lost), then the accept.
        if accepted_at.is_none() && reports.len() >= 3 {
            let accept = command(MavCmd::MAV_CMD_DO_ACCEPT_MAG_CAL, 0.0);
            gcs.send_to(&enc.encode(&accept), ("127.0.0.1", port))
                .await
                .unwrap();
            accepted_at = Some(tokio::time::Instant::now());
        }
    }
    daemon.stop(Duration::from_secs(5)).await;
    let accepted_at = accepted_at.unwrap_or_else(|| panic!("{} reports", reports.len()));
    let before: Vec<_> = reports.iter().filter(|(t, _)| *t <= accepted_at).collect();
    assert!(before.len() >= 3, "{} reports", before.len());
    for (_, r) in &before {
        assert_eq!(r.cal_status, MagCalStatus::MAG_CAL_SUCCESS, "{r:?}");
        assert_eq!(r.autosaved, 0, "{r:?}");
        assert_eq!((r.ofs_x, r.ofs_y, r.ofs_z), {
            let r0 = &before[0].1;
            (r0.ofs_x, r0.ofs_y, r0.ofs_z)
        });
    }
    // Repeated about once a second (REPORT_REPEAT_S), not flooded.
    let gaps: Vec<f64> = before
        .windows(2)
        .map(|w| (w[1].0 - w[0].0).as_secs_f64())
        .collect();
    assert!(gaps.iter().all(|g| *g > 0.5), "gaps {gaps:?} s");
    assert_eq!(ack, Some(MavResult::MAV_RESULT_ACCEPTED));
    // One report may have been on its way as the accept went; none after that.
    let after = reports
        .iter()
        .filter(|(t, _)| *t > accepted_at + Duration::from_millis(300))
        .count();
    assert_eq!(after, 0, "reports after the accept");
    let store = imucald::app::daemon::load_store(&dir.path().join("cal"))
        .unwrap()
        .expect("the accepted calibration written");
    let m = store.mag.expect("a magnetometer calibration");
    let r = &before[0].1;
    // COMPASS_OFS convention: -offset in mGauss (10 per uT).
    assert!(
        (m.offset[0] * -10.0 - r.ofs_x as f64).abs() < 0.01,
        "{m:?} {r:?}"
    );
}

/// A run on a magnetometer with 4 uT of white noise per axis fails as ArduPilot's calibrator with
/// its default COMPASS_CAL_FIT (16 mGauss, doubled to 32 for a compass not known to be external)
/// would fail it: one MAG_CAL_REPORT with FAILED_RESIDUALS_HIGH and the fitness above the
/// tolerance, autosave or not nothing installed or written. (Before, the run succeeded with a
/// fitness of 41.6 mGauss.) The clean run of the test above still succeeds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_noisy_run_fails_on_its_fitness() {
    let dir = tempfile::tempdir().unwrap();
    let scenario = dir.path().join("noisy.toml");
    std::fs::write(&scenario, "name = \"tumble\"\n[mag]\nnoise_sd = 4.0\n").unwrap();
    let (port, mut cfg) = common::udpin_config(dir.path());
    cfg.daemon.mag_cal = MagCalMode::OnCommand;
    cfg.daemon.sources.push(common::mavlink_source(format!(
        "sim:{}?speed=10",
        scenario.display()
    )));
    let daemon = common::Daemon::ready(cfg).await;
    let gcs = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut enc = MavEncoder::new(255, 190);
    // Autosave on, retry off.
    let start = command(MavCmd::MAV_CMD_DO_START_MAG_CAL, 1.0);
    gcs.send_to(&enc.encode(&start), ("127.0.0.1", port))
        .await
        .unwrap();
    let mut dec = imucald::io::decode::FrameDecoder::new();
    let mut buf = vec![0u8; 65536];
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    let mut report = None;
    let mut texts = Vec::new();
    while report.is_none() {
        let Ok(Ok(n)) = tokio::time::timeout_at(deadline, gcs.recv(&mut buf)).await else {
            break;
        };
        for f in dec.push(&buf[..n]) {
            match f.message {
                MavMessage::MAG_CAL_REPORT(r) => report = Some(r),
                MavMessage::STATUSTEXT(t) => texts.push(t.text.to_str().unwrap_or("").to_string()),
                _ => {}
            }
        }
    }
    daemon.stop(Duration::from_secs(5)).await;
    let r = report.unwrap_or_else(|| panic!("no MAG_CAL_REPORT; texts {texts:?}"));
    eprintln!(
        "noisy run: {:?}, fitness {:.1} mGauss",
        r.cal_status, r.fitness
    );
    assert_eq!(
        r.cal_status,
        MagCalStatus::MAG_CAL_FAILED_RESIDUALS_HIGH,
        "{r:?}"
    );
    // Measured 40.0 mGauss (about the noise's 4 uT RMS), over the tolerance of 32.
    assert!(r.fitness > 32.0, "{r:?}");
    assert_eq!(r.autosaved, 0, "{r:?}");
    assert!(
        texts.iter().any(|t| t.contains("mag calibration failed")),
        "{texts:?}"
    );
    let stored = imucald::app::daemon::load_store(&dir.path().join("cal")).unwrap();
    assert!(
        stored.and_then(|s| s.mag).is_none(),
        "a failed run wrote a calibration"
    );
}
