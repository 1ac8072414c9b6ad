//! A gyro bias is claimed only from rest: a steady coordinated turn or a climb holds the gyro and
//! the accelerometer as steady as rest does, so the static detector's poses are checked against
//! how fast the attitude turned through them.

mod common;

use imucald::config::Config;
use imucald::report::CalStatus;
use imucald::sim::{simulate, Scenario};

/// The simulated cruise (legs, climbs and coordinated turns at 18-26 deg of bank, never parked)
/// with a hidden gyro bias of [0.03, -0.05, 0.02] rad/s. Before, every steady segment counted as
/// rest and the bias was 0.034 rad/s off on the worst axis (one "pose" turned at 15 deg/s); now
/// the turning segments are left out and the bias comes from the straight legs.
#[test]
fn a_steady_turn_is_not_rest() {
    for seed in 1..=3 {
        let mut sc = Scenario::named("cruise").unwrap();
        sc.truth.gyro.offset = [0.03, -0.05, 0.02];
        let out = simulate(&sc, seed);
        let r = common::replay_samples(&out.samples, &Config::default()).report;
        let g = &r.calibration.gyro;
        let turning = r
            .static_poses
            .iter()
            .filter(|p| p.turn_rate_deg_s.is_some_and(|t| t > 1.0))
            .count();
        // The check must have turns to refuse: measured 24, 8 and 13 turning poses (seeds 1 to 3).
        assert!(turning >= 5, "seed {seed}: {turning} turning poses");
        eprintln!("seed {seed}: {turning} turning poses");
        assert!(
            g.poses_turning >= turning,
            "seed {seed}: {}",
            g.poses_turning
        );
        if g.status == CalStatus::Ok {
            let err = (0..3)
                .map(|k| (g.bias[k] - sc.truth.gyro.offset[k]).abs())
                .fold(0.0, f64::max);
            eprintln!(
                "seed {seed}: bias {:?} from {} poses at rest ({} left out), worst axis {err:.4} rad/s off",
                g.bias, g.poses_used, g.poses_turning
            );
            // Measured 0.0039 rad/s (seed 1; seeds 2 and 3 claim none): the rest check bounds a
            // pose's turn at 0.25 deg/s (0.0044 rad/s).
            assert!(err < 0.012, "seed {seed}: {:?} off by {err}", g.bias);
        } else {
            eprintln!(
                "seed {seed}: no bias claimed ({} poses turning)",
                g.poses_turning
            );
        }
    }
}

/// With no straight leg either (every steady segment a turn), no bias is claimed, and the summary
/// says why.
#[test]
fn a_flight_of_turns_claims_no_bias_and_says_why() {
    let mut sc = Scenario::named("cruise").unwrap();
    sc.truth.gyro.offset = [0.03, -0.05, 0.02];
    let out = simulate(&sc, 1);
    let r0 = common::replay_samples(&out.samples, &Config::default()).report;
    // Keep only the samples of the turning poses (and what lies between poses).
    let rest: Vec<(f64, f64)> = r0
        .static_poses
        .iter()
        .filter(|p| p.turn_rate_deg_s.is_some_and(|t| t <= 1.0))
        .map(|p| (p.t_start - 0.5, p.t_end + 0.5))
        .collect();
    let turns: Vec<_> = out
        .samples
        .iter()
        .filter(|s| !rest.iter().any(|(a, b)| s.t_s >= *a && s.t_s <= *b))
        .cloned()
        .collect();
    let r = common::replay_samples(&turns, &Config::default()).report;
    let g = &r.calibration.gyro;
    assert_eq!(
        g.status,
        CalStatus::Failed,
        "{:?} from {}",
        g.bias,
        g.poses_used
    );
    assert!(g.poses_turning >= 10, "{}", g.poses_turning);
    let text = imucald::app::replay::summary(&r);
    assert!(
        text.contains("gyro : no bias claimed: no rest in this log"),
        "{text}"
    );
}
