//! ArduPilot DataFlash (`.bin`) reader: bytes in, records out. Pure; no I/O.
//!
//! A DataFlash log describes its own messages. Every record is `A3 95`, a type byte and that type's
//! fields packed little-endian; an `FMT` record (type 128, itself described by a fixed layout) gives
//! a type's id, total length, name, format characters and column names. `FMTU` records add a unit
//! and a multiplier id per column (`MULT` and `UNIT` records give the ids' meanings); a unit `#`
//! marks the instance column of an instanced message (newer logs: one `MAG` with a field `I` rather
//! than `MAG`, `MAG2`, `MAG3`).
//!
//! Bad input is skipped and counted in [`DfStats::skipped`], never fatal: `resync` (bytes that do
//! not start a record), `unknown_type` (a record of a type no FMT defined), `bad_fmt` (an FMT whose
//! format characters are unknown or do not fit its length), `truncated` (the log ends inside a
//! record: what came before is kept). The state is bounded: at most 256 formats.

use super::number::Number;
use crate::io::window::Window;
use std::collections::BTreeMap;

/// The two bytes that start every record.
pub(crate) const HEAD: [u8; 2] = [0xA3, 0x95];
/// The type id of FMT records.
pub(crate) const FMT_TYPE: u8 = 0x80;
/// FMT's own length (head and type included).
const FMT_LEN: usize = 89;

/// How a format character's bytes are read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `b`, `B`/`M`, `h`, `H`, `i`, `I`, `q`, `Q`, `f`, `d`.
    Number(Number),
    /// `c` (int16), `C` (uint16), `e` (int32), `E` (uint32): the integer * 0.01.
    Centi(Number),
    /// `L`: int32 latitude/longitude * 1e-7 (degrees).
    LatLon,
    /// `n`, `N`, `Z`: NUL-padded text of 4, 16, 64 bytes.
    Text(usize),
    /// `a`: int16[32].
    I16Array,
}

impl Kind {
    /// The kind of a DataFlash format character, `None` for an unknown one.
    pub(crate) fn from_char(c: u8) -> Option<Kind> {
        Some(match c {
            b'b' => Kind::Number(Number::I8),
            b'B' | b'M' => Kind::Number(Number::U8),
            b'h' => Kind::Number(Number::I16),
            b'H' => Kind::Number(Number::U16),
            b'i' => Kind::Number(Number::I32),
            b'I' => Kind::Number(Number::U32),
            b'q' => Kind::Number(Number::I64),
            b'Q' => Kind::Number(Number::U64),
            b'f' => Kind::Number(Number::F32),
            b'd' => Kind::Number(Number::F64),
            b'c' => Kind::Centi(Number::I16),
            b'C' => Kind::Centi(Number::U16),
            b'e' => Kind::Centi(Number::I32),
            b'E' => Kind::Centi(Number::U32),
            b'L' => Kind::LatLon,
            b'n' => Kind::Text(4),
            b'N' => Kind::Text(16),
            b'Z' => Kind::Text(64),
            b'a' => Kind::I16Array,
            _ => return None,
        })
    }

    pub fn size(self) -> usize {
        match self {
            Kind::Number(n) | Kind::Centi(n) => n.size(),
            Kind::LatLon => 4,
            Kind::Text(n) => n,
            Kind::I16Array => 64,
        }
    }
}

/// One column of a message type.
#[derive(Debug, Clone, PartialEq)]
pub struct Column {
    pub name: String,
    pub kind: Kind,
    /// Byte offset in the payload (after head and type).
    pub offset: usize,
    /// FMTU unit id (`#` marks the instance column), when the log has FMTU.
    pub unit: Option<char>,
    /// FMTU multiplier id (see [`DfReader::multiplier`]), when the log has FMTU.
    pub mult_id: Option<char>,
}

/// One message type, as its FMT record defines it.
#[derive(Debug, Clone, PartialEq)]
pub struct MessageFormat {
    pub type_id: u8,
    /// Record length with head and type.
    pub length: usize,
    pub name: String,
    pub format: String,
    pub columns: Vec<Column>,
    /// The instance column (FMTU unit `#`, or a column named `I`).
    pub instance: Option<usize>,
}

impl MessageFormat {
    /// Parse an FMT payload (86 bytes); `None` when the format does not fit its length.
    fn from_fmt(payload: &[u8]) -> Option<MessageFormat> {
        if payload.len() < FMT_LEN - 3 {
            return None;
        }
        let type_id = payload[0];
        let length = payload[1] as usize;
        let name = text(&payload[2..6]);
        let format = text(&payload[6..22]);
        let cols = text(&payload[22..86]);
        MessageFormat::new(type_id, length, &name, &format, &cols)
    }

    /// A message format from its parts; `None` when a character is unknown, the names do not
    /// match the characters or the fields do not fit `length`.
    pub fn new(
        type_id: u8,
        length: usize,
        name: &str,
        format: &str,
        columns: &str,
    ) -> Option<MessageFormat> {
        let names: Vec<&str> = if columns.is_empty() {
            Vec::new()
        } else {
            columns.split(',').collect()
        };
        if names.len() != format.len() || length < 3 {
            return None;
        }
        let mut offset = 0;
        let mut cols = Vec::with_capacity(names.len());
        for (c, n) in format.bytes().zip(&names) {
            let kind = Kind::from_char(c)?;
            cols.push(Column {
                name: n.to_string(),
                kind,
                offset,
                unit: None,
                mult_id: None,
            });
            offset += kind.size();
        }
        if offset + 3 > length {
            return None;
        }
        let instance = cols.iter().position(|c| c.name == "I");
        Some(MessageFormat {
            type_id,
            length,
            name: name.to_string(),
            format: format.to_string(),
            columns: cols,
            instance,
        })
    }

    /// The index of column `name`.
    pub fn column(&self, name: &str) -> Option<usize> {
        self.columns.iter().position(|c| c.name == name)
    }
}

/// NUL-terminated text (lossy UTF-8).
fn text(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    String::from_utf8_lossy(&b[..end]).into_owned()
}

/// How a numeric column's bytes become its value ([`Record::value`]): the format character's
/// number type and scale as one choice, so a record's field is read with one dispatch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Read {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
    /// The integer * 0.01 (`c`, `C`, `e`, `E`).
    CentiI16,
    CentiU16,
    CentiI32,
    CentiU32,
    /// int32 * 1e-7 (`L`).
    LatLon,
}

/// Where a numeric column is in a record of its type, and how it is read
/// ([`Record::number_at`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct NumberAt {
    pub offset: usize,
    pub read: Read,
}

impl NumberAt {
    /// Column `c` as a number; `None` for text and arrays, which have no value.
    pub(crate) fn of(c: &Column) -> Option<NumberAt> {
        let read = match c.kind {
            Kind::Number(n) => match n {
                Number::I8 => Read::I8,
                Number::U8 => Read::U8,
                Number::I16 => Read::I16,
                Number::U16 => Read::U16,
                Number::I32 => Read::I32,
                Number::U32 => Read::U32,
                Number::I64 => Read::I64,
                Number::U64 => Read::U64,
                Number::F32 => Read::F32,
                Number::F64 => Read::F64,
            },
            Kind::Centi(Number::I16) => Read::CentiI16,
            Kind::Centi(Number::U16) => Read::CentiU16,
            Kind::Centi(Number::I32) => Read::CentiI32,
            Kind::Centi(Number::U32) => Read::CentiU32,
            // Only the four above are made by format characters.
            Kind::Centi(_) => return None,
            Kind::LatLon => Read::LatLon,
            Kind::Text(_) | Kind::I16Array => return None,
        };
        Some(NumberAt {
            offset: c.offset,
            read,
        })
    }
}

/// One record: its format and its payload (after head and type).
#[derive(Debug, Clone, Copy)]
pub struct Record<'a> {
    pub format: &'a MessageFormat,
    pub payload: &'a [u8],
}

impl Record<'_> {
    /// Column `col` as a number, with the format character's own scale (`c`, `C`, `e`, `E`: 0.01;
    /// `L`: 1e-7), as pymavlink's DFReader gives it. `None` for text, arrays and bad indices.
    pub fn value(&self, col: usize) -> Option<f64> {
        let c = self.format.columns.get(col)?;
        self.value_at(c.offset, c.kind)
    }

    /// The number of kind `kind` at byte `offset` of the payload, as [`Record::value`] reads a
    /// column there: for a reader that found a column's place once and reads it record by record.
    #[inline]
    pub(crate) fn value_at(&self, offset: usize, kind: Kind) -> Option<f64> {
        let b = self.payload.get(offset..offset + kind.size())?;
        match kind {
            Kind::Number(n) => n.read(b),
            Kind::Centi(n) => Some(n.read(b)? * 0.01),
            Kind::LatLon => Some(Number::I32.read(b)? * 1e-7),
            Kind::Text(_) | Kind::I16Array => None,
        }
    }

    /// The number `at` reads ([`NumberAt`]): [`Record::value_at`] of its column, in one step.
    #[inline]
    pub(crate) fn number_at(&self, at: NumberAt) -> Option<f64> {
        let p = self.payload;
        let o = at.offset;
        /// `N` bytes from `o`, or `None` past the payload's end.
        #[inline(always)]
        fn take<const N: usize>(p: &[u8], o: usize) -> Option<[u8; N]> {
            p.get(o..o + N)?.try_into().ok()
        }
        Some(match at.read {
            Read::I8 => take::<1>(p, o)?[0] as i8 as f64,
            Read::U8 => take::<1>(p, o)?[0] as f64,
            Read::I16 => i16::from_le_bytes(take(p, o)?) as f64,
            Read::U16 => u16::from_le_bytes(take(p, o)?) as f64,
            Read::I32 => i32::from_le_bytes(take(p, o)?) as f64,
            Read::U32 => u32::from_le_bytes(take(p, o)?) as f64,
            Read::I64 => i64::from_le_bytes(take(p, o)?) as f64,
            Read::U64 => u64::from_le_bytes(take(p, o)?) as f64,
            Read::F32 => f32::from_le_bytes(take(p, o)?) as f64,
            Read::F64 => f64::from_le_bytes(take(p, o)?),
            Read::CentiI16 => i16::from_le_bytes(take(p, o)?) as f64 * 0.01,
            Read::CentiU16 => u16::from_le_bytes(take(p, o)?) as f64 * 0.01,
            Read::CentiI32 => i32::from_le_bytes(take(p, o)?) as f64 * 0.01,
            Read::CentiU32 => u32::from_le_bytes(take(p, o)?) as f64 * 0.01,
            Read::LatLon => i32::from_le_bytes(take(p, o)?) as f64 * 1e-7,
        })
    }

    /// Column `name` as a number ([`Record::value`]).
    pub fn get(&self, name: &str) -> Option<f64> {
        self.value(self.format.column(name)?)
    }

    /// An integer column exactly (times in us).
    pub fn get_u64(&self, name: &str) -> Option<u64> {
        let c = &self.format.columns[self.format.column(name)?];
        let b = self.payload.get(c.offset..c.offset + c.kind.size())?;
        match c.kind {
            Kind::Number(Number::U64 | Number::I64) => Some(u64::from_le_bytes(b.try_into().ok()?)),
            Kind::Number(Number::U32 | Number::I32) => {
                Some(u32::from_le_bytes(b.try_into().ok()?) as u64)
            }
            _ => None,
        }
    }

    /// A text column (`n`, `N`, `Z`).
    pub fn text(&self, name: &str) -> Option<String> {
        let c = &self.format.columns[self.format.column(name)?];
        match c.kind {
            Kind::Text(n) => Some(text(self.payload.get(c.offset..c.offset + n)?)),
            _ => None,
        }
    }

    /// Text column `col` (`n`, `N`, `Z`), borrowed when it is UTF-8.
    pub(crate) fn text_at(&self, col: usize) -> Option<std::borrow::Cow<'_, str>> {
        let c = self.format.columns.get(col)?;
        let Kind::Text(n) = c.kind else {
            return None;
        };
        let b = self.payload.get(c.offset..c.offset + n)?;
        let end = b.iter().position(|&x| x == 0).unwrap_or(b.len());
        Some(String::from_utf8_lossy(&b[..end]))
    }

    /// The record's time in us: `TimeUS`, or `TimeMS` (older logs) * 1000.
    pub fn time_us(&self) -> Option<u64> {
        self.get_u64("TimeUS")
            .or_else(|| self.get_u64("TimeMS").map(|t| t.saturating_mul(1000)))
    }

    /// The instance: the instance column's value, or 0 for a message without one.
    pub fn instance(&self) -> u8 {
        self.format
            .instance
            .and_then(|c| self.value(c))
            .filter(|v| (0.0..256.0).contains(v))
            .map(|v| v as u8)
            .unwrap_or(0)
    }
}

/// What a [`DfReader`] read and skipped.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DfStats {
    /// Records read (FMT included).
    pub records: u64,
    /// Skipped by reason (`resync` counts bytes).
    pub skipped: BTreeMap<String, u64>,
}

impl DfStats {
    fn skip(&mut self, why: &str, n: u64) {
        *self.skipped.entry(why.to_string()).or_insert(0) += n;
    }
}

/// What a record of a type does to the reader besides being returned: FMT defines a type, FMTU
/// gives units and multipliers, MULT gives multipliers. Set once per FMT, so records are not told
/// apart by name one by one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Meta {
    None,
    Fmt,
    Fmtu,
    Mult,
}

impl Meta {
    fn of(f: &MessageFormat) -> Meta {
        match f.name.as_str() {
            "FMT" => Meta::Fmt,
            "FMTU" => Meta::Fmtu,
            "MULT" => Meta::Mult,
            _ => Meta::None,
        }
    }
}

/// The longest record: its length is one byte.
const MAX_RECORD: usize = 255;

/// The FMT payload a type was defined by, and the instance column that gave.
#[derive(Debug, Clone)]
struct Definition {
    payload: Box<[u8]>,
    instance: Option<usize>,
}

/// Reads the records of a DataFlash log in order ([`DfReader::next_record`]), from whole bytes
/// or from a stream through a window of [`crate::io::window::STREAM_CHUNK_BYTES`].
pub struct DfReader<'a> {
    win: Window<'a>,
    /// Offset of the next record in the window.
    pos: usize,
    formats: Vec<Option<MessageFormat>>,
    /// Per type id, the FMT payload that defined it and the instance column it gave: an FMT
    /// the same as the last (a log repeats them all at each start) is not parsed again.
    defined_by: Vec<Option<Definition>>,
    meta: [Meta; 256],
    /// MULT ids to multipliers.
    mults: BTreeMap<char, f64>,
    pub stats: DfStats,
}

impl<'a> DfReader<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Self::over(Window::whole(data))
    }

    /// A reader of the log `reader` gives, holding a window of it rather than the whole.
    pub fn from_reader(reader: impl std::io::Read + 'a) -> Self {
        Self::over(Window::stream(reader))
    }

    fn over(win: Window<'a>) -> Self {
        let mut formats = vec![None; 256];
        formats[FMT_TYPE as usize] = MessageFormat::new(
            FMT_TYPE,
            FMT_LEN,
            "FMT",
            "BBnNZ",
            "Type,Length,Name,Format,Columns",
        );
        let mut meta = [Meta::None; 256];
        meta[FMT_TYPE as usize] = Meta::Fmt;
        DfReader {
            win,
            pos: 0,
            formats,
            defined_by: vec![None; 256],
            meta,
            mults: BTreeMap::new(),
            stats: DfStats::default(),
        }
    }

    /// Bytes consumed so far.
    pub fn position(&self) -> usize {
        self.win.offset(self.pos)
    }

    /// The error that ended a stream early, if one did (taken).
    pub fn take_error(&mut self) -> Option<std::io::Error> {
        self.win.take_error()
    }

    /// The format of type `id`, once defined.
    pub fn format(&self, id: u8) -> Option<&MessageFormat> {
        self.formats[id as usize].as_ref()
    }

    /// The multiplier a column's FMTU multiplier id stands for (MULT records), when known.
    pub fn multiplier(&self, col: &Column) -> Option<f64> {
        self.mults.get(&col.mult_id?).copied()
    }

    /// The bytes of the window.
    fn window(&self) -> &[u8] {
        self.win.bytes()
    }

    /// Read more of a stream when less than a record is left in its window.
    fn refill(&mut self) {
        self.win.refill(&mut self.pos, MAX_RECORD);
    }

    /// The next record, or `None` at the end (a truncated last record is counted, not returned).
    pub fn next_record(&mut self) -> Option<Record<'_>> {
        loop {
            self.refill();
            let (left, head, id) = {
                let rest = &self.window()[self.pos..];
                (rest.len(), rest.get(..2) == Some(&HEAD[..]), rest.get(2))
            };
            if left < 3 {
                if left > 0 {
                    self.stats.skip("truncated", 1);
                    self.pos += left;
                }
                return None;
            }
            if !head {
                self.garbage(1);
                continue;
            }
            let id = *id.expect("3 bytes left") as usize;
            let Some(len) = self.formats[id].as_ref().map(|f| f.length) else {
                self.stats.skip("unknown_type", 1);
                self.garbage(1);
                continue;
            };
            if left < len {
                self.stats.skip("truncated", 1);
                self.pos += left;
                return None;
            }
            let start = self.pos + 3;
            self.pos += len;
            self.stats.records += 1;
            if self.meta[id] != Meta::None {
                let mut payload = [0u8; MAX_RECORD];
                payload[..len - 3].copy_from_slice(&self.window()[start..start + len - 3]);
                self.absorb_meta(id, &payload[..len - 3]);
            }
            let payload = &self.window()[start..start + len - 3];
            return Some(Record {
                format: self.formats[id].as_ref()?,
                payload,
            });
        }
    }

    fn garbage(&mut self, n: usize) {
        self.stats.skip("resync", n as u64);
        self.pos += n;
    }

    /// FMT defines a type; FMTU gives units and multipliers; MULT gives multipliers.
    fn absorb_meta(&mut self, id: usize, payload: &[u8]) {
        match self.meta[id] {
            Meta::None => {}
            Meta::Fmt => self.absorb_fmt(payload),
            Meta::Mult => {
                let rec = Record {
                    format: self.formats[id]
                        .as_ref()
                        .expect("a type with a meaning has a format"),
                    payload,
                };
                let m = rec.get("Mult");
                let k = rec.get("Id").filter(|v| (0.0..128.0).contains(v));
                if let (Some(m), Some(k)) = (m, k) {
                    self.mults.insert(k as u8 as char, m);
                }
            }
            Meta::Fmtu => self.absorb_fmtu(id, payload),
        }
    }

    /// An FMT record: a type defined, or defined again. The same definition again leaves the
    /// format as its parse would (units and multipliers unknown until an FMTU gives them).
    fn absorb_fmt(&mut self, payload: &[u8]) {
        let k = payload.first().map_or(FMT_TYPE, |&t| t) as usize;
        if let (Some(d), Some(f)) = (&self.defined_by[k], self.formats[k].as_mut()) {
            if *d.payload == *payload {
                for c in f.columns.iter_mut() {
                    c.unit = None;
                    c.mult_id = None;
                }
                f.instance = d.instance;
                return;
            }
        }
        match MessageFormat::from_fmt(payload) {
            // FMT cannot be redefined: its layout is what every log is read by.
            Some(f) if f.type_id != FMT_TYPE => {
                self.meta[k] = Meta::of(&f);
                self.defined_by[k] = Some(Definition {
                    payload: payload.into(),
                    instance: f.instance,
                });
                self.formats[k] = Some(f);
            }
            Some(_) => {}
            None => self.stats.skip("bad_fmt", 1),
        }
    }

    /// An FMTU record: the units and multiplier ids of a type's columns, and its instance column.
    fn absorb_fmtu(&mut self, id: usize, payload: &[u8]) {
        let rec = Record {
            format: self.formats[id]
                .as_ref()
                .expect("a type with a meaning has a format"),
            payload,
        };
        let ty = rec.get("FmtType").filter(|v| (0.0..256.0).contains(v));
        let (Some(ty), Some(units), Some(mults)) = (ty, rec.text("UnitIds"), rec.text("MultIds"))
        else {
            return;
        };
        if let Some(f) = self.formats[ty as usize].as_mut() {
            for (i, c) in f.columns.iter_mut().enumerate() {
                c.unit = units.chars().nth(i);
                c.mult_id = mults.chars().nth(i);
            }
            if let Some(k) = units.chars().position(|u| u == '#') {
                if k < f.columns.len() {
                    f.instance = Some(k);
                }
            }
        }
    }
}

/// Whether `bytes` begin a DataFlash log: an FMT record defining FMT itself within the first bytes.
pub fn looks_like(bytes: &[u8]) -> bool {
    let head = &bytes[..bytes.len().min(1024)];
    head.windows(5)
        .any(|w| w == [HEAD[0], HEAD[1], FMT_TYPE, FMT_TYPE, FMT_LEN as u8])
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An FMT record.
    pub fn fmt(id: u8, name: &str, format: &str, cols: &str) -> Vec<u8> {
        let len = 3 + format
            .bytes()
            .map(|c| Kind::from_char(c).unwrap().size())
            .sum::<usize>();
        let mut r = vec![HEAD[0], HEAD[1], FMT_TYPE, id, len as u8];
        let pad = |s: &str, n: usize| {
            let mut v = s.as_bytes().to_vec();
            v.resize(n, 0);
            v
        };
        r.extend(pad(name, 4));
        r.extend(pad(format, 16));
        r.extend(pad(cols, 64));
        r
    }

    pub fn rec(id: u8, payload: &[u8]) -> Vec<u8> {
        let mut r = vec![HEAD[0], HEAD[1], id];
        r.extend_from_slice(payload);
        r
    }

    fn self_fmt() -> Vec<u8> {
        fmt(FMT_TYPE, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    }

    #[test]
    fn reads_fmt_driven_records_and_skips_damage() {
        let mut log = self_fmt();
        assert!(looks_like(&log));
        log.extend(fmt(200, "ATT", "Qcc", "TimeUS,Roll,Pitch"));
        let mut p = 1234u64.to_le_bytes().to_vec();
        p.extend((-718i16).to_le_bytes());
        p.extend(258i16.to_le_bytes());
        log.extend(rec(200, &p));
        log.extend([1, 2, 3]); // garbage
        log.extend(rec(201, &[0; 4])); // undefined type
        log.extend(rec(200, &p));
        log.extend(&rec(200, &p)[..7]); // truncated tail
        let mut r = DfReader::new(&log);
        let mut names = vec![];
        while let Some(rec) = r.next_record() {
            if rec.format.name == "ATT" {
                assert_eq!(rec.time_us(), Some(1234));
                assert_eq!(rec.get("Roll"), Some(-718.0 * 0.01));
                assert_eq!(rec.get("Pitch"), Some(2.58));
            }
            names.push(rec.format.name.clone());
        }
        assert_eq!(names, ["FMT", "FMT", "ATT", "ATT"]);
        assert_eq!(r.stats.skipped["truncated"], 1);
        assert_eq!(r.stats.skipped["unknown_type"], 1);
        assert!(r.stats.skipped["resync"] >= 3);
    }

    #[test]
    fn a_log_streamed_through_a_window_reads_as_the_whole_bytes() {
        let mut log = self_fmt();
        log.extend(fmt(201, "MULT", "Qbd", "TimeUS,Id,Mult"));
        log.extend(fmt(200, "ATT", "Qcc", "TimeUS,Roll,Pitch"));
        let mut x = 0x2545_F491u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        for i in 0..120_000u64 {
            let mut p = i.to_le_bytes().to_vec();
            p.extend((i as i16).to_le_bytes());
            p.extend((-(i as i16)).to_le_bytes());
            log.extend(rec(200, &p));
            match next() % 53 {
                0 => log.extend((0..next() % 300).map(|_| next() as u8)),
                1 => log.extend(rec(7, &[0; 9])),
                _ => {}
            }
        }
        log.truncate(log.len() - 5);
        assert!(log.len() > 4 * crate::io::window::STREAM_CHUNK_BYTES);
        let read = |mut r: DfReader<'_>| {
            let mut got = Vec::new();
            while let Some(rec) = r.next_record() {
                got.push((rec.format.type_id, rec.time_us(), rec.get("Roll")));
            }
            (got, r.stats.clone(), r.position())
        };
        let whole = read(DfReader::new(&log));
        for step in [1 << 20, 4093] {
            let trickle = crate::io::decode::tests::Trickle { bytes: &log, step };
            let streamed = read(DfReader::from_reader(trickle));
            assert_eq!(streamed.0.len(), whole.0.len());
            assert!(
                streamed == whole,
                "step {step}: {:?} vs {:?}",
                streamed.1,
                whole.1
            );
        }
        assert_eq!(whole.2, log.len());
        assert!(whole.1.skipped["resync"] > 1000, "{:?}", whole.1);
        assert_eq!(whole.1.skipped["truncated"], 1);
    }

    #[test]
    fn fmtu_marks_the_instance_column_and_mult() {
        let mut log = self_fmt();
        log.extend(fmt(201, "MULT", "Qbd", "TimeUS,Id,Mult"));
        log.extend(fmt(202, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds"));
        log.extend(fmt(203, "MAG", "QBhhh", "TimeUS,Inst,MagX,MagY,MagZ"));
        let mut m = 0u64.to_le_bytes().to_vec();
        m.push(b'C');
        m.extend(1e-3f64.to_le_bytes());
        log.extend(rec(201, &m));
        let mut u = 0u64.to_le_bytes().to_vec();
        u.push(203);
        let mut units = b"s#GGG".to_vec();
        units.resize(16, 0);
        let mut mults = b"F-CCC".to_vec();
        mults.resize(16, 0);
        u.extend(units);
        u.extend(mults);
        log.extend(rec(202, &u));
        let mut p = 5u64.to_le_bytes().to_vec();
        p.push(2);
        for v in [100i16, -200, 300] {
            p.extend(v.to_le_bytes());
        }
        log.extend(rec(203, &p));
        let mut r = DfReader::new(&log);
        let mut seen = false;
        while let Some(rec) = r.next_record() {
            if rec.format.name == "MAG" {
                assert_eq!(rec.instance(), 2);
                assert_eq!(rec.get("MagY"), Some(-200.0));
                seen = true;
            }
        }
        assert!(seen);
        let f = r.format(203).unwrap();
        assert_eq!(r.multiplier(&f.columns[2]), Some(1e-3));
    }

    #[test]
    fn a_bad_fmt_is_counted() {
        let mut log = self_fmt();
        let mut bad = fmt(200, "X", "Qf", "TimeUS,A");
        bad[5 + 4] = b'?'; // unknown format character
        log.extend(bad);
        let mut r = DfReader::new(&log);
        while r.next_record().is_some() {}
        assert_eq!(r.stats.skipped["bad_fmt"], 1);
        assert!(r.format(200).is_none());
    }
}
