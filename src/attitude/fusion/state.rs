//! What the filter has learnt that outlives it: saved with the calibration, restored on start.

use super::magref::MagRef;
use super::scale::SCALE_MAX_DEV;
use super::scale::SCALE_RESTORED_SD_MIN;
use super::{v3, OrientationFilter, NS};
use crate::types::Vec3;
use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

/// What the filter has learnt that outlives it (as VQF's `getState`/`setState`): the gyro bias and
/// its uncertainty, and the magnetic reference. The live service saves it with the calibration and
/// restores it on start, and keeps the bias when a new magnetometer calibration makes it restart
/// the filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FilterState {
    /// Gyro bias, rad/s, sensor axes (what is left after the gyro calibration the filter is fed).
    pub gyro_bias_rad_s: Vec3,
    /// 1-sigma of the bias per axis, rad/s.
    pub gyro_bias_sigma_rad_s: Vec3,
    /// Reference field norm (input units, uT) and dip (deg), once learnt: the field the
    /// magnetometer calibration in use gives. `None`: not learnt (or the calibration changed).
    pub mag_reference: Option<(f64, f64)>,
    /// The gyro's per-axis scale learnt between rests and its 1-sigma (relative), once a pair of
    /// rests has given one (`gyro_scale_sigma` > 0). Absent from files written before it existed.
    #[serde(default)]
    pub gyro_scale: Option<(Vec3, Vec3)>,
}

/// Smallest bias uncertainty a restored state starts with, rad/s (0.01 deg/s): a bias moves
/// between runs (temperature, turn-on repeatability), so a saved one is never taken as exact.
pub(crate) const RESTORED_BIAS_SIGMA_MIN_RAD_S: f64 = 1.75e-4;

impl OrientationFilter {
    /// What the filter has learnt, to save ([`OrientationFilter::set_state`] restores it).
    pub fn state(&self) -> FilterState {
        FilterState {
            gyro_bias_rad_s: self.bias(),
            gyro_bias_sigma_rad_s: self.bias_sigma(),
            mag_reference: self.mag_reference(),
            gyro_scale: self.gyro_scale(),
        }
    }

    /// The gyro's per-axis scale learnt between rests and its 1-sigma, once learnt.
    pub(crate) fn gyro_scale(&self) -> Option<(Vec3, Vec3)> {
        (self.scale.enabled() && self.scale.steps > 0).then(|| {
            let sd = |i: usize| self.scale.p[(i, i)].sqrt();
            (
                [self.scale.s.x, self.scale.s.y, self.scale.s.z],
                [sd(0), sd(1), sd(2)],
            )
        })
    }

    /// Start again after a new magnetometer calibration moved the field the filter sees: what does
    /// not depend on the field (the gyro bias) is kept; the field reference and the gyro scale,
    /// learnt against the rests' headings in the old field, are learnt again.
    pub(crate) fn restart_for_new_field(&mut self) {
        let kept = FilterState {
            mag_reference: None,
            gyro_scale: None,
            ..self.state()
        };
        *self = OrientationFilter::new(self.cfg);
        self.set_state(&kept);
    }

    /// Restore what a filter had learnt: the gyro bias with its uncertainty (not below
    /// [`RESTORED_BIAS_SIGMA_MIN_RAD_S`]), and the magnetic reference when given (taken as learnt for
    /// `mag_ref_tau_s`, so it changes only slowly from here). The attitude is not part of it: the
    /// next samples set it as they would in a new filter. Values that are not finite are ignored.
    pub(crate) fn set_state(&mut self, s: &FilterState) {
        let finite = |v: &Vec3| v.iter().all(|x| x.is_finite());
        if finite(&s.gyro_bias_rad_s) && finite(&s.gyro_bias_sigma_rad_s) {
            self.bias = v3(&s.gyro_bias_rad_s);
            for i in 0..3 {
                let sd = s.gyro_bias_sigma_rad_s[i].max(RESTORED_BIAS_SIGMA_MIN_RAD_S);
                for j in 0..NS {
                    self.p[(i + 3, j)] = 0.0;
                    self.p[(j, i + 3)] = 0.0;
                }
                self.p[(i + 3, i + 3)] = sd * sd;
            }
        }
        if let Some((scale, sd)) = s.gyro_scale {
            let ok = |x: &f64| x.is_finite() && (*x - 1.0).abs() <= SCALE_MAX_DEV;
            if self.scale.enabled()
                && scale.iter().all(ok)
                && sd.iter().all(|x| x.is_finite() && *x > 0.0)
            {
                self.scale.s = v3(&scale);
                // Never more certain than the prior allows a new estimate to move it.
                let floor = SCALE_RESTORED_SD_MIN;
                self.scale.p = Matrix3::from_diagonal(&v3(&sd).map(|x| x.max(floor).powi(2)));
                self.scale.steps = 1;
                self.scale_learnt();
            }
        }
        if let Some((norm, dip_deg)) = s.mag_reference {
            if norm.is_finite() && norm > 0.0 && dip_deg.is_finite() {
                self.mag_ref =
                    MagRef::restored(norm, dip_deg.to_radians(), self.cfg.mag_ref.mag_ref_tau_s);
            }
        }
    }
}
