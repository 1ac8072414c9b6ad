//! What a refit takes and gives, and the fits from a snapshot: pure, on any thread. The
//! magnetometer's and the accelerometer's norm fits (points held out when asked), the gyro bias
//! from the poses at rest, and `full12`'s rotation from the dip.

use super::accept::{set_fail, SensorSpec};
use super::sensor::fit_sensor;
use crate::calib::fit::FitFailure;
use crate::calib::gate::Pose;
use crate::calib::model::{CalModel, Calibration, ModelKind};
use crate::calib::outcome::{CalStatus, GyroCalibration, SensorResult};
use crate::calib::settings::{AccelUnits, CalibSettings, MagModelChoice, ModelChoice};
use crate::types::{norm, CalUnits, Unit, Vec3};

/// Everything a refit needs, cloned out of the pipeline so the fit can run elsewhere.
#[derive(Debug, Clone)]
pub struct FitInput {
    pub mag_points: Vec<Vec3>,
    pub poses: Vec<Pose>,
    pub mag_units: Unit,
    pub gyro_units: Unit,
    /// From config.
    pub accel_units: AccelUnits,
    /// Hold every this-many-th magnetometer point and pose out of the fits (0: fit on all); see
    /// [`hold_out`].
    pub hold_out_every: usize,
    /// The magnetometer's own noise (one axis, the stream's units) from its readings
    /// ([`NoiseMeter`](super::NoiseMeter)); `None` before enough readings.
    pub mag_noise: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct FitResults {
    pub mag: SensorResult,
    pub accel: SensorResult,
    pub gyro: GyroCalibration,
}

impl FitInput {
    /// The units the magnetometer's calibration is reported in ([`fit_mag`]).
    pub fn mag_cal_units(&self) -> CalUnits {
        CalUnits::of(self.mag_units, CalUnits::Ut)
    }
}

/// Gyro bias from the static poses at rest ([`Pose::at_rest`]): the mean of pose means. A pose
/// that turned (a steady turn holds the gyro steady too) says nothing about the bias.
fn fit_gyro(poses: &[Pose], units: Unit) -> GyroCalibration {
    let turning = poses
        .iter()
        .filter(|p| p.gyro.is_some() && !p.at_rest())
        .count();
    let g: Vec<Vec3> = poses
        .iter()
        .filter(|p| p.at_rest())
        .filter_map(|p| p.gyro)
        .collect();
    // A gyro at rest reading more than 35 rad/s (2000 deg/s) is in counts, whatever the input said.
    let mut norms: Vec<f64> = g.iter().map(norm).collect();
    norms.sort_by(|a, b| a.total_cmp(b));
    let counts = units == Unit::Counts || norms.get(norms.len() / 2).is_some_and(|m| *m > 35.0);
    let units = if counts {
        CalUnits::Counts
    } else {
        CalUnits::RadS
    };
    if g.len() < 2 {
        return GyroCalibration {
            status: CalStatus::Failed,
            failure: Some(FitFailure::NotEnoughSamples),
            units,
            bias: [0.0; 3],
            bias_sigma: [0.0; 3],
            poses_used: g.len(),
            poses_turning: turning,
            scale: None,
            scale_failure: None,
        };
    }
    let n = g.len() as f64;
    let mut mean = [0.0; 3];
    for v in &g {
        for k in 0..3 {
            mean[k] += v[k] / n;
        }
    }
    let mut sd = [0.0; 3];
    for v in &g {
        for k in 0..3 {
            sd[k] += (v[k] - mean[k]).powi(2) / (n - 1.0);
        }
    }
    GyroCalibration {
        status: CalStatus::Ok,
        failure: None,
        units,
        bias: mean,
        bias_sigma: sd.map(|v| (v / n).sqrt()),
        poses_used: g.len(),
        poses_turning: turning,
        scale: None,
        scale_failure: None,
    }
}

/// Detect accelerometer units from the static norms: near g means m/s^2, otherwise counts.
pub(crate) fn accel_units(poses: &[Pose], setting: AccelUnits) -> Unit {
    match setting {
        AccelUnits::Si => Unit::Si,
        AccelUnits::Counts => Unit::Counts,
        AccelUnits::Auto => {
            let mut norms: Vec<f64> = poses.iter().map(|p| norm(&p.accel)).collect();
            if norms.is_empty() {
                return Unit::Si;
            }
            norms.sort_by(|a, b| a.total_cmp(b));
            let med = norms[norms.len() / 2];
            if (5.0..=15.0).contains(&med) {
                Unit::Si
            } else {
                Unit::Counts
            }
        }
    }
}

/// Fewest points held out for a comparison: below `MIN_HELD_OUT * every` points none are.
pub(crate) const MIN_HELD_OUT: usize = 4;

/// Every `every`-th point (the 1st, the `every+1`-th, ...) held out, the rest to fit: `(fit, held)`.
/// Deterministic; on the direction bins' points (ordered by direction) the held-out ones spread
/// over the whole sphere, on poses (in time order) over the whole run. With `every` 0 or fewer
/// than `MIN_HELD_OUT * every` points, none are held out.
pub(crate) fn hold_out(points: &[Vec3], every: usize) -> (Vec<Vec3>, Vec<Vec3>) {
    if every < 2 || points.len() < MIN_HELD_OUT * every {
        return (points.to_vec(), vec![]);
    }
    let (mut fit, mut held) = (Vec::new(), Vec::new());
    for (i, p) in points.iter().enumerate() {
        if i % every == 0 {
            held.push(*p);
        } else {
            fit.push(*p);
        }
    }
    (fit, held)
}

/// All fits from a snapshot. Pure; may run on any thread.
pub fn fit_all(input: &FitInput, cfg: &CalibSettings) -> FitResults {
    let mag = fit_mag(input, cfg);
    let (accel, gyro) = fit_accel_gyro(input, cfg);
    join_fits(mag, accel, gyro, input, cfg)
}

/// The magnetometer's part of [`fit_all`], before [`join_fits`]: on its own so that a caller can
/// run it beside [`fit_accel_gyro`] (the two share nothing).
pub fn fit_mag(input: &FitInput, cfg: &CalibSettings) -> SensorResult {
    let mag_full12 = cfg.fit.mag_model == MagModelChoice::Full12;
    let (mag_fit, mag_held) = hold_out(&input.mag_points, input.hold_out_every);
    let mut mag = fit_sensor(
        &mag_fit,
        &SensorSpec {
            model: if mag_full12 {
                ModelChoice::Sym9
            } else {
                cfg.fit.mag_model.into()
            },
            target_norm: None,
            units: input.mag_cal_units(),
            units_known: input.mag_units == Unit::Si,
            limits: &cfg.accept.mag,
            is_accel: false,
            noise: input.mag_noise,
        },
    );
    mag.held_out = mag_held;
    mag
}

/// The accelerometer's and the gyroscope's part of [`fit_all`] (the gyro bias from the poses).
pub fn fit_accel_gyro(input: &FitInput, cfg: &CalibSettings) -> (SensorResult, GyroCalibration) {
    let au = accel_units(&input.poses, input.accel_units);
    let accel_points: Vec<Vec3> = input.poses.iter().map(|p| p.accel).collect();
    let (accel_fit, accel_held) = hold_out(&accel_points, input.hold_out_every);
    let mut accel = fit_sensor(
        &accel_fit,
        &SensorSpec {
            model: cfg.fit.accel_model,
            target_norm: Some(cfg.fit.gravity_mps2),
            units: CalUnits::Mps2,
            units_known: au == Unit::Si,
            limits: &cfg.accept.accel,
            is_accel: true,
            noise: None,
        },
    );
    accel.held_out = accel_held;
    let gyro = fit_gyro(&input.poses, input.gyro_units);
    (accel, gyro)
}

/// The results of [`fit_mag`] and [`fit_accel_gyro`] put together: with `fit.mag_model =
/// "full12"` the magnetometer's rotation follows from the dip seen against the accelerometer's.
pub fn join_fits(
    mut mag: SensorResult,
    accel: SensorResult,
    gyro: GyroCalibration,
    input: &FitInput,
    cfg: &CalibSettings,
) -> FitResults {
    if cfg.fit.mag_model == MagModelChoice::Full12 {
        mag_rotation_from_dip(&mut mag, &accel, &input.poses);
    }
    FitResults { mag, accel, gyro }
}

/// `full12` magnetometer: the symmetric (sym9) fit, then the rotation that norms cannot see, from the
/// gravity-field angle at static poses against the calibrated accelerometer (matrix = R S).
fn mag_rotation_from_dip(mag: &mut SensorResult, accel: &SensorResult, poses: &[Pose]) {
    let Some(mcal) = mag.calibration else { return };
    let fail = |mag: &mut SensorResult, d: String| {
        set_fail(&mut mag.report, FitFailure::NotIdentifiable, d);
        mag.report.model = CalModel::Full12;
        mag.calibration = None;
    };
    let Some(acal) = accel.calibration else {
        return fail(mag, "full12 needs an accepted accelerometer calibration to fix the rotation from the dip angle".into());
    };
    let (mut gs, mut ms) = (vec![], vec![]);
    for p in poses {
        if let Some(m) = p.mag {
            let f = acal.apply(&p.accel);
            gs.push([-f[0], -f[1], -f[2]]);
            ms.push(mcal.apply(&m));
        }
    }
    match crate::calib::fit::fit_dip_rotation(&gs, &ms) {
        Some((r, _dip, _rms, cond)) if cond.is_finite() && cond < 1e8 => {
            let m = r * mcal.matrix3();
            let cal = Calibration { model: ModelKind::Full12, offset: mcal.offset, matrix: crate::calib::model::mat_to_rows(&m) };
            mag.report.model = CalModel::Full12;
            mag.report.matrix = cal.matrix;
            mag.calibration = Some(cal);
            mag.dirs_after = mag.dirs_after.iter().map(|v| crate::attitude::rotate(&r, v)).collect();
        }
        _ => fail(mag, format!("full12: {} static poses with accel and mag do not fix the rotation (need 6+ in varied attitudes)", gs.len())),
    }
}
