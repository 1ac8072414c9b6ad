//! The tilt correction from the accelerometer: the specific force low-passed in the almost-inertial
//! frame, its noise grown by the linear acceleration.

use super::lowpass::Butter3;
use super::OrientationFilter;
use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Tilt correction settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TiltConfig {
    /// Tilt measurement noise in motion, before the linear acceleration adds to it: horizontal
    /// specific force in the world frame, m/s^2. Default: 1 (tuned).
    pub acc_noise_mps2: f64,
    /// Tilt measurement noise at rest, m/s^2 (the low-passed force, as in motion). Default: 0.125
    /// (tuned).
    pub acc_rest_noise_mps2: f64,
    /// Time constant of the RMS linear acceleration `|R f - g z|` (the specific force rotated into
    /// the world, gravity removed) that adds to the tilt noise in motion, one for one, s:
    /// sustained translation or vibration, which the norm of the specific force barely shows when
    /// it is horizontal, lowers the weight of the tilt correction. Default: 2 (tuned).
    pub acc_lin_tau_s: f64,
    /// Time constant of the second-order (Butterworth) low-pass applied to the specific force in the
    /// gyro-only (almost-inertial) frame before the tilt correction, s; 0 = none. Default: 1.5
    /// (tuned; VQF's `tauAcc` is 3).
    pub acc_lp_tau_s: f64,
    /// Accelerometer samples with | |f| - g | above this correct nothing (the low-pass still sees
    /// them), m/s^2. Default: 50 (physical: 5 g, which no hand or vehicle motion holds for long;
    /// impacts and crashes do).
    pub acc_reject_mps2: f64,
    /// Accelerometer latency behind the gyro, s (negative: ahead), for rotating it into the world.
    /// Default: 0 (physical: an IMU chip samples both together).
    pub acc_delay_s: f64,
}

impl Default for TiltConfig {
    fn default() -> Self {
        TiltConfig {
            acc_noise_mps2: 1.0,
            acc_rest_noise_mps2: 0.125,
            acc_lin_tau_s: 2.0,
            acc_lp_tau_s: 1.5,
            acc_reject_mps2: 50.0,
            acc_delay_s: 0.0,
        }
    }
}

/// The tilt noise, as a multiple of `acc_noise_mps2`, beyond which the adaptive terms say a linear
/// acceleration is present (the gyro bias is not learnt from the tilt then): twice the
/// unaccelerated noise, i.e. an RMS acceleration of about sqrt(3) `acc_noise_mps2` / gain.
pub(super) const ACC_CLEAN_FACTOR: f64 = 2.0;

impl OrientationFilter {
    /// The tilt measurement's noise now, m/s^2: `acc_rest_noise_mps2` at rest, else
    /// `acc_noise_mps2` grown by the slow RMS of the force's norm deviation and of the world-frame
    /// linear acceleration.
    pub(super) fn tilt_sigma(&self) -> f64 {
        if self.rest.rest {
            self.cfg.tilt.acc_rest_noise_mps2
        } else {
            (self.cfg.tilt.acc_noise_mps2.powi(2) + self.acc_ms + self.lin_ms).sqrt()
        }
    }

    pub(super) fn tilt_update(&mut self, a: &Vector3<f64>, dt: f64) {
        let g = self.cfg.gravity_mps2;
        // The accelerometer's timing against the gyro: rotate it with the attitude `acc_delay_s` ago
        // (a negative delay, an accelerometer ahead of the gyro, extrapolates with the current rate).
        // (No delay, the default: the reading as it is, not a rotation by zero.)
        let a_shifted = if self.cfg.tilt.acc_delay_s == 0.0 {
            *a
        } else {
            UnitQuaternion::from_scaled_axis(
                (self.last_gyro - self.bias) * (-self.cfg.tilt.acc_delay_s),
            ) * a
        };
        // While a reading is clipped, the almost-inertial frame turns wrongly and its low-pass means
        // nothing: the tilt is corrected from the unfiltered force, and the low-pass starts again
        // afresh after the clipping.
        let clipping = self.since_clip_s == 0.0;
        if clipping {
            self.lp_clipped = true;
        } else if self.lp_clipped {
            self.q_gyro = self.q;
            self.acc_lp = Butter3::default();
            self.lp_clipped = false;
        }
        let aw = if self.cfg.tilt.acc_lp_tau_s > 0.0 && !clipping {
            let lp = self
                .acc_lp
                .update(&(self.q_gyro * a_shifted), dt, self.cfg.tilt.acc_lp_tau_s);
            (self.q * self.q_gyro.inverse()) * lp
        } else {
            self.q * a_shifted
        };
        // The low-pass above sees every sample: skipping the large ones would bias the world-frame
        // average it takes (an oscillation along a tilted axis reaches |f| - g = +a on one side and
        // about -a + g on the other, so a threshold cuts the two sides unevenly; on the simulated
        // 10 g shake that tilted the estimate by 1.2 deg). Only the correction is skipped.
        if (a.norm() - g).abs() > self.cfg.tilt.acc_reject_mps2 && !self.rest.rest {
            return;
        }
        let sigma = self.tilt_sigma();
        let r = (sigma / g).powi(2);
        // The gyro bias is learnt from the tilt only while no linear acceleration is seen: an
        // acceleration is no white noise but a slow, correlated error of the tilt measurement, which
        // the bias would take up and keep long after the motion. (On the simulated centrifuge the
        // recovery went from 67 to 64 s with this: there the heading, not the tilt, moves the bias.)
        let frozen: &[usize] =
            if sigma > ACC_CLEAN_FACTOR * self.cfg.tilt.acc_noise_mps2 || self.clip_settling() {
                &[2, 3, 4, 5]
            } else {
                &[2]
            };
        let q_before = self.q;
        self.scalar_update(0, aw.y / g, r, frozen);
        // The first row's correction turns the world-frame force for the second.
        let aw = self.q * q_before.inverse() * aw;
        self.scalar_update(1, -aw.x / g, r, frozen);
    }
}
