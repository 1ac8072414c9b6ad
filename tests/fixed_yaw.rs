//! A fixed-yaw compass calibration driven by a pymavlink ground station, as a user of a vehicle that
//! cannot be tumbled runs it: the vehicle rests at a known yaw, the ground station sends
//! MAV_CMD_FIXED_MAG_CAL_YAW with that yaw and the place, the service answers with COMMAND_ACK and
//! MAG_CAL_REPORT and writes the calibration. The peer (`tests/interop/pymavlink_fixed_yaw.py`) is
//! written against pymavlink; `./scripts/test` installs it into `.venv`.

mod common;

use imucald::attitude::{earth_field, Place};
use std::process::Command;
use std::time::Duration;

#[test]
fn pymavlink_ground_station_runs_a_fixed_yaw_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    // On command only: a resting vehicle never fills the sphere, and nothing else may install a
    // calibration meanwhile.
    let (cal, mut svc) = common::spawn_on_command_service(
        dir.path(),
        &[format!("{{ address = \"udpin:127.0.0.1:{port}\" }}")],
    );
    std::thread::sleep(Duration::from_millis(500));
    // The field the service will use: the WMM at the place, today (the service's date too).
    let (lat, lon) = (47.4, 8.5);
    let place = Place {
        latitude_deg: lat,
        longitude_deg: lon,
        altitude_m: 0.0,
        date: None,
    };
    let b = earth_field(&place).unwrap().field_ned_ut();
    let hard = [14.0, -27.5, 33.0];
    let (yaw, roll, pitch) = (123.0, 3.0, -2.0);
    let out = Command::new(common::python_with("pymavlink"))
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/interop/pymavlink_fixed_yaw.py"
        ))
        .arg(port.to_string())
        .args([yaw, roll, pitch, lat, lon].map(|x| x.to_string()))
        .args(b.map(|x| x.to_string()))
        .args(hard.map(|x| x.to_string()))
        .output()
        .expect("python with pymavlink: run ./scripts/test (it makes .venv)");
    let seen = String::from_utf8_lossy(&out.stdout).to_string();
    eprintln!(
        "peer: {seen}{}",
        String::from_utf8_lossy(&out.stderr)
            .lines()
            .last()
            .unwrap_or("")
    );
    let _ = Command::new("kill")
        .args(["-TERM", &svc.id().to_string()])
        .status();
    let _ = svc.wait();
    assert!(out.status.success(), "peer checks failed: {seen}");
    // Measured: the report 0.048 mGauss from the truth.
    let v: serde_json::Value = serde_json::from_str(seen.trim()).unwrap();
    let e = v["ofs_error_mgauss"].as_f64().unwrap();
    assert!(e < 0.15, "report {e} mGauss off");
    // Written: the calibration file holds the offset found.
    let store = imucald::app::daemon::load_store(&cal)
        .unwrap()
        .expect("written");
    let m = store.mag.expect("a magnetometer calibration");
    let err = (0..3)
        .map(|k| (m.offset[k] - hard[k]).abs())
        .fold(0.0, f64::max);
    eprintln!("stored offset error {err:.4} uT");
    // Measured: 0.0048 uT (the noise's mean over 100 samples).
    assert!(err < 0.015, "stored offset error {err} uT");
}

/// The same ground station commanding a fixed yaw 3 s after the data stopped: refused
/// (MAV_RESULT_FAILED) with the reason in a STATUSTEXT, and nothing installed or written. (Before,
/// it was accepted on the last samples and installed.)
#[test]
fn fixed_yaw_on_stale_data_is_refused_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_udp_port();
    let (cal, mut svc) = common::spawn_on_command_service(
        dir.path(),
        &[format!("{{ address = \"udpin:127.0.0.1:{port}\" }}")],
    );
    std::thread::sleep(Duration::from_millis(500));
    let out = Command::new(common::python_with("pymavlink"))
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/interop/pymavlink_fixed_yaw.py"
        ))
        .arg(port.to_string())
        .args(
            [
                123.0, 3.0, -2.0, 47.4, 8.5, 21.0, 0.8, 43.0, 14.0, -27.5, 33.0,
            ]
            .map(|x: f64| x.to_string()),
        )
        .env("STALE_S", "3")
        .output()
        .expect("python with pymavlink: run ./scripts/test (it makes .venv)");
    let _ = Command::new("kill")
        .args(["-TERM", &svc.id().to_string()])
        .status();
    let _ = svc.wait();
    let seen = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "peer saw: {seen}");
    assert!(imucald::app::daemon::load_store(&cal)
        .unwrap()
        .and_then(|s| s.mag)
        .is_none());
}

/// `imucald fixed-yaw LOG --yaw-deg Y --lat --lon` on a log of a vehicle resting at yaw Y: the
/// offset it prints is the hidden hard iron.
#[test]
fn fixed_yaw_subcommand_finds_the_offset_in_a_log() {
    use nalgebra::{Rotation3, Vector3};
    let dir = tempfile::tempdir().unwrap();
    let (lat, lon, yaw): (f64, f64, f64) = (-33.9, 151.2, 281.0);
    let b = earth_field(&Place {
        latitude_deg: lat,
        longitude_deg: lon,
        altitude_m: 0.0,
        date: None,
    })
    .unwrap()
    .field_ned_ut();
    let hard = [-8.0, 21.0, -4.5];
    let r =
        Rotation3::from_euler_angles(2.0f64.to_radians(), 4.0f64.to_radians(), yaw.to_radians());
    let m = r.inverse() * Vector3::from(b);
    let g = r.inverse() * Vector3::new(0.0, 0.0, -9.80665);
    let mut csv = String::from("t,ax,ay,az,mx,my,mz\n");
    for k in 0..300 {
        let j = 0.03 * ((k as f64) * 1.3).sin();
        csv += &format!(
            "{},{},{},{},{},{},{}\n",
            k as f64 * 0.01,
            g[0],
            g[1],
            g[2] + j,
            m[0] + hard[0] + j,
            m[1] + hard[1],
            m[2] + hard[2] - j
        );
    }
    let log = dir.path().join("rest.csv");
    std::fs::write(&log, csv).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .arg("fixed-yaw")
        .arg(&log)
        .args(["--yaw-deg", &yaw.to_string()])
        .args(["--lat", &lat.to_string(), "--lon", &lon.to_string()])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let line = text.lines().next().unwrap();
    let inside = &line[line.rfind('[').unwrap() + 1..line.rfind(']').unwrap()];
    let got: Vec<f64> = inside
        .split(',')
        .map(|x| x.trim().parse().unwrap())
        .collect();
    let err = (0..3).map(|k| (got[k] - hard[k]).abs()).fold(0.0, f64::max);
    eprintln!("{text}offset error {err:.3} uT");
    // Measured: 0.00 uT at the printed precision (0.01 uT); the jitter averages out.
    assert!(err < 0.03, "offset error {err} uT");
    assert!(
        text.contains("COMPASS_OFS_X") && text.contains("CAL_MAG0_XOFF"),
        "{text}"
    );
}
