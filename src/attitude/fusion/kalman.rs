//! The error-state Kalman core: the gyro's prediction with its process noise (and what a clipped
//! reading adds to it), the scalar updates every measurement uses, and the bias measured at rest.

use super::{small_rotation, OrientationFilter, VectorN, NS, SCALE0};
use nalgebra::{Matrix3, SMatrix, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Prediction settings: the gyro's noise and range (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProcessConfig {
    /// Gyro white noise density for the process noise, rad/s/sqrt(Hz). Default: 0.003136 (tuned;
    /// about ten times a MEMS gyro's datasheet density, standing in for what the model leaves out).
    pub gyro_noise_density: f64,
    /// Extra process noise proportional to the (slow RMS) rotation rate (scale and misalignment
    /// errors), sqrt(s). Default: 0.005 (tuned).
    pub gyro_rate_noise: f64,
    /// Time constant of the motion intensity (mean squares of rate and of | |f| - g |) that sets the
    /// noise levels, s. Default: 3 (tuned, held at its start: weights that follow the instantaneous
    /// acceleration too closely would bias the world-frame average the tilt correction relies on).
    pub intensity_tau_s: f64,
    /// Full-scale range of the gyro, rad/s: a reading at it (on any axis) is clipped, and the true
    /// rate beyond it unknown. While a reading is clipped the attitude's uncertainty grows by what
    /// the clipped axis may have turned, the tilt is corrected from the unfiltered accelerometer and
    /// no bias is learnt. 0 = never clipped. Default: 2000 deg/s (34.9) (physical: the range
    /// ArduPilot and PX4 set on the IMUs they drive).
    pub gyro_range_rad_s: f64,
}

impl Default for ProcessConfig {
    fn default() -> Self {
        ProcessConfig {
            gyro_noise_density: 0.003136,
            gyro_rate_noise: 0.005,
            intensity_tau_s: 3.0,
            gyro_range_rad_s: 2000.0f64.to_radians(),
        }
    }
}

/// Gyro bias settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BiasConfig {
    /// Standard deviation of one gyro sample at rest (the bias measurement noise), rad/s.
    /// Default: 0.004 (physical: 0.2 deg/s, a MEMS gyro's per-sample noise at 100-1000 Hz).
    pub gyro_sample_sd: f64,
    /// Initial bias uncertainty, rad/s. Default: 0.5 deg/s (0.0087) (VQF's value: a factory-
    /// calibrated MEMS gyro's remaining bias).
    pub bias_sigma_init: f64,
    /// Bias random walk, rad/s/sqrt(s), in motion. Default: 0.003125 deg/s/sqrt(s) (5.5e-5)
    /// (tuned).
    pub bias_walk: f64,
    /// Largest bias magnitude per axis, rad/s. Default: 5 deg/s (0.087) (physical: the zero-rate
    /// offset consumer MEMS gyros specify at most).
    pub bias_clip: f64,
}

impl Default for BiasConfig {
    fn default() -> Self {
        BiasConfig {
            gyro_sample_sd: 0.004,
            bias_sigma_init: 0.5f64.to_radians(),
            bias_walk: 0.003125f64.to_radians(),
            bias_clip: 5.0f64.to_radians(),
        }
    }
}

/// A reading counts as clipped from this fraction of `gyro_range_rad_s` (the full-scale count
/// scaled and calibrated lands a little below the nominal range).
pub(super) const CLIP_FRACTION: f64 = 0.995;
/// The unknown rate beyond the range of a clipped axis, as a standard deviation, in units of the
/// range: a rate at one and a half times the range is then a one-sigma event.
pub(super) const CLIP_EXCESS_SD: f64 = 0.5;
/// After the last clipped reading, the bias is not learnt for this long, s: the corrections take
/// the clipping's attitude error out over about this time, and the bias must not take it up.
pub(super) const CLIP_SETTLE_S: f64 = 2.0;

impl OrientationFilter {
    /// Turns the attitude by the gyro step and propagates the covariance; returns the step.
    pub(super) fn predict(&mut self, dt: f64) -> UnitQuaternion<f64> {
        let w = (self.last_gyro - self.bias).component_mul(&self.scale.s);
        let r = self.q.to_rotation_matrix().into_inner();
        let dq = UnitQuaternion::from_scaled_axis(w * dt);
        self.q *= dq;
        if self.cfg.tilt.acc_lp_tau_s > 0.0 {
            // Only the low-pass uses q_gyro, and only gyro steps ever turn it: keep it unit
            // against rounding.
            self.q_gyro *= dq;
            self.q_gyro.renormalize_fast();
        }
        // Error dynamics (world-frame attitude error): dtheta' = -R dbias + R diag(w) dscale (the
        // rate the gyro read short or long, turned into the world), so F = [[I, B], [0, I]] with
        // B = R E, E = [-dt I, diag(w) dt] (3 x 6). F P F^T by blocks (P = [[P11, P12],
        // [P12^T, P22]]):
        //   P11' = P11 + B P12^T + P12 B^T + B P22 B^T,  P12' = P12 + B P22,  P22' = P22,
        // with the products by E (which only scales rows and columns) taken first: a fraction of
        // the cost of the full 9 x 9 product.
        let wdt = w * dt;
        let p11 = self.p.fixed_view::<3, 3>(0, 0).into_owned();
        let p12 = self.p.fixed_view::<3, 6>(0, 3).into_owned();
        let p22 = self.p.fixed_view::<6, 6>(3, 3).into_owned();
        // E P22 (3 x 6), E P12^T and E P22 E^T (3 x 3).
        let ep22 =
            SMatrix::<f64, 3, 6>::from_fn(|i, j| -dt * p22[(i, j)] + wdt[i] * p22[(3 + i, j)]);
        let ep12t = Matrix3::from_fn(|i, j| -dt * p12[(j, i)] + wdt[i] * p12[(j, 3 + i)]);
        let epe = Matrix3::from_fn(|i, j| -dt * ep22[(i, j)] + wdt[j] * ep22[(i, 3 + j)]);
        let bp12t = r * ep12t;
        let n12 = p12 + r * ep22;
        let n11 = p11 + bp12t + bp12t.transpose() + r * epe * r.transpose();
        let qa = (self.cfg.process.gyro_noise_density.powi(2)
            + self.cfg.process.gyro_rate_noise.powi(2) * self.rate_ms)
            * dt;
        let qb = self.cfg.bias.bias_walk.powi(2) * dt;
        self.p.fixed_view_mut::<3, 3>(0, 0).copy_from(&n11);
        self.p.fixed_view_mut::<3, 6>(0, 3).copy_from(&n12);
        self.p
            .fixed_view_mut::<6, 3>(3, 0)
            .copy_from(&n12.transpose());
        for i in 0..3 {
            self.p[(i, i)] += qa;
            self.p[(i + 3, i + 3)] += qb;
        }
        // A clipped axis turned by an unknown amount more than it read: the attitude's uncertainty
        // grows by that amount, about every world axis. (About the clipped axis alone would be
        // exact for one step, but that axis is known in the world only through the attitude the
        // clipping makes wrong, and correcting large tilt errors leaks into the heading.)
        let excess = CLIP_EXCESS_SD * self.cfg.process.gyro_range_rad_s * dt;
        if self.clipped_now > 0 {
            for i in 0..3 {
                self.p[(i, i)] += self.clipped_now as f64 * excess * excess;
            }
        }
        dq
    }

    /// How many axes of a gyro reading are at the gyro's range (`gyro_range_rad_s`).
    pub(super) fn clipped_axes(&self, w: &Vector3<f64>) -> usize {
        if self.cfg.process.gyro_range_rad_s <= 0.0 {
            return 0;
        }
        let limit = CLIP_FRACTION * self.cfg.process.gyro_range_rad_s;
        w.iter().filter(|x| x.abs() >= limit).count()
    }

    /// While clipped readings (or the corrections of their error) are recent, no correction may
    /// move the bias.
    pub(super) fn clip_settling(&self) -> bool {
        self.since_clip_s < CLIP_SETTLE_S
    }

    /// Scalar Kalman update of state `i` measured directly (every measurement here is one state:
    /// `h` is the unit row `e_i`), innovation `y`, variance `r`; entries of the gain listed in
    /// `frozen`, and the scale's (a consider state), are forced to zero (Joseph form keeps P
    /// consistent for that gain).
    pub(super) fn scalar_update(&mut self, i: usize, y: f64, r: f64, frozen: &[usize]) -> f64 {
        // P as a column-major array of fixed size: the loops below then index without checks.
        let p: &mut [f64; NS * NS] = self
            .p
            .as_mut_slice()
            .try_into()
            .expect("an NS x NS matrix has NS^2 entries");
        // a = P h^T is P's column i.
        let a: [f64; NS] = std::array::from_fn(|rr| p[i * NS + rr]);
        let s = a[i] + r;
        let mut k = a.map(|x| x / s);
        for &j in frozen {
            k[j] = 0.0;
        }
        k[SCALE0..].fill(0.0);
        // Joseph form (I - K h) P (I - K h)^T + r K K^T, expanded with a = P h^T and
        // s = h P h^T + r: P - K a^T - a K^T + s K K^T (exact for any K, so also with frozen
        // entries). Symmetric: the upper triangle is computed and mirrored. With the scale's gain
        // zero, its own block does not change (d = 0 there): the columns stop at its start.
        for c in 0..NS {
            for rr in 0..=c.min(SCALE0 - 1) {
                let d = s * k[rr] * k[c] - k[rr] * a[c] - a[rr] * k[c];
                let v = p[c * NS + rr] + d;
                p[c * NS + rr] = v;
                p[rr * NS + c] = v;
            }
        }
        let dx = VectorN::from(k.map(|x| x * y));
        self.apply(&dx);
        s
    }

    pub(super) fn apply(&mut self, dx: &VectorN) {
        let dtheta = Vector3::new(dx[0], dx[1], dx[2]);
        // A bias-only update (attitude gains frozen) leaves the attitude exactly as it is.
        if dtheta != Vector3::zeros() {
            self.q = small_rotation(&dtheta) * self.q;
        }
        self.bias += Vector3::new(dx[3], dx[4], dx[5]);
        let c = self.cfg.bias.bias_clip;
        self.bias = self.bias.map(|b| b.clamp(-c, c));
    }

    pub(super) fn bias_update(&mut self, g: &Vector3<f64>) {
        let r = self.cfg.bias.gyro_sample_sd.powi(2);
        for i in 0..3 {
            let y = g[i] - self.bias[i];
            self.scalar_update(i + 3, y, r, &[0, 1, 2]);
        }
    }
}
