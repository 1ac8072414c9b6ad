//! Everything the daemon sends to a MAVLink link or a JSON-lines consumer, as pure functions and small
//! state machines (no sockets, no tokio): the caller moves the bytes.
//!
//! * [`MavEncoder`]: one complete MAVLink frame per message, with its own sequence counter.
//! * Being a MAVLink component: [`heartbeat`], and [`OwnIds`] to tell our own frames echoed back.
//! * The ground station's calibration commands (ArduPilot's DO_START/ACCEPT/CANCEL_MAG_CAL), read:
//!   [`MagCalStart`], [`mask_param`], [`mask_selects`]; answered: [`command_ack`]. What a command
//!   does to a calibration run is decided above, by the live service (`app::daemon`'s `MagCalRun`).
//! * Calibration progress and result in ArduPilot's messages: [`mag_cal_progress`]
//!   (MAG_CAL_PROGRESS, 191; its completion mask of sections from [`crate::calib::sections`]) and
//!   [`mag_cal_report`] (MAG_CAL_REPORT, 192).
//! * Heading and vectors: [`named_float`], [`debug_vect`], [`statustext`], [`attitude`].
//! * Fused attitude from a quaternion (body FRD -> NED): [`attitude_quaternion`]
//!   (ATTITUDE_QUATERNION, 31) and [`attitude_from_quaternion`] (ATTITUDE, 30).
//! * Reading back ArduPilot's compass parameters ([`param_request_reads`]; undone by
//!   [`crate::io::ardupilot::Telemetry`]).
//! * Writing parameters with read-back verification: [`ParamWriter`].
//! * JSON lines for other consumers: [`LiveEvent`], [`json_line`] (schema [`JSON_SCHEMA`]).
//!
//! Units: our magnetometer numbers are in uT; MAVLink's MAG_CAL_* and ArduPilot's COMPASS_* are in
//! mGauss (1 uT = 10 mGauss).
//!
//! # MAG_CAL_STATUS values 8-10
//! MAVLink added MAG_CAL_FAILED_OFFSETS (8), MAG_CAL_FAILED_DIAG_SCALING (9) and
//! MAG_CAL_FAILED_RESIDUALS_HIGH (10) in 2026. The `mavlink` 0.21 bindings this crate builds with
//! already carry them in `MagCalStatus` (checked in the generated dialect), so [`mag_cal_report`]
//! sets them through the enum and [`MavEncoder::encode`] writes them as the plain payload byte
//! (MAG_CAL_REPORT payload offset 42); the tests read that byte back. Should an older binding lack a
//! variant, [`mag_cal_status_code`] still gives the wire value to patch into the frame.
//!
//! # JSON lines: schema `imucald.live/1`
//! One JSON object per line, terminated by `\n`. Every object starts with `"schema": "imucald.live/1"`
//! and `"type"`; the other fields depend on the type. Numbers that are not finite are written as
//! `null`. Times `t` are seconds since the start of the input (the sample clock). Frames are the
//! sensor's FRD body axes.
//!
//! | type          | fields |
//! |---------------|--------|
//! | `attitude`    | `t` (s), `q` ([w,x,y,z], body FRD -> NED, from the gyro+accel+mag orientation filter), `roll_deg`, `pitch_deg`, `heading_deg` (0..360, ZYX angles of `q`), `true_heading` (as for `heading`), `gyro_bias_rad_s` ([x,y,z] body: the stored gyro calibration plus the filter's residual estimate), `mag_disturbed` (bool: the field's norm or dip is off its reference, so the heading runs on the gyro) |
//! | `heading`     | `t` (s), `roll_deg`, `pitch_deg`, `heading_deg` (0..360, clockwise from north), `true_heading` (bool: true when the declination was added, i.e. from true north; false: magnetic north) |
//! | `calibrated`  | `t` (s), `accel_mps2` ([x,y,z] m/s^2 or null), `gyro_rad_s` ([x,y,z] rad/s or null), `mag_ut` ([x,y,z] uT or null): the latest sample after calibration |
//! | `progress`    | `sensor` ("mag"), `instance` (the compass: MAG_CAL_* `compass_id`; a stream with several compasses has a progress line per compass), `completion_pct` (0..100), `filled_regions` (sphere regions holding a sample, of 100), `regions` (which: 25 hex digits, region i is bit i%4 of digit i/4, regions as in `coverage`), `direction` ([x,y,z] of the latest point about the centre, body axes; zero while no centre is known) |
//! | `calibration` | `sensor` ("mag" or "accel"), `instance` (the IMU instance's compass id, as for `progress`), `status` ("ok" or "failed"), `failure` (null or a reason: not_enough_samples, not_identifiable, coverage, radius, offsets, diagonal_scaling, residuals, did_not_converge), `model` (sphere, diag6, sym9, full12), `offset` ([x,y,z] raw units), `offset_sigma` (its 1-sigma), `matrix` (3x3 row-major; calibrated = matrix * (raw - offset)), `rms_residual` (calibrated units), `method` (magnetometer: "vector" when learnt from the vehicle's attitude, "sphere"; absent otherwise) |
//! | `status`      | `level` (emergency, alert, critical, error, warning, notice, info, debug), `text` |
//!
//! Example lines:
//! ```text
//! {"schema":"imucald.live/1","type":"heading","t":12.5,"roll_deg":1.2,"pitch_deg":-0.4,"heading_deg":273.9,"true_heading":true}
//! {"schema":"imucald.live/1","type":"attitude","t":12.5,"q":[0.259,0.0,0.0,0.966],"roll_deg":0.0,"pitch_deg":0.0,"heading_deg":150.0,"true_heading":false,"gyro_bias_rad_s":[0.001,0.0,-0.002],"mag_disturbed":false}
//! {"schema":"imucald.live/1","type":"progress","sensor":"mag","instance":0,"completion_pct":45.0,"filled_regions":45}
//! {"schema":"imucald.live/1","type":"status","level":"info","text":"mag calibrated"}
//! ```

use crate::calib::ardupilot;
use crate::calib::fit::FitFailure;
use crate::calib::model::CalModel;
use crate::calib::outcome::{CalStatus, SensorCalibration};
use crate::types::Vec3;
use mavlink::dialects::ardupilotmega::{
    MagCalStatus, MavAutopilot, MavCmd, MavMessage, MavModeFlag, MavParamType, MavResult,
    MavSeverity, MavState, MavType, ATTITUDE_DATA, ATTITUDE_QUATERNION_DATA, COMMAND_ACK_DATA,
    COMMAND_LONG_DATA, DEBUG_VECT_DATA, HEARTBEAT_DATA, MAG_CAL_PROGRESS_DATA, MAG_CAL_REPORT_DATA,
    NAMED_VALUE_FLOAT_DATA, PARAM_REQUEST_READ_DATA, PARAM_SET_DATA, PARAM_VALUE_DATA,
    STATUSTEXT_DATA,
};
use mavlink::types::CharArray;
use mavlink::{MavHeader, MavlinkVersion};
use serde::{Deserialize, Serialize};

// ---------------------------------------------------------------------------------------------
// Framing

/// Default component id of the daemon: MAV_COMP_ID_ONBOARD_COMPUTER.
pub const DEFAULT_COMPONENT_ID: u8 = 191;

/// Turns messages into complete MAVLink frames with an incrementing sequence number.
#[derive(Debug, Clone)]
pub struct MavEncoder {
    pub system_id: u8,
    /// 191 (onboard computer) by default.
    pub component_id: u8,
    pub version: MavlinkVersion,
    seq: u8,
}

impl Default for MavEncoder {
    fn default() -> Self {
        MavEncoder::new(1, DEFAULT_COMPONENT_ID)
    }
}

impl MavEncoder {
    /// A MAVLink 2 encoder for the given sender ids.
    pub fn new(system_id: u8, component_id: u8) -> Self {
        MavEncoder {
            system_id,
            component_id,
            version: MavlinkVersion::V2,
            seq: 0,
        }
    }

    /// Sequence number the next frame will carry.
    pub fn seq(&self) -> u8 {
        self.seq
    }

    /// One complete frame (header, payload, CRC) for `msg`; the sequence number then increments
    /// (wrapping at 255). Returns an empty vector only if the bindings refuse the message.
    pub fn encode(&mut self, msg: &MavMessage) -> Vec<u8> {
        let header = MavHeader {
            system_id: self.system_id as u32,
            component_id: self.component_id,
            sequence: self.seq,
        };
        let mut out = Vec::with_capacity(64);
        if mavlink::write_versioned_msg(&mut out, self.version, header, msg).is_err() {
            return Vec::new();
        }
        self.seq = self.seq.wrapping_add(1);
        out
    }
}

/// Our own MAVLink ids. A frame that carries both came from us: a router or a link that loops our
/// output back. It is not a vehicle's, and is never taken as input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct OwnIds {
    pub system_id: u8,
    pub component_id: u8,
}

impl OwnIds {
    /// Whether a frame from `system_id`/`component_id` is our own (both must match: a flight
    /// controller shares our system id on the same vehicle).
    pub(crate) fn is_own(&self, system_id: u8, component_id: u8) -> bool {
        system_id == self.system_id && component_id == self.component_id
    }
}

/// Our HEARTBEAT: an onboard controller with no autopilot of its own, active. Sent at
/// `daemon.heartbeat_rate_hz` (1 Hz) on every MAVLink link, so ground stations and routers
/// (MAVProxy, mavlink-router, QGroundControl) list the component and route messages to it.
pub fn heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// Copy `s` into a fixed MAVLink char array, cut at a UTF-8 character boundary so that at most `N`
/// bytes are used (no NUL terminator when it fills the array, as MAVLink allows).
fn char_array<const N: usize>(s: &str) -> CharArray<N> {
    CharArray::from(&s[..utf8_prefix_len(s, N)])
}

/// Length in bytes of the longest prefix of `s` that is at most `max` bytes and ends on a char boundary.
fn utf8_prefix_len(s: &str, max: usize) -> usize {
    if s.len() <= max {
        return s.len();
    }
    let mut n = max;
    while !s.is_char_boundary(n) {
        n -= 1;
    }
    n
}

/// The text of a MAVLink char array (up to the first NUL; lossy for invalid UTF-8).
fn array_text<const N: usize>(a: &CharArray<N>) -> String {
    let bytes: &[u8; N] = a;
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(N);
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

// ---------------------------------------------------------------------------------------------
// MAG_CAL_PROGRESS

/// `1 << compass_id` (0 for ids of 8 and more, which a MAG_CAL_* `cal_mask` cannot hold).
pub(crate) fn compass_bit(compass_id: u8) -> u8 {
    1u8.checked_shl(compass_id as u32).unwrap_or(0)
}

/// Where a calibration run stands, as MAG_CAL_PROGRESS says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ProgressStatus {
    /// Started with a delay that has not passed (ArduPilot's WAITING_TO_START).
    WaitingToStart,
    /// Collecting (RUNNING_STEP_ONE, or RUNNING_STEP_TWO once the sphere is covered).
    Running,
}

/// MAG_CAL_PROGRESS: `cal_status` WAITING_TO_START while the run waits out its start delay (with
/// `completion_pct` 0 and an empty mask, as ArduPilot's calibrator reports it then); collecting,
/// RUNNING_STEP_ONE below 100 % and RUNNING_STEP_TWO at 100 % (`completion_pct` is capped at
/// 100); `attempt` the run's attempt (1, one more per retry after a failure); `cal_mask` the
/// compasses of the run (ArduPilot's: every compass whose calibrator is not idle);
/// `direction_*` 0, as ArduPilot sends them.
pub(crate) fn mag_cal_progress(
    compass_id: u8,
    cal_mask: u8,
    completion_pct: u8,
    mask: [u8; 10],
    attempt: u8,
    status: ProgressStatus,
) -> MavMessage {
    let waiting = status == ProgressStatus::WaitingToStart;
    let pct = if waiting { 0 } else { completion_pct.min(100) };
    MavMessage::MAG_CAL_PROGRESS(MAG_CAL_PROGRESS_DATA {
        compass_id,
        cal_mask,
        cal_status: if waiting {
            MagCalStatus::MAG_CAL_WAITING_TO_START
        } else if pct < 100 {
            MagCalStatus::MAG_CAL_RUNNING_STEP_ONE
        } else {
            MagCalStatus::MAG_CAL_RUNNING_STEP_TWO
        },
        attempt,
        completion_pct: pct,
        completion_mask: if waiting { [0; 10] } else { mask },
        direction_x: 0.0,
        direction_y: 0.0,
        direction_z: 0.0,
    })
}

// ---------------------------------------------------------------------------------------------
// Ground-station magnetometer calibration commands (MAV_CMD_DO_START/ACCEPT/CANCEL_MAG_CAL)

/// MAV_CMD_DO_START_MAG_CAL's parameters, as ArduPilot reads them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MagCalStart {
    /// p1: compasses to calibrate (bit i: compass i; 0: all).
    pub mask: u8,
    /// p2: after a failed fit, start again from zero coverage.
    pub retry: bool,
    /// p3: install and write a passing result at once; otherwise hold it for DO_ACCEPT_MAG_CAL.
    pub autosave: bool,
    /// p4: wait this long before collecting, s.
    pub delay_s: f64,
    /// p5: reboot after saving (taken, but there is nothing to reboot: the service installs live).
    pub autoreboot: bool,
}

impl MagCalStart {
    /// The parameters of a DO_START_MAG_CAL command (`delay_s` clamped to 0..3600 s, 0 when not
    /// finite).
    pub(crate) fn from_command(c: &COMMAND_LONG_DATA) -> MagCalStart {
        MagCalStart {
            mask: mask_param(c.param1),
            retry: c.param2 != 0.0,
            autosave: c.param3 != 0.0,
            delay_s: if c.param4.is_finite() {
                f64::from(c.param4).clamp(0.0, 3600.0)
            } else {
                0.0
            },
            autoreboot: c.param5 != 0.0,
        }
    }
}

/// A compass mask sent as a float parameter (0..255; anything else reads as 0, all compasses).
pub(crate) fn mask_param(p: f32) -> u8 {
    if p.is_finite() && (0.0..=255.0).contains(&p) {
        p as u8
    } else {
        0
    }
}

/// Whether a compass mask selects compass `compass_id`: 0 means all.
pub(crate) fn mask_selects(mask: u8, compass_id: u8) -> bool {
    mask == 0 || (compass_id < 8 && mask & (1 << compass_id) != 0)
}

/// COMMAND_ACK for `command` to its sender.
pub(crate) fn command_ack(
    command: MavCmd,
    result: MavResult,
    target_system: u8,
    target_component: u8,
) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        target_system,
        target_component,
        ..Default::default()
    })
}

// ---------------------------------------------------------------------------------------------
// MAG_CAL_REPORT

/// Wire value of MAG_CAL_STATUS for a calibration result: 4 (MAG_CAL_SUCCESS) when the status is
/// "ok"; for a failure, by reason: orientation 6 (MAG_CAL_FAILED_ORIENTATION, ArduPilot's
/// BAD_ORIENTATION), radius 7 (MAG_CAL_FAILED_RADIUS, ArduPilot's BAD_RADIUS), offsets 8
/// (MAG_CAL_FAILED_OFFSETS), diagonal_scaling 9 (MAG_CAL_FAILED_DIAG_SCALING), residuals 10
/// (MAG_CAL_FAILED_RESIDUALS_HIGH), anything else 5 (MAG_CAL_FAILED).
pub(crate) fn mag_cal_status_code(cal: &SensorCalibration) -> u8 {
    if cal.status == CalStatus::Ok {
        return 4;
    }
    match cal.failure {
        Some(FitFailure::Orientation) => 6,
        Some(FitFailure::Radius) => 7,
        Some(FitFailure::Offsets) => 8,
        Some(FitFailure::DiagonalScaling) => 9,
        Some(FitFailure::Residuals) => 10,
        _ => 5,
    }
}

fn mag_cal_status_enum(code: u8) -> MagCalStatus {
    match code {
        4 => MagCalStatus::MAG_CAL_SUCCESS,
        6 => MagCalStatus::MAG_CAL_FAILED_ORIENTATION,
        7 => MagCalStatus::MAG_CAL_FAILED_RADIUS,
        8 => MagCalStatus::MAG_CAL_FAILED_OFFSETS,
        9 => MagCalStatus::MAG_CAL_FAILED_DIAG_SCALING,
        10 => MagCalStatus::MAG_CAL_FAILED_RESIDUALS_HIGH,
        _ => MagCalStatus::MAG_CAL_FAILED,
    }
}

/// MAG_CAL_REPORT for a magnetometer calibration in uT, with `autosaved` = 0.
/// See [`mag_cal_report_autosaved`].
pub(crate) fn mag_cal_report(compass_id: u8, cal_mask: u8, cal: &SensorCalibration) -> MavMessage {
    mag_cal_report_autosaved(compass_id, cal_mask, cal, false)
}

/// MAG_CAL_REPORT in ArduPilot's conventions: `fitness` the RMS residual in mGauss; `ofs_*`,
/// `diag_*` and `offdiag_*` as COMPASS_OFS/DIA/ODI ([`ardupilot::Correction::from_model`]: the
/// offset negated in mGauss, the symmetric part of the matrix); `cal_status` from
/// [`mag_cal_status_code`]; `cal_mask` the compasses of the run (as [`mag_cal_progress`]);
/// `scale_factor` 1.0; the orientation fields from the mounting check ([`orientation_fields`]),
/// ROTATION_NONE and confidence 0 without one. The calibration's numbers are taken to be in uT.
pub(crate) fn mag_cal_report_autosaved(
    compass_id: u8,
    cal_mask: u8,
    cal: &SensorCalibration,
    autosaved: bool,
) -> MavMessage {
    let c = ardupilot::Correction::from_model(&cal.offset, &cal.matrix);
    let [ofs_x, ofs_y, ofs_z] = c.ofs_mg.map(|x| x as f32);
    let (dia, odi) = c.dia_odi();
    let [diag_x, diag_y, diag_z] = dia.map(|x| x as f32);
    let [offdiag_x, offdiag_y, offdiag_z] = odi.map(|x| x as f32);
    let (orientation_confidence, old, new) = orientation_fields(cal);
    MavMessage::MAG_CAL_REPORT(MAG_CAL_REPORT_DATA {
        fitness: (cal.rms_residual * ardupilot::MGAUSS_PER_UT) as f32,
        ofs_x,
        ofs_y,
        ofs_z,
        diag_x,
        diag_y,
        diag_z,
        offdiag_x,
        offdiag_y,
        offdiag_z,
        compass_id,
        cal_mask,
        cal_status: mag_cal_status_enum(mag_cal_status_code(cal)),
        autosaved: autosaved as u8,
        scale_factor: 1.0,
        orientation_confidence,
        old_orientation: sensor_orientation(old),
        new_orientation: sensor_orientation(new),
    })
}

/// MAG_CAL_REPORT's orientation fields from the mounting check of the fit
/// ([`crate::calib::mounting`]), in ArduPilot's sense (its `calculate_orientation`):
/// `old_orientation` the configured mounting; `new_orientation` the one the data clearly say when
/// they rule the configured one out (verdict `differs`), else the configured one (ArduPilot keeps
/// it when its check does not pass); `orientation_confidence` the runner-up's score over the
/// best's, squared (ArduPilot's is a ratio of variances, mean squares; ours of RMS angles).
/// (0, ROTATION_NONE, ROTATION_NONE) without a check, or with a custom rotation (which has no
/// MAV_SENSOR_ORIENTATION number; ArduPilot's calibrator does not try those either).
pub(crate) fn orientation_fields(cal: &SensorCalibration) -> (f32, u8, u8) {
    use crate::calib::mounting::{Mounting, Verdict};
    let Some(m) = cal.mounting.as_ref() else {
        return (0.0, 0, 0);
    };
    let number = |mounting: &Mounting| match mounting {
        Mounting::Standard { number, .. } => Some(*number),
        Mounting::Custom { .. } => None,
    };
    let configured = crate::attitude::sensor_rotation(&m.configured)
        .ok()
        .and_then(|r| Mounting::of_matrix(&r))
        .as_ref()
        .and_then(number);
    let Some(old) = configured else {
        return (0.0, 0, 0);
    };
    let new = match &m.verdict {
        Verdict::Differs { set } => number(&set.mounting).unwrap_or(old),
        _ => old,
    };
    let confidence = m
        .margin_ratio
        .filter(|r| r.is_finite())
        .map_or(0.0, |r| (r * r) as f32);
    (confidence, old, new)
}

/// The MAV_SENSOR_ORIENTATION of a rotation number (ROTATION_NONE for one MAVLink lacks).
fn sensor_orientation(number: u8) -> mavlink::dialects::ardupilotmega::MavSensorOrientation {
    use num_traits::FromPrimitive;
    mavlink::dialects::ardupilotmega::MavSensorOrientation::from_u8(number).unwrap_or_default()
}

// ---------------------------------------------------------------------------------------------
// Heading, vectors, text

/// NAMED_VALUE_FLOAT (name cut to 10 bytes), e.g. `named_float("HEADING", t, deg)`.
pub(crate) fn named_float(name: &str, t_boot_ms: u32, value: f32) -> MavMessage {
    MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
        time_boot_ms: t_boot_ms,
        value,
        name: char_array(name),
    })
}

/// DEBUG_VECT (name cut to 10 bytes).
pub(crate) fn debug_vect(name: &str, time_usec: u64, v: [f32; 3]) -> MavMessage {
    MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
        time_usec,
        x: v[0],
        y: v[1],
        z: v[2],
        name: char_array(name),
    })
}

/// The JSON `level` name of a MAVLink severity.
pub(crate) fn severity_name(severity: MavSeverity) -> &'static str {
    match severity {
        MavSeverity::MAV_SEVERITY_EMERGENCY => "emergency",
        MavSeverity::MAV_SEVERITY_ALERT => "alert",
        MavSeverity::MAV_SEVERITY_CRITICAL => "critical",
        MavSeverity::MAV_SEVERITY_ERROR => "error",
        MavSeverity::MAV_SEVERITY_WARNING => "warning",
        MavSeverity::MAV_SEVERITY_NOTICE => "notice",
        MavSeverity::MAV_SEVERITY_INFO => "info",
        MavSeverity::MAV_SEVERITY_DEBUG => "debug",
    }
}

static STATUSTEXT_ID: std::sync::atomic::AtomicU16 = std::sync::atomic::AtomicU16::new(1);

fn next_statustext_id() -> u16 {
    loop {
        let id = STATUSTEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if id != 0 {
            return id;
        }
    }
}

/// STATUSTEXT messages for a text. Up to 50 bytes: one message with `id` 0. Longer: chunks of at
/// most 50 bytes (cut at character boundaries) sharing a non-zero `id` with `chunk_seq` 0, 1, ...;
/// when the last chunk is exactly 50 bytes an empty chunk follows, since a receiver takes a chunk
/// with a NUL in it as the last one. At most 256 chunks (longer text is cut).
pub(crate) fn statustext(sev: MavSeverity, text: &str) -> Vec<MavMessage> {
    const N: usize = 50;
    let msg = |t: &str, id: u16, chunk_seq: u8| {
        MavMessage::STATUSTEXT(STATUSTEXT_DATA {
            severity: sev,
            text: char_array(t),
            id,
            chunk_seq,
        })
    };
    if text.len() <= N {
        return vec![msg(text, 0, 0)];
    }
    let id = next_statustext_id();
    let mut out = Vec::new();
    let mut rest = text;
    let mut last_len = 0;
    while !rest.is_empty() && out.len() < 256 {
        let n = utf8_prefix_len(rest, N).max(rest.chars().next().map_or(0, |c| c.len_utf8()));
        out.push(msg(&rest[..n], id, out.len() as u8));
        last_len = n;
        rest = &rest[n..];
    }
    if last_len == N && out.len() < 256 {
        out.push(msg("", id, out.len() as u8));
    }
    out
}

use crate::attitude::wrap_pi;

/// ATTITUDE from Euler angles in degrees (ZYX, body FRD -> NED): radians, roll and yaw wrapped to
/// (-pi, pi] (a heading of 270 deg is sent as -pi/2). Angular rates are sent as 0.
pub fn attitude(t_boot_ms: u32, roll_deg: f64, pitch_deg: f64, yaw_deg: f64) -> MavMessage {
    MavMessage::ATTITUDE(ATTITUDE_DATA {
        time_boot_ms: t_boot_ms,
        roll: wrap_pi(roll_deg.to_radians()) as f32,
        pitch: pitch_deg.to_radians() as f32,
        yaw: wrap_pi(yaw_deg.to_radians()) as f32,
        ..Default::default()
    })
}

/// A quaternion `[w, x, y, z]` scaled to unit length; `None` when it cannot be (not finite, or zero).
fn unit_wxyz(q: [f64; 4]) -> Option<[f64; 4]> {
    let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    (n.is_finite() && n > 1e-9).then(|| q.map(|c| c / n))
}

/// Roll, pitch, yaw in radians (ZYX) of a body FRD -> NED quaternion `[w, x, y, z]`: roll and yaw in
/// (-pi, pi], pitch in [-pi/2, pi/2]. `None` for a quaternion that is not finite or zero.
pub(crate) fn euler_from_quaternion(q_wxyz: [f64; 4]) -> Option<[f64; 3]> {
    let [w, x, y, z] = unit_wxyz(q_wxyz)?;
    let q = nalgebra::UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(w, x, y, z));
    let [roll, pitch, yaw] = crate::attitude::euler_zyx_deg(&q).map(f64::to_radians);
    Some([wrap_pi(roll), pitch, wrap_pi(yaw)])
}

/// ATTITUDE_QUATERNION: `q1..q4` = w, x, y, z of the body FRD -> NED rotation (normalised; the sign
/// is chosen with w >= 0), body rates in rad/s; `repr_offset_q` is left at zero ("not supported").
/// `None` for a quaternion that is not finite or zero.
pub(crate) fn attitude_quaternion(
    t_boot_ms: u32,
    q_wxyz: [f64; 4],
    rates_rad_s: Vec3,
) -> Option<MavMessage> {
    let q = unit_wxyz(q_wxyz)?;
    let q = if q[0] < 0.0 { q.map(|c| -c) } else { q };
    let r = rates_rad_s.map(|v| if v.is_finite() { v as f32 } else { 0.0 });
    Some(MavMessage::ATTITUDE_QUATERNION(ATTITUDE_QUATERNION_DATA {
        time_boot_ms: t_boot_ms,
        q1: q[0] as f32,
        q2: q[1] as f32,
        q3: q[2] as f32,
        q4: q[3] as f32,
        rollspeed: r[0],
        pitchspeed: r[1],
        yawspeed: r[2],
        ..Default::default()
    }))
}

/// ATTITUDE from a body FRD -> NED quaternion `[w, x, y, z]`: roll, pitch, yaw radians (ZYX; yaw in
/// (-pi, pi]) and body rates in rad/s. `None` for a quaternion that is not finite or zero.
pub(crate) fn attitude_from_quaternion(
    t_boot_ms: u32,
    q_wxyz: [f64; 4],
    rates_rad_s: Vec3,
) -> Option<MavMessage> {
    let [roll, pitch, yaw] = euler_from_quaternion(q_wxyz)?;
    let r = rates_rad_s.map(|v| if v.is_finite() { v as f32 } else { 0.0 });
    Some(MavMessage::ATTITUDE(ATTITUDE_DATA {
        time_boot_ms: t_boot_ms,
        roll: roll as f32,
        pitch: pitch as f32,
        yaw: yaw as f32,
        rollspeed: r[0],
        pitchspeed: r[1],
        yawspeed: r[2],
    }))
}

// ---------------------------------------------------------------------------------------------
// Undoing ArduPilot's correction

/// PARAM_REQUEST_READ by name (`param_index` -1) for what undoing the correction of each compass
/// ArduPilot calibrates needs ([`ardupilot::correction_names`]: ten per compass).
pub(crate) fn param_request_reads(target_system: u8, target_component: u8) -> Vec<MavMessage> {
    (0..ardupilot::COMPASSES)
        .filter_map(ardupilot::correction_names)
        .flatten()
        .map(|name| {
            MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: -1,
                target_system,
                target_component,
                param_id: char_array(&name),
            })
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Serving our own parameters

/// A ground station's request of the parameter protocol addressed to a component.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ParamRequest {
    /// PARAM_REQUEST_LIST: every parameter.
    List,
    /// PARAM_REQUEST_READ by name.
    ReadName(String),
    /// PARAM_REQUEST_READ by index (its name empty or ignored, `param_index` >= 0).
    ReadIndex(u16),
    /// PARAM_SET of a name to a value.
    Set(String, f32),
}

/// The parameter request in `msg` with its target (system, component), or `None` when `msg` is
/// not one.
pub(crate) fn param_request(msg: &MavMessage) -> Option<((u8, u8), ParamRequest)> {
    match msg {
        MavMessage::PARAM_REQUEST_LIST(r) => {
            Some(((r.target_system, r.target_component), ParamRequest::List))
        }
        MavMessage::PARAM_REQUEST_READ(r) => {
            let req = match u16::try_from(r.param_index) {
                Ok(i) => ParamRequest::ReadIndex(i),
                Err(_) => ParamRequest::ReadName(array_text(&r.param_id)),
            };
            Some(((r.target_system, r.target_component), req))
        }
        MavMessage::PARAM_SET(s) => Some((
            (s.target_system, s.target_component),
            ParamRequest::Set(array_text(&s.param_id), s.param_value),
        )),
        _ => None,
    }
}

/// PARAM_VALUE of parameter `index` of `count` (REAL32: every parameter we serve is a float).
pub fn param_value(name: &str, value: f32, index: u16, count: u16) -> MavMessage {
    MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
        param_value: value,
        param_count: count,
        param_index: index,
        param_id: char_array(name),
        param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
    })
}

// ---------------------------------------------------------------------------------------------
// Writing parameters

/// Seconds before an unconfirmed PARAM_SET is sent again.
pub(crate) const PARAM_RETRY_S: f64 = 1.0;
/// Sends per parameter at most.
pub(crate) const PARAM_MAX_TRIES: u8 = 3;

#[derive(Debug, Clone)]
struct ParamEntry {
    name: String,
    value: f64,
    /// Can be sent: a name of at most 16 bytes and a value finite as f32.
    valid: bool,
    tries: u8,
    last_sent: f64,
    confirmed: bool,
    /// Latest echoed value that did not match.
    mismatch: Option<f32>,
}

/// Writes parameters with PARAM_SET (REAL32) and checks each against the PARAM_VALUE the flight
/// controller echoes. Call [`next_messages`](Self::next_messages) periodically (it also advances the
/// writer's clock) and feed every PARAM_VALUE to [`absorb`](Self::absorb).
#[derive(Debug, Clone)]
pub struct ParamWriter {
    entries: Vec<ParamEntry>,
    pub target_system: u8,
    pub target_component: u8,
    now: f64,
}

impl ParamWriter {
    pub fn new(params: Vec<(String, f64)>, target_system: u8, target_component: u8) -> Self {
        let entries = params
            .into_iter()
            .map(|(name, value)| ParamEntry {
                valid: !name.is_empty() && name.len() <= 16 && (value as f32).is_finite(),
                name,
                value,
                tries: 0,
                last_sent: f64::NEG_INFINITY,
                confirmed: false,
                mismatch: None,
            })
            .collect();
        ParamWriter {
            entries,
            target_system,
            target_component,
            now: f64::NEG_INFINITY,
        }
    }

    /// PARAM_SET for every parameter not yet confirmed that is due: never sent, or last sent at least
    /// [`PARAM_RETRY_S`] ago and sent fewer than [`PARAM_MAX_TRIES`] times.
    pub(crate) fn next_messages(&mut self, now_s: f64) -> Vec<MavMessage> {
        self.now = self.now.max(now_s);
        let mut out = Vec::new();
        for e in self.entries.iter_mut() {
            if !e.valid || e.confirmed || e.tries >= PARAM_MAX_TRIES {
                continue;
            }
            if e.tries == 0 || now_s - e.last_sent >= PARAM_RETRY_S {
                e.tries += 1;
                e.last_sent = now_s;
                out.push(MavMessage::PARAM_SET(PARAM_SET_DATA {
                    param_value: e.value as f32,
                    target_system: self.target_system,
                    target_component: self.target_component,
                    param_id: char_array(&e.name),
                    param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
                }));
            }
        }
        out
    }

    /// Take a PARAM_VALUE: one with a name being written and a value within 1e-4 (relative) of the
    /// value sent confirms it; a different value is remembered as a mismatch (the parameter is sent
    /// again while tries remain). Confirmation is final.
    pub(crate) fn absorb(&mut self, msg: &MavMessage) {
        let MavMessage::PARAM_VALUE(p) = msg else {
            return;
        };
        let name = array_text(&p.param_id);
        for e in self.entries.iter_mut().filter(|e| e.name == name) {
            if e.confirmed {
                continue;
            }
            let want = e.value as f32 as f64;
            let got = p.param_value as f64;
            if (got - want).abs() <= 1e-4 * want.abs().max(1e-6) {
                e.confirmed = true;
                e.mismatch = None;
            } else {
                e.mismatch = Some(p.param_value);
            }
        }
    }

    /// Nothing more to do: every parameter is confirmed, cannot be sent, or was sent
    /// [`PARAM_MAX_TRIES`] times with the last try [`PARAM_RETRY_S`] old at the latest
    /// `next_messages` time.
    pub fn done(&self) -> bool {
        self.entries.iter().all(|e| {
            e.confirmed
                || !e.valid
                || (e.tries >= PARAM_MAX_TRIES && self.now - e.last_sent >= PARAM_RETRY_S)
        })
    }

    /// Names not confirmed (never echoed, echoed with a different value, or not sendable). Final once
    /// [`done`](Self::done).
    pub fn failed(&self) -> Vec<String> {
        self.entries
            .iter()
            .filter(|e| !e.confirmed)
            .map(|e| e.name.clone())
            .collect()
    }

    /// Names whose latest echo differed from the value sent, with that value.
    pub fn mismatches(&self) -> Vec<(String, f32)> {
        self.entries
            .iter()
            .filter(|e| !e.confirmed)
            .filter_map(|e| e.mismatch.map(|v| (e.name.clone(), v)))
            .collect()
    }
}

// ---------------------------------------------------------------------------------------------
// JSON lines

/// Schema name carried by every JSON line.
pub(crate) const JSON_SCHEMA: &str = "imucald.live/1";

/// One event of the JSON-lines stream (see the module documentation for the schema).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum LiveEvent {
    /// The fused attitude of the orientation filter (see the module documentation).
    Attitude {
        t: f64,
        /// Body FRD -> NED, `[w, x, y, z]`.
        q: [f64; 4],
        roll_deg: f64,
        pitch_deg: f64,
        heading_deg: f64,
        true_heading: bool,
        gyro_bias_rad_s: Vec3,
        mag_disturbed: bool,
    },
    Heading {
        t: f64,
        roll_deg: f64,
        pitch_deg: f64,
        heading_deg: f64,
        true_heading: bool,
    },
    Calibrated {
        t: f64,
        accel_mps2: Option<Vec3>,
        gyro_rad_s: Option<Vec3>,
        mag_ut: Option<Vec3>,
    },
    Progress {
        sensor: String,
        /// The compass (MAG_CAL_* `compass_id`) of the instance.
        instance: u8,
        completion_pct: f64,
        filled_regions: usize,
        /// The filled regions ([`crate::calib::coverage::regions_hex`]).
        #[serde(default)]
        regions: String,
        /// Direction of the latest point about the centre, body axes (zero while no centre).
        #[serde(default)]
        direction: Vec3,
    },
    Calibration {
        sensor: String,
        /// The IMU instance's compass id (MAG_CAL_* `compass_id`).
        instance: u8,
        status: CalStatus,
        failure: Option<FitFailure>,
        model: CalModel,
        offset: Vec3,
        /// 1-sigma of `offset`.
        #[serde(default)]
        offset_sigma: Vec3,
        matrix: [[f64; 3]; 3],
        rms_residual: f64,
        /// The magnetometer's method ("vector" or "sphere") when one was chosen.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        method: Option<crate::calib::magmethod::MagMethod>,
        /// Whether this fit is now the calibration in use. A fit that passed but is not installed
        /// (on-command mode with no run, a run waiting to be accepted, not better than the one in
        /// use) says false: it is not a calibration of the vehicle.
        #[serde(default)]
        installed: bool,
    },
    Status {
        level: String,
        text: String,
    },
}

impl LiveEvent {
    /// A `calibration` event from a report entry of the instance with compass id `instance`,
    /// `installed` when it is now the calibration in use.
    pub fn calibration(
        sensor: &str,
        instance: u8,
        cal: &SensorCalibration,
        installed: bool,
    ) -> Self {
        LiveEvent::Calibration {
            sensor: sensor.to_string(),
            instance,
            status: cal.status,
            failure: cal.failure,
            model: cal.model,
            offset: cal.offset,
            offset_sigma: cal.offset_sigma,
            matrix: cal.matrix,
            rms_residual: cal.rms_residual,
            method: cal.method.as_ref().map(|m| m.method),
            installed,
        }
    }
}

#[derive(Serialize)]
struct Line<'a> {
    schema: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    vehicle: Option<&'a VehicleTag>,
    #[serde(flatten)]
    event: &'a LiveEvent,
}

/// Which vehicle a JSON line is about, on lines about a vehicle other than the first the live
/// service calibrates: `"vehicle": {"link": "udpin:0.0.0.0:14550", "system_id": 2}`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct VehicleTag {
    /// The link it was heard on (its address as configured).
    pub link: String,
    /// Its MAVLink system id.
    pub system_id: u8,
}

/// One JSON line (terminated by `\n`) for an event: `schema`, then `type`, then the event's fields.
pub fn json_line(ev: &LiveEvent) -> String {
    json_line_for(ev, None)
}

/// [`json_line`] for an event about a vehicle: `schema`, `vehicle` (when given), `type`, fields.
pub(crate) fn json_line_for(ev: &LiveEvent, vehicle: Option<&VehicleTag>) -> String {
    let mut s = serde_json::to_string(&Line {
        schema: JSON_SCHEMA,
        vehicle,
        event: ev,
    })
    .unwrap_or_else(|e| {
        // Not expected for these types; keep the stream well-formed anyway.
        format!(
            "{{\"schema\":\"{JSON_SCHEMA}\",\"type\":\"status\",\"level\":\"error\",\"text\":{}}}",
            serde_json::Value::String(format!("event not serialisable: {e}"))
        )
    });
    s.push('\n');
    s
}

// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::model::{Calibration, ModelKind};
    use crate::io::decode::{parse_frame, Frame, FrameParse};
    use mavlink::dialects::ardupilotmega::PARAM_VALUE_DATA;
    use std::f64::consts::PI;

    fn decode(bytes: &[u8]) -> Frame {
        match parse_frame(bytes) {
            FrameParse::Frame(f, n) => {
                assert_eq!(n, bytes.len());
                f
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn mavout_heartbeat_says_onboard_controller_without_autopilot_with_our_ids() {
        let mut enc = MavEncoder::new(42, 191);
        let f = decode(&enc.encode(&heartbeat()));
        assert_eq!((f.system_id, f.component_id), (42, 191));
        let MavMessage::HEARTBEAT(h) = f.message else {
            panic!("{:?}", f.message)
        };
        assert_eq!(h.mavtype, MavType::MAV_TYPE_ONBOARD_CONTROLLER);
        assert_eq!(h.autopilot, MavAutopilot::MAV_AUTOPILOT_INVALID);
        assert_eq!(h.system_status, MavState::MAV_STATE_ACTIVE);
        assert_eq!(h.mavlink_version, 3);
    }

    #[test]
    fn mavout_start_mag_cal_parameters_as_ardupilot_reads_them() {
        let c = COMMAND_LONG_DATA {
            param1: 1.0,
            param2: 1.0,
            param3: 0.0,
            param4: 2.5,
            param5: 1.0,
            command: MavCmd::MAV_CMD_DO_START_MAG_CAL,
            ..Default::default()
        };
        let o = MagCalStart::from_command(&c);
        assert_eq!(
            o,
            MagCalStart {
                mask: 1,
                retry: true,
                autosave: false,
                delay_s: 2.5,
                autoreboot: true
            }
        );
        let bad = COMMAND_LONG_DATA {
            param1: f32::NAN,
            param4: -3.0,
            ..c
        };
        let o = MagCalStart::from_command(&bad);
        assert_eq!((o.mask, o.delay_s), (0, 0.0));
        assert_eq!(mask_param(300.0), 0);
        assert!(mask_selects(0, 5) && mask_selects(0b100, 2) && !mask_selects(0b100, 1));
        assert!(!mask_selects(0xff, 9));
    }

    #[test]
    fn mavout_own_ids_match_only_both_ids() {
        let own = OwnIds {
            system_id: 1,
            component_id: 191,
        };
        assert!(own.is_own(1, 191));
        // The flight controller of the same vehicle, another computer, a ground station.
        assert!(!own.is_own(1, 1));
        assert!(!own.is_own(2, 191));
        assert!(!own.is_own(255, 190));
    }

    fn sensor_cal(status: CalStatus, failure: Option<FitFailure>) -> SensorCalibration {
        SensorCalibration {
            status,
            failure,
            detail: None,
            model: CalModel::Sym9,
            units: crate::types::CalUnits::Ut,
            offset: [12.0, -30.0, 45.0],
            matrix: [[1.05, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.05, 1.01]],
            radius: 50.0,
            rms_residual: 0.8,
            offset_sigma: [0.1; 3],
            samples_used: 500,
            iterations: 6,
            candidates: vec![],
            outliers_rejected: 0,
            method: None,
            mounting: None,
        }
    }

    fn param_value(name: &str, v: f32) -> MavMessage {
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: v,
            param_id: char_array(name),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
            ..Default::default()
        })
    }

    #[test]
    fn encoder_round_trips_through_parse_frame_and_counts_sequence() {
        for version in [MavlinkVersion::V1, MavlinkVersion::V2] {
            let mut enc = MavEncoder::new(7, DEFAULT_COMPONENT_ID);
            enc.version = version;
            let msg = named_float("HEADING", 1234, 271.5);
            for k in 0..300u32 {
                let b = enc.encode(&msg);
                let seq = if version == MavlinkVersion::V2 {
                    b[4]
                } else {
                    b[2]
                };
                assert_eq!(seq, (k % 256) as u8);
                let f = decode(&b);
                assert_eq!(f.version, version);
                assert_eq!((f.system_id, f.component_id), (7, 191));
                match f.message {
                    MavMessage::NAMED_VALUE_FLOAT(d) => {
                        assert_eq!(array_text(&d.name), "HEADING");
                        assert_eq!(d.value, 271.5);
                        assert_eq!(d.time_boot_ms, 1234);
                    }
                    other => panic!("{other:?}"),
                }
            }
        }
        assert_eq!(MavEncoder::default().component_id, 191);
    }

    #[test]
    fn progress_message_status_and_round_trip() {
        let mask = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10];
        let m = mag_cal_progress(1, 0b11, 42, mask, 2, ProgressStatus::Running);
        let MavMessage::MAG_CAL_PROGRESS(d) = &m else {
            panic!()
        };
        assert_eq!(d.cal_status, MagCalStatus::MAG_CAL_RUNNING_STEP_ONE);
        assert_eq!((d.cal_mask, d.compass_id, d.attempt), (3, 1, 2));
        let MavMessage::MAG_CAL_PROGRESS(d) =
            mag_cal_progress(0, 1, 120, mask, 1, ProgressStatus::Running)
        else {
            panic!()
        };
        assert_eq!(d.cal_status, MagCalStatus::MAG_CAL_RUNNING_STEP_TWO);
        assert_eq!(d.completion_pct, 100);
        // Waiting out the start delay: WAITING_TO_START at 0 % with nothing filled, as ArduPilot.
        let MavMessage::MAG_CAL_PROGRESS(d) =
            mag_cal_progress(0, 1, 37, mask, 1, ProgressStatus::WaitingToStart)
        else {
            panic!()
        };
        assert_eq!(d.cal_status, MagCalStatus::MAG_CAL_WAITING_TO_START);
        assert_eq!((d.completion_pct, d.completion_mask), (0, [0; 10]));
        let f = decode(&MavEncoder::default().encode(&m));
        match f.message {
            MavMessage::MAG_CAL_PROGRESS(r) => {
                assert_eq!(r.completion_mask, mask);
                assert_eq!(r.completion_pct, 42);
                assert_eq!(
                    (r.direction_x, r.direction_y, r.direction_z),
                    (0.0, 0.0, 0.0)
                );
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn report_in_ardupilot_units_and_signs() {
        let cal = sensor_cal(CalStatus::Ok, None);
        let MavMessage::MAG_CAL_REPORT(d) = mag_cal_report(0, 1, &cal) else {
            panic!()
        };
        assert_eq!(d.cal_status, MagCalStatus::MAG_CAL_SUCCESS);
        assert!((d.fitness - 8.0).abs() < 1e-5);
        assert_eq!([d.ofs_x, d.ofs_y, d.ofs_z], [-120.0, 300.0, -450.0]);
        assert_eq!([d.diag_x, d.diag_y, d.diag_z], [1.05, 0.97, 1.01]);
        // Symmetric part of the matrix: (0.03 + 0.05) / 2 for ODI_Z.
        assert!((d.offdiag_x - 0.02).abs() < 1e-7);
        assert!((d.offdiag_y + 0.01).abs() < 1e-7);
        assert!((d.offdiag_z - 0.04).abs() < 1e-7);
        assert_eq!((d.cal_mask, d.autosaved, d.scale_factor), (1, 0, 1.0));
        let MavMessage::MAG_CAL_REPORT(d) = mag_cal_report_autosaved(2, 4, &cal, true) else {
            panic!()
        };
        assert_eq!((d.cal_mask, d.autosaved, d.compass_id), (4, 1, 2));

        // ArduPilot's correct_field with these numbers equals our calibration (symmetric part).
        let raw = [40.0, 5.0, -20.0];
        let m = [
            raw[0] * 10.0 + d.ofs_x as f64,
            raw[1] * 10.0 + d.ofs_y as f64,
            raw[2] * 10.0 + d.ofs_z as f64,
        ];
        let s = [
            [d.diag_x, d.offdiag_x, d.offdiag_y],
            [d.offdiag_x, d.diag_y, d.offdiag_z],
            [d.offdiag_y, d.offdiag_z, d.diag_z],
        ]
        .map(|r| r.map(|x| x as f64));
        let mut sym = cal.matrix;
        sym[1][2] = 0.04;
        sym[2][1] = 0.04;
        let ours = Calibration {
            model: ModelKind::Sym9,
            offset: cal.offset,
            matrix: sym,
        }
        .apply(&raw);
        for i in 0..3 {
            let corrected: f64 = s[i].iter().zip(&m).map(|(a, b)| a * b).sum();
            assert!((corrected - ours[i] * 10.0).abs() < 1e-3);
        }
    }

    #[test]
    fn report_failure_codes_reach_the_wire_including_8_to_10() {
        for (failure, code) in [
            (Some(FitFailure::Orientation), 6u8),
            (Some(FitFailure::Radius), 7),
            (Some(FitFailure::Offsets), 8),
            (Some(FitFailure::DiagonalScaling), 9),
            (Some(FitFailure::Residuals), 10),
            (Some(FitFailure::Coverage), 5),
            (Some(FitFailure::DidNotConverge), 5),
            (None, 5),
        ] {
            let cal = sensor_cal(CalStatus::Failed, failure);
            assert_eq!(mag_cal_status_code(&cal), code);
            let bytes = MavEncoder::default().encode(&mag_cal_report(0, 1, &cal));
            // MAVLink 2 header is 10 bytes; cal_status is payload byte 42 (after 10 floats, id, mask).
            assert_eq!(bytes[10 + 42], code, "{failure:?}");
            match decode(&bytes).message {
                MavMessage::MAG_CAL_REPORT(r) => {
                    assert_eq!(r.cal_status as u8, code);
                    assert_eq!(r.scale_factor, 1.0);
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(mag_cal_status_code(&sensor_cal(CalStatus::Ok, None)), 4);
    }

    /// A compass the mounting check finds turned 90 deg in yaw, configured as not turned: the
    /// report says BAD_ORIENTATION with the configured and the found rotation and the
    /// confidence; a check that cannot tell keeps the configured one as the new one.
    #[test]
    fn report_orientation_fields_come_from_the_mounting_check() {
        use crate::calib::mounting::{Basis, Mounting, MountingReport, Scored, Verdict};
        let scored = |number: u8, score_deg: f64| {
            let mounting = Mounting::standard(number).unwrap();
            Scored {
                ardupilot_compass_orient: mounting.ardupilot_compass_orient(),
                px4_cal_mag_rot: mounting.px4_cal_mag_rot(),
                mounting,
                score_deg,
            }
        };
        let check = |verdict: Verdict| MountingReport {
            basis: Basis::GravityAngle,
            poses: 12,
            spread_deg: 150.0,
            configured: "ROTATION_NONE".into(),
            configured_score_deg: 20.0,
            best: scored(2, 1.0),
            runner_up: Some(scored(0, 3.0)),
            margin_ratio: Some(3.0),
            custom: None,
            field_to_up_deg: 150.0,
            expected_field_to_up_deg: None,
            verdict,
        };
        let mut cal = sensor_cal(CalStatus::Failed, Some(FitFailure::Orientation));
        cal.mounting = Some(check(Verdict::Differs {
            set: scored(2, 1.0),
        }));
        let MavMessage::MAG_CAL_REPORT(r) = mag_cal_report(0, 1, &cal) else {
            panic!()
        };
        assert_eq!(r.cal_status, MagCalStatus::MAG_CAL_FAILED_ORIENTATION);
        assert_eq!(r.old_orientation as u32, 0);
        // MAV_SENSOR_ROTATION_YAW_90 is 2.
        assert_eq!(r.new_orientation as u32, 2);
        assert_eq!(r.orientation_confidence, 9.0);
        cal.mounting = Some(check(Verdict::Mismatch {
            candidates: vec![scored(2, 1.0), scored(0, 3.0)],
        }));
        assert_eq!(orientation_fields(&cal), (9.0, 0, 0));
        cal.mounting = None;
        assert_eq!(orientation_fields(&cal), (0.0, 0, 0));
    }

    #[test]
    fn names_are_cut_to_ten_bytes() {
        let MavMessage::NAMED_VALUE_FLOAT(d) = named_float("HEADING_TRUE_X", 1, 2.0) else {
            panic!()
        };
        assert_eq!(array_text(&d.name), "HEADING_TR");
        let MavMessage::DEBUG_VECT(d) = debug_vect("MAG_UT", 99, [1.0, 2.0, 3.0]) else {
            panic!()
        };
        assert_eq!(array_text(&d.name), "MAG_UT");
        assert_eq!((d.time_usec, d.x, d.y, d.z), (99, 1.0, 2.0, 3.0));
        // A multi-byte character is not split.
        let MavMessage::DEBUG_VECT(d) = debug_vect("ABCDEFGHIé", 0, [0.0; 3]) else {
            panic!()
        };
        assert_eq!(array_text(&d.name), "ABCDEFGHI");
        let f = decode(&MavEncoder::default().encode(&debug_vect("ACC_MPS2", 5, [0.5, 0.0, -9.8])));
        assert!(
            matches!(f.message, MavMessage::DEBUG_VECT(v) if v.z == -9.8 && array_text(&v.name) == "ACC_MPS2")
        );
    }

    #[test]
    fn statustext_chunks_long_text() {
        let short = statustext(MavSeverity::MAV_SEVERITY_INFO, "mag calibrated");
        assert_eq!(short.len(), 1);
        let MavMessage::STATUSTEXT(d) = &short[0] else {
            panic!()
        };
        assert_eq!(
            (d.id, d.chunk_seq, d.severity),
            (0, 0, MavSeverity::MAV_SEVERITY_INFO)
        );
        assert_eq!(array_text(&d.text), "mag calibrated");

        let long: String = (0..120)
            .map(|i| char::from(b'a' + (i % 26) as u8))
            .collect();
        let msgs = statustext(MavSeverity::MAV_SEVERITY_ERROR, &long);
        assert_eq!(msgs.len(), 3);
        let mut joined = String::new();
        let mut ids = vec![];
        for (k, m) in msgs.iter().enumerate() {
            let MavMessage::STATUSTEXT(d) = m else {
                panic!()
            };
            assert_eq!(d.chunk_seq as usize, k);
            assert_eq!(d.severity, MavSeverity::MAV_SEVERITY_ERROR);
            ids.push(d.id);
            joined += &array_text(&d.text);
        }
        assert!(ids[0] != 0 && ids.iter().all(|i| *i == ids[0]));
        assert_eq!(joined, long);

        // Exactly 100 bytes: two full chunks and an empty terminating one.
        let msgs = statustext(MavSeverity::MAV_SEVERITY_WARNING, &long[..100]);
        assert_eq!(msgs.len(), 3);
        let MavMessage::STATUSTEXT(d) = &msgs[2] else {
            panic!()
        };
        assert_eq!(array_text(&d.text), "");
        // Exactly 50 bytes: a single message.
        assert_eq!(
            statustext(MavSeverity::MAV_SEVERITY_WARNING, &long[..50]).len(),
            1
        );
        // A second long text gets another id.
        let MavMessage::STATUSTEXT(d2) = &statustext(MavSeverity::MAV_SEVERITY_ERROR, &long)[0]
        else {
            panic!()
        };
        assert_ne!(d2.id, ids[0]);
        // Multi-byte characters are kept whole.
        let text = "é".repeat(40);
        let msgs = statustext(MavSeverity::MAV_SEVERITY_INFO, &text);
        let joined: String = msgs
            .iter()
            .map(|m| match m {
                MavMessage::STATUSTEXT(d) => array_text(&d.text),
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(joined, text);
    }

    #[test]
    fn attitude_in_radians_with_yaw_wrapped() {
        let MavMessage::ATTITUDE(a) = attitude(10, 10.0, -5.0, 270.0) else {
            panic!()
        };
        assert!((a.roll - 10f32.to_radians()).abs() < 1e-6);
        assert!((a.pitch + 5f32.to_radians()).abs() < 1e-6);
        assert!((a.yaw + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(a.time_boot_ms, 10);
        for (deg, want) in [
            (180.0, PI),
            (-180.0, PI),
            (0.0, 0.0),
            (359.0, -1f64.to_radians()),
            (540.0, PI),
            (-190.0, 170f64.to_radians()),
        ] {
            let MavMessage::ATTITUDE(a) = attitude(0, 0.0, 0.0, deg) else {
                panic!()
            };
            assert!((a.yaw as f64 - want).abs() < 1e-6, "{deg}: {}", a.yaw);
            let y = wrap_pi(deg.to_radians());
            assert!(y > -PI && y <= PI);
        }
    }

    #[test]
    fn param_request_reads_name_every_compass_parameter() {
        let reqs = param_request_reads(1, 1);
        assert_eq!(reqs.len(), 30);
        let names: Vec<String> = (0..ardupilot::COMPASSES)
            .filter_map(ardupilot::correction_names)
            .flatten()
            .collect();
        assert_eq!(names[0], "COMPASS_OFS_X");
        assert_eq!(names[9], "COMPASS_SCALE");
        assert_eq!(names[10], "COMPASS_OFS2_X");
        assert_eq!(names[18], "COMPASS_ODI2_Z");
        assert_eq!(names[29], "COMPASS_SCALE3");
        for (m, n) in reqs.iter().zip(&names) {
            let MavMessage::PARAM_REQUEST_READ(r) = m else {
                panic!()
            };
            assert_eq!(
                (r.param_index, r.target_system, r.target_component),
                (-1, 1, 1)
            );
            assert_eq!(array_text(&r.param_id), *n);
        }
    }

    fn sets(msgs: &[MavMessage]) -> Vec<(String, f32)> {
        msgs.iter()
            .map(|m| match m {
                MavMessage::PARAM_SET(s) => {
                    assert_eq!(s.param_type, MavParamType::MAV_PARAM_TYPE_REAL32);
                    assert_eq!((s.target_system, s.target_component), (1, 1));
                    (array_text(&s.param_id), s.param_value)
                }
                other => panic!("{other:?}"),
            })
            .collect()
    }

    #[test]
    fn param_writer_confirms_echoes() {
        let cal = Calibration {
            model: ModelKind::Sym9,
            offset: [12.0, -30.0, 45.0],
            matrix: [[1.05, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]],
        };
        let (params, _) = crate::calib::export::ardupilot_mag(&cal, 0);
        let mut w = ParamWriter::new(params.clone(), 1, 1);
        let sent = sets(&w.next_messages(0.0));
        assert_eq!(sent.len(), 9);
        assert_eq!(sent[0], ("COMPASS_OFS_X".to_string(), -120.0));
        assert!(!w.done());
        // Nothing due again before a second has passed.
        assert!(w.next_messages(0.5).is_empty());
        for (n, v) in sent.iter() {
            w.absorb(&param_value(n, *v));
        }
        assert!(w.done());
        assert!(w.failed().is_empty());
        assert!(w.next_messages(5.0).is_empty());
        // The frames survive encoding.
        let mut w = ParamWriter::new(params, 1, 1);
        let mut enc = MavEncoder::default();
        for m in w.next_messages(0.0) {
            assert!(matches!(
                decode(&enc.encode(&m)).message,
                MavMessage::PARAM_SET(_)
            ));
        }
    }

    #[test]
    fn param_writer_retries_then_gives_up() {
        let mut w = ParamWriter::new(
            vec![
                ("COMPASS_OFS_X".into(), -120.0),
                ("COMPASS_OFS_Y".into(), 300.0),
            ],
            1,
            1,
        );
        assert_eq!(w.next_messages(0.0).len(), 2);
        w.absorb(&param_value("COMPASS_OFS_Y", 300.00002)); // within 1e-4 relative
        assert_eq!(
            sets(&w.next_messages(1.0)),
            vec![("COMPASS_OFS_X".to_string(), -120.0)]
        );
        assert!(w.next_messages(1.5).is_empty());
        assert_eq!(w.next_messages(2.0).len(), 1);
        // Three tries: no more sends, and done once the last try has had its second.
        assert!(w.next_messages(2.5).is_empty());
        assert!(!w.done());
        assert!(w.next_messages(3.0).is_empty());
        assert!(w.done());
        assert_eq!(w.failed(), vec!["COMPASS_OFS_X".to_string()]);

        // A late echo after a retry still confirms.
        let mut w = ParamWriter::new(vec![("COMPASS_DIA_X".into(), 1.05)], 1, 1);
        w.next_messages(0.0);
        w.next_messages(1.0);
        w.absorb(&param_value("COMPASS_DIA_X", 1.05));
        assert!(w.done() && w.failed().is_empty());
    }

    #[test]
    fn param_writer_reports_mismatch_and_unsendable() {
        let mut w = ParamWriter::new(
            vec![
                ("COMPASS_ODI_X".into(), 0.02),
                ("COMPASS_ODI_Y".into(), 0.0),
                ("A_NAME_LONGER_THAN_16".into(), 1.0),
                ("COMPASS_DIA_Z".into(), f64::NAN),
            ],
            1,
            1,
        );
        assert_eq!(w.next_messages(0.0).len(), 2);
        w.absorb(&param_value("COMPASS_ODI_X", 0.0201));
        w.absorb(&param_value("COMPASS_ODI_Y", 0.0));
        assert_eq!(w.mismatches(), vec![("COMPASS_ODI_X".to_string(), 0.0201)]);
        let mut t = 1.0;
        while !w.done() {
            for m in w.next_messages(t) {
                // The vehicle keeps storing a different value (e.g. it clamps it).
                if let MavMessage::PARAM_SET(s) = m {
                    w.absorb(&param_value(&array_text(&s.param_id), 0.0201));
                }
            }
            t += 0.25;
            assert!(t < 10.0);
        }
        assert_eq!(
            w.failed(),
            vec![
                "COMPASS_ODI_X".to_string(),
                "A_NAME_LONGER_THAN_16".into(),
                "COMPASS_DIA_Z".into()
            ]
        );
        // A PARAM_VALUE with a matching value but another name does not confirm.
        let mut w = ParamWriter::new(vec![("COMPASS_OFS_Z".into(), 5.0)], 1, 1);
        w.next_messages(0.0);
        w.absorb(&param_value("COMPASS_OFS_X", 5.0));
        assert_eq!(w.failed(), vec!["COMPASS_OFS_Z".to_string()]);
    }

    #[test]
    fn json_lines_carry_schema_and_type_first() {
        let events = [
            LiveEvent::Heading {
                t: 12.5,
                roll_deg: 1.2,
                pitch_deg: -0.4,
                heading_deg: 273.9,
                true_heading: true,
            },
            LiveEvent::Calibrated {
                t: 1.0,
                accel_mps2: Some([0.0, 0.0, -9.8]),
                gyro_rad_s: None,
                mag_ut: Some([20.0, 1.0, 40.0]),
            },
            LiveEvent::Progress {
                sensor: "mag".into(),
                instance: 1,
                completion_pct: 45.0,
                filled_regions: 45,
                regions: crate::calib::coverage::regions_hex(&[true; 45]),
                direction: [0.6, 0.0, 0.8],
            },
            LiveEvent::calibration(
                "mag",
                0,
                &sensor_cal(CalStatus::Failed, Some(FitFailure::Residuals)),
                false,
            ),
            LiveEvent::Status {
                level: severity_name(MavSeverity::MAV_SEVERITY_INFO).into(),
                text: "line\nbreak \"quoted\"".into(),
            },
            LiveEvent::Attitude {
                t: 3.25,
                q: [0.5, -0.5, 0.5, 0.5],
                roll_deg: -90.0,
                pitch_deg: 0.0,
                heading_deg: 90.0,
                true_heading: false,
                gyro_bias_rad_s: [0.001, 0.0, -0.002],
                mag_disturbed: true,
            },
        ];
        let types = [
            "heading",
            "calibrated",
            "progress",
            "calibration",
            "status",
            "attitude",
        ];
        for (ev, ty) in events.iter().zip(types) {
            let line = json_line(ev);
            assert!(line.ends_with('\n'));
            assert_eq!(line.matches('\n').count(), 1, "{line}");
            assert!(
                line.starts_with(&format!(
                    "{{\"schema\":\"imucald.live/1\",\"type\":\"{ty}\","
                )),
                "{line}"
            );
            let v: serde_json::Value = serde_json::from_str(&line).unwrap();
            assert_eq!(v["schema"], JSON_SCHEMA);
            let back: LiveEvent = serde_json::from_str(&line).unwrap();
            assert_eq!(&back, ev);
        }
        let v: serde_json::Value = serde_json::from_str(&json_line(&events[3])).unwrap();
        assert_eq!(v["failure"], "residuals");
        assert_eq!(v["matrix"][2][1], 0.05);
        let v: serde_json::Value = serde_json::from_str(&json_line(&events[1])).unwrap();
        assert!(v["gyro_rad_s"].is_null());
        let nan = LiveEvent::Heading {
            t: 0.0,
            roll_deg: f64::NAN,
            pitch_deg: 0.0,
            heading_deg: 0.0,
            true_heading: false,
        };
        let v: serde_json::Value = serde_json::from_str(&json_line(&nan)).unwrap();
        assert!(v["roll_deg"].is_null());
        let v: serde_json::Value = serde_json::from_str(&json_line(&events[5])).unwrap();
        assert_eq!(v["q"][1], -0.5);
        assert_eq!(v["gyro_bias_rad_s"][2], -0.002);
        assert_eq!(v["mag_disturbed"], true);
    }

    /// Body FRD -> NED quaternion `[w, x, y, z]` of ZYX angles in degrees.
    fn q_of(roll: f64, pitch: f64, yaw: f64) -> [f64; 4] {
        let q = nalgebra::UnitQuaternion::from_euler_angles(
            roll.to_radians(),
            pitch.to_radians(),
            yaw.to_radians(),
        );
        [q.w, q.i, q.j, q.k]
    }

    #[test]
    fn euler_from_quaternion_is_zyx_with_yaw_wrapped() {
        for (r, p, y) in [
            (0.0, 0.0, 0.0),
            (20.0, -10.0, 250.0),
            (-170.0, 45.0, 90.0),
            (5.0, 80.0, -30.0),
            (179.0, -60.0, 181.0),
        ] {
            let e = euler_from_quaternion(q_of(r, p, y)).unwrap();
            let want = [r, p, y].map(|d: f64| wrap_pi(d.to_radians()));
            for k in 0..3 {
                assert!(
                    (e[k] - want[k]).abs() < 1e-9,
                    "{r} {p} {y}: {e:?} vs {want:?}"
                );
            }
            assert!(e[2] > -PI && e[2] <= PI);
            // The same angles as the orientation filter's own conversion.
            let q = q_of(r, p, y);
            let uq = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                q[0], q[1], q[2], q[3],
            ));
            let f = crate::attitude::euler_zyx_deg(&uq);
            assert!((f[0] - e[0].to_degrees()).abs() < 1e-6);
            assert!((f[1] - e[1].to_degrees()).abs() < 1e-6);
            assert!((f[2] - e[2].to_degrees().rem_euclid(360.0)).abs() < 1e-6);
        }
        // Scale does not matter; junk is refused, not turned into NaN angles.
        let q = q_of(10.0, 20.0, 30.0).map(|c| 3.0 * c);
        let e = euler_from_quaternion(q).unwrap();
        assert!((e[2] - 30f64.to_radians()).abs() < 1e-9);
        assert!(euler_from_quaternion([0.0; 4]).is_none());
        assert!(euler_from_quaternion([f64::NAN, 0.0, 0.0, 1.0]).is_none());
        assert!(euler_from_quaternion([f64::INFINITY, 0.0, 0.0, 1.0]).is_none());
    }

    #[test]
    fn attitude_quaternion_and_attitude_from_one_quaternion() {
        let q = q_of(20.0, -10.0, 250.0);
        let rates = [0.1, -0.2, 0.3];
        let MavMessage::ATTITUDE_QUATERNION(a) = attitude_quaternion(1234, q, rates).unwrap()
        else {
            panic!()
        };
        assert_eq!(a.time_boot_ms, 1234);
        let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
        for (got, want) in [a.q1, a.q2, a.q3, a.q4].iter().zip(q) {
            assert!((*got as f64 - sign * want).abs() < 1e-6);
        }
        assert!(a.q1 >= 0.0);
        assert_eq!([a.rollspeed, a.pitchspeed, a.yawspeed], [0.1, -0.2, 0.3]);
        // -q is the same rotation: sent with w >= 0.
        let MavMessage::ATTITUDE_QUATERNION(b) =
            attitude_quaternion(0, q.map(|c| -c), rates).unwrap()
        else {
            panic!()
        };
        assert_eq!([a.q1, a.q2, a.q3, a.q4], [b.q1, b.q2, b.q3, b.q4]);
        let MavMessage::ATTITUDE(e) = attitude_from_quaternion(1234, q, rates).unwrap() else {
            panic!()
        };
        assert!((e.roll - 20f32.to_radians()).abs() < 1e-5);
        assert!((e.pitch + 10f32.to_radians()).abs() < 1e-5);
        assert!((e.yaw + 110f32.to_radians()).abs() < 1e-5, "{}", e.yaw);
        assert_eq!([e.rollspeed, e.pitchspeed, e.yawspeed], [0.1, -0.2, 0.3]);
        // Non-finite rates go out as 0, a broken quaternion not at all.
        let MavMessage::ATTITUDE(e) =
            attitude_from_quaternion(0, q, [f64::NAN, 1.0, f64::INFINITY]).unwrap()
        else {
            panic!()
        };
        assert_eq!([e.rollspeed, e.pitchspeed, e.yawspeed], [0.0, 1.0, 0.0]);
        assert!(attitude_quaternion(0, [f64::NAN; 4], rates).is_none());
        assert!(attitude_from_quaternion(0, [0.0; 4], rates).is_none());
        // Both encode to frames that decode back (ids 31 and 30).
        let mut enc = MavEncoder::new(1, 191);
        for (m, id) in [
            (attitude_quaternion(5, q, rates).unwrap(), 31u32),
            (attitude_from_quaternion(5, q, rates).unwrap(), 30),
        ] {
            let message = decode(&enc.encode(&m)).message;
            assert_eq!(mavlink::Message::message_id(&message), id);
            assert_eq!(message, m);
        }
    }
}
