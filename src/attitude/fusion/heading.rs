//! The heading correction from the magnetometer: the field rotated with the attitude of its
//! latency, the disturbance tests, the innovation gate, and a correction about the vertical only.

use super::OrientationFilter;
use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Heading correction settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HeadingConfig {
    /// Heading measurement noise of an undisturbed field, degrees. Not a field reading's noise:
    /// it makes the heading correction slow (tens of seconds), so that the gyro carries the
    /// heading through the field errors that pass the disturbance tests. Default: 240 (tuned).
    pub mag_heading_noise_deg: f64,
    /// Heading measurement noise of an undisturbed field while the rest detector sees the sensor
    /// still, degrees. Default: 120 (tuned).
    pub mag_rest_heading_noise_deg: f64,
    /// Heading innovation gate: a heading innovation larger than `mag_gate_deg` plus this many
    /// standard deviations of the heading state is not used, standard deviations. (The
    /// measurement noise is left out of the gate on purpose: it is large to make the correction
    /// slow, not because a single field reading is that uncertain.) Default: 4 (statistical: a
    /// true heading error is outside it once in 16,000).
    pub mag_gate_sigma: f64,
    /// Floor of the heading innovation gate, degrees: the field errors that pass the norm and dip
    /// checks (a magnet approaching, a field that moves with the sensor) but turn the heading by
    /// more than this are not used. Default: 56 (tuned).
    pub mag_gate_deg: f64,
    /// After this long with every heading innovation gated out, the gate opens until an innovation
    /// is within it again (a real heading error that grew beyond the gate is corrected after all),
    /// s. Default: 10 (tuned, held at its start).
    pub mag_gate_timeout_s: f64,
}

impl Default for HeadingConfig {
    fn default() -> Self {
        HeadingConfig {
            mag_heading_noise_deg: 240.0,
            mag_rest_heading_noise_deg: 120.0,
            mag_gate_sigma: 4.0,
            mag_gate_deg: 56.0,
            mag_gate_timeout_s: 10.0,
        }
    }
}

impl OrientationFilter {
    /// The attitude `d` seconds ago (interpolated from the history; the current one if none).
    pub(super) fn attitude_at_delay(&self, d: f64) -> UnitQuaternion<f64> {
        if d <= 0.0 || self.history.is_empty() {
            return self.q;
        }
        let target = self.t - d;
        let mut prev: Option<&(f64, UnitQuaternion<f64>)> = None;
        for item in self.history.iter().rev() {
            if item.0 <= target {
                return match prev {
                    Some(n) if n.0 > item.0 => {
                        let u = ((target - item.0) / (n.0 - item.0)).clamp(0.0, 1.0);
                        // Two consecutive samples' attitudes are close: the normalised linear
                        // interpolation is the slerp to well below a microradian.
                        item.1.nlerp(&n.1, u)
                    }
                    _ => item.1,
                };
            }
            prev = Some(item);
        }
        self.history.front().map(|x| x.1).unwrap_or(self.q)
    }

    pub(super) fn mag_update(&mut self, m: &Vector3<f64>, dt: f64) {
        let n = m.norm();
        if !(n > 0.0) {
            return;
        }
        let rate_w = self.q * (self.last_gyro - self.bias);
        let d = match self.cfg.mag_delay.mag_delay_s {
            Some(d) => d,
            None => self.delay.estimate(self.cfg.mag_delay.mag_delay_max_s),
        };
        let q_m = self.attitude_at_delay(d);
        let mw = q_m * m;
        if self.cfg.mag_delay.mag_delay_s.is_none() {
            // Undelayed world field for the latency estimate (uses the current attitude).
            let mw_now = self.q * m;
            if !self.mag_ref.disturbed && !self.clip_settling() {
                self.delay.update(&mw_now, &rate_w, dt);
            }
        }
        let h = (mw.x * mw.x + mw.y * mw.y).sqrt();
        let dip = (-mw.z).atan2(h);
        // (Right after clipping the tilt may still be wrong, and the dip with it: the norm alone
        // says whether the field is disturbed then, and the reference learns nothing.)
        let ok = if self.clip_settling() {
            self.mag_ref.norm_ok(n, &self.cfg)
        } else {
            self.mag_ref.update(n, dip, dt, &self.cfg)
        };
        if h < 1e-3 * n {
            return;
        }
        let decl = self.cfg.declination_deg.to_radians();
        let azimuth = mw.x.atan2(mw.y);
        if !azimuth.is_finite() {
            return;
        }
        if !self.heading_init {
            // First field: set the heading directly.
            let rz = UnitQuaternion::from_axis_angle(
                &Vector3::z_axis(),
                crate::attitude::wrap_pi(azimuth - decl),
            );
            self.q = rz * self.q;
            for x in self.history.iter_mut() {
                x.1 = rz * x.1;
            }
            self.heading_init = true;
            self.p[(2, 2)] = self.cfg.heading.mag_heading_noise_deg.to_radians().powi(2);
            for i in [0, 1, 3, 4, 5, 6, 7, 8] {
                self.p[(2, i)] = 0.0;
                self.p[(i, 2)] = 0.0;
            }
            return;
        }
        if !ok {
            return;
        }
        let sd = if self.rest.rest {
            self.cfg.heading.mag_rest_heading_noise_deg
        } else {
            self.cfg.heading.mag_heading_noise_deg
        }
        .to_radians();
        let mut r = sd * sd;
        if self.since_clip_s == 0.0 {
            // The heading noise is large to make the correction slow against a gyro that holds
            // the heading well; a clipped gyro holds nothing, and the field is then trusted as
            // the tilt trusts gravity.
            r = r.min((self.tilt_sigma() / self.cfg.gravity_mps2).powi(2));
        }
        let y = crate::attitude::wrap_pi(azimuth - decl);
        let gate = self.cfg.heading.mag_gate_deg.to_radians()
            + self.cfg.heading.mag_gate_sigma * self.p[(2, 2)].sqrt();
        if y.abs() <= gate {
            self.gated_s = 0.0;
        } else if self.gated_s < self.cfg.heading.mag_gate_timeout_s {
            self.gated_s += dt;
            return;
        }
        // (Timed out: open until an innovation is within the gate again.)
        let frozen: &[usize] = if self.clip_settling() {
            &[0, 1, 3, 4, 5]
        } else {
            &[0, 1]
        };
        self.scalar_update(2, y, r, frozen);
        self.mag_used = true;
    }
}
