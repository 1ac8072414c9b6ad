//! Writers of sample logs: CSV (the columns `replay` reads) and MAVLink `.tlog` (the stream a
//! vehicle would send, with the messages that carry its state), for the simulator's output and for
//! tests that need a log as another tool would write it. Atomic, through
//! [`crate::io::publish::write_atomic_with`].

use crate::error::Error;
use crate::types::Sample;
use crate::types::STANDARD_GRAVITY_MPS2;
use serde::{Deserialize, Serialize};

/// The CSV header [`write_csv`] writes.
pub(crate) const CSV_HEADER: &str = "t,ax,ay,az,gx,gy,gz,mx,my,mz,temp,throttle";

fn csv_rows<W: std::io::Write>(w: &mut W, samples: &[Sample]) -> std::io::Result<()> {
    // Battery current and the reference attitude only when some sample carries them.
    let current = samples.iter().any(|s| s.current_a.is_some());
    let reference = samples.iter().any(|s| s.ref_q.is_some());
    let mut header = CSV_HEADER.to_string();
    if current {
        header.push_str(",current");
    }
    if reference {
        header.push_str(",ref_qw,ref_qx,ref_qy,ref_qz");
    }
    let position = samples.iter().any(|s| s.position.is_some());
    if position {
        header.push_str(",lat,lon,alt");
    }
    writeln!(w, "{header}")?;
    let mut line = String::with_capacity(256);
    for s in samples {
        use std::fmt::Write as _;
        line.clear();
        let _ = write!(line, "{}", s.t_s);
        for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut] {
            match v {
                Some(v) => {
                    let _ = write!(line, ",{},{},{}", v[0], v[1], v[2]);
                }
                None => line.push_str(",,,"),
            }
        }
        for x in [s.temp_c, s.throttle] {
            line.push(',');
            if let Some(x) = x {
                let _ = write!(line, "{x}");
            }
        }
        if current {
            line.push(',');
            if let Some(x) = s.current_a {
                let _ = write!(line, "{x}");
            }
        }
        if reference {
            match s.ref_q {
                Some(q) => {
                    let _ = write!(line, ",{},{},{},{}", q[0], q[1], q[2], q[3]);
                }
                None => line.push_str(",,,,"),
            }
        }
        if position {
            match s.position {
                Some(p) => {
                    let _ = write!(line, ",{},{},{}", p.lat_deg, p.lon_deg, p.alt_m);
                }
                None => line.push_str(",,,"),
            }
        }
        line.push('\n');
        w.write_all(line.as_bytes())?;
    }
    Ok(())
}

/// Write samples as CSV (`t,ax,ay,az,gx,gy,gz,mx,my,mz,temp,throttle`, then `current` (A) and
/// `ref_qw,ref_qx,ref_qy,ref_qz` (sensor -> ENU) and `lat,lon,alt` (deg, deg, m) when some sample has them; SI units: s, m/s^2, rad/s,
/// uT, deg C, 0..1; empty cells for absent fields), gzip-compressed if the path ends in `.gz`. Atomic.
pub fn write_csv(path: &std::path::Path, samples: &[Sample]) -> Result<(), Error> {
    let gz = path.to_string_lossy().to_ascii_lowercase().ends_with(".gz");
    crate::io::publish::write_atomic_with(path, |file| {
        let buf = std::io::BufWriter::with_capacity(1 << 16, file);
        if gz {
            let mut enc = flate2::write::GzEncoder::new(buf, flate2::Compression::default());
            csv_rows(&mut enc, samples)?;
            std::io::Write::flush(&mut enc.finish()?)
        } else {
            let mut buf = buf;
            csv_rows(&mut buf, samples)?;
            std::io::Write::flush(&mut buf)
        }
    })
}

/// Which IMU message [`write_tlog`] writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImuMessage {
    /// HIGHRES_IMU (105): m/s^2, rad/s, gauss, degC.
    #[default]
    HighresImu,
    /// SCALED_IMU (26): mG, mrad/s, mgauss, cdegC (i16, rounded and saturated).
    ScaledImu,
}

/// Options of [`write_tlog`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TlogWriteOptions {
    pub message: ImuMessage,
    pub system_id: u8,
    pub component_id: u8,
    /// 2 (default) or 1.
    pub mavlink_version: u8,
    /// Unix time of `t_s = 0` in the record stamps, us ([`TLOG_EPOCH_US`] by default): the day a
    /// replay takes the earth field of.
    pub epoch_us: u64,
}

impl Default for TlogWriteOptions {
    fn default() -> Self {
        TlogWriteOptions {
            message: ImuMessage::HighresImu,
            system_id: 1,
            component_id: 1,
            mavlink_version: 2,
            epoch_us: TLOG_EPOCH_US,
        }
    }
}

/// Unix time of `t_s = 0` in a written tlog, microseconds.
pub const TLOG_EPOCH_US: u64 = crate::types::SIM_EPOCH_US;
/// Time since boot of `t_s = 0` in the messages' own time fields (non-zero, so readers use it).
pub const TLOG_BOOT_OFFSET_US: u64 = 10_000_000;

fn sat_i16(x: f64) -> i16 {
    if x.is_nan() {
        0
    } else {
        x.round().clamp(i16::MIN as f64, i16::MAX as f64) as i16
    }
}

// `default()` + assignments: the extension fields (HIGHRES_IMU.id, SCALED_IMU.temperature) exist only
// with the `mav2-message-extensions` feature.
#[allow(clippy::field_reassign_with_default)]
fn tlog_records<W: std::io::Write>(
    w: &mut W,
    samples: &[Sample],
    opts: &TlogWriteOptions,
) -> std::io::Result<()> {
    use mavlink::dialects::ardupilotmega as apm;
    let version = if opts.mavlink_version == 1 {
        mavlink::MavlinkVersion::V1
    } else {
        mavlink::MavlinkVersion::V2
    };
    let mut seq: u8 = 0;
    let mut put = |w: &mut W, time_us: u64, msg: &apm::MavMessage| -> std::io::Result<()> {
        let header = mavlink::MavHeader {
            system_id: opts.system_id as u32,
            component_id: opts.component_id,
            sequence: seq,
        };
        seq = seq.wrapping_add(1);
        let mut frame = Vec::with_capacity(64);
        mavlink::write_versioned_msg(&mut frame, version, header, msg).map_err(|e| {
            std::io::Error::new(std::io::ErrorKind::InvalidData, format!("mavlink: {e:?}"))
        })?;
        w.write_all(&time_us.to_be_bytes())?;
        w.write_all(&frame)
    };
    let heartbeat = vehicle_heartbeat();
    let mut next_heartbeat_s = f64::NEG_INFINITY;
    let mut state = VehicleStateStream::default();
    for s in samples {
        if !s.t_s.is_finite() {
            continue;
        }
        let t_us = (s.t_s.max(0.0) * 1e6).round() as u64;
        let stamp = opts.epoch_us + t_us;
        if s.t_s >= next_heartbeat_s {
            put(w, stamp, &heartbeat)?;
            next_heartbeat_s = if next_heartbeat_s.is_finite() {
                next_heartbeat_s + 1.0
            } else {
                s.t_s + 1.0
            };
            while next_heartbeat_s <= s.t_s {
                next_heartbeat_s += 1.0;
            }
        }
        if let Some(th) = s.throttle.filter(|x| x.is_finite()) {
            // Before the IMU message so a reader applies it to this sample.
            let hud = apm::VFR_HUD_DATA {
                throttle: (th * 100.0).round().clamp(0.0, 100.0) as u16,
                ..Default::default()
            };
            put(w, stamp, &apm::MavMessage::VFR_HUD(hud))?;
        }
        for msg in state.messages(s, TLOG_BOOT_OFFSET_US + t_us) {
            put(w, stamp, &msg)?;
        }
        let a = s.accel_mps2.unwrap_or([0.0; 3]);
        let gy = s.gyro_rad_s.unwrap_or([0.0; 3]);
        let m = s.mag_ut.unwrap_or([0.0; 3]);
        let msg = match opts.message {
            ImuMessage::HighresImu => highres_imu(s, TLOG_BOOT_OFFSET_US + t_us),
            ImuMessage::ScaledImu => {
                let k_acc = 1000.0 / STANDARD_GRAVITY_MPS2;
                let mut d = apm::SCALED_IMU_DATA::default();
                d.time_boot_ms = ((TLOG_BOOT_OFFSET_US + t_us) / 1000) as u32;
                d.xacc = sat_i16(a[0] * k_acc);
                d.yacc = sat_i16(a[1] * k_acc);
                d.zacc = sat_i16(a[2] * k_acc);
                d.xgyro = sat_i16(gy[0] * 1000.0);
                d.ygyro = sat_i16(gy[1] * 1000.0);
                d.zgyro = sat_i16(gy[2] * 1000.0);
                d.xmag = sat_i16(m[0] * 10.0);
                d.ymag = sat_i16(m[1] * 10.0);
                d.zmag = sat_i16(m[2] * 10.0);
                // 0 means "no temperature" in SCALED_IMU: send 1 cdegC for an exact 0.
                d.temperature = match s.temp_c {
                    Some(c) => match sat_i16(c * 100.0) {
                        0 => 1,
                        v => v,
                    },
                    None => 0,
                };
                apm::MavMessage::SCALED_IMU(d)
            }
        };
        put(w, stamp, &msg)?;
    }
    Ok(())
}

/// The HEARTBEAT of the simulated vehicle: a quadrotor under PX4, standing by.
pub fn vehicle_heartbeat() -> mavlink::dialects::ardupilotmega::MavMessage {
    use mavlink::dialects::ardupilotmega as apm;
    apm::MavMessage::HEARTBEAT(apm::HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: apm::MavType::MAV_TYPE_QUADROTOR,
        autopilot: apm::MavAutopilot::MAV_AUTOPILOT_PX4,
        base_mode: apm::MavModeFlag::empty(),
        system_status: apm::MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    })
}

/// One HIGHRES_IMU message for a sample (m/s^2, rad/s, gauss, degC; `fields_updated` says which
/// vectors are present), stamped `time_usec`.
#[allow(clippy::field_reassign_with_default)]
pub fn highres_imu(s: &Sample, time_usec: u64) -> mavlink::dialects::ardupilotmega::MavMessage {
    use mavlink::dialects::ardupilotmega as apm;
    let a = s.accel_mps2.unwrap_or([0.0; 3]);
    let gy = s.gyro_rad_s.unwrap_or([0.0; 3]);
    let m = s.mag_ut.unwrap_or([0.0; 3]);
    let mut bits: u16 = 0;
    if s.accel_mps2.is_some() {
        bits |= 0x7;
    }
    if s.gyro_rad_s.is_some() {
        bits |= 0x38;
    }
    if s.mag_ut.is_some() {
        bits |= 0x1C0;
    }
    if s.temp_c.is_some() {
        bits |= 0x1000;
    }
    let mut d = apm::HIGHRES_IMU_DATA::default();
    d.time_usec = time_usec;
    d.xacc = a[0] as f32;
    d.yacc = a[1] as f32;
    d.zacc = a[2] as f32;
    d.xgyro = gy[0] as f32;
    d.ygyro = gy[1] as f32;
    d.zgyro = gy[2] as f32;
    d.xmag = (m[0] / 100.0) as f32;
    d.ymag = (m[1] / 100.0) as f32;
    d.zmag = (m[2] / 100.0) as f32;
    d.temperature = s.temp_c.unwrap_or(0.0) as f32;
    d.fields_updated = apm::HighresImuUpdatedFlags::from_bits_truncate(bits);
    apm::MavMessage::HIGHRES_IMU(d)
}

/// What a flight controller streams about itself beside its IMU messages, made from the samples'
/// reference attitude, position and current: ATTITUDE_QUATERNION whenever the attitude changes
/// (at the reference's own rate), GLOBAL_POSITION_INT and BATTERY_STATUS at most every
/// [`VehicleStateStream::PERIOD_S`]. Used by the `.tlog` writer and by tests that play a vehicle.
#[derive(Debug, Clone, Default)]
pub struct VehicleStateStream {
    last_q: Option<[f64; 4]>,
    next_slow_s: f64,
}

impl VehicleStateStream {
    /// Period of the position and battery messages, s (5 Hz).
    pub(crate) const PERIOD_S: f64 = 0.2;

    /// The messages due before sample `s`; `boot_us` is its time since boot.
    pub fn messages(
        &mut self,
        s: &Sample,
        boot_us: u64,
    ) -> Vec<mavlink::dialects::ardupilotmega::MavMessage> {
        use mavlink::dialects::ardupilotmega as apm;
        let mut out = Vec::new();
        let boot_ms = (boot_us / 1000) as u32;
        if let Some(q) = s.ref_q.filter(|q| Some(*q) != self.last_q) {
            self.last_q = Some(q);
            // sensor -> ENU back to body -> NED: the same half-turn.
            if let Some(b) = crate::attitude::ned_to_enu(q) {
                out.push(apm::MavMessage::ATTITUDE_QUATERNION(
                    apm::ATTITUDE_QUATERNION_DATA {
                        time_boot_ms: boot_ms,
                        q1: b[0] as f32,
                        q2: b[1] as f32,
                        q3: b[2] as f32,
                        q4: b[3] as f32,
                        ..Default::default()
                    },
                ));
            }
        }
        if s.t_s >= self.next_slow_s {
            self.next_slow_s = s.t_s + Self::PERIOD_S;
            if let Some(p) = s.position {
                out.push(apm::MavMessage::GLOBAL_POSITION_INT(
                    apm::GLOBAL_POSITION_INT_DATA {
                        time_boot_ms: boot_ms,
                        lat: (p.lat_deg * 1e7).round() as i32,
                        lon: (p.lon_deg * 1e7).round() as i32,
                        alt: (p.alt_m * 1e3).round() as i32,
                        ..Default::default()
                    },
                ));
            }
            if let Some(c) = s.current_a.filter(|c| c.is_finite()) {
                out.push(apm::MavMessage::BATTERY_STATUS(apm::BATTERY_STATUS_DATA {
                    current_battery: (c * 100.0).round().clamp(0.0, 32767.0) as i16,
                    ..Default::default()
                }));
            }
        }
        out
    }
}

/// Write samples as a `.tlog`: per record a big-endian u64 Unix time in microseconds
/// ([`TLOG_EPOCH_US`] + t_s) then one raw MAVLink frame. A HEARTBEAT (quadrotor, PX4) every second,
/// a VFR_HUD before each sample that has a throttle, the vehicle's attitude, position and current
/// where the samples carry them ([`VehicleStateStream`]), and the IMU message of `opts`. Atomic.
pub fn write_tlog(
    path: &std::path::Path,
    samples: &[Sample],
    opts: &TlogWriteOptions,
) -> Result<(), Error> {
    if opts.mavlink_version != 1 && opts.mavlink_version != 2 {
        return Err(Error::Config {
            key: "mavlink_version".into(),
            message: format!("must be 1 or 2, got {}", opts.mavlink_version),
        });
    }
    crate::io::publish::write_atomic_with(path, |file| {
        let mut buf = std::io::BufWriter::with_capacity(1 << 16, file);
        tlog_records(&mut buf, samples, opts)?;
        std::io::Write::flush(&mut buf)
    })
}
