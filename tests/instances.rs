//! Several IMU/compass instances in one stream: each is calibrated on its own.
//!
//! Two compasses with different hidden hard and soft iron ride through the same simulated tumble
//! and are written as HIGHRES_IMU `id` 0 and 1 into one `.tlog`, in the order an autopilot sends
//! them (both instances' messages of one instant, then the next instant). `replay` must give two
//! calibrations, each near its own truth, in ArduPilot's COMPASS_OFS convention (mGauss, added:
//! COMPASS_OFS = -offset).

mod common;

use imucald::config::Config;
use imucald::io::samplelog::TLOG_EPOCH_US;
use imucald::report::CalStatus;
use imucald::sim::SimOutput;
use mavlink::dialects::ardupilotmega::MavMessage;

/// The tumble with the second compass's hard iron and soft iron changed.
fn two_compasses() -> (SimOutput, SimOutput) {
    common::tumble_and_other_iron(4)
}

fn write_tlog(path: &std::path::Path, streams: &[(&SimOutput, u8)]) {
    let mut bytes = Vec::new();
    let n = streams[0].0.samples.len();
    for i in 0..n {
        for (sim, id) in streams {
            let s = &sim.samples[i];
            let t_us = (s.t_s * 1e6).round() as u64;
            let MavMessage::HIGHRES_IMU(mut d) =
                imucald::io::samplelog::highres_imu(s, 10_000_000 + t_us)
            else {
                unreachable!()
            };
            d.id = *id;
            common::push_tlog_record(
                &mut bytes,
                TLOG_EPOCH_US + t_us,
                &MavMessage::HIGHRES_IMU(d),
            );
        }
    }
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn two_compasses_in_one_log_are_calibrated_each_against_its_own_truth() {
    let (a, b) = two_compasses();
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("two.tlog");
    write_tlog(&log, &[(&a, 0), (&b, 1)]);
    let out = common::replay_log(&log, &Config::default());
    let r = &out.report;
    assert_eq!(
        r.instances.len(),
        2,
        "{:?}",
        r.instances.iter().map(|i| &i.instance).collect::<Vec<_>>()
    );
    for (inst, sim, id) in [(&r.instances[0], &a, 0u8), (&r.instances[1], &b, 1u8)] {
        assert_eq!(inst.compass_id, id);
        assert_eq!(inst.instance, format!("highres_imu:{id}"));
        assert_eq!(inst.primary, id == 0);
        assert_eq!(inst.samples as usize, sim.samples.len());
        assert_eq!(inst.time.segments, 1, "compass {id}: {:?}", inst.time);
        let m = &inst.calibration.mag;
        assert_eq!(m.status, CalStatus::Ok, "compass {id}: {:?}", m.detail);
        // COMPASS_OFS (mGauss, added) from ours and from the truth: 1 uT = 10 mGauss.
        let ofs = |o: &[f64; 3]| o.map(|x| -10.0 * x);
        let (got, want) = (ofs(&m.offset), ofs(&sim.truth.mag.offset));
        let err = (0..3).map(|k| (got[k] - want[k]).abs()).fold(0.0, f64::max);
        eprintln!(
            "compass {id}: COMPASS_OFS {got:.2?} mGauss, truth {want:.2?}, error {err:.3} mGauss"
        );
        // Measured 0.055 (compass 0) and 0.037 mGauss (compass 1).
        assert!(err < 0.2, "compass {id}: COMPASS_OFS error {err} mGauss");
    }
    // The primary's block is the report's own calibration.
    assert_eq!(r.instances[0].calibration.mag, r.calibration.mag);
    // The two are told apart: their offsets differ by far more than either's error.
    let d: f64 = (0..3)
        .map(|k| {
            (r.instances[0].calibration.mag.offset[k] - r.instances[1].calibration.mag.offset[k])
                .abs()
        })
        .fold(0.0, f64::max);
    assert!(d > 10.0, "offsets differ by {d} uT");
}

#[test]
fn a_config_can_still_pick_one_instance() {
    let (a, b) = two_compasses();
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("two.tlog");
    write_tlog(&log, &[(&a, 0), (&b, 1)]);
    let mut cfg = Config::default();
    cfg.input.instance = "highres_imu:1".parse().unwrap();
    let out = common::replay_log(&log, &cfg);
    let r = &out.report;
    assert!(r.instances.is_empty());
    assert_eq!(r.input.instance.as_deref(), Some("highres_imu:1"));
    assert_eq!(
        r.input.skipped.get("other_instance").copied(),
        Some(a.samples.len() as u64)
    );
    let err = (0..3)
        .map(|k| (r.calibration.mag.offset[k] - b.truth.mag.offset[k]).abs())
        .fold(0.0, f64::max);
    // Measured 0.0037 uT (the same as compass 1 among both).
    assert!(err < 0.012, "{err} uT");
}

/// The live service, fed the same two compasses over a UDP MAVLink link as an autopilot streams
/// them: each compass gets its own MAG_CAL_PROGRESS and MAG_CAL_REPORT (its `compass_id` and
/// `cal_mask`), its own JSON lines (`instance`), its own entry in the calibration file and its own
/// parameter names in the exports (COMPASS_OFS / COMPASS_OFS2, CAL_MAG0 / CAL_MAG1).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_service_reports_each_compass_on_its_own() {
    use imucald::io::mavout::MavEncoder;
    use std::collections::BTreeMap;
    use std::time::Duration;
    let (a, b) = two_compasses();
    let dir = tempfile::tempdir().unwrap();
    let peer = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut sink = common::JsonSink::bind().await;
    let (port, mut cfg) = common::udpin_config(dir.path());
    let cal_dir = dir.path().join("cal");
    cfg.daemon.publish = vec![sink.publish()];
    cfg.daemon.report = Some(dir.path().join("report.json").display().to_string());
    cfg.fit.refit_every_s = 5.0;
    cfg.validate().unwrap();
    let daemon = common::Daemon::ready(cfg).await;

    // What comes back from the service: the last MAG_CAL_REPORT and the progress per compass, and
    // the answer to a ping.
    let reports = std::sync::Arc::new(std::sync::Mutex::new(BTreeMap::new()));
    let progress = std::sync::Arc::new(std::sync::Mutex::new(BTreeMap::new()));
    let (pong_tx, mut pong_rx) = tokio::sync::watch::channel(false);
    let listen = {
        let peer_rx = std::sync::Arc::new(peer);
        let peer_tx = peer_rx.clone();
        let (reports, progress) = (reports.clone(), progress.clone());
        let task = tokio::spawn(async move {
            let mut dec = imucald::io::decode::FrameDecoder::new();
            let mut buf = vec![0u8; 4096];
            while let Ok((n, _)) = peer_rx.recv_from(&mut buf).await {
                for f in dec.push(&buf[..n]) {
                    if common::testdata::pong(&f).is_some() {
                        pong_tx.send_replace(true);
                    }
                    match f.message {
                        MavMessage::MAG_CAL_REPORT(r) => {
                            reports.lock().unwrap().insert(r.compass_id, r);
                        }
                        MavMessage::MAG_CAL_PROGRESS(p) => {
                            progress.lock().unwrap().insert(p.compass_id, p);
                        }
                        _ => {}
                    }
                }
            }
        });
        (peer_tx, task)
    };
    let (peer, listener) = listen;
    let mut enc = MavEncoder::new(1, 1);
    let target = format!("127.0.0.1:{port}");
    // At 20 times real time, both compasses' messages of an instant back to back.
    let speed = 20.0;
    let t0 = tokio::time::Instant::now();
    for i in 0..a.samples.len() {
        for (sim, id) in [(&a, 0u8), (&b, 1u8)] {
            let s = &sim.samples[i];
            let t_us = (s.t_s * 1e6).round() as u64;
            let MavMessage::HIGHRES_IMU(mut d) =
                imucald::io::samplelog::highres_imu(s, 10_000_000 + t_us)
            else {
                unreachable!()
            };
            d.id = id;
            peer.send_to(&enc.encode(&MavMessage::HIGHRES_IMU(d)), &target)
                .await
                .unwrap();
        }
        common::pace(i, t0, a.samples[i].t_s, speed).await;
    }
    // Stopped once it took everything: the answer to a ping sent after the last sample.
    peer.send_to(
        &common::testdata::ping(1, common::testdata::SERVICE_IDS),
        &target,
    )
    .await
    .unwrap();
    tokio::time::timeout(Duration::from_secs(20), pong_rx.wait_for(|p| *p))
        .await
        .expect("the service answers the ping")
        .unwrap();
    let summary = daemon.stop(Duration::from_secs(2)).await;
    listener.abort();
    eprintln!("{summary:?}");

    // Two successful reports, each within 1 mGauss of its own compass's truth (COMPASS_OFS: mGauss,
    // added, so -10 x the hard iron in uT).
    let reports = reports.lock().unwrap().clone();
    let progress = progress.lock().unwrap().clone();
    assert_eq!(
        reports.keys().copied().collect::<Vec<_>>(),
        vec![0, 1],
        "{reports:?}"
    );
    for (id, sim) in [(0u8, &a), (1u8, &b)] {
        let r = &reports[&id];
        assert_eq!(r.cal_mask, 1 << id);
        assert_eq!(r.cal_status as u8, 4, "compass {id}: {r:?}"); // MAG_CAL_SUCCESS
        let got = [r.ofs_x, r.ofs_y, r.ofs_z].map(f64::from);
        let want = sim.truth.mag.offset.map(|x| -10.0 * x);
        let err = (0..3).map(|k| (got[k] - want[k]).abs()).fold(0.0, f64::max);
        eprintln!("live compass {id}: COMPASS_OFS {got:.2?} mGauss, truth {want:.2?}, error {err:.3} mGauss");
        // Measured 0.16 (compass 0) and 0.53 mGauss (compass 1). Continuous calibration reports a
        // calibration only once it moved by more than 0.5 mGauss from the last report, so the
        // last report can be that far from the one installed (checked below against the file, at
        // 0.06 and 0.04 mGauss); 1 mGauss is what a report must meet.
        assert!(err < 1.0, "compass {id}: COMPASS_OFS error {err} mGauss");
        let p = &progress[&id];
        assert_eq!(p.cal_mask, 1 << id);
        assert!(p.completion_pct >= 90, "compass {id}: {p:?}");
    }

    // Its own JSON lines.
    let instances: std::collections::BTreeSet<u64> = sink
        .drain()
        .await
        .iter()
        .filter(|v| v["type"] == "calibration" && v["sensor"] == "mag" && v["status"] == "ok")
        .map(|v| v["instance"].as_u64().unwrap())
        .collect();
    assert_eq!(instances.into_iter().collect::<Vec<_>>(), vec![0, 1]);

    // Its own entry in the calibration file, and its own parameter names.
    let store = imucald::app::daemon::load_store(&cal_dir).unwrap().unwrap();
    assert_eq!(store.compass_id, 0);
    assert_eq!(store.instances.len(), 1);
    assert_eq!(store.instances[0].compass_id, 1);
    assert_eq!(store.instances[0].instance, "highres_imu:1");
    for (stored, sim) in [
        (store.mag.as_ref(), &a),
        (store.instances[0].mag.as_ref(), &b),
    ] {
        let m = stored.unwrap();
        let err = (0..3)
            .map(|k| (m.offset[k] - sim.truth.mag.offset[k]).abs())
            .fold(0.0, f64::max);
        eprintln!("stored offset error {err:.4} uT");
        // Measured 0.0064 (compass 0) and 0.0036 uT (compass 1).
        assert!(err < 0.02, "stored offset error {err} uT");
    }
    let parm = std::fs::read_to_string(cal_dir.join("ardupilot.parm")).unwrap();
    let px4 = std::fs::read_to_string(cal_dir.join("px4.params")).unwrap();
    for name in ["COMPASS_OFS_X", "COMPASS_OFS2_X", "COMPASS_DIA2_Z"] {
        assert!(parm.contains(name), "{name} missing:\n{parm}");
    }
    for name in ["CAL_MAG0_XOFF", "CAL_MAG1_XOFF"] {
        assert!(px4.contains(name), "{name} missing:\n{px4}");
    }
    // And its own block in the report.
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap())
            .unwrap();
    let blocks = report["instances"].as_array().unwrap();
    assert_eq!(blocks.len(), 2, "{blocks:?}");
    assert_eq!(blocks[1]["compass_id"], 1);
    assert_eq!(blocks[1]["calibration"]["mag"]["status"], "ok");
}

/// Every compass gets every method: two compasses with different hidden iron ride through the
/// simulated cruise (legs and banked turns: too little coverage for the sphere fit), written as
/// HIGHRES_IMU `id` 0 and 1 with the vehicle's ATTITUDE and position. Each is calibrated by the
/// vector method near its own truth, and the export holds both.
#[test]
fn a_second_compass_of_an_ordinary_flight_gets_the_vector_method_too() {
    use imucald::calib::magmethod::MagMethod;
    use imucald::sim::{simulate, Scenario};
    let sc = Scenario::named("cruise").unwrap();
    let a = simulate(&sc, 2);
    let b = simulate(&common::with_other_iron(&sc), 2);
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("cruise2.tlog");
    let mut bytes = Vec::new();
    let mut state = imucald::io::samplelog::VehicleStateStream::default();
    for (sa, sb) in a.samples.iter().zip(&b.samples) {
        let t_us = (sa.t_s * 1e6).round() as u64;
        let boot_us = 10_000_000 + t_us;
        for m in state.messages(sa, boot_us) {
            common::push_tlog_record(&mut bytes, TLOG_EPOCH_US + t_us, &m);
        }
        for (s, id) in [(sa, 0u8), (sb, 1u8)] {
            let MavMessage::HIGHRES_IMU(mut d) = imucald::io::samplelog::highres_imu(s, boot_us)
            else {
                unreachable!()
            };
            d.id = id;
            common::push_tlog_record(
                &mut bytes,
                TLOG_EPOCH_US + t_us,
                &MavMessage::HIGHRES_IMU(d),
            );
        }
    }
    std::fs::write(&log, bytes).unwrap();
    let cfg = Config {
        place: sc.place.clone(),
        ..Default::default()
    };
    let export = dir.path().join("export");
    let opts = imucald::app::replay::ReplayOptions {
        export_dir: Some(export.clone()),
        ..Default::default()
    };
    let r = imucald::app::replay::replay(&log, &cfg, &opts, &mut |_, _| {})
        .unwrap()
        .report;
    assert_eq!(r.instances.len(), 2);
    let parm = std::fs::read_to_string(export.join("ardupilot.parm")).unwrap();
    for (inst, sim, id) in [(&r.instances[0], &a, 0u8), (&r.instances[1], &b, 1u8)] {
        let m = &inst.calibration.mag;
        let choice = m.method.as_ref().expect("a method for every compass");
        assert_eq!(
            choice.method,
            MagMethod::Vector,
            "compass {id}: {}",
            choice.method_reason
        );
        assert_eq!(m.status, CalStatus::Ok, "compass {id}: {:?}", m.detail);
        let err = (0..3)
            .map(|k| (m.offset[k] - sim.truth.mag.offset[k]).abs())
            .fold(0.0, f64::max);
        eprintln!(
            "compass {id}: offset {:.2?} uT, truth {:.2?}, error {err:.3} uT",
            m.offset, sim.truth.mag.offset
        );
        // Measured 0.33 uT on both compasses.
        assert!(err < 1.0, "compass {id}: offset error {err} uT");
        let name = if id == 0 {
            "COMPASS_OFS_X"
        } else {
            "COMPASS_OFS2_X"
        };
        assert!(parm.contains(name), "{parm}");
    }
}
