//! Flight-controller logs: ArduPilot DataFlash (`.bin`, [`dataflash`]) and PX4 ULog (`.ulg`,
//! [`ulog`]) turned into [`Sample`] streams, one per sensor instance, and the onboard calibration
//! their parameters record. Pure: bytes in, samples and reports out.
//!
//! Instances. DataFlash: instance k takes `IMU`k (accelerometer and gyroscope) and `MAG`k
//! (`IMU`, `IMU2`, `IMU3`, `MAG`, `MAG2`, `MAG3`, or newer instanced messages with a field `I`);
//! instance 0 is the primary. PX4: the primary takes `sensor_combined` (accelerometer, gyroscope)
//! with `sensor_combined.magnetometer_ga` (older logs) or `vehicle_magnetometer[0]`; instance
//! 1 + k takes `sensor_accel[k]`, `sensor_gyro[k]`, `sensor_mag[k]` (raw), or, where the log has
//! a `vehicle_magnetometer[j]` (j > 0) of the same device id (PX4 logs `sensor_mag` at 1 Hz by
//! default), that faster corrected stream with its CAL_MAGn undone instead, said so in
//! `onboard.undone` (the raw readings then skipped as `mag_slower_stream`; where that CAL_MAGn
//! cannot be undone the raw readings stay). A vehicle that runs without a compass (PX4's
//! SYS_HAS_MAG 0) logs no `vehicle_magnetometer`: its primary has no magnetometer, and each raw
//! `sensor_mag[k]` is calibrated in its own instance. Within an instance a
//! sample is made per accelerometer reading, carrying the newest gyroscope and magnetometer
//! readings since the last one (as a MAVLink IMU message does); an instance without an
//! accelerometer gives a sample per reading. Each instance has its own [`SourceClock`].
//!
//! Onboard correction undone. ArduPilot logs `MAG` after its correction
//! ([`crate::calib::ardupilot`], the motor term logged as MOfs), undone with
//! COMPASS_OFS/DIA/ODI/SCALE of that compass (the record's own OfsX/Y/Z where the parameter is
//! absent or differs by more than 1 mGauss: an offset changed in flight). PX4's
//! `vehicle_magnetometer` and `sensor_combined.magnetometer_ga` are `R S (raw - OFF)` (gauss) of
//! the compass PX4 selected: the CAL_MAGn whose CAL_MAGn_ID is the record's `device_id` (PX4 1.12
//! and later choose by CAL_MAGn_PRIO and log no CAL_MAG_PRIME), else the prime compass by the
//! parameters (CAL_MAG_PRIME = CAL_MAGn_ID; without it, CAL_MAG0). Undone to the raw field in body
//! axes, R raw = R S^-1 R^T m + R OFF, with R the compass's rotation (CAL_MAGn_ROT, the board's
//! SENS_BOARD_ROT for -1) when it is one of the yaw / roll-180 rotations. A reading whose
//! correction cannot be undone (no CAL_MAGn for its device, CAL_MAGn_ID 0, offsets missing, another
//! rotation) is never taken as raw: it is skipped as `mag_not_undone`, and `onboard.not_undone`
//! names the stream, the count and the reason. Onboard calibrations are reported in imucald's
//! model, calibrated = M (raw - offset) in uT: ArduPilot's as
//! [`crate::calib::ardupilot::Correction::model`]; PX4's is CAL_MAGn_?OFF x 100, M = S (the
//! CAL_MAGn_?COMP power compensation is not undone).
//! `sensor_mag` is raw. Accelerometer and gyroscope streams are used as logged (corrected on
//! board); their onboard calibration is reported, not undone. The onboard temperature
//! calibration's parameters (INS_TCALn_*, TC_*) are handed on as they were when the log began
//! ([`FlightLog::temperature_params`]) for the replay's temperature calibration to undo.
//!
//! Files. This one: the samples assembled per instance ([`FlightLog`], the assembler every
//! conversion feeds). `dataflash_conv` and `ulog_conv`: the records of each format turned into
//! readings; `ardupilot_onboard` and `px4_onboard`: each stack's onboard calibration, reported
//! and undone. The readers of the bytes are `dataflash` and `ulog` (`number`: the numbers both
//! store); `write` writes such logs.

pub mod dataflash;
pub mod number;
pub mod ulog;
pub mod write;

mod ardupilot_onboard;
mod dataflash_conv;
mod px4_onboard;
mod ulog_conv;

pub(crate) use dataflash_conv::decode_dataflash_stream;
pub use dataflash_conv::decode_dataflash_with;
pub(crate) use ulog_conv::decode_ulog_stream;
pub use ulog_conv::decode_ulog_with;

use crate::io::clock::{ClockSettings, SourceClock};
use crate::io::decode::{DecodeStats, InstanceInfo, MAX_INSTANCES};
use crate::io::onboard::{OnboardReport, SensorStream};
use crate::types::{Sample, Sensor, Unit, Units, Vec3};
use nalgebra::Matrix3;
use std::collections::BTreeMap;

/// What a flight-controller log gave besides its samples.
#[derive(Debug, Clone, Default)]
pub struct FlightLog {
    /// Every instance, as [`crate::io::decode::MessageConverter::instances`] lists tlog instances.
    pub instances: Vec<InstanceInfo>,
    /// The index of the primary instance in `instances`.
    pub primary: Option<usize>,
    /// Every sensor stream read.
    pub sensors: Vec<SensorStream>,
    pub onboard: OnboardReport,
    /// The primary's counts and clock, with the reader's skips.
    pub stats: DecodeStats,
    /// Records per message type and instance (`MAG[2]`, `sensor_mag[1]`), as read.
    pub messages: BTreeMap<String, u64>,
    /// The stream the primary's magnetometer readings come from (`MAG`, `vehicle_magnetometer[0]`).
    pub primary_mag_source: Option<String>,
    /// The day of the first GPS fix that gives one (DataFlash `GPS` week and milliseconds, ULog
    /// `vehicle_gps_position.time_utc_usec`).
    pub date: Option<crate::types::LogDate>,
    /// The parameters of the onboard temperature calibration as the log began (ArduPilot
    /// `INS_TCALn_*`, `INS_ACCn_CALTEMP`, `INS_GYRn_CALTEMP`; PX4 `TC_*`), by name. Empty when the
    /// log has none (no parameters, or firmware without a temperature calibration).
    pub temperature_params: BTreeMap<String, f64>,
}

/// Whether a parameter belongs to the onboard temperature calibration ([`FlightLog::temperature_params`]).
pub(crate) fn is_temperature_param(name: &str) -> bool {
    name.starts_with("INS_TCAL")
        || name.starts_with("TC_")
        || (name.starts_with("INS_ACC") || name.starts_with("INS_GYR"))
            && name.ends_with("_CALTEMP")
}

/// The parameters of `params` that [`is_temperature_param`].
fn temperature_params(params: &BTreeMap<String, f64>) -> BTreeMap<String, f64> {
    params
        .iter()
        .filter(|(k, _)| is_temperature_param(k))
        .map(|(k, v)| (k.clone(), *v))
        .collect()
}

/// One instance being assembled.
#[derive(Debug, Clone)]
struct Group {
    /// DataFlash: the instance k; ULog: 0 for the primary, [`PX4_SENSOR_KEY`] + k for sensor k.
    key: u16,
    name: String,
    clock: SourceClock,
    has_accel: bool,
    gyro: Option<Vec3>,
    /// A magnetometer reading waiting for the next accelerometer sample, and its time (us).
    mag: Option<(u64, Vec3)>,
    samples: u64,
}

/// Turns readings into samples per instance.
#[derive(Debug, Clone)]
struct Assembler {
    groups: Vec<Group>,
    primary: Option<usize>,
    throttle: Option<f64>,
    current_a: Option<f64>,
    /// The newest reference attitude (sensor -> ENU) and its time, us.
    attitude: Option<(u64, [f64; 4])>,
    stats: DecodeStats,
    /// (sensor order, instance, source, readings, device id); a handful, searched in place.
    sensors: Vec<(u8, u8, String, u64, Option<u32>)>,
    messages: BTreeMap<String, u64>,
}

/// Group keys of PX4 sensor instances start here (a `multi_id` is a u8).
const PX4_SENSOR_KEY: u16 = 256;

/// An attitude older than this is not attached to a sample, us.
const ATTITUDE_MAX_AGE_US: u64 = 50_000;

fn sensor_order(s: Sensor) -> u8 {
    match s {
        Sensor::Mag => 0,
        Sensor::Accel => 1,
        Sensor::Gyro => 2,
    }
}

fn finite3(v: Vec3) -> Option<Vec3> {
    v.iter().all(|x| x.is_finite()).then_some(v)
}

impl Assembler {
    fn new() -> Self {
        Assembler {
            groups: Vec::new(),
            primary: None,
            throttle: None,
            current_a: None,
            attitude: None,
            stats: DecodeStats::default(),
            sensors: Vec::new(),
            messages: BTreeMap::new(),
        }
    }

    /// Count a reading of a sensor stream.
    fn stream(&mut self, s: Sensor, instance: u8, source: &str, device_id: Option<u32>) {
        let o = sensor_order(s);
        if let Some(e) = self
            .sensors
            .iter_mut()
            .find(|e| e.0 == o && e.1 == instance && e.2 == source)
        {
            e.3 += 1;
            if device_id.is_some() {
                e.4 = device_id;
            }
        } else if self.sensors.len() < 256 {
            self.sensors
                .push((o, instance, source.to_string(), 1, device_id));
        }
    }

    /// The group of instance `key`, made on first use (at most [`MAX_INSTANCES`]).
    fn group(&mut self, key: u16, name: impl FnOnce() -> String) -> Option<usize> {
        if let Some(k) = self.groups.iter().position(|g| g.key == key) {
            return Some(k);
        }
        if self.groups.len() >= MAX_INSTANCES {
            self.stats.skip("too_many_instances");
            return None;
        }
        self.groups.push(Group {
            key,
            name: name(),
            clock: SourceClock::new(ClockSettings::default()),
            has_accel: false,
            gyro: None,
            mag: None,
            samples: 0,
        });
        let k = self.groups.len() - 1;
        if key == 0 {
            self.primary = Some(k);
        }
        Some(k)
    }

    /// An accelerometer reading (with the gyroscope when the same record has it): a sample.
    fn accel(
        &mut self,
        k: usize,
        t_us: u64,
        acc: Vec3,
        gyro: Option<Vec3>,
        temp: Option<f64>,
    ) -> Option<(usize, Sample)> {
        let g = &mut self.groups[k];
        g.has_accel = true;
        let gyro = gyro.or(g.gyro.take());
        let mag = g.mag.take().map(|(_, m)| m);
        self.emit(k, t_us, Some(acc), gyro, mag, temp)
    }

    fn gyro(&mut self, k: usize, t_us: u64, gyro: Vec3) -> Option<(usize, Sample)> {
        let g = &mut self.groups[k];
        if g.has_accel {
            g.gyro = Some(gyro);
            return None;
        }
        self.emit(k, t_us, None, Some(gyro), None, None)
    }

    fn mag(&mut self, k: usize, t_us: u64, mag: Vec3) -> Option<(usize, Sample)> {
        let g = &mut self.groups[k];
        if g.has_accel {
            // Two readings with no accelerometer sample between: the older goes on its own.
            let (t0, m0) = g.mag.replace((t_us, mag))?;
            return self.emit(k, t0, None, None, Some(m0), None);
        }
        self.emit(k, t_us, None, None, Some(mag), None)
    }

    /// Magnetometer readings still waiting at the end of the log, as samples of their own.
    fn flush(&mut self) -> Vec<(usize, Sample)> {
        let mut out = Vec::new();
        for k in 0..self.groups.len() {
            if let Some((t, m)) = self.groups[k].mag.take() {
                out.extend(self.emit(k, t, None, None, Some(m), None));
            }
        }
        out
    }

    fn emit(
        &mut self,
        k: usize,
        t_us: u64,
        acc: Option<Vec3>,
        gyro: Option<Vec3>,
        mag: Option<Vec3>,
        temp: Option<f64>,
    ) -> Option<(usize, Sample)> {
        let primary = Some(k) == self.primary;
        let g = &mut self.groups[k];
        let stamp = g
            .clock
            .stamp(Some(crate::io::clock::us_from_u64(t_us)), None, None);
        g.samples += 1;
        let mut s = Sample {
            t_s: stamp.t_s,
            segment: stamp.segment,
            throttle: self.throttle,
            current_a: self.current_a,
            ..Default::default()
        };
        let mut bad = false;
        let mut take = |v: Option<Vec3>| {
            let v = v?;
            let r = finite3(v);
            bad |= r.is_none();
            r
        };
        s.accel_mps2 = take(acc);
        s.gyro_rad_s = take(gyro);
        s.mag_ut = take(mag);
        s.temp_c = temp.filter(|x| x.is_finite());
        // The vehicle's attitude rides on every instance's samples: every compass can be fitted
        // against it.
        if let Some((ta, q)) = self.attitude {
            if t_us.abs_diff(ta) <= ATTITUDE_MAX_AGE_US {
                s.ref_q = Some(q);
            }
        }
        if primary {
            if bad {
                self.stats.skip("non_finite");
            }
            self.stats.records += 1;
            self.stats.count_sample(&s);
        }
        Some((k, s))
    }

    fn finish(self, onboard: OnboardReport, extra_skips: &BTreeMap<String, u64>) -> FlightLog {
        let mut stats = self.stats;
        // The primary's clock, as its last sample left it (once, not a copy per sample).
        if let Some(g) = self
            .primary
            .map(|k| &self.groups[k])
            .filter(|g| g.samples > 0)
        {
            stats.time = g.clock.stats.clone();
        }
        for (why, n) in extra_skips {
            stats.skip_n(why, *n);
        }
        FlightLog {
            instances: self
                .groups
                .iter()
                .map(|g| InstanceInfo {
                    name: g.name.clone(),
                    compass_id: (if g.key >= PX4_SENSOR_KEY {
                        g.key - PX4_SENSOR_KEY
                    } else {
                        g.key
                    }) as u8,
                    samples: g.samples,
                    units: Units {
                        accel: Unit::Si,
                        gyro: Unit::Si,
                        mag: Unit::Si,
                    },
                    time: g.clock.stats.clone(),
                })
                .collect(),
            primary: self.primary,
            sensors: {
                let mut v = self.sensors;
                v.sort_by(|a, b| (a.0, a.1, &a.2).cmp(&(b.0, b.1, &b.2)));
                v
            }
            .into_iter()
            .map(|(s, instance, source, samples, device_id)| SensorStream {
                sensor: match s {
                    0 => Sensor::Mag,
                    1 => Sensor::Accel,
                    _ => Sensor::Gyro,
                },
                instance,
                source,
                samples,
                device_id,
            })
            .collect(),
            onboard,
            stats,
            messages: self.messages,
            primary_mag_source: None,
            date: None,
            temperature_params: BTreeMap::new(),
        }
    }
}

impl FlightLog {
    /// The primary instance's compass number from the calibration slot its magnetometer's stream
    /// belongs to (PX4: `vehicle_magnetometer` is whichever `sensor_mag[k]` the vehicle selected,
    /// matched to its CAL_MAGn by device id), so that its calibration is judged against, and
    /// exported to, that compass and no other.
    fn primary_compass_from_onboard(&mut self) {
        let (Some(k), Some(src)) = (self.primary, self.primary_mag_source.as_ref()) else {
            return;
        };
        let slot = self
            .onboard
            .mag
            .iter()
            .find(|c| c.sources.contains(src))
            .map(|c| c.instance);
        if let (Some(slot), Some(i)) = (slot, self.instances.get_mut(k)) {
            i.compass_id = slot;
        }
    }
}

/// Roll and pitch (deg) of a reference attitude `ref_q` (sensor -> ENU, as [`Sample::ref_q`]).
pub(crate) fn roll_pitch_of_ref_q(q: [f64; 4]) -> Option<(f64, f64)> {
    let b = crate::attitude::body_ned_of_ref_q(q)?;
    let [roll, pitch, _] = crate::attitude::euler_zyx_deg(&b);
    Some((roll, pitch))
}

fn rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    crate::calib::model::mat_to_rows(m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn attitude_quaternion_is_sensor_to_enu() {
        // Level, heading north: body x (forward) points north = ENU y.
        let q =
            crate::attitude::ned_to_enu(crate::attitude::quat_from_euler(0.0, 0.0, 0.0)).unwrap();
        let v = rotate_q(q, [1.0, 0.0, 0.0]);
        assert!((v[1] - 1.0).abs() < 1e-12, "{v:?}");
        // Heading east (yaw 90): forward = ENU x; body z (down) = ENU -z.
        let q = crate::attitude::ned_to_enu(crate::attitude::quat_from_euler(
            0.0,
            0.0,
            90f64.to_radians(),
        ))
        .unwrap();
        let v = rotate_q(q, [1.0, 0.0, 0.0]);
        assert!((v[0] - 1.0).abs() < 1e-12, "{v:?}");
        let v = rotate_q(q, [0.0, 0.0, 1.0]);
        assert!((v[2] + 1.0).abs() < 1e-12, "{v:?}");
    }

    #[test]
    fn roll_and_pitch_come_back_from_ref_q() {
        let (r, p, y) = (20f64, -35f64, 250f64);
        let q = crate::attitude::ned_to_enu(crate::attitude::quat_from_euler(
            r.to_radians(),
            p.to_radians(),
            y.to_radians(),
        ))
        .unwrap();
        let (r2, p2) = roll_pitch_of_ref_q(q).unwrap();
        assert!((r2 - r).abs() < 1e-9 && (p2 - p).abs() < 1e-9, "{r2} {p2}");
    }

    fn rotate_q(q: [f64; 4], v: Vec3) -> Vec3 {
        let uq = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q[0], q[1], q[2], q[3],
        ));
        let r = uq * Vector3::from(v);
        [r[0], r[1], r[2]]
    }
}
