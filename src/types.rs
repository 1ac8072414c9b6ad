//! Plain data types shared by every stage. No I/O.

use serde::{Deserialize, Serialize};

/// A 3-vector in sensor or body axes.
pub type Vec3 = [f64; 3];

/// One instant of IMU data after decoding, in SI-like units:
/// accelerometer in m/s^2 (or raw counts when the source gives counts),
/// gyroscope in rad/s, magnetometer in uT, temperature in deg C.
/// A `None` field means "no new reading at this instant" (sensors run at different rates).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Time since the start of the recording, seconds; never decreases along a stream.
    pub t_s: f64,
    /// Time segment ([`crate::io::clock`]): a new one starts wherever the source's time broke (a
    /// reboot, logs joined, a gap). Nothing integrates over time across a change.
    pub segment: u32,
    /// Specific force, m/s^2 (FRD sensor axes), or counts when `Units::accel` says so.
    pub accel_mps2: Option<Vec3>,
    /// Angular rate, rad/s, or counts.
    pub gyro_rad_s: Option<Vec3>,
    /// Magnetic field, uT, or counts.
    pub mag_ut: Option<Vec3>,
    /// Sensor temperature, deg C.
    pub temp_c: Option<f64>,
    /// Motor throttle 0..1.
    pub throttle: Option<f64>,
    /// Battery current, A.
    pub current_a: Option<f64>,
    /// Reference orientation (w, x, y, z), sensor -> ENU, when the log carries one.
    pub ref_q: Option<[f64; 4]>,
    /// 1 inside a movement phase marked by the log (BROAD), when present.
    pub moving: Option<bool>,
    /// Where the vehicle was (a GPS fix), when the log carries one at this instant.
    pub position: Option<GeoPoint>,
}

/// A place on the earth: WGS84 latitude and longitude, height above the ellipsoid.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct GeoPoint {
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub alt_m: f64,
}

impl Sample {
    /// True when no sensor field is present.
    pub fn is_empty(&self) -> bool {
        self.accel_mps2.is_none() && self.gyro_rad_s.is_none() && self.mag_ut.is_none()
    }
}

/// What unit a sensor's numbers are in, as far as the input tells.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Unit {
    /// Physical units (m/s^2, rad/s, uT).
    #[default]
    Si,
    /// Raw counts with unknown scale: the fit scales them.
    Counts,
}

/// Units of each sensor stream of an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct Units {
    pub accel: Unit,
    pub gyro: Unit,
    pub mag: Unit,
}

/// Which sensor a calibration is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sensor {
    Accel,
    Mag,
    Gyro,
}

impl Sensor {
    pub fn name(self) -> &'static str {
        match self {
            Sensor::Accel => "accel",
            Sensor::Mag => "mag",
            Sensor::Gyro => "gyro",
        }
    }
}

/// Standard gravity, m/s^2.
pub const STANDARD_GRAVITY_MPS2: f64 = 9.80665;

pub fn norm(v: &Vec3) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

pub fn is_finite3(v: &Vec3) -> bool {
    v.iter().all(|x| x.is_finite())
}
