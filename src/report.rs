//! The replay/run report (`imucald.report/1`), as serialisable data. Field names are the contract.

use crate::calib::coverage::Coverage;
use crate::calib::gate::Pose;
use crate::io::decode::DecodeStats;
use crate::types::Vec3;
use serde::{Deserialize, Serialize};

pub use crate::calib::outcome::{
    CalStatus, Candidate, GyroCalibration, GyroScaleReport, HeldOut, QualityReport, RefitReport,
    SensorCalibration, Verdict,
};
pub use crate::calib::tempcal::{OnboardTcal, TempCalReport};
pub use crate::io::onboard::{OnboardCal, OnboardComparison, OnboardReport, SensorStream};

pub(crate) const SCHEMA: &str = "imucald.report/1";

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
    /// Per compass with a calibration: whether it is one to load on the vehicle, and why. The
    /// exports and the terminal's `next:` follow it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub load: Vec<LoadDecision>,
    /// Per IMU instance whose readings carry a temperature: the accelerometer's and gyro's
    /// biases against temperature from a warm-up at rest, or why none was made. Absent for
    /// logs without temperature.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub temperature: Vec<TempCalReport>,
}

/// Whether a compass's calibration is one to load on the vehicle ([`LoadReason`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoadDecision {
    pub instance: String,
    /// The flight stack's compass number (COMPASS_OFS is 0, COMPASS_OFS2 1; CAL_MAGn n).
    pub compass_id: u8,
    pub load: bool,
    pub reason: LoadReason,
}

/// Why a compass's calibration is, or is not, one to load.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LoadReason {
    /// Better than the vehicle's own on the held-out blocks.
    Better,
    /// The log carries no calibration of the vehicle's; imucald's passed its checks.
    NoOnboard,
    /// The log has no attitude to judge it on held-out blocks; it passed its checks.
    NotJudged,
    /// Not clearly better than the vehicle's own on the held-out blocks: keep the vehicle's.
    KeepVehicle,
    /// imucald's fit on the fitting blocks failed, so nothing vouches for it held out.
    HeldOutFailed,
    /// The vehicle does not use this compass (COMPASS_USEn 0, CAL_MAGn_PRIO 0).
    Unused,
    /// Its RMS residual is over `accept.max_rms_ratio` of the field.
    OverRmsLimit,
    /// Another record of the log is of the same compass (PX4's `vehicle_magnetometer` is one of
    /// its `sensor_mag[k]`) and its calibration is the one to load: one per compass.
    SameCompass,
    /// The fit failed: no calibration.
    FitFailed,
}

impl LoadReason {
    /// The reason in words, for the terminal and the exports' comments.
    pub fn words(self) -> &'static str {
        match self {
            LoadReason::Better => "better than the vehicle's own on held-out blocks",
            LoadReason::NoOnboard => {
                "no calibration of the vehicle's; better than the readings as logged on held-out blocks, or passed its checks where they cannot be scored"
            }
            LoadReason::NotJudged => {
                "no attitude in the log to judge it held out; passed its checks"
            }
            LoadReason::KeepVehicle => {
                "keep the vehicle's (the readings as logged, where it has none): imucald's is not better on held-out blocks"
            }
            LoadReason::HeldOutFailed => {
                "imucald's fit on the fitting blocks failed: nothing vouches for it held out"
            }
            LoadReason::Unused => "the vehicle does not use this compass",
            LoadReason::OverRmsLimit => {
                "its RMS residual is over accept.max_rms_ratio of the field"
            }
            LoadReason::FitFailed => "the fit failed",
            LoadReason::SameCompass => {
                "the same compass as another record of this log, whose calibration is the one to load"
            }
        }
    }
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
