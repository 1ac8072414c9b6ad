//! Temperature calibration of an IMU instance from a warm-up at rest: each accelerometer and gyro
//! axis's bias as a cubic in temperature, as the flight stacks model it.
//!
//! * ArduPilot (`AP_InertialSensor_tempcal`, and its log tool `tempcal_IMU.py`): the correction
//!   subtracts `p(T - 35) - p(T_cal - 35)` with `p(x) = (c1 x + c2 x^2 + c3 x^3) * 1e-6`, the
//!   temperature clamped to INS_TCALn_TMIN..TMAX (the learnt range), T_cal the temperature of the
//!   accelerometer/gyro calibration. No constant term: the constant is the ordinary offsets' (for
//!   the accelerometer it holds gravity, so only the bias relative to its value at 35 C is known).
//!   INS_TCALn_ACCk_X = 1e6 * (m/s^2 per C^k), GYRk = 1e6 * (rad/s per C^k).
//! * PX4 (`TemperatureCompensation::calc_thermal_offsets_3D`, `process_sensor_caldata.py`): the
//!   offset `X0 + X1 dT + X2 dT^2 + X3 dT^3`, `dT = clip(T, TMIN, TMAX) - TREF`, is subtracted
//!   from the reading (SI units, unscaled); TREF the middle of the range. The gyro's X0 is its
//!   whole bias at TREF; the accelerometer's is 0 here (its constant, with gravity, is left to the
//!   accelerometer calibration, which PX4's procedure redoes after loading these).
//!
//! The vehicle must stay still: readings are judged in short blocks ([`bins::motion`]); a warm-up
//! that moved, spans too few degrees or leaves temperature bands too thin gives no calibration,
//! with the reason and its numbers ([`Refusal`]). Each axis is a weighted least-squares cubic on
//! the means of 0.5 C bins (weights 1 / standard error^2), scored held out on alternate 1 C bands.
//!
//! Must not: do I/O or know tokio. The readings are in the axes the samples carry (the sensor's).

mod bins;
pub mod export;
pub mod onboard;
pub mod poly;

use crate::types::Sample;
use poly::{Cubic, HeldOut, Point};
use serde::{Deserialize, Serialize};

/// ArduPilot's fixed reference temperature of the cubic, deg C.
pub const ARDUPILOT_TREF_C: f64 = 35.0;
/// ArduPilot's scale of the stored coefficients (INS_TCALn_ACCk/GYRk = value * 1e6).
pub const ARDUPILOT_SCALE: f64 = 1.0e6;

/// The settings of a temperature calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TempCalSettings {
    /// Length of the blocks judged still or moving, s. Default 1.0.
    pub block_s: f64,
    /// A block whose accelerometer axis spreads more than this (standard deviation) is moving,
    /// m/s^2. Default 0.15 (a still MEMS accelerometer spreads 0.01-0.05).
    pub accel_std_max_mps2: f64,
    /// A block whose gyro axis spreads more than this, or whose mean rate departs this far from
    /// the warm-up's median, is moving, rad/s. Default 0.02 (1.1 deg/s).
    pub gyro_std_max_rad_s: f64,
    /// At most this share of the warm-up may be moving, else no calibration. Default 0.05.
    pub max_moving_fraction: f64,
    /// At most this rotation (the moving blocks' rates integrated), deg, else no calibration: a
    /// turned vehicle sees gravity on other axes. Default 2.0.
    pub max_rotation_deg: f64,
    /// Width of the temperature bins, deg C. Default 0.5.
    pub bin_c: f64,
    /// A bin needs this many still readings to be a point. Default 50.
    pub min_per_bin: usize,
    /// At most this share of the bins between the coldest and the hottest may have fewer than
    /// `min_per_bin`, else no calibration. Default 0.2.
    pub max_thin_fraction: f64,
    /// The warm-up must span this many degrees, deg C. Default 10 (ArduPilot's minimum).
    pub min_span_c: f64,
    /// Width of the alternate bands of the held-out score, deg C. Default 1.0.
    pub held_out_band_c: f64,
}

impl Default for TempCalSettings {
    fn default() -> Self {
        TempCalSettings {
            block_s: 1.0,
            accel_std_max_mps2: 0.15,
            gyro_std_max_rad_s: 0.02,
            max_moving_fraction: 0.05,
            max_rotation_deg: 2.0,
            bin_c: 0.5,
            min_per_bin: 50,
            max_thin_fraction: 0.2,
            min_span_c: 10.0,
            held_out_band_c: 1.0,
        }
    }
}

/// What the data lack for a temperature calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum Refusal {
    /// The temperature spans fewer degrees than needed.
    Span { span_c: f64, min_span_c: f64 },
    /// The vehicle moved during the warm-up.
    Motion {
        moving_s: f64,
        moving_fraction: f64,
        rotated_deg: f64,
        peak_rate_dps: f64,
        max_moving_fraction: f64,
        max_rotation_deg: f64,
    },
    /// Too many temperature bands hold too few still readings.
    TooFewPoints {
        thin_bands: usize,
        bands: usize,
        fewest: usize,
        min_per_band: usize,
        band_c: f64,
    },
    /// The fit could not be made (a singular system).
    Singular,
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::Span { span_c, min_span_c } => write!(
                f,
                "the temperature spans {span_c:.1} C, under the {min_span_c:.0} C needed"
            ),
            Refusal::Motion {
                moving_s,
                moving_fraction,
                rotated_deg,
                peak_rate_dps,
                max_moving_fraction,
                max_rotation_deg,
            } => write!(
                f,
                "the vehicle moved during the warm-up: {moving_s:.0} s ({:.1} %, at most {:.0} %), turned up to {rotated_deg:.1} deg (at most {max_rotation_deg:.0}), peak {peak_rate_dps:.1} deg/s",
                100.0 * moving_fraction,
                100.0 * max_moving_fraction
            ),
            Refusal::TooFewPoints {
                thin_bands,
                bands,
                fewest,
                min_per_band,
                band_c,
            } => write!(
                f,
                "{thin_bands} of {bands} bands of {band_c} C hold fewer than {min_per_band} still readings (the fewest {fewest})"
            ),
            Refusal::Singular => write!(f, "the cubic could not be fitted (singular system)"),
        }
    }
}

/// One axis's bias curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AxisCurve {
    /// c0..c3 of the bias in (T - 35 C), the sensor's unit per C^k (ArduPilot's c1..c3 times
    /// 1e6 are INS_TCALn_*; c0, the value at 35 C, is not exported).
    pub ardupilot: [f64; 4],
    /// X0..X3 of the offset in (T - TREF), the sensor's unit per C^k (PX4's TC_*n_Xk_axis).
    pub px4: [f64; 4],
    /// The bias variation over the range (largest minus smallest of the curve), the sensor's unit.
    pub variation: f64,
    /// RMS of the points about the curve, and the median standard error of a point.
    pub residual_rms: f64,
    pub point_se: f64,
    /// Fitted on alternate bands, scored on the others.
    pub held_out: Option<HeldOut>,
}

/// A sensor's three axes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorCurves {
    /// The sensor's unit: "m/s^2" or "rad/s".
    pub units: String,
    pub axes: [AxisCurve; 3],
}

/// A temperature calibration of one IMU instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TempCal {
    /// The range of the points, deg C (INS_TCALn_TMIN/TMAX, TC_*n_TMIN/TMAX).
    pub tmin_c: f64,
    pub tmax_c: f64,
    /// PX4's reference temperature (the middle of the range), deg C.
    pub px4_tref_c: f64,
    /// Bins used as points, and their width, deg C.
    pub points: usize,
    pub bin_c: f64,
    pub accel: SensorCurves,
    pub gyro: SensorCurves,
}

/// What a warm-up gave.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum TempOutcome {
    Calibrated(Box<TempCal>),
    Refused(Refusal),
}

/// The temperature calibration of one IMU instance with what it was made from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TempCalResult {
    /// Samples with accelerometer, gyro and temperature; the rest skipped.
    pub samples: usize,
    pub skipped: usize,
    /// The range of the temperature (block means), deg C.
    pub range_c: [f64; 2],
    /// Share of the warm-up judged still.
    pub still_fraction: f64,
    #[serde(flatten)]
    pub outcome: TempOutcome,
}

/// Whether any sample carries a temperature (no temperature: no temperature calibration at all).
/// A stream whose every temperature is exactly 0 has none: loggers write 0 for a sensor without one.
pub fn has_temperature(samples: &[Sample]) -> bool {
    samples
        .iter()
        .any(|s| s.temp_c.is_some_and(|t| t.is_finite() && t != 0.0))
}

/// The temperature calibration of one IMU instance's samples (time-ordered, sensor axes).
pub fn calibrate(samples: &[Sample], s: &TempCalSettings) -> TempCalResult {
    let (r, skipped) = bins::readings(samples);
    let blocks = bins::blocks(&r, s.block_s);
    let (lo, hi) = blocks
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), b| {
            (l.min(b.temp_c), h.max(b.temp_c))
        });
    let mut res = TempCalResult {
        samples: r.len(),
        skipped,
        range_c: if lo <= hi { [lo, hi] } else { [f64::NAN; 2] },
        still_fraction: 0.0,
        outcome: TempOutcome::Refused(Refusal::Singular),
    };
    let span = |lo: f64, hi: f64| if lo <= hi { hi - lo } else { 0.0 };
    if span(lo, hi) < s.min_span_c {
        res.outcome = TempOutcome::Refused(Refusal::Span {
            span_c: span(lo, hi),
            min_span_c: s.min_span_c,
        });
        return res;
    }
    let m = bins::motion(&blocks, s);
    res.still_fraction = 1.0 - m.moving_fraction;
    if m.moving_fraction > s.max_moving_fraction || m.rotated_deg > s.max_rotation_deg {
        res.outcome = TempOutcome::Refused(Refusal::Motion {
            moving_s: m.moving_s,
            moving_fraction: m.moving_fraction,
            rotated_deg: m.rotated_deg,
            peak_rate_dps: m.peak_rate_dps,
            max_moving_fraction: s.max_moving_fraction,
            max_rotation_deg: s.max_rotation_deg,
        });
        return res;
    }
    let all = bins::temperature_bins(&r, &blocks, &m.still, s.bin_c);
    let thin = all.iter().filter(|b| b.n < s.min_per_bin).count();
    if all.is_empty() || thin as f64 > s.max_thin_fraction * all.len() as f64 {
        res.outcome = TempOutcome::Refused(Refusal::TooFewPoints {
            thin_bands: thin,
            bands: all.len(),
            fewest: all.iter().map(|b| b.n).min().unwrap_or(0),
            min_per_band: s.min_per_bin,
            band_c: s.bin_c,
        });
        return res;
    }
    let kept: Vec<&bins::Bin> = all.iter().filter(|b| b.n >= s.min_per_bin).collect();
    let channel = |k: usize| -> Vec<Point> { kept.iter().map(|b| b.point(k)).collect() };
    let temps: Vec<f64> = channel(0).iter().map(|p| p.temp_c).collect();
    let (tmin, tmax) = temps
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), t| {
            (l.min(*t), h.max(*t))
        });
    if tmax - tmin < s.min_span_c {
        res.outcome = TempOutcome::Refused(Refusal::Span {
            span_c: tmax - tmin,
            min_span_c: s.min_span_c,
        });
        return res;
    }
    let tref = 0.5 * (tmin + tmax);
    let curves = |first: usize, units: &str, absolute: bool| -> Option<SensorCurves> {
        let axis = |k: usize| axis_curve(&channel(first + k), tmin, tmax, tref, absolute, s);
        Some(SensorCurves {
            units: units.into(),
            axes: [axis(0)?, axis(1)?, axis(2)?],
        })
    };
    res.outcome = match (curves(0, "m/s^2", false), curves(3, "rad/s", true)) {
        (Some(accel), Some(gyro)) => TempOutcome::Calibrated(Box::new(TempCal {
            tmin_c: tmin,
            tmax_c: tmax,
            px4_tref_c: tref,
            points: kept.len(),
            bin_c: s.bin_c,
            accel,
            gyro,
        })),
        _ => TempOutcome::Refused(Refusal::Singular),
    };
    res
}

/// One axis's cubic: ArduPilot's about 35 C, PX4's about `tref` (with its constant when
/// `absolute`, else 0 there), its spread, residual and held-out score.
fn axis_curve(
    pts: &[Point],
    tmin: f64,
    tmax: f64,
    tref: f64,
    absolute: bool,
    s: &TempCalSettings,
) -> Option<AxisCurve> {
    let c = poly::fit(pts, 3, ARDUPILOT_TREF_C)?;
    let mut px4 = c.about(tref);
    if !absolute {
        px4.c[0] = 0.0;
    }
    let grid = (0..=100).map(|k| c.eval(tmin + (tmax - tmin) * k as f64 / 100.0));
    let (lo, hi) = grid.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
        (l.min(v), h.max(v))
    });
    let mut se: Vec<f64> = pts.iter().map(|p| p.se).collect();
    se.sort_by(f64::total_cmp);
    Some(AxisCurve {
        ardupilot: c.c,
        px4: px4.c,
        variation: hi - lo,
        residual_rms: poly::rms_about(pts, |t| c.eval(t)),
        point_se: se.get(se.len() / 2).copied().unwrap_or(f64::NAN),
        held_out: poly::held_out(pts, s.held_out_band_c),
    })
}

impl AxisCurve {
    /// The fitted bias at `temp_c` (ArduPilot's cubic, with its constant).
    pub fn bias_at(&self, temp_c: f64) -> f64 {
        Cubic {
            ref_c: ARDUPILOT_TREF_C,
            c: self.ardupilot,
        }
        .eval(temp_c)
    }
}

/// The binned points of one instance's still readings, per channel (accelerometer x, y, z, gyro
/// x, y, z), as the fit sees them: for a peer's fit on the same points. Empty when the warm-up
/// is refused before binning.
pub fn binned_points(samples: &[Sample], s: &TempCalSettings) -> Vec<[Point; 6]> {
    let (r, _) = bins::readings(samples);
    let blocks = bins::blocks(&r, s.block_s);
    let m = bins::motion(&blocks, s);
    bins::temperature_bins(&r, &blocks, &m.still, s.bin_c)
        .iter()
        .filter(|b| b.n >= s.min_per_bin)
        .map(|b| std::array::from_fn(|k| b.point(k)))
        .collect()
}

/// Whether a temperature calibration the flight controller applied before logging was undone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnboardTcal {
    /// The log's parameters enable one (INS_TCALn_ENABLE 1, TC_A/G_ENABLE 1): undone first.
    Undone,
    /// The log's parameters do not enable one (disabled, learning, or no such parameters): the
    /// readings are the sensor's.
    NotEnabled,
    /// The log's parameters enable one but name no slot of this instance's device id (PX4's
    /// TC_An_ID / TC_Gn_ID; a stream whose log gives no device id): not undone, the correction
    /// stays in the readings.
    NotMatched,
    /// The input carries no parameters (CSV, telemetry).
    NoParameters,
}

/// The report's record of one IMU instance's temperature calibration (`temperature`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TempCalReport {
    /// The log's instance (`IMU2+MAG2`, `primary` for a single stream).
    pub instance: String,
    /// The IMU's instance number, 0-based (ArduPilot's INS_TCAL{imu + 1}, PX4's TC_*{imu}).
    pub imu: usize,
    /// The accelerometer's device id, where the log gives it (PX4's TC_*n_ID).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_id: Option<u32>,
    pub onboard: OnboardTcal,
    #[serde(flatten)]
    pub result: TempCalResult,
}

impl TempCalReport {
    /// Whether this instance got a temperature calibration.
    pub fn calibrated(&self) -> bool {
        matches!(self.result.outcome, TempOutcome::Calibrated(_))
    }
}
