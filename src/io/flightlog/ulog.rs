//! PX4 ULog (`.ulg`) reader: bytes in, records out. Pure; no I/O.
//!
//! A ULog file is a 16-byte header (`ULog` magic, version, start time) and then messages, each a
//! u16 size, a type byte and that many bytes: flag bits (`B`: incompatible flags and the offsets of
//! appended data), formats (`F`: `name:type field;type[n] field;...`, where a type may be another
//! format, nested), information (`I`, `M`), parameters (`P`, `Q`), subscriptions (`A`: a topic
//! instance, `multi_id`, under a message id), data (`D`: message id and the topic's fields),
//! dropouts (`O`), log text (`L`, `C`) and sync markers (`S`). A subscription's layout is resolved
//! once into flattened fields (`gyro_rad[0]`, `nested.field`), `_padding*` fields left out, as
//! pyulog names them; data records are read in place.
//!
//! Bad input is skipped and counted in [`UlogStats::skipped`], never fatal: `resync` (a message
//! header that cannot be one: reading goes on after the next sync marker), `unknown_subscription`
//! (data under an id no subscription gave), `bad_format`, `bad_subscription`, `bad_message` (a
//! known message too short for its fields), `short_data` (data shorter than its topic's fields),
//! `truncated` (the file ends inside a message). Appended data (flag bits) is read from its
//! offset. State is bounded: at most [`MAX_FORMATS`] formats, [`MAX_SUBSCRIPTIONS`]
//! subscriptions, [`MAX_PARAMS`] parameters, [`MAX_FIELDS`] flattened fields per topic.

use super::number::Number;
use crate::io::window::Window;
use std::collections::BTreeMap;

/// The file magic (`ULog`, then 01 12 35), followed by a version byte and the start time.
pub const MAGIC: [u8; 7] = [0x55, 0x4c, 0x6f, 0x67, 0x01, 0x12, 0x35];
/// A sync message's payload.
pub(crate) const SYNC: [u8; 8] = [0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12];
pub(crate) const MAX_FORMATS: usize = 4096;
pub(crate) const MAX_SUBSCRIPTIONS: usize = 4096;
pub const MAX_PARAMS: usize = 16384;
pub(crate) const MAX_FIELDS: usize = 8192;
const MAX_NESTING: usize = 8;

/// A primitive field type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ty {
    Number(Number),
    Bool,
    Char,
}

impl Ty {
    fn parse(s: &str) -> Option<Ty> {
        Some(match s {
            "int8_t" => Ty::Number(Number::I8),
            "uint8_t" => Ty::Number(Number::U8),
            "int16_t" => Ty::Number(Number::I16),
            "uint16_t" => Ty::Number(Number::U16),
            "int32_t" => Ty::Number(Number::I32),
            "uint32_t" => Ty::Number(Number::U32),
            "int64_t" => Ty::Number(Number::I64),
            "uint64_t" => Ty::Number(Number::U64),
            "float" => Ty::Number(Number::F32),
            "double" => Ty::Number(Number::F64),
            "bool" => Ty::Bool,
            "char" => Ty::Char,
            _ => return None,
        })
    }

    pub fn size(self) -> usize {
        match self {
            Ty::Number(n) => n.size(),
            Ty::Bool | Ty::Char => 1,
        }
    }

    /// The value at the start of `b`; `None` when `b` is shorter than [`Ty::size`].
    pub(crate) fn read(self, b: &[u8]) -> Option<f64> {
        match self {
            Ty::Number(n) => n.read(b),
            Ty::Bool | Ty::Char => b.first().map(|&v| v as f64),
        }
    }
}

/// A flattened field of a topic.
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub name: String,
    pub ty: Ty,
    pub offset: usize,
}

/// A subscription: a topic instance and its resolved layout.
#[derive(Debug, Clone, PartialEq)]
pub struct Subscription {
    pub msg_id: u16,
    pub multi_id: u8,
    pub name: String,
    pub fields: Vec<Field>,
    /// Bytes of the topic (padding included).
    pub size: usize,
    /// End of the last field that is not padding.
    pub used: usize,
    /// Data records read.
    pub records: u64,
    /// Which `A` message made it (counting from 0): tells a re-subscription under the same id.
    pub serial: u32,
    /// The index of the `timestamp` field.
    timestamp: Option<usize>,
    /// Where a `uint64_t timestamp` field ends in the data (bytes), if the topic has one.
    timestamp_end: Option<usize>,
    /// Its records are returned ([`UlogReader::only_topics`]).
    wanted: bool,
}

impl Subscription {
    /// The index of field `name`.
    pub fn field(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }
}

/// One data record: its subscription and its bytes (after the message id).
#[derive(Debug, Clone, Copy)]
pub struct Data<'a> {
    pub sub: &'a Subscription,
    pub payload: &'a [u8],
}

impl Data<'_> {
    /// Field `k` (an index from [`Subscription::field`]) as a number; `None` past the data's end.
    pub fn value(&self, k: usize) -> Option<f64> {
        let f = self.sub.fields.get(k)?;
        f.ty.read(self.payload.get(f.offset..)?)
    }

    /// Field `name` as a number.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.value(self.sub.field(name)?)
    }

    /// The `timestamp` field (us), exactly.
    pub fn timestamp_us(&self) -> Option<u64> {
        let f = &self.sub.fields[self.sub.timestamp?];
        let b = self.payload.get(f.offset..f.offset + 8)?;
        (f.ty == Ty::Number(Number::U64))
            .then(|| u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }
}

/// What a [`UlogReader`] read and skipped.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UlogStats {
    /// Messages read (all types).
    pub messages: u64,
    /// Data records read.
    pub data: u64,
    /// Dropouts the logger marked, and their total duration (ms).
    pub dropouts: u64,
    pub dropout_ms: u64,
    /// Parameter messages after the first value of a parameter (changes in flight).
    pub param_changes: u64,
    pub skipped: BTreeMap<String, u64>,
}

impl UlogStats {
    fn skip(&mut self, why: &str) {
        *self.skipped.entry(why.to_string()).or_insert(0) += 1;
    }
}

/// A parsed format: fields as (type name, array length, field name).
type RawFormat = Vec<(String, Option<usize>, String)>;

/// The longest message: a u16 size, the type byte and that many bytes.
const MAX_MESSAGE: usize = 3 + u16::MAX as usize;

/// Reads a ULog file's data records in order ([`UlogReader::next_data`]), from whole bytes or
/// from a stream through a window of [`crate::io::window::STREAM_CHUNK_BYTES`]; formats,
/// parameters, information and subscriptions are taken in on the way. Records of topics left
/// out ([`UlogReader::only_topics`]) are counted from their header and not returned.
pub struct UlogReader<'a> {
    win: Window<'a>,
    /// Offset of the next message in the window.
    pos: usize,
    pub version: u8,
    pub start_us: u64,
    formats: BTreeMap<String, RawFormat>,
    /// Subscriptions in the order made (a re-subscription under an id replaces its entry).
    subs: Vec<Subscription>,
    /// Message id -> 1 + the index of its subscription in `subs` (0: none).
    by_id: Vec<u32>,
    /// Which topics' records are returned, by name (`None`: all).
    topics: Option<fn(&str) -> bool>,
    /// A data record was returned.
    returned: bool,
    /// Every parameter's first value (the one in use when the log started).
    params: BTreeMap<String, f64>,
    /// Information messages (`I`) with text values.
    pub info: BTreeMap<String, String>,
    /// Offsets (in the file) of appended data still ahead.
    appended: Vec<usize>,
    /// Subscriptions made so far.
    serial: u32,
    pub stats: UlogStats,
}

impl<'a> UlogReader<'a> {
    /// A reader over a file; `None` when it does not start with the ULog header.
    pub fn new(data: &'a [u8]) -> Option<Self> {
        if !looks_like(data) || data.len() < 16 {
            return None;
        }
        let mut rd = Self::empty(Window::whole(data));
        rd.start(data);
        Some(rd)
    }

    /// A reader of the file `reader` gives, holding a window of it rather than the whole; `None`
    /// when it does not start with the ULog header (or a read error comes before it).
    pub fn from_reader(reader: impl std::io::Read + 'a) -> Option<Self> {
        let mut rd = Self::empty(Window::stream(reader));
        rd.refill();
        let head: [u8; 16] = rd.window().get(..16)?.try_into().ok()?;
        if !looks_like(&head) {
            return None;
        }
        rd.start(&head);
        Some(rd)
    }

    fn empty(win: Window<'a>) -> Self {
        UlogReader {
            win,
            pos: 0,
            version: 0,
            start_us: 0,
            formats: BTreeMap::new(),
            subs: Vec::new(),
            by_id: Vec::new(),
            topics: None,
            returned: false,
            params: BTreeMap::new(),
            info: BTreeMap::new(),
            appended: Vec::new(),
            serial: 0,
            stats: UlogStats::default(),
        }
    }

    /// Take the 16-byte file header `head` (already checked).
    fn start(&mut self, head: &[u8]) {
        self.version = head[7];
        self.start_us = u64::from_le_bytes(head[8..16].try_into().expect("8 bytes"));
        self.pos = 16;
    }

    /// Return the records of the topics `wanted` accepts only (and the first data record, whatever its topic,
    /// so a caller sees the definitions section end as it would reading all). A record of
    /// another topic is counted in its subscription's [`Subscription::records`] from its header;
    /// one without a `uint64_t timestamp` in its bytes is returned all the same, as a record
    /// that cannot be placed in time is the caller's to count.
    /// Takes effect for subscriptions made after it.
    pub fn only_topics(&mut self, wanted: fn(&str) -> bool) {
        self.topics = Some(wanted);
    }

    /// Bytes consumed so far.
    pub fn position(&self) -> usize {
        self.win.offset(self.pos)
    }

    /// The error that ended a stream early, if one did (taken).
    pub fn take_error(&mut self) -> Option<std::io::Error> {
        self.win.take_error()
    }

    /// Parameters read so far (first value of each).
    pub fn params(&self) -> &BTreeMap<String, f64> {
        &self.params
    }

    /// Subscriptions made so far.
    pub(crate) fn subscriptions(&self) -> impl Iterator<Item = &Subscription> {
        self.subs.iter()
    }

    /// The bytes of the window.
    fn window(&self) -> &[u8] {
        self.win.bytes()
    }

    /// Read more of a stream when less than the longest message is left in its window.
    fn refill(&mut self) {
        self.win.refill(&mut self.pos, MAX_MESSAGE);
    }

    /// The whole input is in the window (bytes, or a stream read to its end).
    fn at_end(&self) -> bool {
        self.win.at_end()
    }

    /// The input's length, once all of it is in the window.
    fn known_len(&self) -> Option<usize> {
        self.win.known_len()
    }

    /// The index in `subs` of message id `id`'s subscription.
    fn sub_index(&self, id: u16) -> Option<usize> {
        match self.by_id.get(id as usize) {
            Some(&k) if k > 0 => Some(k as usize - 1),
            _ => None,
        }
    }

    /// The next data record, or `None` at the end of the file.
    pub fn next_data(&mut self) -> Option<Data<'_>> {
        loop {
            self.refill();
            let here = self.position();
            // Appended data starts at its offset, whatever the message before it left.
            if let Some(&a) = self.appended.first() {
                if here >= a {
                    self.appended.remove(0);
                }
            }
            let (left, size, ty) = {
                let rest = &self.window()[self.pos..];
                match rest {
                    [a, b, t, ..] => (rest.len(), u16::from_le_bytes([*a, *b]) as usize, *t),
                    _ => (rest.len(), 0, 0),
                }
            };
            if left < 3 {
                if left > 0 {
                    self.stats.skip("truncated");
                    self.pos += left;
                }
                return None;
            }
            if !b"BFIMPQARDLCSO".contains(&ty) {
                self.stats.skip("resync");
                self.resync();
                continue;
            }
            if let Some(&a) = self.appended.first() {
                if here < a && here + 3 + size > a {
                    self.stats.skip("truncated");
                    self.skip_to(a);
                    self.appended.remove(0);
                    continue;
                }
            }
            if left < 3 + size {
                self.stats.skip("truncated");
                self.pos += left;
                return None;
            }
            let start = self.pos + 3;
            self.pos += 3 + size;
            self.stats.messages += 1;
            if ty != b'D' {
                let body = self.window()[start..start + size].to_vec();
                self.absorb(ty, &body);
                continue;
            }
            let head = self.window().get(start..start + 2.min(size));
            let Some(&[lo, hi]) = head else {
                self.stats.skip("bad_message");
                continue;
            };
            let Some(k) = self.sub_index(u16::from_le_bytes([lo, hi])) else {
                self.stats.skip("unknown_subscription");
                continue;
            };
            let payload_len = size - 2;
            let sub = &mut self.subs[k];
            if payload_len < sub.used {
                self.stats.skip("short_data");
            }
            sub.records += 1;
            self.stats.data += 1;
            let timed = sub.timestamp_end.is_some_and(|e| payload_len >= e);
            if sub.wanted || !timed || !self.returned {
                self.returned = true;
                let payload = &self.window()[start + 2..start + size];
                return Some(Data {
                    sub: &self.subs[k],
                    payload,
                });
            }
        }
    }

    /// Move on to file offset `to` (at or after the current one), or to the end.
    fn skip_to(&mut self, to: usize) {
        loop {
            let ahead = to - self.position();
            let left = self.window().len() - self.pos;
            if ahead <= left {
                self.pos += ahead;
                return;
            }
            self.pos += left;
            if self.at_end() {
                return;
            }
            self.refill();
        }
    }

    /// Skip to just after the next sync marker (or to the end).
    fn resync(&mut self) {
        self.pos += 1;
        loop {
            let found = self.window()[self.pos..]
                .windows(SYNC.len())
                .position(|w| w == SYNC);
            if let Some(k) = found {
                self.pos += k + SYNC.len();
                return;
            }
            // A marker may begin in the last bytes of the window: they are searched again.
            let keep = (SYNC.len() - 1).min(self.window().len() - self.pos);
            self.pos = self.window().len() - keep;
            if self.at_end() {
                self.pos = self.window().len();
                return;
            }
            self.refill();
        }
    }

    fn absorb(&mut self, ty: u8, body: &[u8]) {
        match ty {
            b'B' => {
                if body.len() < 40 {
                    self.stats.skip("bad_message");
                    return;
                }
                // incompat_flags[0] bit 0: data appended at the offsets that follow.
                if body[8] & 1 != 0 {
                    for k in 0..3 {
                        let o = 16 + 8 * k;
                        let off = u64::from_le_bytes(body[o..o + 8].try_into().expect("8"));
                        let beyond = self.known_len().is_some_and(|n| off >= n as u64);
                        if off > 0 && off as usize > self.position() && !beyond {
                            self.appended.push(off as usize);
                        }
                    }
                    self.appended.sort_unstable();
                }
            }
            b'F' => {
                let text = String::from_utf8_lossy(body);
                match parse_format(&text) {
                    Some((name, f)) if self.formats.len() < MAX_FORMATS => {
                        self.formats.insert(name, f);
                    }
                    _ => self.stats.skip("bad_format"),
                }
            }
            b'A' => {
                if body.len() < 3 {
                    self.stats.skip("bad_message");
                    return;
                }
                let multi_id = body[0];
                let msg_id = u16::from_le_bytes([body[1], body[2]]);
                let name = String::from_utf8_lossy(&body[3..]).into_owned();
                let mut fields = Vec::new();
                let mut used = 0;
                match flatten(&self.formats, &name, "", 0, &mut fields, &mut used, 0) {
                    Some(size) if self.subs.len() < MAX_SUBSCRIPTIONS => {
                        let timestamp = fields.iter().position(|f| f.name == "timestamp");
                        let timestamp_end = timestamp
                            .map(|k| &fields[k])
                            .filter(|f| f.ty == Ty::Number(Number::U64))
                            .map(|f| f.offset + 8);
                        let wanted = self.topics.is_none_or(|want| want(&name));
                        self.serial += 1;
                        let sub = Subscription {
                            msg_id,
                            multi_id,
                            name,
                            fields,
                            size,
                            used,
                            records: 0,
                            serial: self.serial,
                            timestamp,
                            timestamp_end,
                            wanted,
                        };
                        match self.sub_index(msg_id) {
                            Some(k) => self.subs[k] = sub,
                            None => {
                                self.subs.push(sub);
                                if self.by_id.len() <= msg_id as usize {
                                    self.by_id.resize(msg_id as usize + 1, 0);
                                }
                                self.by_id[msg_id as usize] = self.subs.len() as u32;
                            }
                        }
                    }
                    _ => self.stats.skip("bad_subscription"),
                }
            }
            b'P' | b'I' => {
                let Some((key, value)) = key_value(body) else {
                    self.stats.skip("bad_message");
                    return;
                };
                let Some((tyname, name)) = key.split_once(' ') else {
                    self.stats.skip("bad_message");
                    return;
                };
                if ty == b'I' {
                    if tyname.starts_with("char[") && self.info.len() < 1024 {
                        self.info.insert(
                            name.to_string(),
                            String::from_utf8_lossy(value).into_owned(),
                        );
                    }
                    return;
                }
                let v = match Ty::parse(tyname).and_then(|t| t.read(value)) {
                    Some(v) => v,
                    None => {
                        self.stats.skip("bad_message");
                        return;
                    }
                };
                if self.params.contains_key(name) {
                    self.stats.param_changes += 1;
                } else if self.params.len() < MAX_PARAMS {
                    self.params.insert(name.to_string(), v);
                }
            }
            b'O' => {
                if body.len() >= 2 {
                    self.stats.dropouts += 1;
                    self.stats.dropout_ms += u16::from_le_bytes([body[0], body[1]]) as u64;
                } else {
                    self.stats.skip("bad_message");
                }
            }
            // Multi information, default parameters, unsubscribe, log text, sync: nothing needed.
            _ => {}
        }
    }
}

/// `key_len`, key, value of an information or parameter message.
fn key_value(body: &[u8]) -> Option<(String, &[u8])> {
    let n = *body.first()? as usize;
    let key = body.get(1..1 + n)?;
    Some((String::from_utf8_lossy(key).into_owned(), &body[1 + n..]))
}

/// `name:type field;type[n] field;...`
fn parse_format(text: &str) -> Option<(String, RawFormat)> {
    let (name, rest) = text.split_once(':')?;
    let mut fields = Vec::new();
    for part in rest.split(';').filter(|p| !p.trim().is_empty()) {
        let (ty, field) = part.trim().split_once(' ')?;
        let (ty, n) = match ty.split_once('[') {
            Some((t, n)) => (t, Some(n.strip_suffix(']')?.parse::<usize>().ok()?)),
            None => (ty, None),
        };
        if n.is_some_and(|n| n > MAX_FIELDS) {
            return None;
        }
        fields.push((ty.to_string(), n, field.to_string()));
    }
    Some((name.to_string(), fields))
}

/// Flatten format `name` into `out` from byte `base` with name prefix `prefix`; returns its size.
/// `used` is set to the end of the last non-padding field. `None` on an unknown type, nesting
/// deeper than [`MAX_NESTING`] (or a cycle) or more than [`MAX_FIELDS`] fields.
fn flatten(
    formats: &BTreeMap<String, RawFormat>,
    name: &str,
    prefix: &str,
    base: usize,
    out: &mut Vec<Field>,
    used: &mut usize,
    depth: usize,
) -> Option<usize> {
    if depth > MAX_NESTING {
        return None;
    }
    let f = formats.get(name)?;
    let mut off = 0usize;
    for (ty, n, field) in f {
        let count = n.unwrap_or(1);
        let padding = field.starts_with("_padding");
        match Ty::parse(ty) {
            Some(t) => {
                if !padding {
                    for i in 0..count {
                        if out.len() >= MAX_FIELDS {
                            return None;
                        }
                        let fname = match n {
                            Some(_) => format!("{prefix}{field}[{i}]"),
                            None => format!("{prefix}{field}"),
                        };
                        out.push(Field {
                            name: fname,
                            ty: t,
                            offset: base + off + i * t.size(),
                        });
                    }
                }
                off = off.checked_add(t.size().checked_mul(count)?)?;
                if !padding {
                    *used = (*used).max(base + off);
                }
            }
            None => {
                for i in 0..count {
                    let p = match n {
                        Some(_) => format!("{prefix}{field}[{i}]."),
                        None => format!("{prefix}{field}."),
                    };
                    let size = flatten(formats, ty, &p, base + off, out, used, depth + 1)?;
                    off = off.checked_add(size)?;
                }
            }
        }
        if off > 1 << 20 {
            return None;
        }
    }
    Some(off)
}

/// Whether `bytes` begin a ULog file.
pub fn looks_like(bytes: &[u8]) -> bool {
    bytes.len() >= MAGIC.len() && bytes[..MAGIC.len()] == MAGIC
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub fn msg(ty: u8, body: &[u8]) -> Vec<u8> {
        let mut m = (body.len() as u16).to_le_bytes().to_vec();
        m.push(ty);
        m.extend_from_slice(body);
        m
    }

    pub fn header() -> Vec<u8> {
        let mut h = MAGIC.to_vec();
        h.push(1);
        h.extend(0u64.to_le_bytes());
        h
    }

    pub fn param(name: &str, v: f32) -> Vec<u8> {
        let key = format!("float {name}");
        let mut b = vec![key.len() as u8];
        b.extend(key.as_bytes());
        b.extend(v.to_le_bytes());
        msg(b'P', &b)
    }

    pub fn sub(multi: u8, id: u16, name: &str) -> Vec<u8> {
        let mut b = vec![multi];
        b.extend(id.to_le_bytes());
        b.extend(name.as_bytes());
        msg(b'A', &b)
    }

    #[test]
    fn nested_formats_padding_and_multi_instances() {
        let mut f = header();
        f.extend(msg(b'F', b"vec3:float x;float y;float z;"));
        f.extend(msg(
            b'F',
            b"sensor_mag:uint64_t timestamp;uint32_t device_id;vec3 v;uint8_t[2] _padding0;int16_t[2] k;",
        ));
        f.extend(param("CAL_MAG0_XOFF", 0.25));
        f.extend(sub(0, 3, "sensor_mag"));
        f.extend(sub(1, 4, "sensor_mag"));
        f.extend(msg(b'O', &50u16.to_le_bytes()));
        let data = |id: u16, t: u64, x: f32| {
            let mut b = id.to_le_bytes().to_vec();
            b.extend(t.to_le_bytes());
            b.extend(7u32.to_le_bytes());
            for v in [x, 2.0, 3.0] {
                b.extend(v.to_le_bytes());
            }
            b.extend([0, 0]);
            b.extend(5i16.to_le_bytes());
            b.extend((-6i16).to_le_bytes());
            msg(b'D', &b)
        };
        f.extend(data(3, 100, 1.5));
        f.extend([0xFF, 0xFF, b'X']); // damaged header
        f.extend(msg(b'S', &SYNC));
        f.extend(data(4, 200, -1.5));
        f.extend(data(9, 300, 0.0)); // no subscription
        let last = data(3, 400, 9.0);
        f.extend(&last[..last.len() - 3]); // truncated tail
        let mut r = UlogReader::new(&f).unwrap();
        let mut got = vec![];
        while let Some(d) = r.next_data() {
            got.push((
                d.sub.name.clone(),
                d.sub.multi_id,
                d.timestamp_us().unwrap(),
                d.get("v.x").unwrap(),
                d.get("k[1]").unwrap(),
            ));
        }
        assert_eq!(
            got,
            [
                ("sensor_mag".to_string(), 0, 100, 1.5, -6.0),
                ("sensor_mag".to_string(), 1, 200, -1.5, -6.0)
            ]
        );
        assert_eq!(r.params()["CAL_MAG0_XOFF"], 0.25);
        assert_eq!(r.stats.dropouts, 1);
        assert_eq!(r.stats.dropout_ms, 50);
        assert_eq!(r.stats.skipped["resync"], 1);
        assert_eq!(r.stats.skipped["unknown_subscription"], 1);
        assert_eq!(r.stats.skipped["truncated"], 1);
        let s = r.subscriptions().next().unwrap();
        assert!(s.field("_padding0").is_none());
        assert_eq!(s.size, 8 + 4 + 12 + 2 + 4);
    }

    /// A log of more than four windows: data of a used and an unused topic, large log texts,
    /// damaged bytes and sync markers, a truncated tail.
    fn long_log() -> Vec<u8> {
        let mut f = header();
        f.extend(msg(b'F', b"used:uint64_t timestamp;float x;"));
        f.extend(msg(b'F', b"other:uint64_t timestamp;float y;uint8_t[3] z;"));
        f.extend(msg(b'F', b"untimed:float w;"));
        f.extend(sub(0, 1, "used"));
        f.extend(sub(0, 2, "other"));
        f.extend(sub(0, 3, "untimed"));
        let mut x = 0x2545_F491u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        for i in 0..150_000u64 {
            let id: u16 = [1, 2, 2, 3][i as usize % 4];
            let mut b = id.to_le_bytes().to_vec();
            b.extend(i.to_le_bytes());
            b.extend((i as f32).to_le_bytes());
            b.extend([1, 2, 3]);
            f.extend(msg(b'D', &b));
            match next() % 997 {
                0 => {
                    // Damaged bytes, then a sync marker to read on from.
                    f.extend((0..1 + next() % 300).map(|_| next() as u8 | 0x80));
                    f.extend(msg(b'S', &SYNC));
                }
                1 => f.extend(msg(b'S', &SYNC)),
                2 => f.extend(msg(b'L', &vec![b'.'; 40_000 + next() as usize % 25_000])),
                _ => {}
            }
        }
        f.truncate(f.len() - 5);
        f
    }

    /// A returned record: topic, timestamp, first float.
    type Got = (String, Option<u64>, f64);

    /// What a reader returns, and its counts: stats, bytes read, records per subscription.
    fn read_all(mut r: UlogReader<'_>, only_used: bool) -> (Vec<Got>, UlogStats, usize, Vec<u64>) {
        if only_used {
            r.only_topics(|name| name == "used");
        }
        let mut got = Vec::new();
        while let Some(d) = r.next_data() {
            let v = d.value(1).or_else(|| d.value(0)).unwrap();
            got.push((d.sub.name.clone(), d.timestamp_us(), v));
        }
        let records = r.subscriptions().map(|s| s.records).collect();
        (got, r.stats.clone(), r.position(), records)
    }

    #[test]
    fn a_log_streamed_through_a_window_reads_as_the_whole_bytes() {
        let log = long_log();
        assert!(log.len() > 4 * crate::io::window::STREAM_CHUNK_BYTES);
        for only_used in [false, true] {
            let whole = read_all(UlogReader::new(&log).unwrap(), only_used);
            for step in [1 << 20, 4093, 65_537] {
                let trickle = crate::io::decode::tests::Trickle { bytes: &log, step };
                let streamed = read_all(UlogReader::from_reader(trickle).unwrap(), only_used);
                assert_eq!(streamed.0.len(), whole.0.len());
                assert!(
                    streamed == whole,
                    "step {step}: {:?} vs {:?}",
                    streamed.1,
                    whole.1
                );
            }
            assert_eq!(whole.2, log.len());
            assert!(whole.1.skipped["resync"] > 50, "{:?}", whole.1);
            assert_eq!(whole.1.skipped["truncated"], 1);
        }
    }

    #[test]
    fn records_of_topics_left_out_are_counted_not_returned() {
        let log = long_log();
        let all = read_all(UlogReader::new(&log).unwrap(), false);
        let used = read_all(UlogReader::new(&log).unwrap(), true);
        // The same messages read and counted per topic.
        assert_eq!(used.1, all.1);
        assert_eq!(used.3, all.3);
        // Returned: the first record, then every record of `used` and of `untimed` (no timestamp).
        let keep = |(k, r): (usize, &Got)| k == 0 || r.0 == "used" || r.0 == "untimed";
        let expected: Vec<_> = all
            .0
            .iter()
            .enumerate()
            .filter(|x| keep(*x))
            .map(|(_, r)| r.clone())
            .collect();
        assert_eq!(used.0, expected);
        assert!(used.0.iter().filter(|r| r.0 == "other").count() == 0);
        assert!(all.0.iter().filter(|r| r.0 == "other").count() > 70_000);
    }

    #[test]
    fn a_file_cut_anywhere_in_its_last_message_is_a_counted_skip() {
        let mut f = header();
        f.extend(msg(b'F', b"used:uint64_t timestamp;float x;"));
        f.extend(sub(0, 1, "used"));
        let mut b = 1u16.to_le_bytes().to_vec();
        b.extend(7u64.to_le_bytes());
        b.extend(1.5f32.to_le_bytes());
        f.extend(msg(b'D', &b));
        f.extend(msg(b'D', &b));
        let last = f.len() - (b.len() + 3);
        for cut in last + 1..f.len() {
            let trickle = crate::io::decode::tests::Trickle {
                bytes: &f[..cut],
                step: 3,
            };
            let (got, stats, read, _) = read_all(UlogReader::from_reader(trickle).unwrap(), false);
            assert_eq!(got.len(), 1, "cut at {cut}");
            assert_eq!(stats.skipped["truncated"], 1, "cut at {cut}");
            assert_eq!(read, cut);
        }
        assert!(UlogReader::from_reader(&f[..15]).is_none());
    }

    #[test]
    fn a_cyclic_format_is_refused() {
        let mut f = header();
        f.extend(msg(b'F', b"a:b x;"));
        f.extend(msg(b'F', b"b:a y;"));
        f.extend(sub(0, 1, "a"));
        let mut r = UlogReader::new(&f).unwrap();
        assert!(r.next_data().is_none());
        assert_eq!(r.stats.skipped["bad_subscription"], 1);
    }
}
