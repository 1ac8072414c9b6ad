//! `.tlog` files (each record a big-endian u64 of microseconds, then one raw MAVLink frame):
//! records from whole bytes ([`TlogRecords`]) or from a stream through a bounded window
//! ([`TlogStream`]), and their samples ([`decode_tlog`]).

use super::convert::MessageConverter;
use super::frame::{parse_frame, Frame, FrameParse, V1_MAGIC, V2_MAGIC};
use super::stats::DecodeStats;
use crate::types::Sample;

/// Read a whole `.tlog` (each record: big-endian u64 microseconds, then one raw frame) into samples.
/// Garbage between records, damaged frames and a truncated tail are counted and skipped.
pub fn decode_tlog(bytes: &[u8], conv: &mut MessageConverter) -> Vec<Sample> {
    let mut out = Vec::new();
    decode_tlog_with(bytes, conv, &mut |k, s, _, conv| {
        if Some(k) == conv.primary_index() {
            out.push(s)
        }
    });
    out
}

/// As [`decode_tlog`], handing each sample of every instance the converter takes to
/// `emit(instance_index, sample, bytes_read_so_far, converter)` as it is decoded.
pub(crate) fn decode_tlog_with(
    bytes: &[u8],
    conv: &mut MessageConverter,
    emit: &mut dyn FnMut(usize, Sample, usize, &MessageConverter),
) {
    let mut records = TlogRecords::new(bytes);
    while let Some((ts, f)) = records.next() {
        if let Some((k, s)) = conv.convert_any(&f.message, ts) {
            emit(k, s, records.position(), conv);
        }
    }
    for (why, n) in &records.stats.skipped {
        conv.stats.skip_n(why, *n);
    }
}

/// The `.tlog` reader, for `replay` and the live `file:` link alike: records (record time in us,
/// frame), each a big-endian u64 timestamp then one raw MAVLink frame. Garbage between records and
/// damaged frames are skipped (resynchronising on the next good record) and a truncated tail
/// ends the log, each counted in `stats.skipped`; `stats.records` counts frames.
pub struct TlogRecords<'a> {
    bytes: &'a [u8],
    cursor: TlogCursor,
    pub stats: DecodeStats,
}

/// Where a tlog reader is in its bytes, and what it knows there.
#[derive(Debug, Clone, Copy)]
struct TlogCursor {
    /// Offset of the next record.
    pos: usize,
    last_ts: Option<u64>,
    /// More bytes follow the bytes read (a window of a [`TlogStream`]): nothing within
    /// [`TLOG_LOOKAHEAD`] of their end is decided on, and their end is no truncation.
    more: bool,
    /// A resynchronisation reached the end of the window: the next window goes on with it.
    resyncing: bool,
}

impl TlogCursor {
    fn new(more: bool) -> TlogCursor {
        TlogCursor {
            pos: 0,
            last_ts: None,
            more,
            resyncing: false,
        }
    }
}

/// Bytes a window of a stream keeps beyond the last offset it decides on: a resynchronisation
/// checks a whole record and the next, each a timestamp and a frame of at most
/// [`MAX_FRAME_BYTES`].
const TLOG_LOOKAHEAD: usize = 2 * (8 + MAX_FRAME_BYTES) + 8;

/// The longest MAVLink frame: a v2 header of 10 bytes, 255 of payload, a CRC and a 13-byte signature.
const MAX_FRAME_BYTES: usize = 280;

/// How far from the last record time a resynchronisation trusts a timestamp on its own, us.
const RESYNC_NEAR_US: u64 = 86_400_000_000;

impl<'a> TlogRecords<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        TlogRecords {
            bytes,
            cursor: TlogCursor::new(false),
            stats: DecodeStats::default(),
        }
    }

    /// Bytes read so far.
    pub fn position(&self) -> usize {
        self.cursor.pos
    }
}

/// A tlog reader's bytes with its cursor and counts, borrowed for one step: [`TlogRecords`] and
/// [`TlogStream`] read through it alike.
struct TlogReader<'a> {
    bytes: &'a [u8],
    cursor: &'a mut TlogCursor,
    stats: &'a mut DecodeStats,
}

impl TlogReader<'_> {
    /// The offset up to which records are read: the end, or short of it by [`TLOG_LOOKAHEAD`]
    /// when more bytes follow.
    fn limit(&self) -> usize {
        if self.cursor.more {
            self.bytes.len().saturating_sub(TLOG_LOOKAHEAD)
        } else {
            self.bytes.len()
        }
    }

    fn ts_at(&self, p: usize) -> u64 {
        let mut b = [0u8; 8];
        b.copy_from_slice(&self.bytes[p..p + 8]);
        u64::from_be_bytes(b)
    }

    /// A whole record (timestamp and a frame that checks out) at `p`, and its length.
    fn record_at(&self, p: usize) -> Option<usize> {
        let rest = self.bytes.get(p + 8..).filter(|r| r.len() > 1)?;
        match parse_frame(rest) {
            FrameParse::Frame(_, n) if rest[0] == V1_MAGIC || rest[0] == V2_MAGIC => Some(8 + n),
            _ => None,
        }
    }

    /// The next offset from `from` that holds a good record: one whose timestamp is within a day
    /// of the last, or (two logs joined, days apart) one followed by another good record. A
    /// CRC-checked pair does not happen by chance in garbage.
    fn skip_to(&mut self, from: usize) {
        self.cursor.pos = self.resync(from);
        self.cursor.resyncing = self.cursor.more && self.cursor.pos >= self.limit();
    }

    fn resync(&self, from: usize) -> usize {
        let n = self.bytes.len();
        let end = self.limit();
        let mut p = from;
        while p < end && p + 9 < n {
            let m = self.bytes[p + 8];
            if m == V1_MAGIC || m == V2_MAGIC {
                if let Some(len) = self.record_at(p) {
                    let ts = self.ts_at(p);
                    let near = match self.cursor.last_ts {
                        Some(l) => ts.abs_diff(l) < RESYNC_NEAR_US,
                        None => ts > 0,
                    };
                    if near || self.record_at(p + len).is_some() {
                        return p;
                    }
                }
            }
            p += 1;
        }
        if self.cursor.more {
            p
        } else {
            n
        }
    }

    /// The next record, `None` at the end (of the window, when more bytes follow).
    fn next_record(&mut self) -> Option<(u64, Frame)> {
        let n = self.bytes.len();
        let end = self.limit();
        if self.cursor.resyncing {
            self.cursor.resyncing = false;
            self.skip_to(self.cursor.pos);
        }
        while self.cursor.pos < end && self.cursor.pos + 8 < n {
            let pos = self.cursor.pos;
            let ts = self.ts_at(pos);
            let rest = &self.bytes[pos + 8..];
            // Where a record is expected, a magic byte and a frame that checks out are enough:
            // its record time may be anything (logs joined with `cat` jump back by hours or
            // days); the source's clock sorts that out.
            if !(rest[0] == V1_MAGIC || rest[0] == V2_MAGIC) {
                self.stats.skip("resync");
                self.skip_to(pos + 1);
                continue;
            }
            match parse_frame(rest) {
                FrameParse::Frame(f, len) => {
                    self.cursor.last_ts = Some(ts);
                    self.cursor.pos += 8 + len;
                    self.stats.records += 1;
                    return Some((ts, f));
                }
                FrameParse::Incomplete => {
                    self.stats.skip("truncated");
                    self.cursor.pos = n;
                    return None;
                }
                FrameParse::Skip(len, why) => {
                    self.stats.skip(why.name());
                    if why.whole_frame() {
                        self.cursor.last_ts = Some(ts);
                        self.cursor.pos += 8 + len;
                    } else {
                        self.skip_to(pos + 1);
                    }
                }
            }
        }
        if !self.cursor.more && self.cursor.pos < n {
            self.stats.skip("truncated");
            self.cursor.pos = n;
        }
        None
    }
}

impl Iterator for TlogRecords<'_> {
    type Item = (u64, Frame);

    fn next(&mut self) -> Option<(u64, Frame)> {
        TlogReader {
            bytes: self.bytes,
            cursor: &mut self.cursor,
            stats: &mut self.stats,
        }
        .next_record()
    }
}

/// [`TlogRecords`] read from a stream (a file, gunzipped or not) through a window of about
/// [`crate::io::window::STREAM_CHUNK_BYTES`]: the same records and counts as from the whole bytes, in memory that
/// does not grow with the log. A read error ends the records and is kept ([`TlogStream::error`]).
pub(crate) struct TlogStream<R> {
    reader: R,
    buf: crate::io::window::StreamBuf,
    /// The cursor in `buf` (`more` until the stream's end), and the offset of `buf` in the stream.
    cursor: TlogCursor,
    base: usize,
    pub stats: DecodeStats,
    pub error: Option<std::io::Error>,
}

impl<R: std::io::Read> TlogStream<R> {
    pub fn new(reader: R) -> Self {
        TlogStream {
            reader,
            buf: crate::io::window::StreamBuf::with_capacity(
                crate::io::window::STREAM_CHUNK_BYTES + TLOG_LOOKAHEAD,
            ),
            cursor: TlogCursor::new(true),
            base: 0,
            stats: DecodeStats::default(),
            error: None,
        }
    }

    /// Bytes of the stream read so far as records (or skipped).
    pub fn bytes_read(&self) -> usize {
        self.base + self.cursor.pos
    }

    /// The next record, as [`TlogRecords::next`] gives it.
    pub fn next_record(&mut self) -> Option<(u64, Frame)> {
        loop {
            let record = TlogReader {
                bytes: self.buf.data(),
                cursor: &mut self.cursor,
                stats: &mut self.stats,
            }
            .next_record();
            if record.is_some() || !self.cursor.more {
                return record;
            }
            let mut eof = false;
            self.buf.fill(
                &mut self.reader,
                (&mut self.cursor.pos, &mut self.base),
                &mut eof,
                &mut self.error,
            );
            self.cursor.more = !eof;
        }
    }
}

impl<R: std::io::Read> Iterator for TlogStream<R> {
    type Item = (u64, Frame);

    fn next(&mut self) -> Option<(u64, Frame)> {
        self.next_record()
    }
}

/// As [`decode_tlog_with`], the records read from a stream ([`TlogStream`]); `emit` gets the
/// bytes of the stream read so far. A read error is returned after what came before it.
pub(crate) fn decode_tlog_stream(
    records: &mut TlogStream<impl std::io::Read>,
    conv: &mut MessageConverter,
    emit: &mut dyn FnMut(usize, Sample, usize, &MessageConverter),
) -> Option<std::io::Error> {
    while let Some((ts, f)) = records.next_record() {
        if let Some((k, s)) = conv.convert_any(&f.message, ts) {
            emit(k, s, records.bytes_read(), conv);
        }
    }
    for (why, n) in &records.stats.skipped {
        conv.stats.skip_n(why, *n);
    }
    records.error.take()
}
