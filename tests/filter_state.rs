//! The live service keeps what its orientation filter learnt (residual gyro bias, field reference)
//! in the calibration file and starts from it the next time, instead of learning it again.

mod common;

use imucald::app::daemon::load_store;
use imucald::config::Config;
use std::path::Path;
use std::time::Duration;

/// Run the service over the simulated tumble (as fast as it goes, so it stops at the end) with
/// `cal_dir`; returns the `gyro_bias_rad_s` of the attitude lines it published, in order.
async fn run_tumble(cal_dir: &Path) -> Vec<[f64; 3]> {
    let sink = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut cfg = Config::default();
    cfg.daemon.sources = vec![common::mavlink_source("sim:tumble?seed=3&speed=0")];
    cfg.daemon.calibration_dir = cal_dir.display().to_string();
    cfg.daemon.publish = vec![format!("udp:{}", sink.local_addr().unwrap())];
    cfg.daemon.attitude_every_samples = 500;
    cfg.validate().unwrap();
    let collect = tokio::spawn(async move {
        let mut out = vec![];
        let mut buf = vec![0u8; 65_536];
        while let Ok(Ok(n)) =
            tokio::time::timeout(Duration::from_secs(3), sink.recv(&mut buf)).await
        {
            for line in String::from_utf8_lossy(&buf[..n]).lines() {
                let v: serde_json::Value = serde_json::from_str(line).unwrap();
                if v["type"] == "attitude" {
                    let b = &v["gyro_bias_rad_s"];
                    out.push([0, 1, 2].map(|k| b[k].as_f64().unwrap()));
                }
            }
        }
        out
    });
    let (_stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::time::timeout(
        Duration::from_secs(120),
        imucald::app::daemon::run(cfg, stop_rx),
    )
    .await
    .expect("the simulated source ends")
    .unwrap();
    collect.await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn filter_state_is_saved_and_restored() {
    let dir = tempfile::tempdir().unwrap();
    let cal_dir = dir.path().join("cal");
    // First run: calibrates, and saves what the filter learnt beside the calibration.
    run_tumble(&cal_dir).await;
    let mut store = load_store(&cal_dir).unwrap().expect("calibration written");
    let learnt = store.filter.expect("filter state saved");
    let radius = store.mag.as_ref().unwrap().radius;
    eprintln!("saved {learnt:?}; mag radius {radius}");
    // The reference (unless the last calibration restarted the filter just before the end) is
    // the calibrated field: its norm is the fit's radius.
    if let Some((norm, dip)) = learnt.mag_reference {
        assert!((norm / radius - 1.0).abs() < 0.02, "{norm} vs {radius}");
        assert!(dip.abs() < 90.0);
    }
    let stored_bias = store.gyro.as_ref().unwrap().bias;
    // The gyro calibration took the simulated bias (0.01, -0.02, 0.005 rad/s) out of what the
    // filter sees, and the filter's own estimate moved with it: what is left is small. (Measured
    // 5.5e-4 to 1.7e-3 rad/s at most over runs; before the filter's estimate followed a new gyro
    // calibration it was 0.014: the bias removed twice.)
    let left = learnt
        .gyro_bias_rad_s
        .iter()
        .fold(0.0f64, |m, b| m.max(b.abs()));
    // With the filter settings tuned on BROAD the estimate settles more slowly: measured up to
    // 5.5e-3 rad/s. The bound must still catch the bias removed twice (0.014).
    assert!(left < 1e-2, "residual bias {:?}", learnt.gyro_bias_rad_s);

    // A restored bias is where the next run's filter starts: set a known one, run again.
    let planted = [0.02, -0.03, 0.01];
    store.filter = Some(imucald::attitude::fusion::FilterState {
        gyro_bias_rad_s: planted,
        ..learnt
    });
    imucald::app::daemon::save_store(&cal_dir, &store).unwrap();
    let restored = run_tumble(&cal_dir).await;
    // Without the state, the same run starts from zero residual bias.
    let mut store = load_store(&cal_dir).unwrap().unwrap();
    store.filter = None;
    imucald::app::daemon::save_store(&cal_dir, &store).unwrap();
    let fresh = run_tumble(&cal_dir).await;
    let first = |lines: &[[f64; 3]]| {
        let b = lines.first().copied().expect("an attitude line");
        [0, 1, 2].map(|k| b[k] - stored_bias[k])
    };
    let (r, f) = (first(&restored), first(&fresh));
    eprintln!(
        "first attitude line, bias beyond the gyro calibration: restored {r:.5?}, fresh {f:.5?}"
    );
    let off =
        |b: [f64; 3], want: [f64; 3]| (0..3).map(|k| (b[k] - want[k]).abs()).fold(0.0, f64::max);
    // Measured: the restored run 4.8e-4 rad/s from the planted bias at most, the fresh one 9.8e-4
    // from zero.
    assert!(
        off(r, planted) < 2e-3,
        "restored run starts at {r:?}, not {planted:?}"
    );
    assert!(off(f, [0.0; 3]) < 2e-3, "fresh run starts at {f:?}");
}
