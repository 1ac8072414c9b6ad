//! MAVLink framing: one v1 or v2 frame checked by its CRC and parsed by the dialect
//! ([`parse_frame`]), and a byte stream cut into frames with resynchronisation ([`FrameDecoder`]).

use super::stats::DecodeStats;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavlinkVersion, Message};

/// Tables of the MAVLink checksum (CRC-16/MCRF4XX: reflected polynomial 0x8408, initial 0xFFFF, no
/// final XOR), built at compile time: `CRC_TABLES[0]` is the usual one-byte table and
/// `CRC_TABLES[k][i]` is the effect of byte `i` followed by `k` zero bytes, so eight bytes are
/// folded in per step ("slicing by 8"; the CRC is linear, so the eight lookups combine by XOR).
const CRC_TABLES: [[u16; 256]; 8] = {
    let mut t = [[0u16; 256]; 8];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u16;
        let mut b = 0;
        while b < 8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0x8408
            } else {
                c >> 1
            };
            b += 1;
        }
        t[0][i] = c;
        i += 1;
    }
    let mut k = 1;
    while k < 8 {
        let mut i = 0;
        while i < 256 {
            let prev = t[k - 1][i];
            t[k][i] = (prev >> 8) ^ t[0][(prev & 0xFF) as usize];
            i += 1;
        }
        k += 1;
    }
    t
};

/// The MAVLink frame checksum over `data` (the frame after the magic byte, up to the payload's
/// end) and the message's extra CRC byte: the same value as `mavlink::calculate_crc`, eight bytes
/// per step instead of a bit loop per byte (that loop was a tenth of replay time).
pub(crate) fn frame_crc(data: &[u8], extra_crc: u8) -> u16 {
    let t = &CRC_TABLES;
    let mut crc = 0xFFFFu16;
    let mut chunks = data.chunks_exact(8);
    for c in &mut chunks {
        let x = crc ^ u16::from_le_bytes([c[0], c[1]]);
        crc = t[7][(x & 0xFF) as usize]
            ^ t[6][(x >> 8) as usize]
            ^ t[5][c[2] as usize]
            ^ t[4][c[3] as usize]
            ^ t[3][c[4] as usize]
            ^ t[2][c[5] as usize]
            ^ t[1][c[6] as usize]
            ^ t[0][c[7] as usize];
    }
    for &b in chunks.remainder().iter().chain(std::iter::once(&extra_crc)) {
        crc = (crc >> 8) ^ t[0][((crc ^ b as u16) & 0xFF) as usize];
    }
    crc
}

/// A decoded frame.
#[derive(Debug, Clone)]
pub struct Frame {
    pub version: MavlinkVersion,
    pub system_id: u8,
    pub component_id: u8,
    pub message: MavMessage,
}

/// Result of looking for one frame at the start of a buffer.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)] // The frame is moved once, into where it is kept: no box.
pub enum FrameParse {
    /// A good frame and the number of bytes it used.
    Frame(Frame, usize),
    /// The buffer holds the start of a frame but not all of it.
    Incomplete,
    /// Not a frame here (or a damaged one): skip `usize` bytes, counted under the reason.
    Skip(usize, SkipReason),
}

/// Why bytes of a MAVLink stream were skipped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkipReason {
    /// No frame starts here: look for the next magic byte.
    Resync,
    /// A whole frame of a message this build does not know.
    UnknownMessage,
    /// A frame whose checksum does not match: its first byte is skipped.
    BadCrc,
    /// A frame whose payload the bindings refuse.
    BadPayload,
}

impl SkipReason {
    /// The name counted in [`DecodeStats::skipped`] and shown in reports.
    pub fn name(self) -> &'static str {
        match self {
            SkipReason::Resync => "resync",
            SkipReason::UnknownMessage => "unknown_message",
            SkipReason::BadCrc => "bad_crc",
            SkipReason::BadPayload => "bad_payload",
        }
    }

    /// A whole frame is skipped (the stream goes on after it), not a byte to resynchronise.
    pub(crate) fn whole_frame(self) -> bool {
        matches!(self, SkipReason::UnknownMessage | SkipReason::BadPayload)
    }
}

pub(super) const V1_MAGIC: u8 = 0xFE;
pub(super) const V2_MAGIC: u8 = 0xFD;

/// Parse one MAVLink v1 or v2 frame at the start of `buf`, checking the CRC with the dialect's extra
/// CRC. Signed v2 frames are accepted (the signature is not checked).
pub fn parse_frame(buf: &[u8]) -> FrameParse {
    let Some(&magic) = buf.first() else {
        return FrameParse::Incomplete;
    };
    let (version, header_len, total) = match magic {
        V1_MAGIC => {
            if buf.len() < 2 {
                return FrameParse::Incomplete;
            }
            let len = buf[1] as usize;
            (MavlinkVersion::V1, 6usize, 6 + len + 2)
        }
        V2_MAGIC => {
            if buf.len() < 3 {
                return FrameParse::Incomplete;
            }
            let len = buf[1] as usize;
            let incompat = buf[2];
            if incompat & !0x01 != 0 {
                return FrameParse::Skip(1, SkipReason::Resync);
            }
            let sig = if incompat & 0x01 != 0 { 13 } else { 0 };
            (MavlinkVersion::V2, 10usize, 10 + len + 2 + sig)
        }
        _ => return FrameParse::Skip(1, SkipReason::Resync),
    };
    if buf.len() < total {
        return FrameParse::Incomplete;
    }
    let len = buf[1] as usize;
    let (sys, comp, msgid) = match version {
        MavlinkVersion::V1 => (buf[3], buf[4], buf[5] as u32),
        MavlinkVersion::V2 => (
            buf[5],
            buf[6],
            u32::from_le_bytes([buf[7], buf[8], buf[9], 0]),
        ),
    };
    let payload = &buf[header_len..header_len + len];
    let crc_got = u16::from_le_bytes([buf[header_len + len], buf[header_len + len + 1]]);
    if !known_message(msgid) {
        // The CRC cannot be checked without the message's extra CRC: skip the frame as unknown.
        return FrameParse::Skip(total, SkipReason::UnknownMessage);
    }
    let crc = frame_crc(&buf[1..header_len + len], MavMessage::extra_crc(msgid));
    if crc != crc_got {
        return FrameParse::Skip(1, SkipReason::BadCrc);
    }
    match MavMessage::parse(version, msgid, payload) {
        Ok(message) => FrameParse::Frame(
            Frame {
                version,
                system_id: sys,
                component_id: comp,
                message,
            },
            total,
        ),
        Err(_) => FrameParse::Skip(total, SkipReason::BadPayload),
    }
}

/// Whether the dialect knows message `id`. The dialect only answers by building a default
/// message, a few hundred bytes, so the answers for ids below 65536 (all of ardupilotmega's) are
/// kept in a bit set built on first use.
pub(super) fn known_message(id: u32) -> bool {
    static KNOWN: std::sync::OnceLock<Vec<u64>> = std::sync::OnceLock::new();
    let known = KNOWN.get_or_init(|| {
        let mut bits = vec![0u64; 1 << 10];
        for i in 0..1u32 << 16 {
            if MavMessage::default_message_from_id(i).is_some() {
                bits[(i >> 6) as usize] |= 1 << (i & 63);
            }
        }
        bits
    });
    match known.get((id >> 6) as usize) {
        Some(w) => w & (1 << (id & 63)) != 0,
        None => MavMessage::default_message_from_id(id).is_some(),
    }
}

/// Streaming frame decoder for byte streams (serial, TCP): feed bytes, take frames.
#[derive(Debug, Default)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    pub stats: DecodeStats,
}

impl FrameDecoder {
    pub fn new() -> Self {
        Self::default()
    }
    /// Append bytes and return every complete frame now available.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Frame> {
        self.buf.extend_from_slice(bytes);
        let mut out = Vec::new();
        let mut pos = 0;
        while pos < self.buf.len() {
            match parse_frame(&self.buf[pos..]) {
                FrameParse::Frame(f, n) => {
                    out.push(f);
                    pos += n;
                }
                FrameParse::Incomplete => break,
                FrameParse::Skip(n, why) => {
                    // Count a bad frame once, not once per byte of it.
                    if why != SkipReason::Resync
                        || self.buf[pos] == V1_MAGIC
                        || self.buf[pos] == V2_MAGIC
                    {
                        self.stats.skip(why.name());
                    }
                    pos += n;
                }
            }
        }
        self.buf.drain(..pos);
        // Bound memory: a frame is at most 280 bytes.
        if self.buf.len() > 4096 {
            let drop = self.buf.len() - 280;
            self.stats.skip_n("resync", 1);
            self.buf.drain(..drop);
        }
        out
    }
}
