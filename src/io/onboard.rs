//! The onboard calibration a flight-controller log or telemetry records, and the sensor streams it
//! holds, as the readers find them (ArduPilot's COMPASS_*/INS_ACC* parameters, PX4's CAL_MAG*/CAL_ACC*),
//! in imucald's model: calibrated = matrix (raw - offset). Plain data; `crate::report` holds it.

use crate::types::Vec3;
use serde::{Deserialize, Serialize};

/// One sensor stream of the input (`input.sensors`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorStream {
    /// "mag", "accel" or "gyro".
    pub sensor: crate::types::Sensor,
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
    pub units: crate::types::CalUnits,
    /// The parameters it was made from, as logged.
    pub params: std::collections::BTreeMap<String, f64>,
}
