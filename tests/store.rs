//! The calibration store: one service per store (a lock file with the holder's process id), and
//! a simulator's calibration kept apart from a vehicle's and never resumed onto one.

mod common;

use common::{free_udp_port, mavlink_source};
use imucald::app::daemon::{load_store, VehicleSource};
use imucald::config::Config;
use imucald::io::mavout::MavEncoder;
use std::time::Duration;

/// The service on `cfg` (simulated sources only) until they ended.
async fn run_to_end(cfg: Config) -> imucald::app::daemon::RunSummary {
    let (_stop, stop_rx) = tokio::sync::watch::channel(false);
    imucald::app::daemon::run(cfg, stop_rx).await.unwrap()
}

/// A second `imucald run` on a store a running service holds exits with status 2 at once, naming
/// the holder's process id; the first keeps running and stops cleanly.
#[test]
fn a_second_service_on_the_same_store_exits_2_naming_the_holder() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("svc.toml");
    std::fs::write(
        &cfg,
        format!(
            "[daemon]\ncalibration_dir = \"{}\"\npublish = []\nsources = [{{ address = \"udpin:127.0.0.1:0\" }}]\n",
            dir.path().join("cal").display()
        ),
    )
    .unwrap();
    let mut first = common::Service::start(&["--config".as_ref(), cfg.as_os_str()]);
    let holder = first.child().id();
    let second = std::process::Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["run", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&second.stderr);
    assert_eq!(second.status.code(), Some(2), "{said}");
    assert!(said.contains(&format!("pid {holder}")), "{said}");
    assert!(said.contains("imucald.lock"), "{said}");
    let (status, _) = first.stop(Duration::from_secs(5));
    assert_eq!(status.and_then(|s| s.code()), Some(0));
    // Free again once the holder stopped.
    let mut third = common::Service::start(&["--config".as_ref(), cfg.as_os_str()]);
    let (status, _) = third.stop(Duration::from_secs(5));
    assert_eq!(status.and_then(|s| s.code()), Some(0));
}

/// A calibration made from the built-in simulator is recorded as the simulator's; a vehicle on a
/// MAVLink link that then comes to the same store does not resume it (said) and starts from
/// nothing; and a simulator run on a store holding a vehicle's calibration keeps its own in
/// `sim/`, leaving the vehicle's as it was.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_simulator_calibration_is_never_resumed_onto_a_vehicle() {
    let dir = tempfile::tempdir().unwrap();
    let cal_dir = dir.path().join("cal");
    let simulated = |sources: Vec<String>| {
        let mut cfg = Config::default();
        cfg.daemon.sources = sources.into_iter().map(mavlink_source).collect();
        cfg.daemon.calibration_dir = cal_dir.display().to_string();
        cfg.daemon.publish = vec![];
        cfg
    };
    // The simulated tumble, played to its end.
    let summary = run_to_end(simulated(vec!["sim:tumble?speed=50".into()])).await;
    assert!(summary.accepted > 0, "{summary:?}");
    let sim = load_store(&cal_dir)
        .unwrap()
        .expect("the simulator's calibration");
    assert!(sim.mag.is_some());
    let recorded = sim.vehicle.as_ref().expect("a record");
    assert_eq!(recorded.source, VehicleSource::Simulator);

    // A vehicle on a link: not resumed, said.
    let port = free_udp_port();
    let mut sink = common::JsonSink::bind().await;
    let mut cfg = simulated(vec![format!("udpin:127.0.0.1:{port}")]);
    cfg.daemon.publish = vec![sink.publish()];
    let daemon = common::Daemon::ready(cfg).await;
    let peer = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let tumble = imucald::sim::simulate(&imucald::sim::Scenario::named("tumble").unwrap(), 5);
    let mut enc = MavEncoder::new(1, 1);
    for s in &tumble.samples[..200] {
        let frame = enc.encode(&common::highres_imu_at(s));
        peer.send_to(&frame, ("127.0.0.1", port)).await.unwrap();
    }
    let not_resumed = |v: &serde_json::Value| {
        v["type"] == "status"
            && v["text"]
                .as_str()
                .is_some_and(|t| t.contains("the simulator's calibration in"))
    };
    let said = sink
        .wait_for("the refusal", not_resumed, Duration::from_secs(20))
        .await;
    daemon.stop(Duration::from_secs(2)).await;
    assert!(
        said["text"]
            .as_str()
            .unwrap()
            .contains("is not resumed onto a vehicle"),
        "{said}"
    );
    let now = load_store(&cal_dir).unwrap().unwrap();
    assert!(now.mag.is_none(), "the simulator's calibration was resumed");
    let v = now.vehicle.expect("the vehicle recorded");
    assert_eq!((v.source, v.system_id), (VehicleSource::Vehicle, 1));

    // The simulator again: into sim/, the vehicle's record untouched.
    let summary = run_to_end(simulated(vec!["sim:tumble?speed=50".into()])).await;
    assert!(summary.accepted > 0, "{summary:?}");
    let apart = load_store(&cal_dir.join("sim")).unwrap().expect("in sim/");
    assert_eq!(apart.vehicle.unwrap().source, VehicleSource::Simulator);
    let kept = load_store(&cal_dir).unwrap().unwrap();
    assert_eq!(kept.vehicle.unwrap().source, VehicleSource::Vehicle);
    assert!(kept.mag.is_none());
}
