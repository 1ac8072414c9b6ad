//! The Python module `imucald`: a log's replay report as a dict (docs/python.md).
//!
//! `imucald.replay(path, config=None)` runs the library's replay ([`imucald::app::replay::replay`],
//! the function `imucald replay` runs) with the interpreter released, and returns the report
//! that `imucald replay LOG --report FILE` writes, as the dict `json.load` makes of that file.
//! The library's errors raise `imucald.Error` with the library's message.

use pyo3::prelude::*;
use std::path::Path;

pyo3::create_exception!(
    imucald,
    Error,
    pyo3::exceptions::PyException,
    "A log or configuration imucald could not use; the message is the library's."
);

/// The configuration at `config` (TOML, as `imucald replay --config`), or the defaults.
fn load_config(config: Option<&Path>) -> Result<imucald::config::Config, imucald::Error> {
    match config {
        Some(p) => imucald::config::Config::load(p),
        None => Ok(imucald::config::Config::default()),
    }
}

/// The replay report of the log at `log` as JSON text, with nothing written besides.
fn report_json(log: &Path, config: Option<&Path>) -> Result<String, imucald::Error> {
    let cfg = load_config(config)?;
    let opts = imucald::app::replay::ReplayOptions::default();
    let out = imucald::app::replay::replay(log, &cfg, &opts, &mut |_, _| {})?;
    serde_json::to_string(&out.report).map_err(|e| imucald::Error::Other(format!("json: {e}")))
}

/// The replay report of a log as a dict: what `imucald replay LOG --report FILE` writes.
///
/// `path` is the log (.tlog, .csv, .csv.gz, .bin, .ulg); `config` a TOML configuration or None
/// for the defaults. The interpreter is released while the log is read and fitted, so threads
/// (and Dask's threaded workers) replay logs in parallel. Raises `imucald.Error` with the
/// library's message when the log or the configuration cannot be used.
#[pyfunction]
#[pyo3(signature = (path, config=None))]
fn replay<'py>(
    py: Python<'py>,
    path: std::path::PathBuf,
    config: Option<std::path::PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    let text = py
        .detach(|| report_json(&path, config.as_deref()))
        .map_err(|e| Error::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// imucald's calibration of accelerometer, magnetometer and gyroscope, from Python:
/// `replay(path, config=None)` returns a log's replay report as a dict.
#[pymodule(name = "imucald")]
mod imucald_py {
    #[pymodule_export]
    use super::replay;
    #[pymodule_export]
    use super::Error;

    /// The version of imucald this module was built from.
    #[allow(non_upper_case_globals)]
    #[pymodule_export]
    const __version__: &str = env!("CARGO_PKG_VERSION");
}
