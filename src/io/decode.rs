//! Decoding bytes into [`Sample`](crate::types::Sample)s: MAVLink frames (live links and
//! `.tlog` files) and CSV text. Pure functions over byte slices; the transports live in `sources`.
//!
//! Every kind of bad input is counted by reason in [`DecodeStats`] and skipped, never fatal:
//! `bad_crc`, `truncated`, `resync` (garbage bytes between frames), `unknown_message` (an id this
//! dialect does not know), `bad_payload`, `non_finite`, `bad_row`, `other_instance`.
//!
//! The parts: `stats` (the counts), `frame` (MAVLink framing), `convert` (messages to samples),
//! `tlog` (the `.tlog` reader), `csv` (the CSV reader); here, the formats and how a file's is told.

mod convert;
mod csv;
mod frame;
mod stats;
#[cfg(test)]
pub(crate) mod tests;
mod tlog;

pub use convert::*;
pub use csv::*;
pub use frame::*;
pub use stats::*;
pub use tlog::*;

use serde::{Deserialize, Serialize};

/// Decompress if gzip, else borrow.
pub fn maybe_gunzip(bytes: &[u8]) -> std::io::Result<std::borrow::Cow<'_, [u8]>> {
    if bytes.len() >= 2 && bytes[0] == 0x1F && bytes[1] == 0x8B {
        use std::io::Read;
        let mut out = Vec::new();
        let mut d = flate2::read::MultiGzDecoder::new(bytes);
        match d.read_to_end(&mut out) {
            Ok(_) => {}
            // A truncated .gz still yields what came before the cut.
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !out.is_empty() => {}
            Err(e) => return Err(e),
        }
        Ok(std::borrow::Cow::Owned(out))
    } else {
        Ok(std::borrow::Cow::Borrowed(bytes))
    }
}

/// Input formats (also the command line's `--format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    Tlog,
    Csv,
    /// ArduPilot DataFlash log (.bin)
    Bin,
    /// PX4 ULog (.ulg)
    Ulg,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Tlog => "tlog",
            Format::Csv => "csv",
            Format::Bin => "bin",
            Format::Ulg => "ulg",
        }
    }
}

/// Detect the format from content: a tlog has a MAVLink magic byte after its first 8-byte
/// timestamp; CSV is text whose first line has a comma; a ULog file starts with its magic; a
/// DataFlash log has an FMT record defining FMT in its first bytes.
pub fn detect_format(bytes: &[u8]) -> Option<Format> {
    if crate::io::flightlog::ulog::looks_like(bytes) {
        return Some(Format::Ulg);
    }
    if crate::io::flightlog::dataflash::looks_like(bytes) {
        return Some(Format::Bin);
    }
    if bytes.len() > 9 && (bytes[8] == V1_MAGIC || bytes[8] == V2_MAGIC) {
        return Some(Format::Tlog);
    }
    let head = &bytes[..bytes.len().min(4096)];
    let text = String::from_utf8_lossy(head);
    let first = text
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))?;
    if first.contains(',')
        && first
            .chars()
            .all(|c| !c.is_control() || c == '\t' || c == '\r')
    {
        return Some(Format::Csv);
    }
    None
}
