//! Typed errors of the library (anyhow only in `main`).

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("config {key}: {message}")]
    Config { key: String, message: String },
    /// The calibration store is held by another service (its process id, when its lock file
    /// says it).
    #[error("{} is held by another imucald service ({}): one service per calibration store; stop that one, or give this one another daemon.calibration_dir", .path.display(), holder_text(.holder))]
    StoreLocked { path: PathBuf, holder: Option<u32> },
    #[error("{0}")]
    Other(String),
}

pub type Result<T> = std::result::Result<T, Error>;

/// "pid N", or that it is not known.
fn holder_text(holder: &Option<u32>) -> String {
    match holder {
        Some(p) => format!("pid {p}"),
        None => "pid unknown".into(),
    }
}
