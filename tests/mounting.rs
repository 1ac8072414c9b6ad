//! The compass mounting found from the data in `replay`: a compass turned against the IMU is
//! refused with the parameter to set; a correctly mounted one is not.

mod common;

use imucald::calib::fit::FitFailure;
use imucald::calib::mounting::{rotation_vector_deg, Mounting, Verdict};
use imucald::config::Config;
use imucald::report::CalStatus;
use imucald::sim::{simulate, Scenario};

fn replay_tumble(mount: Option<u8>, seed: u64) -> imucald::report::SensorCalibration {
    let mut sc = Scenario::named("tumble").unwrap();
    sc.effects.mag_accel_rotation_deg =
        mount.map(|n| rotation_vector_deg(&Mounting::standard(n).unwrap().matrix()));
    let sim = simulate(&sc, seed);
    common::replay_samples(&sim.samples, &Config::default())
        .report
        .calibration
        .mag
}

#[test]
fn a_compass_turned_by_yaw_90_is_refused_naming_the_parameter() {
    let mag = replay_tumble(Some(2), 11);
    assert_eq!(mag.status, CalStatus::Failed, "{:?}", mag.detail);
    assert_eq!(mag.failure, Some(FitFailure::Orientation));
    let detail = mag.detail.unwrap();
    assert!(detail.contains("ROTATION_YAW_90"), "{detail}");
    assert!(detail.contains("COMPASS_ORIENT = 2"), "{detail}");
    assert!(detail.contains("CAL_MAG0_ROT = 2"), "{detail}");
    let m = mag.mounting.unwrap();
    let Verdict::Differs { set } = &m.verdict else {
        panic!("{m:?}")
    };
    assert_eq!(set.ardupilot_compass_orient, 2);
    assert_eq!(set.px4_cal_mag_rot, Some(2));
    eprintln!(
        "yaw 90: best {:.2} deg, runner-up {:?} ratio {:.1}, configured {:.1} deg",
        m.best.score_deg,
        m.runner_up
            .as_ref()
            .map(|r| (r.mounting.label(), r.score_deg)),
        m.margin_ratio.unwrap(),
        m.configured_score_deg
    );
}

/// The exports offer the mounting to set as a value (ArduPilot's COMPASS_ORIENT, PX4's
/// CAL_MAG0_ROT), with a comment saying why, and write no calibration of that compass.
#[test]
fn the_exports_offer_the_mounting_found_and_no_calibration_of_that_compass() {
    let mut sc = Scenario::named("tumble").unwrap();
    sc.effects.mag_accel_rotation_deg = Some(rotation_vector_deg(
        &Mounting::standard(2).unwrap().matrix(),
    ));
    let sim = simulate(&sc, 11);
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("log.csv");
    imucald::io::samplelog::write_csv(&log, &sim.samples).unwrap();
    let opts = imucald::app::replay::ReplayOptions {
        export_dir: Some(dir.path().join("export")),
        ..Default::default()
    };
    let out =
        imucald::app::replay::replay(&log, &Config::default(), &opts, &mut |_, _| {}).unwrap();
    assert_eq!(
        out.report.calibration.mag.failure,
        Some(FitFailure::Orientation)
    );
    let ap = std::fs::read_to_string(dir.path().join("export/ardupilot.parm")).unwrap();
    assert!(ap.lines().any(|l| l == "COMPASS_ORIENT 2.000000"), "{ap}");
    assert!(ap.contains("ROTATION_YAW_90"), "{ap}");
    assert!(!ap.contains("COMPASS_OFS_X"), "{ap}");
    let px = std::fs::read_to_string(dir.path().join("export/px4.params")).unwrap();
    assert!(
        px.lines().any(|l| l.starts_with("1\t1\tCAL_MAG0_ROT\t2.")),
        "{px}"
    );
    assert!(!px.contains("CAL_MAG0_XOFF"), "{px}");
}

#[test]
fn a_correctly_mounted_compass_is_not_refused() {
    let mag = replay_tumble(None, 11);
    assert_eq!(mag.status, CalStatus::Ok, "{:?}", mag.detail);
    let m = mag.mounting.unwrap();
    assert_eq!(m.verdict, Verdict::Matches, "{m:?}");
    let json = serde_json::to_value(&m).unwrap();
    assert_eq!(json["verdict"], "matches");
    assert_eq!(json["best"]["mounting"]["name"], "ROTATION_NONE");
    eprintln!(
        "none: best {:.2} deg, runner-up ratio {:.1}",
        m.best.score_deg,
        m.margin_ratio.unwrap()
    );
}

/// The live service, refitting as the poses arrive (a CSV `file:` source at 20x its pace, a
/// refit every half second): with the compass at YAW_90 and ROTATION_NONE configured, no refit's
/// magnetometer calibration is installed or written, from the first poses (while two other
/// rotations still fit alike) to the end; the report names the parameter to set.
#[test]
fn the_live_service_never_installs_a_calibration_from_a_compass_mounted_otherwise() {
    let mut sc = Scenario::named("tumble").unwrap();
    sc.effects.mag_accel_rotation_deg = Some(rotation_vector_deg(
        &Mounting::standard(2).unwrap().matrix(),
    ));
    let sim = simulate(&sc, 11);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let csv = d.join("tumble.csv");
    imucald::io::samplelog::write_csv(&csv, &sim.samples).unwrap();
    let (out, r) = common::run_on_file(&csv, 20, "[\"stdout\"]", "[fit]\nrefit_every_s = 0.5\n");
    let mut refits = 0;
    let mut refusals = 0;
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        if v["type"] == "calibration" && v["sensor"] == "mag" {
            refits += 1;
            assert_ne!(v["status"], "ok", "installed: {line}");
            refusals += (v["failure"] == "orientation") as usize;
        }
    }
    eprintln!("{refits} magnetometer refits, {refusals} refused for the mounting");
    assert!(refusals > 0);
    let stored = imucald::app::daemon::load_store(&d.join("cal")).unwrap();
    assert!(
        stored.as_ref().and_then(|s| s.mag.as_ref()).is_none(),
        "{stored:?}"
    );
    let mag = &r.calibration.mag;
    assert_eq!(mag.failure, Some(FitFailure::Orientation), "{mag:?}");
    let detail = mag.detail.as_deref().unwrap();
    assert!(detail.contains("COMPASS_ORIENT = 2"), "{detail}");
}
