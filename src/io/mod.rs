//! Bytes in and out: the only folder that knows files, sockets, serial ports and formats.
//!
//! In: [`sources`] (log files, decoded whole) and [`link`] (live transports and the paced replay
//! of a file) hand bytes to [`decode`] (MAVLink frames, `.tlog` records, CSV) and [`flightlog`]
//! (ArduPilot DataFlash, PX4 ULog), which turn them into samples (a file read as a stream through a
//! [`window`]), and [`mocap`] reads optical motion
//! capture (OptiTrack Motive CSV exports) as an attitude reference; [`clock`] gives every source one
//! time line that never goes backwards. Out: [`mavout`] encodes what the service says (MAVLink
//! frames, JSON lines) as pure functions, [`publish`] writes files atomically.
//!
//! Must not: fit, filter or decide anything about a calibration; that is `calib` and `attitude`.
//! Bad input is counted and skipped here, never passed on as NaN and never a panic.

pub mod ardupilot;
pub mod clock;
pub mod decode;
pub mod flightlog;
pub mod identity;
pub mod link;
pub mod mavftp;
pub mod mavout;
pub mod mocap;
pub mod onboard;
pub mod publish;
pub mod samplelog;
pub mod sources;
pub(crate) mod window;
