//! The vector magnetometer calibration through `replay` on simulated ordinary flights (the `cruise`
//! scenario: legs and banked turns, attitude at 10 Hz with 0.5 deg of noise, the WMM2025 field at
//! the place and date, hidden hard and soft iron), against the sphere fit on the same data.

mod common;

use imucald::calib::magmethod::{MagMethod, MethodChoice};
use imucald::config::Config;
use imucald::report::SensorCalibration;
use imucald::sim::{simulate, Scenario};
use imucald::types::Vec3;

fn dist(a: &Vec3, b: &Vec3) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Replay the scenario's samples (written as CSV) with the configuration `toml`.
fn replay_sim(
    sc: &Scenario,
    seed: u64,
    toml: &str,
    strip_position: bool,
) -> imucald::report::Report {
    let mut out = simulate(sc, seed);
    if strip_position {
        for s in out.samples.iter_mut() {
            s.position = None;
        }
    }
    common::replay_samples(&out.samples, &Config::from_toml_str(toml).unwrap()).report
}

/// The method chosen for `m`, checked to be the vector method with the field at the log's position.
#[track_caller]
fn vector_from_the_logs_position(m: &SensorCalibration) -> &MethodChoice {
    let choice = m.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    assert!(
        choice.method_reason.contains("the log's position"),
        "{}",
        choice.method_reason
    );
    choice
}

/// The date of the simulation, so the field is the one the vehicle flew in.
const DATE: &str = "[place]\nlatitude_deg = 47.3769\nlongitude_deg = 8.5417\naltitude_m = 600.0\ndate = \"2026-06-01\"\n";

#[test]
fn cruise_offset_within_1_ut_by_the_vector_method_the_sphere_fails_or_is_far_worse() {
    let sc = Scenario::named("cruise").unwrap();
    let truth = sc.truth.mag.offset;
    let r = replay_sim(&sc, 1, DATE, false);
    let m = &r.calibration.mag;
    let choice = vector_from_the_logs_position(m);
    let v = choice.vector.as_ref().unwrap();
    assert!(
        v.offset_identifiable && v.unidentified().count() == 0,
        "{v:?}"
    );
    // Measured: 0.43 uT off ([12.12, -25.18, 40.37] against [12, -25, 40]), 1-sigma 0.07-0.13 uT.
    let err = dist(&m.offset, &truth);
    assert!(err < 1.0, "vector offset {:?} is {err} uT off", m.offset);
    assert!(
        v.offset_sigma_ut.iter().all(|s| *s < 0.4),
        "{:?}",
        v.offset_sigma_ut
    );
    assert_eq!(m.status, imucald::report::CalStatus::Ok);
    // The sphere fit on the same data fails: 16 of 100 coverage regions (needs 25).
    assert!(
        choice
            .method_reason
            .contains("the sphere fit failed (coverage)"),
        "{}",
        choice.method_reason
    );
    assert_eq!(choice.sphere_offset, None);

    // With the coverage gate off and the sphere model forced, it passes but is far off:
    // measured 4.42 uT ([13.43, -26.90, 36.27]), ten times the vector fit's error.
    let relaxed =
        format!("{DATE}[fit]\nmag_model = \"sphere\"\n[accept.mag]\nmin_filled_regions = 1\n");
    let r = replay_sim(&sc, 1, &relaxed, false);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Vector);
    let sphere = choice.sphere_offset.expect("the relaxed sphere fit passes");
    let sphere_err = dist(&sphere, &truth);
    assert!(
        sphere_err > 1.5 && sphere_err > 3.0 * err,
        "sphere {sphere_err} vector {err}"
    );
}

/// Without a position or a place the earth field is fitted with the calibration (as ArduPilot's
/// MAGFit fits the EKF's field). On the ordinary cruise (banks of 18-26 deg) one half of the
/// flight alone does not determine the offset with the field free: the sphere stays, and the
/// reason says so. With steep banks (45-70 deg) the offset is found near its truth, each half of
/// the flight giving the same, and the report names the field as fitted with its inclination.
#[test]
fn without_a_position_or_place_the_field_is_fitted_or_the_sphere_stays_with_the_reason() {
    let mut sc = Scenario::named("cruise").unwrap();
    let r = replay_sim(&sc, 2, "", true);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Sphere);
    assert!(
        choice.method_reason.contains("no position")
            && choice
                .method_reason
                .contains("blocks alone do not determine the offset"),
        "{}",
        choice.method_reason
    );
    sc.cruise.bank_deg = [45.0, 70.0];
    let r = replay_sim(&sc, 2, "", true);
    let m = &r.calibration.mag;
    let choice = m.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    assert!(
        choice.method_reason.contains("no position")
            && choice.method_reason.contains("field fitted"),
        "{}",
        choice.method_reason
    );
    let f = choice.earth_field.as_ref().unwrap();
    assert_eq!(f.model, imucald::attitude::FieldModel::Fitted);
    let truth_field = imucald::attitude::earth_field(&sc.place_dated().unwrap()).unwrap();
    let err = dist(&m.offset, &sc.truth.mag.offset);
    eprintln!(
        "fitted field: offset error {err:.3} uT, inclination {:.2} deg (model {:.2})",
        f.inclination_deg, truth_field.inclination_deg
    );
    // Measured 0.11 uT and 63.45 deg against the model's 63.51.
    assert!(
        err < 0.35,
        "offset {:?} against {:?}",
        m.offset,
        sc.truth.mag.offset
    );
    assert!((f.inclination_deg - truth_field.inclination_deg).abs() < 0.2);
    // Without a reference attitude at all.
    let mut tumble = Scenario::named("tumble").unwrap();
    tumble.duration_s = Some(20.0);
    let r = replay_sim(&tumble, 2, DATE, false);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Sphere);
    assert!(
        choice.method_reason.contains("no attitude"),
        "{}",
        choice.method_reason
    );
}

#[test]
fn nearly_level_turns_leave_the_offset_undetermined_and_say_why() {
    // Banks of 1-2 deg (plus the 1.5 deg wobble): the body-z field hardly changes.
    let mut sc = Scenario::named("cruise").unwrap();
    sc.cruise.bank_deg = [1.0, 2.0];
    let r = replay_sim(&sc, 3, DATE, false);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Sphere, "{}", choice.method_reason);
    let v = choice.vector.as_ref().unwrap();
    assert!(!v.offset_identifiable);
    assert!(!v.soft_iron_fitted[2], "{:?}", v.soft_iron_fitted);
    assert!(
        choice.method_reason.contains("do not determine the offset")
            && choice.method_reason.contains("soft iron (body-z field)"),
        "{}",
        choice.method_reason
    );
}

#[test]
fn current_interference_fitted_jointly_within_a_percent() {
    // 0.5-60 A leg by leg, 0.3 / -0.2 / 0.45 uT per A added to the raw field.
    let mut sc = Scenario::named("cruise").unwrap();
    let k_true = [0.3, -0.2, 0.45];
    sc.effects.motor_interference = Some(k_true);
    sc.effects.motor_driver = imucald::sim::MotorDriver::Current;
    let r = replay_sim(&sc, 1, DATE, false);
    let m = &r.calibration.mag;
    let choice = m.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    let v = choice.vector.as_ref().unwrap();
    assert_eq!(v.current_identifiable, Some(true));
    let k = v.current_ut_per_a.unwrap();
    // Measured: [0.2998, -0.2001, 0.4491], at most 0.21 % off (seeds 2 and 3: 0.28 %, 0.39 %).
    for j in 0..3 {
        let rel = (k[j] - k_true[j]).abs() / k_true[j].abs();
        assert!(rel < 0.007, "k {k:?}");
    }
    // The offset is the one without current: measured 0.43 uT off.
    assert!(
        dist(&m.offset, &sc.truth.mag.offset) < 1.0,
        "{:?}",
        m.offset
    );
    // Exported as ArduPilot COMPASS_MOT (after the soft iron, mGauss/A) and PX4 CAL_MAG0_?COMP
    // (before the offset, G/kA), each by its stack's sign: the truth's would be -(M k) x 10 and -k x 10.
    // The calibration's own current term is the model ladder's, fitted with its offset and
    // matrix: measured [0.2996, -0.2001, 0.4495], at most 0.14 % off.
    assert!(choice.rung.is_some(), "{}", choice.method_reason);
    let k = m.motor_ut_per_a().expect("the calibration's current term");
    for j in 0..3 {
        let rel = (k[j] - k_true[j]).abs() / k_true[j].abs();
        assert!(rel < 0.007, "k {k:?}");
    }
    let ap = imucald::calib::export::ardupilot_motor(&k, &m.matrix, 0);
    let px = imucald::calib::export::px4_motor(&k, 0);
    for (j, axis) in ["X", "Y", "Z"].iter().enumerate() {
        let mk: f64 = (0..3).map(|c| m.matrix[j][c] * k_true[c]).sum();
        let got = |p: &[(String, f64)], n: String| p.iter().find(|(q, _)| *q == n).unwrap().1;
        let a = got(&ap, format!("COMPASS_MOT_{axis}"));
        assert!(
            (a + 10.0 * mk).abs() < 0.01 * (10.0 * mk).abs(),
            "COMPASS_MOT_{axis} {a}"
        );
        let p = got(&px, format!("CAL_MAG0_{axis}COMP"));
        assert!(
            (p + 10.0 * k_true[j]).abs() < 0.01 * (10.0 * k_true[j]).abs(),
            "{axis}COMP {p}"
        );
    }
}

/// PX4 log of a short flight (AUAV-X21): `vehicle_attitude` at 100 Hz, yaw only between -48 and
/// -20 deg, roll within +-22 deg, pitch within +-9 deg; no GPS. The vector fit says what that
/// cannot determine, and keeps the sphere fit.
#[test]
fn px4_flight_log_names_what_its_narrow_yaw_range_cannot_determine() {
    let Some(data) = common::testdata::shared_data() else {
        return;
    };
    let path = data.join("flightlogs/px4_auav_x21.ulg");
    // The log has no position: a northern mid-latitude place whose field (48.4 uT) matches the
    // strength of the log's own calibrated field (48.2 uT).
    let cfg = Config::from_toml_str(DATE).unwrap();
    let out = common::replay_log(&path, &cfg);
    let m = &out.report.calibration.mag;
    let choice = m.method.as_ref().unwrap();
    // The full vector fit does not determine the offset; the model ladder, started from the
    // vehicle's own CAL_MAG0 and chosen on held-out blocks, calibrates it.
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    assert!(choice.rung.is_some(), "{}", choice.method_reason);
    assert!(
        choice
            .method_reason
            .contains("started from the vehicle's own calibration"),
        "{}",
        choice.method_reason
    );
    let v = choice.vector.as_ref().unwrap();
    // Measured: one direction varied by 0.2 % of the field (+0.70 offset -0.63 soft iron (body-z)
    // -0.29 (body-x) -0.16 (body-y)); the offset rests on the soft iron for up to 2.4 uT.
    let un: Vec<_> = v.unidentified().collect();
    assert_eq!(un.len(), 1, "{:?}", v.directions);
    assert!(un[0].spread < 0.006, "{}", un[0].spread);
    assert!(
        un[0].description.contains("offset")
            && un[0].description.contains("soft iron (body-z field)")
    );
    assert!(!v.offset_identifiable && v.offset_assumption_ut > 1.0);
    // Under that assumption (soft iron held at identity along that direction) the offset is near
    // the log's CAL_MAG0, within what rests on the assumption: measured [4.68, -22.24, -14.68]
    // against [2.82, -20.02, -13.69] uT, 3.06 uT apart, with 2.4 uT of it assumed (holding the
    // forward regression's soft iron instead of the reverse's gave 0.95 uT).
    let onboard = &out.report.onboard.as_ref().unwrap().mag[0];
    let d = dist(&v.offset_ut, &onboard.offset);
    assert!(
        d < v.offset_assumption_ut + 1.5,
        "{:?} against {:?}",
        v.offset_ut,
        onboard.offset
    );
    // The ladder's calibration is better than the vehicle's own held out (measured: the scale
    // rung, norm 1.38 against 1.55 %, dip 0.79 against 0.89 deg). The log has no position: the
    // configured place is only a stand-in of the right strength, and the common scale (1.2)
    // takes up the difference of its horizontal field, moving the offset by 12.5 uT from
    // CAL_MAG0. The offset is within ArduPilot's bounds, and the distance is reported.
    let d = dist(&m.offset, &onboard.offset);
    let q = &out.report.quality[0];
    println!(
        "ladder: {} rung, offset {:?}, {d:.2} uT from CAL_MAG0; {}",
        choice.rung.unwrap(),
        m.offset,
        q.verdict
    );
    assert_eq!(
        q.verdict_kind,
        Some(imucald::report::Verdict::Better),
        "{}",
        q.verdict
    );
}

/// The live service learns the vector calibration continuously from the stream a flight
/// controller sends: HIGHRES_IMU with ATTITUDE_QUATERNION (10 Hz, 0.5 deg noise),
/// GLOBAL_POSITION_INT and BATTERY_STATUS (5 Hz), no `[place]`. The sphere fit fails for coverage
/// all flight long; the vector fit is installed, written and reported as `"method": "vector"`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_service_learns_the_vector_calibration_in_flight() {
    let sc = Scenario::named("cruise").unwrap();
    let sim = simulate(&sc, 1);
    let dir = tempfile::tempdir().unwrap();
    let (port, cfg) = common::udpin_config(dir.path());
    let lines = common::stream_flight(&sim.samples, port, cfg).await;
    let store = imucald::app::daemon::load_store(&dir.path().join("cal"))
        .unwrap()
        .expect("a calibration stored");
    let m = store.mag.expect("a magnetometer calibration");
    let choice = m.method.as_ref().expect("the method is recorded");
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    assert!(
        choice.method_reason.contains("learnt live") && choice.method_reason.contains("GPS"),
        "{}",
        choice.method_reason
    );
    let err = dist(&m.offset, &sc.truth.mag.offset);
    println!(
        "live vector offset {:?} against {:?}: {err:.3} uT; {}",
        m.offset, sc.truth.mag.offset, choice.method_reason
    );
    // Measured: 0.41 uT ([12.10, -25.19, 40.35]; the replay of the same flight: 0.43 uT). The
    // bound is the figure promised for ordinary flights.
    assert!(err < 1.0, "live vector offset {err} uT off");
    // The JSON calibration lines say the method too.
    assert!(
        lines
            .iter()
            .any(|l| l.contains("\"type\":\"calibration\"") && l.contains("\"vector\"")),
        "no calibration line with the vector method among {} lines",
        lines.len()
    );
}

/// The same flight recorded by another tool: pymavlink writes the `.tlog` a ground station keeps
/// of an ArduPilot vehicle (ATTITUDE as Euler angles, GPS_RAW_INT, SYS_STATUS current, HIGHRES_IMU;
/// `tests/interop/pymavlink_flight_tlog.py`, its own frame conversion). `replay` takes the
/// attitude, position and current from those messages and chooses the vector method.
#[test]
fn replay_of_a_pymavlink_flight_tlog_takes_attitude_position_and_current_from_its_messages() {
    let sc = Scenario::named("cruise").unwrap();
    let out = simulate(&sc, 1);
    let dir = tempfile::tempdir().unwrap();
    let Some(tlog) = common::pymavlink_flight_tlog(&out.samples, dir.path()) else {
        return;
    };
    let r = common::replay_log(&tlog, &Config::default()).report;
    let m = &r.calibration.mag;
    let choice = vector_from_the_logs_position(m);
    let err = dist(&m.offset, &sc.truth.mag.offset);
    println!(
        "pymavlink tlog: vector offset {:?}, {err:.3} uT off; {}",
        m.offset, choice.method_reason
    );
    // Measured: 0.419 uT from 3000 attitudes (the CSV of the same flight: 0.43 uT). The bound is
    // the figure promised for ordinary flights.
    assert!(err < 1.0, "vector offset {err} uT off");
}

/// The earth field of the day the log was recorded: a cruise flown in 2015 (IGRF-13, the WMM in use
/// starts in 2020) and one in 2025 (WMM), each written as a `.tlog` whose record clock is that
/// day's. The replay, with no date configured, takes the field of the log's day, says so in
/// `calibration.mag.earth_field`, and the vector fit finds the hidden offset with it.
#[test]
fn the_field_is_the_one_of_the_day_the_log_was_recorded() {
    use imucald::attitude::FieldModel;
    let dir = tempfile::tempdir().unwrap();
    for (date, epoch_us, model) in [
        ("2015-06-01", 1_433_160_000_000_000u64, FieldModel::Igrf13),
        ("2025-06-01", 1_748_779_200_000_000u64, FieldModel::Wmm),
    ] {
        let mut sc = Scenario::named("cruise").unwrap();
        let place = sc.place.clone().expect("the cruise flies at a place");
        sc.place = Some(imucald::attitude::Place {
            date: Some(date.into()),
            ..place
        });
        let out = simulate(&sc, 3);
        let log = dir.path().join(format!("{date}.tlog"));
        imucald::io::samplelog::write_tlog(
            &log,
            &out.samples,
            &imucald::io::samplelog::TlogWriteOptions {
                epoch_us,
                ..Default::default()
            },
        )
        .unwrap();
        let r = common::replay_log(&log, &Config::default()).report;
        let m = &r.calibration.mag;
        let choice = vector_from_the_logs_position(m);
        let f = choice
            .earth_field
            .as_ref()
            .expect("the field used is reported");
        assert_eq!(f.date, date);
        assert_eq!(f.date_source, "record_clock");
        assert_eq!(f.model, model, "{date}");
        assert!(
            choice.method_reason.contains(date),
            "{}",
            choice.method_reason
        );
        let err = dist(&m.offset, &sc.truth.mag.offset);
        eprintln!(
            "{date}: {:?} {:.1} uT, offset error {err:.3} uT",
            f.model, f.total_ut
        );
        // Measured 0.20 uT in both years.
        assert!(
            err < 0.6,
            "{date}: offset {:?} against {:?}",
            m.offset,
            sc.truth.mag.offset
        );
    }
}
