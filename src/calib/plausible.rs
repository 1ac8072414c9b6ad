//! Is it a compass seeing the earth's field? Two checks on a compass's readings before any
//! calibration of it is believed, each failing with its numbers:
//!
//! - **Strength.** The common drone compasses read at most +-8 gauss ([`FULL_SCALE_UT`]: the
//!   HMC5883L's and QMC5883L's largest range), and the earth's field is at most [`EARTH_MAX_UT`]
//!   anywhere (the place's own strength where it is known). Readings whose typical strength is
//!   beyond the two together are not a compass reading the earth's field through a hard iron:
//!   a magnet or a power lead beside it, a failing sensor, or a wrong unit. (A phone's hard iron
//!   of 400 uT is within; a flight stack accepts at most COMPASS_OFFS_MAX, 180 uT, which the
//!   model ladder's bounds check.)
//! - **Turning.** With the vehicle's attitude and the earth's field, the field seen in body axes
//!   varies as the vehicle turns by a known amount; the readings must vary with it. Readings that
//!   vary by less than [`MIN_TURN_RATIO`] of it do not turn with the vehicle (a field fixed in the
//!   body swamps the earth's, or the sensor is stuck); readings that vary by more than
//!   [`MAX_TURN_RATIO`] times it change on their own (a current, a moving magnet, a failing
//!   sensor). Judged only when the attitudes turn the expected field by [`MIN_EXPECTED_SPREAD`] of
//!   its strength or more.
//! - **Turning, without an attitude** ([`check_still`]). When the accelerometer's direction
//!   spreads about two axes by [`MIN_TILT_SPREAD`] or more, the vehicle turned in a way no
//!   rotation about the field's own direction can give, and the earth's field (at least
//!   [`EARTH_MIN_UT`]) seen in body axes must vary with it. Readings varying by less than
//!   [`MIN_TURN_RATIO`] of that weakest field do not turn with the vehicle.
//!
//! Pure: no I/O.

use nalgebra::Vector3;

/// The strongest earth field anywhere (about 66 uT near the south magnetic pole), uT.
pub const EARTH_MAX_UT: f64 = 67.0;
/// The largest range of the common drone compasses, +-8 gauss (HMC5883L: 8.1 G; QMC5883L: 8 G), uT.
pub const FULL_SCALE_UT: f64 = 800.0;
/// Readings varying by less than this share of the expected field's variation do not turn with
/// the vehicle. A soft iron scales the field by 0.8-1.2 ([`crate::calib::ladder::DIAG_RANGE`]);
/// a fifth is far outside anything a calibration can correct.
pub const MIN_TURN_RATIO: f64 = 0.2;
/// ... by more than this many times it, they change on their own (the inverse of the above).
pub const MAX_TURN_RATIO: f64 = 5.0;
/// The expected field must vary by at least this share of its strength (RMS) to judge turning:
/// a few degrees of attitude noise aside (0.05 is a turn of about 3 deg).
pub const MIN_EXPECTED_SPREAD: f64 = 0.05;

/// The weakest earth field anywhere (about 22 uT, in the South Atlantic Anomaly), uT.
pub const EARTH_MIN_UT: f64 = 22.0;
/// The accelerometer's direction must spread by this much (RMS of the unit vector, second
/// largest axis; 0.2 is about 12 deg) about two axes before a compass is expected to turn.
pub const MIN_TILT_SPREAD: f64 = 0.2;

/// Why a compass's readings are not believed.
#[derive(Debug, Clone, PartialEq)]
pub enum Implausible {
    /// The readings' median strength, and the most the earth's field plus an accepted hard iron
    /// could give, uT.
    TooStrong {
        median_ut: f64,
        limit_ut: f64,
        earth_ut: f64,
    },
    /// RMS variation of the readings and of the expected field, uT.
    DoesNotTurn {
        readings_ut: f64,
        expected_ut: f64,
    },
    VariesOnItsOwn {
        readings_ut: f64,
        expected_ut: f64,
    },
    /// No attitude: RMS variation of the readings, uT, while gravity's direction spread by
    /// `tilt_spread` (RMS of the unit vector, second largest axis) about two axes.
    StillWhileTurning {
        readings_ut: f64,
        tilt_spread: f64,
    },
}

impl std::fmt::Display for Implausible {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Implausible::TooStrong {
                median_ut,
                limit_ut,
                earth_ut,
            } => write!(
                f,
                "the compass reads {median_ut:.0} uT (median), the earth's field is {earth_ut:.0} uT: beyond the +-8 gauss of the common drone compasses with the earth's field on top ({limit_ut:.0} uT at most), no hard iron a calibration can take out; look for a magnet or a power lead beside the compass, a failing sensor, or a wrong unit"
            ),
            Implausible::DoesNotTurn {
                readings_ut,
                expected_ut,
            } => write!(
                f,
                "the field does not turn with the vehicle: the readings vary by {readings_ut:.2} uT (RMS) while the earth's field seen through the attitude varies by {expected_ut:.2} uT; a field fixed in the vehicle swamps the earth's, or the sensor is stuck"
            ),
            Implausible::VariesOnItsOwn {
                readings_ut,
                expected_ut,
            } => write!(
                f,
                "the field changes on its own: the readings vary by {readings_ut:.1} uT (RMS) while the earth's field seen through the attitude varies by {expected_ut:.1} uT; look for a current or a moving magnet near the compass, or a failing sensor"
            ),
            Implausible::StillWhileTurning {
                readings_ut,
                tilt_spread,
            } => write!(
                f,
                "the field does not turn with the vehicle: the readings vary by {readings_ut:.2} uT (RMS) while the accelerometer shows the vehicle turned about two axes (gravity's direction spreads by {tilt_spread:.2}), which turns even the weakest earth field ({EARTH_MIN_UT:.0} uT) by more than {:.1} uT; a field fixed in the vehicle swamps the earth's, or the sensor is stuck",
                MIN_TURN_RATIO * EARTH_MIN_UT
            ),
        }
    }
}

/// Check `readings` (raw field in body axes, uT, any onboard correction undone) against the
/// earth's strength where known (`earth_ut`, else [`EARTH_MAX_UT`]); `expected` holds, for the
/// readings that have one, the earth's field seen in body axes at the reading's attitude (pairs
/// of reading and expected field). `None` when nothing is implausible or there is too little to
/// judge (fewer than [`MIN_READINGS`]).
pub fn check(
    readings: &[Vector3<f64>],
    expected: &[(Vector3<f64>, Vector3<f64>)],
    earth_ut: Option<f64>,
) -> Option<Implausible> {
    if readings.len() >= MIN_READINGS {
        let mut norms: Vec<f64> = readings
            .iter()
            .map(|r| r.norm())
            .filter(|n| n.is_finite())
            .collect();
        if norms.len() >= MIN_READINGS {
            let mid = norms.len() / 2;
            let median_ut = *norms.select_nth_unstable_by(mid, f64::total_cmp).1;
            let earth = earth_ut.unwrap_or(EARTH_MAX_UT);
            let limit_ut = FULL_SCALE_UT + earth;
            if median_ut > limit_ut {
                return Some(Implausible::TooStrong {
                    median_ut,
                    limit_ut,
                    earth_ut: earth,
                });
            }
        }
    }
    if expected.len() < MIN_READINGS {
        return None;
    }
    let spread = |v: &mut dyn Iterator<Item = Vector3<f64>>| {
        let all: Vec<Vector3<f64>> = v.collect();
        let n = all.len() as f64;
        let mean = all.iter().sum::<Vector3<f64>>() / n;
        (all.iter().map(|x| (x - mean).norm_squared()).sum::<f64>() / n).sqrt()
    };
    let readings_ut = spread(&mut expected.iter().map(|p| p.0));
    let expected_ut = spread(&mut expected.iter().map(|p| p.1));
    let strength = expected.iter().map(|p| p.1.norm()).sum::<f64>() / expected.len() as f64;
    if !(expected_ut >= MIN_EXPECTED_SPREAD * strength) {
        return None;
    }
    if readings_ut < MIN_TURN_RATIO * expected_ut {
        return Some(Implausible::DoesNotTurn {
            readings_ut,
            expected_ut,
        });
    }
    if readings_ut > MAX_TURN_RATIO * expected_ut {
        return Some(Implausible::VariesOnItsOwn {
            readings_ut,
            expected_ut,
        });
    }
    None
}

/// [`check`]'s turning without an attitude: `readings` (uT) and the accelerometer's readings
/// (any unit) of the same samples. `None` when the vehicle did not turn about two axes, the
/// readings turn, or they are all weaker than the variation asked for (another unit).
pub fn check_still(readings: &[Vector3<f64>], accel: &[Vector3<f64>]) -> Option<Implausible> {
    if readings.len() < MIN_READINGS || accel.len() < MIN_READINGS {
        return None;
    }
    let units: Vec<Vector3<f64>> = accel.iter().filter_map(|a| a.try_normalize(1e-9)).collect();
    if units.len() < MIN_READINGS {
        return None;
    }
    let mut eig: Vec<f64> = covariance(&units)
        .symmetric_eigen()
        .eigenvalues
        .iter()
        .copied()
        .collect();
    eig.sort_by(|a, b| b.total_cmp(a));
    let tilt_spread = eig[1].max(0.0).sqrt();
    let readings_ut = variance_sum(readings).max(0.0).sqrt();
    // Readings weaker than the variation asked for are in another unit (gauss read as uT), which
    // the fit's radius check names; not a field that stays put.
    let strength_ut = readings.iter().map(|r| r.norm()).sum::<f64>() / readings.len() as f64;
    let floor_ut = MIN_TURN_RATIO * EARTH_MIN_UT;
    (tilt_spread >= MIN_TILT_SPREAD && readings_ut < floor_ut && strength_ut >= floor_ut).then_some(
        Implausible::StillWhileTurning {
            readings_ut,
            tilt_spread,
        },
    )
}

/// The covariance of `v` about its mean: the sum of the outer products `(x - mean)(x - mean)^T`
/// over `n`, each element summed in the order of `v`, as nalgebra's matrix product and sum give
/// it (to the bit), without a general matrix product per point.
fn covariance(v: &[Vector3<f64>]) -> nalgebra::Matrix3<f64> {
    let n = v.len() as f64;
    let mean = v.iter().sum::<Vector3<f64>>() / n;
    let mut c = [[0.0f64; 3]; 3];
    for x in v {
        let d = x - mean;
        for (i, row) in c.iter_mut().enumerate() {
            for (j, e) in row.iter_mut().enumerate() {
                *e += d[i] * d[j];
            }
        }
    }
    nalgebra::Matrix3::from_fn(|i, j| c[i][j]) / n
}

/// The trace of [`covariance`] (its diagonal alone summed, as nalgebra's `trace` sums it).
fn variance_sum(v: &[Vector3<f64>]) -> f64 {
    let n = v.len() as f64;
    let mean = v.iter().sum::<Vector3<f64>>() / n;
    let mut c = [0.0f64; 3];
    for x in v {
        let d = x - mean;
        for (i, e) in c.iter_mut().enumerate() {
            *e += d[i] * d[i];
        }
    }
    let mut trace = 0.0;
    for e in c {
        trace += e / n;
    }
    trace
}

/// Fewest readings judged.
pub const MIN_READINGS: usize = 20;

#[cfg(test)]
mod tests {
    use super::*;

    fn turning(scale: f64, hard_iron_ut: Vector3<f64>) -> Vec<(Vector3<f64>, Vector3<f64>)> {
        (0..200)
            .map(|k| {
                let yaw = k as f64 * 0.05;
                let h = Vector3::new(20.0 * yaw.cos(), -20.0 * yaw.sin(), 44.0);
                (h * scale + hard_iron_ut, h)
            })
            .collect()
    }

    #[test]
    fn the_covariance_is_nalgebras_to_the_bit() {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 100.0 - 30.0
        };
        for n in [1usize, 2, 20, 1000, 20_000] {
            let v: Vec<Vector3<f64>> = (0..n)
                .map(|_| Vector3::new(next(), next(), next()))
                .collect();
            let nf = n as f64;
            let mean = v.iter().sum::<Vector3<f64>>() / nf;
            let by_nalgebra = v
                .iter()
                .map(|x| (x - mean) * (x - mean).transpose())
                .sum::<nalgebra::Matrix3<f64>>()
                / nf;
            let ours = covariance(&v);
            for (a, b) in ours.iter().zip(by_nalgebra.iter()) {
                assert_eq!(a.to_bits(), b.to_bits(), "{n}");
            }
            assert_eq!(variance_sum(&v).to_bits(), by_nalgebra.trace().to_bits());
        }
    }

    #[test]
    fn an_ordinary_compass_passes_and_a_large_hard_iron_too() {
        // A phone's hard iron of 400 uT (the tyrex recordings) is a compass all the same.
        let p = turning(1.0, Vector3::new(40.0, -100.0, 400.0));
        let r: Vec<_> = p.iter().map(|x| x.0).collect();
        assert_eq!(check(&r, &p, Some(48.0)), None);
    }

    #[test]
    fn a_reading_of_1548_ut_is_too_strong_with_its_numbers() {
        let p = turning(1.0, Vector3::new(0.0, 1500.0, 400.0));
        let r: Vec<_> = p.iter().map(|x| x.0).collect();
        let e = check(&r, &p, Some(48.0)).expect("implausible");
        assert!(matches!(e, Implausible::TooStrong { .. }), "{e}");
        assert!(e.to_string().contains("uT (median)"), "{e}");
    }

    #[test]
    fn a_field_that_stays_put_while_the_accelerometer_turns_is_named_without_an_attitude() {
        let turn = |k: usize| {
            let (a, b) = (k as f64 * 0.07, k as f64 * 0.05);
            Vector3::new(a.sin() * b.cos(), a.sin() * b.sin(), a.cos())
        };
        let accel: Vec<Vector3<f64>> = (0..300).map(|k| turn(k) * 9.8).collect();
        // A field of 1.3 uT about a fixed 35 uT: stuck, or swamped by the vehicle's own.
        let still: Vec<Vector3<f64>> = (0..300)
            .map(|k| Vector3::new(20.0, 21.0, 19.0) + turn(k) * 1.3)
            .collect();
        let e = check_still(&still, &accel).expect("named");
        assert!(
            e.to_string().contains("does not turn with the vehicle"),
            "{e}"
        );
        // The earth's 48 uT turning with the vehicle passes, and so does a level vehicle.
        let turning: Vec<Vector3<f64>> = (0..300).map(|k| turn(k) * 48.0).collect();
        assert_eq!(check_still(&turning, &accel), None);
        let level: Vec<Vector3<f64>> = (0..300).map(|_| Vector3::new(0.0, 0.0, 9.8)).collect();
        assert_eq!(check_still(&still, &level), None);
    }

    #[test]
    fn a_field_that_does_not_turn_or_varies_on_its_own_is_named() {
        let p = turning(0.05, Vector3::new(10.0, 0.0, 0.0));
        let r: Vec<_> = p.iter().map(|x| x.0).collect();
        assert!(matches!(
            check(&r, &p, None),
            Some(Implausible::DoesNotTurn { .. })
        ));
        // A field jumping by 150 uT from reading to reading while the vehicle turns as before.
        let mut p = turning(1.0, Vector3::zeros());
        for (k, x) in p.iter_mut().enumerate() {
            x.0.x += if k % 2 == 0 { 150.0 } else { -150.0 };
        }
        let r: Vec<_> = p.iter().map(|x| x.0).collect();
        assert!(matches!(
            check(&r, &p, None),
            Some(Implausible::VariesOnItsOwn { .. })
        ));
    }
}
