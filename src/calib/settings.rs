//! The calibration's settings: which model each sensor is fitted with, how often it is refitted,
//! and the bounds a fit must meet to be accepted. Plain data with documented defaults; the
//! configuration (`[fit]`, `[accept]`, `input.accel_units`) holds them and the pipeline reads them.

use crate::calib::gate::GateConfig;
use crate::calib::model::ModelKind;
use serde::{Deserialize, Serialize};

/// `input.accel_units`: the accelerometer's units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AccelUnits {
    /// m/s^2 when the static norm is near g, else counts.
    Auto,
    /// m/s^2.
    Si,
    Counts,
}

/// `fit.accel_model`, and the model a norm fit is asked for: one model, the simplest the data
/// support ("auto"), or six-position (accelerometer only).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelChoice {
    /// The simplest of sphere, diag6 and sym9 the data support (nested F-test).
    Auto,
    Sphere,
    Diag6,
    Sym9,
    Full12,
    /// Six static poses near the axes (accelerometer only).
    SixPosition,
}

impl ModelChoice {
    /// The name in the configuration and the report.
    pub fn name(self) -> &'static str {
        match self {
            ModelChoice::Auto => "auto",
            ModelChoice::SixPosition => "six_position",
            m => m.kind().map_or("?", ModelKind::name),
        }
    }

    /// The one model asked for, if one is.
    pub fn kind(self) -> Option<ModelKind> {
        match self {
            ModelChoice::Auto | ModelChoice::SixPosition => None,
            ModelChoice::Sphere => Some(ModelKind::Sphere),
            ModelChoice::Diag6 => Some(ModelKind::Diag6),
            ModelChoice::Sym9 => Some(ModelKind::Sym9),
            ModelChoice::Full12 => Some(ModelKind::Full12),
        }
    }
}

/// `fit.mag_model`: [`ModelChoice`] without six-position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MagModelChoice {
    Auto,
    Sphere,
    Diag6,
    Sym9,
    Full12,
}

impl From<ModelChoice> for crate::calib::model::CalModel {
    /// What a result names when nothing was fitted under this choice.
    fn from(m: ModelChoice) -> Self {
        use crate::calib::model::CalModel;
        match m {
            ModelChoice::Auto => CalModel::Auto,
            ModelChoice::SixPosition => CalModel::SixPosition,
            ModelChoice::Sphere => CalModel::Sphere,
            ModelChoice::Diag6 => CalModel::Diag6,
            ModelChoice::Sym9 => CalModel::Sym9,
            ModelChoice::Full12 => CalModel::Full12,
        }
    }
}

impl From<MagModelChoice> for ModelChoice {
    fn from(m: MagModelChoice) -> ModelChoice {
        match m {
            MagModelChoice::Auto => ModelChoice::Auto,
            MagModelChoice::Sphere => ModelChoice::Sphere,
            MagModelChoice::Diag6 => ModelChoice::Diag6,
            MagModelChoice::Sym9 => ModelChoice::Sym9,
            MagModelChoice::Full12 => ModelChoice::Full12,
        }
    }
}

impl From<ModelKind> for MagModelChoice {
    fn from(k: ModelKind) -> MagModelChoice {
        match k {
            ModelKind::Sphere => MagModelChoice::Sphere,
            ModelKind::Diag6 => MagModelChoice::Diag6,
            ModelKind::Sym9 => MagModelChoice::Sym9,
            ModelKind::Full12 => MagModelChoice::Full12,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct FitConfig {
    /// Magnetometer model: "auto" (the simplest the data support, by a nested F-test), "sphere",
    /// "diag6", "sym9", "full12". Default: "auto".
    pub mag_model: MagModelChoice,
    /// Accelerometer model: as `mag_model`, or "six_position". Default: "auto".
    pub accel_model: ModelChoice,
    /// Refit every this many seconds of data, s. Default: 10.
    pub refit_every_s: f64,
    /// Local gravity, m/s^2 (the accelerometer's calibrated norm). Default: 9.80665.
    pub gravity_mps2: f64,
    /// Minimum angle between kept magnetometer samples, deg. Default: 1.
    pub min_separation_deg: f64,
    /// Before a first fit, the magnetometer's centre (for the progress regions and the direction
    /// bins) is taken from the kept points once they spread enough: their standard deviation along
    /// their narrowest direction at least this many field radii (0.25: about a cap reaching 80 deg
    /// from its middle, filled; a still or barely turned sensor stays far below), and they lie on
    /// one sphere (see [`crate::calib::pipeline::Pipeline::mag_centre`]). Field radii. Default: 0.15.
    pub centre_min_spread_radii: f64,
    /// The scalar Kalman prefilter of Ren and Liu, "Calibration of MEMS Accelerometers and
    /// Magnetometers for Rotor UAV Attitude Estimation", on accel and mag before gating and
    /// fitting. Default: false.
    pub prefilter: bool,
    /// Its process noise Q (squared input units per sample). Default: 1e-4 (Ren and Liu's).
    pub prefilter_q: f64,
    /// Its measurement noise R (squared input units). Default: 1 (Ren and Liu's).
    pub prefilter_r: f64,
}

impl Default for FitConfig {
    fn default() -> Self {
        FitConfig {
            mag_model: MagModelChoice::Auto,
            accel_model: ModelChoice::Auto,
            refit_every_s: 10.0,
            gravity_mps2: crate::types::STANDARD_GRAVITY_MPS2,
            min_separation_deg: 1.0,
            centre_min_spread_radii: 0.15,
            prefilter: false,
            prefilter_q: 1e-4,
            prefilter_r: 1.0,
        }
    }
}

/// Acceptance limits of one sensor's fit. Field magnitudes are in the sensor's calibrated units.
/// Defaults (magnetometer uT / accelerometer m/s^2) are given as `[accept.mag]` / `[accept.accel]`.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct AcceptLimits {
    /// Smallest radius (field magnitude); checked only when the input's units are known.
    /// Default: 15 / 7.
    pub min_radius: f64,
    /// Largest radius. Default: 95 / 12.
    pub max_radius: f64,
    /// Largest |offset| per axis, raw units (checked when units are known). Default: 1000 / 3.5.
    pub max_offset: f64,
    /// Smallest diagonal element of the normalised matrix. Default: 0.2 / 0.8.
    pub min_diag: f64,
    /// Largest diagonal element of the normalised matrix. Default: 5 / 1.2.
    pub max_diag: f64,
    /// Largest |off-diagonal| of the normalised matrix. Default: 1 / 0.2.
    pub max_offdiag: f64,
    /// Largest RMS residual as a fraction of the radius. Default: 0.05 / 0.02.
    pub max_rms_ratio: f64,
    /// Fewest filled coverage regions (of 100). Default: 25 / 6.
    pub min_filled_regions: usize,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(from = "AcceptToml")]
pub struct AcceptConfig {
    /// Magnetometer limits (uT). Default: the first of each pair in [`AcceptLimits`].
    pub mag: AcceptLimits,
    /// Accelerometer limits (m/s^2). Default: the second of each pair in [`AcceptLimits`].
    pub accel: AcceptLimits,
}

impl Default for AcceptConfig {
    fn default() -> Self {
        AcceptConfig {
            // ArduPilot's calibrator accepts radius 150-950 mG, DIA in (0.2, 5), |ODI| < 1 and
            // |OFS| < 1800 mG; phones carry far larger hard iron (~400 uT), so the offset limit is wider.
            mag: AcceptLimits {
                min_radius: 15.0,
                max_radius: 95.0,
                max_offset: 1000.0,
                min_diag: 0.2,
                max_diag: 5.0,
                max_offdiag: 1.0,
                max_rms_ratio: 0.05,
                min_filled_regions: 25,
            },
            // ArduPilot: accel scale 0.8-1.2, offsets within 3.5 m/s^2.
            accel: AcceptLimits {
                min_radius: 7.0,
                max_radius: 12.0,
                max_offset: 3.5,
                min_diag: 0.8,
                max_diag: 1.2,
                max_offdiag: 0.2,
                max_rms_ratio: 0.02,
                min_filled_regions: 6,
            },
        }
    }
}

/// TOML form of the limits: every key optional, missing keys keep the sensor's default.
#[derive(Debug, Clone, Copy, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct LimitsToml {
    min_radius: Option<f64>,
    max_radius: Option<f64>,
    max_offset: Option<f64>,
    min_diag: Option<f64>,
    max_diag: Option<f64>,
    max_offdiag: Option<f64>,
    max_rms_ratio: Option<f64>,
    min_filled_regions: Option<usize>,
}

#[derive(Debug, Clone, Copy, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
struct AcceptToml {
    mag: LimitsToml,
    accel: LimitsToml,
}

impl LimitsToml {
    fn over(self, d: AcceptLimits) -> AcceptLimits {
        AcceptLimits {
            min_radius: self.min_radius.unwrap_or(d.min_radius),
            max_radius: self.max_radius.unwrap_or(d.max_radius),
            max_offset: self.max_offset.unwrap_or(d.max_offset),
            min_diag: self.min_diag.unwrap_or(d.min_diag),
            max_diag: self.max_diag.unwrap_or(d.max_diag),
            max_offdiag: self.max_offdiag.unwrap_or(d.max_offdiag),
            max_rms_ratio: self.max_rms_ratio.unwrap_or(d.max_rms_ratio),
            min_filled_regions: self.min_filled_regions.unwrap_or(d.min_filled_regions),
        }
    }
}

impl From<AcceptToml> for AcceptConfig {
    fn from(t: AcceptToml) -> Self {
        let d = AcceptConfig::default();
        AcceptConfig {
            mag: t.mag.over(d.mag),
            accel: t.accel.over(d.accel),
        }
    }
}

/// Everything the pipeline ([`crate::calib::pipeline::Pipeline`]) and the fits read: the parts of
/// the configuration that concern calibration, gathered by `Config::calib`.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibSettings {
    /// Models, refit period, gravity and the prefilter. Default: see [`FitConfig`].
    pub fit: FitConfig,
    /// Acceptance limits per sensor. Default: see [`AcceptConfig`].
    pub accept: AcceptConfig,
    /// The static-pose detector. Default: see [`GateConfig`].
    pub gate: GateConfig,
    /// The IMU's mounting, as `orientation.sensor` names it (a MAV_SENSOR_ORIENTATION name).
    /// Default: "ROTATION_NONE".
    pub sensor_orientation: String,
    /// The accelerometer's units. Default: auto.
    pub accel_units: AccelUnits,
}

impl Default for CalibSettings {
    fn default() -> Self {
        CalibSettings {
            fit: FitConfig::default(),
            accept: AcceptConfig::default(),
            gate: GateConfig::default(),
            sensor_orientation: "ROTATION_NONE".into(),
            accel_units: AccelUnits::Auto,
        }
    }
}
