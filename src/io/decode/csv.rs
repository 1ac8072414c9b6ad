//! CSV text to samples: imucald's own columns or a user's, mapped and scaled ([`CsvMapping`]),
//! with the rate from the file's preamble when it has no time column ([`decode_csv`]).

use super::stats::DecodeStats;
use crate::io::clock::{ClockSettings, SourceClock};
use crate::types::{Sample, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

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

/// Decode CSV text (header row first; blank lines and `#` lines before it are skipped). Cells
/// may be quoted (RFC 4180). Columns may come in any order and subset; empty cells mean "no
/// reading". Rows with the wrong number of cells or unparsable numbers are counted and skipped.
/// In steps: the header ([`csv_header`]), the fields' columns ([`field_columns`]), the rows'
/// period when there is no time column ([`row_period_s`]), then the rows ([`read_rows`]).
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
    let idx = field_columns(&cols, mapping, header)?;
    let layout = RowLayout {
        idx,
        width: cols.len(),
        row_period_s: row_period_s(&idx, mapping, preamble_rate_hz, header)?,
        scale: FIELDS
            .iter()
            .map(|f| mapping.scales.get(*f).copied().unwrap_or(1.0))
            .collect(),
    };
    Ok(read_rows(&mut rows, &layout, stats))
}

/// Each field's column in the header `cols` (`usize::MAX`: none), by the mapping's name for it or
/// its own; an error when the mapping names an unknown field or a column not in the header, or
/// when no sensor column is found.
fn field_columns(
    cols: &[String],
    mapping: &CsvMapping,
    header: &str,
) -> Result<[usize; FIELDS.len()], String> {
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
    if !(has_field(&idx, "ax") || has_field(&idx, "mx") || has_field(&idx, "gx")) {
        return Err(format!(
            "no sensor columns found in header `{header}`: expected ax/ay/az, gx/gy/gz or mx/my/mz, or a [input.csv] columns mapping"
        ));
    }
    Ok(idx)
}

/// Whether field `f` has a column in `idx` ([`field_columns`]).
fn has_field(idx: &[usize; FIELDS.len()], f: &str) -> bool {
    idx[FIELDS.iter().position(|x| *x == f).expect("field")] != usize::MAX
}

/// Row i's time step, s, when the file has no time column: from the mapping's rate, else the
/// preamble's; `None` with a time column; an error when neither gives a positive rate.
fn row_period_s(
    idx: &[usize; FIELDS.len()],
    mapping: &CsvMapping,
    preamble_rate_hz: Option<f64>,
    header: &str,
) -> Result<Option<f64>, String> {
    if has_field(idx, "t") {
        return Ok(None);
    }
    match mapping.rate_hz.or(preamble_rate_hz) {
        Some(r) if r.is_finite() && r > 0.0 => Ok(Some(1.0 / r)),
        Some(r) => Err(format!("the sample rate {r} Hz is not a positive number")),
        None => Err(format!(
            "no time column in header `{header}` and no sample rate: give the rate (`imucald replay --rate-hz 100`, or rate_hz = 100 under [input.csv]), or name the time column (t = \"your_column\" under [input.csv.columns])"
        )),
    }
}

/// How the data rows are read: each field's column ([`field_columns`]), the cells a row has,
/// the row period without a time column ([`row_period_s`]) and each field's scale.
struct RowLayout {
    idx: [usize; FIELDS.len()],
    width: usize,
    row_period_s: Option<f64>,
    scale: Vec<f64>,
}

/// The samples of the data rows, stamped by one clock (the `t` column is the message clock, kept
/// as the file has it; there is no receive clock). Bad rows, non-finite times and repeated rows
/// are counted and skipped; the clock's counts go into `stats.time`.
fn read_rows(
    rows: &mut csv::Reader<&[u8]>,
    layout: &RowLayout,
    stats: &mut DecodeStats,
) -> Vec<Sample> {
    let mut out = Vec::new();
    let mut clock = SourceClock::new(ClockSettings {
        keep_origin: true,
        ..ClockSettings::default()
    });
    let mut row = csv::StringRecord::new();
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
        let Some(vals) = row_values(&row, layout) else {
            stats.skip("bad_row");
            continue;
        };
        let t_s = match layout.row_period_s {
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
    out
}

/// A row's values per field, scaled (`None` for an empty cell or a field without a column);
/// `None` when the row has the wrong number of cells or a cell is not a number.
fn row_values(row: &csv::StringRecord, layout: &RowLayout) -> Option<[Option<f64>; FIELDS.len()]> {
    if row.len() != layout.width {
        return None;
    }
    let mut vals = [None::<f64>; FIELDS.len()];
    let mut bad = false;
    for fi in 0..FIELDS.len() {
        let ci = layout.idx[fi];
        if ci == usize::MAX {
            continue;
        }
        let c = &row[ci];
        if c.is_empty() {
            continue;
        }
        match c.parse::<f64>() {
            Ok(v) => vals[fi] = Some(v * layout.scale[fi]),
            Err(_) => bad = true,
        }
    }
    (!bad).then_some(vals)
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
