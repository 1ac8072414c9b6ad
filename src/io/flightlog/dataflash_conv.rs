//! DataFlash records turned into readings per instance: IMU, MAG (ArduPilot's correction
//! undone), the attitude, throttle, current and the first GPS fix, with the parameters as they
//! change and the counts the report gives.

use super::ardupilot_onboard::{ap_onboard, ap_undo_cached, ApUndo};
use super::{dataflash, sensor_order, Assembler, FlightLog};
use crate::types::{Sample, Sensor, Vec3};
use std::collections::BTreeMap;

/// The Unix time of the GPS epoch (1980-01-06), s. GPS time runs ahead of UTC by the leap
/// seconds since (18 in 2017-2026), which never moves a date by more than those seconds.
const GPS_EPOCH_UNIX_S: u64 = 315_964_800;

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
        log.temperature_params = super::temperature_params(&self.first_params);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::flightlog::write;

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
}
