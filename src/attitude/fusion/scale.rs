//! The gyro's per-axis scale, learnt between rests; its uncertainty is carried in the filter's
//! covariance as a consider state.

use super::{OrientationFilter, NS, SCALE0};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Gyro scale settings (keys at the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GyroScaleConfig {
    /// Prior 1-sigma of the gyro's per-axis scale factors, which the filter learns from the rotation
    /// between rests (relative: 0.002 = 0.2 %); what is left of it also weighs the attitude's
    /// uncertainty by the angle turned (the module docs); 0 = not learnt (the readings' scale
    /// taken as exact). Default: 0.007 (tuned from 0.005, a MEMS gyro's sensitivity error).
    pub gyro_scale_sigma: f64,
    /// 1-sigma of the rest-to-rest residual per radian turned between the rests, rad/rad: the
    /// errors the scale does not model (a bias that moves in fast motion, misalignment), which
    /// grow with the angle turned. Larger: each motion teaches the scale less. Default: 0.001
    /// (physical: a milliradian of axis misalignment; the tuning kept it).
    pub gyro_scale_path_sd: f64,
}

impl Default for GyroScaleConfig {
    fn default() -> Self {
        GyroScaleConfig {
            gyro_scale_sigma: 0.007,
            gyro_scale_path_sd: 0.001,
        }
    }
}

/// The gyro's per-axis scale factors learnt from rest to rest, after Tedaldi, Pretto and Menegatti,
/// "A Robust and Easy to Implement Method for IMU Calibration without External Equipments" (2014):
/// the gyro integrated from one rest to the next must carry the first rest's attitude onto the
/// second's. A rest's attitude is the TRIAD of its mean specific force and field; a pair of rests
/// whose field was undisturbed at both gives one recursive least-squares step at the end of the
/// second rest (three equations: the residual rotation, linearised in the scale). A residual the
/// scale cannot explain (chi-square gate) is not used, and no step spans a new time segment. The
/// calibrator's gyro fit (`crate::calib::gyro`) solves the full 3x3 model at once from a dozen
/// rotations or more, gravity alone; this is its recursive, per-axis counterpart, usable from the
/// second rest on, which the field's heading at the rests makes observable about the vertical too.
#[derive(Debug, Clone)]
pub(super) struct ScaleEst {
    /// Scale per sensor axis (true rate = scale * (reading - bias)) and its covariance.
    pub(super) s: Vector3<f64>,
    pub(super) p: Matrix3<f64>,
    /// The last usable rest's attitude, sensor -> world (TRIAD).
    r0: Option<Matrix3<f64>>,
    /// Sensor now -> sensor at the end of that rest, as integrated with `s`; and the sum of
    /// R(t) diag(w) dt, the sensitivity of that rotation to the scale (in the rest's sensor frame).
    q_s: UnitQuaternion<f64>,
    sens: Matrix3<f64>,
    /// The angle turned through since then (the sum of |w| dt), rad.
    path_rad: f64,
    /// Specific force and field summed over the current rest, their counts, and whether the field
    /// stayed undisturbed.
    acc_sum: Vector3<f64>,
    mag_sum: Vector3<f64>,
    n_acc: u32,
    n_mag: u32,
    mag_ok: bool,
    was_rest: bool,
    /// Least-squares steps taken (or restored).
    pub(super) steps: u32,
    /// `GyroScaleConfig::gyro_scale_path_sd`.
    path_sd: f64,
}

/// 1-sigma of the rest-to-rest residual about every axis, rad: the rests' attitudes (a few tenths
/// of a degree) plus what the bias and the gyro noise add up to over half a minute of motion.
pub(super) const SCALE_TILT_SD_RAD: f64 = 0.01;
/// Further 1-sigma about the vertical, rad: the field's heading at a rest.
pub(super) const SCALE_HEADING_SD_RAD: f64 = 0.02;
/// A residual whose squared Mahalanobis distance exceeds this is not used (chi-square, three
/// degrees of freedom, 0.1 %).
pub(super) const SCALE_GATE_CHI2: f64 = 16.3;
/// The scale is kept within 1 -+ this.
pub(super) const SCALE_MAX_DEV: f64 = 0.1;
/// Smallest 1-sigma a restored scale starts with (relative): a scale moves with temperature, so a
/// saved one is never taken as exact.
pub(super) const SCALE_RESTORED_SD_MIN: f64 = 5e-4;

/// Sensor -> world rotation whose z axis is the specific force `a` and whose north (y) is the
/// horizontal part of the field `m` (TRIAD).
pub(super) fn triad(a: &Vector3<f64>, m: &Vector3<f64>) -> Option<Matrix3<f64>> {
    let z = a.try_normalize(1e-9)?;
    let x = m.cross(&z).try_normalize(1e-9)?;
    let y = z.cross(&x);
    Some(Matrix3::from_rows(&[
        x.transpose(),
        y.transpose(),
        z.transpose(),
    ]))
}

impl ScaleEst {
    pub(super) fn new(sigma: f64, path_sd: f64) -> Self {
        ScaleEst {
            path_sd,
            s: Vector3::repeat(1.0),
            p: Matrix3::identity() * (sigma * sigma),
            r0: None,
            q_s: UnitQuaternion::identity(),
            sens: Matrix3::zeros(),
            path_rad: 0.0,
            acc_sum: Vector3::zeros(),
            mag_sum: Vector3::zeros(),
            n_acc: 0,
            n_mag: 0,
            mag_ok: true,
            was_rest: false,
            steps: 0,
        }
    }

    pub(super) fn enabled(&self) -> bool {
        self.p[(0, 0)] > 0.0
    }

    /// One sample: the rest flag, the bias-corrected reading `w` (rad/s), the step the filter
    /// turned by (`dq`, from `w` and the current scale), and the rest's specific force and field
    /// (with whether the field is undisturbed).
    pub(super) fn update(
        &mut self,
        rest: bool,
        w: &Vector3<f64>,
        dq: &UnitQuaternion<f64>,
        acc: Option<&Vector3<f64>>,
        mag: Option<(&Vector3<f64>, bool)>,
        dt: f64,
    ) {
        if rest {
            self.accumulate(acc, mag);
        } else if self.was_rest && self.n_acc > 0 {
            self.rest_ended();
        }
        self.was_rest = rest;
        if self.r0.is_some() {
            let r = self.q_s.to_rotation_matrix().into_inner();
            for i in 0..3 {
                let mut col = self.sens.column_mut(i);
                col += r.column(i) * (w[i] * dt);
            }
            self.q_s *= dq;
            self.path_rad += w.norm() * dt;
        }
    }

    /// The time broke (a new time segment): the last rest no longer opens a motion the gyro
    /// integrated whole; the next rest starts a new chain.
    pub(super) fn break_chain(&mut self) {
        self.r0 = None;
        self.q_s = UnitQuaternion::identity();
        self.sens = Matrix3::zeros();
        self.path_rad = 0.0;
        self.was_rest = false;
    }

    pub(super) fn accumulate(
        &mut self,
        acc: Option<&Vector3<f64>>,
        mag: Option<(&Vector3<f64>, bool)>,
    ) {
        if !self.was_rest {
            self.acc_sum = Vector3::zeros();
            self.mag_sum = Vector3::zeros();
            self.n_acc = 0;
            self.n_mag = 0;
            self.mag_ok = true;
        }
        if let Some(a) = acc {
            self.acc_sum += a;
            self.n_acc += 1;
        }
        if let Some((m, ok)) = mag {
            self.mag_sum += m;
            self.n_mag += 1;
            self.mag_ok &= ok;
        }
    }

    /// A rest has ended: its attitude closes the last motion (one least-squares step) and opens
    /// the next.
    pub(super) fn rest_ended(&mut self) {
        let r1 = if self.mag_ok && self.n_mag > 0 {
            triad(
                &(self.acc_sum / self.n_acc as f64),
                &(self.mag_sum / self.n_mag as f64),
            )
        } else {
            None
        };
        if let (Some(r0), Some(r1)) = (self.r0, r1) {
            self.scale_step(&r0, &r1);
        }
        self.r0 = r1;
        self.q_s = UnitQuaternion::identity();
        self.sens = Matrix3::zeros();
        self.path_rad = 0.0;
    }

    /// The least-squares step from two rests' attitudes (sensor -> world).
    pub(super) fn scale_step(&mut self, r0: &Matrix3<f64>, r1: &Matrix3<f64>) {
        // Sensor at this rest -> sensor at the last one: as integrated, and as measured.
        let r_int = self.q_s.to_rotation_matrix().into_inner();
        let r_meas = r0.transpose() * r1;
        let res = nalgebra::Rotation3::from_matrix(&(r_int.transpose() * r_meas)).scaled_axis();
        let j = r_int.transpose() * self.sens;
        // Noise: tilt about every axis, heading about the vertical (this rest's sensor frame).
        let up = r1.row(2).transpose();
        let tilt_var = SCALE_TILT_SD_RAD.powi(2) + (self.path_sd * self.path_rad).powi(2);
        let rn =
            Matrix3::identity() * tilt_var + up * up.transpose() * SCALE_HEADING_SD_RAD.powi(2);
        let Some(si) = (j * self.p * j.transpose() + rn).try_inverse() else {
            return;
        };
        if res.dot(&(si * res)) > SCALE_GATE_CHI2 {
            return;
        }
        let k = self.p * j.transpose() * si;
        self.s = (self.s + k * res).map(|x| x.clamp(1.0 - SCALE_MAX_DEV, 1.0 + SCALE_MAX_DEV));
        let p = (Matrix3::identity() - k * j) * self.p;
        self.p = (p + p.transpose()) * 0.5;
        self.steps += 1;
    }
}

impl OrientationFilter {
    /// The rests gave the scale a new estimate (`ScaleEst::p` its uncertainty): its error is new,
    /// and owes nothing to the attitude and bias errors so far (the cross-covariances go; the
    /// matrix stays positive semi-definite, two blocks of it being so).
    pub(super) fn scale_learnt(&mut self) {
        for i in 0..SCALE0 {
            for j in SCALE0..NS {
                self.p[(i, j)] = 0.0;
                self.p[(j, i)] = 0.0;
            }
        }
        self.p
            .fixed_view_mut::<3, 3>(SCALE0, SCALE0)
            .copy_from(&self.scale.p);
    }
}
