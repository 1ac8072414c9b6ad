//! Set-up the integration tests share: loopback ports, service configurations and the Python
//! peers that `scripts/test` installs.

// Each test file uses a part of this module.
#![allow(dead_code)]

use imucald::config::{Config, SourceConfig};
use std::path::Path;

/// A UDP port on the loopback that was free a moment ago.
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A MAVLink source at `address` (`udpin:IP:PORT`, `file:LOG`, `sim:SCENARIO` ...).
pub fn mavlink_source(address: impl Into<String>) -> SourceConfig {
    SourceConfig {
        address: address.into(),
        payload: "mavlink".into(),
        fields: vec![],
        scales: Default::default(),
    }
}

/// A service config with one `udpin:` MAVLink source on a free loopback port (returned) and its
/// calibration directory under `dir`.
pub fn udpin_config(dir: &Path) -> (u16, Config) {
    let port = free_udp_port();
    let mut cfg = Config::default();
    cfg.daemon.sources = vec![mavlink_source(format!("udpin:127.0.0.1:{port}"))];
    cfg.daemon.calibration_dir = dir.join("cal").display().to_string();
    (port, cfg)
}

/// The Python `scripts/test` installs (`.venv`), or `IMUCALD_PYTHON`.
pub fn python_path() -> String {
    std::env::var("IMUCALD_PYTHON")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/.venv/bin/python").to_string())
}

/// [`python_path`], checked to import `module` (pymavlink, pyulog).
pub fn python_with(module: &str) -> String {
    let p = python_path();
    let ok = std::process::Command::new(&p)
        .args(["-c", &format!("import {module}")])
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        ok,
        "no Python with {module} at {p}: run ./scripts/test (it installs a venv) or set IMUCALD_PYTHON"
    );
    p
}
