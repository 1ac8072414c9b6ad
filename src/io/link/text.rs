//! Text-line links: MotionCal's `Raw:` lines and CSV lines, cut from a byte stream with a bounded
//! line buffer.

use crate::io::decode::FIELDS as CSV_FIELDS;
use crate::types::{Sample, STANDARD_GRAVITY_MPS2};
use std::collections::BTreeMap;

/// MotionCal accelerometer counts per g.
pub(crate) const MOTIONCAL_ACCEL_COUNTS_PER_G: f64 = 8192.0;
/// MotionCal gyroscope counts per deg/s.
pub(crate) const MOTIONCAL_GYRO_COUNTS_PER_DPS: f64 = 16.0;
/// MotionCal magnetometer counts per uT.
pub(crate) const MOTIONCAL_MAG_COUNTS_PER_UT: f64 = 10.0;

/// Parse one MotionCal line `Raw:ax,ay,az,gx,gy,gz,mx,my,mz` (int16 counts) into a sample at
/// `t_s`: m/s^2, rad/s, uT. Anything else (`Uni:`, `Cal1:`, garbage, out-of-range numbers) is
/// `None`.
pub fn parse_motioncal_line(line: &str, t_s: f64) -> Option<Sample> {
    let body = line.trim().strip_prefix("Raw:")?;
    let mut v = [0.0f64; 9];
    let mut n = 0;
    for cell in body.split(',') {
        if n == 9 {
            return None;
        }
        let x: i16 = cell.trim().parse().ok()?;
        v[n] = x as f64;
        n += 1;
    }
    if n != 9 {
        return None;
    }
    let a = STANDARD_GRAVITY_MPS2 / MOTIONCAL_ACCEL_COUNTS_PER_G;
    let g = (1.0 / MOTIONCAL_GYRO_COUNTS_PER_DPS).to_radians();
    let m = 1.0 / MOTIONCAL_MAG_COUNTS_PER_UT;
    Some(Sample {
        t_s,
        accel_mps2: Some([v[0] * a, v[1] * a, v[2] * a]),
        gyro_rad_s: Some([v[3] * g, v[4] * g, v[5] * g]),
        mag_ut: Some([v[6] * m, v[7] * m, v[8] * m]),
        ..Default::default()
    })
}

/// Parser of [`Payload::Csv`] lines: numbers in a fixed field order, scaled.
#[derive(Debug, Clone)]
pub struct CsvLineParser {
    /// Per column: index into [`CSV_FIELDS`] and scale, or `None` for an ignored column.
    columns: Vec<Option<(usize, f64)>>,
    has_t: bool,
}

impl CsvLineParser {
    /// Unknown field names are ignored columns (see [`Payload::check`]).
    pub fn new(fields: &[String], scales: &BTreeMap<String, f64>) -> CsvLineParser {
        let columns: Vec<Option<(usize, f64)>> = fields
            .iter()
            .map(|f| {
                let i = CSV_FIELDS.iter().position(|k| *k == f.as_str())?;
                let s = scales
                    .get(f)
                    .copied()
                    .filter(|s| s.is_finite())
                    .unwrap_or(1.0);
                Some((i, s))
            })
            .collect();
        let has_t = columns.iter().any(|c| matches!(c, Some((0, _))));
        CsvLineParser { columns, has_t }
    }

    /// One line into a sample; `arrival_s` is its time when there is no `t` field. `None` for a
    /// line with the wrong number of cells, a non-number, a non-finite time or no sensor data.
    pub fn parse(&self, line: &str, arrival_s: f64) -> Option<Sample> {
        let mut vals = [None::<f64>; CSV_FIELDS.len()];
        let mut n = 0;
        for cell in line.trim().split(',') {
            let col = self.columns.get(n)?;
            n += 1;
            let c = cell.trim();
            let Some((i, scale)) = col else { continue };
            if c.is_empty() {
                continue;
            }
            vals[*i] = Some(c.parse::<f64>().ok()? * scale);
        }
        if n != self.columns.len() {
            return None;
        }
        let t_s = if self.has_t { vals[0]? } else { arrival_s };
        if !t_s.is_finite() {
            return None;
        }
        let s = crate::io::decode::sample_from_fields(t_s, &vals, None);
        (!s.is_empty()).then_some(s)
    }
}

/// Longest text line kept; a longer one is dropped (and counted) up to its newline.
pub const MAX_LINE: usize = 1024;

/// Splits a byte stream into lines across reads; strips CR of CRLF.
#[derive(Debug, Default)]
pub struct LineBuffer {
    buf: Vec<u8>,
    /// Inside an over-long line: drop bytes up to the next newline.
    discarding: bool,
}

impl LineBuffer {
    pub fn new() -> Self {
        Self::default()
    }

    /// Append bytes; return the complete lines and the number of over-long lines dropped.
    pub fn push(&mut self, bytes: &[u8]) -> (Vec<String>, u64) {
        let mut lines = Vec::new();
        let mut dropped = 0;
        let mut rest = bytes;
        while let Some(i) = rest.iter().position(|b| *b == b'\n') {
            if self.discarding {
                self.discarding = false;
            } else if self.buf.len() + i > MAX_LINE {
                // Over-long even though its start fitted in an earlier read (found by fuzzing).
                dropped += 1;
            } else {
                self.buf.extend_from_slice(&rest[..i]);
                lines.push(Self::text(&self.buf));
            }
            self.buf.clear();
            rest = &rest[i + 1..];
        }
        if !self.discarding {
            self.buf.extend_from_slice(rest);
            if self.buf.len() > MAX_LINE {
                self.buf.clear();
                self.discarding = true;
                dropped += 1;
            }
        }
        (lines, dropped)
    }

    /// The unterminated rest, if any (a datagram's last line).
    pub fn take_partial(&mut self) -> Option<String> {
        let was_discarding = std::mem::take(&mut self.discarding);
        if self.buf.is_empty() || was_discarding {
            self.buf.clear();
            return None;
        }
        let s = Self::text(&self.buf);
        self.buf.clear();
        Some(s)
    }

    fn text(b: &[u8]) -> String {
        let b = b.strip_suffix(b"\r").unwrap_or(b);
        String::from_utf8_lossy(b).into_owned()
    }
}

/// Text line parsers by payload.
#[derive(Debug, Clone)]
pub(crate) enum LineParser {
    MotionCal,
    Csv(CsvLineParser),
}
