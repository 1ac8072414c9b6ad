//! ULog records turned into readings per instance: `sensor_combined`, `sensor_accel`,
//! `sensor_gyro`, `sensor_mag`, `vehicle_magnetometer` (PX4's correction undone), the attitude,
//! throttle, current and the first GPS fix, with the counts the report gives.

use super::px4_onboard::{px4_onboard, Px4Cals};
use super::{ulog, Assembler, FlightLog, PX4_SENSOR_KEY};
use crate::io::onboard::OnboardReport;
use crate::types::{Sample, Sensor, Vec3};
use std::collections::{BTreeMap, BTreeSet};

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
        log.temperature_params = super::temperature_params(params);
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
    use nalgebra::{Matrix3, Vector3};

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
    fn the_temperature_calibration_parameters_are_handed_on() {
        let params = [
            ("CAL_MAG0_ID", 1000.0),
            ("TC_A_ENABLE", 1.0),
            ("TC_A0_ID", 1_310_988.0),
            ("TC_A0_X1_2", 2.5e-4),
        ];
        let recs: Vec<Px4Rec> = (0..3u64).map(|i| Px4Rec::Combined(1_000_000 + i)).collect();
        let (log, _) = px4_decode(&px4_log(&params, &recs));
        let names: Vec<&str> = log.temperature_params.keys().map(String::as_str).collect();
        assert_eq!(names, ["TC_A0_ID", "TC_A0_X1_2", "TC_A_ENABLE"]);
        assert_eq!(log.temperature_params["TC_A0_ID"], 1_310_988.0);
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
}
