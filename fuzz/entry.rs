// The fuzz targets' bodies: one function per target, on arbitrary bytes. Each calls the library
// as the daemon and the CLI do and asserts what must hold for any input (a panic is a finding).
// Shared by fuzz/fuzz_targets/*.rs (`#[path]` module) and by the regression test
// `fuzz_regressions` in tests/main.rs (`include!`), so both run the same entry points.
// Plain `//` comments only: this file is `include!`d.

use imucald::config::Config;
use imucald::io::decode::TlogRecords;
use imucald::io::decode::{
    decode_csv, decode_tlog, detect_format, maybe_gunzip, CsvMapping, DecodeStats, FrameDecoder,
    InstanceChoice, MessageConverter, RawImuScale,
};
use imucald::io::link::{parse_motioncal_line, CsvLineParser, LineBuffer, MAX_LINE};
use imucald::types::Sample;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

// Cut a stream into chunks as a serial port or socket would deliver it: the first byte chooses the
// chunk sizes (1..=256, varying chunk to chunk), the rest is the stream.
pub fn chunks(data: &[u8]) -> (Vec<&[u8]>, &[u8]) {
    let Some((&k, stream)) = data.split_first() else {
        return (Vec::new(), data);
    };
    let mut out = Vec::new();
    let mut rest = stream;
    let mut i = 0usize;
    while !rest.is_empty() {
        let n = 1 + (usize::from(k).wrapping_mul(i + 7) ^ i) % 256;
        let (a, b) = rest.split_at(n.min(rest.len()));
        out.push(a);
        rest = b;
        i += 1;
    }
    (out, stream)
}

// Every number a sample carries is finite.
pub fn check_sample(s: &Sample) {
    assert!(s.t_s.is_finite(), "{s:?}");
    for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut].into_iter().flatten() {
        assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
    }
    for x in [s.temp_c, s.throttle, s.current_a].into_iter().flatten() {
        assert!(x.is_finite(), "{s:?}");
    }
    if let Some(q) = s.ref_q {
        assert!(q.iter().all(|x| x.is_finite()), "{s:?}");
    }
}

fn converter(kind: usize) -> MessageConverter {
    // Vary the instance choice with the input so every IMU message kind is taken somewhere.
    let scale = RawImuScale {
        accel: 9.80665 / 4096.0,
        gyro: 0.0,
        mag: 0.1,
    };
    match kind % 5 {
        0 => MessageConverter::new(InstanceChoice::Auto, RawImuScale::default()),
        1 => MessageConverter::new(InstanceChoice::Named("highres_imu:0".into()), scale),
        2 => MessageConverter::new(InstanceChoice::Named("raw_imu:0".into()), scale),
        3 => MessageConverter::new(InstanceChoice::Named("scaled_imu2".into()), scale),
        _ => MessageConverter::new(InstanceChoice::Auto, scale),
    }
}

// Target `tlog`: the log-file readers on arbitrary bytes. `sources::decode_log` (gunzip, format
// detection, tlog or CSV, as `imucald replay` reads a file), then `decode_tlog` forced on the
// (gunzipped) bytes, checked against the records of `decode::TlogRecords` converted one by one.
// Returns the samples of the forced tlog decode and its stats.
pub fn tlog(data: &[u8]) -> (Vec<Sample>, DecodeStats) {
    static CFG: OnceLock<Config> = OnceLock::new();
    let cfg = CFG.get_or_init(Config::default);
    if let Ok(log) = imucald::io::sources::decode_log(data, Path::new("fuzz.tlog"), None, &cfg.input) {
        assert_eq!(log.samples.len() as u64, log.stats.records);
        log.samples.iter().for_each(check_sample);
    }
    let Ok(bytes) = maybe_gunzip(data) else {
        return (Vec::new(), DecodeStats::default());
    };
    let _ = detect_format(&bytes);
    let mut conv = converter(data.len());
    let samples = decode_tlog(&bytes, &mut conv);
    assert_eq!(samples.len() as u64, conv.stats.records);
    samples.iter().for_each(check_sample);
    // The replay link reads the same records as the offline reader.
    let mut conv2 = converter(data.len());
    let replayed: Vec<Sample> = TlogRecords::new(&bytes)
        .filter_map(|(ts, f)| conv2.convert(&f.message, ts))
        .collect();
    assert_eq!(samples, replayed);
    (samples, conv.stats)
}

// Target `mavlink_frames`: the live MAVLink path. `FrameDecoder::push` on a stream cut into chunks
// (as serial and TCP reads deliver it), then every frame through `MessageConverter::convert`, as
// link.rs and daemon.rs do. Returns the frames' count and the samples of the `Auto` converter.
pub fn mavlink_frames(data: &[u8]) -> (usize, Vec<Sample>) {
    let (chunks, stream) = chunks(data);
    let mut dec = FrameDecoder::new();
    let mut frames = Vec::new();
    for c in &chunks {
        frames.extend(dec.push(c));
    }
    // The frames do not depend on how the stream was cut.
    let once = FrameDecoder::new().push(stream);
    assert_eq!(frames.len(), once.len());
    for (a, b) in frames.iter().zip(&once) {
        assert_eq!((a.system_id, a.component_id), (b.system_id, b.component_id));
        assert_eq!(format!("{:?}", a.message), format!("{:?}", b.message));
    }
    let scale = RawImuScale {
        accel: 1e-3,
        gyro: 1e-3,
        mag: 0.1,
    };
    let mut auto_samples = Vec::new();
    for choice in [
        InstanceChoice::Auto,
        InstanceChoice::Named("raw_imu:0".into()),
    ] {
        let auto = choice == InstanceChoice::Auto;
        let mut conv = MessageConverter::new(choice, scale);
        // Receive times as the daemon gives them: a clock that moves on.
        let mut time_us = 1_700_000_000_000_000u64;
        for f in &frames {
            time_us += 1000;
            if let Some(s) = conv.convert(&f.message, time_us) {
                check_sample(&s);
                if auto {
                    auto_samples.push(s);
                }
            }
        }
        let _ = conv.units();
    }
    (frames.len(), auto_samples)
}

fn user_mapping() -> CsvMapping {
    CsvMapping::from_pairs(
        &[
            ("t", "time_ms"),
            ("ax", "AccX"),
            ("ay", "AccY"),
            ("az", "AccZ"),
            ("mx", "MagX"),
            ("my", "MagY"),
            ("mz", "MagZ"),
        ],
        &[
            ("t", 0.001),
            ("ax", 9.80665),
            ("ay", 9.80665),
            ("az", 9.80665),
            ("gx", 1e300),
        ],
    )
}

// Target `csv`: `decode::decode_csv` on arbitrary text, with the default column names and with a
// user mapping (renamed columns, unit scales). Returns what the default mapping gave.
pub fn csv(data: &[u8]) -> Result<(Vec<Sample>, DecodeStats), String> {
    static MAPS: OnceLock<[CsvMapping; 2]> = OnceLock::new();
    let maps = MAPS.get_or_init(|| [CsvMapping::default(), user_mapping()]);
    let text = String::from_utf8_lossy(data);
    let mut first = None;
    for m in maps {
        let mut stats = DecodeStats::default();
        let r = decode_csv(&text, m, &mut stats);
        match &r {
            Ok(samples) => {
                assert_eq!(samples.len() as u64, stats.records);
                for s in samples {
                    assert!(!s.is_empty(), "{s:?}");
                    check_sample(s);
                }
            }
            Err(e) => assert!(!e.is_empty()),
        }
        first.get_or_insert(r.map(|s| (s, stats)));
    }
    first.expect("two mappings")
}

fn line_parsers() -> Vec<CsvLineParser> {
    let f = |names: &[&str]| names.iter().map(|s| s.to_string()).collect::<Vec<String>>();
    let mut scales = BTreeMap::new();
    for k in ["ax", "ay", "az"] {
        scales.insert(k.to_string(), 9.80665);
    }
    scales.insert("gx".to_string(), f64::NAN);
    scales.insert("t".to_string(), 1e-3);
    vec![
        CsvLineParser::new(
            &f(&["ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz"]),
            &scales,
        ),
        CsvLineParser::new(&f(&["t", "ax", "ay", "az", "_", "mx", "my", "mz"]), &scales),
        CsvLineParser::new(
            &f(&[
                "t", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz", "temp", "throttle",
                "current", "ref_qw", "ref_qx", "ref_qy", "ref_qz", "moving",
            ]),
            &BTreeMap::new(),
        ),
        CsvLineParser::new(&f(&["mx", "", "my", "bogus", "mz"]), &BTreeMap::new()),
    ]
}

// Target `serial_lines`: `link::LineBuffer` over a chunked byte stream, then each line through
// `parse_motioncal_line` and `CsvLineParser::parse` (four column layouts). Returns the lines and
// how many MotionCal lines parsed.
pub fn serial_lines(data: &[u8]) -> (Vec<String>, usize) {
    static PARSERS: OnceLock<Vec<CsvLineParser>> = OnceLock::new();
    let parsers = PARSERS.get_or_init(line_parsers);
    let (chunks, _) = chunks(data);
    let mut buf = LineBuffer::new();
    let mut lines = Vec::new();
    for c in &chunks {
        let (got, _dropped) = buf.push(c);
        lines.extend(got);
    }
    lines.extend(buf.take_partial());
    let mut motioncal = 0;
    for (i, line) in lines.iter().enumerate() {
        // Over-long lines are dropped, never handed on.
        assert!(
            line.chars().count() <= MAX_LINE,
            "line of {} chars",
            line.chars().count()
        );
        let t = i as f64 * 0.01;
        if let Some(s) = parse_motioncal_line(line, t) {
            motioncal += 1;
            check_sample(&s);
            assert_eq!(s.t_s, t);
            // int16 counts: at most 4 g per axis.
            let a = s.accel_mps2.expect("accel");
            assert!(a.iter().all(|x| x.abs() <= 4.0 * 9.80665 + 1e-9), "{a:?}");
        }
        for p in parsers {
            if let Some(s) = p.parse(line, t) {
                assert!(!s.is_empty(), "{s:?}");
                check_sample(&s);
            }
        }
    }
    (lines, motioncal)
}

// Target `config`: `Config::from_toml_str` on arbitrary text, then `validate()`. A config is
// accepted whole and valid, or refused with `Error::Config` naming a key.
pub fn config(data: &[u8]) -> Result<Config, (String, String)> {
    let Ok(text) = std::str::from_utf8(data) else {
        return Err(("utf-8".into(), "not UTF-8 text".into()));
    };
    match Config::from_toml_str(text) {
        Ok(cfg) => {
            cfg.validate().expect("an accepted config validates");
            let _ = cfg.declination_deg();
            for s in &cfg.daemon.sources {
                imucald::io::link::Address::parse(&s.address).expect("validated address");
            }
            Ok(cfg)
        }
        Err(imucald::Error::Config { key, message }) => {
            assert!(
                !key.is_empty() && !message.is_empty(),
                "{key:?}: {message:?}"
            );
            Err((key, message))
        }
        Err(other) => panic!("not a config error: {other}"),
    }
}

// Check a flight-log decode: every sample is finite, each instance's count is what the summary
// says, and the primary's count is its `records`.
pub fn check_flight(log: &imucald::io::flightlog::FlightLog, per_instance: &[u64], primary: u64) {
    assert!(per_instance.len() <= log.instances.len());
    for (k, i) in log.instances.iter().enumerate() {
        assert_eq!(
            i.samples,
            per_instance.get(k).copied().unwrap_or(0),
            "{}",
            i.name
        );
    }
    assert_eq!(log.stats.records, primary);
    for c in log.onboard.mag.iter().chain(&log.onboard.accel) {
        assert!(
            c.offset.iter().all(|x| x.is_finite()) || c.params.values().any(|v| !v.is_finite())
        );
    }
}

// A flight-log decoder: `flightlog::decode_dataflash_with` or `decode_ulog_with`.
pub type FlightDecode = fn(
    &[u8],
    &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> Option<imucald::io::flightlog::FlightLog>;

pub fn decode_flight(
    f: FlightDecode,
    bytes: &[u8],
) -> Option<(imucald::io::flightlog::FlightLog, Vec<Sample>)> {
    let mut per_instance = Vec::<u64>::new();
    let mut primary = Vec::new();
    let mut last_read = 0usize;
    let log = f(bytes, &mut |k, s, read, p| {
        check_sample(&s);
        assert!(read >= last_read && read <= bytes.len());
        last_read = read;
        if per_instance.len() <= k {
            per_instance.resize(k + 1, 0);
        }
        per_instance[k] += 1;
        if Some(k) == p {
            primary.push(s);
        }
    })?;
    check_flight(&log, &per_instance, primary.len() as u64);
    Some((log, primary))
}

pub fn dataflash_some(
    bytes: &[u8],
    emit: &mut dyn FnMut(usize, Sample, usize, Option<usize>),
) -> Option<imucald::io::flightlog::FlightLog> {
    Some(imucald::io::flightlog::decode_dataflash_with(bytes, emit))
}

// Target `dataflash`: the DataFlash reader on arbitrary bytes (records in order: each payload its
// format's length, positions moving on), the conversion to samples of every instance, and
// `sources::decode_log` forced to `bin`. Returns the primary's samples.
pub fn dataflash(data: &[u8]) -> Vec<Sample> {
    static CFG: OnceLock<Config> = OnceLock::new();
    let cfg = CFG.get_or_init(Config::default);
    let mut rd = imucald::io::flightlog::dataflash::DfReader::new(data);
    let mut pos = 0;
    while let Some(rec) = rd.next_record() {
        assert_eq!(rec.payload.len() + 3, rec.format.length);
        for k in 0..rec.format.columns.len() {
            let _ = rec.value(k);
        }
        let _ = (rec.time_us(), rec.instance());
        let p = rd.position();
        assert!(p > pos && p <= data.len());
        pos = p;
    }
    let (_, samples) = decode_flight(dataflash_some, data).expect("DataFlash always decodes");
    if let Ok(log) = imucald::io::sources::decode_log(
        data,
        Path::new("fuzz.bin"),
        Some(imucald::io::decode::Format::Bin),
        &cfg.input,
    ) {
        assert_eq!(log.samples, samples);
    }
    samples
}

// Target `ulog`: the ULog reader on arbitrary bytes after a valid 16-byte header (every field of
// every data record read), the conversion to samples of every instance, and
// `sources::decode_log` forced to `ulg`. Returns the primary's samples.
pub fn ulog(data: &[u8]) -> Vec<Sample> {
    static CFG: OnceLock<Config> = OnceLock::new();
    let cfg = CFG.get_or_init(Config::default);
    let owned;
    let bytes: &[u8] = if imucald::io::flightlog::ulog::looks_like(data) {
        data
    } else {
        let mut v = imucald::io::flightlog::ulog::MAGIC.to_vec();
        v.extend([1, 0, 0, 0, 0, 0, 0, 0, 0]);
        v.extend_from_slice(data);
        owned = v;
        &owned
    };
    if let Some(mut rd) = imucald::io::flightlog::ulog::UlogReader::new(bytes) {
        let mut pos = rd.position();
        while let Some(d) = rd.next_data() {
            for k in 0..d.sub.fields.len() {
                let _ = d.value(k);
            }
            let _ = d.timestamp_us();
            let p = rd.position();
            assert!(p > pos && p <= bytes.len());
            pos = p;
        }
        assert!(rd.params().len() <= imucald::io::flightlog::ulog::MAX_PARAMS);
    }
    let samples = match decode_flight(imucald::io::flightlog::decode_ulog_with, bytes) {
        Some((_, s)) => s,
        None => Vec::new(),
    };
    if let Ok(log) = imucald::io::sources::decode_log(
        bytes,
        Path::new("fuzz.ulg"),
        Some(imucald::io::decode::Format::Ulg),
        &cfg.input,
    ) {
        assert_eq!(log.samples, samples);
    }
    samples
}
