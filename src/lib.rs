//! imucald: online calibration of accelerometer, magnetometer and gyroscope, with heading.
//!
//! Modules by pipeline stage (see ARCHITECTURE.md). The math and gating modules (`gate`, `coverage`,
//! `model`, `fit`, `attitude`, `pipeline`, `export`) do no I/O and know nothing of tokio; only
//! `sources`/`decode` read bytes and only `publish` writes them.

// `!(x > 0.0)` is deliberate throughout: it is true for NaN, which `x <= 0.0` is not.
// Index loops over the three axes read more plainly than iterator chains in the math.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod attitude;
pub mod clock;
pub mod config;
pub mod coverage;
pub mod daemon;
pub mod decode;
pub mod diagnose;
pub mod error;
pub mod eval;
pub mod export;
pub mod fit;
pub mod fixedyaw;
pub mod flightlog;
pub mod fusion;
pub mod gate;
pub mod gyro;
pub mod link;
pub mod lm;
pub mod magmethod;
pub mod mavout;
pub mod model;
pub mod pipeline;
pub mod planar;
pub mod plot;
pub mod publish;
pub mod replay;
pub mod report;
pub mod sim;
pub mod sources;
#[doc(hidden)]
pub mod testdata;
pub mod types;
pub mod ui;
pub mod vector;

pub use error::Error;
