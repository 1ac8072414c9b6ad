//! The one integration-test binary: real recordings, simulated logs with known truth, the CLI.

use imucald::config::Config;
use imucald::replay::{replay, ReplayOptions};
use std::path::{Path, PathBuf};

/// `../shared/data` beside the checkout, or `None` with a plain message when it is absent.
fn shared_data() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: {} is absent; real-data tests need the shared recordings beside the checkout", p.display());
        None
    }
}

/// Return early from a test (with the message above) when the shared data is absent.
macro_rules! require_data {
    () => {
        match shared_data() {
            Some(p) => p,
            None => return,
        }
    };
}

fn run(path: &Path, cfg: &Config) -> imucald::replay::ReplayOutcome {
    replay(path, cfg, &ReplayOptions::default(), &mut |_, _| {}).unwrap_or_else(|e| panic!("replay {}: {e}", path.display()))
}

mod real_data {
    use super::*;

    fn reference_hard_iron(path: &Path) -> [f64; 3] {
        let text = std::fs::read_to_string(path).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        let a = v["os_hard_iron_uT_median"].as_array().unwrap();
        [a[0].as_f64().unwrap(), a[1].as_f64().unwrap(), a[2].as_f64().unwrap()]
    }

    #[test]
    fn tyrex_hard_iron_within_3_ut_of_the_phone() {
        let data = require_data!();
        for set in ["calib_mag_Nexus5_d1", "calib_mag_Nexus5_d3"] {
            let out = run(&data.join(format!("tyrex/{set}.csv.gz")), &Config::default());
            let m = &out.report.calibration.mag;
            assert_eq!(m.status, "ok", "{set}: {:?} {:?}", m.failure, m.detail);
            let r = reference_hard_iron(&data.join(format!("tyrex/{set}.reference.json")));
            for k in 0..3 {
                let d = (m.offset[k] - r[k]).abs();
                eprintln!("{set} axis {k}: ours {:.3} phone {:.3} diff {d:.3} uT", m.offset[k], r[k]);
                assert!(d < 3.0, "{set} axis {k}: {} vs {}", m.offset[k], r[k]);
            }
            assert!(out.report.coverage.mag.filled >= 80);
        }
    }

    #[test]
    fn imu_tk_poses_and_gravity_norm_residual() {
        let data = require_data!();
        let out = run(&data.join("imu_tk/xsens_raw_counts.csv.gz"), &Config::default());
        let poses = out.report.static_poses.len();
        let a = &out.report.calibration.accel;
        eprintln!("imu_tk: {poses} poses, accel model {} rms {:.5} m/s^2", a.model, a.rms_residual);
        assert!(poses >= 34, "{poses} static poses");
        assert_eq!(a.status, "ok", "{:?}", a.detail);
        assert!(a.rms_residual < 0.003, "{}", a.rms_residual);
        assert_eq!(a.units, "m/s^2");
        assert_eq!(out.report.calibration.gyro.units, "counts");
    }

    #[test]
    fn tyrex_accel_log_without_mag_tumble_says_coverage() {
        let data = require_data!();
        let out = run(&data.join("tyrex/calib_acc_Nexus5_d1.csv.gz"), &Config::default());
        assert_eq!(out.report.calibration.mag.failure.as_deref(), Some("coverage"));
        assert_eq!(out.report.calibration.accel.status, "ok");
    }
}

mod config_files {
    #[test]
    fn example_configs_parse() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let mut n = 0;
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                imucald::config::Config::load(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
                n += 1;
            }
        }
        assert!(n >= 1);
    }
}
