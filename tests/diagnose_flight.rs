//! `diagnose` on simulated ordinary flights (the `cruise` scenario: legs and banked turns, attitude
//! at 10 Hz with 0.5 deg of noise, position, hidden hard and soft iron, a current of 0.5-60 A leg
//! by leg): with an attitude and the earth field the base model starts from the vector
//! calibration and the moving windows carry the field's direction, so the current's field is
//! named although the sphere fit has no coverage.

mod common;

use imucald::config::Config;
use imucald::diagnose::{diagnose, DiagnoseOptions, DiagnosisReport, Effect};
use imucald::sim::{simulate, MotorDriver, Scenario};

const DATE: &str = "[place]\nlatitude_deg = 47.3769\nlongitude_deg = 8.5417\naltitude_m = 600.0\ndate = \"2026-06-01\"\n";

fn flight(k: Option<[f64; 3]>, seed: u64) -> DiagnosisReport {
    let mut sc = Scenario::named("cruise").unwrap();
    sc.effects.motor_interference = k;
    sc.effects.motor_driver = MotorDriver::Current;
    let out = simulate(&sc, seed);
    let cfg = Config::from_toml_str(DATE).unwrap();
    let r = diagnose(&out.samples, &cfg, &DiagnoseOptions::default());
    eprintln!("seed {seed}:\n{}", imucald::diagnose::summary_table(&r));
    r
}

#[test]
fn current_interference_is_named_on_an_ordinary_flight_and_the_gap_shrinks() {
    let k_true = [0.3, -0.2, 0.45];
    let (mut worst_rel, mut least_shrink) = (0.0f64, f64::INFINITY);
    for seed in 1..=3 {
        let r = flight(Some(k_true), seed);
        assert_eq!(
            r.found.first(),
            Some(&Effect::MotorInterference),
            "seed {seed}"
        );
        let est = &r.effects["motor_interference"];
        for (j, axis) in ["k_x", "k_y", "k_z"].iter().enumerate() {
            let rel = (est[*axis].value - k_true[j]).abs() / k_true[j].abs();
            worst_rel = worst_rel.max(rel);
        }
        least_shrink = least_shrink.min(r.rms_before / r.rms_after);
    }
    eprintln!("worst relative error of k {worst_rel:.5}; least held-out shrink {least_shrink:.1}x");
    // Measured: k within 0.19 % over seeds 1-3 (seed 1: 0.29988, -0.20002, 0.45003 uT/A); the
    // held-out RMS shrinks 17.1x to 20.5x (seed 1: 19.4 -> 1.06 expected-noise units), with
    // motor_interference then cross_axis (the hidden soft iron's off-diagonal terms, which the
    // diag6 base leaves out).
    assert!(worst_rel < 0.006, "{worst_rel}");
    assert!(least_shrink > 6.0, "{least_shrink}");
}

#[test]
fn without_interference_the_current_is_not_blamed() {
    // Measured: cross_axis alone is named (held-out RMS 4.82 -> 1.09).
    let r = flight(None, 1);
    assert!(
        !r.found.contains(&Effect::MotorInterference),
        "{:?}",
        r.found
    );
}

/// The same flight as a `.tlog` written by pymavlink (HIGHRES_IMU, ATTITUDE at the reference's
/// rate, GPS_RAW_INT and SYS_STATUS current at 5 Hz, in its own units and frame conversions):
/// read as `imucald diagnose` reads a log, the current's field is named from the messages alone.
#[test]
fn current_interference_is_named_from_a_pymavlink_flight_tlog() {
    let k_true = [0.3, -0.2, 0.45];
    let mut sc = Scenario::named("cruise").unwrap();
    sc.effects.motor_interference = Some(k_true);
    sc.effects.motor_driver = MotorDriver::Current;
    let out = simulate(&sc, 1);
    let dir = tempfile::tempdir().unwrap();
    let Some(tlog) = common::pymavlink_flight_tlog(&out.samples, dir.path()) else {
        return;
    };
    let cfg = Config::default();
    let log = imucald::io::sources::read_log(&tlog, None, &cfg.input).unwrap();
    let r = diagnose(&log.samples, &cfg, &DiagnoseOptions::default());
    eprintln!("{}", imucald::diagnose::summary_table(&r));
    assert_eq!(
        r.found.first(),
        Some(&Effect::MotorInterference),
        "{}",
        r.outcome()
    );
    let est = &r.effects["motor_interference"];
    let mut worst: f64 = 0.0;
    for (j, axis) in ["k_x", "k_y", "k_z"].iter().enumerate() {
        worst = worst.max((est[*axis].value - k_true[j]).abs() / k_true[j].abs());
    }
    eprintln!(
        "pymavlink tlog: worst relative error of k {worst:.4}; {}",
        r.outcome()
    );
    // Measured: k within 0.19 % (0.2967, -0.2013, 0.4501 uT/A), then cross_axis; held-out RMS
    // 19.4 -> 7.3 noise units, the last round `unexplained` (mag_norm 26.7x its noise: the CSV's
    // 0.15 uT was the same, so the messages' units and rates leave structure; not broken down).
    assert!(worst < 0.006, "{worst}");
}

/// The current's field ends in the flight controllers' per-ampere compensation: ArduPilot
/// COMPASS_MOT = -(M k) x 10 mGauss/A with COMPASS_MOTCT 2, PX4 CAL_MAG0_xCOMP = -k x 10 G/kA with
/// CAL_MAG_COMP_TYP 2 (M the truth's soft-iron matrix at unit determinant, k the hidden field
/// per ampere).
#[test]
fn current_interference_exports_the_per_ampere_compensation() {
    let k_true = [0.3, -0.2, 0.45];
    let mut sc = Scenario::named("cruise").unwrap();
    sc.effects.motor_interference = Some(k_true);
    sc.effects.motor_driver = MotorDriver::Current;
    // The export's matrix has unit determinant (the field's scale is the calibration's radius).
    let m0 = nalgebra::Matrix3::from_fn(|r, c| sc.truth.mag.matrix[r][c]);
    let m0 = m0 / m0.determinant().cbrt();
    let m: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m0[(r, c)]));
    let out = simulate(&sc, 2);
    let cfg = Config::from_toml_str(DATE).unwrap();
    let r = diagnose(&out.samples, &cfg, &DiagnoseOptions::default());
    let fx = imucald::diagnose::fix::fixes(&r);
    let f = fx
        .iter()
        .find(|f| f.effect == Effect::MotorInterference)
        .expect("motor_interference named");
    let get = |list: &[(String, f64)], n: &str| {
        list.iter().find(|(x, _)| x == n).map(|(_, v)| *v).unwrap()
    };
    assert_eq!(get(&f.ardupilot, "COMPASS_MOTCT"), 2.0);
    assert_eq!(get(&f.px4, "CAL_MAG_COMP_TYP"), 2.0);
    let (mut e_ap, mut n_ap, mut e_px, mut n_px) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for (i, axis) in ["X", "Y", "Z"].iter().enumerate() {
        let truth_ap = -(0..3).map(|c| m[i][c] * k_true[c]).sum::<f64>() * 10.0;
        let got_ap = get(&f.ardupilot, &format!("COMPASS_MOT_{axis}"));
        let truth_px = -k_true[i] * 10.0;
        let got_px = get(&f.px4, &format!("CAL_MAG0_{axis}COMP"));
        eprintln!("{axis}: COMPASS_MOT {got_ap:.3} (truth {truth_ap:.3}) mGauss/A, CAL_MAG0_COMP {got_px:.3} (truth {truth_px:.3}) G/kA");
        e_ap += (got_ap - truth_ap).powi(2);
        n_ap += truth_ap.powi(2);
        e_px += (got_px - truth_px).powi(2);
        n_px += truth_px.powi(2);
    }
    let (rel_ap, rel_px) = ((e_ap / n_ap).sqrt(), (e_px / n_px).sqrt());
    eprintln!("relative error: ArduPilot {rel_ap:.4}, PX4 {rel_px:.4}");
    // Measured: see docs/diagnose.md.
    assert!(rel_ap < 0.05, "{rel_ap}");
    assert!(rel_px < 0.02, "{rel_px}");
}
