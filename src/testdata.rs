//! Where the tests find the real recordings (`../shared/data` beside the checkout), and what a test
//! does when they are absent: it says so plainly and returns, unless `IMUCALD_REQUIRE_DATA=1` (set by
//! `scripts/test`, which CI runs) makes the absence a failure. Also a HIGHRES_IMU message and a
//! passing magnetometer calibration for tests that need one to send or store. For tests only; no other use.

use crate::report::{CalStatus, SensorCalibration};
use crate::types::Vec3;
use std::path::PathBuf;

/// Environment variable that turns "recordings absent" into a test failure when set to `1`.
pub(crate) const REQUIRE_DATA_ENV: &str = "IMUCALD_REQUIRE_DATA";

/// The shared recordings directory, or `None` (with a message) when it is absent.
///
/// # Panics
/// When it is absent and `IMUCALD_REQUIRE_DATA=1`: a real-data test must not pass without its data.
pub fn shared_data() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"));
    if p.is_dir() {
        return Some(p);
    }
    if std::env::var(REQUIRE_DATA_ENV).is_ok_and(|v| v == "1") {
        panic!(
            "{} is absent and {REQUIRE_DATA_ENV}=1: real-data tests need the shared recordings",
            p.display()
        );
    }
    eprintln!(
        "SKIPPED: {} is absent; real-data tests need the shared recordings beside the checkout",
        p.display()
    );
    None
}

/// A HIGHRES_IMU of a level vehicle at `time_usec` reading `xacc` m/s^2 along x (z: -9.8 m/s^2;
/// field 0.2, 0.01, 0.4 gauss; 30 degC).
pub fn level_highres_imu(
    time_usec: u64,
    xacc: f32,
) -> mavlink::dialects::ardupilotmega::MavMessage {
    use mavlink::dialects::ardupilotmega::{MavMessage, HIGHRES_IMU_DATA};
    MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
        time_usec,
        xacc,
        zacc: -9.8,
        xmag: 0.2,
        ymag: 0.01,
        zmag: 0.4,
        temperature: 30.0,
        ..Default::default()
    })
}

/// A passing magnetometer calibration of `model` with hard iron `offset_ut`, no soft iron, and
/// plausible figures (radius 50 uT, RMS residual 0.1 uT, offset sigma 0.01 uT, 500 samples, 5
/// iterations).
pub fn passing_mag_calibration(
    model: crate::calib::model::CalModel,
    offset_ut: Vec3,
) -> SensorCalibration {
    SensorCalibration {
        offset: offset_ut,
        radius: 50.0,
        rms_residual: 0.1,
        offset_sigma: [0.01; 3],
        samples_used: 500,
        iterations: 5,
        ..SensorCalibration::new(CalStatus::Ok, model, crate::types::CalUnits::Ut)
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn finds_the_recordings_or_says_why_not() {
        // Both branches are real: with the data present the path is a directory; without it, the
        // result is None unless the switch is set (then the call fails the test).
        match super::shared_data() {
            Some(p) => assert!(p.is_dir(), "{}", p.display()),
            None => assert!(std::env::var(super::REQUIRE_DATA_ENV).ok().as_deref() != Some("1")),
        }
    }
}
