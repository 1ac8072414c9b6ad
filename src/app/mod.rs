//! What a user runs: [`daemon`] (the live service, `imucald run`), [`replay`] (a log through the
//! same pipeline), [`batch`] (many logs, one table), [`eval`] (the orientation filter against a
//! reference), [`fixedyaw`] (offsets at one known heading, for `imucald fixed-yaw` and the
//! service), [`simulate`] (a simulated log written), [`ui`] (the live page and the HTML report) and
//! [`plot`] (PNG and SVG pictures).
//!
//! Composes `io`, `calib` and `attitude`; holds no math of its own. Only here does tokio appear,
//! and only the daemon spawns tasks; every queue it makes is bounded and counts its drops.

pub mod batch;
pub mod daemon;
pub mod eval;
pub mod fixedyaw;
pub mod plot;
pub mod replay;
pub mod simulate;
pub mod ui;
