//! MAVFTP (FILE_TRANSFER_PROTOCOL, message 110) as the service answers it, pure: the request and
//! reply packets, the packed parameter file a ground station downloads as `@PARAM/param.pck`, and
//! the few open files of a small read-only server.
//!
//! A ground station that speaks MAVFTP (MAVProxy's `param fetch`, QGroundControl) first asks for
//! the parameters as one file and falls back to PARAM_REQUEST_LIST only after its request timed
//! out (MAVProxy: about 11 s of retries). The service serves that file at once, so a fetch takes
//! one round trip and a burst; every other path or operation gets a NAK with the reason, as
//! ArduPilot's server (`GCS_FTP`, `AP_Filesystem_Param`) answers.
//!
//! Packet layout (the message's 251-byte `payload`, little endian): `seq_number` u16, `session`
//! u8, `opcode` u8, `size` u8 (bytes of `data` used), `req_opcode` u8 (the request a reply
//! answers), `burst_complete` u8, padding u8, `offset` u32, `data` 239 bytes. A reply carries the
//! request's `session` byte (the protocol's handle of an open file) and `seq_number + 1`; the packets of a burst count on from there.
//!
//! The packed parameter file: a header (`magic` 0x671b, `num_params`, `total_params`, u16 each),
//! then per parameter a type byte (low four bits: 4 = float; high four bits: flags, 0), a length
//! byte (low four bits: bytes shared with the previous name, 0..15; high four bits: the length
//! of the rest of the name less one), the rest of the name and the value (f32). The file is made
//! once per open, so every read of a download sees the same bytes (no padding is needed, unlike
//! a server that packs again on each read).

use mavlink::dialects::ardupilotmega::{MavMessage, FILE_TRANSFER_PROTOCOL_DATA};
use std::collections::VecDeque;

/// Bytes of `data` in one packet.
pub const DATA_MAX: usize = 239;
/// Bytes before `data`.
const HEADER_LEN: usize = 12;
/// The parameter file's path, as ArduPilot names it (options after a `?` are accepted and
/// ignored: `?withdefaults=1` is answered without defaults).
pub const PARAM_FILE: &str = "@PARAM/param.pck";
/// Magic number of a packed parameter file without default values.
pub const PACKED_MAGIC: u16 = 0x671b;
/// Files open at once (the oldest is closed for a new one): one per ground station's open
/// handle (`session` byte).
pub const MAX_OPEN_FILES: usize = 4;

/// An operation (the `opcode` and `req_opcode` fields).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Opcode {
    None,
    TerminateSession,
    ResetSessions,
    ListDirectory,
    OpenFileRO,
    ReadFile,
    BurstReadFile,
    Ack,
    Nak,
    /// Any other (writes, renames, CRC ...): not served.
    Other(u8),
}

impl Opcode {
    /// The operation numbered `code`.
    pub fn of(code: u8) -> Opcode {
        match code {
            0 => Opcode::None,
            1 => Opcode::TerminateSession,
            2 => Opcode::ResetSessions,
            3 => Opcode::ListDirectory,
            4 => Opcode::OpenFileRO,
            5 => Opcode::ReadFile,
            15 => Opcode::BurstReadFile,
            128 => Opcode::Ack,
            129 => Opcode::Nak,
            other => Opcode::Other(other),
        }
    }

    /// Its number on the wire.
    pub fn code(self) -> u8 {
        match self {
            Opcode::None => 0,
            Opcode::TerminateSession => 1,
            Opcode::ResetSessions => 2,
            Opcode::ListDirectory => 3,
            Opcode::OpenFileRO => 4,
            Opcode::ReadFile => 5,
            Opcode::BurstReadFile => 15,
            Opcode::Ack => 128,
            Opcode::Nak => 129,
            Opcode::Other(c) => c,
        }
    }
}

/// Why a request was refused: the first `data` byte of a NAK.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FtpError {
    /// Read past the end of the file (ends a download).
    EndOfFile = 6,
    /// The operation is not served here.
    UnknownCommand = 7,
    /// No such file, or no file open under the request's `session` byte.
    FileNotFound = 10,
}

/// One FILE_TRANSFER_PROTOCOL packet.
#[derive(Debug, Clone, PartialEq)]
pub struct FtpPacket {
    pub seq_number: u16,
    pub session: u8,
    pub opcode: Opcode,
    pub req_opcode: Opcode,
    pub burst_complete: bool,
    pub offset: u32,
    /// The `size` bytes of `data` used (at most [`DATA_MAX`]).
    pub data: Vec<u8>,
}

impl FtpPacket {
    /// The packet in a message's payload; a `size` past the data field is cut to it.
    pub fn parse(payload: &[u8; 251]) -> FtpPacket {
        let size = (payload[4] as usize).min(DATA_MAX);
        FtpPacket {
            seq_number: u16::from_le_bytes([payload[0], payload[1]]),
            session: payload[2],
            opcode: Opcode::of(payload[3]),
            req_opcode: Opcode::of(payload[5]),
            burst_complete: payload[6] != 0,
            offset: u32::from_le_bytes([payload[8], payload[9], payload[10], payload[11]]),
            data: payload[HEADER_LEN..HEADER_LEN + size].to_vec(),
        }
    }

    /// The message's payload (unused data bytes zero).
    pub fn to_payload(&self) -> [u8; 251] {
        let mut p = [0u8; 251];
        let n = self.data.len().min(DATA_MAX);
        p[0..2].copy_from_slice(&self.seq_number.to_le_bytes());
        p[2] = self.session;
        p[3] = self.opcode.code();
        p[4] = n as u8;
        p[5] = self.req_opcode.code();
        p[6] = u8::from(self.burst_complete);
        p[8..12].copy_from_slice(&self.offset.to_le_bytes());
        p[HEADER_LEN..HEADER_LEN + n].copy_from_slice(&self.data[..n]);
        p
    }

    /// The request's file path: `data` up to the first NUL.
    fn path(&self) -> String {
        let end = self
            .data
            .iter()
            .position(|&b| b == 0)
            .unwrap_or(self.data.len());
        String::from_utf8_lossy(&self.data[..end]).into_owned()
    }
}

/// The FILE_TRANSFER_PROTOCOL message carrying `packet` to (`target_system`, `target_component`).
pub fn message(target_system: u8, target_component: u8, packet: &FtpPacket) -> MavMessage {
    MavMessage::FILE_TRANSFER_PROTOCOL(FILE_TRANSFER_PROTOCOL_DATA {
        target_network: 0,
        target_system,
        target_component,
        payload: packet.to_payload(),
    })
}

/// Whether `path` names the packed parameter file (with or without options after `?`).
pub fn is_param_file(path: &str) -> bool {
    path.strip_prefix(PARAM_FILE)
        .is_some_and(|rest| rest.is_empty() || rest.starts_with('?'))
}

/// The packed parameter file of `params` (names of 1 to 16 ASCII bytes, each a float), in their
/// order; a name longer than 16 bytes is cut to 16, as PARAM_VALUE cuts it.
pub fn pack_params(params: &[(&str, f32)]) -> Vec<u8> {
    let n = params.len().min(u16::MAX as usize) as u16;
    let mut out = Vec::with_capacity(6 + params.len() * 16);
    out.extend_from_slice(&PACKED_MAGIC.to_le_bytes());
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&n.to_le_bytes());
    let mut last: &[u8] = &[];
    for (name, value) in params.iter().take(n as usize) {
        let name = &name.as_bytes()[..name.len().min(16)];
        let shared = name.iter().zip(last).take_while(|(a, b)| a == b).count();
        // At least one byte of its own (a name that is the previous one's start shares one less),
        // and at most 15 shared.
        let shared = shared.min(name.len().saturating_sub(1)).min(15);
        let rest = &name[shared..];
        out.push(4);
        out.push(shared as u8 | (((rest.len().max(1) - 1) as u8) << 4));
        out.extend_from_slice(rest);
        out.extend_from_slice(&value.to_le_bytes());
        last = name;
    }
    out
}

/// A file open for reading: whose session, and its bytes as they were when opened.
#[derive(Debug)]
struct OpenFile {
    /// (system, component, session) of the ground station that opened it.
    key: (u8, u8, u8),
    bytes: Vec<u8>,
}

/// The read-only server: the parameter file open for each ground-station session (at most
/// [`MAX_OPEN_FILES`]).
#[derive(Debug, Default)]
pub struct FtpServer {
    open: VecDeque<OpenFile>,
}

impl FtpServer {
    /// The replies to request `req` from (`system`, `component`): one packet, or a burst for
    /// BurstReadFile; none for a stray ACK or NAK. `param_file` makes the parameter file's bytes
    /// when it is opened.
    pub fn handle(
        &mut self,
        from: (u8, u8),
        req: &FtpPacket,
        param_file: impl FnOnce() -> Vec<u8>,
    ) -> Vec<FtpPacket> {
        let key = (from.0, from.1, req.session);
        let reply = |opcode: Opcode, offset: u32, data: Vec<u8>| FtpPacket {
            seq_number: req.seq_number.wrapping_add(1),
            session: req.session,
            opcode,
            req_opcode: req.opcode,
            burst_complete: false,
            offset,
            data,
        };
        let nak = |e: FtpError| reply(Opcode::Nak, 0, vec![e as u8]);
        match req.opcode {
            Opcode::Ack | Opcode::Nak => vec![],
            Opcode::None => vec![reply(Opcode::Ack, 0, vec![])],
            Opcode::TerminateSession => {
                self.open.retain(|f| f.key != key);
                vec![reply(Opcode::Ack, 0, vec![])]
            }
            Opcode::ResetSessions => {
                self.open.retain(|f| (f.key.0, f.key.1) != from);
                vec![reply(Opcode::Ack, 0, vec![])]
            }
            Opcode::OpenFileRO if is_param_file(&req.path()) => {
                // A repeated open (its reply lost) opens the file again.
                self.open.retain(|f| f.key != key);
                if self.open.len() >= MAX_OPEN_FILES {
                    self.open.pop_front();
                }
                let bytes = param_file();
                let size = (bytes.len() as u32).to_le_bytes().to_vec();
                self.open.push_back(OpenFile { key, bytes });
                vec![reply(Opcode::Ack, 0, size)]
            }
            Opcode::OpenFileRO => vec![nak(FtpError::FileNotFound)],
            Opcode::ReadFile | Opcode::BurstReadFile => {
                let Some(file) = self.open.iter().find(|f| f.key == key) else {
                    return vec![nak(FtpError::FileNotFound)];
                };
                read(&file.bytes, req)
            }
            Opcode::ListDirectory | Opcode::Other(_) => vec![nak(FtpError::UnknownCommand)],
        }
    }
}

/// The replies to a read of `bytes`: ReadFile one chunk at the offset (or end of file);
/// BurstReadFile every chunk from the offset to the end, then end of file, the last packet
/// marked `burst_complete`. Chunks are the request's size (all of `data` when 0).
fn read(bytes: &[u8], req: &FtpPacket) -> Vec<FtpPacket> {
    // A read request's `size` is the chunk it asks for (its data bytes say nothing else).
    let chunk = match req.data.len() {
        0 => DATA_MAX,
        asked => asked.min(DATA_MAX),
    };
    let mut out = Vec::new();
    let mut offset = req.offset as usize;
    let mut seq = req.seq_number.wrapping_add(1);
    loop {
        let packet = |opcode, offset: usize, data: Vec<u8>, seq| FtpPacket {
            seq_number: seq,
            session: req.session,
            opcode,
            req_opcode: req.opcode,
            burst_complete: false,
            offset: offset as u32,
            data,
        };
        if offset >= bytes.len() {
            let mut eof = packet(Opcode::Nak, offset, vec![FtpError::EndOfFile as u8], seq);
            eof.burst_complete = req.opcode == Opcode::BurstReadFile;
            out.push(eof);
            return out;
        }
        let end = (offset + chunk).min(bytes.len());
        out.push(packet(
            Opcode::Ack,
            offset,
            bytes[offset..end].to_vec(),
            seq,
        ));
        if req.opcode == Opcode::ReadFile {
            return out;
        }
        offset = end;
        seq = seq.wrapping_add(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(opcode: Opcode, session: u8, offset: u32, data: &[u8]) -> FtpPacket {
        FtpPacket {
            seq_number: 41,
            session,
            opcode,
            req_opcode: Opcode::None,
            burst_complete: false,
            offset,
            data: data.to_vec(),
        }
    }

    /// The packed file read back as the format says, independently of [`pack_params`].
    fn unpack(bytes: &[u8]) -> Vec<(String, f32)> {
        assert_eq!(u16::from_le_bytes([bytes[0], bytes[1]]), PACKED_MAGIC);
        let total = u16::from_le_bytes([bytes[4], bytes[5]]) as usize;
        let (mut at, mut last, mut out) = (6, Vec::<u8>::new(), Vec::new());
        while at < bytes.len() {
            assert_eq!(bytes[at] & 0x0f, 4, "a float");
            let shared = (bytes[at + 1] & 0x0f) as usize;
            let own = ((bytes[at + 1] >> 4) + 1) as usize;
            let mut name = last[..shared].to_vec();
            name.extend_from_slice(&bytes[at + 2..at + 2 + own]);
            let v = &bytes[at + 2 + own..at + 6 + own];
            out.push((
                String::from_utf8(name.clone()).unwrap(),
                f32::from_le_bytes([v[0], v[1], v[2], v[3]]),
            ));
            last = name;
            at += 6 + own;
        }
        assert_eq!(out.len(), total);
        out
    }

    #[test]
    fn a_packet_survives_the_payload_and_a_size_past_the_data_is_cut() {
        let p = FtpPacket {
            seq_number: 0xbeef,
            session: 7,
            opcode: Opcode::Ack,
            req_opcode: Opcode::BurstReadFile,
            burst_complete: true,
            offset: 0x0102_0304,
            data: vec![1, 2, 3],
        };
        assert_eq!(FtpPacket::parse(&p.to_payload()), p);
        let mut raw = p.to_payload();
        raw[4] = 255;
        assert_eq!(FtpPacket::parse(&raw).data.len(), DATA_MAX);
    }

    #[test]
    fn the_packed_file_lists_every_name_and_value_in_order() {
        let params = [
            ("CAL_MAG_MODE", 1.0),
            ("CAL_MAG", 2.0),
            ("MAG0_OFS_X", 12.5),
            ("MAG0_OFS_Y", f32::NAN),
            ("A_NAME_OF_16_BYT", -3.0),
            ("A_NAME_OF_16_BYTES_AND_MORE", 4.0),
        ];
        let back = unpack(&pack_params(&params));
        assert_eq!(back.len(), params.len());
        for ((n, v), (bn, bv)) in params.iter().zip(&back) {
            assert_eq!(&n[..n.len().min(16)], bn);
            assert!(v.to_bits() == bv.to_bits(), "{n}: {v} != {bv}");
        }
        // Shared starts are not repeated: "MAG0_OFS_Y" takes 1 byte of its own name.
        let packed = pack_params(&params[2..4]);
        assert_eq!(packed.len(), 6 + (2 + 10 + 4) + (2 + 1 + 4));
    }

    #[test]
    fn the_parameter_file_is_served_in_a_burst_and_every_other_path_is_refused() {
        let names: Vec<String> = (0..71).map(|i| format!("PARAM_NUMBER_{i}")).collect();
        let params: Vec<(&str, f32)> = names.iter().map(|n| (n.as_str(), 1.5)).collect();
        let file = pack_params(&params);
        let mut server = FtpServer::default();
        let gcs = (255, 190);
        let open = |s: &mut FtpServer, path: &str| {
            s.handle(
                gcs,
                &request(Opcode::OpenFileRO, 3, 0, path.as_bytes()),
                || file.clone(),
            )
        };
        let nak = open(&mut server, "@SYS/threads.txt");
        assert_eq!(nak[0].opcode, Opcode::Nak);
        assert_eq!(nak[0].data, vec![FtpError::FileNotFound as u8]);
        // Nothing open in the session yet.
        let read = server.handle(gcs, &request(Opcode::BurstReadFile, 3, 0, &[]), Vec::new);
        assert_eq!(read[0].data, vec![FtpError::FileNotFound as u8]);
        let ack = open(&mut server, "@PARAM/param.pck?withdefaults=1");
        assert_eq!(
            (ack[0].opcode, ack[0].req_opcode),
            (Opcode::Ack, Opcode::OpenFileRO)
        );
        assert_eq!((ack[0].seq_number, ack[0].session), (42, 3));
        assert_eq!(ack[0].data, (file.len() as u32).to_le_bytes().to_vec());
        let burst = server.handle(
            gcs,
            &request(Opcode::BurstReadFile, 3, 0, &[0; 80]),
            Vec::new,
        );
        let (data, end) = burst.split_at(burst.len() - 1);
        let got: Vec<u8> = data.iter().flat_map(|p| p.data.clone()).collect();
        assert_eq!(got, file);
        assert!(data
            .iter()
            .all(|p| p.opcode == Opcode::Ack && p.data.len() <= 80));
        assert!(data
            .windows(2)
            .all(|w| w[1].seq_number == w[0].seq_number + 1));
        assert_eq!(end[0].data, vec![FtpError::EndOfFile as u8]);
        assert!(end[0].burst_complete);
        assert_eq!(unpack(&got).len(), 71);
        // A gap read again, then past the end.
        let one = server.handle(gcs, &request(Opcode::ReadFile, 3, 80, &[0; 80]), Vec::new);
        assert_eq!(one[0].data, file[80..160].to_vec());
        let past = file.len() as u32;
        let eof = server.handle(gcs, &request(Opcode::ReadFile, 3, past, &[0; 80]), Vec::new);
        assert_eq!(eof[0].data, vec![FtpError::EndOfFile as u8]);
        assert!(!eof[0].burst_complete);
        let unknown = server.handle(gcs, &request(Opcode::Other(7), 3, 0, b"x"), Vec::new);
        assert_eq!(unknown[0].data, vec![FtpError::UnknownCommand as u8]);
        let done = server.handle(gcs, &request(Opcode::TerminateSession, 3, 0, &[]), Vec::new);
        assert_eq!(done[0].opcode, Opcode::Ack);
        let gone = server.handle(gcs, &request(Opcode::ReadFile, 3, 0, &[0; 10]), Vec::new);
        assert_eq!(gone[0].data, vec![FtpError::FileNotFound as u8]);
    }

    #[test]
    fn open_files_are_bounded_and_the_oldest_closes() {
        let mut server = FtpServer::default();
        for session in 0..=MAX_OPEN_FILES as u8 {
            let open = request(Opcode::OpenFileRO, session, 0, PARAM_FILE.as_bytes());
            server.handle((255, 190), &open, || vec![1, 2, 3]);
        }
        assert_eq!(server.open.len(), MAX_OPEN_FILES);
        let first = server.handle((255, 190), &request(Opcode::ReadFile, 0, 0, &[]), Vec::new);
        assert_eq!(first[0].data, vec![FtpError::FileNotFound as u8]);
        let last = request(Opcode::ReadFile, MAX_OPEN_FILES as u8, 0, &[]);
        assert_eq!(
            server.handle((255, 190), &last, Vec::new)[0].data,
            vec![1, 2, 3]
        );
    }
}
