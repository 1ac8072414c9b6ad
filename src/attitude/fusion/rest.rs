//! Rest detection: steady, not turning and not accelerating for a while. At rest the gyro measures
//! its bias and gravity the tilt closely.

use super::lowpass::Lp3;
use super::FusionConfig;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Rest detector settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RestConfig {
    /// Rest: gyro deviation threshold, rad/s. Default: 4 deg/s (0.070) (tuned within 2 to 4 deg/s:
    /// above a flight controller's gyro noise at rest, below a slow turn).
    pub rest_gyro_rad_s: f64,
    /// Rest: accel deviation threshold, m/s^2. Default: 0.5 (VQF's value).
    pub rest_acc_mps2: f64,
    /// Rest: shortest still time before rest counts, s. Default: 1.5 (VQF's value).
    pub rest_min_s: f64,
}

impl Default for RestConfig {
    fn default() -> Self {
        RestConfig {
            rest_gyro_rad_s: 4.0f64.to_radians(),
            rest_acc_mps2: 0.5,
            rest_min_s: 1.5,
        }
    }
}

/// Rest detector: the sensor is at rest when, for `rest_min_s`, (1) gyro and accel stay within
/// thresholds of their low-passed values (steady), (2) the rate less the bias estimate is within
/// three standard deviations of what the gyro's noise (`gyro_sample_sd`) and the bias estimate's
/// uncertainty leave in it (not turning: a steady turn is steady but not rest), and (3) the specific force's norm is within `2 rest_acc_mps2` of
/// gravity (no sustained acceleration: a coordinated turn or a centrifuge is steady but not rest).
/// Rest is what lets each gyro sample measure the bias and the accelerometer measure the tilt
/// closely, so what it lets through sets their errors: a rotation it accepts becomes bias, at most
/// the threshold.
#[derive(Debug, Clone, Default)]
pub(super) struct Rest {
    gyr_lp: Lp3,
    acc_lp: Lp3,
    still_s: f64,
    pub(super) rest: bool,
}

pub(super) const REST_TAU_S: f64 = 0.5;

impl Rest {
    /// `bias` and `bias_sd`: the filter's gyro bias estimate and the norm of its standard
    /// deviations, rad/s.
    pub(super) fn update(
        &mut self,
        gyr: Option<&Vector3<f64>>,
        acc: Option<&Vector3<f64>>,
        dt: f64,
        bias: (&Vector3<f64>, f64),
        cfg: &FusionConfig,
    ) {
        let mut still = true;
        if let Some(g) = gyr {
            let lp = self.gyr_lp.update(g, dt, REST_TAU_S);
            let (b, b_sd) = bias;
            // Each reading, not the low-passed rate (which would lag the end of a motion): its
            // noise on three axes is sqrt(3) `gyro_sample_sd`.
            let noise = 3f64.sqrt() * cfg.bias.gyro_sample_sd;
            still &=
                (g - lp).norm() < cfg.rest.rest_gyro_rad_s && (g - b).norm() < 3.0 * (noise + b_sd);
        }
        if let Some(a) = acc {
            let lp = self.acc_lp.update(a, dt, REST_TAU_S);
            still &= (a - lp).norm() < cfg.rest.rest_acc_mps2
                && (lp.norm() - cfg.gravity_mps2).abs() < cfg.rest.rest_acc_mps2 * 2.0;
        }
        if still {
            self.still_s += dt;
        } else {
            self.still_s = 0.0;
        }
        self.rest = self.still_s >= cfg.rest.rest_min_s;
    }
}
