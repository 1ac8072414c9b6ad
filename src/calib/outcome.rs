//! One sensor's outcome of a fit, shared by the steps that produce and amend it: the pipeline
//! ([`crate::calib::pipeline`]) makes it, the magnetometer's method choice
//! ([`crate::calib::magmethod`]) and mounting check ([`crate::calib::mounting`]) rework it.
//!
//! Also the report's records of a calibration: [`SensorCalibration`] (status, model, offset,
//! matrix, figures), the gyro's, the refit history, and the held-out quality of a magnetometer
//! calibration. The report ([`crate::report`]) holds them.
//!
//! Pure data: no fitting here.

use crate::calib::coverage::Coverage;
use crate::calib::fit::FitFailure;
use crate::calib::model::{CalModel, Calibration};
use crate::types::{CalUnits, Vec3};
use serde::{Deserialize, Serialize};

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

impl SensorResult {
    /// The mounting check ([`crate::calib::mounting::check`]) of this magnetometer result, put in
    /// `report.mounting`; a mounting clearly other than `configured` refuses the calibration
    /// (failure `orientation`, the parameter to set for compass `index` named). Nothing happens
    /// without a calibration or with an unknown `configured`.
    pub(crate) fn check_mounting(
        &mut self,
        accel: Option<&Calibration>,
        poses: &[crate::calib::gate::Pose],
        attitudes: &[Option<nalgebra::UnitQuaternion<f64>>],
        field: Option<&crate::attitude::EarthField>,
        configured: &str,
        index: usize,
    ) {
        let Some(cal) = self.calibration else {
            return;
        };
        let Some(rep) =
            crate::calib::mounting::check(&cal, accel, poses, attitudes, field, configured)
        else {
            return;
        };
        if let Some(why) = rep.refusal(index) {
            self.report.status = CalStatus::Failed;
            self.report.failure = Some(FitFailure::Orientation);
            self.report.detail = Some(why);
            self.calibration = None;
        }
        self.report.mounting = Some(rep);
    }
}

/// A calibration fitted on alternate blocks of the log and scored on the others: what the field
/// looks like through it where it was not fitted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QualityReport {
    /// The instance judged.
    pub instance: String,
    /// Length of the alternating blocks, s: fitted on the even ones (counted from the log's
    /// first sample), scored on the odd ones.
    pub block_s: f64,
    /// imucald's method on the fitting blocks (`vector`).
    pub method: String,
    /// Through imucald's calibration fitted on the even blocks.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imucald: Option<HeldOut>,
    /// Through the vehicle's own calibration (as the log records it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub onboard: Option<HeldOut>,
    /// Why imucald's held-out score is missing, when it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imucald_failure: Option<String>,
    /// The plain answer and the next step.
    pub verdict: String,
    /// The answer as a fixed word: `better`, `keep_vehicle`, `no_onboard`, `failed`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdict_kind: Option<Verdict>,
    /// Where the ladder of models started: the vehicle's own calibration, or the identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<Start>,
    /// The rung of the ladder taken ([`crate::calib::ladder`]), and why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rung: Option<Rung>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rung_reason: Option<String>,
    /// Every rung: its held-out score, or why it gave no calibration.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rungs: Vec<RungReport>,
}

/// One rung of the ladder, the simplest first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rung {
    /// Offsets only, the soft iron kept (the vehicle's, where the log carries it).
    Offsets,
    /// Offsets and one scale.
    Scale,
    /// Offsets and one scale per axis.
    Diagonal,
    /// Offsets and the full soft iron.
    Full,
}

impl Rung {
    pub const ALL: [Rung; 4] = [Rung::Offsets, Rung::Scale, Rung::Diagonal, Rung::Full];

    pub fn name(self) -> &'static str {
        match self {
            Rung::Offsets => "offsets",
            Rung::Scale => "scale",
            Rung::Diagonal => "diagonal",
            Rung::Full => "full",
        }
    }
}

impl std::fmt::Display for Rung {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Where the ladder starts: the calibration every rung refines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Start {
    /// The vehicle's own calibration, as the log records it.
    Vehicle,
    /// No calibration known: the identity.
    Identity,
}

/// One rung as the report states it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RungReport {
    pub rung: Rung,
    /// Fitted on the even blocks, scored on the odd ones.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out: Option<HeldOut>,
    /// Why it gave no calibration, when it did not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refused: Option<String>,
    /// The rung taken.
    pub taken: bool,
}

/// The held-out answer as a fixed word.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// imucald's is better than the vehicle's on the held-out blocks: load it.
    Better,
    /// imucald's is not clearly better: keep the vehicle's.
    KeepVehicle,
    /// The log carries no calibration of the vehicle's to compare with.
    NoOnboard,
    /// imucald's held-out fit failed.
    Failed,
}

impl Verdict {
    pub fn word(self) -> &'static str {
        match self {
            Verdict::Better => "better",
            Verdict::KeepVehicle => "keep_vehicle",
            Verdict::NoOnboard => "no_onboard",
            Verdict::Failed => "failed",
        }
    }
}

/// The field seen through one calibration on held-out readings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeldOut {
    /// Standard deviation of the field's norm over its mean, %.
    pub norm_spread_pct: f64,
    /// Standard deviation of the field's dip below the horizontal (from the vehicle's attitude), deg.
    pub dip_spread_deg: f64,
    /// Mean dip, deg.
    pub dip_mean_deg: f64,
    /// Spread of the field's horizontal direction in the vehicle's NED frame (circular standard
    /// deviation), deg: how far the compass heading wanders against the vehicle's own yaw, a
    /// constant offset (the declination) aside.
    #[serde(default)]
    pub heading_spread_deg: f64,
    /// Readings scored.
    pub readings: usize,
}

/// Whether a calibration passed: "ok" or "failed" in the report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalStatus {
    Ok,
    Failed,
}

impl std::fmt::Display for CalStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl CalStatus {
    /// The report's name of the status.
    pub fn name(self) -> &'static str {
        match self {
            CalStatus::Ok => "ok",
            CalStatus::Failed => "failed",
        }
    }
}

/// One sensor's calibration result.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SensorCalibration {
    pub status: CalStatus,
    /// Null or the reason ([`FitFailure`]): not_enough_samples, not_identifiable, coverage, radius,
    /// offsets, diagonal_scaling, residuals, did_not_converge, disturbed, axis_fault, held_out,
    /// orientation.
    pub failure: Option<FitFailure>,
    /// Human-readable detail of the failure.
    pub detail: Option<String>,
    pub model: CalModel,
    /// Units of the calibrated output: "m/s^2", "uT", or "counts" when the input's units are unknown.
    pub units: CalUnits,
    pub offset: Vec3,
    /// calibrated = matrix * (raw - offset)
    pub matrix: [[f64; 3]; 3],
    /// Field magnitude in calibrated units.
    pub radius: f64,
    pub rms_residual: f64,
    pub offset_sigma: Vec3,
    pub samples_used: usize,
    pub iterations: usize,
    /// Every model tried, for `auto`.
    pub candidates: Vec<Candidate>,
    /// Points left out as outliers before the final fit (magnetometer: readings that do not lie on
    /// the field's ellipsoid, e.g. while a magnet or a motor was near).
    #[serde(default)]
    pub outliers_rejected: usize,
    /// Magnetometer of a replay: `method` ("vector" or "sphere"), `method_reason`, and the vector
    /// fit (`vector`) when one was made ([`crate::calib::magmethod`]).
    #[serde(flatten)]
    pub method: Option<MethodChoice>,
    /// Magnetometer of a replay: the mounting found from the static poses and the verdict on the
    /// configured one ([`crate::calib::mounting`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mounting: Option<crate::calib::mounting::MountingReport>,
}

impl SensorCalibration {
    /// A result of `status` for `model` in `units` with nothing fitted: no failure, zero offset,
    /// identity matrix, every figure zero, no candidates. The base a refusal or a made-up result
    /// fills in.
    pub fn new(status: CalStatus, model: CalModel, units: CalUnits) -> SensorCalibration {
        SensorCalibration {
            status,
            failure: None,
            detail: None,
            model,
            units,
            offset: [0.0; 3],
            matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            radius: 0.0,
            rms_residual: 0.0,
            offset_sigma: [0.0; 3],
            samples_used: 0,
            iterations: 0,
            candidates: vec![],
            outliers_rejected: 0,
            method: None,
            mounting: None,
        }
    }

    /// The calibration to apply when it passed (`status` "ok"), with the norm model that applies
    /// it ([`CalModel::kind`]).
    pub fn calibration(&self) -> Option<crate::calib::model::Calibration> {
        (self.status == CalStatus::Ok).then(|| crate::calib::model::Calibration {
            model: self.model.kind(),
            offset: self.offset,
            matrix: self.matrix,
        })
    }

    /// [`SensorCalibration::calibration`] of a magnetometer in uT (what flight-stack parameters
    /// can hold).
    pub(crate) fn calibration_ut(&self) -> Option<crate::calib::model::Calibration> {
        self.calibration().filter(|_| self.units == CalUnits::Ut)
    }

    /// What the data did not determine of this calibration (a planar fit's z offset and z soft
    /// iron, held at nominal): never exported.
    pub(crate) fn unknowns(&self) -> crate::calib::export::Unknowns {
        use crate::calib::planar::Undetermined;
        let mut u = crate::calib::export::Unknowns::default();
        if let Some(p) = self.method.as_ref().and_then(|m| m.planar.as_ref()) {
            for d in &p.undetermined {
                match d {
                    Undetermined::OffsetZ => u.offset[2] = true,
                    Undetermined::SoftIronZ => u.axis[2] = true,
                    Undetermined::FieldVertical | Undetermined::HeadingDeviation => {}
                }
            }
            if u.any() {
                u.why = "turns about the vertical only: the body-z axis never sees the field from another side".into();
            }
        }
        u
    }

    /// The field per ampere of battery current (uT/A, raw body axes) of a vector calibration in
    /// use whose data determined it: what the motor-compensation parameters export.
    pub fn motor_ut_per_a(&self) -> Option<Vec3> {
        let m = self.method.as_ref()?;
        if m.method != MagMethod::Vector || self.calibration_ut().is_none() {
            return None;
        }
        // The ladder's calibration carries its own current term.
        if m.rung.is_some() {
            return m.current_ut_per_a;
        }
        let v = m.vector.as_ref()?;
        (v.current_identifiable == Some(true)).then_some(v.current_ut_per_a)?
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Candidate {
    pub model: CalModel,
    pub rms_residual: f64,
    pub params: usize,
    pub chosen: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GyroCalibration {
    pub status: CalStatus,
    /// Null or not_enough_samples.
    pub failure: Option<FitFailure>,
    pub units: CalUnits,
    /// Bias = mean gyro over the static poses, rad/s.
    pub bias: Vec3,
    pub bias_sigma: Vec3,
    pub poses_used: usize,
    /// Steady poses left out of the bias because they turned faster than
    /// [`crate::calib::gate::REST_MAX_RATE_DEG_S`] (a steady turn is not rest).
    #[serde(default)]
    pub poses_turning: usize,
    /// Scale and misalignment from the rotations between static poses (replay only: it needs the
    /// whole log), present only when its held-out check passed. `None` when not attempted or
    /// refused; a refusal is in `scale_failure`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<GyroScaleReport>,
    /// Why no scale is published: `failure` (not_enough_samples, not_identifiable, held_out,
    /// needs_calibration), `detail`, and `held_out` figures when that check was made.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale_failure: Option<crate::calib::gyro::ScaleFailure>,
}

/// The 12-parameter gyro calibration `omega_rad_s = matrix (raw - bias)` and how well it carries the
/// gravity direction from one static pose to the next.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GyroScaleReport {
    /// Row-major scale/misalignment matrix (rad/s per input unit).
    pub matrix: [[f64; 3]; 3],
    /// Rotations between poses used.
    pub segments: usize,
    /// RMS gravity-direction error over those rotations, bias-only model then fitted, degrees.
    pub rms_before_deg: f64,
    pub rms_after_deg: f64,
    /// The same on every other rotation, left out of a second fit (the check the scale passed).
    pub held_out: Option<crate::calib::gyro::HeldOut>,
    pub conditioning: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RefitReport {
    pub t_s: f64,
    pub sensor: crate::types::Sensor,
    pub model: CalModel,
    pub status: CalStatus,
    pub failure: Option<FitFailure>,
    pub rms_residual: f64,
}

/// How the magnetometer calibration was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MagMethod {
    /// From the attitude and the earth field ([`crate::calib::vector`]).
    Vector,
    /// From the field's norm (the pipeline's fit).
    Sphere,
    /// In the horizontal plane with a heading deviation curve ([`crate::calib::planar`]): a vehicle
    /// that only turns about the vertical.
    Planar,
}

impl MagMethod {
    /// The name the report uses (`vector`, `sphere`, `planar`).
    pub fn name(self) -> &'static str {
        match self {
            MagMethod::Vector => "vector",
            MagMethod::Sphere => "sphere",
            MagMethod::Planar => "planar",
        }
    }
}

/// The method chosen and why (flattened into `calibration.mag`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodChoice {
    pub method: MagMethod,
    pub method_reason: String,
    /// The vector fit, when one was made (chosen or not).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vector: Option<crate::calib::vector::VectorFit>,
    /// The 2-D fit, when the planar method was chosen.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub planar: Option<crate::calib::planar::PlanarFit>,
    /// The sphere fit's offset (uT) when it passed but the vector fit was chosen.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sphere_offset: Option<crate::types::Vec3>,
    /// The earth field the vector and planar fits compare with, where the log was taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub earth_field: Option<FieldUsed>,
    /// The rung of the model ladder taken ([`crate::calib::ladder`]), when the vector method's
    /// calibration is the ladder's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rung: Option<Rung>,
    /// The field per ampere of battery current of the rung's calibration, as the raw reading
    /// carries it (raw = A h + o + k c), uT/A: when the logged current varies.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_ut_per_a: Option<crate::types::Vec3>,
}

/// The earth field at the log's place and date, and where both came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldUsed {
    /// `WMM` or `IGRF-13`.
    pub model: crate::attitude::FieldModel,
    /// `YYYY-MM-DD`.
    pub date: String,
    /// `configured` ([place] date), `record_clock` (a `.tlog`'s record times), `gps_time`,
    /// `today` (the log gives no date: the day of the run) or `simulated` (the simulator's day).
    pub date_source: String,
    /// The place (none when the field is fitted).
    pub latitude_deg: Option<f64>,
    pub longitude_deg: Option<f64>,
    /// Where the place came from: the log's position, its GPS, or `[place]`.
    pub place_source: String,
    pub total_ut: f64,
    pub inclination_deg: f64,
    pub declination_deg: f64,
}
