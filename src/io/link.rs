//! Live transports: the only code that knows sockets, serial ports and the wall clock of a replay.
//!
//! One address per link (`udpin:`, `udpout:`, `tcpout:`, `tcpin:`, `serial:`, `file:`, `sim:`),
//! like rust-mavlink's `connect`, but the bytes are read here and framed by
//! [`crate::io::decode`], so MAVLink v1 and v2 are both accepted and every bad frame is counted.
//!
//! Each link runs as one tokio task started by [`spawn_link`] and reports what it reads as
//! [`Inbound`] items on a shared bounded channel:
//! - live links (udp, tcp, serial) never wait on that channel: when it is full the item is
//!   dropped and counted in [`LinkCounters::inbound_dropped`];
//! - replays (`file:`, `sim:`) wait for room instead (nothing is lost), paced by their own
//!   timestamps divided by `speed` (0 = as fast as possible).
//!
//! A live link that fails (refused, closed, serial port gone, I/O error) reports
//! [`LinkStatus::Lost`] once, then retries with exponential backoff until it is back
//! ([`LinkStatus::Connected`]). Nothing here panics on bad input or a vanished peer, and every
//! loop watches the shutdown flag. How the first opening went (the bound local address, the port
//! the system chose for port 0, or why it failed) is told once, on [`LinkHandle::opening`].

use crate::io::decode::{
    self, DecodeStats, Frame, FrameDecoder, FrameParse, SkipReason, TlogRecords,
};

mod udp_batch;
use crate::error::Error;
use crate::types::{Sample, STANDARD_GRAVITY_MPS2};
use std::collections::BTreeMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;

// ---------------------------------------------------------------------------------------------
// Addresses

/// Where a link reads from (and writes to).
#[derive(Debug, Clone, PartialEq)]
pub enum Address {
    /// `udpin:IP:PORT`: bind this address; replies go to the last sender.
    UdpIn(SocketAddr),
    /// `udpout:IP:PORT`: send to this address; receive on the same socket.
    UdpOut(SocketAddr),
    /// `tcpout:HOST:PORT`: connect (reconnect with backoff).
    TcpOut(String),
    /// `tcpin:IP:PORT`: listen, one client at a time.
    TcpIn(SocketAddr),
    /// `serial:PATH:BAUD`.
    Serial { path: String, baud: u32 },
    /// `file:PATH[?speed=N]`: a .tlog or a CSV (.csv, .csv.gz). Speed 0 = as fast as possible;
    /// 1 (the default) = recorded pace.
    File { path: PathBuf, speed: f64 },
    /// `sim:SCENARIO[?seed=N&speed=N]`: a built-in scenario name or a path to a scenario .toml.
    Sim {
        scenario: String,
        seed: u64,
        speed: f64,
    },
}

/// The accepted address forms, for error messages.
pub(crate) const ADDRESS_FORMS: &str =
    "udpin:IP:PORT, udpout:IP:PORT, tcpout:HOST:PORT, tcpin:IP:PORT, \
serial:PATH:BAUD, file:PATH[?speed=N], sim:SCENARIO[?seed=N&speed=N]";

/// Seed of `sim:` when the address names none (the same as `imucald simulate`).
pub(crate) const DEFAULT_SIM_SEED: u64 = 1;

fn source_err(s: &str, why: impl std::fmt::Display) -> Error {
    Error::Config {
        key: "source".into(),
        message: format!("`{s}`: {why} (accepted forms: {ADDRESS_FORMS})"),
    }
}

fn parse_socket(s: &str, scheme: &str, rest: &str) -> Result<SocketAddr, Error> {
    rest.parse::<SocketAddr>().map_err(|_| {
        source_err(
            s,
            format!(
                "{scheme}: needs an IP address and port such as {scheme}:127.0.0.1:14550 \
                 (IPv6: {scheme}:[::1]:14550; host names are not resolved here)"
            ),
        )
    })
}

/// Split `PATH?k=v&k=v` into the path and its options. Unknown keys and bad numbers are errors.
fn split_query<'a>(
    s: &str,
    rest: &'a str,
    allowed: &[&str],
) -> Result<(&'a str, BTreeMap<String, String>), Error> {
    let (path, query) = match rest.rfind('?') {
        Some(i) => (&rest[..i], Some(&rest[i + 1..])),
        None => (rest, None),
    };
    let mut opts = BTreeMap::new();
    if let Some(q) = query {
        for kv in q.split('&').filter(|kv| !kv.is_empty()) {
            let Some((k, v)) = kv.split_once('=') else {
                return Err(source_err(
                    s,
                    format!("option `{kv}` needs a value (`key=value`)"),
                ));
            };
            if !allowed.contains(&k) {
                return Err(source_err(
                    s,
                    format!("unknown option `{k}` (known: {})", allowed.join(", ")),
                ));
            }
            opts.insert(k.to_string(), v.to_string());
        }
    }
    Ok((path, opts))
}

fn parse_speed(s: &str, v: Option<&String>) -> Result<f64, Error> {
    match v {
        None => Ok(1.0),
        Some(v) => match v.parse::<f64>() {
            Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
            _ => Err(source_err(
                s,
                format!("speed `{v}` must be a number >= 0 (0 = as fast as possible, 1 = recorded pace)"),
            )),
        },
    }
}

impl Address {
    /// Parse a link address. Errors are `Error::Config { key: "source" }` naming the accepted forms.
    pub fn parse(s: &str) -> Result<Address, Error> {
        let s = s.trim();
        let Some((scheme, rest)) = s.split_once(':') else {
            return Err(source_err(s, "no scheme"));
        };
        match scheme {
            "udpin" => Ok(Address::UdpIn(parse_socket(s, scheme, rest)?)),
            "udpout" => Ok(Address::UdpOut(parse_socket(s, scheme, rest)?)),
            "tcpin" => Ok(Address::TcpIn(parse_socket(s, scheme, rest)?)),
            "tcpout" => {
                let ok = rest
                    .rsplit_once(':')
                    .is_some_and(|(h, p)| !h.is_empty() && p.parse::<u16>().is_ok_and(|p| p > 0));
                if ok {
                    Ok(Address::TcpOut(rest.to_string()))
                } else {
                    Err(source_err(
                        s,
                        "tcpout: needs HOST:PORT such as tcpout:127.0.0.1:5760 (port 1-65535)",
                    ))
                }
            }
            "serial" => {
                let Some((path, baud)) = rest.rsplit_once(':') else {
                    return Err(source_err(
                        s,
                        "serial: needs a port and a baud rate such as serial:/dev/ttyUSB0:115200",
                    ));
                };
                let baud = baud.parse::<u32>().ok().filter(|b| *b > 0);
                match baud {
                    Some(baud) if !path.is_empty() => Ok(Address::Serial {
                        path: path.to_string(),
                        baud,
                    }),
                    _ => Err(source_err(
                        s,
                        "serial: needs a port and a baud rate such as serial:/dev/ttyUSB0:115200",
                    )),
                }
            }
            "file" => {
                let (path, opts) = split_query(s, rest, &["speed"])?;
                if path.is_empty() {
                    return Err(source_err(s, "file: needs a path such as file:flight.tlog"));
                }
                Ok(Address::File {
                    path: PathBuf::from(path),
                    speed: parse_speed(s, opts.get("speed"))?,
                })
            }
            "sim" => {
                let (name, opts) = split_query(s, rest, &["seed", "speed"])?;
                crate::sim::named::check_name(name)
                    .map_err(|e| source_err(s, format!("sim: {e}")))?;
                let seed = match opts.get("seed") {
                    None => DEFAULT_SIM_SEED,
                    Some(v) => v.parse::<u64>().map_err(|_| {
                        source_err(s, format!("seed `{v}` must be a whole number >= 0"))
                    })?,
                };
                Ok(Address::Sim {
                    scenario: name.to_string(),
                    seed,
                    speed: parse_speed(s, opts.get("speed"))?,
                })
            }
            other => Err(source_err(s, format!("unknown scheme `{other}:`"))),
        }
    }

    /// True for replays (`file:`, `sim:`), which wait for room on the inbound channel.
    pub fn is_replay(&self) -> bool {
        matches!(self, Address::File { .. } | Address::Sim { .. })
    }
}

impl std::str::FromStr for Address {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Address::parse(s)
    }
}

impl std::fmt::Display for Address {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Address::UdpIn(a) => write!(f, "udpin:{a}"),
            Address::UdpOut(a) => write!(f, "udpout:{a}"),
            Address::TcpOut(h) => write!(f, "tcpout:{h}"),
            Address::TcpIn(a) => write!(f, "tcpin:{a}"),
            Address::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
            Address::File { path, speed } => {
                write!(f, "file:{}", path.display())?;
                if *speed != 1.0 {
                    write!(f, "?speed={speed}")?;
                }
                Ok(())
            }
            Address::Sim {
                scenario,
                seed,
                speed,
            } => {
                write!(f, "sim:{scenario}")?;
                let mut sep = '?';
                if *seed != DEFAULT_SIM_SEED {
                    write!(f, "{sep}seed={seed}")?;
                    sep = '&';
                }
                if *speed != 1.0 {
                    write!(f, "{sep}speed={speed}")?;
                }
                Ok(())
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Public types

/// What the bytes of a link are.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Payload {
    /// MAVLink v1/v2 frames.
    #[default]
    Mavlink,
    /// MotionCal text lines `Raw:ax,ay,az,gx,gy,gz,mx,my,mz` (int16 counts).
    MotionCal,
    /// Comma-separated numbers per line in the order of `fields` (t, ax, ay, az, gx, gy, gz, mx,
    /// my, mz, temp, throttle, current, ref_qw, ref_qx, ref_qy, ref_qz, moving, lat, lon, alt; `_` or an empty
    /// name ignores a column), each multiplied by its scale. No `t` field: arrival time.
    Csv {
        fields: Vec<String>,
        scales: BTreeMap<String, f64>,
    },
}

/// The field names a [`Payload::Csv`] line may carry (those of `decode`'s CSV reader).
pub(crate) const CSV_FIELDS: [&str; crate::io::decode::FIELDS.len()] = crate::io::decode::FIELDS;

impl Payload {
    /// Check a CSV payload's field names and scales (the others are always valid).
    pub fn check(&self) -> Result<(), Error> {
        let Payload::Csv { fields, scales } = self else {
            return Ok(());
        };
        let err = |message: String| Error::Config {
            key: "fields".into(),
            message,
        };
        for f in fields {
            if !(f.is_empty() || f == "_" || CSV_FIELDS.contains(&f.as_str())) {
                return Err(err(format!(
                    "unknown field `{f}` (known: {}; `_` skips a column)",
                    CSV_FIELDS.join(", ")
                )));
            }
        }
        let has = |n: &str| fields.iter().any(|f| f == n);
        let sensors = ["ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz"];
        if !sensors.iter().any(|s| has(s)) {
            return Err(err(
                "no sensor fields: expected ax/ay/az, gx/gy/gz or mx/my/mz".to_string(),
            ));
        }
        for (k, v) in scales {
            if !CSV_FIELDS.contains(&k.as_str()) || !v.is_finite() {
                return Err(Error::Config {
                    key: "scales".into(),
                    message: format!("scale `{k} = {v}` needs a known field and a finite number"),
                });
            }
        }
        Ok(())
    }
}

/// One item from a link to the service.
#[derive(Debug, Clone)]
pub(crate) enum Inbound {
    /// A MAVLink frame; `time_us` is the arrival time (Unix microseconds) or, for `file:`, the
    /// tlog timestamp.
    Frame {
        link: usize,
        /// Boxed: a MAVLink message is a few hundred bytes, moved several times on its way.
        frame: Box<Frame>,
        time_us: u64,
    },
    /// A sample from a text-line link, a CSV file or `sim:`.
    Sample { link: usize, sample: Sample },
    /// A change of the link's state.
    Status { link: usize, status: LinkStatus },
}

/// State changes of a link.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum LinkStatus {
    /// Up (again); the text says with what.
    Connected(String),
    /// Down, with the reason; a live link retries with backoff.
    Lost(String),
    /// No bytes for `for_s` seconds while connected (reported once per silence).
    Silent { for_s: f64 },
    /// A replay reached its end.
    Ended,
}

/// How a link's first opening went: what the live service's `ready` line lists for it. Set once,
/// before the link's first [`LinkStatus`], and never changed after (a link that fails later says
/// so with [`LinkStatus::Lost`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum LinkOpening {
    /// Open: a socket bound (a UDP link, a TCP listener), a connection made, a serial port or a
    /// file opened, a simulation made. `local` is the bound local address when the link has one
    /// (the port the system chose when the address asked for port 0).
    Open {
        local: Option<SocketAddr>,
        detail: String,
    },
    /// The first attempt failed: a live link keeps trying with backoff, a replay never works.
    Failed { detail: String },
}

/// Counters of one link, readable while it runs.
#[derive(Default, Debug)]
pub(crate) struct LinkCounters {
    pub bytes_in: AtomicU64,
    pub frames_in: AtomicU64,
    pub samples_in: AtomicU64,
    /// Text lines that were not samples (MotionCal `Uni:`/`Cal1:` lines, headers, garbage).
    pub lines_skipped: AtomicU64,
    /// Items a live link could not queue because the inbound channel was full.
    pub inbound_dropped: AtomicU64,
    /// Outbound messages not written: link down, no UDP peer yet, send error.
    pub outbound_dropped: AtomicU64,
    /// Connection attempts after the first (and, for tcpin, clients after the first).
    pub reconnects: AtomicU64,
}

impl LinkCounters {
    fn add(c: &AtomicU64, n: u64) {
        c.fetch_add(n, Ordering::Relaxed);
    }
}

/// What [`spawn_link`] returns.
#[derive(Debug)]
pub(crate) struct LinkHandle {
    /// Bytes to write to the link (already-encoded frames or text).
    pub outbound: mpsc::Sender<Vec<u8>>,
    pub counters: Arc<LinkCounters>,
    /// Decode counters of this link (frames/lines decoded, skips by reason).
    pub decode_stats: Arc<Mutex<DecodeStats>>,
    /// `None` until the link first opened or failed to ([`LinkOpening`]); closed without a value
    /// when the link stopped before that.
    pub opening: watch::Receiver<Option<LinkOpening>>,
    pub task: tokio::task::JoinHandle<()>,
}

/// Tuning of a link.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LinkOptions {
    /// Report [`LinkStatus::Silent`] after this many seconds without bytes (0 = never).
    pub silent_after_s: f64,
    /// First reconnect delay, s.
    pub backoff_min_s: f64,
    /// Longest reconnect delay, s.
    pub backoff_max_s: f64,
    /// Capacity of the outbound channel.
    pub outbound_capacity: usize,
    /// UDP: read the socket every this many seconds, taking everything queued, instead of waking
    /// for each datagram (0). The socket is then not watched by the reactor at all, so arriving
    /// datagrams wake nothing: fewer wake-ups for up to this much more latency.
    pub udp_poll_s: f64,
    /// UDP polls fall on the grid `poll_epoch + k * period` (while the period is the configured
    /// one), so that other timers on the same grid, like the service's periodic outputs, fire in
    /// the same wake-up. `None`: the grid starts when the link does.
    pub poll_epoch: Option<tokio::time::Instant>,
}

impl Default for LinkOptions {
    fn default() -> Self {
        LinkOptions {
            silent_after_s: 3.0,
            backoff_min_s: 0.2,
            backoff_max_s: 5.0,
            outbound_capacity: 256,
            udp_poll_s: 0.0,
            poll_epoch: None,
        }
    }
}

/// A duration from seconds, clamped so that no input (NaN, negative, huge) can panic.
fn secs(x: f64) -> Duration {
    if x.is_finite() && x > 0.0 {
        Duration::from_secs_f64(x.min(1.0e6))
    } else {
        Duration::ZERO
    }
}

/// Options made safe to use.
#[derive(Debug, Clone)]
struct Tuning {
    silent: Option<Duration>,
    udp_poll: Option<Duration>,
    poll_epoch: Option<tokio::time::Instant>,
    backoff_min: Duration,
    backoff_max: Duration,
}

impl Tuning {
    fn from(o: &LinkOptions) -> Tuning {
        let silent = (o.silent_after_s.is_finite() && o.silent_after_s > 0.0)
            .then(|| secs(o.silent_after_s));
        let min = if o.backoff_min_s.is_finite() && o.backoff_min_s > 0.0 {
            secs(o.backoff_min_s).max(Duration::from_millis(1))
        } else {
            Duration::from_millis(200)
        };
        let max = if o.backoff_max_s.is_finite() && o.backoff_max_s > 0.0 {
            secs(o.backoff_max_s).max(min)
        } else {
            Duration::from_secs(5).max(min)
        };
        Tuning {
            silent,
            udp_poll: (o.udp_poll_s.is_finite() && o.udp_poll_s > 0.0)
                .then(|| secs(o.udp_poll_s.min(0.1)).max(Duration::from_millis(1))),
            poll_epoch: o.poll_epoch,
            backoff_min: min,
            backoff_max: max,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Text lines

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
enum LineParser {
    MotionCal,
    Csv(CsvLineParser),
}

// ---------------------------------------------------------------------------------------------
// Decoding bytes of a live link

/// Frames of one UDP datagram. Unlike the stream decoder, a datagram's end is a frame boundary:
/// an unfinished frame there is counted `truncated`; each run of garbage counts one `resync`.
/// Each frame goes to `emit` as it is found (boxed, as it will travel); returns how many.
fn decode_datagram(buf: &[u8], stats: &mut DecodeStats, mut emit: impl FnMut(Box<Frame>)) -> u64 {
    let mut n_frames = 0;
    let mut pos = 0;
    let mut in_garbage = false;
    while pos < buf.len() {
        match decode::parse_frame(&buf[pos..]) {
            FrameParse::Frame(f, n) => {
                emit(f);
                n_frames += 1;
                pos += n;
                in_garbage = false;
            }
            FrameParse::Incomplete => {
                stats.skip("truncated");
                break;
            }
            FrameParse::Skip(n, why) => {
                if why != SkipReason::Resync || !in_garbage {
                    stats.skip(why.name());
                }
                // The bytes after a damaged frame's first byte are its rest, not new garbage.
                in_garbage = matches!(why, SkipReason::Resync | SkipReason::BadCrc);
                pos += n.max(1);
            }
        }
    }
    n_frames
}

fn merge_stats(dst: &mut DecodeStats, src: &DecodeStats) {
    dst.records += src.records;
    dst.counts.add(&src.counts);
    for (k, v) in &src.skipped {
        *dst.skipped.entry(k.clone()).or_insert(0) += v;
    }
    dst.time.add(&src.time);
}

use crate::io::clock::now_us;

/// The link's fixed parts, shared by all its loops.
struct Shared {
    index: usize,
    inbound: mpsc::Sender<Inbound>,
    counters: Arc<LinkCounters>,
    stats: Arc<Mutex<DecodeStats>>,
    tuning: Tuning,
    start: Instant,
    /// Where the link's first opening is told ([`LinkHandle::opening`]).
    opening: watch::Sender<Option<LinkOpening>>,
}

impl Shared {
    /// Queue an item without waiting (live links). False when the service is gone.
    fn offer(&self, item: Inbound) -> bool {
        match self.inbound.try_send(item) {
            Ok(()) => true,
            Err(mpsc::error::TrySendError::Full(_)) => {
                LinkCounters::add(&self.counters.inbound_dropped, 1);
                true
            }
            Err(mpsc::error::TrySendError::Closed(_)) => false,
        }
    }

    /// Tell how the first opening went (later ones are not told: the first is the start-up's).
    fn opened(&self, how: LinkOpening) {
        self.opening.send_if_modified(|o| {
            if o.is_some() {
                return false;
            }
            tracing::debug!("link {}: {how:?}", self.index);
            *o = Some(how);
            true
        });
    }

    fn status(&self, status: LinkStatus) -> bool {
        match &status {
            LinkStatus::Lost(r) => tracing::debug!("link {}: lost: {r}", self.index),
            s => tracing::debug!("link {}: {s:?}", self.index),
        }
        self.offer(Inbound::Status {
            link: self.index,
            status,
        })
    }

    fn merge(&self, local: &DecodeStats) {
        if local.records == 0
            && local.skipped.is_empty()
            && local.counts.is_empty()
            && local.time.segments == 0
        {
            return;
        }
        if let Ok(mut s) = self.stats.lock() {
            merge_stats(&mut s, local);
        }
    }

    fn elapsed_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }
}

/// Per-connection receive state.
enum Rx {
    Mavlink(FrameDecoder),
    Text {
        lines: LineBuffer,
        parser: LineParser,
    },
}

impl Rx {
    fn new(payload: &Payload) -> Rx {
        match payload {
            Payload::Mavlink => Rx::Mavlink(FrameDecoder::new()),
            Payload::MotionCal => Rx::Text {
                lines: LineBuffer::new(),
                parser: LineParser::MotionCal,
            },
            Payload::Csv { fields, scales } => Rx::Text {
                lines: LineBuffer::new(),
                parser: LineParser::Csv(CsvLineParser::new(fields, scales)),
            },
        }
    }

    /// Decode bytes and queue what they hold. False when the service is gone.
    fn on_bytes(&mut self, sh: &Shared, bytes: &[u8], datagram: bool) -> bool {
        let mut local = DecodeStats::default();
        let open = self.take_bytes(sh, bytes, datagram, now_us(), &mut local);
        sh.merge(&local);
        open
    }

    /// [`Rx::on_bytes`] for bytes that arrived at `time_us` (Unix us), counted into `local`:
    /// datagrams read together share one arrival time and one merge of their counts.
    fn take_bytes(
        &mut self,
        sh: &Shared,
        bytes: &[u8],
        datagram: bool,
        time_us: u64,
        local: &mut DecodeStats,
    ) -> bool {
        LinkCounters::add(&sh.counters.bytes_in, bytes.len() as u64);
        let mut open = true;
        match self {
            Rx::Mavlink(dec) => {
                let mut offer = |frame: Box<Frame>| {
                    open &= sh.offer(Inbound::Frame {
                        link: sh.index,
                        frame,
                        time_us,
                    });
                };
                let n = if datagram {
                    decode_datagram(bytes, local, offer)
                } else {
                    let frames = dec.push(bytes);
                    merge_stats(local, &std::mem::take(&mut dec.stats));
                    let n = frames.len() as u64;
                    frames.into_iter().for_each(|f| offer(Box::new(f)));
                    n
                };
                local.records += n;
                LinkCounters::add(&sh.counters.frames_in, n);
            }
            Rx::Text { lines, parser } => {
                let (mut got, overlong) = lines.push(bytes);
                if datagram {
                    got.extend(lines.take_partial());
                }
                let mut skipped = overlong;
                let t = sh.elapsed_s();
                for line in got {
                    if line.trim().is_empty() {
                        continue;
                    }
                    let s = match parser {
                        LineParser::MotionCal => parse_motioncal_line(&line, t),
                        LineParser::Csv(p) => p.parse(&line, t),
                    };
                    match s {
                        Some(sample) => {
                            local.records += 1;
                            local.count_sample(&sample);
                            LinkCounters::add(&sh.counters.samples_in, 1);
                            open &= sh.offer(Inbound::Sample {
                                link: sh.index,
                                sample,
                            });
                        }
                        None => skipped += 1,
                    }
                }
                if skipped > 0 {
                    LinkCounters::add(&sh.counters.lines_skipped, skipped);
                    local.skip_n("bad_line", skipped);
                }
            }
        }
        open
    }
}

// ---------------------------------------------------------------------------------------------
// Task plumbing

/// The link's receivers: shutdown flag and outbound bytes.
struct Control {
    shutdown: watch::Receiver<bool>,
    outbound: mpsc::Receiver<Vec<u8>>,
    /// False once every outbound sender is gone (then the channel is no longer polled).
    outbound_open: bool,
}

/// Resolves when shutdown is requested (or its sender is gone).
async fn wait_stop(rx: &mut watch::Receiver<bool>) {
    let _ = rx.wait_for(|stop| *stop).await;
}

/// Run `fut` while watching shutdown (-> `None`) and dropping outbound bytes (the link is not
/// writable meanwhile).
async fn guarded<F: Future>(
    ctl: &mut Control,
    counters: &LinkCounters,
    fut: F,
) -> Option<F::Output> {
    tokio::pin!(fut);
    loop {
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return None,
            r = &mut fut => return Some(r),
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                Some(_) => LinkCounters::add(&counters.outbound_dropped, 1),
                None => ctl.outbound_open = false,
            },
        }
    }
}

/// How a connection ended.
enum End {
    Stop,
    Lost(String),
}

trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

/// An open live connection.
enum Conn {
    Stream {
        io: Box<dyn Io>,
        /// The local end of a TCP connection (none for a serial port).
        local: Option<SocketAddr>,
        desc: String,
        eof: &'static str,
    },
    Udp {
        sock: UdpSocket,
        /// udpout's target; `None` for udpin (reply to the last sender).
        target: Option<SocketAddr>,
        desc: String,
    },
}

impl Conn {
    /// What the link's `ready` entry says of this connection.
    fn opening(&self) -> LinkOpening {
        match self {
            Conn::Stream { local, desc, .. } => LinkOpening::Open {
                local: *local,
                detail: desc.clone(),
            },
            Conn::Udp { sock, desc, .. } => LinkOpening::Open {
                local: sock.local_addr().ok(),
                detail: desc.clone(),
            },
        }
    }
}

const TCP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

async fn open(addr: &Address) -> Result<Conn, String> {
    match addr {
        Address::UdpIn(a) => {
            let sock = UdpSocket::bind(a)
                .await
                .map_err(|e| format!("cannot bind udp {a}: {e}"))?;
            let local = sock
                .local_addr()
                .map(|l| l.to_string())
                .unwrap_or_else(|_| a.to_string());
            Ok(Conn::Udp {
                sock,
                target: None,
                desc: format!("listening on udp {local}"),
            })
        }
        Address::UdpOut(t) => {
            let local: SocketAddr = match (t.is_ipv4(), t.ip().is_loopback()) {
                (true, true) => "127.0.0.1:0",
                (true, false) => "0.0.0.0:0",
                (false, true) => "[::1]:0",
                (false, false) => "[::]:0",
            }
            .parse()
            .expect("literal socket address");
            let sock = UdpSocket::bind(local)
                .await
                .map_err(|e| format!("cannot bind udp {local}: {e}"))?;
            sock.connect(t)
                .await
                .map_err(|e| format!("cannot address udp {t}: {e}"))?;
            let local = sock.local_addr().map(|l| l.to_string()).unwrap_or_default();
            Ok(Conn::Udp {
                sock,
                target: Some(*t),
                desc: format!("udp to {t} from {local}"),
            })
        }
        Address::TcpOut(h) => {
            let s = match tokio::time::timeout(TCP_CONNECT_TIMEOUT, TcpStream::connect(h.as_str()))
                .await
            {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => return Err(format!("cannot connect to tcp {h}: {e}")),
                Err(_) => return Err(format!("cannot connect to tcp {h}: timed out")),
            };
            let _ = s.set_nodelay(true);
            let local = s.local_addr().ok();
            let peer = s
                .peer_addr()
                .map(|p| p.to_string())
                .unwrap_or_else(|_| h.clone());
            Ok(Conn::Stream {
                io: Box::new(s),
                local,
                desc: format!("tcp {peer}"),
                eof: "connection closed by the remote end",
            })
        }
        Address::Serial { path, baud } => {
            use tokio_serial::SerialPortBuilderExt;
            let port = tokio_serial::new(path.as_str(), *baud)
                .open_native_async()
                .map_err(|e| format!("cannot open serial {path}: {e}"))?;
            Ok(Conn::Stream {
                io: Box::new(port),
                local: None,
                desc: format!("serial {path} at {baud} baud"),
                eof: "serial port closed (end of stream)",
            })
        }
        Address::TcpIn(_) | Address::File { .. } | Address::Sim { .. } => {
            Err(format!("{addr} is not a dialled link"))
        }
    }
}

/// Start a link task. Must be called inside a tokio runtime.
pub(crate) fn spawn_link(
    index: usize,
    addr: Address,
    payload: Payload,
    inbound: mpsc::Sender<Inbound>,
    shutdown: watch::Receiver<bool>,
    opts: LinkOptions,
) -> LinkHandle {
    let (out_tx, out_rx) = mpsc::channel(opts.outbound_capacity.max(1));
    let counters = Arc::new(LinkCounters::default());
    let decode_stats = Arc::new(Mutex::new(DecodeStats::default()));
    let (opening_tx, opening) = watch::channel(None);
    let sh = Shared {
        index,
        inbound,
        counters: counters.clone(),
        stats: decode_stats.clone(),
        tuning: Tuning::from(&opts),
        start: Instant::now(),
        opening: opening_tx,
    };
    let ctl = Control {
        shutdown,
        outbound: out_rx,
        outbound_open: true,
    };
    let task = tokio::spawn(run(sh, ctl, addr, payload));
    LinkHandle {
        outbound: out_tx,
        counters,
        decode_stats,
        opening,
        task,
    }
}

async fn run(sh: Shared, mut ctl: Control, addr: Address, payload: Payload) {
    if *ctl.shutdown.borrow() {
        return;
    }
    match &addr {
        Address::File { path, speed } => run_file(&sh, &mut ctl, path, *speed, &payload).await,
        Address::Sim {
            scenario,
            seed,
            speed,
        } => run_sim(&sh, &mut ctl, scenario, *seed, *speed).await,
        Address::TcpIn(a) => run_tcp_in(&sh, &mut ctl, *a, &payload).await,
        _ => run_dialled(&sh, &mut ctl, &addr, &payload).await,
    }
    tracing::debug!("link {} ({addr}) stopped", sh.index);
}

// ---------------------------------------------------------------------------------------------
// Live links

/// udpin, udpout, tcpout, serial: open, serve, and on failure retry with backoff.
async fn run_dialled(sh: &Shared, ctl: &mut Control, addr: &Address, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut first = true;
    let mut lost_reported = false;
    loop {
        if !first {
            LinkCounters::add(&sh.counters.reconnects, 1);
        }
        first = false;
        let Some(res) = guarded(ctl, &sh.counters, open(addr)).await else {
            return;
        };
        match res {
            Ok(conn) => {
                let up = Instant::now();
                let mut rx = Rx::new(payload);
                sh.opened(conn.opening());
                let end = match conn {
                    Conn::Stream { io, desc, eof, .. } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        serve_stream(sh, ctl, io, &mut rx, None, eof).await
                    }
                    Conn::Udp { sock, target, desc } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        match sh.tuning.udp_poll {
                            Some(period) => {
                                serve_udp_polled(sh, ctl, sock, target, &mut rx, period).await
                            }
                            None => serve_udp(sh, ctl, &sock, target, &mut rx).await,
                        }
                    }
                };
                match end {
                    End::Stop => return,
                    End::Lost(r) => {
                        if !sh.status(LinkStatus::Lost(r)) {
                            return;
                        }
                        lost_reported = true;
                    }
                }
                // A connection that lasted resets the backoff; one that flaps keeps growing it.
                if up.elapsed() >= t.backoff_max {
                    backoff = t.backoff_min;
                }
            }
            Err(reason) => {
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                } else {
                    tracing::trace!("link {}: still down: {reason}", sh.index);
                }
            }
        }
        if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
            .await
            .is_none()
        {
            return;
        }
        backoff = (backoff * 2).min(t.backoff_max);
    }
}

/// tcpin: listen on the given address; serve one client at a time (others are closed at once).
async fn run_tcp_in(sh: &Shared, ctl: &mut Control, a: SocketAddr, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut lost_reported = false;
    let mut clients = 0u64;
    loop {
        let listener = match guarded(ctl, &sh.counters, TcpListener::bind(a)).await {
            None => return,
            Some(Ok(l)) => l,
            Some(Err(e)) => {
                let reason = format!("cannot listen on tcp {a}: {e}");
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                }
                if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
                    .await
                    .is_none()
                {
                    return;
                }
                backoff = (backoff * 2).min(t.backoff_max);
                LinkCounters::add(&sh.counters.reconnects, 1);
                continue;
            }
        };
        let local = listener.local_addr().ok();
        let shown = local.map_or_else(|| a.to_string(), |l| l.to_string());
        tracing::info!("link {}: listening on tcp {shown}", sh.index);
        sh.opened(LinkOpening::Open {
            local,
            detail: format!("listening on tcp {shown}"),
        });
        loop {
            let Some(acc) = guarded(ctl, &sh.counters, listener.accept()).await else {
                return;
            };
            let (stream, peer) = match acc {
                Ok(x) => x,
                Err(e) => {
                    // Transient (e.g. out of file descriptors): wait a little and accept again.
                    tracing::debug!("link {}: accept failed: {e}", sh.index);
                    let pause = tokio::time::sleep(Duration::from_millis(100));
                    if guarded(ctl, &sh.counters, pause).await.is_none() {
                        return;
                    }
                    continue;
                }
            };
            clients += 1;
            if clients > 1 {
                LinkCounters::add(&sh.counters.reconnects, 1);
            }
            let _ = stream.set_nodelay(true);
            if !sh.status(LinkStatus::Connected(format!("tcp client {peer}"))) {
                return;
            }
            let mut rx = Rx::new(payload);
            let eof = "client closed the connection";
            match serve_stream(sh, ctl, Box::new(stream), &mut rx, Some(&listener), eof).await {
                End::Stop => return,
                End::Lost(r) => {
                    if !sh.status(LinkStatus::Lost(format!(
                        "{r} ({peer}); waiting for a client"
                    ))) {
                        return;
                    }
                }
            }
        }
    }
}

/// Read a byte stream (TCP, serial) until it fails; write outbound bytes concurrently so a
/// stalled writer never stops the reader.
async fn serve_stream(
    sh: &Shared,
    ctl: &mut Control,
    io: Box<dyn Io>,
    rx: &mut Rx,
    listener: Option<&TcpListener>,
    eof: &str,
) -> End {
    let (mut rd, mut wr) = tokio::io::split(io);
    let Control {
        shutdown,
        outbound,
        outbound_open,
    } = ctl;
    let silent_after = sh.tuning.silent;

    let reader = async {
        let mut buf = vec![0u8; 4096];
        let mut last = Instant::now();
        let mut silent = false;
        loop {
            let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
            tokio::select! {
                r = rd.read(&mut buf) => match r {
                    Ok(0) => return End::Lost(eof.to_string()),
                    Ok(n) => {
                        last = Instant::now();
                        silent = false;
                        if !rx.on_bytes(sh, &buf[..n], false) {
                            return End::Stop;
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => return End::Lost(format!("read failed: {e}")),
                },
                _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                    silent = true;
                    let for_s = last.elapsed().as_secs_f64();
                    if !sh.status(LinkStatus::Silent { for_s }) {
                        return End::Stop;
                    }
                }
            }
        }
    };

    let writer = async {
        loop {
            if !*outbound_open {
                std::future::pending::<()>().await;
            }
            match outbound.recv().await {
                Some(bytes) => {
                    if let Err(e) = wr.write_all(&bytes).await {
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                        return End::Lost(format!("write failed: {e}"));
                    }
                }
                None => *outbound_open = false,
            }
        }
    };

    // tcpin: one client at a time; close the others at once.
    let extra_clients = async {
        match listener {
            Some(l) => loop {
                match l.accept().await {
                    Ok((_s, peer)) => {
                        tracing::info!("link {}: refused a second tcp client {peer}", sh.index)
                    }
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            },
            None => std::future::pending::<()>().await,
        }
    };

    tokio::select! {
        biased;
        _ = wait_stop(shutdown) => End::Stop,
        e = reader => e,
        e = writer => e,
        _ = extra_clients => End::Stop,
    }
}

fn transient_udp_error(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    // ICMP port-unreachable from an earlier send shows up as refused/reset: the peer is not up
    // yet, which is normal for UDP.
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionReset | WouldBlock | Interrupted
    )
}

/// Serve a UDP socket: each datagram is decoded on its own; outbound goes to the target
/// (udpout) or to the last sender (udpin).
async fn serve_udp(
    sh: &Shared,
    ctl: &mut Control,
    sock: &UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
) -> End {
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut buf = vec![0u8; 65_536];
    let mut last = Instant::now();
    let mut silent = false;
    loop {
        let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            r = sock.recv_from(&mut buf) => match r {
                Ok((n, from)) => {
                    if target.is_none() && peer != Some(from) {
                        tracing::debug!("link {}: udp peer {from}", sh.index);
                        peer = Some(from);
                    }
                    last = Instant::now();
                    silent = false;
                    if !rx.on_bytes(sh, &buf[..n], true) {
                        return End::Stop;
                    }
                }
                Err(e) if transient_udp_error(&e) => {}
                Err(e) => return End::Lost(format!("udp receive failed: {e}")),
            },
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).await.map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).await.map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
            _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                silent = true;
                if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                    return End::Stop;
                }
            }
        }
    }
}

/// Receive-buffer bytes one small datagram takes in Linux's accounting (its `truesize`: the
/// payload's allocation and the socket buffer around it), as SO_RCVBUF reads back: Linux's default
/// `rmem_default` of 212992 bytes holds 256 datagrams of a HIGHRES_IMU's size (measured on
/// loopback: 256 queued at the default, 2520 at 2 MiB).
const DATAGRAM_TRUESIZE: usize = 832;

/// Datagrams per poll above which the poll period shrinks (aiming at half this many per read), and
/// below which it doubles back towards the configured one, for a receive buffer of `bytes` (0:
/// not known, taken as Linux's default): a fast sender is read often enough that the buffer never
/// fills between reads, 3/8 of it at most (96 of the default's 256). The grow threshold is under
/// half the shrink one, so doubling the period never overshoots it.
fn poll_thresholds(bytes: usize) -> (usize, usize) {
    let holds = (bytes / DATAGRAM_TRUESIZE).max(256);
    let shrink_above = holds * 3 / 8;
    (shrink_above, shrink_above * 5 / 12)
}
/// Shortest poll period.
const POLL_MIN: Duration = Duration::from_millis(1);
/// How long a shortened poll period is kept after the last busy read before it may grow again, so
/// a sender that pauses briefly does not come back to a long period (and a full buffer).
const POLL_HOLD: Duration = Duration::from_secs(2);
/// The first point of the grid `epoch + k * every` after `now` (`now + every` when `now` is before
/// the epoch or `every` is zero).
fn next_on_grid(
    epoch: tokio::time::Instant,
    every: Duration,
    now: tokio::time::Instant,
) -> tokio::time::Instant {
    let (since, step) = (now.saturating_duration_since(epoch), every.as_nanos());
    if now < epoch || step == 0 {
        return now + every;
    }
    let k = since.as_nanos() / step + 1;
    // (k * step is at most `since + every`, so it fits a Duration whenever `now + every` does.)
    epoch + Duration::from_nanos(u64::try_from(k * step).unwrap_or(u64::MAX))
}

/// Receive buffer asked for on a polled socket, bytes (the kernel caps it at `net.core.rmem_max`).
const POLL_RECEIVE_BUFFER: usize = 1 << 20;

/// As [`serve_udp`], but the socket is taken off the reactor and read every `period` (shorter while
/// datagrams arrive fast, see [`poll_thresholds`]): whatever queued in the kernel meanwhile is
/// taken in one go. Arriving datagrams wake nothing.
async fn serve_udp_polled(
    sh: &Shared,
    ctl: &mut Control,
    sock: UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
    period: Duration,
) -> End {
    let sock = match sock.into_std() {
        Ok(s) => s,
        Err(e) => return End::Lost(format!("udp socket: {e}")),
    };
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut batch = udp_batch::UdpBatch::new();
    let buffer = match udp_batch::grow_receive_buffer(&sock, POLL_RECEIVE_BUFFER) {
        Ok(b) => b,
        Err(e) => {
            tracing::debug!("link {}: udp receive buffer left as it was: {e}", sh.index);
            0
        }
    };
    let (shrink_above, grow_below) = poll_thresholds(buffer);
    let mut fast_until = Instant::now();
    let mut last = Instant::now();
    let mut silent = false;
    let mut every = period;
    let epoch = sh
        .tuning
        .poll_epoch
        .unwrap_or_else(tokio::time::Instant::now);
    let next = tokio::time::sleep(Duration::ZERO);
    tokio::pin!(next);
    // A second timer, never awaited, kept one period past `next`. When `next` fires, the timer
    // driver's next wake-up becomes the earliest timer left; without this one that is later than
    // the next poll (or none), and re-arming `next` earlier than it makes tokio wake its driver
    // (an eventfd write and one more epoll_wait per poll). With it, re-arming is never earlier, and
    // moving `guard` later only extends a pending timer.
    let guard = tokio::time::sleep_until(next_on_grid(epoch, every, tokio::time::Instant::now()));
    tokio::pin!(guard);
    loop {
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            _ = &mut next => {
                let mut taken = 0usize;
                let mut local = DecodeStats::default();
                loop {
                    let n = match batch.recv(&sock) {
                        Ok(n) => n,
                        Err(e) if transient_udp_error(&e) => break,
                        Err(e) => {
                            sh.merge(&local);
                            return End::Lost(format!("udp receive failed: {e}"));
                        }
                    };
                    let time_us = now_us();
                    for i in 0..n {
                        let (bytes, from) = batch.get(i);
                        if let Some(from) = from.filter(|f| target.is_none() && peer != Some(*f)) {
                            tracing::debug!("link {}: udp peer {from}", sh.index);
                            peer = Some(from);
                        }
                        taken += 1;
                        if !rx.take_bytes(sh, bytes, true, time_us, &mut local) {
                            return End::Stop;
                        }
                    }
                    if n < udp_batch::BATCH {
                        break;
                    }
                }
                sh.merge(&local);
                if taken > shrink_above {
                    // Aim at about half the threshold per read at the rate just seen.
                    let aim = (shrink_above / 2) as u32;
                    every = (every * aim / taken as u32).max(POLL_MIN.min(period));
                    fast_until = Instant::now() + POLL_HOLD;
                } else if taken < grow_below && Instant::now() >= fast_until {
                    every = (every * 2).min(period);
                }
                let due = next_on_grid(epoch, every, tokio::time::Instant::now());
                next.as_mut().reset(due);
                guard.as_mut().reset(due + every);
                let got = taken > 0;
                if got {
                    last = Instant::now();
                    silent = false;
                } else if let Some(after) = silent_after {
                    if !silent && last.elapsed() >= after {
                        silent = true;
                        if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                            return End::Stop;
                        }
                    }
                }
            }
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Replays

/// Longest pause a replay makes for one gap in its timestamps (recorded time), s.
pub(crate) const MAX_REPLAY_GAP_S: f64 = 10.0;

/// Maps recorded times onto the clock at `speed` (0 = no waiting). Backwards steps do not wait;
/// gaps longer than [`MAX_REPLAY_GAP_S`] are shortened to it.
struct Pacer {
    speed: f64,
    start: Instant,
    last: Option<f64>,
    elapsed: f64,
}

impl Pacer {
    fn new(speed: f64) -> Pacer {
        Pacer {
            speed,
            start: Instant::now(),
            last: None,
            elapsed: 0.0,
        }
    }

    fn deadline(&mut self, t_s: f64) -> Option<Instant> {
        if !(self.speed > 0.0) || !t_s.is_finite() {
            return None;
        }
        let Some(last) = self.last.replace(t_s) else {
            self.start = Instant::now();
            return None;
        };
        self.elapsed += (t_s - last).clamp(0.0, MAX_REPLAY_GAP_S);
        Some(self.start + secs(self.elapsed / self.speed))
    }

    /// Wait until `t_s` is due. False on shutdown.
    async fn wait(&mut self, sh: &Shared, ctl: &mut Control, t_s: f64) -> bool {
        match self.deadline(t_s) {
            Some(d) if d > Instant::now() => {
                guarded(ctl, &sh.counters, tokio::time::sleep_until(d))
                    .await
                    .is_some()
            }
            _ => true,
        }
    }
}

/// Queue an item, waiting for room (replays). False on shutdown or when the service is gone.
async fn deliver(sh: &Shared, ctl: &mut Control, item: Inbound) -> bool {
    matches!(
        guarded(ctl, &sh.counters, sh.inbound.send(item)).await,
        Some(Ok(()))
    )
}

/// A replay's status, waiting for room; its first says how the opening went (a replay connects
/// once, or fails once).
async fn deliver_status(sh: &Shared, ctl: &mut Control, status: LinkStatus) -> bool {
    match &status {
        LinkStatus::Connected(d) => sh.opened(LinkOpening::Open {
            local: None,
            detail: d.clone(),
        }),
        LinkStatus::Lost(d) => sh.opened(LinkOpening::Failed { detail: d.clone() }),
        LinkStatus::Silent { .. } | LinkStatus::Ended => {}
    }
    let link = sh.index;
    deliver(sh, ctl, Inbound::Status { link, status }).await
}

/// Run blocking work off the executor, watching shutdown.
async fn blocking<T: Send + 'static>(
    sh: &Shared,
    ctl: &mut Control,
    f: impl FnOnce() -> Result<T, String> + Send + 'static,
) -> Option<Result<T, String>> {
    match guarded(ctl, &sh.counters, tokio::task::spawn_blocking(f)).await? {
        Ok(r) => Some(r),
        Err(e) => Some(Err(format!("worker failed: {e}"))),
    }
}

/// True when a CSV payload's file has no header row (its first line starts with a number).
fn headerless(text: &str) -> bool {
    text.lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split(',').next())
        .is_some_and(|c| c.trim().parse::<f64>().is_ok())
}

async fn run_file(
    sh: &Shared,
    ctl: &mut Control,
    path: &std::path::Path,
    speed: f64,
    payload: &Payload,
) {
    let p = path.to_path_buf();
    let read = blocking(sh, ctl, move || {
        let raw = std::fs::read(&p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
        let data = decode::maybe_gunzip(&raw)
            .map_err(|e| format!("cannot decompress {}: {e}", p.display()))?
            .into_owned();
        Ok((raw.len(), data))
    })
    .await;
    let (size, data) = match read {
        None => return,
        Some(Ok(x)) => x,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    LinkCounters::add(&sh.counters.bytes_in, size as u64);
    let name = path.display().to_string();
    let lower = name.to_ascii_lowercase();
    let format = decode::detect_format(&data).or_else(|| {
        if lower.ends_with(".tlog") {
            Some(decode::Format::Tlog)
        } else if lower.ends_with(".csv") || lower.ends_with(".csv.gz") {
            Some(decode::Format::Csv)
        } else {
            None
        }
    });
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let ok = match format {
        Some(decode::Format::Tlog) => {
            deliver_status(
                sh,
                ctl,
                LinkStatus::Connected(format!("replaying tlog {name} {pace}")),
            )
            .await
                && replay_tlog(sh, ctl, &data, speed).await
        }
        Some(decode::Format::Csv) => {
            let text = String::from_utf8_lossy(&data);
            let mut mapping = decode::CsvMapping::default();
            let owned;
            let text: &str = match payload {
                Payload::Csv { fields, scales } => {
                    mapping.scales = scales.clone();
                    if headerless(&text) {
                        owned = format!("{}\n{text}", fields.join(","));
                        &owned
                    } else {
                        &text
                    }
                }
                _ => &text,
            };
            let mut stats = DecodeStats::default();
            match decode::decode_csv(text, &mapping, &mut stats) {
                Ok(samples) => {
                    sh.merge(&stats);
                    deliver_status(
                        sh,
                        ctl,
                        LinkStatus::Connected(format!("replaying csv {name} {pace}")),
                    )
                    .await
                        && replay_samples(sh, ctl, samples, speed).await
                }
                Err(e) => deliver_status(sh, ctl, LinkStatus::Lost(format!("{name}: {e}"))).await,
            }
        }
        Some(decode::Format::Bin | decode::Format::Ulg) | None => {
            let msg = format!("{name}: neither a .tlog nor a CSV with a header row (flight-controller logs: use `imucald replay`)");
            deliver_status(sh, ctl, LinkStatus::Lost(msg)).await
        }
    };
    if ok {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}

async fn replay_tlog(sh: &Shared, ctl: &mut Control, data: &[u8], speed: f64) -> bool {
    let mut records = TlogRecords::new(data);
    let mut pacer = Pacer::new(speed);
    let mut ok = true;
    while let Some((ts, frame)) = records.next() {
        // Publish the records and skips so far.
        sh.merge(&std::mem::take(&mut records.stats));
        if !pacer.wait(sh, ctl, ts as f64 * 1e-6).await {
            ok = false;
            break;
        }
        LinkCounters::add(&sh.counters.frames_in, 1);
        let item = Inbound::Frame {
            link: sh.index,
            frame,
            time_us: ts,
        };
        if !deliver(sh, ctl, item).await {
            ok = false;
            break;
        }
    }
    sh.merge(&records.stats);
    ok
}

/// Emit samples paced by their `t_s`. False on shutdown.
async fn replay_samples(sh: &Shared, ctl: &mut Control, samples: Vec<Sample>, speed: f64) -> bool {
    let mut pacer = Pacer::new(speed);
    for sample in samples {
        if !pacer.wait(sh, ctl, sample.t_s).await {
            return false;
        }
        LinkCounters::add(&sh.counters.samples_in, 1);
        let item = Inbound::Sample {
            link: sh.index,
            sample,
        };
        if !deliver(sh, ctl, item).await {
            return false;
        }
    }
    true
}

async fn run_sim(sh: &Shared, ctl: &mut Control, scenario: &str, seed: u64, speed: f64) {
    let name = scenario.to_string();
    let made = blocking(sh, ctl, move || {
        let sc = crate::sim::named::scenario(&name).map_err(|e| e.to_string())?;
        Ok(crate::sim::simulate(&sc, seed).samples)
    })
    .await;
    let samples = match made {
        None => return,
        Some(Ok(s)) => s,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    let mut stats = DecodeStats::default();
    for s in &samples {
        stats.records += 1;
        stats.count_sample(s);
    }
    sh.merge(&stats);
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let desc = format!(
        "simulating {scenario} (seed {seed}, {} samples) {pace}",
        samples.len()
    );
    if deliver_status(sh, ctl, LinkStatus::Connected(desc)).await
        && replay_samples(sh, ctl, samples, speed).await
    {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}

// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega as apm;
    use mavlink::MavlinkVersion;
    use std::sync::atomic::Ordering::Relaxed;

    /// Polls land on the shared grid, strictly after now, whatever the phase of `now`.
    #[test]
    fn polls_land_on_the_shared_grid() {
        let epoch = tokio::time::Instant::now();
        let ms = Duration::from_millis;
        assert_eq!(next_on_grid(epoch, ms(10), epoch), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, ms(10), epoch + ms(3)), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, ms(10), epoch + ms(10)), epoch + ms(20));
        assert_eq!(
            next_on_grid(epoch, ms(10), epoch + ms(1234)),
            epoch + ms(1240)
        );
        // Before the epoch, or no period: one period from now.
        let later = epoch + ms(50);
        assert_eq!(next_on_grid(later, ms(10), epoch), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, Duration::ZERO, later), later);
    }

    const WAIT: Duration = Duration::from_secs(5);

    fn frame_bytes(msg: &apm::MavMessage, v: MavlinkVersion) -> Vec<u8> {
        let mut out = Vec::new();
        let h = mavlink::MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: 0,
        };
        mavlink::write_versioned_msg(&mut out, v, h, msg).expect("encode");
        out
    }

    fn imu(x: f32) -> apm::MavMessage {
        apm::MavMessage::HIGHRES_IMU(apm::HIGHRES_IMU_DATA {
            time_usec: 1000,
            xacc: x,
            zacc: -9.8,
            xmag: 0.2,
            zmag: 0.4,
            ..Default::default()
        })
    }

    fn heartbeat() -> apm::MavMessage {
        apm::MavMessage::HEARTBEAT(apm::HEARTBEAT_DATA::default())
    }

    fn fast_opts() -> LinkOptions {
        LinkOptions {
            silent_after_s: 0.0,
            backoff_min_s: 0.05,
            backoff_max_s: 0.2,
            ..LinkOptions::default()
        }
    }

    struct Rig {
        rx: mpsc::Receiver<Inbound>,
        stop: watch::Sender<bool>,
        handle: LinkHandle,
    }

    fn start(addr: Address, payload: Payload, opts: LinkOptions, capacity: usize) -> Rig {
        let (tx, rx) = mpsc::channel(capacity);
        let (stop, stop_rx) = watch::channel(false);
        let handle = spawn_link(7, addr, payload, tx, stop_rx, opts);
        Rig { rx, stop, handle }
    }

    impl Rig {
        async fn next(&mut self) -> Inbound {
            match tokio::time::timeout(WAIT, self.rx.recv()).await {
                Ok(Some(i)) => i,
                Ok(None) => panic!("inbound channel closed"),
                Err(_) => panic!("nothing from the link within {WAIT:?}"),
            }
        }

        /// The next status, skipping data items.
        async fn status(&mut self) -> LinkStatus {
            loop {
                if let Inbound::Status { link, status } = self.next().await {
                    assert_eq!(link, 7);
                    return status;
                }
            }
        }

        async fn frame(&mut self) -> (Frame, u64) {
            match self.next().await {
                Inbound::Frame {
                    link,
                    frame,
                    time_us,
                } => {
                    assert_eq!(link, 7);
                    (*frame, time_us)
                }
                other => panic!("expected a frame, got {other:?}"),
            }
        }

        /// Stop the link and check that its task ends promptly and without a panic.
        async fn stop(self) {
            self.stop.send(true).expect("stop");
            let t0 = std::time::Instant::now();
            let r = tokio::time::timeout(Duration::from_millis(500), self.handle.task).await;
            let joined = r.expect("link task did not stop within 500 ms");
            joined.expect("link task panicked");
            assert!(t0.elapsed() < Duration::from_millis(500));
        }
    }

    fn free_udp_port() -> u16 {
        let s = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        s.local_addr().expect("addr").port()
    }

    /// Waits until `done` holds: a counter the link task moves, looked at every 5 ms (an atomic
    /// counter has no event to wait on). Fails after [`WAIT`].
    async fn until(what: &str, mut done: impl FnMut() -> bool) {
        let t0 = std::time::Instant::now();
        while !done() {
            assert!(t0.elapsed() < WAIT, "not within {WAIT:?}: {what}");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// How the link's first opening went, once it is known.
    async fn opening(rig: &mut Rig) -> LinkOpening {
        let o = tokio::time::timeout(WAIT, rig.handle.opening.wait_for(Option::is_some))
            .await
            .expect("opened or failed within WAIT")
            .expect("told before the link stopped");
        o.clone().expect("some")
    }

    // --- addresses -----------------------------------------------------------------------------

    #[test]
    fn address_parse_round_trips() {
        let forms = [
            "udpin:127.0.0.1:14550",
            "udpout:127.0.0.1:14551",
            "udpin:[::1]:14550",
            "tcpout:localhost:5760",
            "tcpout:10.0.0.2:5762",
            "tcpin:127.0.0.1:5760",
            "serial:/dev/ttyUSB0:115200",
            "serial:COM3:57600",
            "file:logs/flight.tlog",
            "file:log.tlog?speed=10",
            "file:log.csv.gz?speed=0",
            "file:log.tlog?speed=0.5",
            "sim:tumble",
            "sim:tumble?seed=3&speed=5",
            "sim:flight?speed=0",
            "sim:turntable?seed=42",
            "sim:scenarios/my.toml?seed=9",
        ];
        for f in forms {
            let a = Address::parse(f).unwrap_or_else(|e| panic!("{f}: {e}"));
            assert_eq!(a.to_string(), f, "display of {a:?}");
            assert_eq!(Address::parse(&a.to_string()).unwrap(), a);
        }
        assert_eq!(
            Address::parse("serial:/dev/ttyUSB0:115200").unwrap(),
            Address::Serial {
                path: "/dev/ttyUSB0".into(),
                baud: 115200
            }
        );
        assert_eq!(
            Address::parse("sim:tumble?seed=3&speed=5").unwrap(),
            Address::Sim {
                scenario: "tumble".into(),
                seed: 3,
                speed: 5.0
            }
        );
        // Defaults: speed 1, seed 1; a default written out reads back the same.
        assert_eq!(
            Address::parse("file:a.tlog?speed=1").unwrap(),
            Address::File {
                path: "a.tlog".into(),
                speed: 1.0
            }
        );
        assert_eq!(
            Address::parse("sim:tumble?seed=1").unwrap().to_string(),
            "sim:tumble"
        );
        assert!(Address::parse("sim:tumble").unwrap().is_replay());
        assert!(!Address::parse("udpin:127.0.0.1:1").unwrap().is_replay());
    }

    #[test]
    fn address_parse_rejects_bad_forms_helpfully() {
        let cases = [
            ("", "no scheme"),
            ("/dev/ttyUSB0", "no scheme"),
            ("udp:127.0.0.1:14550", "unknown scheme"),
            ("udpin:localhost:14550", "IP address and port"),
            ("udpin:127.0.0.1", "IP address and port"),
            ("udpout:127.0.0.1:99999", "IP address and port"),
            ("tcpout:host", "HOST:PORT"),
            ("tcpout::5760", "HOST:PORT"),
            ("tcpout:host:0", "HOST:PORT"),
            ("serial:/dev/ttyUSB0", "baud rate"),
            ("serial:/dev/ttyUSB0:fast", "baud rate"),
            ("serial::115200", "baud rate"),
            ("file:", "needs a path"),
            ("file:a.tlog?speed=-1", "speed"),
            ("file:a.tlog?speed=fast", "speed"),
            ("file:a.tlog?rate=2", "unknown option `rate`"),
            ("file:a.tlog?speed", "needs a value"),
            ("sim:nope", "tumble"),
            ("sim:", "scenario name"),
            ("sim:tumble?seed=-3", "seed"),
        ];
        for (s, want) in cases {
            match Address::parse(s) {
                Ok(a) => panic!("`{s}` parsed as {a:?}"),
                Err(Error::Config { key, message }) => {
                    assert_eq!(key, "source");
                    assert!(message.contains(want), "`{s}`: {message}");
                    assert!(message.contains("udpin:IP:PORT"), "forms listed: {message}");
                }
                Err(e) => panic!("`{s}`: wrong error kind {e:?}"),
            }
        }
    }

    // --- text lines ----------------------------------------------------------------------------

    #[test]
    fn motioncal_raw_line_in_si_units() {
        let s =
            parse_motioncal_line("Raw:8192,-4096,0,16,-32,160,100,-25,0", 1.5).expect("raw line");
        assert_eq!(s.t_s, 1.5);
        let a = s.accel_mps2.unwrap();
        assert!((a[0] - 9.80665).abs() < 1e-12 && (a[1] + 4.903325).abs() < 1e-12 && a[2] == 0.0);
        let g = s.gyro_rad_s.unwrap();
        assert!((g[0] - 1f64.to_radians()).abs() < 1e-12);
        assert!((g[1] + 2f64.to_radians()).abs() < 1e-12);
        assert!((g[2] - 10f64.to_radians()).abs() < 1e-12);
        assert_eq!(s.mag_ut, Some([10.0, -2.5, 0.0]));
        // Whitespace and CR around the numbers are tolerated.
        assert!(parse_motioncal_line(" Raw: 1, 2,3,4,5,6,7,8,9\r", 0.0).is_some());
    }

    #[test]
    fn motioncal_other_lines_are_rejected() {
        for bad in [
            "Uni:0.01,0.02,9.81,0,0,0,12.5,3.0,-40.1",
            "Cal1:0,0,0,0,0,0,0,0,0,0",
            "Raw:1,2,3,4,5,6,7,8",
            "Raw:1,2,3,4,5,6,7,8,9,10",
            "Raw:1,2,3,4,5,6,7,8,x",
            "Raw:1,2,3,4,5,6,7,8,40000",
            "Raw:1.5,2,3,4,5,6,7,8,9",
            "Raw:",
            "garbage \u{fffd}\u{fffd}",
            "",
        ] {
            assert!(parse_motioncal_line(bad, 0.0).is_none(), "{bad:?}");
        }
    }

    #[test]
    fn line_buffer_joins_partial_lines_and_strips_crlf() {
        let mut b = LineBuffer::new();
        let (l, d) = b.push(b"Raw:1,2,");
        assert!(l.is_empty() && d == 0);
        let (l, _) = b.push(b"3\r\nUni:9\r");
        assert_eq!(l, vec!["Raw:1,2,3".to_string()]);
        let (l, _) = b.push(b"\nA\nB\r\n\r\nC");
        assert_eq!(l, vec!["Uni:9", "A", "B", ""]);
        assert_eq!(b.take_partial().as_deref(), Some("C"));
        assert_eq!(b.take_partial(), None);
        // An over-long line is dropped once, up to its newline; the next line is intact.
        let long = vec![b'x'; MAX_LINE + 10];
        let (l, d) = b.push(&long);
        assert!(l.is_empty());
        assert_eq!(d, 1);
        let (l, d) = b.push(b"yyy\nok\n");
        assert_eq!((l, d), (vec!["ok".to_string()], 0));
        // Also when its start fitted in an earlier read, and when one read holds all of it.
        let (l, d) = b.push(&long[..MAX_LINE - 5]);
        assert!(l.is_empty() && d == 0);
        let (l, d) = b.push(b"123456\nok\n");
        assert_eq!((l, d), (vec!["ok".to_string()], 1));
        let mut one = long.clone();
        one.extend(b"\nok\n");
        assert_eq!(b.push(&one), (vec!["ok".to_string()], 1));
        // A line of exactly MAX_LINE bytes is kept.
        let mut max = vec![b'z'; MAX_LINE];
        max.push(b'\n');
        assert_eq!(b.push(&max).0[0].len(), MAX_LINE);
    }

    #[test]
    fn csv_lines_in_field_order_with_scales() {
        let fields: Vec<String> = ["t", "ax", "ay", "az", "_", "mx", "my", "mz"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let mut scales = BTreeMap::new();
        scales.insert("t".to_string(), 0.001);
        scales.insert("az".to_string(), STANDARD_GRAVITY_MPS2);
        let p = CsvLineParser::new(&fields, &scales);
        let s = p.parse("1500,0,0,-1,99,10,20,30", 7.0).unwrap();
        assert_eq!(s.t_s, 1.5);
        assert_eq!(s.accel_mps2, Some([0.0, 0.0, -STANDARD_GRAVITY_MPS2]));
        assert_eq!(s.mag_ut, Some([10.0, 20.0, 30.0]));
        assert_eq!(s.gyro_rad_s, None);
        // Empty cells: no reading of that sensor.
        let s = p.parse("1600,,,,0,10,20,30", 7.0).unwrap();
        assert_eq!(s.accel_mps2, None);
        assert!(p.parse("t,ax,ay,az,_,mx,my,mz", 0.0).is_none(), "header");
        assert!(p.parse("1,2,3", 0.0).is_none(), "too few cells");
        assert!(
            p.parse("1,2,3,4,5,6,7,8,9", 0.0).is_none(),
            "too many cells"
        );
        assert!(p.parse("1700,,,,,,,", 0.0).is_none(), "no sensor data");
        // No t field: the arrival time.
        let p = CsvLineParser::new(&fields[1..4], &BTreeMap::new());
        assert_eq!(p.parse("0,0,9.8", 2.25).unwrap().t_s, 2.25);

        let ok = Payload::Csv {
            fields: fields.clone(),
            scales: scales.clone(),
        };
        ok.check().unwrap();
        let bad = Payload::Csv {
            fields: vec!["t".into(), "accx".into()],
            scales: BTreeMap::new(),
        };
        assert!(bad.check().unwrap_err().to_string().contains("accx"));
    }

    #[test]
    fn datagram_decoder_counts_garbage_runs_and_truncation() {
        let mut d = frame_bytes(&imu(1.0), MavlinkVersion::V2);
        d.extend(b"junk junk");
        d.extend(frame_bytes(&heartbeat(), MavlinkVersion::V1));
        let whole = frame_bytes(&imu(2.0), MavlinkVersion::V2);
        d.extend(&whole[..whole.len() - 3]);
        let mut st = DecodeStats::default();
        let mut frames = vec![];
        let n = decode_datagram(&d, &mut st, |f| frames.push(f));
        assert_eq!((n, frames.len()), (2, 2));
        assert_eq!(st.skipped.get("resync"), Some(&1));
        assert_eq!(st.skipped.get("truncated"), Some(&1));
    }

    // --- udp -----------------------------------------------------------------------------------

    #[test]
    fn poll_thresholds_scale_with_the_buffer_the_kernel_granted() {
        // Linux's default buffer (212992 bytes) holds 256 small datagrams: 96 and 40.
        assert_eq!(poll_thresholds(212_992), (96, 40));
        // Not known, or smaller: as the default.
        assert_eq!(poll_thresholds(0), (96, 40));
        // The 1 MiB asked for reads back as 2 MiB, 2520 datagrams: 945 and 393.
        assert_eq!(poll_thresholds(2 << 20), (945, 393));
    }

    #[tokio::test]
    async fn udpin_polled_takes_a_burst_replies_reports_silence_and_stops() {
        // `udp_poll_s`: the socket is read every 20 ms; a burst of 50 datagrams sent between two
        // reads all arrive, in order; the reply goes to the sender; silence is reported once.
        let port = free_udp_port();
        let addr = Address::parse(&format!("udpin:127.0.0.1:{port}")).unwrap();
        let opts = LinkOptions {
            udp_poll_s: 0.02,
            silent_after_s: 0.3,
            ..fast_opts()
        };
        let mut rig = start(addr, Payload::Mavlink, opts, 256);
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        for i in 0..50 {
            let d = frame_bytes(&imu(i as f32), MavlinkVersion::V2);
            client.send_to(&d, ("127.0.0.1", port)).await.unwrap();
        }
        for i in 0..50 {
            match rig.frame().await.0.message {
                apm::MavMessage::HIGHRES_IMU(a) => assert_eq!(a.xacc, i as f32),
                other => panic!("{other:?}"),
            }
        }
        let reply = frame_bytes(&heartbeat(), MavlinkVersion::V2);
        rig.handle.outbound.send(reply.clone()).await.unwrap();
        let mut buf = [0u8; 512];
        let (n, _) = tokio::time::timeout(WAIT, client.recv_from(&mut buf))
            .await
            .expect("reply within 5 s")
            .unwrap();
        assert_eq!(&buf[..n], &reply[..]);
        match rig.status().await {
            LinkStatus::Silent { for_s } => assert!(for_s >= 0.29, "{for_s}"),
            s => panic!("{s:?}"),
        }
        rig.stop().await;
    }

    /// The first opening is told once, before the first status: the bound address of a link asked
    /// for port 0, the failure of one that cannot open (and not again on its retries), no local
    /// address for a replay.
    #[tokio::test]
    async fn link_opening_tells_the_bound_port_or_the_failure() {
        let mut udp = start(
            Address::parse("udpin:127.0.0.1:0").unwrap(),
            Payload::Mavlink,
            fast_opts(),
            64,
        );
        let local = match opening(&mut udp).await {
            LinkOpening::Open { local: Some(a), .. } => a,
            other => panic!("{other:?}"),
        };
        assert!(local.ip().is_loopback() && local.port() != 0, "{local}");
        match udp.status().await {
            LinkStatus::Connected(s) => assert!(s.contains(&local.to_string()), "{s}"),
            s => panic!("{s:?}"),
        }
        // It listens there: a datagram sent to the told port arrives.
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        client
            .send_to(&frame_bytes(&imu(5.0), MavlinkVersion::V2), local)
            .await
            .unwrap();
        assert!(matches!(
            udp.frame().await.0.message,
            apm::MavMessage::HIGHRES_IMU(_)
        ));
        udp.stop().await;

        let refused = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            l.local_addr().unwrap()
        };
        let mut tcp = start(
            Address::TcpOut(refused.to_string()),
            Payload::Mavlink,
            fast_opts(),
            64,
        );
        match opening(&mut tcp).await {
            LinkOpening::Failed { detail } => {
                assert!(detail.contains("cannot connect"), "{detail}")
            }
            other => panic!("{other:?}"),
        }
        let c = tcp.handle.counters.clone();
        until("a retry", || c.reconnects.load(Relaxed) >= 1).await;
        assert!(!tcp.handle.opening.has_changed().unwrap(), "told once");
        tcp.stop().await;

        let mut sim = start(
            Address::parse("sim:turntable?speed=0").unwrap(),
            Payload::Mavlink,
            fast_opts(),
            64,
        );
        match opening(&mut sim).await {
            LinkOpening::Open {
                local: None,
                detail,
            } => {
                assert!(detail.contains("turntable"), "{detail}")
            }
            other => panic!("{other:?}"),
        }
        sim.stop().await;
    }

    #[tokio::test]
    async fn udpin_frames_v1_v2_garbage_counted_and_reply_to_sender() {
        let port = free_udp_port();
        let addr = Address::parse(&format!("udpin:127.0.0.1:{port}")).unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 64);
        match rig.status().await {
            LinkStatus::Connected(s) => assert!(s.contains(&port.to_string()), "{s}"),
            s => panic!("{s:?}"),
        }
        // Before any datagram there is no peer: outbound is dropped and counted.
        rig.handle.outbound.send(b"early".to_vec()).await.unwrap();

        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut dgram = frame_bytes(&imu(1.0), MavlinkVersion::V2);
        dgram.extend(b"\x00garbage\x01\x02");
        dgram.extend(frame_bytes(&imu(2.0), MavlinkVersion::V1));
        client.send_to(&dgram, ("127.0.0.1", port)).await.unwrap();

        let (f1, t1) = rig.frame().await;
        let (f2, _) = rig.frame().await;
        assert_eq!(f1.version, MavlinkVersion::V2);
        assert_eq!(f2.version, MavlinkVersion::V1);
        match (&f1.message, &f2.message) {
            (apm::MavMessage::HIGHRES_IMU(a), apm::MavMessage::HIGHRES_IMU(b)) => {
                assert_eq!((a.xacc, b.xacc), (1.0, 2.0))
            }
            other => panic!("{other:?}"),
        }
        assert!(t1 > 1_600_000_000_000_000, "arrival time in Unix us: {t1}");
        let c = &rig.handle.counters;
        assert_eq!(c.frames_in.load(Relaxed), 2);
        assert_eq!(c.bytes_in.load(Relaxed), dgram.len() as u64);
        assert_eq!(c.outbound_dropped.load(Relaxed), 1);
        {
            let st = rig.handle.decode_stats.lock().unwrap();
            assert_eq!(st.skipped.get("resync"), Some(&1), "{st:?}");
            assert_eq!(st.records, 2);
        }

        // Outbound now goes back to the sender's socket.
        let reply = frame_bytes(&heartbeat(), MavlinkVersion::V2);
        rig.handle.outbound.send(reply.clone()).await.unwrap();
        let mut buf = [0u8; 512];
        let (n, from) = tokio::time::timeout(WAIT, client.recv_from(&mut buf))
            .await
            .expect("reply within 5 s")
            .unwrap();
        assert_eq!(&buf[..n], &reply[..]);
        assert_eq!(from.port(), port);
        rig.stop().await;
    }

    #[tokio::test]
    async fn udp_full_inbound_drops_and_counts_without_blocking() {
        let port = free_udp_port();
        let addr = Address::UdpIn(format!("127.0.0.1:{port}").parse().unwrap());
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 2);
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut dgram = Vec::new();
        for i in 0..5 {
            dgram.extend(frame_bytes(&imu(i as f32), MavlinkVersion::V2));
        }
        let c = rig.handle.counters.clone();
        for round in 1..=2u64 {
            client.send_to(&dgram, ("127.0.0.1", port)).await.unwrap();
            until("the reader takes both datagrams", || {
                c.frames_in.load(Relaxed) >= 5 * round
            })
            .await;
        }
        // 2 fit in the channel; the other 8 were dropped, and the reader went on.
        assert_eq!(c.inbound_dropped.load(Relaxed), 8);
        rig.stop().await;
    }

    #[tokio::test]
    async fn udpout_sends_to_target_and_reports_silence_once_per_gap() {
        let peer = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let target = peer.local_addr().unwrap();
        let opts = LinkOptions {
            silent_after_s: 0.2,
            ..fast_opts()
        };
        let mut rig = start(Address::UdpOut(target), Payload::Mavlink, opts, 64);
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        rig.handle.outbound.send(b"hello".to_vec()).await.unwrap();
        let mut buf = [0u8; 64];
        let (n, from) = tokio::time::timeout(WAIT, peer.recv_from(&mut buf))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(&buf[..n], b"hello");
        match rig.status().await {
            LinkStatus::Silent { for_s } => assert!(for_s >= 0.19, "{for_s}"),
            s => panic!("{s:?}"),
        }
        // Still silent: no second report until bytes arrive.
        assert!(
            tokio::time::timeout(Duration::from_millis(400), rig.rx.recv())
                .await
                .is_err()
        );
        peer.send_to(&frame_bytes(&heartbeat(), MavlinkVersion::V2), from)
            .await
            .unwrap();
        rig.frame().await;
        assert!(matches!(rig.status().await, LinkStatus::Silent { .. }));
        rig.stop().await;
    }

    // --- tcp -----------------------------------------------------------------------------------

    #[tokio::test]
    async fn tcpout_reconnects_after_the_peer_drops() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let addr = Address::parse(&format!("tcpout:127.0.0.1:{port}")).unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 64);

        let (first, _) = tokio::time::timeout(WAIT, listener.accept())
            .await
            .unwrap()
            .unwrap();
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        drop(first);
        match rig.status().await {
            LinkStatus::Lost(r) => assert!(r.contains("closed"), "{r}"),
            s => panic!("{s:?}"),
        }
        let (mut second, _) = tokio::time::timeout(WAIT, listener.accept())
            .await
            .unwrap()
            .unwrap();
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        assert!(rig.handle.counters.reconnects.load(Relaxed) >= 1);

        // The stream decoder reassembles a frame split across writes.
        let f = frame_bytes(&imu(3.0), MavlinkVersion::V2);
        second.write_all(&f[..7]).await.unwrap();
        second.flush().await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
        second.write_all(&f[7..]).await.unwrap();
        let (frame, _) = rig.frame().await;
        assert!(matches!(frame.message, apm::MavMessage::HIGHRES_IMU(_)));
        // Outbound reaches the peer.
        rig.handle.outbound.send(b"ping".to_vec()).await.unwrap();
        let mut buf = [0u8; 4];
        tokio::time::timeout(WAIT, second.read_exact(&mut buf))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(&buf, b"ping");
        rig.stop().await;
    }

    #[tokio::test]
    async fn tcpout_refused_is_lost_once_and_outbound_dropped_while_down() {
        // A port with nobody listening.
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            l.local_addr().unwrap().port()
        };
        let mut rig = start(
            Address::TcpOut(format!("127.0.0.1:{port}")),
            Payload::Mavlink,
            fast_opts(),
            64,
        );
        match rig.status().await {
            LinkStatus::Lost(r) => assert!(r.contains("cannot connect"), "{r}"),
            s => panic!("{s:?}"),
        }
        rig.handle.outbound.send(b"x".to_vec()).await.unwrap();
        let c = rig.handle.counters.clone();
        until("retries with backoff", || c.reconnects.load(Relaxed) >= 2).await;
        assert_eq!(c.outbound_dropped.load(Relaxed), 1);
        // Repeated failures are not reported again.
        assert!(rig.rx.try_recv().is_err());
        rig.stop().await;
    }

    #[tokio::test]
    async fn tcpin_serves_one_client_at_a_time() {
        // Port 0: the listener's opening says which port it got.
        let addr = Address::parse("tcpin:127.0.0.1:0").unwrap();
        let mut rig = start(addr, Payload::MotionCal, fast_opts(), 64);
        let port = match opening(&mut rig).await {
            LinkOpening::Open {
                local: Some(a),
                detail,
            } => {
                assert!(detail.contains(&a.to_string()), "{detail}");
                a.port()
            }
            other => panic!("{other:?}"),
        };
        assert_ne!(port, 0);
        let mut c1 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("client")));
        // A second client is closed at once.
        let mut c2 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let mut b = [0u8; 1];
        let r = tokio::time::timeout(WAIT, c2.read(&mut b)).await.unwrap();
        assert!(matches!(r, Ok(0) | Err(_)));

        c1.write_all(b"Raw:0,0,8192,0,0,0,0,0,0\n").await.unwrap();
        match rig.next().await {
            Inbound::Sample { sample, .. } => {
                assert!((sample.accel_mps2.unwrap()[2] - 9.80665).abs() < 1e-12)
            }
            other => panic!("{other:?}"),
        }
        drop(c1);
        assert!(matches!(rig.status().await, LinkStatus::Lost(_)));
        let _c3 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        assert_eq!(rig.handle.counters.reconnects.load(Relaxed), 1);
        rig.stop().await;
    }

    // --- serial --------------------------------------------------------------------------------

    #[tokio::test]
    async fn serial_pty_motioncal_samples_then_lost_when_the_other_end_closes() {
        let (mut master, slave) = match tokio_serial::SerialStream::pair() {
            Ok(p) => p,
            Err(e) => {
                eprintln!("skipped: no pseudo-terminal available: {e}");
                return;
            }
        };
        let path = tokio_serial::SerialPort::name(&slave).expect("pty name");
        drop(slave);
        let opts = LinkOptions {
            backoff_min_s: 1.0,
            ..fast_opts()
        };
        let addr = Address::Serial { path, baud: 115200 };
        let mut rig = start(addr, Payload::MotionCal, opts, 64);
        match rig.status().await {
            LinkStatus::Connected(s) => assert!(s.contains("serial"), "{s}"),
            s => panic!("{s:?}"),
        }
        for chunk in [
            &b"Uni:0.00,0.01,9.80,0,0,0,1,2,3\r\nRaw:8192,0,-8192,16,-16,0,100,-100,0\r"[..],
            b"\nRaw:0,0,81",
            b"92,0,0,160,0,0,-500\r\ngarbage\xff\r\n",
        ] {
            master.write_all(chunk).await.unwrap();
            master.flush().await.unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let mut samples = Vec::new();
        while samples.len() < 2 {
            match rig.next().await {
                Inbound::Sample { sample, .. } => samples.push(sample),
                other => panic!("{other:?}"),
            }
        }
        let g = STANDARD_GRAVITY_MPS2;
        let a = samples[0].accel_mps2.unwrap();
        assert!((a[0] - g).abs() < 1e-12 && a[1] == 0.0 && (a[2] + g).abs() < 1e-12);
        let w = samples[0].gyro_rad_s.unwrap();
        assert!(
            (w[0] - 1f64.to_radians()).abs() < 1e-12 && (w[1] + 1f64.to_radians()).abs() < 1e-12
        );
        assert_eq!(samples[0].mag_ut, Some([10.0, -10.0, 0.0]));
        assert_eq!(samples[1].mag_ut, Some([0.0, 0.0, -50.0]));
        assert!(samples[1].t_s >= samples[0].t_s && samples[0].t_s >= 0.0);
        let c = rig.handle.counters.clone();
        until("two lines skipped", || c.lines_skipped.load(Relaxed) >= 2).await;
        assert_eq!(c.samples_in.load(Relaxed), 2);

        drop(master);
        match rig.status().await {
            LinkStatus::Lost(r) => assert!(!r.is_empty()),
            s => panic!("{s:?}"),
        }
        assert!(!rig.handle.task.is_finished(), "keeps retrying");
        rig.stop().await;
    }

    // --- replays -------------------------------------------------------------------------------

    fn tlog(records: &[(u64, Vec<u8>)]) -> Vec<u8> {
        let mut out = Vec::new();
        for (ts, f) in records {
            out.extend(ts.to_be_bytes());
            out.extend(f);
        }
        out
    }

    const T0: u64 = 1_700_000_000_000_000;

    #[tokio::test]
    async fn file_tlog_at_speed_zero_is_emitted_completely_then_ended() {
        let mut recs = Vec::new();
        for i in 0..6u64 {
            let v = if i % 2 == 0 {
                MavlinkVersion::V2
            } else {
                MavlinkVersion::V1
            };
            let msg = if i == 3 { heartbeat() } else { imu(i as f32) };
            recs.push((T0 + i * 10_000, frame_bytes(&msg, v)));
        }
        let mut bytes = tlog(&recs[..3]);
        bytes.extend(b"noise!");
        bytes.extend(tlog(&recs[3..]));
        bytes.extend(&T0.to_be_bytes()[..5]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("small.tlog");
        std::fs::write(&path, &bytes).unwrap();

        let addr = Address::parse(&format!("file:{}?speed=0", path.display())).unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 2);
        assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("tlog")));
        for i in 0..6u64 {
            let (f, ts) = rig.frame().await;
            assert_eq!(ts, T0 + i * 10_000);
            assert_eq!(f.version == MavlinkVersion::V2, i % 2 == 0);
        }
        assert_eq!(rig.status().await, LinkStatus::Ended);
        let st = rig.handle.decode_stats.lock().unwrap().clone();
        assert_eq!(st.records, 6);
        assert!(st.skipped.contains_key("resync"), "{st:?}");
        assert_eq!(st.skipped.get("truncated"), Some(&1), "{st:?}");
        assert_eq!(rig.handle.counters.inbound_dropped.load(Relaxed), 0);
        tokio::time::timeout(WAIT, rig.handle.task)
            .await
            .unwrap()
            .unwrap();
    }

    #[tokio::test]
    async fn file_tlog_is_paced_by_its_timestamps() {
        // 0.3 s of recording at speed 2: about 0.15 s.
        let recs: Vec<_> = (0..4u64)
            .map(|i| (T0 + i * 100_000, frame_bytes(&imu(0.0), MavlinkVersion::V2)))
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("paced.tlog");
        std::fs::write(&path, tlog(&recs)).unwrap();
        let mut rig = start(
            Address::File { path, speed: 2.0 },
            Payload::Mavlink,
            fast_opts(),
            64,
        );
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let t0 = std::time::Instant::now();
        rig.frame().await;
        for _ in 0..3 {
            rig.frame().await;
        }
        let dt = t0.elapsed().as_secs_f64();
        assert!((0.14..1.5).contains(&dt), "{dt}");
        assert_eq!(rig.status().await, LinkStatus::Ended);
    }

    #[tokio::test]
    async fn file_csv_gz_headerless_with_payload_fields_and_scales() {
        use std::io::Write;
        let text =
            "0,0,0,-1000,10,20,30\n0.01,0,0,-1000,11,21,31\nbad,row\n0.02,0,0,-1000,12,22,32\n";
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("imu.csv.gz");
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        gz.write_all(text.as_bytes()).unwrap();
        std::fs::write(&path, gz.finish().unwrap()).unwrap();
        let fields = ["t", "ax", "ay", "az", "mx", "my", "mz"]
            .map(String::from)
            .to_vec();
        let mut scales = BTreeMap::new();
        for f in ["ax", "ay", "az"] {
            scales.insert(f.to_string(), STANDARD_GRAVITY_MPS2 / 1000.0);
        }
        let payload = Payload::Csv { fields, scales };
        let mut rig = start(Address::File { path, speed: 0.0 }, payload, fast_opts(), 64);
        assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("csv")));
        let mut got = Vec::new();
        loop {
            match rig.next().await {
                Inbound::Sample { sample, .. } => got.push(sample),
                Inbound::Status { status, .. } => {
                    assert_eq!(status, LinkStatus::Ended);
                    break;
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(got.len(), 3);
        assert_eq!(got[2].t_s, 0.02);
        assert!((got[0].accel_mps2.unwrap()[2] + STANDARD_GRAVITY_MPS2).abs() < 1e-12);
        assert_eq!(got[1].mag_ut, Some([11.0, 21.0, 31.0]));
        let st = rig.handle.decode_stats.lock().unwrap().clone();
        assert_eq!(st.skipped.get("bad_row"), Some(&1));
    }

    #[tokio::test]
    async fn file_missing_is_lost_then_ended() {
        let addr = Address::parse("file:/nonexistent/dir/x.tlog?speed=0").unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 8);
        match rig.status().await {
            LinkStatus::Lost(r) => assert!(r.contains("cannot read"), "{r}"),
            s => panic!("{s:?}"),
        }
        assert_eq!(rig.status().await, LinkStatus::Ended);
    }

    #[tokio::test]
    async fn sim_at_speed_zero_emits_every_sample_then_ended() {
        let want = crate::sim::simulate(&crate::sim::Scenario::named("tumble").unwrap(), 3).samples;
        let addr = Address::parse("sim:tumble?seed=3&speed=0").unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 256);
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let mut n = 0;
        loop {
            match rig.next().await {
                Inbound::Sample { sample, .. } => {
                    assert_eq!(sample, want[n]);
                    n += 1;
                }
                Inbound::Status { status, .. } => {
                    assert_eq!(status, LinkStatus::Ended);
                    break;
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(n, want.len());
        assert_eq!(rig.handle.counters.samples_in.load(Relaxed), n as u64);
    }

    #[tokio::test]
    async fn sim_paced_stops_promptly_on_shutdown() {
        let mut rig = start(
            Address::parse("sim:tumble").unwrap(),
            Payload::Mavlink,
            fast_opts(),
            256,
        );
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let t0 = std::time::Instant::now();
        for _ in 0..10 {
            assert!(matches!(rig.next().await, Inbound::Sample { .. }));
        }
        // 10 samples at 100 Hz, recorded pace: about 0.09 s.
        assert!(
            t0.elapsed() > Duration::from_millis(60),
            "{:?}",
            t0.elapsed()
        );
        rig.stop().await;
    }

    #[tokio::test]
    async fn sim_scenario_file_and_bad_scenario() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("short.toml");
        std::fs::write(&path, "name = \"tumble\"\nduration_s = 2.0\n").unwrap();
        let addr = Address::parse(&format!("sim:{}?speed=0", path.display())).unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 1024);
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let mut n = 0;
        while let Inbound::Sample { .. } = rig.next().await {
            n += 1;
        }
        assert!(n > 0);
        let addr = Address::parse("sim:/nonexistent/x.toml").unwrap();
        let mut rig = start(addr, Payload::Mavlink, fast_opts(), 8);
        assert!(matches!(rig.status().await, LinkStatus::Lost(_)));
        assert_eq!(rig.status().await, LinkStatus::Ended);
    }

    #[tokio::test]
    async fn live_links_stop_promptly() {
        let port = free_udp_port();
        let mut rig = start(
            Address::UdpIn(format!("127.0.0.1:{port}").parse().unwrap()),
            Payload::Mavlink,
            fast_opts(),
            8,
        );
        assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
        let t0 = std::time::Instant::now();
        rig.stop.send(true).unwrap();
        tokio::time::timeout(Duration::from_millis(100), &mut rig.handle.task)
            .await
            .expect("stopped within 100 ms")
            .unwrap();
        assert!(t0.elapsed() < Duration::from_millis(100));
        // Already stopped before it started: returns at once.
        let (tx, _rx) = mpsc::channel(1);
        let (_s, stop_rx) = watch::channel(true);
        let h = spawn_link(
            0,
            Address::parse("sim:tumble").unwrap(),
            Payload::Mavlink,
            tx,
            stop_rx,
            LinkOptions::default(),
        );
        tokio::time::timeout(Duration::from_millis(100), h.task)
            .await
            .unwrap()
            .unwrap();
    }
}
