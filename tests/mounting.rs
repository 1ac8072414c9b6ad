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
