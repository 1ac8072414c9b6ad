//! imucald: online calibration of accelerometer, magnetometer and gyroscope, with heading.
//!
//! Folders by pipeline stage (see ARCHITECTURE.md):
//!
//! * [`io`]: bytes in and out. Logs and live links become [`types::Sample`]s; calibrations become
//!   MAVLink messages and files. The only place that knows transports, formats and the disk.
//! * [`calib`]: gating, coverage, calibration models and fits, and the choice of method. Pure math:
//!   no I/O, no tokio.
//! * [`attitude`]: orientation from calibrated vectors (the fusion filter, tilt-compensated
//!   heading, the earth field) and its error metrics. Pure math.
//! * [`diagnose`]: where simulation and measurement disagree, and which effect is missing. Pure.
//! * [`sim`]: the simulator of IMUs, trajectories and disturbances the tests and `diagnose` use.
//! * [`app`]: what a user runs: the live service, `replay`, the pages and plots. Composes the
//!   others; holds no math of its own.
//!
//! At the root, the vocabulary every stage shares: [`types`] (samples), [`config`] (settings),
//! [`report`] (the JSON report's types), [`error`] (typed errors).

// `!(x > 0.0)` is deliberate throughout: it is true for NaN, which `x <= 0.0` is not.
// Index loops over the three axes read more plainly than iterator chains in the math.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod app;
pub mod attitude;
pub mod calib;
pub mod config;
pub mod diagnose;
pub mod error;
pub mod io;
pub mod report;
pub mod sim;
/// Test set-up shared with the integration tests (`tests/common` includes the same file).
#[cfg(test)]
mod testdata;
/// `imucald::` names this crate in test builds, as it does in the integration tests, so that
/// [`testdata`] is one text for both.
#[cfg(test)]
extern crate self as imucald;
pub mod types;

pub use error::Error;
