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
