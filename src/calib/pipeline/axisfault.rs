//! A dead, stuck or saturated axis, found in a sensor's readings before any fit is tried.

use crate::types::Vec3;

/// A dead, stuck or saturated axis, with the reason; `None` when every axis looks alive. The points
/// are taken in their order (time, or neighbouring directions once binned); a step is two
/// successive points.
///
/// - Dead: one value in every point while the others change.
/// - Stuck part of the time: one value, inside the axis's range, in a fifth of the points, and
///   the axis stays on it across at least [`STUCK_MIN_HELD_STEPS`] and [`STUCK_MIN_HOLD_SHARE`] of
///   the steps from it over which the vehicle turns ([`held_while_turning`]). A still sensor read
///   in whole counts repeats its readings as well, but not while it turns.
/// - Saturated: at least 5 points and 3% of them at exactly the axis's lowest or highest value,
///   piled up there ([`CLIP_MIN_PILE_RATIO`]) on an axis that spans more than [`TURN_MIN_QUANTA`]
///   of its quantisation steps: the reading is clipped at the sensor's range, not the end of a
///   still sensor's noise.
pub fn axis_fault(points: &[Vec3]) -> Option<String> {
    let n = points.len();
    if n < 7 {
        return None;
    }
    const AXIS: [&str; 3] = ["x", "y", "z"];
    let mut ranges = [(f64::INFINITY, f64::NEG_INFINITY); 3];
    for p in points {
        for (r, v) in ranges.iter_mut().zip(p) {
            *r = (r.0.min(*v), r.1.max(*v));
        }
    }
    let widest = ranges.iter().map(|(lo, hi)| hi - lo).fold(0.0, f64::max);
    for (k, (lo, hi)) in ranges.iter().enumerate() {
        if widest > 0.0 && hi - lo <= 1e-6 * widest {
            return Some(format!(
                "axis {} reads {lo} in all {n} points while the others change: the axis is stuck or dead",
                AXIS[k]
            ));
        }
    }
    for k in 0..3 {
        if let Some((val, best)) = frequent_value(points.iter().map(|p| p[k]), 0.2) {
            if best < 5 || val <= ranges[k].0 || val >= ranges[k].1 {
                continue;
            }
            let (held, turning) = held_while_turning(points, k, val, widest);
            if held >= STUCK_MIN_HELD_STEPS && held as f64 >= STUCK_MIN_HOLD_SHARE * turning as f64
            {
                return Some(format!(
                    "axis {} reads exactly {val} in {best} of {n} points and stays on it across {held} of \
                     the {turning} steps from it over which the vehicle turns (another axis moves by more \
                     than {TURN_MIN_QUANTA} of its quantisation steps): the axis is stuck part of the time",
                    AXIS[k]
                ));
            }
        }
    }
    let need = (0.03 * n as f64).ceil().max(5.0) as usize;
    // Points at each axis's low and high extreme, counted in one pass.
    let mut at_rail = [[0usize; 2]; 3];
    for p in points {
        for k in 0..3 {
            at_rail[k][0] += (p[k] == ranges[k].0) as usize;
            at_rail[k][1] += (p[k] == ranges[k].1) as usize;
        }
    }
    let quanta = smallest_steps(points.windows(2), widest);
    for (k, (lo, hi)) in ranges.iter().enumerate() {
        if hi - lo <= TURN_MIN_QUANTA * quanta[k] {
            continue; // a still axis: its ends are its noise's
        }
        for (side, rail) in [*lo, *hi].into_iter().enumerate() {
            let at = at_rail[k][side];
            if at < need {
                continue;
            }
            let inside = count_next_inside(points, k, rail, side == 1);
            if at as f64 > CLIP_MIN_PILE_RATIO * inside as f64 {
                return Some(format!(
                    "axis {} reads exactly {rail} in {at} of {n} points ({inside} at the next value \
                     inside): saturated (the field or acceleration exceeds the sensor's range, or the \
                     reading is clipped)",
                    AXIS[k]
                ));
            }
        }
    }
    None
}

/// Quantisation steps (quanta: the smallest nonzero change an axis shows between two successive
/// readings) by which another axis must move over a step for the vehicle to count as turning over
/// it. Rounding alone moves a still reading by one quantum, and a compass's rest noise, about a
/// count rms, by a few; more than 4 quanta is, for a 50 uT field read in ArduPilot's 0.1 uT
/// (milligauss) steps, a turn of more than half a degree (8.7 quanta per degree).
const TURN_MIN_QUANTA: f64 = 4.0;

/// Share of the turning steps from a value that an axis must stay on it across to be stuck. A
/// stuck axis stays on its value over every turning step of a stuck stretch but the one that ends
/// it (3 of 4 for a stretch of four steps, more for longer ones). A working axis leaves the value
/// whenever its noise takes it a quantum away: about as often as it reads other values. Measured:
/// 0.40 for the x axis of an ArduSub ROV's SCALED_IMU2 at rest (one value in 156 of 625 readings,
/// its other axes' noise moving them by up to 30 quanta between readings, so that most steps count
/// as turning).
const STUCK_MIN_HOLD_SHARE: f64 = 0.75;

/// Fewest turning steps a stuck axis must stay on its value across: five successive points on one
/// value while the vehicle turns.
const STUCK_MIN_HELD_STEPS: usize = 4;

/// How many times the count at the next value inside a rail the rail's own count must exceed for
/// the axis to be clipped there. Clipping folds every reading beyond the rail onto it: with the
/// readings spread about evenly near the rail, the rail holds the count of one quantum times the
/// quanta by which the field went beyond it, so more than twice the next value's count is a field
/// more than two quanta beyond the sensor's range (a clip a fit cannot absorb as noise). The end
/// of a still sensor's noise thins out instead (an ArduSub ROV's compass at rest: 24 readings on
/// its lowest x value, 23 on the next).
const CLIP_MIN_PILE_RATIO: f64 = 2.0;

/// Over the steps (two successive points) that start with axis `k` at `val`: how many of those
/// over which the vehicle turns the axis stays on `val` across, and how many turn. A step turns
/// when another axis moves by more than [`TURN_MIN_QUANTA`] of its quantisation step, the smallest
/// nonzero change it shows over these steps ([`smallest_steps`]).
fn held_while_turning(points: &[Vec3], k: usize, val: f64, widest: f64) -> (usize, usize) {
    let from_val = || points.windows(2).filter(|w| w[0][k] == val);
    let quanta = smallest_steps(from_val(), widest);
    let min_move = quanta.map(|q| (TURN_MIN_QUANTA * q).max(1e-6 * widest));
    let (mut held, mut turning) = (0, 0);
    for w in from_val() {
        let turns = (0..3)
            .filter(|&j| j != k)
            .any(|j| (w[1][j] - w[0][j]).abs() > min_move[j]);
        if turns {
            turning += 1;
            held += (w[1][k] == val) as usize;
        }
    }
    (held, turning)
}

/// Each axis's quantisation step as the steps (pairs of successive points) show it: the smallest
/// change over a step larger than `1e-6 * widest` (smaller ones are a conversion's rounding, not a
/// count); 0 for an axis with none.
fn smallest_steps<'a>(steps: impl Iterator<Item = &'a [Vec3]>, widest: f64) -> [f64; 3] {
    let mut q = [f64::INFINITY; 3];
    for w in steps {
        for (j, q) in q.iter_mut().enumerate() {
            let d = (w[1][j] - w[0][j]).abs();
            if d > 1e-6 * widest {
                *q = q.min(d);
            }
        }
    }
    q.map(|q| if q.is_finite() { q } else { 0.0 })
}

/// How many points have axis `k` at the value next to `rail` on its inner side (above it for the
/// low rail, below it for the high one).
fn count_next_inside(points: &[Vec3], k: usize, rail: f64, high: bool) -> usize {
    let inner = points
        .iter()
        .map(|p| p[k])
        .filter(|&v| if high { v < rail } else { v > rail });
    let next = if high {
        inner.fold(f64::NEG_INFINITY, f64::max)
    } else {
        inner.fold(f64::INFINITY, f64::min)
    };
    points.iter().filter(|p| p[k] == next).count()
}

/// The value that occurs most often (the smallest of equally frequent ones) and its count, when it
/// occurs in at least `min_share` of the values (`min_share` > 1/6). O(n): the Misra-Gries summary
/// with five counters keeps every value more frequent than n/6, then one pass counts them exactly.
fn frequent_value(
    values: impl Iterator<Item = f64> + Clone,
    min_share: f64,
) -> Option<(f64, usize)> {
    let mut cand: [(f64, usize); 5] = [(f64::NAN, 0); 5];
    let mut n = 0usize;
    for v in values.clone() {
        n += 1;
        if let Some(c) = cand.iter_mut().find(|c| c.1 > 0 && c.0 == v) {
            c.1 += 1;
        } else if let Some(c) = cand.iter_mut().find(|c| c.1 == 0) {
            *c = (v, 1);
        } else {
            for c in cand.iter_mut() {
                c.1 -= 1;
            }
        }
    }
    let mut counts = [0usize; 5];
    for v in values {
        for (i, c) in cand.iter().enumerate() {
            if c.1 > 0 && c.0 == v {
                counts[i] += 1;
            }
        }
    }
    let mut best: Option<(f64, usize)> = None;
    for (i, c) in cand.iter().enumerate() {
        if c.1 == 0 {
            continue;
        }
        let better = match best {
            None => true,
            Some((bv, bc)) => counts[i] > bc || (counts[i] == bc && c.0 < bv),
        };
        if better {
            best = Some((c.0, counts[i]));
        }
    }
    best.filter(|&(_, c)| c as f64 >= min_share * n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sensor resting for a third of a run (a vehicle on the ground streamed at a low rate)
    /// repeats one y reading exactly while x and z jitter by a count: not a stuck axis. The same
    /// y value held while x and z sweep is one.
    #[test]
    fn axis_fault_tells_a_resting_sensor_from_a_stuck_axis() {
        let sweep: Vec<Vec3> = (0..200)
            .map(|i| {
                let (a, b) = (i as f64 * 0.37, i as f64 * 0.11);
                [
                    40.0 * a.cos() * b.cos(),
                    40.0 * a.sin() * b.cos(),
                    40.0 * b.sin(),
                ]
            })
            .collect();
        let mut resting = sweep.clone();
        resting.extend((0..100).map(|i| {
            [
                -1.4 + 0.1 * (i % 2) as f64,
                -17.0,
                28.8 - 0.1 * (i % 3) as f64,
            ]
        }));
        assert_eq!(axis_fault(&resting), None);
        let mut stuck = sweep.clone();
        stuck.extend(sweep.iter().take(100).map(|p| [p[0], -17.0, p[2]]));
        let why = axis_fault(&stuck).expect("a stuck axis");
        assert!(
            why.contains("axis y reads exactly -17 in 100 of 300"),
            "{why}"
        );
    }

    /// Readings of a compass read in whole milligauss (ArduPilot's SCALED_IMU), in uT: the true
    /// field in counts plus Gaussian noise of `sigma_counts` per axis, rounded to a count.
    fn milligauss_readings(
        field_counts: impl Iterator<Item = Vec3>,
        sigma_counts: Vec3,
        seed: u32,
    ) -> Vec<Vec3> {
        let mut x = seed;
        let mut uniform = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as f64 / u32::MAX as f64
        };
        field_counts
            .map(|f| {
                let mut r = [0.0; 3];
                for k in 0..3 {
                    // Twelve uniforms less 6: mean 0, variance 1, close to Gaussian.
                    let g = (0..12).map(|_| uniform()).sum::<f64>() - 6.0;
                    r[k] = 0.1 * (f[k] + sigma_counts[k] * g).round();
                }
                r
            })
            .collect()
    }

    /// A field of 500 counts (50 uT) about a hard-iron offset, turned through many directions, in
    /// counts: `steps` readings.
    fn turning_counts(steps: usize) -> impl Iterator<Item = Vec3> {
        (0..steps).map(|i| {
            let (a, b) = (i as f64 * 0.37, i as f64 * 0.11);
            [
                120.0 + 500.0 * a.cos() * b.cos(),
                -40.0 + 500.0 * a.sin() * b.cos(),
                380.0 + 500.0 * b.sin(),
            ]
        })
    }

    /// A compass read in whole milligauss that sits still repeats its readings: one x, y and z
    /// count in most of them when its noise is under a count, and its lowest and highest readings
    /// in many. Its other axes' noise moving them by several counts between readings (as on an
    /// ArduSub ROV at rest) does not make a quiet axis stuck either. Neither is an axis fault.
    #[test]
    fn axis_fault_passes_a_still_compass_read_in_whole_counts() {
        let still = |_| [123.4, -45.7, 387.2];
        let quiet = milligauss_readings((0..300).map(still), [0.25; 3], 0x2545_F491);
        assert_eq!(axis_fault(&quiet), None);
        // Its lowest and highest readings (x: 12.3 and 12.4 uT) hold far more than 3% of them:
        // not saturated, the ends of its noise.
        let lowest_x = quiet.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
        let at_lowest = quiet.iter().filter(|p| p[0] == lowest_x).count();
        let highest_x = quiet.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max);
        let at_highest = quiet.iter().filter(|p| p[0] == highest_x).count();
        assert!(at_lowest.min(at_highest) > 30, "{at_lowest} {at_highest}");
        // x quiet (0.7 counts rms), y and z noisy (3 counts rms): most steps move y or z by more
        // than 4 counts, and x stays on its most frequent count across about half of them.
        let still = |_| [128.0, -45.7, 387.2];
        let noisy = milligauss_readings((0..300).map(still), [0.7, 3.0, 3.0], 0x1B87_3593);
        assert_eq!(axis_fault(&noisy), None);
    }

    /// The same compass turning with its y axis stuck on one count for the last third: stuck while
    /// the vehicle turns, in whole counts as in floating point
    /// (`axis_fault_tells_a_resting_sensor_from_a_stuck_axis`).
    #[test]
    fn axis_fault_names_an_axis_stuck_while_the_compass_turns() {
        let mut stuck = milligauss_readings(turning_counts(300), [0.7; 3], 0x2545_F491);
        assert_eq!(axis_fault(&stuck), None, "the turn itself");
        assert!(stuck.iter().all(|p| p[1] != -12.5));
        for p in stuck.iter_mut().skip(200) {
            p[1] = -12.5;
        }
        let why = axis_fault(&stuck).expect("a stuck axis");
        // 99 steps from the stuck value; over one of them x and z move too little to count as a
        // turn (less than 4 times the smallest move they make over these steps).
        let expected = "axis y reads exactly -12.5 in 100 of 300 points and stays on it across 98 \
                        of the 98 steps from it over which the vehicle turns";
        assert!(why.contains(expected), "{why}");
        assert!(why.contains("stuck part of the time"), "{why}");
    }

    /// An axis clipped at the sensor's range while the compass turns is saturated, whether its
    /// readings are whole counts or floating point.
    #[test]
    fn axis_fault_names_a_clipped_axis() {
        let turning = milligauss_readings(turning_counts(300), [0.7; 3], 0x2545_F491);
        let clipped: Vec<Vec3> = turning
            .iter()
            .map(|p| [p[0].min(45.0), p[1], p[2]])
            .collect();
        let why = axis_fault(&clipped).expect("a clipped axis");
        assert!(why.contains("axis x reads exactly 45 in"), "{why}");
        assert!(why.contains("saturated"), "{why}");
        let float: Vec<Vec3> = turning_counts(300)
            .map(|f| [f[0] * 0.1, (f[1] * 0.1).max(-30.0), f[2] * 0.1])
            .collect();
        let why = axis_fault(&float).expect("a clipped axis");
        assert!(why.contains("axis y reads exactly -30 in"), "{why}");
        assert!(why.contains("saturated"), "{why}");
    }

    #[test]
    fn frequent_value_agrees_with_sorting_and_counting() {
        let mut x = 0x2545_F491u32;
        for case in 0..400 {
            let n = 5 + case % 60;
            let vals: Vec<f64> = (0..n)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    // Few distinct values in some cases, many in others.
                    (x % [3, 5, 8, 40][case % 4]) as f64 - 1.0
                })
                .collect();
            let mut sorted = vals.clone();
            sorted.sort_by(|a, b| a.total_cmp(b));
            let (mut best, mut run, mut val) = (0, 0, f64::NAN);
            for i in 0..n {
                run = if i > 0 && sorted[i] == sorted[i - 1] {
                    run + 1
                } else {
                    1
                };
                if run > best {
                    best = run;
                    val = sorted[i];
                }
            }
            let expected = (best as f64 >= 0.2 * n as f64).then_some((val, best));
            assert_eq!(
                frequent_value(vals.iter().copied(), 0.2),
                expected,
                "case {case}: {vals:?}"
            );
        }
    }
}
