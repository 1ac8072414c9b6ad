//! MAVLink messages to samples: [`MessageConverter`] takes the IMU messages of one instance or of
//! every instance (each with its own clock) and the vehicle's state that rides on them
//! (attitude, position, current, throttle, an ArduPilot vehicle's compass calibration).

use super::stats::DecodeStats;
use crate::io::clock::{ClockSettings, SourceClock, TimeStats};
use crate::types::{Sample, Unit, Units, Vec3};
use mavlink::dialects::ardupilotmega::MavMessage;
use serde::{Deserialize, Serialize};

/// Which IMU instance to take samples from (the `input.instance` setting, read and written as
/// its text: "auto" or the instance's name).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum InstanceChoice {
    /// The first instance seen that carries a magnetometer (the default).
    Auto,
    /// A named instance: `highres_imu:ID`, `scaled_imu`, `scaled_imu2`, `scaled_imu3`, `raw_imu:ID`.
    Named(String),
}

impl std::str::FromStr for InstanceChoice {
    type Err = String;

    /// "auto", or the name of an instance of a kind the converter reads (an id from 0 to 255).
    fn from_str(s: &str) -> Result<InstanceChoice, String> {
        if s == "auto" {
            return Ok(InstanceChoice::Auto);
        }
        let named = ["scaled_imu", "scaled_imu2", "scaled_imu3"].contains(&s)
            || s.strip_prefix("highres_imu:")
                .or(s.strip_prefix("raw_imu:"))
                .is_some_and(|n| n.parse::<u8>().is_ok());
        if named {
            Ok(InstanceChoice::Named(s.to_string()))
        } else {
            Err(format!(
                "`{s}` is not auto, highres_imu:N, scaled_imu, scaled_imu2, scaled_imu3 or raw_imu:N"
            ))
        }
    }
}

impl TryFrom<String> for InstanceChoice {
    type Error = String;

    fn try_from(s: String) -> Result<InstanceChoice, String> {
        s.parse()
    }
}

impl From<InstanceChoice> for String {
    fn from(c: InstanceChoice) -> String {
        match c {
            InstanceChoice::Auto => "auto".into(),
            InstanceChoice::Named(n) => n,
        }
    }
}

/// Scales for RAW_IMU counts (from config).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RawImuScale {
    /// m/s^2 per count; 0 keeps counts (the fit scales them).
    pub accel: f64,
    /// rad/s per count; 0 keeps counts.
    pub gyro: f64,
    /// uT per count; 0 keeps counts.
    pub mag: f64,
}

impl Default for RawImuScale {
    fn default() -> Self {
        RawImuScale {
            accel: 0.0,
            gyro: 0.0,
            mag: 0.0,
        }
    }
}

/// An IMU instance of a message: its kind (`highres_imu`, `scaled_imu2`, ...) and, for kinds that
/// carry one, its id. Compared as it is; the name (`highres_imu:1`) is built only for display and
/// for [`InstanceChoice::Named`] before an instance is chosen, not once per sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Instance {
    kind: ImuKind,
    id: Option<u8>,
}

/// The MAVLink message an IMU instance arrives in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ImuKind {
    HighresImu,
    ScaledImu,
    ScaledImu2,
    ScaledImu3,
    RawImu,
    /// No instance yet.
    Unknown,
}

impl ImuKind {
    fn name(self) -> &'static str {
        match self {
            ImuKind::HighresImu => "highres_imu",
            ImuKind::ScaledImu => "scaled_imu",
            ImuKind::ScaledImu2 => "scaled_imu2",
            ImuKind::ScaledImu3 => "scaled_imu3",
            ImuKind::RawImu => "raw_imu",
            ImuKind::Unknown => "",
        }
    }
}

impl Instance {
    /// The compass number a ground station knows the instance by.
    fn compass_id(&self) -> u8 {
        match (self.kind, self.id) {
            (_, Some(id)) => id,
            (ImuKind::ScaledImu2, None) => 1,
            (ImuKind::ScaledImu3, None) => 2,
            _ => 0,
        }
    }

    fn name(&self) -> String {
        match self.id {
            Some(id) => format!("{}:{id}", self.kind.name()),
            None => self.kind.name().to_string(),
        }
    }
}

/// Turns MAVLink messages into samples of one IMU instance (the primary, which `choice` picks),
/// or of every instance ([`MessageConverter::with_other_instances`]), with throttle from VFR_HUD.
/// Each instance has its own clock.
#[derive(Debug, Clone)]
pub struct MessageConverter {
    pub choice: InstanceChoice,
    pub raw_scale: RawImuScale,
    /// Every instance taken so far, at most [`MAX_INSTANCES`].
    tracks: Vec<Track>,
    /// The index in `tracks` of the primary instance, once chosen.
    primary: Option<usize>,
    /// Take the other instances too.
    others: bool,
    throttle: Option<f64>,
    /// The newest vehicle attitude (ATTITUDE_QUATERNION or ATTITUDE; sensor -> ENU, as
    /// [`Sample::ref_q`]) and when it was received (us, 0 when unknown).
    attitude: Option<(u64, [f64; 4])>,
    /// Attitude messages taken so far: each instance attaches an attitude to its first sample
    /// after it arrives only (as a CSV carries `ref_q` on the rows where it was measured), so a
    /// reading is never paired with an attitude older than the one before it.
    attitude_count: u64,
    /// The newest position fix (GLOBAL_POSITION_INT, or GPS_RAW_INT with a 3-D fix).
    position: Option<crate::types::GeoPoint>,
    /// The newest battery current (BATTERY_STATUS or SYS_STATUS), A.
    current_a: Option<f64>,
    time_revision: u64,
    /// The vehicle's flight stack, from its HEARTBEAT (a ground station's says nothing).
    autopilot: Autopilot,
    /// Whether RAW_IMU is read in ArduPilot's units (mG, mrad/s, mGauss), latched at the first
    /// RAW_IMU message so that a stream never changes units.
    raw_imu_ardupilot: Option<bool>,
    /// An ArduPilot vehicle's compass corrections from its telemetry, and what to do with its
    /// magnetometer readings.
    ardupilot: crate::io::ardupilot::Telemetry,
    ardupilot_mag: ArduPilotMag,
    /// The first position fix.
    first_position: Option<crate::types::GeoPoint>,
    /// The primary instance's counts; `stats.time` is its clock's.
    pub stats: DecodeStats,
}

/// What a converter does with an ArduPilot vehicle's magnetometer readings, which carry the
/// vehicle's own calibration.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ArduPilotMag {
    /// Pass them on as streamed.
    Keep,
    /// Undo the calibration ([`crate::io::ardupilot::Telemetry`]); readings before it is known
    /// are left out, skipped as `mag_awaiting_params`.
    Undo,
    /// Leave every reading out, skipped as `mag_awaiting_params`.
    Refuse,
}

/// The flight stack a vehicle's HEARTBEAT names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Autopilot {
    /// No vehicle HEARTBEAT yet.
    Unknown,
    /// ArduPilot: RAW_IMU in SCALED_IMU's units, magnetometer streamed with its calibration applied.
    ArduPilot,
    /// Any other (PX4, ...): messages as the MAVLink specification defines them.
    Other,
}

/// An attitude received longer before a sample than this is not attached to it, us: ArduPilot and
/// PX4 stream ATTITUDE at 10 Hz or more, so this lets one message be lost.
pub(crate) const ATTITUDE_MAX_AGE_US: u64 = 250_000;

/// Instances of one stream a converter keeps apart; more are skipped (`too_many_instances`).
pub(crate) const MAX_INSTANCES: usize = 8;

/// One instance's state in a converter.
#[derive(Debug, Clone)]
struct Track {
    instance: Instance,
    name: String,
    /// Message time, or receive/record time where that is unusable.
    clock: SourceClock,
    /// The last frame's time and readings (to tell a repeated frame).
    last_frame: Option<(MsgTime, Vec3, Vec3, Vec3)>,
    samples: u64,
    /// The converter's `attitude_count` when this instance last took an attitude.
    attitudes_taken: u64,
}

/// An IMU instance a converter took samples from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InstanceInfo {
    /// `highres_imu:1`, `scaled_imu2`, ...
    pub name: String,
    /// The compass number a ground station knows it by (MAG_CAL_* `compass_id`): a HIGHRES_IMU or
    /// RAW_IMU `id`, or 0, 1, 2 for SCALED_IMU, SCALED_IMU2, SCALED_IMU3.
    pub compass_id: u8,
    pub samples: u64,
    pub units: Units,
    pub time: TimeStats,
}

const MG_TO_MPS2: f64 = crate::types::STANDARD_GRAVITY_MPS2 / 1000.0;

fn finite3(v: Vec3) -> Option<Vec3> {
    if v.iter().all(|x| x.is_finite()) {
        Some(v)
    } else {
        None
    }
}

impl MessageConverter {
    /// Copy the primary clock's statistics into `stats.time` when they changed.
    fn sync_time_stats(&mut self) {
        let Some(t) = self.primary.map(|k| &self.tracks[k]) else {
            return;
        };
        if t.clock.revision() != self.time_revision {
            self.time_revision = t.clock.revision();
            self.stats.time = t.clock.stats.clone();
        }
    }

    pub fn new(choice: InstanceChoice, raw_scale: RawImuScale) -> Self {
        MessageConverter {
            choice,
            raw_scale,
            tracks: Vec::new(),
            primary: None,
            others: false,
            throttle: None,
            attitude: None,
            attitude_count: 0,
            position: None,
            current_a: None,
            time_revision: u64::MAX,
            autopilot: Autopilot::Unknown,
            raw_imu_ardupilot: None,
            ardupilot: Default::default(),
            ardupilot_mag: ArduPilotMag::Keep,
            first_position: None,
            stats: DecodeStats::default(),
        }
    }

    /// What to do with an ArduPilot vehicle's magnetometer readings ([`ArduPilotMag`]; `Keep`
    /// unless set). `Undo` uses the COMPASS_* values its telemetry gives at each reading's time
    /// ([`crate::io::ardupilot`]).
    pub(crate) fn with_ardupilot_mag(mut self, mode: ArduPilotMag) -> Self {
        self.ardupilot_mag = mode;
        self
    }

    /// Whether compass `k` of an ArduPilot vehicle is external, as its parameters say (`None`:
    /// not known).
    pub(crate) fn compass_external(&self, k: u8) -> Option<bool> {
        self.ardupilot.compass_external(k)
    }

    /// A HEARTBEAT has named the vehicle's flight stack ArduPilot.
    pub(crate) fn is_ardupilot(&self) -> bool {
        self.autopilot == Autopilot::ArduPilot
    }

    /// An ArduPilot vehicle's onboard magnetometer calibration as its telemetry gave it, and what
    /// was undone (`None` for other vehicles or without the undo).
    pub(crate) fn ardupilot_onboard(&self) -> Option<crate::io::onboard::OnboardReport> {
        if self.autopilot != Autopilot::ArduPilot || self.ardupilot_mag != ArduPilotMag::Undo {
            return None;
        }
        let sources: std::collections::BTreeMap<u8, String> = self
            .tracks
            .iter()
            .map(|t| (t.instance.compass_id(), t.name.clone()))
            .collect();
        let (undone, not_undone) = self.ardupilot.describe(&sources);
        Some(crate::io::onboard::OnboardReport {
            stack: "ardupilot".into(),
            mag: self.ardupilot.onboard_cals(&sources),
            undone,
            not_undone,
            gps: self.first_position.map(|p| [p.lat_deg, p.lon_deg, p.alt_m]),
            ..Default::default()
        })
    }

    /// Take every instance, not only the primary: [`MessageConverter::convert_any`] gives them.
    pub(crate) fn with_other_instances(mut self) -> Self {
        self.others = true;
        self
    }

    /// The instance samples are taken from, once chosen.
    pub fn instance(&self) -> Option<&str> {
        self.primary.map(|k| self.tracks[k].name.as_str())
    }

    /// The index of the primary instance among [`MessageConverter::instances`], once chosen.
    pub(crate) fn primary_index(&self) -> Option<usize> {
        self.primary
    }

    /// Every instance taken so far, in the order first seen.
    pub fn instances(&self) -> Vec<InstanceInfo> {
        self.tracks
            .iter()
            .map(|t| InstanceInfo {
                name: t.name.clone(),
                compass_id: t.instance.compass_id(),
                samples: t.samples,
                units: self.units_of(&t.instance),
                time: t.clock.stats.clone(),
            })
            .collect()
    }

    /// Units of the primary instance's samples (RAW_IMU without a scale gives counts).
    pub fn units(&self) -> Units {
        match self.primary {
            Some(k) => self.units_of(&self.tracks[k].instance),
            None => self.units_of(&Instance {
                kind: ImuKind::Unknown,
                id: None,
            }),
        }
    }

    fn units_of(&self, i: &Instance) -> Units {
        let raw = i.kind == ImuKind::RawImu && self.raw_imu_ardupilot != Some(true);
        let u = |scale: f64| {
            if raw && scale == 0.0 {
                Unit::Counts
            } else {
                Unit::Si
            }
        };
        Units {
            accel: u(self.raw_scale.accel),
            gyro: u(self.raw_scale.gyro),
            mag: u(self.raw_scale.mag),
        }
    }

    /// The track of an instance, taken on when `choice` (or taking every instance) admits it;
    /// `None` (counted) when it is not wanted.
    fn track_for(&mut self, inst: Instance, has_mag: bool) -> Option<usize> {
        if let Some(k) = self.tracks.iter().position(|t| t.instance == inst) {
            if Some(k) == self.primary || self.others {
                return Some(k);
            }
            self.stats.skip("other_instance");
            return None;
        }
        let primary = self.primary.is_none()
            && match &self.choice {
                InstanceChoice::Named(want) => *want == inst.name(),
                InstanceChoice::Auto => has_mag,
            };
        let other = self.others && matches!(self.choice, InstanceChoice::Auto);
        if !(primary || other) {
            self.stats.skip("other_instance");
            return None;
        }
        if self.tracks.len() >= MAX_INSTANCES {
            self.stats.skip("too_many_instances");
            return None;
        }
        self.tracks.push(Track {
            instance: inst,
            name: inst.name(),
            clock: SourceClock::new(ClockSettings::default()),
            last_frame: None,
            attitudes_taken: 0,
            samples: 0,
        });
        let k = self.tracks.len() - 1;
        if primary {
            self.primary = Some(k);
        }
        Some(k)
    }

    /// Keep what the vehicle says about itself for the samples that follow: its attitude (body
    /// FRD -> NED in MAVLink, kept as sensor -> ENU with the body taken as the sensor frame), its
    /// position and its battery current. Values that are not finite or say "unknown" are ignored.
    fn vehicle_state(&mut self, msg: &MavMessage, time_us: u64) {
        self.vehicle_state_inner(msg, time_us);
        if self.first_position.is_none() {
            self.first_position = self.position;
        }
    }

    fn vehicle_state_inner(&mut self, msg: &MavMessage, time_us: u64) {
        match msg {
            MavMessage::ATTITUDE_QUATERNION(d) => {
                let q = [d.q1, d.q2, d.q3, d.q4].map(f64::from);
                if let Some(q) = crate::attitude::ned_to_enu(q) {
                    self.attitude = Some((time_us, q));
                    self.attitude_count += 1;
                }
            }
            MavMessage::ATTITUDE(d) => {
                let q = crate::attitude::quat_from_euler(
                    f64::from(d.roll),
                    f64::from(d.pitch),
                    f64::from(d.yaw),
                );
                if let Some(q) = crate::attitude::ned_to_enu(q) {
                    self.attitude = Some((time_us, q));
                    self.attitude_count += 1;
                }
            }
            MavMessage::GLOBAL_POSITION_INT(d) if d.lat != 0 || d.lon != 0 => {
                self.position = Some(crate::types::GeoPoint {
                    lat_deg: f64::from(d.lat) * 1e-7,
                    lon_deg: f64::from(d.lon) * 1e-7,
                    alt_m: f64::from(d.alt) * 1e-3,
                });
            }
            MavMessage::GPS_RAW_INT(d) if (d.fix_type as u32) >= 3 => {
                self.position = Some(crate::types::GeoPoint {
                    lat_deg: f64::from(d.lat) * 1e-7,
                    lon_deg: f64::from(d.lon) * 1e-7,
                    alt_m: f64::from(d.alt) * 1e-3,
                });
            }
            // Centiamperes; -1 is "not measured".
            MavMessage::BATTERY_STATUS(d) if d.current_battery >= 0 => {
                self.current_a = Some(f64::from(d.current_battery) / 100.0);
            }
            MavMessage::SYS_STATUS(d) if d.current_battery >= 0 => {
                self.current_a = Some(f64::from(d.current_battery) / 100.0);
            }
            _ => {}
        }
    }

    /// Convert one message of the primary instance (see [`MessageConverter::convert_any`]).
    pub fn convert(&mut self, msg: &MavMessage, time_us: u64) -> Option<Sample> {
        match self.convert_any(msg, time_us)? {
            (k, s) if Some(k) == self.primary => Some(s),
            _ => None,
        }
    }

    /// The readings of an IMU message: instance, its own time, accelerometer, gyroscope,
    /// magnetometer (in the units [`MessageConverter::units`] gives), temperature, and whether the
    /// message carries a magnetometer. `None` for other messages.
    fn imu_reading(&self, msg: &MavMessage) -> Option<ImuReading> {
        Some(match msg {
            MavMessage::HIGHRES_IMU(d) => {
                let m = [
                    d.xmag as f64 * 100.0,
                    d.ymag as f64 * 100.0,
                    d.zmag as f64 * 100.0,
                ];
                let has = m.iter().any(|v| *v != 0.0);
                (
                    Instance {
                        kind: ImuKind::HighresImu,
                        id: Some(d.id),
                    },
                    MsgTime::Usec(d.time_usec),
                    [d.xacc as f64, d.yacc as f64, d.zacc as f64],
                    [d.xgyro as f64, d.ygyro as f64, d.zgyro as f64],
                    m,
                    Some(d.temperature as f64),
                    has,
                )
            }
            MavMessage::SCALED_IMU(d) => scaled_imu!(ImuKind::ScaledImu, d),
            MavMessage::SCALED_IMU2(d) => scaled_imu!(ImuKind::ScaledImu2, d),
            MavMessage::SCALED_IMU3(d) => scaled_imu!(ImuKind::ScaledImu3, d),
            MavMessage::RAW_IMU(d) => {
                let sc = |v: i16, s: f64| if s == 0.0 { v as f64 } else { v as f64 * s };
                // ArduPilot fills RAW_IMU as SCALED_IMU (mG, mrad/s, mGauss); a configured
                // scale still wins.
                let ap = self.raw_imu_ardupilot == Some(true);
                let pick = |configured: f64, ardupilot: f64| {
                    if configured == 0.0 && ap {
                        ardupilot
                    } else {
                        configured
                    }
                };
                let (ka, kg, km) = (
                    pick(self.raw_scale.accel, MG_TO_MPS2),
                    pick(self.raw_scale.gyro, 1e-3),
                    pick(self.raw_scale.mag, 0.1),
                );
                let m = [sc(d.xmag, km), sc(d.ymag, km), sc(d.zmag, km)];
                (
                    Instance {
                        kind: ImuKind::RawImu,
                        id: Some(d.id),
                    },
                    MsgTime::Usec(d.time_usec),
                    [sc(d.xacc, ka), sc(d.yacc, ka), sc(d.zacc, ka)],
                    [sc(d.xgyro, kg), sc(d.ygyro, kg), sc(d.zgyro, kg)],
                    m,
                    if d.temperature != 0 {
                        Some(d.temperature as f64 / 100.0)
                    } else {
                        None
                    },
                    m.iter().any(|v| *v != 0.0),
                )
            }
            _ => return None,
        })
    }

    /// Convert one message: the instance's index among [`MessageConverter::instances`] and the
    /// sample. `time_us` is the receive time (tlog record time or the link's clock, 0 when
    /// unknown), which the instance's [`SourceClock`] falls back on when the message's own time is
    /// unusable. A repeated frame (same time and readings) gives `None`, counted in its clock's
    /// statistics.
    #[allow(deprecated)] // SENSOR_OFFSETS: deprecated in the dialect, sent by older ArduPilot
    pub(crate) fn convert_any(
        &mut self,
        msg: &MavMessage,
        time_us: u64,
    ) -> Option<(usize, Sample)> {
        let (name, t_us, acc, gyr, mag, temp, has_mag) = match msg {
            MavMessage::VFR_HUD(d) => {
                let th = d.throttle as f64 / 100.0;
                self.throttle = if th.is_finite() {
                    Some(th.clamp(0.0, 1.5))
                } else {
                    None
                };
                return None;
            }
            MavMessage::ATTITUDE_QUATERNION(_)
            | MavMessage::ATTITUDE(_)
            | MavMessage::GLOBAL_POSITION_INT(_)
            | MavMessage::GPS_RAW_INT(_)
            | MavMessage::BATTERY_STATUS(_)
            | MavMessage::SYS_STATUS(_) => {
                self.vehicle_state(msg, time_us);
                return None;
            }
            MavMessage::HEARTBEAT(h) => {
                use mavlink::dialects::ardupilotmega::MavAutopilot;
                // A ground station's or companion's HEARTBEAT names no flight stack. Once one
                // names ArduPilot, its magnetometer data are taken as calibrated from then on.
                if h.autopilot == MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA {
                    self.autopilot = Autopilot::ArduPilot;
                } else if self.autopilot == Autopilot::Unknown
                    && h.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
                {
                    self.autopilot = Autopilot::Other;
                }
                return None;
            }
            MavMessage::PARAM_VALUE(_) | MavMessage::SENSOR_OFFSETS(_) => {
                self.ardupilot.absorb(msg);
                return None;
            }
            MavMessage::RAW_IMU(_) => {
                if self.raw_imu_ardupilot.is_none() {
                    self.raw_imu_ardupilot = Some(self.autopilot == Autopilot::ArduPilot);
                }
                self.imu_reading(msg)?
            }
            _ => self.imu_reading(msg)?,
        };
        let k = self.track_for(name, has_mag)?;
        let throttle = self.throttle;
        let t = &mut self.tracks[k];
        // A repeated frame (same time and readings, e.g. from two routes through a router) is
        // dropped and counted; a repeated time with new readings is the clock's to judge.
        let key = (t_us, acc, gyr, mag);
        if t.last_frame.replace(key) == Some(key) {
            t.clock.duplicate();
            self.sync_time_stats();
            return None;
        }
        let (msg_us, wrap_us) = match t_us {
            MsgTime::Usec(t) => (crate::io::clock::us_from_u64(t), None),
            MsgTime::BootMs(t) => (i64::from(t) * 1000, Some(MS32_WRAP_US)),
        };
        let recv_us = Some(crate::io::clock::us_from_u64(time_us)).filter(|t| *t > 0);
        let stamp = t.clock.stamp(Some(msg_us), recv_us, wrap_us);
        t.samples += 1;
        self.sync_time_stats();
        let fresh = self.tracks[k].attitudes_taken < self.attitude_count;
        self.tracks[k].attitudes_taken = self.attitude_count;
        let ref_q = self
            .attitude
            .filter(|(at, _)| {
                fresh && (*at == 0 || time_us == 0 || time_us.abs_diff(*at) <= ATTITUDE_MAX_AGE_US)
            })
            .map(|(_, q)| q);
        let mut s = Sample {
            t_s: stamp.t_s,
            segment: stamp.segment,
            throttle,
            current_a: self.current_a,
            ref_q,
            position: self.position,
            ..Default::default()
        };
        let mut bad = false;
        let mut take = |v: Vec3| {
            let r = finite3(v);
            bad |= r.is_none();
            r
        };
        s.accel_mps2 = take(acc);
        s.gyro_rad_s = take(gyr);
        s.mag_ut = if has_mag { take(mag) } else { None };
        s.temp_c = temp.filter(|x| x.is_finite());
        if self.autopilot == Autopilot::ArduPilot {
            if let Some(m) = s.mag_ut {
                let compass = self.tracks[k].instance.compass_id();
                s.mag_ut = match self.ardupilot_mag {
                    ArduPilotMag::Keep => Some(m),
                    ArduPilotMag::Undo => self.ardupilot.undo(compass, m.map(|v| v * 10.0), s.t_s),
                    ArduPilotMag::Refuse => None,
                };
                if s.mag_ut.is_none() {
                    self.stats.skip("mag_awaiting_params");
                }
            }
        }
        if Some(k) == self.primary {
            if bad {
                self.stats.skip("non_finite");
            }
            self.stats.records += 1;
            self.stats.count_sample(&s);
        }
        Some((k, s))
    }
}

/// An IMU message's readings (see [`MessageConverter::imu_reading`]).
type ImuReading = (Instance, MsgTime, Vec3, Vec3, Vec3, Option<f64>, bool);

/// A message's own time field.
#[derive(Debug, Clone, Copy, PartialEq)]
enum MsgTime {
    /// `time_usec`: microseconds (since boot or the Unix epoch).
    Usec(u64),
    /// `time_boot_ms`: milliseconds since boot, a u32 that wraps.
    BootMs(u32),
}

/// The wrap period of a u32 millisecond time field, us.
const MS32_WRAP_US: i64 = (1i64 << 32) * 1000;

/// [`scaled`] of a SCALED_IMU, SCALED_IMU2 or SCALED_IMU3 message (`$d`): the same fields in three
/// types.
macro_rules! scaled_imu {
    ($name:expr, $d:expr) => {
        scaled(
            $name,
            $d.time_boot_ms,
            [$d.xacc, $d.yacc, $d.zacc],
            [$d.xgyro, $d.ygyro, $d.zgyro],
            [$d.xmag, $d.ymag, $d.zmag],
            $d.temperature,
        )
    };
}
use scaled_imu;

fn scaled(
    name: ImuKind,
    t_ms: u32,
    a: [i16; 3],
    g: [i16; 3],
    m: [i16; 3],
    temp: i16,
) -> (Instance, MsgTime, Vec3, Vec3, Vec3, Option<f64>, bool) {
    let f = |v: [i16; 3], k: f64| [v[0] as f64 * k, v[1] as f64 * k, v[2] as f64 * k];
    (
        Instance {
            kind: name,
            id: None,
        },
        MsgTime::BootMs(t_ms),
        f(a, MG_TO_MPS2),
        f(g, 1e-3),
        f(m, 0.1),
        if temp != 0 {
            Some(temp as f64 / 100.0)
        } else {
            None
        },
        m.iter().any(|v| *v != 0),
    )
}
