//! Decoding bytes into [`Sample`]s: MAVLink frames (live links and `.tlog` files) and CSV text.
//! Pure functions over byte slices; the transports live in `sources`.
//!
//! Every kind of bad input is counted by reason in [`DecodeStats`] and skipped, never fatal:
//! `bad_crc`, `truncated`, `resync` (garbage bytes between frames), `unknown_message` (an id this
//! dialect does not know), `bad_payload`, `non_finite`, `bad_row`, `other_instance`.

use crate::io::clock::{ClockSettings, SourceClock, TimeStats};
use crate::types::{Sample, Unit, Units, Vec3};
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavlinkVersion, Message};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Counters of what was read and what was skipped, by reason.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct DecodeStats {
    /// Frames (or CSV rows) decoded.
    pub records: u64,
    /// Samples carrying each sensor.
    pub counts: SensorCounts,
    /// Skipped items by reason.
    pub skipped: BTreeMap<String, u64>,
    /// What the source's clock did: its choice, time segments, faults by kind.
    #[serde(default)]
    pub time: TimeStats,
}

impl DecodeStats {
    pub fn skip(&mut self, reason: &str) {
        bump(&mut self.skipped, reason, 1);
    }
    pub(crate) fn skip_n(&mut self, reason: &str, n: u64) {
        if n > 0 {
            bump(&mut self.skipped, reason, n);
        }
    }
    pub(crate) fn count_sample(&mut self, s: &Sample) {
        let c = &mut self.counts;
        c.accel += s.accel_mps2.is_some() as u64;
        c.gyro += s.gyro_rad_s.is_some() as u64;
        c.mag += s.mag_ut.is_some() as u64;
        c.temp += s.temp_c.is_some() as u64;
        c.throttle += s.throttle.is_some() as u64;
    }
}

/// How many samples carried each sensor. Serialised as a map of the non-zero counts
/// (`{"accel": 12, "mag": 12}`); counted once per sample, so plain fields rather than a map.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(default, deny_unknown_fields)]
pub struct SensorCounts {
    #[serde(skip_serializing_if = "is_zero")]
    pub accel: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub gyro: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub mag: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub temp: u64,
    #[serde(skip_serializing_if = "is_zero")]
    pub throttle: u64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

impl SensorCounts {
    pub fn is_empty(&self) -> bool {
        *self == SensorCounts::default()
    }

    pub fn add(&mut self, o: &SensorCounts) {
        self.accel += o.accel;
        self.gyro += o.gyro;
        self.mag += o.mag;
        self.temp += o.temp;
        self.throttle += o.throttle;
    }

    /// The non-zero counts by sensor name.
    pub fn to_map(&self) -> BTreeMap<String, u64> {
        [
            ("accel", self.accel),
            ("gyro", self.gyro),
            ("mag", self.mag),
            ("temp", self.temp),
            ("throttle", self.throttle),
        ]
        .into_iter()
        .filter(|(_, n)| *n > 0)
        .map(|(k, n)| (k.to_string(), n))
        .collect()
    }
}

/// Add `n` to counter `key`, allocating the key only the first time it is seen.
fn bump(map: &mut BTreeMap<String, u64>, key: &str, n: u64) {
    match map.get_mut(key) {
        Some(c) => *c += n,
        None => {
            map.insert(key.to_string(), n);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// MAVLink framing

/// Tables of the MAVLink checksum (CRC-16/MCRF4XX: reflected polynomial 0x8408, initial 0xFFFF, no
/// final XOR), built at compile time: `CRC_TABLES[0]` is the usual one-byte table and
/// `CRC_TABLES[k][i]` is the effect of byte `i` followed by `k` zero bytes, so eight bytes are
/// folded in per step ("slicing by 8"; the CRC is linear, so the eight lookups combine by XOR).
const CRC_TABLES: [[u16; 256]; 8] = {
    let mut t = [[0u16; 256]; 8];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u16;
        let mut b = 0;
        while b < 8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0x8408
            } else {
                c >> 1
            };
            b += 1;
        }
        t[0][i] = c;
        i += 1;
    }
    let mut k = 1;
    while k < 8 {
        let mut i = 0;
        while i < 256 {
            let prev = t[k - 1][i];
            t[k][i] = (prev >> 8) ^ t[0][(prev & 0xFF) as usize];
            i += 1;
        }
        k += 1;
    }
    t
};

/// The MAVLink frame checksum over `data` (the frame after the magic byte, up to the payload's
/// end) and the message's extra CRC byte: the same value as `mavlink::calculate_crc`, eight bytes
/// per step instead of a bit loop per byte (that loop was a tenth of replay time).
pub(crate) fn frame_crc(data: &[u8], extra_crc: u8) -> u16 {
    let t = &CRC_TABLES;
    let mut crc = 0xFFFFu16;
    let mut chunks = data.chunks_exact(8);
    for c in &mut chunks {
        let x = crc ^ u16::from_le_bytes([c[0], c[1]]);
        crc = t[7][(x & 0xFF) as usize]
            ^ t[6][(x >> 8) as usize]
            ^ t[5][c[2] as usize]
            ^ t[4][c[3] as usize]
            ^ t[3][c[4] as usize]
            ^ t[2][c[5] as usize]
            ^ t[1][c[6] as usize]
            ^ t[0][c[7] as usize];
    }
    for &b in chunks.remainder().iter().chain(std::iter::once(&extra_crc)) {
        crc = (crc >> 8) ^ t[0][((crc ^ b as u16) & 0xFF) as usize];
    }
    crc
}

/// A decoded frame.
#[derive(Debug, Clone)]
pub struct Frame {
    pub version: MavlinkVersion,
    pub system_id: u8,
    pub component_id: u8,
    pub message: MavMessage,
}

/// Result of looking for one frame at the start of a buffer.
#[derive(Debug)]
pub enum FrameParse {
    /// A good frame and the number of bytes it used.
    Frame(Box<Frame>, usize),
    /// The buffer holds the start of a frame but not all of it.
    Incomplete,
    /// Not a frame here (or a damaged one): skip `usize` bytes, counted under the reason.
    Skip(usize, SkipReason),
}

/// Why bytes of a MAVLink stream were skipped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkipReason {
    /// No frame starts here: look for the next magic byte.
    Resync,
    /// A whole frame of a message this build does not know.
    UnknownMessage,
    /// A frame whose checksum does not match: its first byte is skipped.
    BadCrc,
    /// A frame whose payload the bindings refuse.
    BadPayload,
}

impl SkipReason {
    /// The name counted in [`DecodeStats::skipped`] and shown in reports.
    pub fn name(self) -> &'static str {
        match self {
            SkipReason::Resync => "resync",
            SkipReason::UnknownMessage => "unknown_message",
            SkipReason::BadCrc => "bad_crc",
            SkipReason::BadPayload => "bad_payload",
        }
    }

    /// A whole frame is skipped (the stream goes on after it), not a byte to resynchronise.
    pub(crate) fn whole_frame(self) -> bool {
        matches!(self, SkipReason::UnknownMessage | SkipReason::BadPayload)
    }
}

const V1_MAGIC: u8 = 0xFE;
const V2_MAGIC: u8 = 0xFD;

/// Parse one MAVLink v1 or v2 frame at the start of `buf`, checking the CRC with the dialect's extra
/// CRC. Signed v2 frames are accepted (the signature is not checked).
pub fn parse_frame(buf: &[u8]) -> FrameParse {
    let Some(&magic) = buf.first() else {
        return FrameParse::Incomplete;
    };
    let (version, header_len, total) = match magic {
        V1_MAGIC => {
            if buf.len() < 2 {
                return FrameParse::Incomplete;
            }
            let len = buf[1] as usize;
            (MavlinkVersion::V1, 6usize, 6 + len + 2)
        }
        V2_MAGIC => {
            if buf.len() < 3 {
                return FrameParse::Incomplete;
            }
            let len = buf[1] as usize;
            let incompat = buf[2];
            if incompat & !0x01 != 0 {
                return FrameParse::Skip(1, SkipReason::Resync);
            }
            let sig = if incompat & 0x01 != 0 { 13 } else { 0 };
            (MavlinkVersion::V2, 10usize, 10 + len + 2 + sig)
        }
        _ => return FrameParse::Skip(1, SkipReason::Resync),
    };
    if buf.len() < total {
        return FrameParse::Incomplete;
    }
    let len = buf[1] as usize;
    let (sys, comp, msgid) = match version {
        MavlinkVersion::V1 => (buf[3], buf[4], buf[5] as u32),
        MavlinkVersion::V2 => (
            buf[5],
            buf[6],
            u32::from_le_bytes([buf[7], buf[8], buf[9], 0]),
        ),
    };
    let payload = &buf[header_len..header_len + len];
    let crc_got = u16::from_le_bytes([buf[header_len + len], buf[header_len + len + 1]]);
    if !known_message(msgid) {
        // The CRC cannot be checked without the message's extra CRC: skip the frame as unknown.
        return FrameParse::Skip(total, SkipReason::UnknownMessage);
    }
    let crc = frame_crc(&buf[1..header_len + len], MavMessage::extra_crc(msgid));
    if crc != crc_got {
        return FrameParse::Skip(1, SkipReason::BadCrc);
    }
    match MavMessage::parse(version, msgid, payload) {
        Ok(message) => FrameParse::Frame(
            Box::new(Frame {
                version,
                system_id: sys,
                component_id: comp,
                message,
            }),
            total,
        ),
        Err(_) => FrameParse::Skip(total, SkipReason::BadPayload),
    }
}

/// Whether the dialect knows message `id`. The dialect only answers by building a default
/// message, a few hundred bytes, so the answers for ids below 65536 (all of ardupilotmega's) are
/// kept in a bit set built on first use.
fn known_message(id: u32) -> bool {
    static KNOWN: std::sync::OnceLock<Vec<u64>> = std::sync::OnceLock::new();
    let known = KNOWN.get_or_init(|| {
        let mut bits = vec![0u64; 1 << 10];
        for i in 0..1u32 << 16 {
            if MavMessage::default_message_from_id(i).is_some() {
                bits[(i >> 6) as usize] |= 1 << (i & 63);
            }
        }
        bits
    });
    match known.get((id >> 6) as usize) {
        Some(w) => w & (1 << (id & 63)) != 0,
        None => MavMessage::default_message_from_id(id).is_some(),
    }
}

/// Streaming frame decoder for byte streams (serial, TCP): feed bytes, take frames.
#[derive(Debug, Default)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    pub stats: DecodeStats,
}

impl FrameDecoder {
    pub fn new() -> Self {
        Self::default()
    }
    /// Append bytes and return every complete frame now available.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Frame> {
        self.buf.extend_from_slice(bytes);
        let mut out = Vec::new();
        let mut pos = 0;
        while pos < self.buf.len() {
            match parse_frame(&self.buf[pos..]) {
                FrameParse::Frame(f, n) => {
                    out.push(*f);
                    pos += n;
                }
                FrameParse::Incomplete => break,
                FrameParse::Skip(n, why) => {
                    // Count a bad frame once, not once per byte of it.
                    if why != SkipReason::Resync
                        || self.buf[pos] == V1_MAGIC
                        || self.buf[pos] == V2_MAGIC
                    {
                        self.stats.skip(why.name());
                    }
                    pos += n;
                }
            }
        }
        self.buf.drain(..pos);
        // Bound memory: a frame is at most 280 bytes.
        if self.buf.len() > 4096 {
            let drop = self.buf.len() - 280;
            self.stats.skip_n("resync", 1);
            self.buf.drain(..drop);
        }
        out
    }
}

// ---------------------------------------------------------------------------------------------
// Messages to samples

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

// ---------------------------------------------------------------------------------------------
// tlog

/// Read a whole `.tlog` (each record: big-endian u64 microseconds, then one raw frame) into samples.
/// Garbage between records, damaged frames and a truncated tail are counted and skipped.
pub fn decode_tlog(bytes: &[u8], conv: &mut MessageConverter) -> Vec<Sample> {
    let mut out = Vec::new();
    decode_tlog_with(bytes, conv, &mut |k, s, _, conv| {
        if Some(k) == conv.primary_index() {
            out.push(s)
        }
    });
    out
}

/// As [`decode_tlog`], handing each sample of every instance the converter takes to
/// `emit(instance_index, sample, bytes_read_so_far, converter)` as it is decoded.
pub(crate) fn decode_tlog_with(
    bytes: &[u8],
    conv: &mut MessageConverter,
    emit: &mut dyn FnMut(usize, Sample, usize, &MessageConverter),
) {
    let mut records = TlogRecords::new(bytes);
    while let Some((ts, f)) = records.next() {
        if let Some((k, s)) = conv.convert_any(&f.message, ts) {
            emit(k, s, records.position(), conv);
        }
    }
    for (why, n) in &records.stats.skipped {
        conv.stats.skip_n(why, *n);
    }
}

/// The `.tlog` reader, for `replay` and the live `file:` link alike: records (record time in us,
/// frame), each a big-endian u64 timestamp then one raw MAVLink frame. Garbage between records and
/// damaged frames are skipped (resynchronising on the next good record) and a truncated tail
/// ends the log, each counted in `stats.skipped`; `stats.records` counts frames.
pub struct TlogRecords<'a> {
    bytes: &'a [u8],
    cursor: TlogCursor,
    pub stats: DecodeStats,
}

/// Where a tlog reader is in its bytes, and what it knows there.
#[derive(Debug, Clone, Copy)]
struct TlogCursor {
    /// Offset of the next record.
    pos: usize,
    last_ts: Option<u64>,
    /// More bytes follow the bytes read (a window of a [`TlogStream`]): nothing within
    /// [`TLOG_LOOKAHEAD`] of their end is decided on, and their end is no truncation.
    more: bool,
    /// A resynchronisation reached the end of the window: the next window goes on with it.
    resyncing: bool,
}

impl TlogCursor {
    fn new(more: bool) -> TlogCursor {
        TlogCursor {
            pos: 0,
            last_ts: None,
            more,
            resyncing: false,
        }
    }
}

/// Bytes a window of a stream keeps beyond the last offset it decides on: a resynchronisation
/// checks a whole record and the next, each a timestamp and a frame of at most
/// [`MAX_FRAME_BYTES`].
const TLOG_LOOKAHEAD: usize = 2 * (8 + MAX_FRAME_BYTES) + 8;

/// The longest MAVLink frame: a v2 header of 10 bytes, 255 of payload, a CRC and a 13-byte signature.
const MAX_FRAME_BYTES: usize = 280;

/// How far from the last record time a resynchronisation trusts a timestamp on its own, us.
const RESYNC_NEAR_US: u64 = 86_400_000_000;

impl<'a> TlogRecords<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        TlogRecords {
            bytes,
            cursor: TlogCursor::new(false),
            stats: DecodeStats::default(),
        }
    }

    /// Bytes read so far.
    pub fn position(&self) -> usize {
        self.cursor.pos
    }
}

/// A tlog reader's bytes with its cursor and counts, borrowed for one step: [`TlogRecords`] and
/// [`TlogStream`] read through it alike.
struct TlogReader<'a> {
    bytes: &'a [u8],
    cursor: &'a mut TlogCursor,
    stats: &'a mut DecodeStats,
}

impl TlogReader<'_> {
    /// The offset up to which records are read: the end, or short of it by [`TLOG_LOOKAHEAD`]
    /// when more bytes follow.
    fn limit(&self) -> usize {
        if self.cursor.more {
            self.bytes.len().saturating_sub(TLOG_LOOKAHEAD)
        } else {
            self.bytes.len()
        }
    }

    fn ts_at(&self, p: usize) -> u64 {
        let mut b = [0u8; 8];
        b.copy_from_slice(&self.bytes[p..p + 8]);
        u64::from_be_bytes(b)
    }

    /// A whole record (timestamp and a frame that checks out) at `p`, and its length.
    fn record_at(&self, p: usize) -> Option<usize> {
        let rest = self.bytes.get(p + 8..).filter(|r| r.len() > 1)?;
        match parse_frame(rest) {
            FrameParse::Frame(_, n) if rest[0] == V1_MAGIC || rest[0] == V2_MAGIC => Some(8 + n),
            _ => None,
        }
    }

    /// The next offset from `from` that holds a good record: one whose timestamp is within a day
    /// of the last, or (two logs joined, days apart) one followed by another good record. A
    /// CRC-checked pair does not happen by chance in garbage.
    fn skip_to(&mut self, from: usize) {
        self.cursor.pos = self.resync(from);
        self.cursor.resyncing = self.cursor.more && self.cursor.pos >= self.limit();
    }

    fn resync(&self, from: usize) -> usize {
        let n = self.bytes.len();
        let end = self.limit();
        let mut p = from;
        while p < end && p + 9 < n {
            let m = self.bytes[p + 8];
            if m == V1_MAGIC || m == V2_MAGIC {
                if let Some(len) = self.record_at(p) {
                    let ts = self.ts_at(p);
                    let near = match self.cursor.last_ts {
                        Some(l) => ts.abs_diff(l) < RESYNC_NEAR_US,
                        None => ts > 0,
                    };
                    if near || self.record_at(p + len).is_some() {
                        return p;
                    }
                }
            }
            p += 1;
        }
        if self.cursor.more {
            p
        } else {
            n
        }
    }

    /// The next record, `None` at the end (of the window, when more bytes follow).
    fn next_record(&mut self) -> Option<(u64, Box<Frame>)> {
        let n = self.bytes.len();
        let end = self.limit();
        if self.cursor.resyncing {
            self.cursor.resyncing = false;
            self.skip_to(self.cursor.pos);
        }
        while self.cursor.pos < end && self.cursor.pos + 8 < n {
            let pos = self.cursor.pos;
            let ts = self.ts_at(pos);
            let rest = &self.bytes[pos + 8..];
            // Where a record is expected, a magic byte and a frame that checks out are enough:
            // its record time may be anything (logs joined with `cat` jump back by hours or
            // days); the source's clock sorts that out.
            if !(rest[0] == V1_MAGIC || rest[0] == V2_MAGIC) {
                self.stats.skip("resync");
                self.skip_to(pos + 1);
                continue;
            }
            match parse_frame(rest) {
                FrameParse::Frame(f, len) => {
                    self.cursor.last_ts = Some(ts);
                    self.cursor.pos += 8 + len;
                    self.stats.records += 1;
                    return Some((ts, f));
                }
                FrameParse::Incomplete => {
                    self.stats.skip("truncated");
                    self.cursor.pos = n;
                    return None;
                }
                FrameParse::Skip(len, why) => {
                    self.stats.skip(why.name());
                    if why.whole_frame() {
                        self.cursor.last_ts = Some(ts);
                        self.cursor.pos += 8 + len;
                    } else {
                        self.skip_to(pos + 1);
                    }
                }
            }
        }
        if !self.cursor.more && self.cursor.pos < n {
            self.stats.skip("truncated");
            self.cursor.pos = n;
        }
        None
    }
}

impl Iterator for TlogRecords<'_> {
    type Item = (u64, Box<Frame>);

    fn next(&mut self) -> Option<(u64, Box<Frame>)> {
        TlogReader {
            bytes: self.bytes,
            cursor: &mut self.cursor,
            stats: &mut self.stats,
        }
        .next_record()
    }
}

/// [`TlogRecords`] read from a stream (a file, gunzipped or not) through a window of about
/// [`crate::io::window::STREAM_CHUNK_BYTES`]: the same records and counts as from the whole bytes, in memory that
/// does not grow with the log. A read error ends the records and is kept ([`TlogStream::error`]).
pub(crate) struct TlogStream<R> {
    reader: R,
    buf: Vec<u8>,
    /// The cursor in `buf` (`more` until the stream's end), and the offset of `buf` in the stream.
    cursor: TlogCursor,
    base: usize,
    pub stats: DecodeStats,
    pub error: Option<std::io::Error>,
}

impl<R: std::io::Read> TlogStream<R> {
    pub fn new(reader: R) -> Self {
        TlogStream {
            reader,
            buf: Vec::with_capacity(crate::io::window::STREAM_CHUNK_BYTES + TLOG_LOOKAHEAD),
            cursor: TlogCursor::new(true),
            base: 0,
            stats: DecodeStats::default(),
            error: None,
        }
    }

    /// Bytes of the stream read so far as records (or skipped).
    pub fn bytes_read(&self) -> usize {
        self.base + self.cursor.pos
    }

    /// The next record, as [`TlogRecords::next`] gives it.
    pub fn next_record(&mut self) -> Option<(u64, Box<Frame>)> {
        loop {
            let record = TlogReader {
                bytes: &self.buf,
                cursor: &mut self.cursor,
                stats: &mut self.stats,
            }
            .next_record();
            if record.is_some() || !self.cursor.more {
                return record;
            }
            let mut eof = false;
            crate::io::window::fill_window(
                &mut self.reader,
                &mut self.buf,
                (&mut self.cursor.pos, &mut self.base),
                &mut eof,
                &mut self.error,
            );
            self.cursor.more = !eof;
        }
    }
}

impl<R: std::io::Read> Iterator for TlogStream<R> {
    type Item = (u64, Box<Frame>);

    fn next(&mut self) -> Option<(u64, Box<Frame>)> {
        self.next_record()
    }
}

/// As [`decode_tlog_with`], the records read from a stream ([`TlogStream`]); `emit` gets the
/// bytes of the stream read so far. A read error is returned after what came before it.
pub(crate) fn decode_tlog_stream(
    records: &mut TlogStream<impl std::io::Read>,
    conv: &mut MessageConverter,
    emit: &mut dyn FnMut(usize, Sample, usize, &MessageConverter),
) -> Option<std::io::Error> {
    while let Some((ts, f)) = records.next_record() {
        if let Some((k, s)) = conv.convert_any(&f.message, ts) {
            emit(k, s, records.bytes_read(), conv);
        }
    }
    for (why, n) in &records.stats.skipped {
        conv.stats.skip_n(why, *n);
    }
    records.error.take()
}

// ---------------------------------------------------------------------------------------------
// CSV

/// Column mapping for CSV input: which header name feeds which field, with a unit scale.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CsvMapping {
    /// Field -> column name in the user's file. Fields: t, ax, ay, az, gx, gy, gz, mx, my, mz, temp,
    /// throttle, current, ref_qw, ref_qx, ref_qy, ref_qz, moving, lat, lon, alt (deg, deg, m).
    #[serde(default)]
    pub columns: BTreeMap<String, String>,
    /// Field -> factor that turns the column's unit into ours (e.g. ax = 9.80665 for g, t = 0.001 for ms).
    #[serde(default)]
    pub scales: BTreeMap<String, f64>,
    /// Rows per second, Hz, for a file without a time column (row i is at i / rate_hz s).
    /// Default: none; a file without a `t` column then needs it, or a rate in its preamble
    /// (a `Fs,50` or `rate_hz,50` line before the header). A `t` column wins over both.
    #[serde(default)]
    pub rate_hz: Option<f64>,
}

impl CsvMapping {
    /// The mapping of (field, column) pairs with (field, scale) pairs, as a config would give them.
    pub fn from_pairs(columns: &[(&str, &str)], scales: &[(&str, f64)]) -> CsvMapping {
        CsvMapping {
            columns: columns
                .iter()
                .map(|&(f, c)| (f.to_string(), c.to_string()))
                .collect(),
            scales: scales.iter().map(|&(f, k)| (f.to_string(), k)).collect(),
            rate_hz: None,
        }
    }
}

/// Lines of a CSV preamble (`key,value` lines before the header row) read at most.
const CSV_PREAMBLE_LINES: usize = 32;

/// Preamble keys that give the rows' rate, Hz (lower case): `Fs` as the sampling frequency is
/// written by MATLAB-style loggers.
const CSV_RATE_KEYS: [&str; 5] = [
    "fs",
    "rate_hz",
    "sample_rate",
    "sample_rate_hz",
    "sampling_rate",
];

/// Field names of CSV input, in the order [`sample_from_fields`] indexes them.
pub(crate) const FIELDS: [&str; 21] = [
    "t", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz", "temp", "throttle", "current",
    "ref_qw", "ref_qx", "ref_qy", "ref_qz", "moving", "lat", "lon", "alt",
];

/// Decompress if gzip, else borrow.
pub fn maybe_gunzip(bytes: &[u8]) -> std::io::Result<std::borrow::Cow<'_, [u8]>> {
    if bytes.len() >= 2 && bytes[0] == 0x1F && bytes[1] == 0x8B {
        use std::io::Read;
        let mut out = Vec::new();
        let mut d = flate2::read::MultiGzDecoder::new(bytes);
        match d.read_to_end(&mut out) {
            Ok(_) => {}
            // A truncated .gz still yields what came before the cut.
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !out.is_empty() => {}
            Err(e) => return Err(e),
        }
        Ok(std::borrow::Cow::Owned(out))
    } else {
        Ok(std::borrow::Cow::Borrowed(bytes))
    }
}

/// Decode CSV text (header row first; blank lines and `#` lines before it are skipped). Cells
/// may be quoted (RFC 4180). Columns may come in any order and subset; empty cells mean "no
/// reading". Rows with the wrong number of cells or unparsable numbers are counted and skipped.
pub fn decode_csv(
    text: &str,
    mapping: &CsvMapping,
    stats: &mut DecodeStats,
) -> Result<Vec<Sample>, String> {
    let (start, header, preamble_rate_hz) = csv_header(text, mapping)?;
    let mut rows = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(&text.as_bytes()[start..]);
    let mut row = csv::StringRecord::new();
    // (The header line is read whole above, so the reader's first record is the header.)
    if !matches!(rows.read_record(&mut row), Ok(true)) {
        return Err("empty file: no header row".into());
    }
    let cols: Vec<String> = row.iter().map(|c| c.to_string()).collect();
    // field index -> column index
    let mut idx = [usize::MAX; FIELDS.len()];
    for (fi, f) in FIELDS.iter().enumerate() {
        let want = mapping.columns.get(*f).map(String::as_str).unwrap_or(f);
        if let Some(ci) = cols.iter().position(|c| c == want) {
            idx[fi] = ci;
        }
    }
    for (f, c) in &mapping.columns {
        if !FIELDS.contains(&f.as_str()) {
            return Err(format!(
                "column mapping names unknown field `{f}` (known: {})",
                FIELDS.join(", ")
            ));
        }
        if !cols.iter().any(|h| h == c) {
            return Err(format!(
                "column `{c}` (mapped to `{f}`) is not in the header: {}",
                cols.join(",")
            ));
        }
    }
    let has = |f: &str| idx[FIELDS.iter().position(|x| *x == f).expect("field")] != usize::MAX;
    if !(has("ax") || has("mx") || has("gx")) {
        return Err(format!(
            "no sensor columns found in header `{header}`: expected ax/ay/az, gx/gy/gz or mx/my/mz, or a [input.csv] columns mapping"
        ));
    }
    // Row i's time when the file has no time column.
    let row_period_s = if has("t") {
        None
    } else {
        match mapping.rate_hz.or(preamble_rate_hz) {
            Some(r) if r.is_finite() && r > 0.0 => Some(1.0 / r),
            Some(r) => return Err(format!("the sample rate {r} Hz is not a positive number")),
            None => {
                return Err(format!(
                    "no time column in header `{header}` and no sample rate: give the rate (`imucald replay --rate-hz 100`, or rate_hz = 100 under [input.csv]), or name the time column (t = \"your_column\" under [input.csv.columns])"
                ))
            }
        }
    };
    let scale: Vec<f64> = FIELDS
        .iter()
        .map(|f| mapping.scales.get(*f).copied().unwrap_or(1.0))
        .collect();
    let mut out = Vec::new();
    // The `t` column is the message clock, kept as the file has it; there is no receive clock.
    let mut clock = SourceClock::new(ClockSettings {
        keep_origin: true,
        ..ClockSettings::default()
    });
    let mut last: Option<Sample> = None;
    let mut row_no = 0u64;
    loop {
        match rows.read_record(&mut row) {
            Ok(true) => {}
            Ok(false) => break,
            Err(_) => {
                stats.skip("bad_row");
                continue;
            }
        }
        // A line of blanks only (an empty line the reader skips itself).
        if row.len() == 1 && row[0].is_empty() {
            continue;
        }
        row_no += 1;
        if row.len() != cols.len() {
            stats.skip("bad_row");
            continue;
        }
        let mut vals = [None::<f64>; FIELDS.len()];
        let mut bad = false;
        for fi in 0..FIELDS.len() {
            let ci = idx[fi];
            if ci == usize::MAX {
                continue;
            }
            let c = &row[ci];
            if c.is_empty() {
                continue;
            }
            match c.parse::<f64>() {
                Ok(v) => vals[fi] = Some(v * scale[fi]),
                Err(_) => bad = true,
            }
        }
        if bad {
            stats.skip("bad_row");
            continue;
        }
        let t_s = match row_period_s {
            Some(dt) => (row_no - 1) as f64 * dt,
            None => vals[0].unwrap_or(f64::NAN),
        };
        let mut s = sample_from_fields(t_s, &vals, Some(stats));
        if !s.t_s.is_finite() {
            stats.skip("non_finite");
            continue;
        }
        if s.is_empty() {
            continue;
        }
        if last.replace(s) == Some(s) {
            // The same row again (time and readings): dropped and counted.
            clock.duplicate();
            continue;
        }
        let stamp = clock.stamp(Some(crate::io::clock::us_from_s(s.t_s)), None, None);
        (s.t_s, s.segment) = (stamp.t_s, stamp.segment);
        stats.records += 1;
        stats.count_sample(&s);
        out.push(s);
    }
    stats.time = clock.stats;
    Ok(out)
}

/// Where a CSV's header row starts (byte offset), the header line, and the rate its preamble
/// gives, if any. Blank and `#` lines are skipped; so are up to [`CSV_PREAMBLE_LINES`] lines
/// before a line naming a sensor column (`key,value` lines such as `Fs,50.00`).
fn csv_header<'a>(
    text: &'a str,
    mapping: &CsvMapping,
) -> Result<(usize, &'a str, Option<f64>), String> {
    let sensor_columns: Vec<&str> = ["ax", "gx", "mx"]
        .iter()
        .map(|f| mapping.columns.get(*f).map(String::as_str).unwrap_or(f))
        .collect();
    let names_sensor = |line: &str| {
        line.split(',')
            .any(|c| sensor_columns.contains(&c.trim().trim_matches('"')))
    };
    let mut first: Option<(usize, &str)> = None;
    let mut rate = None;
    let mut start = 0;
    for (n, l) in text.split_inclusive('\n').enumerate() {
        let line = l.trim_end_matches(['\n', '\r']);
        let at = start;
        start += l.len();
        if line.trim().is_empty() || line.starts_with('#') {
            continue;
        }
        if names_sensor(line) {
            return Ok((at, line, rate));
        }
        first.get_or_insert((at, line));
        if n >= CSV_PREAMBLE_LINES {
            break;
        }
        let mut cells = line.split(',').map(str::trim);
        if let (Some(k), Some(v), None) = (cells.next(), cells.next(), cells.next()) {
            if CSV_RATE_KEYS.contains(&k.to_ascii_lowercase().as_str()) {
                rate = v.parse::<f64>().ok();
            }
        }
    }
    // No line names a sensor column: the first is taken as the header (and refused by the caller).
    first
        .map(|(at, line)| (at, line, None))
        .ok_or_else(|| "empty file: no header row".to_string())
}

/// A sample from per-field values indexed like [`FIELDS`] (already scaled). A vector needs all three
/// components finite; a partial or non-finite one is dropped and, with `stats`, counted
/// (`partial_vector`, `non_finite`).
pub(crate) fn sample_from_fields(
    t_s: f64,
    vals: &[Option<f64>; FIELDS.len()],
    mut stats: Option<&mut DecodeStats>,
) -> Sample {
    let mut v3 = |a: usize| -> Option<Vec3> {
        match (vals[a], vals[a + 1], vals[a + 2]) {
            (Some(x), Some(y), Some(z)) => {
                let v = [x, y, z];
                if v.iter().all(|q| q.is_finite()) {
                    Some(v)
                } else {
                    if let Some(st) = stats.as_deref_mut() {
                        st.skip("non_finite");
                    }
                    None
                }
            }
            (None, None, None) => None,
            _ => {
                if let Some(st) = stats.as_deref_mut() {
                    st.skip("partial_vector");
                }
                None
            }
        }
    };
    let (accel_mps2, gyro_rad_s, mag_ut) = (v3(1), v3(4), v3(7));
    let fin = |x: Option<f64>| x.filter(|v| v.is_finite());
    Sample {
        t_s,
        segment: 0,
        accel_mps2,
        gyro_rad_s,
        mag_ut,
        temp_c: fin(vals[10]),
        throttle: fin(vals[11]),
        current_a: fin(vals[12]),
        ref_q: match (vals[13], vals[14], vals[15], vals[16]) {
            (Some(w), Some(x), Some(y), Some(z)) if [w, x, y, z].iter().all(|q| q.is_finite()) => {
                Some([w, x, y, z])
            }
            _ => None,
        },
        moving: vals[17].map(|v| v > 0.5),
        // A fix needs latitude and longitude; the height is 0 when absent.
        position: match (fin(vals[18]), fin(vals[19])) {
            (Some(lat_deg), Some(lon_deg)) => Some(crate::types::GeoPoint {
                lat_deg,
                lon_deg,
                alt_m: fin(vals[20]).unwrap_or(0.0),
            }),
            _ => None,
        },
    }
}

/// Input formats (also the command line's `--format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    Tlog,
    Csv,
    /// ArduPilot DataFlash log (.bin)
    Bin,
    /// PX4 ULog (.ulg)
    Ulg,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Tlog => "tlog",
            Format::Csv => "csv",
            Format::Bin => "bin",
            Format::Ulg => "ulg",
        }
    }
}

/// Detect the format from content: a tlog has a MAVLink magic byte after its first 8-byte
/// timestamp; CSV is text whose first line has a comma; a ULog file starts with its magic; a
/// DataFlash log has an FMT record defining FMT in its first bytes.
pub fn detect_format(bytes: &[u8]) -> Option<Format> {
    if crate::io::flightlog::ulog::looks_like(bytes) {
        return Some(Format::Ulg);
    }
    if crate::io::flightlog::dataflash::looks_like(bytes) {
        return Some(Format::Bin);
    }
    if bytes.len() > 9 && (bytes[8] == V1_MAGIC || bytes[8] == V2_MAGIC) {
        return Some(Format::Tlog);
    }
    let head = &bytes[..bytes.len().min(4096)];
    let text = String::from_utf8_lossy(head);
    let first = text
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))?;
    if first.contains(',')
        && first
            .chars()
            .all(|c| !c.is_control() || c == '\t' || c == '\r')
    {
        return Some(Format::Csv);
    }
    None
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn known_message_ids_are_the_dialects() {
        let mut known = 0;
        for id in (0..70_000u32).chain([1 << 20, (1 << 24) - 1, u32::MAX]) {
            let want = MavMessage::default_message_from_id(id).is_some();
            assert_eq!(known_message(id), want, "id {id}");
            known += want as usize;
        }
        // HEARTBEAT, HIGHRES_IMU, ArduPilot's MAG_CAL_REPORT: and a few hundred in all.
        assert!(known_message(0) && known_message(105) && known_message(192));
        assert!(known > 200, "{known}");
    }

    /// `msg` as a MAVLink `v` frame from system 1, component 1.
    fn frame_bytes(msg: &MavMessage, v: MavlinkVersion) -> Vec<u8> {
        let mut enc = crate::io::mavout::MavEncoder::new(1, 1);
        enc.version = v;
        enc.encode(msg)
    }

    fn imu_msg(x: f32) -> MavMessage {
        crate::testdata::level_highres_imu(1000, x)
    }

    #[test]
    fn frame_crc_matches_the_mavlink_crate() {
        let mut x = 0x1234_5678u32;
        for len in [0usize, 1, 2, 9, 30, 255, 280] {
            let data: Vec<u8> = (0..len)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    x as u8
                })
                .collect();
            for extra in [0u8, 46, 255] {
                assert_eq!(
                    frame_crc(&data, extra),
                    mavlink::calculate_crc(&data, extra)
                );
            }
        }
    }

    #[test]
    fn frames_v1_and_v2_roundtrip_and_bad_crc_is_counted() {
        for v in [MavlinkVersion::V1, MavlinkVersion::V2] {
            let b = frame_bytes(&imu_msg(0.5), v);
            match parse_frame(&b) {
                FrameParse::Frame(f, n) => {
                    assert_eq!(n, b.len());
                    assert!(matches!(f.message, MavMessage::HIGHRES_IMU(_)));
                }
                other => panic!("{other:?}"),
            }
            let mut bad = b.clone();
            let k = bad.len() - 4;
            bad[k] ^= 0x55;
            assert!(matches!(
                parse_frame(&bad),
                FrameParse::Skip(_, SkipReason::BadCrc)
            ));
            assert!(matches!(
                parse_frame(&b[..b.len() - 1]),
                FrameParse::Incomplete
            ));
        }
    }

    #[test]
    fn stream_decoder_resyncs_over_garbage() {
        let mut bytes = vec![0x00, 0x13, 0xFD, 0x77];
        bytes.extend(frame_bytes(&imu_msg(1.0), MavlinkVersion::V2));
        bytes.extend([1, 2, 3]);
        bytes.extend(frame_bytes(&imu_msg(2.0), MavlinkVersion::V1));
        let mut d = FrameDecoder::new();
        let mut frames = d.push(&bytes[..10]);
        frames.extend(d.push(&bytes[10..]));
        assert_eq!(frames.len(), 2);
    }

    #[test]
    fn tlog_with_damage_is_decoded_and_counted() {
        let mut log = Vec::new();
        for i in 0..10u64 {
            log.extend((1_700_000_000_000_000u64 + i * 10_000).to_be_bytes());
            log.extend(frame_bytes(&imu_msg(i as f32), MavlinkVersion::V2));
        }
        // Damage record 3's CRC and cut the last record in half.
        let rec = log.len() / 10;
        log[3 * rec + rec - 3] ^= 0xFF;
        log.truncate(log.len() - rec / 2);
        let mut conv = MessageConverter::new(InstanceChoice::Auto, RawImuScale::default());
        let s = decode_tlog(&log, &mut conv);
        assert_eq!(s.len(), 8);
        assert_eq!(conv.stats.skipped.get("bad_crc"), Some(&1));
        assert_eq!(conv.stats.skipped.get("truncated"), Some(&1));
        let m = s[0].mag_ut.unwrap();
        assert!((m[0] - 20.0).abs() < 1e-4 && (m[2] - 40.0).abs() < 1e-4);
        assert_eq!(conv.instance(), Some("highres_imu:0"));
    }

    /// A reader that hands out at most `step` bytes a read, the way a pipe or a gzip stream may.
    pub(crate) struct Trickle<'a> {
        pub bytes: &'a [u8],
        pub step: usize,
    }

    impl std::io::Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(self.step).min(self.bytes.len());
            buf[..n].copy_from_slice(&self.bytes[..n]);
            self.bytes = &self.bytes[n..];
            Ok(n)
        }
    }

    #[test]
    fn a_tlog_streamed_through_a_window_reads_as_the_whole_bytes() {
        // Over a megabyte (several windows) of records with damage of every kind spread
        // through it, so that windows end inside garbage, inside a resynchronisation and inside
        // records; the last record cut.
        let mut log = Vec::new();
        let mut x = 0x9E37_79B9u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        for i in 0..24_000u64 {
            let v = if i % 2 == 0 {
                MavlinkVersion::V2
            } else {
                MavlinkVersion::V1
            };
            let at = log.len();
            log.extend((1_700_000_000_000_000u64 + i * 10_000).to_be_bytes());
            log.extend(frame_bytes(&imu_msg(i as f32), v));
            match next() % 97 {
                0 => log.extend((0..next() % 700).map(|_| next() as u8)),
                1 => log[at + 12] ^= 0x5A,
                2 => log.extend([0xFD, 0x09, 0x00]),
                _ => {}
            }
        }
        log.truncate(log.len() - 20);
        assert!(
            log.len() > 4 * crate::io::window::STREAM_CHUNK_BYTES,
            "{} bytes",
            log.len()
        );
        let mut whole = TlogRecords::new(&log);
        let expected: Vec<(u64, f32)> = whole.by_ref().map(|(t, f)| (t, xacc(&f))).collect();
        for step in [1 << 20, 4093] {
            let mut stream = TlogStream::new(Trickle { bytes: &log, step });
            let got: Vec<(u64, f32)> = stream.by_ref().map(|(t, f)| (t, xacc(&f))).collect();
            assert_eq!(got.len(), expected.len());
            assert!(got == expected, "records differ at step {step}");
            assert_eq!(stream.stats, whole.stats, "step {step}");
            assert_eq!(stream.bytes_read(), log.len());
        }
        assert!(whole.stats.skipped["resync"] > 100, "{:?}", whole.stats);
        assert!(whole.stats.skipped["bad_crc"] > 100, "{:?}", whole.stats);
        assert_eq!(whole.stats.skipped["truncated"], 1);
    }

    /// The x acceleration of a HIGHRES_IMU frame, NaN for another.
    fn xacc(f: &Frame) -> f32 {
        match &f.message {
            MavMessage::HIGHRES_IMU(m) => m.xacc,
            _ => f32::NAN,
        }
    }

    #[test]
    fn csv_any_order_subset_and_empty_cells() {
        let text =
            "mz,t,mx,my,ax,ay,az\n3,0.0,1,2,,,\n6,0.1,4,5,0,0,-9.8\nbad,row\n9,0.2,7,8,0,NaN,1\n";
        let mut st = DecodeStats::default();
        let s = decode_csv(text, &CsvMapping::default(), &mut st).unwrap();
        assert_eq!(s.len(), 3);
        assert_eq!(s[0].mag_ut, Some([1.0, 2.0, 3.0]));
        assert_eq!(s[0].accel_mps2, None);
        assert_eq!(s[1].accel_mps2, Some([0.0, 0.0, -9.8]));
        assert_eq!(s[2].accel_mps2, None);
        assert_eq!(st.skipped.get("bad_row"), Some(&1));
        assert_eq!(st.skipped.get("non_finite"), Some(&1));
    }

    #[test]
    fn csv_without_time_takes_the_rate_given_or_its_preamble_or_says_what_to_give() {
        let body = "mx,my,mz\n1,2,3\n4,5,6\nbad\n7,8,9\n";
        let mut st = DecodeStats::default();
        let e = decode_csv(body, &CsvMapping::default(), &mut st).unwrap_err();
        assert!(e.contains("--rate-hz") && e.contains("rate_hz"), "{e}");
        let with_preamble = format!("Fs,50.00\nInitialization time,60\n{body}");
        let s = decode_csv(&with_preamble, &CsvMapping::default(), &mut st).unwrap();
        let t: Vec<f64> = s.iter().map(|s| s.t_s).collect();
        // The bad row keeps its place in time.
        assert_eq!(t, vec![0.0, 0.02, 0.06]);
        let m = CsvMapping {
            rate_hz: Some(10.0),
            ..Default::default()
        };
        let s = decode_csv(&with_preamble, &m, &mut st).unwrap();
        assert!((s[1].t_s - 0.1).abs() < 1e-12);
        let m = CsvMapping {
            rate_hz: Some(0.0),
            ..Default::default()
        };
        assert!(decode_csv(body, &m, &mut st)
            .unwrap_err()
            .contains("positive"));
    }

    #[test]
    fn csv_user_mapping_with_scales() {
        let text = "time_ms,AccX,AccY,AccZ\n10,0,0,-1\n";
        let mut m = CsvMapping::from_pairs(
            &[
                ("t", "time_ms"),
                ("ax", "AccX"),
                ("ay", "AccY"),
                ("az", "AccZ"),
            ],
            &[
                ("t", 0.001),
                ("ax", 9.80665),
                ("ay", 9.80665),
                ("az", 9.80665),
            ],
        );
        let mut st = DecodeStats::default();
        let s = decode_csv(text, &m, &mut st).unwrap();
        assert!((s[0].t_s - 0.01).abs() < 1e-12);
        assert_eq!(s[0].accel_mps2, Some([0.0, 0.0, -9.80665]));
        m.columns.insert("mx".into(), "Nope".into());
        assert!(decode_csv(text, &m, &mut st).unwrap_err().contains("Nope"));
    }
}
