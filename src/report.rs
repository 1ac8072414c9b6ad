//! The replay/run report (`imucald.report/1`), as serialisable data. Field names are the contract.

use crate::calib::coverage::Coverage;
use crate::calib::fit::FitFailure;
use crate::calib::gate::Pose;
use crate::io::decode::DecodeStats;
use crate::types::Vec3;
use serde::{Deserialize, Serialize};

pub const SCHEMA: &str = "imucald.report/1";

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Report {
    pub schema: String,
    pub input: InputReport,
    pub static_poses: Vec<PoseReport>,
    pub coverage: CoverageReport,
    pub calibration: CalibrationReport,
    /// True heading uses this declination (deg, east positive) when a place is configured.
    pub declination_deg: Option<f64>,
    /// Refits done while the data came in (time of data, model, status).
    pub refits: Vec<RefitReport>,
    /// Every IMU instance of a MAVLink log, each calibrated on its own (the primary's calibration
    /// is also `calibration`); empty for other inputs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub instances: Vec<InstanceReport>,
    /// The live service only: what its outputs delivered and dropped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outputs: Option<OutputsReport>,
    /// The live service only: every vehicle calibrated after the first (the rest of the report
    /// is the first's), each on its own.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub vehicles: Vec<VehicleReport>,
    /// Flight-controller logs (`.bin`, `.ulg`): the calibration the flight controller applied, as
    /// its parameters record it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub onboard: Option<OnboardReport>,
    /// Each compass's calibration judged on the part of the log it was not fitted on, against
    /// the vehicle's own (logs with an attitude): the primary's first, then the further
    /// instances'.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub quality: Vec<QualityReport>,
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

/// One sensor stream of the input (`input.sensors`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorStream {
    /// "mag", "accel" or "gyro".
    pub sensor: String,
    /// The sensor's own instance number (DataFlash `MAG2` is 1; ULog the topic's `multi_id`).
    pub instance: u8,
    /// Where it was read: `MAG2`, `IMU[1]`, `sensor_mag[1]`, `sensor_combined`, ...
    pub source: String,
    /// Readings.
    pub samples: u64,
    /// The device id the log gives the sensor (ULog `device_id`, ArduPilot COMPASS_DEV_IDn).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_id: Option<u32>,
}

/// The onboard calibration of a flight-controller log.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct OnboardReport {
    /// "ardupilot" or "px4".
    pub stack: String,
    /// Per compass calibration slot (ArduPilot compass k, PX4 CAL_MAGn).
    pub mag: Vec<OnboardCal>,
    /// Per accelerometer calibration slot (ArduPilot INS_ACCk, PX4 CAL_ACCn).
    pub accel: Vec<OnboardCal>,
    /// Streams whose onboard correction was undone before fitting, and how.
    pub undone: Vec<String>,
    /// Streams logged corrected whose correction could not be undone, and why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_undone: Vec<String>,
    /// The first GPS fix (latitude deg, longitude deg, altitude m), when the log has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gps: Option<[f64; 3]>,
    /// imucald's magnetometer calibration of the primary against the onboard one of the same
    /// compass, when imucald's fit passed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comparison: Option<OnboardComparison>,
}

/// imucald's calibration against the onboard one.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OnboardComparison {
    /// The onboard slot (`onboard.mag[].instance`) and the stream compared.
    pub instance: u8,
    pub source: String,
    /// imucald's offset minus the onboard one, uT.
    pub offset_diff_ut: Vec3,
    /// Tilt-compensated heading from the two calibrations of the same readings, at the flight
    /// controller's own roll and pitch (`ATT`, `vehicle_attitude`): RMS and largest difference, deg.
    pub heading_diff_rms_deg: f64,
    pub heading_diff_max_deg: f64,
    /// Readings compared (those with the flight controller's attitude).
    pub samples: usize,
}

/// One onboard calibration in imucald's model: calibrated = matrix (raw - offset).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OnboardCal {
    /// The flight controller's slot: ArduPilot compass/IMU k (0-based), PX4 CAL_MAGn / CAL_ACCn.
    pub instance: u8,
    /// The device id the slot belongs to (PX4 CAL_*n_ID, ArduPilot COMPASS_DEV_IDn).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_id: Option<u32>,
    /// The log's streams this calibration applies to (matched by device id on PX4).
    pub sources: Vec<String>,
    /// Offset in `units` (sensor axes).
    pub offset: Vec3,
    pub matrix: [[f64; 3]; 3],
    pub units: String,
    /// The parameters it was made from, as logged.
    pub params: std::collections::BTreeMap<String, f64>,
}

/// One IMU instance of the input and its calibration.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct InstanceReport {
    /// `highres_imu:1`, `scaled_imu2`, ...
    pub instance: String,
    /// MAG_CAL_* `compass_id`: the message's `id`, or 0, 1, 2 for SCALED_IMU, SCALED_IMU2, SCALED_IMU3.
    pub compass_id: u8,
    /// The instance `calibration` and the rest of the report describe.
    pub primary: bool,
    pub samples: u64,
    /// Its clock ([`InputReport::time`]).
    pub time: crate::io::clock::TimeStats,
    pub calibration: CalibrationReport,
}

/// A further vehicle calibrated by the live service (a link and system id of its own).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VehicleReport {
    /// The link it was heard on (its address as configured).
    pub link: String,
    /// Its MAVLink system id; the service speaks for it as our component in this system.
    pub system_id: u8,
    /// Where its calibration is kept.
    pub calibration_dir: String,
    pub input: InputReport,
    /// Its latest fits; none before the first.
    pub calibration: Option<CalibrationReport>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub instances: Vec<InstanceReport>,
}

/// The live service's outputs: what each JSON consumer and MAVLink link could not take.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct OutputsReport {
    pub json_sinks: Vec<SinkReport>,
    pub links: Vec<LinkOutputReport>,
}

/// One JSON-lines consumer (`publish`): lines handed to it, and lines lost.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SinkReport {
    /// As configured: "stdout", "udp:IP:PORT", "tcp:IP:PORT".
    pub sink: String,
    pub sent: u64,
    /// Dropped because its queue was full (the consumer was not taking lines).
    pub queue_full: u64,
    /// Taken from the queue but not delivered (not connected, refused by the socket).
    pub not_delivered: u64,
}

/// One link's outbound MAVLink.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LinkOutputReport {
    pub link: String,
    /// Datagrams (or writes) of frames not sent: its outbound queue was full, no peer yet (udpin),
    /// link down.
    pub outbound_dropped: u64,
    /// Of those, dropped because its outbound queue was full.
    #[serde(default)]
    pub outbound_queue_full: u64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct InputReport {
    pub format: String,
    pub path: Option<String>,
    /// MAVLink instance used, when the input is MAVLink.
    pub instance: Option<String>,
    pub samples: u64,
    pub counts: std::collections::BTreeMap<String, u64>,
    pub skipped: std::collections::BTreeMap<String, u64>,
    pub duration_s: f64,
    /// The source's clock: which one (`message` or `receive`), time segments, faults by kind.
    #[serde(default)]
    pub time: crate::io::clock::TimeStats,
    /// Every sensor stream of a flight-controller log; empty for other inputs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sensors: Vec<SensorStream>,
}

impl InputReport {
    pub fn new(
        format: &str,
        path: Option<String>,
        instance: Option<String>,
        stats: &DecodeStats,
        samples: u64,
        duration_s: f64,
    ) -> Self {
        InputReport {
            format: format.into(),
            path,
            instance,
            samples,
            counts: stats.counts.to_map(),
            skipped: stats.skipped.clone(),
            duration_s,
            time: stats.time.clone(),
            sensors: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoseReport {
    pub t_start: f64,
    pub t_end: f64,
    pub samples: usize,
    pub accel: Vec3,
    pub mag: Option<Vec3>,
    pub gyro: Option<Vec3>,
    /// How fast it turned, deg/s ([`Pose::turn_rate_deg_s`]); a pose that turned is not rest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turn_rate_deg_s: Option<f64>,
}

impl From<&Pose> for PoseReport {
    fn from(p: &Pose) -> Self {
        PoseReport {
            t_start: p.t_start,
            t_end: p.t_end,
            samples: p.samples,
            accel: p.accel,
            mag: p.mag,
            gyro: p.gyro,
            turn_rate_deg_s: p.turn_rate_deg_s,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CoverageReport {
    pub mag: Coverage,
    pub accel: Coverage,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CalibrationReport {
    pub mag: SensorCalibration,
    pub accel: SensorCalibration,
    pub gyro: GyroCalibration,
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
    pub model: String,
    /// Units of the calibrated output: "m/s^2", "uT", or "counts" when the input's units are unknown.
    pub units: String,
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
    pub method: Option<crate::calib::magmethod::MethodChoice>,
    /// Magnetometer of a replay: the mounting found from the static poses and the verdict on the
    /// configured one ([`crate::calib::mounting`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mounting: Option<crate::calib::mounting::MountingReport>,
}

impl SensorCalibration {
    /// A result of `status` for `model` in `units` with nothing fitted: no failure, zero offset,
    /// identity matrix, every figure zero, no candidates. The base a refusal or a made-up result
    /// fills in.
    pub fn new(status: CalStatus, model: &str, units: &str) -> SensorCalibration {
        SensorCalibration {
            status,
            failure: None,
            detail: None,
            model: model.into(),
            units: units.into(),
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

    /// The calibration to apply when it passed (`status` "ok"); a model name this build does not
    /// know reads as the general one (full12), which applies the stored matrix as it is.
    pub fn calibration(&self) -> Option<crate::calib::model::Calibration> {
        use crate::calib::model::ModelKind;
        (self.status == CalStatus::Ok).then(|| crate::calib::model::Calibration {
            model: ModelKind::parse(&self.model).unwrap_or(ModelKind::Full12),
            offset: self.offset,
            matrix: self.matrix,
        })
    }

    /// [`SensorCalibration::calibration`] of a magnetometer in uT (what flight-stack parameters
    /// can hold).
    pub fn calibration_ut(&self) -> Option<crate::calib::model::Calibration> {
        self.calibration().filter(|_| self.units == "uT")
    }

    /// What the data did not determine of this calibration (a planar fit's z offset and z soft
    /// iron, held at nominal): never exported.
    pub fn unknowns(&self) -> crate::calib::export::Unknowns {
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
        let v = m.vector.as_ref()?;
        (m.method == crate::calib::magmethod::MagMethod::Vector
            && self.calibration_ut().is_some()
            && v.current_identifiable == Some(true))
        .then_some(v.current_ut_per_a)?
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Candidate {
    pub model: String,
    pub rms_residual: f64,
    pub params: usize,
    pub chosen: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GyroCalibration {
    pub status: CalStatus,
    /// Null or not_enough_samples.
    pub failure: Option<FitFailure>,
    pub units: String,
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
    pub sensor: String,
    pub model: String,
    pub status: CalStatus,
    pub failure: Option<FitFailure>,
    pub rms_residual: f64,
}
