//! Calibration as pure math: samples in, calibrations with their uncertainties and verdicts out.
//!
//! [`gate`] finds static poses, [`coverage`] tracks which directions they cover (its regions and
//! ArduPilot's 80 [`sections`], the MAG_CAL_PROGRESS mask), [`model`] holds the calibration models
//! (`calibrated = M (raw - offset)`), [`fit`] fits them with the one
//! Levenberg-Marquardt solver ([`lm`]), [`pipeline`] composes these per sample for `replay` and the
//! live service, each sensor's fit ending as an [`outcome`]. Methods beside the sphere fit:
//! [`vector`] (attitude and the earth field),
//! [`fixedyaw`] (one known heading), [`planar`] (ground vehicles), chosen by [`magmethod`], and [`learn`] (the vector fit
//! learnt continuously by the live service); [`gyro`] for the gyroscope;
//! [`export`] converts a calibration to flight-stack parameters.
//!
//! Must not: do I/O, know tokio, or read the clock. Fits are plain functions the live service
//! runs off its executor.

pub mod ardupilot;
pub mod blockmean;
pub mod coverage;
pub mod export;
pub mod fit;
pub mod fixedyaw;
pub mod gate;
pub mod gyro;
pub mod ladder;
pub mod learn;
pub mod lm;
pub mod magmethod;
pub mod model;
pub mod mounting;
pub mod outcome;
pub mod pipeline;
pub mod planar;
pub mod plausible;
pub mod sections;
pub mod settings;
pub mod tempcal;
pub mod vector;
