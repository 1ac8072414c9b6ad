//! The magnetometer's latency behind the gyro: a setting, or estimated online from the IMU data.

use super::lowpass::Lp3;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Magnetometer latency settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MagDelayConfig {
    /// Magnetometer latency behind the gyro, s: `Some(d)` fixed, `None` estimated online.
    /// Default: none (estimated).
    pub mag_delay_s: Option<f64>,
    /// Largest magnetometer latency considered by the online estimate, s. Default: 0.05
    /// (physical: one sample period of a 20 Hz magnetometer, the slowest in common use).
    pub mag_delay_max_s: f64,
}

impl Default for MagDelayConfig {
    fn default() -> Self {
        MagDelayConfig {
            mag_delay_s: None,
            mag_delay_max_s: 0.05,
        }
    }
}

/// Online estimate of the magnetometer latency behind the gyro: with a delay `d` the world-frame field
/// reads `H + d (omega_w x H)` (to first order), so `d` is the least-squares slope of the high-passed
/// world field on `omega_w x m_w`. Accumulated with exponential forgetting. The high-pass on the
/// field only makes this an effective latency weighted toward fast rotations (on BROAD's IMU: about
/// 10 ms in fast trials, 5-12 ms in slow ones), which is what the heading needs there.
#[derive(Debug, Clone, Default)]
pub(super) struct DelayEst {
    sxy: f64,
    sxx: f64,
    mean: Lp3,
    /// The last step and its forgetting factor (steps repeat: one `exp` per new step, not per sample).
    forget: (f64, f64),
}

pub(super) const DELAY_FORGET_S: f64 = 60.0;
pub(super) const DELAY_HP_TAU_S: f64 = 0.5;

impl DelayEst {
    pub(super) fn update(&mut self, m_w: &Vector3<f64>, w_w: &Vector3<f64>, dt: f64) {
        // The field high-passed (slow field changes do not enter); the regressor is not, which
        // weights fast rotations (where the latency matters) over slow ones.
        let y = m_w - self.mean.update(m_w, dt, DELAY_HP_TAU_S);
        let x = w_w.cross(m_w);
        if !(self.forget.0 == dt && dt > 0.0) {
            self.forget = (dt, (-dt / DELAY_FORGET_S).exp());
        }
        let f = self.forget.1;
        self.sxy = self.sxy * f + x.dot(&y);
        self.sxx = self.sxx * f + x.dot(&x);
    }
    pub(super) fn estimate(&self, max: f64) -> f64 {
        // Needs enough rotation before it is trusted: ~ (1 rad/s * 40 uT)^2 for a second at 100 Hz.
        if self.sxx < 1.0e5 {
            return 0.0;
        }
        (self.sxy / self.sxx).clamp(0.0, max)
    }
}
