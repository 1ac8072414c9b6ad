//! The attitude filter under motion harder than any calibration needs, with truth: the simulator's
//! stress scenarios (`shake`: 10 g at 8 Hz for 20 s; `spin`: to 2000 deg/s; `centrifuge`: 2 g
//! for two minutes, a turn every 4 s; `saturation`: a spin to 2500 deg/s with the gyro's range at
//! 2000 deg/s), each between calm rotation before (the filters settle) and after (they recover).
//! imucald's filter and VQF (Laidig and Seel, "VQF: Highly Accurate IMU Orientation Estimation
//! with Bias Estimation and Magnetic Disturbance Rejection", 2023; PyPI `vqf`, default
//! parameters, 9D) run on the same streams and are scored by BROAD's total error.
//!
//! Per scenario: the total RMSE over the whole run, the largest error during the stress, and the
//! recovery time: from the end of the stress until the error (RMS over 1 s windows) stays below
//! [`RECOVERED_DEG`]. `cargo test --release --test stress -- --nocapture` prints the table.

mod common;

use imucald::attitude::eval::errors;
use imucald::attitude::fusion::{median_dt, FusionConfig, OrientationFilter, WorldFrame};
use imucald::sim::{simulate, Scenario};
use imucald::types::Sample;
use nalgebra::{Quaternion, UnitQuaternion};
use std::process::Command;

/// The error a filter has recovered to, deg: a few times what either filter shows in the calm
/// rotation before the stress (0.1 to 0.7 deg).
const RECOVERED_DEG: f64 = 2.0;

/// The stress phase of the stress scenarios starts here, s (10 s rest, 20 s calm rotation).
const STRESS_START_S: f64 = 30.0;

struct Score {
    rmse_deg: f64,
    peak_deg: f64,
    recovery_s: f64,
}

fn quat(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// BROAD's total error, deg, of each estimate (sensor -> ENU) against the samples' reference.
fn total_errors_deg(samples: &[Sample], est: &[UnitQuaternion<f64>]) -> Vec<(f64, f64)> {
    samples
        .iter()
        .zip(est)
        .filter_map(|(s, q)| Some((s.t_s, errors(q, &quat(s.ref_q?)).0.to_degrees())))
        .collect()
}

fn score(errs: &[(f64, f64)], stress_end_s: f64) -> Score {
    let rmse_deg = (errs.iter().map(|e| e.1 * e.1).sum::<f64>() / errs.len() as f64).sqrt();
    let peak_deg = errs
        .iter()
        .filter(|e| e.0 >= STRESS_START_S && e.0 < stress_end_s)
        .map(|e| e.1)
        .fold(0.0, f64::max);
    // 1 s windows from the stress's end; recovered at the start of the first window from which
    // every later one is below the bound.
    let mut windows: Vec<(f64, f64)> = Vec::new();
    for chunk in errs
        .iter()
        .filter(|e| e.0 >= stress_end_s)
        .collect::<Vec<_>>()
        .chunk_by(|a, b| ((a.0 - stress_end_s) as u64) == ((b.0 - stress_end_s) as u64))
    {
        let ms = chunk.iter().map(|e| e.1 * e.1).sum::<f64>() / chunk.len() as f64;
        windows.push((chunk[0].0, ms.sqrt()));
    }
    let last_bad = windows.iter().rposition(|w| w.1 >= RECOVERED_DEG);
    let recovery_s = match last_bad {
        None => 0.0,
        Some(k) if k + 1 < windows.len() => windows[k + 1].0 - stress_end_s,
        Some(_) => f64::INFINITY,
    };
    Score {
        rmse_deg,
        peak_deg,
        recovery_s,
    }
}

fn imucald_estimates(samples: &[Sample], cfg: &FusionConfig) -> Vec<UnitQuaternion<f64>> {
    let mut f = OrientationFilter::new(FusionConfig {
        world: WorldFrame::Enu,
        ..*cfg
    });
    let dt = median_dt(samples);
    samples
        .iter()
        .map(|s| {
            f.update_sample(s, dt);
            f.quaternion()
        })
        .collect()
}

/// VQF's estimates through `scripts/vqf_peer.py`, or `None` (said) without a Python with `vqf`.
fn vqf_estimates(samples: &[Sample]) -> Option<Vec<UnitQuaternion<f64>>> {
    let Some(py) = common::python("vqf") else {
        eprintln!("scoring imucald alone");
        return None;
    };
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.csv"), dir.path().join("out.csv"));
    imucald::io::samplelog::write_csv(&input, samples).unwrap();
    let out = Command::new(py)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/vqf_peer.py"))
        .args([&input, &output])
        .output()
        .unwrap();
    common::assert_success(&out);
    let text = std::fs::read_to_string(&output).unwrap();
    Some(
        text.lines()
            .skip(1)
            .map(|l| {
                let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
                quat([v[0], v[1], v[2], v[3]])
            })
            .collect(),
    )
}

/// Bounds on imucald alone, about three times the measured value (2026-11-26, seed 1), so the
/// test holds without the Python peer too: (scenario, total RMSE deg, recovery s).
const BOUNDS: [(&str, f64, f64); 4] = [
    // measured 0.11 deg, recovered at once (the error never reaches 2 deg)
    ("shake", 0.33, 3.0),
    // measured 0.40 deg, 0 s
    ("spin", 1.2, 3.0),
    // measured 1.42 deg, 5 s: the tilt noise grows by the linear acceleration itself, so the
    // centripetal force barely tilts the estimate
    ("centrifuge", 4.3, 15.0),
    // measured 0.88 deg, 0 s: clipped readings grow the attitude's uncertainty, and gravity and
    // the field hold the attitude until the gyro reads again
    ("saturation", 2.6, 3.0),
];

/// Runs `name`, prints its row, and returns (imucald, VQF) scores.
fn run(name: &str) -> (Score, Option<Score>) {
    let sc = Scenario::named(name).unwrap();
    let stress_end_s = STRESS_START_S + sc.stress.stress_s;
    let samples = simulate(&sc, 1).samples;
    let ours = score(
        &total_errors_deg(
            &samples,
            &imucald_estimates(&samples, &FusionConfig::default()),
        ),
        stress_end_s,
    );
    // The settings before the tuning on BROAD, which never saw these streams.
    let untuned = score(
        &total_errors_deg(
            &samples,
            &imucald_estimates(&samples, &common::untuned_fusion()),
        ),
        stress_end_s,
    );
    let vqf = vqf_estimates(&samples).map(|q| score(&total_errors_deg(&samples, &q), stress_end_s));
    let fmt = |s: &Score| format!("{:7.2} {:7.1} {:7.1}", s.rmse_deg, s.peak_deg, s.recovery_s);
    eprintln!(
        "{name:<11} {}   {}   {}",
        fmt(&ours),
        vqf.as_ref().map_or("-".into(), fmt),
        fmt(&untuned)
    );
    (ours, vqf)
}

#[test]
fn stress_scenarios_against_vqf() {
    eprintln!(
        "scenario    imucald: RMSE, peak (deg), recovery (s)   VQF: the same   imucald untuned: the same"
    );
    let (mut ours_sum, mut vqf_sum) = (0.0, 0.0);
    for (name, rmse_bound, recovery_bound) in BOUNDS {
        let (ours, vqf) = run(name);
        assert!(
            ours.rmse_deg <= rmse_bound,
            "{name}: imucald RMSE {:.2} deg, bound {rmse_bound}",
            ours.rmse_deg
        );
        assert!(
            ours.recovery_s <= recovery_bound,
            "{name}: imucald recovers in {} s, bound {recovery_bound}",
            ours.recovery_s
        );
        if let Some(v) = vqf {
            // Half a degree: below it both are as good as a real reference can tell.
            assert!(
                ours.rmse_deg <= (1.5 * v.rmse_deg).max(0.5),
                "{name}: imucald {:.2} deg against VQF {:.2}",
                ours.rmse_deg,
                v.rmse_deg
            );
            ours_sum += ours.rmse_deg;
            vqf_sum += v.rmse_deg;
        }
    }
    if vqf_sum > 0.0 {
        // Measured 0.07 (mean RMSE 0.70 deg against 10.62).
        let ratio = ours_sum / vqf_sum;
        eprintln!(
            "mean RMSE imucald {:.2} deg, VQF {:.2}: ratio {ratio:.2}",
            ours_sum / 4.0,
            vqf_sum / 4.0
        );
        assert!(
            ratio <= 0.8,
            "mean RMSE ratio to VQF {ratio:.2}, target 0.8"
        );
    }
}
