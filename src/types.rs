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

/// Unix time of the simulator's `t_s = 0`, us (2023-11-14 22:13:20 UTC): the record clock of the
/// `.tlog`s it writes and the day of its earth field when a scenario's place gives no date.
pub(crate) const SIM_EPOCH_US: u64 = 1_700_000_000_000_000;

/// The day a log was recorded, and what says so.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct LogDate {
    pub year: i32,
    pub month: u8,
    pub day: u8,
    pub source: DateSource,
}

/// Where a log's date comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DateSource {
    /// The receiving computer's clock that stamped each `.tlog` record (Unix time).
    RecordClock,
    /// The GPS receiver's time (DataFlash `GPS` week and milliseconds, ULog `time_utc_usec`,
    /// MAVLink SYSTEM_TIME).
    GpsTime,
    /// The day the program ran (`io::clock::today`): the log gives no date.
    Today,
    /// The simulator's fixed day ([`crate::types::SIM_EPOCH_US`]), so a simulation gives the same
    /// field in any year.
    Simulated,
}

impl LogDate {
    /// The day of a Unix time in microseconds, if it is after 2000-01-01 (earlier is a clock that
    /// counts from boot, not a date).
    pub(crate) fn from_unix_us(us: u64, source: DateSource) -> Option<LogDate> {
        const Y2000_US: u64 = 946_684_800_000_000;
        if us < Y2000_US {
            return None;
        }
        // Days since 1970-01-01 to a civil date (proleptic Gregorian).
        let days = (us / 86_400_000_000) as i64;
        let z = days + 719_468;
        let era = z.div_euclid(146_097);
        let doe = z - era * 146_097;
        let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
        let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
        let mp = (5 * doy + 2) / 153;
        let day = (doy - (153 * mp + 2) / 5 + 1) as u8;
        let month = if mp < 10 { mp + 3 } else { mp - 9 } as u8;
        let year = (yoe + era * 400 + i64::from(month <= 2)) as i32;
        Some(LogDate {
            year,
            month,
            day,
            source,
        })
    }

    /// `YYYY-MM-DD`.
    pub fn iso(&self) -> String {
        format!("{:04}-{:02}-{:02}", self.year, self.month, self.day)
    }
}

/// What a log says of where and when it was recorded, for the earth field.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LogWhere {
    /// The first GPS fix: latitude deg, longitude deg, altitude m.
    pub gps: Option<[f64; 3]>,
    pub date: Option<LogDate>,
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

/// The units a calibration's output is in: what `calibration.*.units` says in the report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum CalUnits {
    /// Microtesla: a magnetometer in physical units.
    #[serde(rename = "uT")]
    Ut,
    /// m/s^2: an accelerometer in physical units.
    #[serde(rename = "m/s^2")]
    Mps2,
    /// rad/s: a gyroscope in physical units.
    #[serde(rename = "rad/s")]
    RadS,
    /// Raw counts with unknown scale (the input's units are unknown).
    #[serde(rename = "counts")]
    Counts,
}

impl CalUnits {
    /// The name the report and the messages use.
    pub fn name(self) -> &'static str {
        match self {
            CalUnits::Ut => "uT",
            CalUnits::Mps2 => "m/s^2",
            CalUnits::RadS => "rad/s",
            CalUnits::Counts => "counts",
        }
    }

    /// `physical` for a stream in physical units, else counts.
    pub fn of(unit: Unit, physical: CalUnits) -> CalUnits {
        match unit {
            Unit::Si => physical,
            Unit::Counts => CalUnits::Counts,
        }
    }
}

impl std::fmt::Display for CalUnits {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
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

pub(crate) fn is_finite3(v: &Vec3) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// The tracing target of the service's status lines for the operator (links connected, lost,
/// ended; where calibrations go; the live page's address): the binary shows it on stderr.
pub const STATUS_TARGET: &str = "imucald::status";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unix_time_to_civil_date() {
        let d = |us: u64| LogDate::from_unix_us(us, DateSource::RecordClock).map(|d| d.iso());
        // 2013-10-13 21:59:05 UTC (the first record of a 2013 telemetry log).
        assert_eq!(d(1_381_701_545_375_000).as_deref(), Some("2013-10-13"));
        assert_eq!(d(951_782_400_000_000).as_deref(), Some("2000-02-29"));
        assert_eq!(d(1_767_225_599_000_000).as_deref(), Some("2025-12-31"));
        // A clock since boot is no date.
        assert_eq!(d(60_455_792), None);
    }
}
