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
//! board); their onboard calibration is reported, not undone.

pub mod dataflash;
pub mod number;
pub mod ulog;
pub mod write;

use crate::io::clock::{ClockSettings, SourceClock};
use crate::io::decode::{DecodeStats, InstanceInfo, MAX_INSTANCES};
use crate::io::onboard::{OnboardCal, OnboardReport, SensorStream};
use crate::types::{Sample, Sensor, Unit, Units, Vec3};
use nalgebra::{Matrix3, Vector3};
use std::collections::{BTreeMap, BTreeSet};

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
}

/// The Unix time of the GPS epoch (1980-01-06), s. GPS time runs ahead of UTC by the leap
/// seconds since (18 in 2017-2026), which never moves a date by more than those seconds.
const GPS_EPOCH_UNIX_S: u64 = 315_964_800;

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

// ---------------------------------------------------------------------------------------------
// ArduPilot

fn ap_onboard(
    params: &BTreeMap<String, f64>,
    sources: &BTreeMap<(u8, u8), String>,
) -> OnboardReport {
    let mut r = OnboardReport {
        stack: "ardupilot".into(),
        ..Default::default()
    };
    for k in 0..crate::calib::ardupilot::COMPASSES {
        let Some(c) = crate::calib::ardupilot::correction(params, k, true) else {
            continue;
        };
        let sources = sources.get(&(0, k)).cloned().into_iter().collect();
        r.mag
            .push(crate::io::ardupilot::onboard_cal(params, k, &c, sources));
    }
    for k in 0..3u8 {
        let s = ["", "2", "3"][k as usize];
        let get3 = |what: &str| -> Option<[f64; 3]> {
            let mut v = [0.0; 3];
            for (i, ax) in ["X", "Y", "Z"].iter().enumerate() {
                v[i] = *params.get(&format!("INS_ACC{s}{what}_{ax}"))?;
            }
            Some(v)
        };
        let Some(offs) = get3("OFFS") else {
            continue;
        };
        let scal = get3("SCAL").unwrap_or([1.0; 3]);
        let mut p = BTreeMap::new();
        for what in ["OFFS", "SCAL"] {
            for ax in ["X", "Y", "Z"] {
                let n = format!("INS_ACC{s}{what}_{ax}");
                if let Some(v) = params.get(&n) {
                    p.insert(n, *v);
                }
            }
        }
        // AP_InertialSensor: accel = scale * (raw - offset), per axis.
        r.accel.push(OnboardCal {
            instance: k,
            device_id: None,
            sources: sources.get(&(1, k)).cloned().into_iter().collect(),
            offset: offs,
            matrix: rows(&Matrix3::from_diagonal(&Vector3::from(scal))),
            units: crate::types::CalUnits::Mps2,
            params: p,
        });
    }
    r
}

/// Undo ArduPilot's correction of one MAG record (mGauss in, uT out). `rec_ofs` is the record's
/// OfsX/Y/Z and `mofs` its MOfsX/Y/Z when logged.
#[cfg(test)]
fn ap_undo(
    params: &BTreeMap<String, f64>,
    k: u8,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    ap_undo_with(
        crate::calib::ardupilot::correction(params, k, true),
        mag_mg,
        rec_ofs,
        mofs,
    )
}

/// [`ap_undo`] with the compass's correction from its parameters, when they give one.
#[cfg(test)]
fn ap_undo_with(
    correction: Option<crate::calib::ardupilot::Correction>,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    ap_undo_cached(correction.map(ApUndo::new).as_ref(), mag_mg, rec_ofs, mofs)
}

/// The inverse of the identity soft iron, for records undone with their own offsets alone.
fn identity_undo() -> &'static ApUndo {
    static ID: std::sync::OnceLock<ApUndo> = std::sync::OnceLock::new();
    ID.get_or_init(|| ApUndo::new(crate::calib::ardupilot::Correction::offsets_only([0.0; 3])))
}

/// Undo a MAG record's correction: the compass's from its parameters (`correction`, with its
/// inverse), else the record's offsets `rec_ofs` with no soft iron; the record's offsets stand in
/// for the parameter's where they differ by more than 1 mGauss (an offset changed in flight).
fn ap_undo_cached(
    correction: Option<&ApUndo>,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    let (undo, mut ofs) = match correction {
        Some(c) => (c, c.correction.ofs_mg),
        // No parameters: the record's offsets, no soft iron.
        None => (identity_undo(), rec_ofs?),
    };
    if let Some(r) = rec_ofs {
        if (0..3).any(|i| (r[i] - ofs[i]).abs() > 1.0) {
            ofs = r;
        }
    }
    undo.undo(&ofs, mag_mg, mofs)
}

/// Which sensor instance a DataFlash message name is (old per-instance names), or `None`.
fn df_name_instance(name: &str, base: &str) -> Option<u8> {
    let rest = name.strip_prefix(base)?;
    match rest {
        "" => Some(0),
        "2" => Some(1),
        "3" => Some(2),
        _ => None,
    }
}

/// Read a DataFlash log, handing each sample of every instance to `emit(instance_index, sample,
/// bytes_read, primary_index)`.
pub fn decode_dataflash_with(
    bytes: &[u8],
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> FlightLog {
    decode_dataflash_from(dataflash::DfReader::new(bytes), emit)
}

/// As [`decode_dataflash_with`], the log read from a stream through a window
/// ([`dataflash::DfReader::from_reader`]); a read error comes back after what came before it.
pub(crate) fn decode_dataflash_stream(
    reader: impl std::io::Read,
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> (FlightLog, Option<std::io::Error>) {
    let mut error = None;
    let rd = dataflash::DfReader::from_reader(reader);
    let log = decode_dataflash_records(rd, emit, &mut error);
    (log, error)
}

fn decode_dataflash_from(
    rd: dataflash::DfReader<'_>,
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> FlightLog {
    decode_dataflash_records(rd, emit, &mut None)
}

/// The records of `rd` through the conversion; a stream's read error into `error`.
fn decode_dataflash_records(
    mut rd: dataflash::DfReader<'_>,
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
    error: &mut Option<std::io::Error>,
) -> FlightLog {
    let mut conv = DfConv::new();
    // Per type id, found once per definition: where the fields used are ([`DfPlan`]) and what
    // the type is to the conversion ([`DfType`]).
    let mut types: Vec<Option<DfPlan>> = vec![None; 256];
    // The FMT payload each type was last defined by: the same again keeps what was found.
    let mut defined_by: Vec<Option<Box<[u8]>>> = vec![None; 256];
    while let Some(rec) = rd.next_record() {
        let plan = types[rec.format.type_id as usize].get_or_insert_with(|| DfPlan::of(rec.format));
        let ty = plan.ty;
        let f = DfFields { plan, rec };
        let k = conv.count(&rec, ty);
        if ty.kind == DfKind::Fmt {
            // A type (re)defined otherwise: its columns are looked up again.
            if let Some(t) = f.get(DfField::Type).filter(|t| (0.0..256.0).contains(t)) {
                let t = t as usize;
                if defined_by[t].as_deref() != Some(rec.payload) {
                    types[t] = None;
                    defined_by[t] = Some(rec.payload.into());
                }
            }
            continue;
        }
        let out = conv.sample(ty.kind, k, &f);
        let read = rd.position();
        if let Some((gi, s)) = out {
            emit(gi, s, read, conv.asm.primary);
        }
    }
    *error = rd.take_error();
    let end = rd.position();
    conv.finish(&rd, end, emit)
}

/// What a DataFlash message type is to the conversion, by its name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DfKind {
    Fmt,
    Parm,
    Imu,
    Mag,
    Att,
    Rcou,
    Ctun,
    /// `BAT` and `CURR`.
    Battery,
    Gps,
    Other,
}

/// A message type's kind, and the instance its name gives (`IMU2`: 1) for a type without an
/// instance column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct DfType {
    kind: DfKind,
    name_instance: u8,
}

impl DfType {
    fn of(name: &str) -> DfType {
        let named = |kind| DfType {
            kind,
            name_instance: 0,
        };
        if let Some(k) = df_name_instance(name, "IMU") {
            return DfType {
                kind: DfKind::Imu,
                name_instance: k,
            };
        }
        if let Some(k) = df_name_instance(name, "MAG") {
            return DfType {
                kind: DfKind::Mag,
                name_instance: k,
            };
        }
        named(match name {
            "FMT" => DfKind::Fmt,
            "PARM" => DfKind::Parm,
            "ATT" => DfKind::Att,
            "RCOU" => DfKind::Rcou,
            "CTUN" => DfKind::Ctun,
            "BAT" | "CURR" => DfKind::Battery,
            "GPS" => DfKind::Gps,
            _ => DfKind::Other,
        })
    }
}

/// What the conversion found of a message type once per definition: what the type is to it, and
/// for each of [`DF_FIELDS`] its column and that column's place and kind in a record (so a record
/// is read by offset, not column by column through the format).
#[derive(Debug, Clone)]
struct DfPlan {
    ty: DfType,
    cols: [Option<usize>; DF_FIELDS.len()],
    at: [Option<dataflash::NumberAt>; DF_FIELDS.len()],
}

impl DfPlan {
    fn of(format: &dataflash::MessageFormat) -> DfPlan {
        let cols = DF_FIELDS.map(|f| format.column(f));
        DfPlan {
            ty: DfType::of(&format.name),
            cols,
            at: cols.map(|c| c.and_then(|k| dataflash::NumberAt::of(&format.columns[k]))),
        }
    }
}

/// One DataFlash record with the plan of its type.
struct DfFields<'a> {
    plan: &'a DfPlan,
    rec: dataflash::Record<'a>,
}

impl DfFields<'_> {
    #[inline]
    fn get(&self, f: DfField) -> Option<f64> {
        self.at(f as usize)
    }

    /// Field `i` of [`DF_FIELDS`] as [`dataflash::Record::value`] reads its column.
    #[inline]
    fn at(&self, i: usize) -> Option<f64> {
        self.rec.number_at(self.plan.at[i]?)
    }

    /// The three consecutive fields from `f` (a vector's axes).
    #[inline]
    fn get3(&self, f: DfField) -> Option<Vec3> {
        let k = f as usize;
        Some([self.at(k)?, self.at(k + 1)?, self.at(k + 2)?])
    }

    /// A text field, without a copy when it is UTF-8 (as parameter names are).
    fn text(&self, f: DfField) -> Option<std::borrow::Cow<'_, str>> {
        self.plan.cols[f as usize].and_then(|k| self.rec.text_at(k))
    }

    /// `TimeUS`, or `TimeMS` * 1000 (older logs), us.
    fn time_us(&self) -> Option<u64> {
        self.get(DfField::TimeUs)
            .or_else(|| self.get(DfField::TimeMs).map(|t| t * 1000.0))
            .filter(|t| *t >= 0.0)
            .map(|t| t as u64)
    }
}

/// The DataFlash conversion between records: the samples being assembled, the parameters, and
/// what the onboard report and the message counts need at the end.
struct DfConv {
    asm: Assembler,
    params: BTreeMap<String, f64>,
    /// Each parameter's first value (the onboard report states the calibration the log began with).
    first_params: BTreeMap<String, f64>,
    /// (sensor 0 mag / 1 accel, instance) -> message name, for the onboard report.
    sources: BTreeMap<(u8, u8), String>,
    /// Magnetometer streams whose correction was undone.
    undone: std::collections::BTreeSet<String>,
    gps: Option<[f64; 3]>,
    date: Option<crate::types::LogDate>,
    /// Records per type id, and per instance for instanced types (by type id, made on its first
    /// record: a count per record is an index, not a look-up).
    type_counts: [u64; 256],
    inst_counts: Vec<Option<Box<[u64; 256]>>>,
    /// (type id, instance of an instanced type) -> its name (`MAG[1]`, `MAG2`).
    names: BTreeMap<(u8, Option<u8>), String>,
    /// Bumped whenever a parameter changes.
    params_version: u64,
    /// Per compass instance, what its parameters give, as of a `params_version`.
    compasses: Vec<Option<CompassParams>>,
    /// Per stream of records ([`DfStreamKey`]), what its records resolve to the same way every
    /// time ([`DfStream`]), found on its first record.
    streams: Vec<Vec<Option<DfStream>>>,
}

/// A stream of records: its type id, whether the type has an instance column, and the instance.
/// Its name ([`df_source`]) is fixed by its first record, so is everything [`DfStream`] keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct DfStreamKey {
    type_id: u8,
    instanced: bool,
    instance: u8,
}

impl DfStreamKey {
    /// The index of its list in [`DfConv::streams`] (by type id and whether instanced).
    fn list(self) -> usize {
        2 * self.type_id as usize + self.instanced as usize
    }
}

/// What the records of one stream resolve to, kept after its first record so the next ones
/// need no look-up by name: the name they are reported under, the entries of its sensor streams
/// in the assembler (by [`sensor_order`]), its instance group, and whether its source is named in
/// `sources` and `undone` already.
#[derive(Debug, Clone)]
struct DfStream {
    src: String,
    sensors: [Option<usize>; 3],
    group: Option<usize>,
    sourced: bool,
    undone: bool,
}

/// A compass's correction and device id from the parameters, as of a version of them.
struct CompassParams {
    version: u64,
    correction: Option<ApUndo>,
    dev_id: Option<u32>,
}

impl CompassParams {
    fn new(params: &BTreeMap<String, f64>, k: u8, version: u64) -> CompassParams {
        CompassParams {
            version,
            correction: crate::calib::ardupilot::correction(params, k, true).map(ApUndo::new),
            dev_id: crate::calib::ardupilot::dev_id(params, k),
        }
    }
}

/// ArduPilot's correction of a compass with the inverse of its soft iron, worked out once per
/// correction rather than once per reading: [`ApUndo::undo`] gives what
/// [`crate::calib::ardupilot::Correction::undo`] gives, to the bit (the same inverse, the same
/// operations in the same order).
#[derive(Debug, Clone, Copy)]
struct ApUndo {
    correction: crate::calib::ardupilot::Correction,
    /// S^-1; `None` when S is singular (nothing can be undone).
    inverse: Option<Matrix3<f64>>,
}

impl ApUndo {
    fn new(correction: crate::calib::ardupilot::Correction) -> ApUndo {
        ApUndo {
            correction,
            inverse: correction.s.try_inverse(),
        }
    }

    /// The raw field (uT) behind a corrected one (mGauss) with the motor term `mot_mg` removed,
    /// the offsets `ofs_mg` in place of the correction's: raw = (S^-1 (mag - MOT)) / scale - OFS.
    /// `None` when S is singular or a value not finite.
    fn undo(&self, ofs_mg: &Vec3, mag_mg: Vec3, mot_mg: Option<Vec3>) -> Option<Vec3> {
        use crate::calib::ardupilot::MGAUSS_PER_UT;
        let inv = self.inverse?;
        let c = Vector3::from(mag_mg) - Vector3::from(mot_mg.unwrap_or([0.0; 3]));
        let u = inv * c / self.correction.scale;
        let raw = [0, 1, 2].map(|i| (u[i] - ofs_mg[i]) / MGAUSS_PER_UT);
        raw.iter().all(|x| x.is_finite()).then_some(raw)
    }
}

impl DfConv {
    fn new() -> Self {
        DfConv {
            asm: Assembler::new(),
            params: BTreeMap::new(),
            first_params: BTreeMap::new(),
            sources: BTreeMap::new(),
            undone: std::collections::BTreeSet::new(),
            gps: None,
            date: None,
            type_counts: [0; 256],
            inst_counts: (0..256).map(|_| None).collect(),
            names: BTreeMap::new(),
            params_version: 0,
            compasses: (0..256).map(|_| None).collect(),
            streams: (0..512).map(|_| Vec::new()).collect(),
        }
    }

    /// Count `rec` (of type `ty`) under its name; its instance.
    fn count(&mut self, rec: &dataflash::Record<'_>, ty: DfType) -> u8 {
        let name = rec.format.name.as_str();
        let id = rec.format.type_id;
        let inst_col = rec.format.instance.is_some();
        let k = if inst_col {
            rec.instance()
        } else {
            ty.name_instance
        };
        if inst_col {
            let n = &mut self.inst_counts[id as usize].get_or_insert_with(|| Box::new([0; 256]))
                [k as usize];
            *n += 1;
            if *n == 1 {
                self.names
                    .entry((id, Some(k)))
                    .or_insert_with(|| format!("{name}[{k}]"));
            }
        } else {
            self.type_counts[id as usize] += 1;
            if self.type_counts[id as usize] == 1 {
                self.names.insert((id, None), name.to_string());
            }
        }
        k
    }

    /// Convert one record (base name `base`, instance `k`): the sample it completes.
    fn sample(&mut self, kind: DfKind, k: u8, f: &DfFields) -> Option<(usize, Sample)> {
        match kind {
            DfKind::Parm => {
                if let (Some(n), Some(v)) = (f.text(DfField::Name), f.get(DfField::Value)) {
                    self.parameter(&n, v);
                }
                None
            }
            DfKind::Imu => self.imu(k, f),
            DfKind::Mag => self.mag(k, f),
            DfKind::Att => {
                if let (Some(t), Some(r), Some(p), Some(y)) = (
                    f.time_us(),
                    f.get(DfField::Roll),
                    f.get(DfField::Pitch),
                    f.get(DfField::Yaw),
                ) {
                    let q = crate::attitude::quat_from_euler(
                        r.to_radians(),
                        p.to_radians(),
                        y.to_radians(),
                    );
                    self.asm.attitude = crate::attitude::ned_to_enu(q).map(|q| (t, q));
                }
                None
            }
            DfKind::Rcou => {
                // Channel 3 is the throttle by ArduPilot's default RCMAP.
                if let Some(pwm) = f.get(DfField::C3).filter(|p| *p >= 900.0 && *p <= 2200.0) {
                    self.asm.throttle = Some(((pwm - 1000.0) / 1000.0).clamp(0.0, 1.5));
                }
                None
            }
            DfKind::Ctun => {
                // Copter logs ThO (0..1); Plane ThrOut (percent).
                if let Some(v) = f.get(DfField::ThO).filter(|v| v.is_finite()) {
                    self.asm.throttle = Some(v.clamp(0.0, 1.5));
                } else if let Some(v) = f.get(DfField::ThrOut).filter(|v| v.is_finite()) {
                    self.asm.throttle = Some((v / 100.0).clamp(0.0, 1.5));
                }
                None
            }
            DfKind::Battery if k == 0 => {
                if let Some(c) = f.get(DfField::Curr).filter(|c| c.is_finite()) {
                    self.asm.current_a = Some(c);
                }
                None
            }
            DfKind::Gps if k == 0 && self.gps.is_none() => {
                self.gps_fix(f);
                None
            }
            _ => None,
        }
    }

    /// A PARM record: the parameter's value (its first kept too), at most 16384 parameters. A
    /// parameter logged again at its value (a log repeats them all at each start) changes nothing.
    fn parameter(&mut self, name: &str, v: f64) {
        if let Some(old) = self.params.get_mut(name) {
            if old.to_bits() != v.to_bits() {
                *old = v;
                self.params_version += 1;
            }
        } else if self.params.len() < 16384 {
            self.first_params.entry(name.to_string()).or_insert(v);
            self.params.insert(name.to_string(), v);
            self.params_version += 1;
        }
    }

    /// Compass `k`'s correction as the parameters give it ([`crate::calib::ardupilot::correction`])
    /// and its device id, worked out again only when a parameter changed.
    fn compass(&mut self, k: u8) -> (Option<ApUndo>, Option<u32>) {
        let version = self.params_version;
        let params = &self.params;
        let c = self.compasses[k as usize]
            .get_or_insert_with(|| CompassParams::new(params, k, version));
        if c.version != version {
            *c = CompassParams::new(params, k, version);
        }
        (c.correction, c.dev_id)
    }

    /// An IMU record: accelerometer and gyroscope of instance `k`.
    fn imu(&mut self, k: u8, f: &DfFields) -> Option<(usize, Sample)> {
        let (Some(t), Some(a), Some(g)) =
            (f.time_us(), f.get3(DfField::AccX), f.get3(DfField::GyrX))
        else {
            self.asm.stats.skip("bad_record");
            return None;
        };
        let key = self.stream_key(&f.rec, k);
        self.count_stream(key, Sensor::Accel, None);
        self.count_stream(key, Sensor::Gyro, None);
        self.name_source(key, 1);
        let gi = self.stream_group(key)?;
        self.asm.accel(gi, t, a, Some(g), f.get(DfField::T))
    }

    /// The stream of record `rec` of instance `k`, its [`DfStream`] made on its first record.
    fn stream_key(&mut self, rec: &dataflash::Record<'_>, k: u8) -> DfStreamKey {
        let key = DfStreamKey {
            type_id: rec.format.type_id,
            instanced: rec.format.instance.is_some(),
            instance: k,
        };
        let list = &mut self.streams[key.list()];
        if list.len() <= k as usize {
            list.resize_with(k as usize + 1, || None);
        }
        if list[k as usize].is_none() {
            list[k as usize] = Some(DfStream {
                src: df_source(&self.names, rec, k).to_string(),
                sensors: [None; 3],
                group: None,
                sourced: false,
                undone: false,
            });
        }
        key
    }

    /// The [`DfStream`] of `key` ([`DfConv::stream_key`] made it).
    fn stream(&mut self, key: DfStreamKey) -> &mut DfStream {
        self.streams[key.list()][key.instance as usize]
            .as_mut()
            .expect("made by stream_key")
    }

    /// Count a reading of sensor `s` of stream `key` ([`Assembler::stream`]), its entry in the
    /// assembler found by name once.
    fn count_stream(&mut self, key: DfStreamKey, s: Sensor, device_id: Option<u32>) {
        let o = sensor_order(s) as usize;
        let (streams, asm) = (&mut self.streams, &mut self.asm);
        let st = streams[key.list()][key.instance as usize]
            .as_mut()
            .expect("made by stream_key");
        if let Some(i) = st.sensors[o] {
            let e = &mut asm.sensors[i];
            e.3 += 1;
            if device_id.is_some() {
                e.4 = device_id;
            }
            return;
        }
        asm.stream(s, key.instance, &st.src, device_id);
        // Entries are only added (and sorted at the end): its index stays.
        st.sensors[o] = asm
            .sensors
            .iter()
            .position(|e| e.0 as usize == o && e.1 == key.instance && e.2 == st.src);
    }

    /// The stream's name as the source of sensor `sensor` (0 mag, 1 accel) of its instance, if
    /// that has none yet.
    fn name_source(&mut self, key: DfStreamKey, sensor: u8) {
        if self.stream(key).sourced {
            return;
        }
        let src = self.stream(key).src.clone();
        self.sources.entry((sensor, key.instance)).or_insert(src);
        self.stream(key).sourced = true;
    }

    /// The instance group of the stream ([`Assembler::group`]), found once.
    fn stream_group(&mut self, key: DfStreamKey) -> Option<usize> {
        if let Some(gi) = self.stream(key).group {
            return Some(gi);
        }
        let k = key.instance;
        let gi = self
            .asm
            .group(u16::from(k), || df_group_name(key.instanced, k))?;
        self.stream(key).group = Some(gi);
        Some(gi)
    }

    /// A MAG record of instance `k`: ArduPilot's correction undone, uT.
    fn mag(&mut self, k: u8, f: &DfFields) -> Option<(usize, Sample)> {
        let (Some(t), Some(m)) = (f.time_us(), f.get3(DfField::MagX)) else {
            self.asm.stats.skip("bad_record");
            return None;
        };
        let (correction, dev_id) = self.compass(k);
        let key = self.stream_key(&f.rec, k);
        self.count_stream(key, Sensor::Mag, dev_id);
        self.name_source(key, 0);
        let ofs = f.get3(DfField::OfsX);
        let mofs = f.get3(DfField::MOfsX);
        let Some(raw) = ap_undo_cached(correction.as_ref(), m, ofs, mofs) else {
            self.asm.stats.skip("not_undone");
            return None;
        };
        let st = self.stream(key);
        if !st.undone {
            st.undone = true;
            let src = st.src.clone();
            self.undone.insert(src);
        }
        let gi = self.stream_group(key)?;
        self.asm.mag(gi, t, raw)
    }

    /// The first GPS record with a 3D fix: the position for the field model.
    fn gps_fix(&mut self, f: &DfFields) {
        let status = f.get(DfField::Status).unwrap_or(0.0);
        if let (Some(lat), Some(lng), Some(alt)) = (
            f.get(DfField::Lat),
            f.get(DfField::Lng),
            f.get(DfField::Alt),
        ) {
            if status >= 3.0 && (lat != 0.0 || lng != 0.0) {
                self.gps = Some([lat, lng, alt]);
                // GWk and GMS; firmware before them (ArduCopter 3.2 and older) names the GPS
                // week `Week` and the time of week `TimeMS` (then GPS time, not the boot clock).
                let week_ms = match (f.get(DfField::GWk), f.get(DfField::Gms)) {
                    (Some(wk), Some(ms)) => Some((wk, ms)),
                    _ => f.get(DfField::Week).zip(f.get(DfField::TimeMs)),
                };
                if let Some((wk, ms)) = week_ms {
                    if (1.0..1.0e5).contains(&wk) && (0.0..1.0e9).contains(&ms) {
                        let s = GPS_EPOCH_UNIX_S + wk as u64 * 604_800 + (ms / 1000.0) as u64;
                        self.date = crate::types::LogDate::from_unix_us(
                            s * 1_000_000,
                            crate::types::DateSource::GpsTime,
                        );
                    }
                }
            }
        }
    }

    /// Emit what is still held, and the log with its onboard report and message counts.
    fn finish(
        mut self,
        rd: &dataflash::DfReader<'_>,
        n_bytes: usize,
        emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
    ) -> FlightLog {
        for (gi, s) in self.asm.flush() {
            emit(gi, s, n_bytes, self.asm.primary);
        }
        let mut onboard = ap_onboard(&self.first_params, &self.sources);
        onboard.undone = self
            .undone
            .iter()
            .map(|s| format!("{s}: COMPASS_OFS/DIA/ODI/SCALE and the logged motor term removed"))
            .collect();
        onboard.gps = self.gps;
        let skips = rd.stats.skipped.clone();
        let primary_mag = self.sources.get(&(0, 0)).cloned();
        let mut log = self.asm.finish(onboard, &skips);
        log.primary_mag_source = primary_mag;
        log.date = self.date;
        for (id, n) in self.type_counts.iter().enumerate() {
            if let (true, Some(name)) = (*n > 0, self.names.get(&(id as u8, None))) {
                *log.messages.entry(name.clone()).or_insert(0) += n;
            }
        }
        for (id, counts) in self.inst_counts.iter().enumerate() {
            for (k, n) in counts.iter().flat_map(|c| c.iter().enumerate()) {
                if *n == 0 {
                    continue;
                }
                if let Some(name) = self.names.get(&(id as u8, Some(k as u8))) {
                    *log.messages.entry(name.clone()).or_insert(0) += n;
                }
            }
        }
        log
    }
}

/// The name a DataFlash record's stream is reported under (`IMU[1]`, `MAG2`).
fn df_source<'a>(
    names: &'a BTreeMap<(u8, Option<u8>), String>,
    rec: &dataflash::Record<'a>,
    k: u8,
) -> &'a str {
    let inst_col = rec.format.instance.is_some();
    names
        .get(&(rec.format.type_id, inst_col.then_some(k)))
        .map(String::as_str)
        .unwrap_or(rec.format.name.as_str())
}

/// The DataFlash fields the conversion reads, in [`DF_FIELDS`] order; a vector's three axes are
/// consecutive.
#[derive(Debug, Clone, Copy)]
enum DfField {
    TimeUs,
    TimeMs,
    AccX,
    GyrX = 5,
    T = 8,
    MagX,
    OfsX = 12,
    MOfsX = 15,
    Roll = 18,
    Pitch,
    Yaw,
    C3,
    ThO,
    ThrOut,
    Curr,
    Status,
    Lat,
    Lng,
    Alt,
    Value,
    Type,
    GWk,
    Gms,
    Name,
    Week,
}

const DF_FIELDS: [&str; 35] = [
    "TimeUS", "TimeMS", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ", "T", "MagX", "MagY",
    "MagZ", "OfsX", "OfsY", "OfsZ", "MOfsX", "MOfsY", "MOfsZ", "Roll", "Pitch", "Yaw", "C3", "ThO",
    "ThrOut", "Curr", "Status", "Lat", "Lng", "Alt", "Value", "Type", "GWk", "GMS", "Name", "Week",
];

fn df_group_name(instanced: bool, k: u8) -> String {
    if instanced {
        format!("IMU[{k}]+MAG[{k}]")
    } else {
        let s = ["", "2", "3"].get(k as usize).copied().unwrap_or("?");
        format!("IMU{s}+MAG{s}")
    }
}

// ---------------------------------------------------------------------------------------------
// PX4

/// PX4's rotation enum for the ids this reader undoes: 0-7 yaw by 45 deg steps, 8-15 roll 180
/// then yaw.
fn px4_rotation(id: i64) -> Option<Matrix3<f64>> {
    let name = match id {
        0 => "NONE".to_string(),
        1..=7 => format!("YAW_{}", id * 45),
        8 => "ROLL_180".to_string(),
        9..=15 => format!("ROLL_180_YAW_{}", (id - 8) * 45),
        _ => return None,
    };
    crate::attitude::sensor_rotation(&name).ok()
}

/// PX4's magnetometer calibration n: (OFF gauss, S, device id), or why the log's parameters do not
/// give it, naming them (absent, CAL_MAGn_ID 0, a value not finite). Firmware without the scale or
/// off-diagonal parameters applied none: 1 and 0 stand for those.
fn px4_mag_cal(
    params: &BTreeMap<String, f64>,
    n: u8,
) -> Result<([f64; 3], Matrix3<f64>, u32), String> {
    let name = |s: &str| format!("CAL_MAG{n}_{s}");
    let p = |s: &str| params.get(&name(s)).copied();
    let id = match p("ID") {
        None => return Err(format!("{} not in the log", name("ID"))),
        Some(v) if v > 0.0 && v < u32::MAX as f64 => v as u32,
        Some(v) => {
            return Err(format!(
                "{} is {v} (no compass calibrated in that slot)",
                name("ID")
            ))
        }
    };
    let missing: Vec<String> = ["XOFF", "YOFF", "ZOFF"]
        .iter()
        .filter(|s| p(s).is_none())
        .map(|s| name(s))
        .collect();
    if !missing.is_empty() {
        return Err(format!("{} not in the log", missing.join(", ")));
    }
    let get = |s: &str, default: f64| p(s).unwrap_or(default);
    let named = [
        ("XOFF", get("XOFF", 0.0)),
        ("YOFF", get("YOFF", 0.0)),
        ("ZOFF", get("ZOFF", 0.0)),
        ("XSCALE", get("XSCALE", 1.0)),
        ("YSCALE", get("YSCALE", 1.0)),
        ("ZSCALE", get("ZSCALE", 1.0)),
        ("XODIAG", get("XODIAG", 0.0)),
        ("YODIAG", get("YODIAG", 0.0)),
        ("ZODIAG", get("ZODIAG", 0.0)),
    ];
    let bad: Vec<String> = named
        .iter()
        .filter(|(_, v)| !v.is_finite())
        .map(|(s, _)| name(s))
        .collect();
    if !bad.is_empty() {
        return Err(format!("{} not finite", bad.join(", ")));
    }
    let v = named.map(|(_, v)| v);
    let off = [v[0], v[1], v[2]];
    let s = crate::calib::ardupilot::symmetric([v[3], v[4], v[5]], [v[6], v[7], v[8]]);
    Ok((off, s, id))
}

/// The rotation PX4 applies to calibration n's compass (CAL_MAGn_ROT, -1: the board's
/// SENS_BOARD_ROT), or why it is not one this reader undoes.
fn px4_mag_rotation(params: &BTreeMap<String, f64>, n: u8) -> Result<Matrix3<f64>, String> {
    let own = format!("CAL_MAG{n}_ROT");
    let rot = params.get(&own).copied().unwrap_or(-1.0);
    let (name, id) = if rot < 0.0 {
        let board = params.get("SENS_BOARD_ROT").copied().unwrap_or(0.0);
        ("SENS_BOARD_ROT".to_string(), board)
    } else {
        (own, rot)
    };
    Some(id)
        .filter(|v| v.is_finite() && v.fract() == 0.0)
        .and_then(|v| px4_rotation(v as i64))
        .ok_or_else(|| {
            format!(
                "{name} is {id}, not a rotation this reader undoes (0-15: yaw in 45 deg steps, roll 180 then yaw)"
            )
        })
}

/// The calibration slot of the prime compass by the parameters (CAL_MAG_PRIME = CAL_MAGn_ID;
/// without CAL_MAG_PRIME, slot 0), for a corrected field whose records name no device; or why
/// there is none.
fn px4_prime_slot(params: &BTreeMap<String, f64>) -> Result<u8, String> {
    let id = |n: u8| params.get(&format!("CAL_MAG{n}_ID")).copied();
    match params.get("CAL_MAG_PRIME").copied() {
        Some(p) if p != 0.0 => (0..4u8)
            .find(|n| id(*n) == Some(p))
            .ok_or_else(|| format!("CAL_MAG_PRIME is {p}, the CAL_MAGn_ID of no slot")),
        _ if id(0).is_some() => Ok(0),
        _ => Err("neither CAL_MAG_PRIME nor CAL_MAG0_ID in the log".into()),
    }
}

/// The PX4 correction of slot n undone: gauss (corrected, body) in, uT out.
#[derive(Debug)]
struct Px4Undo {
    inv: Matrix3<f64>,
    /// R OFF, gauss.
    off_body: Vector3<f64>,
}

impl Px4Undo {
    /// Slot n's correction to undo, or why the parameters do not allow it.
    fn new(params: &BTreeMap<String, f64>, n: u8) -> Result<Px4Undo, String> {
        let (off, s, _) = px4_mag_cal(params, n)?;
        let r = px4_mag_rotation(params, n)?;
        let inv = (r * s * r.transpose())
            .try_inverse()
            .ok_or_else(|| format!("CAL_MAG{n}'s scale matrix is singular"))?;
        Ok(Px4Undo {
            inv,
            off_body: r * Vector3::from(off),
        })
    }

    /// `None` when the reading is not finite.
    fn apply(&self, m_ga: Vec3) -> Option<Vec3> {
        let u = self.inv * Vector3::from(m_ga) + self.off_body;
        finite3([u[0] * 100.0, u[1] * 100.0, u[2] * 100.0])
    }
}

/// PX4's magnetometer calibrations as the log's parameters give them, each to undo or not.
#[derive(Debug)]
struct Px4Cals {
    /// Slot n's correction (CAL_MAGn_*) to undo, or why it cannot be.
    slots: Vec<Result<Px4Undo, String>>,
    /// The slot of each device id (CAL_MAGn_ID, complete or not; the first where two share one).
    by_device: BTreeMap<u32, u8>,
    /// The prime compass's slot for a corrected field whose records name no device
    /// ([`px4_prime_slot`]).
    prime: Result<u8, String>,
}

impl Px4Cals {
    fn new(params: &BTreeMap<String, f64>) -> Px4Cals {
        let mut by_device = BTreeMap::new();
        for n in 0..4u8 {
            let id = params.get(&format!("CAL_MAG{n}_ID")).copied();
            if let Some(id) = id.filter(|v| *v > 0.0 && *v < u32::MAX as f64) {
                by_device.entry(id as u32).or_insert(n);
            }
        }
        Px4Cals {
            slots: (0..4u8).map(|n| Px4Undo::new(params, n)).collect(),
            by_device,
            prime: px4_prime_slot(params),
        }
    }

    /// The slot a corrected reading was corrected with: by the device id its record names (the
    /// compass PX4 selected for that reading), else, for the prime compass's stream
    /// (`prime`), by the parameters; or why none is known.
    fn slot(&self, device_id: Option<u32>, prime: bool) -> Result<u8, String> {
        match device_id.filter(|d| *d != 0) {
            Some(d) => self
                .by_device
                .get(&d)
                .copied()
                .ok_or_else(|| format!("its device id {d} is no CAL_MAGn_ID")),
            None if prime => self.prime.clone(),
            None => Err("its records name no device id to find its CAL_MAGn by".into()),
        }
    }

    /// Slot n's correction, or why it cannot be undone.
    fn undo(&self, n: u8) -> Result<&Px4Undo, String> {
        match self.slots.get(n as usize) {
            Some(Ok(u)) => Ok(u),
            Some(Err(why)) => Err(why.clone()),
            None => Err(format!("no slot CAL_MAG{n}")),
        }
    }
}

fn px4_onboard(
    params: &BTreeMap<String, f64>,
    mag_ids: &BTreeMap<u8, u32>,
    accel_ids: &BTreeMap<u8, u32>,
    prime_source: Option<&str>,
    prime_slots: &BTreeSet<u8>,
) -> OnboardReport {
    let mut r = OnboardReport {
        stack: "px4".into(),
        ..Default::default()
    };
    let pick = |prefix: &str| -> BTreeMap<String, f64> {
        params
            .range(prefix.to_string()..)
            .take_while(|(k, _)| k.starts_with(prefix))
            .map(|(k, v)| (k.clone(), *v))
            .collect()
    };
    for n in 0..4u8 {
        let Ok((off, s, id)) = px4_mag_cal(params, n) else {
            continue;
        };
        let mut sources: Vec<String> = mag_ids
            .iter()
            .filter(|(_, d)| **d == id)
            .map(|(k, _)| format!("sensor_mag[{k}]"))
            .collect();
        if prime_slots.contains(&n) {
            sources.extend(prime_source.map(String::from));
        }
        r.mag.push(OnboardCal {
            instance: n,
            device_id: Some(id),
            sources,
            offset: off.map(|o| o * 100.0),
            matrix: rows(&s),
            units: crate::types::CalUnits::Ut,
            params: pick(&format!("CAL_MAG{n}_")),
        });
    }
    for n in 0..4u8 {
        let p = |s: &str| params.get(&format!("CAL_ACC{n}_{s}")).copied();
        let Some(id) = p("ID").filter(|v| *v > 0.0 && *v < u32::MAX as f64) else {
            continue;
        };
        let (Some(x), Some(y), Some(z)) = (p("XOFF"), p("YOFF"), p("ZOFF")) else {
            continue;
        };
        let d = [
            p("XSCALE").unwrap_or(1.0),
            p("YSCALE").unwrap_or(1.0),
            p("ZSCALE").unwrap_or(1.0),
        ];
        let id = id as u32;
        r.accel.push(OnboardCal {
            instance: n,
            device_id: Some(id),
            sources: accel_ids
                .iter()
                .filter(|(_, d)| **d == id)
                .map(|(k, _)| format!("sensor_accel[{k}]"))
                .collect(),
            offset: [x, y, z],
            matrix: rows(&Matrix3::from_diagonal(&Vector3::from(d))),
            units: crate::types::CalUnits::Mps2,
            params: pick(&format!("CAL_ACC{n}_")),
        });
    }
    r
}

/// Read a ULog file, handing each sample of every instance to `emit(instance_index, sample,
/// bytes_read, primary_index)`. `None` when the bytes are not a ULog file.
pub fn decode_ulog_with(
    bytes: &[u8],
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> Option<FlightLog> {
    let mut rd = ulog::UlogReader::new(bytes)?;
    Some(decode_ulog_records(&mut rd, emit))
}

/// As [`decode_ulog_with`], the log read from a stream through a window
/// ([`ulog::UlogReader::from_reader`]); a read error comes back after what came before it.
/// `None` when the stream does not begin as a ULog file.
pub(crate) fn decode_ulog_stream(
    reader: impl std::io::Read,
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> Option<(FlightLog, Option<std::io::Error>)> {
    let mut rd = ulog::UlogReader::from_reader(reader)?;
    let log = decode_ulog_records(&mut rd, emit);
    Some((log, rd.take_error()))
}

/// The data records of `rd` (of the topics the conversion reads, [`Topic::is_read`]) through
/// the conversion.
fn decode_ulog_records(
    rd: &mut ulog::UlogReader<'_>,
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> FlightLog {
    let mut conv = UlogConv::new();
    rd.only_topics(Topic::is_read);
    // By message id (a u16: at most 65536 entries), so a record finds its columns by indexing.
    let mut cols: Vec<Option<UlogCols>> = Vec::new();
    loop {
        let params_ready = conv.params_read;
        let Some(d) = rd.next_data() else {
            break;
        };
        let multi = d.sub.multi_id;
        let t_us = d.timestamp_us();
        // The topic and its columns, found once per subscription.
        let id = d.sub.msg_id;
        let slot = id as usize;
        if cols.len() <= slot {
            cols.resize_with(slot + 1, || None);
        }
        let c = match &mut cols[slot] {
            Some(c) if c.serial == d.sub.serial => c,
            other => other.insert(UlogCols::new(d.sub)),
        };
        let r = UlogRecord::read(c, multi, d.payload);
        let read = rd.position();
        if !params_ready {
            // The definitions section (parameters included) precedes the first data record.
            conv.params_known(rd.params());
        }
        let Some(t) = t_us else {
            conv.asm.stats.skip("bad_record");
            continue;
        };
        if let Some((gi, s)) = conv.sample(r, multi, &c.source, t, read, emit) {
            emit(gi, s, read, conv.asm.primary);
        }
    }
    let end = rd.position();
    conv.finish(rd, end, emit)
}

/// What the conversion takes from one ULog record.
enum UlogRecord {
    /// `sensor_combined`: accelerometer, gyroscope and magnetometer (gauss), each when logged.
    Combined(Option<Vec3>, Option<Vec3>, Option<Vec3>),
    /// `sensor_accel[k]`: m/s^2, temperature, device id.
    Accel(Vec3, Option<f64>, Option<u32>),
    /// `sensor_gyro[k]`: rad/s, device id.
    Gyro(Vec3, Option<u32>),
    /// `sensor_mag[k]`: gauss, device id.
    Mag(Vec3, Option<u32>),
    /// `vehicle_magnetometer[k]`: the corrected field, gauss, device id.
    VMag(Vec3, Option<u32>),
    /// `vehicle_attitude[0]`: w, x, y, z (body FRD -> NED).
    Att([f64; 4]),
    /// `actuator_controls_0[0]` control 3.
    Throttle(f64),
    /// `battery_status[0]`, A.
    Current(f64),
    /// `vehicle_gps_position[0]`: lat, lon (1e-7 deg), alt (mm), fix type.
    /// lat, lon (1e-7 deg), alt (mm), fix type, UTC time (us since the Unix epoch, 0 unknown).
    Gps(f64, f64, f64, f64, f64),
    None,
}

impl UlogRecord {
    /// The fields the conversion uses of a record of instance `multi` (its bytes `payload`), by
    /// its subscription's column plan `c`.
    fn read(c: &UlogCols, multi: u8, payload: &[u8]) -> UlogRecord {
        use UlogRecord as R;
        let val = |k: usize| c.plan[k].and_then(|(o, ty)| ty.read(payload.get(o..)?));
        let get = |f: UlField| val(f as usize);
        let v3 = |f: UlField| {
            let k = f as usize;
            Some([val(k)?, val(k + 1)?, val(k + 2)?])
        };
        let dev = get(UlField::DeviceId).map(|v| v as u32);
        match c.topic {
            Topic::Combined => {
                R::Combined(v3(UlField::Acc0), v3(UlField::Gyro0), v3(UlField::MagGa0))
            }
            Topic::Accel => match v3(UlField::X) {
                Some(a) => R::Accel(a, get(UlField::Temperature), dev),
                None => R::None,
            },
            Topic::Gyro => match v3(UlField::X) {
                Some(g) => R::Gyro(g, dev),
                None => R::None,
            },
            Topic::Mag => match v3(UlField::X) {
                Some(m) => R::Mag(m, dev),
                None => R::None,
            },
            Topic::VehicleMag => match v3(UlField::MagGa0) {
                Some(m) => R::VMag(m, dev),
                None => R::None,
            },
            Topic::Attitude if multi == 0 => match (
                get(UlField::Q0),
                get(UlField::Q1),
                get(UlField::Q2),
                get(UlField::Q3),
            ) {
                (Some(w), Some(x), Some(y), Some(z)) => R::Att([w, x, y, z]),
                _ => R::None,
            },
            Topic::Actuators if multi == 0 => match get(UlField::Control3) {
                Some(t) => R::Throttle(t),
                None => R::None,
            },
            Topic::Battery if multi == 0 => match get(UlField::CurrentA) {
                Some(c) => R::Current(c),
                None => R::None,
            },
            Topic::Gps if multi == 0 => match (
                get(UlField::Lat),
                get(UlField::Lon),
                get(UlField::Alt),
                get(UlField::FixType),
            ) {
                (Some(a), Some(b), Some(c), Some(f)) => {
                    R::Gps(a, b, c, f, get(UlField::TimeUtc).unwrap_or(0.0))
                }
                _ => R::None,
            },
            _ => R::None,
        }
    }
}

/// The ULog conversion between records: the samples being assembled and what the onboard report
/// needs at the end.
struct UlogConv {
    asm: Assembler,
    /// The log's magnetometer calibrations (from no parameters until they are read).
    cals: Px4Cals,
    params_read: bool,
    /// The stream the corrected (prime) field came from.
    prime_source: Option<String>,
    /// The slots the prime field's readings were corrected with, and the newest device id its
    /// records named.
    prime_slots: BTreeSet<u8>,
    prime_device: Option<u32>,
    /// Device id per `sensor_mag` / `sensor_accel` instance.
    mag_ids: BTreeMap<u8, u32>,
    accel_ids: BTreeMap<u8, u32>,
    gps: Option<[f64; 3]>,
    date: Option<crate::types::LogDate>,
    /// Per corrected stream: the slots undone from its readings.
    undone: BTreeMap<String, BTreeSet<u8>>,
    /// Per corrected stream: why readings were left out (`mag_not_undone`), and how many.
    left_out: BTreeMap<String, BTreeMap<String, u64>>,
    /// Each further `vehicle_magnetometer[k]` instance -> the `sensor_mag` instance of the same
    /// device.
    further: BTreeMap<u8, u8>,
    /// `sensor_mag` instances fed by their faster `vehicle_magnetometer` instance instead (one
    /// whose correction can be undone); their raw readings are skipped (`mag_slower_stream`).
    fast_mag: BTreeSet<u8>,
}

impl UlogConv {
    fn new() -> Self {
        UlogConv {
            asm: Assembler::new(),
            cals: Px4Cals::new(&BTreeMap::new()),
            params_read: false,
            prime_source: None,
            prime_slots: BTreeSet::new(),
            prime_device: None,
            mag_ids: BTreeMap::new(),
            accel_ids: BTreeMap::new(),
            gps: None,
            date: None,
            undone: BTreeMap::new(),
            left_out: BTreeMap::new(),
            further: BTreeMap::new(),
            fast_mag: BTreeSet::new(),
        }
    }

    /// The parameters are read: the compasses' corrections, each to undo or not.
    fn params_known(&mut self, params: &BTreeMap<String, f64>) {
        self.cals = Px4Cals::new(params);
        self.params_read = true;
    }

    /// Convert one record of instance `multi` from stream `src` at `t_us`: the sample it completes.
    /// A combined record's magnetometer sample goes to `emit` here, with `read` bytes read.
    fn sample(
        &mut self,
        r: UlogRecord,
        multi: u8,
        src: &str,
        t_us: u64,
        read: usize,
        emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
    ) -> Option<(usize, Sample)> {
        let t = t_us;
        match r {
            UlogRecord::Combined(a, g, m) => self.combined(a, g, m, t, read, emit),
            UlogRecord::VMag(m, dev) if multi == 0 => self.vehicle_mag(m, src, dev, t),
            UlogRecord::VMag(m, dev) => self.further_vehicle_mag(m, multi, src, dev, t),
            UlogRecord::Accel(a, temp, dev) => {
                self.asm.stream(Sensor::Accel, multi, src, dev);
                if let Some(d) = dev {
                    self.accel_ids.insert(multi, d);
                }
                let gi = self.sensor_group(multi)?;
                self.asm.accel(gi, t, a, None, temp)
            }
            UlogRecord::Gyro(g, dev) => {
                self.asm.stream(Sensor::Gyro, multi, src, dev);
                let gi = self.sensor_group(multi)?;
                self.asm.gyro(gi, t, g)
            }
            UlogRecord::Mag(m, dev) => {
                self.asm.stream(Sensor::Mag, multi, src, dev);
                if let Some(d) = dev {
                    self.mag_ids.insert(multi, d);
                }
                if self.fast_mag.contains(&multi) {
                    // The same compass arrives faster through its vehicle_magnetometer instance.
                    self.asm.stats.skip("mag_slower_stream");
                    return None;
                }
                let gi = self.sensor_group(multi)?;
                self.asm.mag(gi, t, m.map(|x| x * 100.0))
            }
            UlogRecord::Att(q) => {
                self.asm.attitude = crate::attitude::ned_to_enu(q).map(|q| (t, q));
                None
            }
            UlogRecord::Throttle(v) => {
                if v.is_finite() {
                    self.asm.throttle = Some(v.clamp(0.0, 1.5));
                }
                None
            }
            UlogRecord::Current(c) => {
                if c.is_finite() && c >= 0.0 {
                    self.asm.current_a = Some(c);
                }
                None
            }
            UlogRecord::Gps(lat, lon, alt, fix, utc_us) => {
                if self.gps.is_none() && fix >= 3.0 {
                    self.gps = Some([lat * 1e-7, lon * 1e-7, alt * 1e-3]);
                }
                if self.date.is_none() && fix >= 3.0 && utc_us > 0.0 {
                    self.date = crate::types::LogDate::from_unix_us(
                        utc_us as u64,
                        crate::types::DateSource::GpsTime,
                    );
                }
                None
            }
            UlogRecord::None => None,
        }
    }

    /// The instance of `sensor_accel[k]`, `sensor_gyro[k]` and `sensor_mag[k]`.
    fn sensor_group(&mut self, k: u8) -> Option<usize> {
        self.asm
            .group(PX4_SENSOR_KEY + k as u16, || px4_group_name(k))
    }

    /// A `sensor_combined` record; its magnetometer reading (emitted here) rides on the record's
    /// accelerometer sample (returned).
    fn combined(
        &mut self,
        a: Option<Vec3>,
        g: Option<Vec3>,
        m: Option<Vec3>,
        t: u64,
        read: usize,
        emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
    ) -> Option<(usize, Sample)> {
        let gi = self.asm.group(0, || "sensor_combined".into())?;
        self.asm.groups[gi].has_accel |= a.is_some();
        if let Some(m) = m {
            const SRC: &str = "sensor_combined.magnetometer_ga";
            self.asm.stream(Sensor::Mag, 0, SRC, None);
            self.prime_source.get_or_insert_with(|| SRC.into());
            if let Some(raw) = self.undo(SRC, None, true, m) {
                if let Some((g2, s2)) = self.asm.mag(gi, t, raw) {
                    emit(g2, s2, read, self.asm.primary);
                }
            }
        }
        if g.is_some() {
            self.asm.stream(Sensor::Gyro, 0, "sensor_combined", None);
        }
        match a {
            Some(a) => {
                self.asm.stream(Sensor::Accel, 0, "sensor_combined", None);
                self.asm.accel(gi, t, a, g, None)
            }
            None => g.and_then(|g| self.asm.gyro(gi, t, g)),
        }
    }

    /// A `vehicle_magnetometer[0]` record (stream `src`): the corrected field of the compass PX4
    /// selected (`dev`, where the record names it), undone onto the primary instance.
    fn vehicle_mag(
        &mut self,
        m: Vec3,
        src: &str,
        dev: Option<u32>,
        t: u64,
    ) -> Option<(usize, Sample)> {
        self.asm.stream(Sensor::Mag, 0, src, dev);
        self.prime_source.get_or_insert_with(|| src.into());
        let gi = self.asm.group(0, || "sensor_combined".into())?;
        let raw = self.undo(src, dev, true, m)?;
        self.asm.mag(gi, t, raw)
    }

    /// A `vehicle_magnetometer[k]` record (k > 0, stream `src`): a further compass's corrected
    /// field, logged faster than its raw `sensor_mag` topic (PX4 logs those at 1 Hz by default).
    /// Where its correction (the CAL_MAGn of its device id) can be undone, the reading goes to the
    /// instance of the `sensor_mag` with the same device id (else `sensor_mag[k]`), whose raw
    /// readings are then skipped (`mag_slower_stream`); where it cannot, the raw readings stay.
    fn further_vehicle_mag(
        &mut self,
        m: Vec3,
        k: u8,
        src: &str,
        dev: Option<u32>,
        t: u64,
    ) -> Option<(usize, Sample)> {
        let j = dev
            .and_then(|d| {
                self.mag_ids
                    .iter()
                    .find(|(_, id)| **id == d)
                    .map(|(j, _)| *j)
            })
            .unwrap_or(k);
        self.further.entry(k).or_insert(j);
        if !self.fast_mag.contains(&j) {
            let undoable = self
                .cals
                .slot(dev, false)
                .and_then(|n| self.cals.undo(n))
                .is_ok();
            if undoable {
                self.fast_mag.insert(j);
            }
        }
        self.asm.stream(Sensor::Mag, j, src, dev);
        let raw = self.undo(src, dev, false, m)?;
        let gi = self.sensor_group(j)?;
        self.asm.mag(gi, t, raw)
    }

    /// The onboard correction undone from a reading `m` (gauss) of the corrected stream `src`:
    /// the raw field in body axes, uT. `dev` is the device id its record names; `prime`, whether
    /// `src` is the prime compass's field. A reading whose correction cannot be undone is never
    /// taken as raw: it is skipped as `mag_not_undone` (the reason kept for
    /// `onboard.not_undone`), one not finite as `non_finite`.
    fn undo(&mut self, src: &str, dev: Option<u32>, prime: bool, m: Vec3) -> Option<Vec3> {
        let slot = self.cals.slot(dev, prime);
        if prime {
            if let Ok(n) = slot {
                self.prime_slots.insert(n);
            }
            if let Some(d) = dev.filter(|d| *d != 0) {
                self.prime_device = Some(d);
            }
        }
        let undone = slot.and_then(|n| Ok((n, self.cals.undo(n)?.apply(m))));
        match undone {
            Ok((n, Some(raw))) => {
                match self.undone.get_mut(src) {
                    Some(slots) => {
                        slots.insert(n);
                    }
                    None => {
                        self.undone.insert(src.to_string(), BTreeSet::from([n]));
                    }
                }
                Some(raw)
            }
            Ok((_, None)) => {
                self.asm.stats.skip("non_finite");
                None
            }
            Err(why) => {
                self.asm.stats.skip("mag_not_undone");
                *self
                    .left_out
                    .entry(src.to_string())
                    .or_default()
                    .entry(why)
                    .or_insert(0) += 1;
                None
            }
        }
    }

    /// What became of a corrected stream's readings, for `onboard.undone` / `onboard.not_undone`:
    /// what the stream is (`what`), the slots undone, and the readings left out by reason.
    fn onboard_notes(&self, src: &str, what: &str, onboard: &mut OnboardReport) {
        if let Some(slots) = self.undone.get(src) {
            let names: Vec<String> = slots.iter().map(|n| format!("CAL_MAG{n}")).collect();
            onboard.undone.push(format!(
                "{what}: {} offsets, scales and rotation removed",
                names.join(" and ")
            ));
        }
        if let Some(why) = self.left_out.get(src) {
            let n: u64 = why.values().sum();
            let reasons: Vec<&str> = why.keys().map(String::as_str).collect();
            onboard.not_undone.push(format!(
                "{what}: {n} readings left out (skipped as mag_not_undone): {}",
                reasons.join("; ")
            ));
        }
    }

    /// Emit what is still held, and the log with its onboard report and message counts.
    fn finish(
        mut self,
        rd: &ulog::UlogReader<'_>,
        n_bytes: usize,
        emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
    ) -> FlightLog {
        for (gi, s) in self.asm.flush() {
            emit(gi, s, n_bytes, self.asm.primary);
        }
        let params = rd.params();
        let mut onboard = px4_onboard(
            params,
            &self.mag_ids,
            &self.accel_ids,
            self.prime_source.as_deref(),
            &self.prime_slots,
        );
        if let Some(src) = &self.prime_source {
            let mut what = src.clone();
            if self.left_out.contains_key(src) {
                // Where the same compass is also logged raw, that stream is fitted as it is.
                let raw = self.prime_device.and_then(|d| {
                    self.mag_ids
                        .iter()
                        .find(|(_, id)| **id == d)
                        .map(|(j, _)| *j)
                });
                if let Some(j) = raw {
                    what = format!("{src} (its compass logged raw as sensor_mag[{j}], fitted in that instance)");
                }
            }
            self.onboard_notes(src, &what, &mut onboard);
        }
        for (k, j) in &self.further {
            let src = format!("vehicle_magnetometer[{k}]");
            let what = if self.fast_mag.contains(j) {
                format!("{src} (the same device as sensor_mag[{j}], logged faster), used for sensor_mag[{j}]'s instance")
            } else {
                format!("{src} (the same device as sensor_mag[{j}], logged faster), not used: sensor_mag[{j}]'s raw readings fitted instead")
            };
            self.onboard_notes(&src, &what, &mut onboard);
            for c in onboard.mag.iter_mut() {
                if c.sources.contains(&format!("sensor_mag[{j}]")) {
                    c.sources.push(src.clone());
                }
            }
        }
        onboard.gps = self.gps;
        let mut skips = rd.stats.skipped.clone();
        if rd.stats.dropouts > 0 {
            skips.insert("dropouts".into(), rd.stats.dropouts);
        }
        let mut log = self.asm.finish(onboard, &skips);
        log.primary_mag_source = self.prime_source;
        log.primary_compass_from_onboard();
        log.date = self.date;
        for sub in rd.subscriptions().filter(|s| s.records > 0) {
            *log.messages
                .entry(format!("{}[{}]", sub.name, sub.multi_id))
                .or_insert(0) += sub.records;
        }
        log
    }
}

/// The ULog topics the conversion reads.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Topic {
    Combined,
    Accel,
    Gyro,
    Mag,
    VehicleMag,
    Attitude,
    Actuators,
    Battery,
    Gps,
    Other,
}

impl Topic {
    /// The topic of a subscription's name.
    fn of(name: &str) -> Topic {
        match name {
            "sensor_combined" => Topic::Combined,
            "sensor_accel" => Topic::Accel,
            "sensor_gyro" => Topic::Gyro,
            "sensor_mag" => Topic::Mag,
            "vehicle_magnetometer" => Topic::VehicleMag,
            "vehicle_attitude" => Topic::Attitude,
            "actuator_controls_0" => Topic::Actuators,
            "battery_status" => Topic::Battery,
            "vehicle_gps_position" => Topic::Gps,
            _ => Topic::Other,
        }
    }

    /// Whether the conversion reads the topic of this name.
    fn is_read(name: &str) -> bool {
        Topic::of(name) != Topic::Other
    }
}

/// The ULog fields the conversion reads, in [`UL_FIELDS`] order; a vector's axes are consecutive.
#[derive(Debug, Clone, Copy)]
enum UlField {
    Acc0,
    Gyro0 = 3,
    MagGa0 = 6,
    X = 9,
    Temperature = 12,
    DeviceId,
    Q0,
    Q1,
    Q2,
    Q3,
    Control3,
    CurrentA,
    Lat,
    Lon,
    Alt,
    FixType,
    TimeUtc,
}

const UL_FIELDS: [&str; 25] = [
    "accelerometer_m_s2[0]",
    "accelerometer_m_s2[1]",
    "accelerometer_m_s2[2]",
    "gyro_rad[0]",
    "gyro_rad[1]",
    "gyro_rad[2]",
    "magnetometer_ga[0]",
    "magnetometer_ga[1]",
    "magnetometer_ga[2]",
    "x",
    "y",
    "z",
    "temperature",
    "device_id",
    "q[0]",
    "q[1]",
    "q[2]",
    "q[3]",
    "control[3]",
    "current_a",
    "lat",
    "lon",
    "alt",
    "fix_type",
    "time_utc_usec",
];

/// A subscription's topic, its column plan (where each of [`UL_FIELDS`] is in a record, and its
/// type), and its source name.
struct UlogCols {
    serial: u32,
    topic: Topic,
    plan: Vec<Option<(usize, ulog::Ty)>>,
    source: String,
}

impl UlogCols {
    fn new(sub: &ulog::Subscription) -> UlogCols {
        let topic = Topic::of(&sub.name);
        let plan = if topic == Topic::Other {
            vec![None; UL_FIELDS.len()]
        } else {
            UL_FIELDS
                .iter()
                .map(|f| {
                    sub.field(f)
                        .map(|k| (sub.fields[k].offset, sub.fields[k].ty))
                })
                .collect()
        };
        UlogCols {
            serial: sub.serial,
            topic,
            plan,
            source: format!("{}[{}]", sub.name, sub.multi_id),
        }
    }
}

fn px4_group_name(k: u8) -> String {
    format!("sensor_accel[{k}]+sensor_gyro[{k}]+sensor_mag[{k}]")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_old_dataflash_gps_message_gives_the_date_from_week_and_time_ms() {
        // ArduCopter 3.2 and older: GPS with Week and TimeMS (the time of week) instead of GWk
        // and GMS. Week 1850 plus half a week is 2015-06-24.
        let mut bytes = write::dataflash_bytes(&[], &write::OnboardMag::example()).unwrap();
        bytes.extend(write::fmt_record(
            133,
            "GPS",
            "BIHBcLLeeEefI",
            "Status,TimeMS,Week,NSats,HDop,Lat,Lng,RelAlt,Alt,Spd,GCrs,VZ,T",
        ));
        bytes.extend([0xA3, 0x95, 133, 3]);
        bytes.extend(302_400_000u32.to_le_bytes());
        bytes.extend(1850u16.to_le_bytes());
        bytes.push(10);
        bytes.extend(100i16.to_le_bytes());
        bytes.extend(520_381_699i32.to_le_bytes());
        bytes.extend(51_448_234i32.to_le_bytes());
        bytes.extend(0i32.to_le_bytes());
        bytes.extend(1000i32.to_le_bytes());
        bytes.extend(0u32.to_le_bytes());
        bytes.extend(0i32.to_le_bytes());
        bytes.extend(0f32.to_le_bytes());
        bytes.extend(0u32.to_le_bytes());
        let log = decode_dataflash_with(&bytes, &mut |_, _, _, _| {});
        let date = log.date.expect("a date from the GPS message");
        assert_eq!(date.iso(), "2015-06-24");
        assert_eq!(date.source, crate::types::DateSource::GpsTime);
        let gps = log.onboard.gps.expect("the fix");
        assert!((gps[0] - 52.0381699).abs() < 1e-6, "{gps:?}");
    }

    #[test]
    fn ardupilot_undo_inverts_its_correction() {
        let p = crate::calib::ardupilot::example_compass2();
        let raw_ut = [12.0, -30.0, 41.0];
        let c = crate::calib::ardupilot::correction(&p, 1, true)
            .unwrap()
            .apply(raw_ut);
        let back = ap_undo(&p, 1, [c[0], c[1], c[2]], None, None).unwrap();
        for i in 0..3 {
            assert!((back[i] - raw_ut[i]).abs() < 1e-9, "{back:?}");
        }
        // The onboard model in imucald's convention gives the corrected field back from raw.
        let r = ap_onboard(&p, &BTreeMap::new());
        let cal = &r.mag[0];
        assert_eq!(cal.instance, 1);
        let mm = crate::calib::model::rows_to_mat(&cal.matrix);
        let d = Vector3::new(
            raw_ut[0] - cal.offset[0],
            raw_ut[1] - cal.offset[1],
            raw_ut[2] - cal.offset[2],
        );
        let cal_ut = mm * d;
        for i in 0..3 {
            assert!((cal_ut[i] * 10.0 - c[i]).abs() < 1e-9);
        }
    }

    #[test]
    fn px4_undo_with_board_rotation() {
        let mut p = BTreeMap::new();
        for (n, v) in [
            ("CAL_MAG0_ID", 1234.0),
            ("CAL_MAG0_ROT", -1.0),
            ("SENS_BOARD_ROT", 4.0),
            ("CAL_MAG0_XOFF", 0.1),
            ("CAL_MAG0_YOFF", -0.2),
            ("CAL_MAG0_ZOFF", 0.3),
            ("CAL_MAG0_XSCALE", 1.1),
            ("CAL_MAG0_YSCALE", 0.9),
            ("CAL_MAG0_ZSCALE", 1.0),
            ("CAL_MAG0_XODIAG", 0.05),
            ("CAL_MAG_PRIME", 1234.0),
        ] {
            p.insert(n.to_string(), v);
        }
        let raw_sensor = Vector3::new(0.2, 0.1, -0.4);
        let (off, s, _) = px4_mag_cal(&p, 0).unwrap();
        let r = px4_mag_rotation(&p, 0).unwrap();
        let corrected = r * (s * (raw_sensor - Vector3::from(off)));
        let u = Px4Undo::new(&p, px4_prime_slot(&p).unwrap()).unwrap();
        let back = u.apply([corrected[0], corrected[1], corrected[2]]).unwrap();
        let want = r * raw_sensor * 100.0;
        for i in 0..3 {
            assert!((back[i] - want[i]).abs() < 1e-9, "{back:?} {want:?}");
        }
    }

    #[test]
    fn px4_undo_names_what_the_parameters_lack() {
        let params = |kv: &[(&str, f64)]| -> BTreeMap<String, f64> {
            kv.iter().map(|(k, v)| (k.to_string(), *v)).collect()
        };
        let why = |p: &BTreeMap<String, f64>| Px4Undo::new(p, 0).unwrap_err();
        assert_eq!(why(&params(&[])), "CAL_MAG0_ID not in the log");
        assert_eq!(
            why(&params(&[("CAL_MAG0_ID", 0.0)])),
            "CAL_MAG0_ID is 0 (no compass calibrated in that slot)"
        );
        let partial = [("CAL_MAG0_ID", 7.0), ("CAL_MAG0_YOFF", 0.1)];
        assert_eq!(
            why(&params(&partial)),
            "CAL_MAG0_XOFF, CAL_MAG0_ZOFF not in the log"
        );
        let complete = [
            ("CAL_MAG0_ID", 7.0),
            ("CAL_MAG0_XOFF", 0.1),
            ("CAL_MAG0_YOFF", 0.1),
            ("CAL_MAG0_ZOFF", 0.1),
        ];
        let mut p = params(&complete);
        p.insert("CAL_MAG0_XSCALE".into(), f64::NAN);
        assert_eq!(why(&p), "CAL_MAG0_XSCALE not finite");
        let mut p = params(&complete);
        p.insert("CAL_MAG0_ROT".into(), 38.0);
        assert!(
            why(&p).starts_with("CAL_MAG0_ROT is 38, not a rotation"),
            "{}",
            why(&p)
        );
        let mut p = params(&complete);
        p.insert("SENS_BOARD_ROT".into(), 20.0);
        assert!(why(&p).starts_with("SENS_BOARD_ROT is 20,"), "{}", why(&p));
        assert!(Px4Undo::new(&params(&complete), 0).is_ok());
        let mut p = params(&complete);
        p.insert("CAL_MAG_PRIME".into(), 5.0);
        assert_eq!(
            px4_prime_slot(&p).unwrap_err(),
            "CAL_MAG_PRIME is 5, the CAL_MAGn_ID of no slot"
        );
    }

    /// A record of a synthetic PX4 log ([`px4_log`]): time (us), and for the magnetometer topics
    /// the instance, device id and field (gauss).
    enum Px4Rec {
        Combined(u64),
        VehicleMag(u8, u64, u32, [f32; 3]),
        SensorMag(u8, u64, u32, [f32; 3]),
    }

    /// A ULog with `params` (as floats) and `records`: `sensor_combined` (message 0), and
    /// `vehicle_magnetometer[k]` (10 + k) and `sensor_mag[k]` (20 + k) for k < 2.
    fn px4_log(params: &[(&str, f32)], records: &[Px4Rec]) -> Vec<u8> {
        use ulog::tests::{header, msg, param, sub};
        let mut f = header();
        for def in [
            &b"sensor_combined:uint64_t timestamp;float[3] gyro_rad;float[3] accelerometer_m_s2;"[..],
            b"vehicle_magnetometer:uint64_t timestamp;uint32_t device_id;float[3] magnetometer_ga;",
            b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;float z;",
        ] {
            f.extend(msg(b'F', def));
        }
        for (k, v) in params {
            f.extend(param(k, *v));
        }
        f.extend(sub(0, 0, "sensor_combined"));
        for k in 0..2u8 {
            f.extend(sub(k, 10 + k as u16, "vehicle_magnetometer"));
            f.extend(sub(k, 20 + k as u16, "sensor_mag"));
        }
        for r in records {
            let (id, t, body): (u16, u64, Vec<f32>) = match r {
                Px4Rec::Combined(t) => (0, *t, vec![0.0, 0.0, 0.0, 0.0, 0.0, -9.81]),
                Px4Rec::VehicleMag(k, t, _, m) => (10 + *k as u16, *t, m.to_vec()),
                Px4Rec::SensorMag(k, t, _, m) => (20 + *k as u16, *t, m.to_vec()),
            };
            let mut b = id.to_le_bytes().to_vec();
            b.extend(t.to_le_bytes());
            if let Px4Rec::VehicleMag(_, _, dev, _) | Px4Rec::SensorMag(_, _, dev, _) = r {
                b.extend(dev.to_le_bytes());
            }
            for v in body {
                b.extend(v.to_le_bytes());
            }
            f.extend(msg(b'D', &b));
        }
        f
    }

    /// The log and every sample emitted, with its instance index.
    fn px4_decode(bytes: &[u8]) -> (FlightLog, Vec<(usize, Sample)>) {
        let mut out = Vec::new();
        let log = decode_ulog_with(bytes, &mut |gi, s, _, _| out.push((gi, s))).unwrap();
        (log, out)
    }

    /// The magnetometer readings emitted for the instance named `name`.
    fn mags_of(log: &FlightLog, samples: &[(usize, Sample)], name: &str) -> Vec<Vec3> {
        let gi = log.instances.iter().position(|i| i.name == name).unwrap();
        samples
            .iter()
            .filter(|(g, _)| *g == gi)
            .filter_map(|(_, s)| s.mag_ut)
            .collect()
    }

    #[test]
    fn a_px4_prime_field_that_cannot_be_undone_is_counted_and_named() {
        // CAL_MAG0 of the compass vehicle_magnetometer[0] names lacks its X and Y offsets.
        let params = [
            ("CAL_MAG0_ID", 1000.0),
            ("CAL_MAG0_ROT", 0.0),
            ("CAL_MAG0_ZOFF", 0.1),
        ];
        let mut recs = Vec::new();
        for i in 0..5u64 {
            let t = 1_000_000 + i * 20_000;
            recs.push(Px4Rec::SensorMag(0, t, 1000, [0.2, 0.1, -0.4]));
            recs.push(Px4Rec::VehicleMag(0, t, 1000, [0.2, 0.1, -0.5]));
            recs.push(Px4Rec::Combined(t + 1));
        }
        let (log, samples) = px4_decode(&px4_log(&params, &recs));
        // Every corrected reading left out, counted with its reason; none fitted as raw.
        assert_eq!(log.stats.skipped.get("mag_not_undone"), Some(&5));
        assert_eq!(log.stats.counts.mag, 0);
        assert!(mags_of(&log, &samples, "sensor_combined").is_empty());
        assert_eq!(
            log.onboard.not_undone,
            ["vehicle_magnetometer[0] (its compass logged raw as sensor_mag[0], fitted in that instance): 5 readings left out (skipped as mag_not_undone): CAL_MAG0_XOFF, CAL_MAG0_YOFF not in the log"]
        );
        assert!(log.onboard.undone.is_empty(), "{:?}", log.onboard.undone);
        // The same compass's raw readings are fitted in their own instance.
        let raw = mags_of(&log, &samples, &px4_group_name(0));
        assert_eq!(raw.len(), 5);
    }

    #[test]
    fn a_px4_prime_field_is_undone_with_the_calibration_of_its_device() {
        // PX4 1.12 and later log no CAL_MAG_PRIME: the compass PX4 selected is the device id of
        // the vehicle_magnetometer record (CAL_MAG1's), not slot 0 (disabled, identity).
        let (off, d, o) = ([0.1f32, -0.2, 0.3], [1.1f32, 0.9, 1.0], 0.05f32);
        let params = [
            ("CAL_MAG0_ID", 1000.0),
            ("CAL_MAG0_PRIO", 0.0),
            ("CAL_MAG0_XOFF", 0.0),
            ("CAL_MAG0_YOFF", 0.0),
            ("CAL_MAG0_ZOFF", 0.0),
            ("CAL_MAG1_ID", 2000.0),
            ("CAL_MAG1_PRIO", 75.0),
            ("CAL_MAG1_ROT", 0.0),
            ("CAL_MAG1_XOFF", off[0]),
            ("CAL_MAG1_YOFF", off[1]),
            ("CAL_MAG1_ZOFF", off[2]),
            ("CAL_MAG1_XSCALE", d[0]),
            ("CAL_MAG1_YSCALE", d[1]),
            ("CAL_MAG1_ZSCALE", d[2]),
            ("CAL_MAG1_XODIAG", o),
        ];
        let raw_ga = Vector3::new(0.25, -0.1, 0.45);
        let s = Matrix3::new(
            d[0] as f64,
            o as f64,
            0.0,
            o as f64,
            d[1] as f64,
            0.0,
            0.0,
            0.0,
            d[2] as f64,
        );
        let c = s * (raw_ga - Vector3::new(off[0] as f64, off[1] as f64, off[2] as f64));
        let corrected = [c[0] as f32, c[1] as f32, c[2] as f32];
        let mut recs = Vec::new();
        for i in 0..4u64 {
            let t = 1_000_000 + i * 20_000;
            recs.push(Px4Rec::VehicleMag(0, t, 2000, corrected));
            recs.push(Px4Rec::Combined(t + 1));
        }
        let (log, samples) = px4_decode(&px4_log(&params, &recs));
        let got = mags_of(&log, &samples, "sensor_combined");
        assert_eq!(got.len(), 4);
        for m in got {
            for k in 0..3 {
                assert!((m[k] - raw_ga[k] * 100.0).abs() < 1e-4, "{m:?} {raw_ga:?}");
            }
        }
        assert_eq!(
            log.onboard.undone,
            ["vehicle_magnetometer[0]: CAL_MAG1 offsets, scales and rotation removed"]
        );
        let slot1 = log.onboard.mag.iter().find(|c| c.instance == 1).unwrap();
        assert!(slot1
            .sources
            .contains(&"vehicle_magnetometer[0]".to_string()));
        assert!(log.stats.skipped.is_empty(), "{:?}", log.stats.skipped);
    }

    #[test]
    fn a_px4_further_fast_stream_not_undone_leaves_its_raw_readings() {
        // vehicle_magnetometer[1] is sensor_mag[0]'s device, which no CAL_MAGn names.
        let params = [
            ("CAL_MAG0_ID", 1000.0),
            ("CAL_MAG0_XOFF", 0.0),
            ("CAL_MAG0_YOFF", 0.0),
            ("CAL_MAG0_ZOFF", 0.0),
        ];
        let mut recs = Vec::new();
        for i in 0..6u64 {
            let t = 1_000_000 + i * 20_000;
            if i % 2 == 0 {
                recs.push(Px4Rec::SensorMag(0, t, 3000, [0.2, 0.1, -0.4]));
            }
            recs.push(Px4Rec::VehicleMag(1, t, 3000, [0.2, 0.1, -0.5]));
        }
        let (log, samples) = px4_decode(&px4_log(&params, &recs));
        assert_eq!(log.stats.skipped.get("mag_not_undone"), Some(&6));
        assert_eq!(log.stats.skipped.get("mag_slower_stream"), None);
        // The raw readings, and only those, reach the compass's instance.
        let got = mags_of(&log, &samples, &px4_group_name(0));
        assert_eq!(got.len(), 3);
        assert!(got.iter().all(|m| (m[2] + 40.0).abs() < 1e-4), "{got:?}");
        assert_eq!(
            log.onboard.not_undone,
            ["vehicle_magnetometer[1] (the same device as sensor_mag[0], logged faster), not used: sensor_mag[0]'s raw readings fitted instead: 6 readings left out (skipped as mag_not_undone): its device id 3000 is no CAL_MAGn_ID"]
        );
    }

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
    fn ulog_sensor_instances_up_to_255_stay_apart() {
        // A multi_id above 155 once overflowed the instance key (found by fuzzing).
        use ulog::tests::{header, msg, sub};
        let mut f = header();
        f.extend(msg(
            b'F',
            b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;float z;",
        ));
        f.extend(sub(0, 1, "sensor_mag"));
        f.extend(sub(200, 2, "sensor_mag"));
        for (id, t) in [(1u16, 10u64), (2, 11), (1, 20), (2, 21)] {
            let mut b = id.to_le_bytes().to_vec();
            b.extend(t.to_le_bytes());
            b.extend(7u32.to_le_bytes());
            for v in [0.2f32, 0.1, -0.4] {
                b.extend(v.to_le_bytes());
            }
            f.extend(msg(b'D', &b));
        }
        let log = decode_ulog_with(&f, &mut |_, _, _, _| {}).unwrap();
        let ids: Vec<(u8, u64)> = log
            .instances
            .iter()
            .map(|i| (i.compass_id, i.samples))
            .collect();
        assert_eq!(ids, [(0, 2), (200, 2)]);
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
