//! Sources: the only layer that knows where bytes come from. Files (`file:` addresses and plain
//! paths) decoded whole ([`read_log`]) or as a stream ([`decode_file_batched`]: a tlog and a
//! DataFlash log through a bounded window); live transports build on the same decoders.

use crate::calib::settings::AccelUnits;
use crate::error::Error;
use crate::io::decode::{
    decode_csv, decode_tlog_with, detect_format, maybe_gunzip, CsvMapping, DecodeStats, Format,
    InstanceChoice, InstanceInfo, MessageConverter, RawImuScale,
};
use crate::types::{Sample, Unit, Units};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A decoded log.
#[derive(Debug, Clone)]
pub struct Log {
    pub format: Format,
    pub samples: Vec<Sample>,
    pub stats: DecodeStats,
    pub instance: Option<String>,
    pub units: Units,
    /// Every IMU instance read (MAVLink and flight-controller logs), the primary among them.
    pub instances: Vec<InstanceInfo>,
    /// Flight-controller logs (`.bin`, `.ulg`): sensor streams, onboard calibration, message
    /// counts (`instances` and `stats` above are its own).
    pub flight: Option<crate::io::flightlog::FlightLog>,
    /// A MAVLink log of an ArduPilot vehicle: its onboard magnetometer calibration as the
    /// telemetry gave it, and what was undone.
    pub telemetry_onboard: Option<crate::io::onboard::OnboardReport>,
    /// The day the log was recorded, when it says (GPS time, or a `.tlog`'s record clock).
    pub date: Option<crate::types::LogDate>,
}

impl Log {
    /// Where and when the log was recorded, for the earth field; a log that gives no date is
    /// dated today ([`crate::io::clock::today`], `date_source` "today" in the report).
    pub fn place(&self) -> crate::types::LogWhere {
        crate::types::LogWhere {
            gps: self.onboard().and_then(|o| o.gps),
            date: self.date.or_else(|| Some(crate::io::clock::today())),
        }
    }

    /// The onboard calibration the log records (flight-controller logs, ArduPilot telemetry).
    pub fn onboard(&self) -> Option<&crate::io::onboard::OnboardReport> {
        match &self.flight {
            Some(f) => Some(&f.onboard),
            None => self.telemetry_onboard.as_ref(),
        }
    }
}

/// Records read from the start of a `.tlog` for the vehicle's HEARTBEAT before decoding, so that
/// its flight stack (which fixes RAW_IMU's units) is known from the first sample on.
const HEARTBEAT_SCAN_RECORDS: usize = 4096;

/// `[input]`: how logs are read: format, instance, units.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct InputConfig {
    /// "auto" (from content), "tlog", "csv", "bin" (ArduPilot DataFlash) or "ulg" (PX4 ULog). Default: "auto".
    pub format: InputFormat,
    /// IMU instance in MAVLink logs: "auto" (default: every instance, each calibrated on its own in
    /// `replay`, the first with a magnetometer primary; the live service takes the primary), or one
    /// instance only: "highres_imu:0", "scaled_imu", "scaled_imu2", "scaled_imu3", "raw_imu:0".
    /// Default: "auto".
    pub instance: InstanceChoice,
    /// Scales for RAW_IMU counts (0 = keep counts and let the fit scale them). Default: all 0.
    pub raw_imu_scale: RawImuScale,
    /// Column mapping and unit scales for users' own CSV files. Default: imucald's own column
    /// names (`t,ax,ay,az,gx,gy,gz,mx,my,mz,...`) in SI units.
    pub csv: CsvMapping,
    /// Accelerometer units: "auto" (m/s^2 when the static norm is near g, else counts), "si", "counts".
    /// Default: "auto".
    pub accel_units: AccelUnits,
}

/// `input.format`: how the format of a log is found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputFormat {
    /// From the file's content.
    Auto,
    Tlog,
    Csv,
    /// ArduPilot DataFlash log.
    Bin,
    /// PX4 ULog.
    Ulg,
}

impl InputFormat {
    /// The format asked for; `None` for "auto".
    pub fn format(self) -> Option<Format> {
        match self {
            InputFormat::Auto => None,
            InputFormat::Tlog => Some(Format::Tlog),
            InputFormat::Csv => Some(Format::Csv),
            InputFormat::Bin => Some(Format::Bin),
            InputFormat::Ulg => Some(Format::Ulg),
        }
    }
}

impl Default for InputConfig {
    fn default() -> Self {
        InputConfig {
            format: InputFormat::Auto,
            instance: InstanceChoice::Auto,
            raw_imu_scale: RawImuScale::default(),
            csv: CsvMapping::default(),
            accel_units: AccelUnits::Auto,
        }
    }
}

/// Read and decode a log file (`.tlog`, `.csv`, `.csv.gz`). `format` overrides detection.
pub fn read_log(path: &Path, format: Option<Format>, cfg: &InputConfig) -> Result<Log, Error> {
    let bytes = std::fs::read(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    decode_log(&bytes, path, format, cfg)
}

/// Decode the bytes of a log file (gzip or not, tlog or CSV); `path` only names it in errors.
/// Any bytes give a log or an error, never a panic (fuzzed: `fuzz/fuzz_targets/tlog.rs`).
pub fn decode_log(
    bytes: &[u8],
    path: &Path,
    format: Option<Format>,
    cfg: &InputConfig,
) -> Result<Log, Error> {
    let mut samples = Vec::new();
    let mut log = decode_log_batched(bytes, path, format, cfg, &mut |batch| {
        samples.extend_from_slice(&batch.samples)
    })?;
    log.samples = samples;
    Ok(log)
}

/// Samples handed on while a log is decoded, with what is known so far. Its sample lists go
/// back to the decoder that made it when it is dropped ([`Recycled`]).
pub(crate) struct Batch {
    /// Samples of the primary instance.
    pub samples: Vec<Sample>,
    /// Samples of the other instances (MAVLink logs with `input.instance = "auto"`), with their
    /// index among [`Log::instances`].
    pub others: Vec<(usize, Sample)>,
    /// The instances read so far (names, units), indexed as in `others`.
    pub instances: Vec<InstanceInfo>,
    /// Units of the samples (fixed once the first sample is decoded).
    pub units: Units,
    /// Bytes of the (decompressed) log read so far, and in all.
    pub bytes_read: usize,
    pub bytes_total: usize,
    /// Where the lists go when the batch is dropped, if anywhere.
    recycle: Option<std::sync::Arc<Recycled>>,
}

impl Drop for Batch {
    fn drop(&mut self) {
        if let Some(r) = self.recycle.take() {
            r.give(
                std::mem::take(&mut self.samples),
                std::mem::take(&mut self.others),
            );
        }
    }
}

/// The sample lists of batches their consumer has dropped, for the decoder to fill again: a
/// long log then goes over in the same few lists, not in a fresh allocation per batch (whose
/// pages the kernel would map and zero again each time). At most [`RECYCLED_MAX`] of each are
/// kept; a consumer that keeps its batches simply leaves the decoder to allocate.
#[derive(Debug, Default)]
struct Recycled(std::sync::Mutex<RecycledLists>);

/// The lists [`Recycled`] keeps: of primary samples, and of the other instances' samples.
type RecycledLists = (Vec<Vec<Sample>>, Vec<Vec<(usize, Sample)>>);

/// Lists of each kind [`Recycled`] keeps.
const RECYCLED_MAX: usize = 8;

impl Recycled {
    fn give(&self, mut samples: Vec<Sample>, mut others: Vec<(usize, Sample)>) {
        // A poisoned lock (a panic elsewhere) only means the lists are not reused.
        let Ok(mut kept) = self.0.lock() else {
            return;
        };
        if samples.capacity() > 0 && kept.0.len() < RECYCLED_MAX {
            samples.clear();
            kept.0.push(samples);
        }
        if others.capacity() > 0 && kept.1.len() < RECYCLED_MAX {
            others.clear();
            kept.1.push(others);
        }
    }

    /// An empty list for primary samples, with room for `room` of them.
    fn samples(&self, room: usize) -> Vec<Sample> {
        let mut v = self
            .0
            .lock()
            .ok()
            .and_then(|mut kept| kept.0.pop())
            .unwrap_or_default();
        v.reserve(room);
        v
    }

    /// An empty list for the other instances' samples.
    fn others(&self) -> Vec<(usize, Sample)> {
        self.0
            .lock()
            .ok()
            .and_then(|mut kept| kept.1.pop())
            .unwrap_or_default()
    }
}

/// Samples per [`Batch`]: few enough that the consumer starts soon after the decoding does, and
/// that the batches in flight stay in the processor's caches between the two.
pub(crate) const BATCH_SAMPLES: usize = 1024;

/// Gathers decoded samples into [`Batch`]es of [`BATCH_SAMPLES`]: the primary instance's in
/// `samples`, the others' in `others`.
struct Batcher {
    samples: Vec<Sample>,
    others: Vec<(usize, Sample)>,
    /// The lists of the batches dropped, to fill again.
    recycled: std::sync::Arc<Recycled>,
    /// A primary sample was handed on.
    any: bool,
}

impl Batcher {
    fn new() -> Batcher {
        Batcher {
            samples: Vec::with_capacity(BATCH_SAMPLES),
            others: Vec::new(),
            recycled: std::sync::Arc::default(),
            any: false,
        }
    }

    /// Take a sample of instance `k`; true when a batch is full.
    fn push(&mut self, k: usize, s: Sample, primary: Option<usize>) -> bool {
        if Some(k) == primary {
            self.samples.push(s);
        } else {
            self.others.push((k, s));
        }
        self.samples.len() + self.others.len() >= BATCH_SAMPLES
    }

    /// Hand on what was gathered (nothing when empty).
    fn flush(
        &mut self,
        sink: &mut dyn FnMut(Batch),
        info: (Vec<InstanceInfo>, Units),
        read: (usize, usize),
    ) {
        if self.samples.is_empty() && self.others.is_empty() {
            return;
        }
        self.any |= !self.samples.is_empty();
        let samples = self.recycled.samples(BATCH_SAMPLES);
        let others = if self.others.is_empty() {
            Vec::new()
        } else {
            self.recycled.others()
        };
        sink(Batch {
            samples: std::mem::replace(&mut self.samples, samples),
            others: std::mem::replace(&mut self.others, others),
            instances: info.0,
            units: info.1,
            bytes_read: read.0,
            bytes_total: read.1,
            recycle: Some(self.recycled.clone()),
        });
    }
}

/// As [`decode_log`], handing the samples on in batches of [`BATCH_SAMPLES`] as they are decoded
/// (a tlog; a CSV comes as one batch), so a consumer can work while decoding goes on. The returned
/// [`Log`] has everything but the samples.
pub(crate) fn decode_log_batched(
    bytes: &[u8],
    path: &Path,
    format: Option<Format>,
    cfg: &InputConfig,
    sink: &mut dyn FnMut(Batch),
) -> Result<Log, Error> {
    let data = maybe_gunzip(bytes).map_err(|e| Error::Format {
        path: path.to_path_buf(),
        message: format!("gzip: {e}"),
    })?;
    let format = log_format(&data, path, format, cfg)?;
    match format {
        Format::Tlog => {
            let mut conv = tlog_converter(cfg);
            let date = tlog_prescan(crate::io::decode::TlogRecords::new(&data), &mut conv);
            let total = data.len();
            let mut b = Batcher::new();
            decode_tlog_with(&data, &mut conv, &mut |k, s, read, conv| {
                if b.push(k, s, conv.primary_index()) {
                    // Units are fixed by the instance, which the first sample locked.
                    b.flush(sink, (conv.instances(), conv.units()), (read, total));
                }
            });
            b.flush(sink, (conv.instances(), conv.units()), (total, total));
            tlog_log(conv, date, b.any, path)
        }
        Format::Csv => {
            let text = String::from_utf8_lossy(&data);
            let mut stats = DecodeStats::default();
            let samples =
                decode_csv(&text, &cfg.csv, &mut stats).map_err(|message| Error::Format {
                    path: path.to_path_buf(),
                    message,
                })?;
            let accel_units = match cfg.accel_units {
                AccelUnits::Counts => Unit::Counts,
                AccelUnits::Auto | AccelUnits::Si => Unit::Si,
            };
            let units = Units {
                accel: accel_units,
                gyro: Unit::Si,
                mag: Unit::Si,
            };
            sink(Batch {
                samples,
                others: Vec::new(),
                instances: Vec::new(),
                units,
                bytes_read: data.len(),
                bytes_total: data.len(),
                recycle: None,
            });
            Ok(Log {
                format,
                samples: Vec::new(),
                stats,
                instance: None,
                instances: Vec::new(),
                units,
                flight: None,
                telemetry_onboard: None,
                date: None,
            })
        }
        Format::Bin | Format::Ulg => decode_flight_log(&data, path, format, sink),
    }
}

/// Bytes of a file's (gunzipped) content read ahead to tell its format.
const HEAD_BYTES: usize = 64 * 1024;

/// A file opened for streaming: the first [`HEAD_BYTES`] of its content (gunzipped when it is
/// gzip) to tell its format by, and a reader of the whole content from its start.
struct Opened {
    head: Vec<u8>,
    reader: Box<dyn std::io::Read>,
    /// Bytes of the file read so far (compressed ones for a gzip file), and its length.
    read: std::rc::Rc<std::cell::Cell<u64>>,
    total: u64,
}

/// A reader that counts the bytes read through it.
struct Counted<R> {
    inner: R,
    read: std::rc::Rc<std::cell::Cell<u64>>,
}

impl<R: std::io::Read> std::io::Read for Counted<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.read.set(self.read.get() + n as u64);
        Ok(n)
    }
}

/// Open `path` for streaming ([`Opened`]).
fn open_stream(path: &Path) -> Result<Opened, Error> {
    use std::io::{BufRead, Read};
    let read_err = |source| Error::Read {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(read_err)?;
    let total = file.metadata().map_err(read_err)?.len();
    let read = std::rc::Rc::new(std::cell::Cell::new(0));
    let counted = Counted {
        inner: file,
        read: read.clone(),
    };
    let mut buffered = std::io::BufReader::with_capacity(HEAD_BYTES, counted);
    let gzip = buffered
        .fill_buf()
        .map_err(read_err)?
        .starts_with(&[0x1F, 0x8B]);
    let mut content: Box<dyn Read> = if gzip {
        Box::new(flate2::read::MultiGzDecoder::new(buffered))
    } else {
        Box::new(buffered)
    };
    let mut head = Vec::with_capacity(HEAD_BYTES);
    match (&mut content)
        .take(HEAD_BYTES as u64)
        .read_to_end(&mut head)
    {
        Ok(_) => {}
        // A truncated .gz still yields what came before the cut.
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !head.is_empty() => {}
        Err(e) if gzip => {
            return Err(Error::Format {
                path: path.to_path_buf(),
                message: format!("gzip: {e}"),
            })
        }
        Err(e) => return Err(read_err(e)),
    }
    let reader = Box::new(std::io::Cursor::new(head.clone()).chain(content));
    Ok(Opened {
        head,
        reader,
        read,
        total,
    })
}

/// As [`decode_log_batched`], the file at `path` read as a stream (gunzipped when it is gzip):
/// a tlog, a DataFlash log and a ULog through a window of
/// [`crate::io::window::STREAM_CHUNK_BYTES`], so memory does not grow with the log's length; a
/// CSV is read whole. Progress counts the file's bytes.
pub(crate) fn decode_file_batched(
    path: &Path,
    format: Option<Format>,
    cfg: &InputConfig,
    sink: &mut dyn FnMut(Batch),
) -> Result<Log, Error> {
    let opened = open_stream(path)?;
    let format = log_format(&opened.head, path, format, cfg)?;
    let io_err = |e: std::io::Error| Error::Format {
        path: path.to_path_buf(),
        message: format!("reading: {e}"),
    };
    match format {
        Format::Tlog => {
            let mut conv = tlog_converter(cfg);
            let first = open_stream(path)?;
            let date = tlog_prescan(crate::io::decode::TlogStream::new(first.reader), &mut conv);
            let (read, total) = (opened.read.clone(), opened.total as usize);
            let mut records = crate::io::decode::TlogStream::new(opened.reader);
            let mut b = Batcher::new();
            let error = crate::io::decode::decode_tlog_stream(
                &mut records,
                &mut conv,
                &mut |k, s, _, conv| {
                    if b.push(k, s, conv.primary_index()) {
                        let at = (read.get() as usize).min(total);
                        b.flush(sink, (conv.instances(), conv.units()), (at, total));
                    }
                },
            );
            if let Some(e) = error {
                return Err(io_err(e));
            }
            b.flush(sink, (conv.instances(), conv.units()), (total, total));
            tlog_log(conv, date, b.any, path)
        }
        Format::Bin | Format::Ulg => {
            let (read, total) = (opened.read.clone(), opened.total as usize);
            let mut b = Batcher::new();
            let mut seen = 0usize;
            let mut emit = |k: usize, s: Sample, _: usize, primary: Option<usize>| {
                seen = seen.max(k + 1);
                if b.push(k, s, primary) {
                    let at = (read.get() as usize).min(total);
                    b.flush(sink, placeholder_instances(seen), (at, total));
                }
            };
            let decoded = match format {
                Format::Bin => Some(crate::io::flightlog::decode_dataflash_stream(
                    opened.reader,
                    &mut emit,
                )),
                _ => crate::io::flightlog::decode_ulog_stream(opened.reader, &mut emit),
            };
            let Some((flight, error)) = decoded else {
                return Err(not_ulog(path));
            };
            if let Some(e) = error {
                return Err(io_err(e));
            }
            b.flush(sink, placeholder_instances(seen), (total, total));
            flight_log(flight, format, b.any, path)
        }
        Format::Csv => {
            // (The file's size: read once into place, not grown and copied as it is read.)
            let mut data = Vec::with_capacity(usize::try_from(opened.total).unwrap_or(0));
            let mut reader = opened.reader;
            match std::io::Read::read_to_end(&mut reader, &mut data) {
                Ok(_) => {}
                Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !data.is_empty() => {}
                Err(e) => return Err(io_err(e)),
            }
            decode_log_batched(&data, path, Some(format), cfg, sink)
        }
    }
}

/// The format of a log whose content begins with `head`: the one asked for, else the
/// configured one, else detected; an error for a text file under a binary log's name (unless
/// asked for) and for content of no known format.
fn log_format(
    head: &[u8],
    path: &Path,
    format: Option<Format>,
    cfg: &InputConfig,
) -> Result<Format, Error> {
    if head.is_empty() {
        return Err(Error::Format {
            path: path.to_path_buf(),
            message: "the file is empty (0 bytes): was the log still being written, or copied before it was closed?".into(),
        });
    }
    let chosen = format.or(cfg.format.format());
    if chosen.is_none() && detect_format(head) == Some(Format::Csv) {
        // A binary log's name on a text file: say so rather than read it as CSV unasked.
        let name = path.display().to_string().to_ascii_lowercase();
        if let Some(ext) = [".tlog", ".bin", ".ulg"]
            .iter()
            .find(|e| name.ends_with(*e))
        {
            return Err(Error::Format {
                path: path.to_path_buf(),
                message: format!(
                    "named {ext} but holds text: a CSV, or a log exported as text? Give --format csv to read it as CSV"
                ),
            });
        }
    }
    chosen.or_else(|| detect_format(head)).ok_or_else(|| Error::Format {
        path: path.to_path_buf(),
        message: "cannot tell the format: neither a MAVLink .tlog (u64 timestamp + frame), an ArduPilot DataFlash .bin, a PX4 .ulg nor CSV with a header row; use --format tlog|csv|bin|ulg".into(),
    })
}

/// The converter of a tlog's messages for `input`: every instance when it is "auto".
fn tlog_converter(cfg: &InputConfig) -> MessageConverter {
    let mut conv = MessageConverter::new(cfg.instance.clone(), cfg.raw_imu_scale)
        .with_ardupilot_mag(crate::io::decode::ArduPilotMag::Undo);
    if conv.choice == InstanceChoice::Auto {
        conv = conv.with_other_instances();
    }
    conv
}

/// The first records of a tlog: the vehicle's HEARTBEAT among the first
/// [`HEARTBEAT_SCAN_RECORDS`] into `conv` (its flight stack fixes RAW_IMU's units from the first
/// sample on), and the day of the first record. The clock that stamped the records is the
/// ground station's: a date, unless it counted from its own start.
fn tlog_prescan(
    mut records: impl Iterator<Item = (u64, crate::io::decode::Frame)>,
    conv: &mut MessageConverter,
) -> Option<crate::types::LogDate> {
    let first = records.next();
    let date = first.as_ref().and_then(|(ts, _)| {
        crate::types::LogDate::from_unix_us(*ts, crate::types::DateSource::RecordClock)
    });
    let heartbeat = first
        .into_iter()
        .chain(records)
        .take(HEARTBEAT_SCAN_RECORDS)
        .find(|(_, f)| is_vehicle_heartbeat(&f.message));
    if let Some((ts, f)) = heartbeat {
        conv.convert_any(&f.message, ts);
    }
    date
}

/// A HEARTBEAT of a vehicle (an autopilot), not of a ground station.
fn is_vehicle_heartbeat(m: &mavlink::dialects::ardupilotmega::MavMessage) -> bool {
    matches!(m, mavlink::dialects::ardupilotmega::MavMessage::HEARTBEAT(h)
        if h.autopilot != mavlink::dialects::ardupilotmega::MavAutopilot::MAV_AUTOPILOT_INVALID)
}

/// The [`Log`] of a decoded tlog (without its samples), or the error of one with none of the
/// instance asked for.
fn tlog_log(
    conv: MessageConverter,
    date: Option<crate::types::LogDate>,
    any: bool,
    path: &Path,
) -> Result<Log, Error> {
    if !any {
        let what = match &conv.choice {
            InstanceChoice::Auto => {
                "no IMU message with a magnetometer (HIGHRES_IMU, SCALED_IMU*, RAW_IMU)".to_string()
            }
            InstanceChoice::Named(n) => {
                format!("no messages of instance `{n}` (set input.instance to one the log has)")
            }
        };
        return Err(Error::Format {
            path: path.to_path_buf(),
            message: format!("{what}{}", skipped_text(&conv.stats.skipped)),
        });
    }
    let units = conv.units();
    Ok(Log {
        format: Format::Tlog,
        samples: Vec::new(),
        instance: conv.instance().map(String::from),
        instances: conv.instances(),
        telemetry_onboard: conv.ardupilot_onboard(),
        date,
        stats: conv.stats,
        units,
        flight: None,
    })
}

/// Instance names of a flight-controller log are known only at its end: batches carry
/// placeholders for the `n` seen so far, with SI units (such logs are in physical units
/// throughout).
fn placeholder_instances(n: usize) -> (Vec<InstanceInfo>, Units) {
    let info = (0..n)
        .map(|k| InstanceInfo {
            name: format!("instance {k}"),
            compass_id: 0,
            samples: 0,
            units: Units::default(),
            time: Default::default(),
        })
        .collect();
    (info, Units::default())
}

/// The [`Log`] of a decoded flight-controller log (without its samples), or the error of one
/// with no samples.
fn flight_log(
    flight: crate::io::flightlog::FlightLog,
    format: Format,
    any: bool,
    path: &Path,
) -> Result<Log, Error> {
    if !any {
        let what = match format {
            Format::Bin => "no IMU or MAG record with a known layout (FMT) in the DataFlash log",
            _ => "no sensor_combined, vehicle_magnetometer or sensor_* data in the ULog file",
        };
        return Err(Error::Format {
            path: path.to_path_buf(),
            message: format!("{what}{}", skipped_text(&flight.stats.skipped)),
        });
    }
    Ok(Log {
        format,
        samples: Vec::new(),
        stats: flight.stats.clone(),
        instance: flight
            .primary
            .and_then(|k| flight.instances.get(k))
            .map(|i| i.name.clone()),
        instances: flight.instances.clone(),
        units: Units::default(),
        date: flight.date,
        flight: Some(flight),
        telemetry_onboard: None,
    })
}

/// A DataFlash or ULog file: samples of every instance handed on in batches, as for a tlog.
fn decode_flight_log(
    data: &[u8],
    path: &Path,
    format: Format,
    sink: &mut dyn FnMut(Batch),
) -> Result<Log, Error> {
    let total = data.len();
    let mut b = Batcher::new();
    let mut seen = 0usize;
    let mut emit = |k: usize, s: Sample, read: usize, primary: Option<usize>| {
        seen = seen.max(k + 1);
        if b.push(k, s, primary) {
            b.flush(sink, placeholder_instances(seen), (read, total));
        }
    };
    let flight = match format {
        Format::Bin => Some(crate::io::flightlog::decode_dataflash_with(data, &mut emit)),
        _ => crate::io::flightlog::decode_ulog_with(data, &mut emit),
    };
    let Some(flight) = flight else {
        return Err(not_ulog(path));
    };
    b.flush(sink, placeholder_instances(seen), (total, total));
    flight_log(flight, format, b.any, path)
}

/// The error of a file taken for a ULog file that does not begin as one.
fn not_ulog(path: &Path) -> Error {
    Error::Format {
        path: path.to_path_buf(),
        message: "not a ULog file (no `ULog` header)".into(),
    }
}

/// "; skipped: 12 bad_crc, 3 resync" for an error message, or nothing when nothing was skipped.
fn skipped_text(skipped: &std::collections::BTreeMap<String, u64>) -> String {
    if skipped.is_empty() {
        return String::new();
    }
    let parts: Vec<String> = skipped.iter().map(|(k, n)| format!("{n} {k}")).collect();
    format!("; skipped: {}", parts.join(", "))
}
