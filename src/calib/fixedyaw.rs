//! Magnetometer offsets from one known heading, for a vehicle that cannot be tumbled: the vehicle
//! rests at a yaw the user knows (a compass rose, a runway heading, GNSS yaw), its tilt comes from
//! the accelerometer, and the earth field from the World Magnetic Model at its place. The field it
//! should read in body axes is then R^T B_ned, and the hard iron is what the mean raw reading has on
//! top of it:
//!
//! ```text
//! calibrated = M (raw - offset) = R^T B_ned   =>   offset = raw - M^-1 R^T B_ned
//! ```
//!
//! R = Rz(yaw) Ry(pitch) Rx(roll) takes body FRD axes to NED, yaw is the true heading (degrees,
//! clockwise from true north), B_ned = F (cos I cos D, cos I sin D, sin I) with declination D,
//! inclination I and total intensity F. One reading gives three equations, so only the offset is
//! found; the soft iron M is the one in use (identity without one). This is the calibration ArduPilot
//! runs for MAV_CMD_FIXED_MAG_CAL_YAW. Pure math: no I/O.

use crate::attitude::{roll_pitch_deg, EarthField};
use crate::types::Vec3;
use nalgebra::{Matrix3, Rotation3, Vector3};

/// How still and how level the vehicle must be, and over how many samples it is averaged.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixedYawSettings {
    /// Samples averaged (the latest ones). Default: 100 (1 s at 100 Hz).
    pub window_samples: usize,
    /// Largest standard deviation of the specific-force norm over the window, m/s^2: above it the
    /// vehicle is moving and its tilt is not known from the accelerometer. Default: 0.15.
    pub max_accel_sd_mps2: f64,
    /// Largest standard deviation of each magnetometer axis over the window, uT. Default: 1.0.
    pub max_mag_sd_ut: f64,
    /// Largest tilt from level, deg: near 90 deg the yaw is not defined. Default: 60.
    pub max_tilt_deg: f64,
}

impl FixedYawSettings {
    /// The defaults, as a constant (the live service sizes its sample buffers with it).
    pub(crate) const DEFAULT: FixedYawSettings = FixedYawSettings {
        window_samples: 100,
        max_accel_sd_mps2: 0.15,
        max_mag_sd_ut: 1.0,
        max_tilt_deg: 60.0,
    };
}

impl Default for FixedYawSettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// The offset found, and what it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FixedYaw {
    /// Hard iron in the magnetometer's units (uT), calibrated = M (raw - offset).
    pub offset_ut: Vec3,
    /// The field the vehicle should read, body axes after calibration, uT.
    pub expected_body_ut: Vec3,
    /// The earth field at the place, NED, uT.
    pub field_ned_ut: Vec3,
    /// Tilt from the accelerometer, deg.
    pub roll_deg: f64,
    pub pitch_deg: f64,
    /// Samples averaged.
    pub samples: usize,
}

/// Why no offset was found.
#[derive(Debug, Clone, PartialEq)]
pub enum FixedYawFailure {
    /// Fewer samples with both accelerometer and magnetometer than the window needs.
    NotEnoughSamples { have: usize, need: usize },
    /// The vehicle moved during the window.
    NotStill { accel_sd_mps2: f64, mag_sd_ut: f64 },
    /// Tilted too far from level for the yaw to mean anything.
    Tilted { tilt_deg: f64 },
    /// The soft-iron matrix in use cannot be inverted, or a reading is not finite.
    Degenerate,
}

impl std::fmt::Display for FixedYawFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FixedYawFailure::NotEnoughSamples { have, need } => write!(
                f,
                "{have} samples with accelerometer and magnetometer, {need} needed: keep the vehicle still a little longer"
            ),
            FixedYawFailure::NotStill {
                accel_sd_mps2,
                mag_sd_ut,
            } => write!(
                f,
                "the vehicle moved (specific force sd {accel_sd_mps2:.3} m/s^2, field sd {mag_sd_ut:.2} uT): hold it still at the yaw given"
            ),
            FixedYawFailure::Tilted { tilt_deg } => write!(
                f,
                "tilted {tilt_deg:.0} deg from level: set the vehicle roughly level"
            ),
            FixedYawFailure::Degenerate => {
                write!(f, "the readings or the soft iron in use are degenerate")
            }
        }
    }
}

/// Mean and the largest per-axis standard deviation of a set of vectors.
fn mean_and_sd(v: &[Vec3]) -> (Vec3, f64) {
    let n = v.len() as f64;
    let mut mean = [0.0; 3];
    for x in v {
        (0..3).for_each(|k| mean[k] += x[k] / n);
    }
    let sd = (0..3)
        .map(|k| (v.iter().map(|x| (x[k] - mean[k]).powi(2)).sum::<f64>() / n).sqrt())
        .fold(0.0, f64::max);
    (mean, sd)
}

/// The offset from the latest samples of a vehicle resting at true heading `yaw_deg`.
/// `samples`: (raw magnetometer uT, specific force m/s^2), both body axes, oldest first; the last
/// `settings.window_samples` are used. `matrix`: the soft iron in use (calibrated = M (raw - o)).
pub(crate) fn fixed_yaw_offset(
    samples: &[(Vec3, Vec3)],
    yaw_deg: f64,
    field: &EarthField,
    matrix: &[[f64; 3]; 3],
    settings: &FixedYawSettings,
) -> Result<FixedYaw, FixedYawFailure> {
    let need = settings.window_samples.max(1);
    if samples.len() < need {
        return Err(FixedYawFailure::NotEnoughSamples {
            have: samples.len(),
            need,
        });
    }
    let window = &samples[samples.len() - need..];
    let mags: Vec<Vec3> = window.iter().map(|s| s.0).collect();
    let norms: Vec<Vec3> = window
        .iter()
        .map(|s| [crate::types::norm(&s.1), 0.0, 0.0])
        .collect();
    let (mag, mag_sd_ut) = mean_and_sd(&mags);
    let accels: Vec<Vec3> = window.iter().map(|s| s.1).collect();
    let (accel, _) = mean_and_sd(&accels);
    let (_, accel_sd_mps2) = mean_and_sd(&norms);
    if ![mag, accel].iter().flatten().all(|x| x.is_finite()) || !yaw_deg.is_finite() {
        return Err(FixedYawFailure::Degenerate);
    }
    if accel_sd_mps2 > settings.max_accel_sd_mps2 || mag_sd_ut > settings.max_mag_sd_ut {
        return Err(FixedYawFailure::NotStill {
            accel_sd_mps2,
            mag_sd_ut,
        });
    }
    let (roll_deg, pitch_deg) = roll_pitch_deg(&accel);
    // The angle between body z and down: cos(tilt) = cos(roll) cos(pitch).
    let cos_tilt = roll_deg.to_radians().cos() * pitch_deg.to_radians().cos();
    let tilt_deg = cos_tilt.clamp(-1.0, 1.0).acos().to_degrees();
    if tilt_deg > settings.max_tilt_deg {
        return Err(FixedYawFailure::Tilted { tilt_deg });
    }
    let r = Rotation3::from_euler_angles(
        roll_deg.to_radians(),
        pitch_deg.to_radians(),
        yaw_deg.to_radians(),
    );
    let b_ned = field.field_ned_ut();
    let expected = r.inverse() * Vector3::from(b_ned);
    let m = Matrix3::from_fn(|i, j| matrix[i][j]);
    let m_inv = m.try_inverse().ok_or(FixedYawFailure::Degenerate)?;
    let raw_expected = m_inv * expected;
    Ok(FixedYaw {
        offset_ut: [0, 1, 2].map(|k| mag[k] - raw_expected[k]),
        expected_body_ut: [expected[0], expected[1], expected[2]],
        field_ned_ut: b_ned,
        roll_deg,
        pitch_deg,
        samples: need,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

    fn field() -> EarthField {
        EarthField {
            declination_deg: 3.5,
            inclination_deg: 64.0,
            total_ut: 49.0,
            model: Default::default(),
        }
    }

    /// Samples of a vehicle at rest at (roll, pitch, yaw) with hard iron `o` and soft iron `a`
    /// (raw = A R^T B + o), with a small deterministic jitter.
    fn resting(rpy_deg: [f64; 3], o: Vec3, a: [[f64; 3]; 3], n: usize) -> Vec<(Vec3, Vec3)> {
        let [r, p, y] = rpy_deg.map(f64::to_radians);
        let rot = Rotation3::from_euler_angles(r, p, y);
        let b = rot.inverse() * Vector3::from(field().field_ned_ut());
        let g = rot.inverse() * Vector3::new(0.0, 0.0, -9.81);
        let am = Matrix3::from_fn(|i, j| a[i][j]);
        let raw = am * b;
        (0..n)
            .map(|k| {
                let j = 0.05 * ((k as f64) * 0.7).sin();
                (
                    [raw[0] + o[0] + j, raw[1] + o[1] - j, raw[2] + o[2]],
                    [g[0] + 0.01 * j, g[1], g[2] - 0.01 * j],
                )
            })
            .collect()
    }

    #[test]
    fn fixed_yaw_recovers_the_hard_iron_at_any_heading_and_modest_tilt() {
        let o = [12.0, -30.5, 41.0];
        for rpy in [
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 137.0],
            [4.0, -3.0, 250.0],
            [-20.0, 10.0, 35.0],
        ] {
            let s = resting(rpy, o, IDENTITY, 150);
            let r = fixed_yaw_offset(&s, rpy[2], &field(), &IDENTITY, &Default::default()).unwrap();
            let err = (0..3)
                .map(|k| (r.offset_ut[k] - o[k]).abs())
                .fold(0.0, f64::max);
            // Measured: 0.00033 uT at each (the jitter's mean over the window).
            assert!(err < 0.001, "{rpy:?}: offset error {err} uT");
            assert!((r.roll_deg - rpy[0]).abs() < 0.1 && (r.pitch_deg - rpy[1]).abs() < 0.1);
        }
    }

    #[test]
    fn fixed_yaw_uses_the_soft_iron_in_use() {
        let a = [[1.05, 0.02, 0.0], [0.02, 0.97, 0.01], [0.0, 0.01, 1.01]];
        let m = Matrix3::from_fn(|i, j| a[i][j]).try_inverse().unwrap();
        let m = [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[(i, j)]));
        let o = [-5.0, 8.0, 2.0];
        let s = resting([2.0, 1.0, 90.0], o, a, 100);
        let r = fixed_yaw_offset(&s, 90.0, &field(), &m, &Default::default()).unwrap();
        let err = (0..3)
            .map(|k| (r.offset_ut[k] - o[k]).abs())
            .fold(0.0, f64::max);
        // Measured: 0.00006 uT.
        assert!(err < 0.0002, "offset error {err} uT");
        // The wrong yaw by 10 deg moves the offset by about 2 F sin(5 deg) cos(I) ~ 3.7 uT.
        let wrong = fixed_yaw_offset(&s, 100.0, &field(), &m, &Default::default()).unwrap();
        let moved = (0..3)
            .map(|k| (wrong.offset_ut[k] - o[k]).abs())
            .fold(0.0, f64::max);
        assert!(moved > 2.0, "{moved}");
    }

    #[test]
    fn fixed_yaw_refuses_motion_tilt_and_too_few_samples() {
        let o = [0.0; 3];
        let settings = FixedYawSettings::default();
        let few = resting([0.0; 3], o, IDENTITY, 20);
        assert!(matches!(
            fixed_yaw_offset(&few, 0.0, &field(), &IDENTITY, &settings),
            Err(FixedYawFailure::NotEnoughSamples {
                have: 20,
                need: 100
            })
        ));
        let mut moving = resting([0.0; 3], o, IDENTITY, 100);
        for (k, s) in moving.iter_mut().enumerate() {
            s.1[2] += if k % 2 == 0 { 1.0 } else { -1.0 };
        }
        assert!(matches!(
            fixed_yaw_offset(&moving, 0.0, &field(), &IDENTITY, &settings),
            Err(FixedYawFailure::NotStill { .. })
        ));
        let tilted = resting([70.0, 0.0, 0.0], o, IDENTITY, 100);
        let e = fixed_yaw_offset(&tilted, 0.0, &field(), &IDENTITY, &settings).unwrap_err();
        assert!(matches!(e, FixedYawFailure::Tilted { .. }), "{e:?}");
        assert!(e.to_string().contains("level"));
        let singular = [[0.0; 3]; 3];
        let still = resting([0.0; 3], o, IDENTITY, 100);
        assert_eq!(
            fixed_yaw_offset(&still, 0.0, &field(), &singular, &settings),
            Err(FixedYawFailure::Degenerate)
        );
    }
}
