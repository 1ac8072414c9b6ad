//! One sensor's outcome of a fit, shared by the steps that produce and amend it: the pipeline
//! ([`crate::calib::pipeline`]) makes it, the magnetometer's method choice
//! ([`crate::calib::magmethod`]) and mounting check ([`crate::calib::mounting`]) rework it.
//!
//! Pure data: no fitting here.

use crate::calib::coverage::Coverage;
use crate::calib::model::Calibration;
use crate::report::SensorCalibration;
use crate::types::Vec3;

/// One sensor's outcome.
#[derive(Debug, Clone)]
pub struct SensorResult {
    pub report: SensorCalibration,
    /// The calibration when status is ok.
    pub calibration: Option<Calibration>,
    pub coverage_before: Coverage,
    pub coverage_after: Coverage,
    /// Raw points about the raw centre and calibrated points, for plots.
    pub dirs_before: Vec<Vec3>,
    pub dirs_after: Vec<Vec3>,
    /// Per fitted point: time unknown for bins, so index; norm residual in calibrated units.
    pub residuals: Vec<f64>,
    /// Raw points held out of the fit ([`crate::calib::pipeline::hold_out`]): what a new
    /// calibration is judged on against the current one.
    pub held_out: Vec<Vec3>,
}
