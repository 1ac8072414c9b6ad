//! The physical range of every catalogue effect's parameters, and the record of why a fitted
//! effect lies outside it ([`OutOfRange`], numbers and limits; rendered to text only at the edge).
//! An effect outside its range is not named: the fit has bent it to absorb something else.

use super::layout::{decode, sl3, Ctx, Layout};
use super::Effect;
use nalgebra::DVector;
use serde::{Deserialize, Serialize};

/// Largest symmetric off-diagonal term of a normalised matrix (cross_axis), 1. A magnetometer's
/// cross-axis sensitivity is a few percent by its datasheet and the soft iron of a frame adds a few
/// more; 20 % is a matrix the fit bent to absorb something else.
pub(crate) const MAX_CROSS_AXIS: f64 = 0.2;
/// Largest rotation between the magnetometer and accelerometer frames, deg. Boards are mounted by
/// hand to a few degrees; beyond 10 deg (and on to 45 deg, where the next rotation of the
/// flight stacks' table begins) the compass's mounting setting is wrong rather than the compass
/// misaligned, which the mounting check of `replay` names.
pub(crate) const MAX_MISALIGNMENT_DEG: f64 = 10.0;
/// Largest magnetometer bias per degree, uT/degC: magnetometer datasheets give offset drifts of
/// tenths of a uT per degree; 2 uT/degC over a 20 degC warm-up would be most of the earth field.
pub(crate) const MAX_MAG_TEMP_UT_PER_C: f64 = 2.0;
/// Largest accelerometer bias per degree, m/s^2/degC: MEMS accelerometers drift by at most a
/// few mg per degree (0.05 m/s^2/degC is 5 mg/degC).
pub(crate) const MAX_ACCEL_TEMP_MPS2_PER_C: f64 = 0.05;
/// Largest motor field over the driver's range, in multiples of the earth field: a compass that
/// close to the power lead would not point north at all.
pub(crate) const MAX_MOTOR_FIELD_RATIO: f64 = 2.0;
/// Largest mounting yaw against the reference attitude, deg; beyond it the mounting setting is
/// wrong (a rotation of the table), not the mounting off by a little.
pub(crate) const MAX_HEADING_OFFSET_DEG: f64 = 30.0;
/// Largest per-axis cubic scale coefficient, 1: the nonlinearity datasheets give is under 1 % of
/// full scale; 15 % at the field's magnitude is a fit absorbing something else.
pub(crate) const MAX_CUBIC: f64 = 0.15;
/// Largest change of the gyro bias over the log's time or temperature range, rad/s (11 deg/s: more
/// than any MEMS gyro's bias drift).
pub(crate) const MAX_GYRO_BIAS_CHANGE_RAD_S: f64 = 0.2;
/// Each diagonal entry of a calibration matrix scaled to unit determinant stays in this range
/// with the effect in (else the base calibration collapsed to absorb the effect), 1.
pub(crate) const SANE_SCALE: std::ops::Range<f64> = 0.5..2.0;

/// Which sensor's calibration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SensorKind {
    Mag,
    Accel,
}

impl SensorKind {
    fn name(self) -> &'static str {
        match self {
            SensorKind::Mag => "mag",
            SensorKind::Accel => "accel",
        }
    }
}

/// Why a fitted effect lies outside its physical range: the value found and the limit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum OutOfRange {
    /// Largest cross-axis term, relative to the diagonal (1).
    CrossAxis { off_diagonal: f64, limit: f64 },
    /// Rotation between the magnetometer and accelerometer frames, deg.
    Misalignment { rotation_deg: f64, limit_deg: f64 },
    /// Largest magnetometer bias per degree, uT/degC.
    MagTemperature { ut_per_c: f64, limit_ut_per_c: f64 },
    /// Largest accelerometer bias per degree, m/s^2/degC.
    AccelTemperature {
        mps2_per_c: f64,
        limit_mps2_per_c: f64,
    },
    /// Motor field over the driver's range, uT, against the limit in uT.
    MotorField { field_ut: f64, limit_ut: f64 },
    /// Mounting yaw, deg.
    HeadingOffset { offset_deg: f64, limit_deg: f64 },
    /// Largest cubic scale coefficient, 1.
    Cubic { coefficient: f64, limit: f64 },
    /// Gyro bias change over the log's time, rad/s.
    GyroDriftOverTime { change_rad_s: f64, limit_rad_s: f64 },
    /// Gyro bias change over the log's temperature range, rad/s.
    GyroDriftOverTemperature { change_rad_s: f64, limit_rad_s: f64 },
    /// A diagonal entry of the base calibration's matrix (unit determinant) left its sane range:
    /// the base calibration collapsed to absorb the effect.
    ScaleCollapsed {
        sensor: SensorKind,
        axis: usize,
        scale: f64,
        low: f64,
        high: f64,
    },
    /// The effect has no parameters in this layout.
    NotInModel,
}

impl std::fmt::Display for OutOfRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use OutOfRange::*;
        match self {
            CrossAxis {
                off_diagonal,
                limit,
            } => write!(f, "off-diagonal {off_diagonal:.3} beyond {limit}"),
            Misalignment {
                rotation_deg,
                limit_deg,
            } => write!(f, "rotation {rotation_deg:.2} deg beyond {limit_deg} deg"),
            MagTemperature {
                ut_per_c,
                limit_ut_per_c,
            } => write!(f, "mag {ut_per_c:.3} uT/degC beyond {limit_ut_per_c}"),
            AccelTemperature {
                mps2_per_c,
                limit_mps2_per_c,
            } => write!(f, "accel {mps2_per_c:.4} m/s^2/degC beyond {limit_mps2_per_c}"),
            MotorField { field_ut, limit_ut } => write!(
                f,
                "motor field {field_ut:.2} uT over the driver range beyond {limit_ut:.1} uT"
            ),
            HeadingOffset {
                offset_deg,
                limit_deg,
            } => write!(f, "heading offset {offset_deg:.2} deg beyond {limit_deg} deg"),
            Cubic { coefficient, limit } => {
                write!(f, "cubic coefficient {coefficient:.3} beyond {limit}")
            }
            GyroDriftOverTime {
                change_rad_s,
                limit_rad_s,
            } => write!(
                f,
                "gyro bias change {change_rad_s:.3} rad/s over the log beyond {limit_rad_s}"
            ),
            GyroDriftOverTemperature {
                change_rad_s,
                limit_rad_s,
            } => write!(
                f,
                "gyro bias change {change_rad_s:.3} rad/s over the temperature range beyond {limit_rad_s}"
            ),
            ScaleCollapsed {
                sensor,
                axis,
                scale,
                low,
                high,
            } => write!(
                f,
                "{} scale {} collapsed to {scale:.3} (sane {low} to {high})",
                sensor.name(),
                ["x", "y", "z"][(*axis).min(2)]
            ),
            NotInModel => f.write_str("the effect has no parameters in this model"),
        }
    }
}

/// The reasons as one line ("; " between them).
pub(crate) fn render(reasons: &[OutOfRange]) -> String {
    reasons
        .iter()
        .map(|r| r.to_string())
        .collect::<Vec<_>>()
        .join("; ")
}

fn maxabs(v: &[f64]) -> f64 {
    v.iter().fold(0.0f64, |a, x| a.max(x.abs()))
}

/// The temperature coefficients against their ranges (magnetometer part, then accelerometer).
fn temperature_ranges(q: &[f64], b: &super::layout::EffBlock, out: &mut Vec<OutOfRange>) {
    let mut k = 0;
    if b.mag {
        let m = maxabs(&q[k..k + 3]);
        if !(m < MAX_MAG_TEMP_UT_PER_C) {
            out.push(OutOfRange::MagTemperature {
                ut_per_c: m,
                limit_ut_per_c: MAX_MAG_TEMP_UT_PER_C,
            });
        }
        k += 3;
    }
    if b.acc {
        let m = maxabs(&q[k..k + 3]);
        if !(m < MAX_ACCEL_TEMP_MPS2_PER_C) {
            out.push(OutOfRange::AccelTemperature {
                mps2_per_c: m,
                limit_mps2_per_c: MAX_ACCEL_TEMP_MPS2_PER_C,
            });
        }
    }
}

/// The gyro drift's change over the log's time and temperature range against its limit.
fn gyro_drift_ranges(ctx: &Ctx, q: &[f64], b: &super::layout::EffBlock, out: &mut Vec<OutOfRange>) {
    let mut k = 0;
    if b.time {
        let m = maxabs(&q[k..k + 3]) * ctx.time_span;
        if !(m < MAX_GYRO_BIAS_CHANGE_RAD_S) {
            out.push(OutOfRange::GyroDriftOverTime {
                change_rad_s: m,
                limit_rad_s: MAX_GYRO_BIAS_CHANGE_RAD_S,
            });
        }
        k += 3;
    }
    if b.temp {
        let m = maxabs(&q[k..k + 3]) * ctx.temp_range;
        if !(m < MAX_GYRO_BIAS_CHANGE_RAD_S) {
            out.push(OutOfRange::GyroDriftOverTemperature {
                change_rad_s: m,
                limit_rad_s: MAX_GYRO_BIAS_CHANGE_RAD_S,
            });
        }
    }
}

/// The effect's own parameters against their ranges.
fn effect_ranges(ctx: &Ctx, e: Effect, q: &[f64], b: &super::layout::EffBlock) -> Vec<OutOfRange> {
    let mut out = vec![];
    let mut check = |ok: bool, r: OutOfRange| {
        if !ok {
            out.push(r)
        }
    };
    match e {
        Effect::CrossAxis => check(
            maxabs(q) < MAX_CROSS_AXIS,
            OutOfRange::CrossAxis {
                off_diagonal: maxabs(q),
                limit: MAX_CROSS_AXIS,
            },
        ),
        Effect::MagAccelMisalignment => {
            let a = sl3(q).norm().to_degrees();
            check(
                a < MAX_MISALIGNMENT_DEG,
                OutOfRange::Misalignment {
                    rotation_deg: a,
                    limit_deg: MAX_MISALIGNMENT_DEG,
                },
            );
        }
        Effect::TemperatureBias => temperature_ranges(q, b, &mut out),
        Effect::MotorInterference => {
            let k = sl3(q).norm() * ctx.drv_range;
            let limit = MAX_MOTOR_FIELD_RATIO * ctx.s0m;
            check(
                k < limit,
                OutOfRange::MotorField {
                    field_ut: k,
                    limit_ut: limit,
                },
            );
        }
        Effect::HeadingOffset => {
            let a = q[0].to_degrees().abs();
            check(
                a < MAX_HEADING_OFFSET_DEG,
                OutOfRange::HeadingOffset {
                    offset_deg: a,
                    limit_deg: MAX_HEADING_OFFSET_DEG,
                },
            );
        }
        Effect::ScaleNonlinearity => check(
            maxabs(q) < MAX_CUBIC,
            OutOfRange::Cubic {
                coefficient: maxabs(q),
                limit: MAX_CUBIC,
            },
        ),
        Effect::GyroBiasDrift => gyro_drift_ranges(ctx, q, b, &mut out),
    }
    out
}

/// Physical plausibility of effect `e` in the fitted parameters `p`: every parameter of the
/// effect inside its range and the base calibration still sane. Empty when plausible.
pub(super) fn out_of_range(
    ctx: &Ctx,
    lay: &Layout,
    p: &DVector<f64>,
    e: Effect,
) -> Vec<OutOfRange> {
    let Some(b) = lay.block(e) else {
        return vec![OutOfRange::NotInModel];
    };
    let q: Vec<f64> = (0..b.len).map(|k| p[b.start + k]).collect();
    let mut out = effect_ranges(ctx, e, &q, b);
    let md = decode(ctx, lay, p.as_slice());
    for (sensor, a) in [(SensorKind::Mag, md.am), (SensorKind::Accel, md.aa)] {
        let d = a.determinant();
        if d.abs() > 0.0 {
            let nm = a / d.abs().cbrt();
            if let Some(axis) = (0..3).find(|&i| !SANE_SCALE.contains(&nm[(i, i)])) {
                out.push(OutOfRange::ScaleCollapsed {
                    sensor,
                    axis,
                    scale: nm[(axis, axis)],
                    low: SANE_SCALE.start,
                    high: SANE_SCALE.end,
                });
            }
        }
    }
    out
}
