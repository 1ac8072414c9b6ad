//! Where the tests find the real recordings (`../shared/data` beside the checkout), and what a test
//! does when a resource it needs is absent ([`absent`]: the recordings here, Chromium and the
//! Python peers in `tests/common`): it says SKIPPED plainly and returns, unless the resource's
//! `IMUCALD_REQUIRE_*=1` (set by `scripts/test`, which CI runs) makes the absence a failure. Also a
//! HIGHRES_IMU message and a passing magnetometer calibration for tests that need one to send or
//! store. For tests only; no other use.

use crate::report::{CalStatus, SensorCalibration};
use crate::types::Vec3;
use std::path::PathBuf;

/// Environment variable that turns "recordings absent" into a test failure when set to `1`.
pub const REQUIRE_DATA_ENV: &str = "IMUCALD_REQUIRE_DATA";

/// The shared recordings directory, or `None` (SKIPPED said) when it is absent.
///
/// # Panics
/// When it is absent and `IMUCALD_REQUIRE_DATA=1`: a real-data test must not pass without its data.
pub fn shared_data() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"));
    if p.is_dir() {
        return Some(p);
    }
    absent(
        &p.display().to_string(),
        REQUIRE_DATA_ENV,
        "real-data tests need the shared recordings beside the checkout",
    )
}

/// What a test does without a resource it needs (`what`): says `SKIPPED` plainly, with `how` to
/// get it, and gives `None` for the test to return on; or fails when `require_env` is `1`.
///
/// # Panics
/// When `require_env` is `1`: a test must not pass without what it tests against.
pub fn absent<T>(what: &str, require_env: &str, how: &str) -> Option<T> {
    if std::env::var(require_env).is_ok_and(|v| v == "1") {
        panic!("{what} is absent and {require_env}=1 ({how})");
    }
    eprintln!("SKIPPED: {what} is absent ({how}; {require_env}=1 makes this a failure)");
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

/// The system id a test's ground station sends its pings with (no test vehicle uses it).
pub const PING_SYSTEM: u8 = 250;

/// The live service's ids as configured by default (system 1, component 191): whom a ping goes to.
pub const SERVICE_IDS: (u8, u8) = (1, crate::io::mavout::DEFAULT_COMPONENT_ID);

/// A ping for the live service: a command it does not support (REQUEST_MESSAGE), addressed to it as
/// `to` (system, component), from ground station [`PING_SYSTEM`] as component `mark`. The service
/// answers it with a COMMAND_ACK whose `target_component` is `mark`, once it took everything the
/// link delivered before: a link is read in order.
pub fn ping(mark: u8, to: (u8, u8)) -> Vec<u8> {
    use mavlink::dialects::ardupilotmega::{MavCmd, MavMessage, COMMAND_LONG_DATA};
    crate::io::mavout::MavEncoder::new(PING_SYSTEM, mark).encode(&MavMessage::COMMAND_LONG(
        COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            target_system: to.0,
            target_component: to.1,
            ..Default::default()
        },
    ))
}

/// The mark of the [`ping`] a frame answers, if it is such an answer.
pub fn pong(f: &crate::io::decode::Frame) -> Option<u8> {
    use mavlink::dialects::ardupilotmega::{MavCmd, MavMessage};
    match &f.message {
        MavMessage::COMMAND_ACK(a)
            if a.command == MavCmd::MAV_CMD_REQUEST_MESSAGE && a.target_system == PING_SYSTEM =>
        {
            Some(a.target_component)
        }
        _ => None,
    }
}

/// Sends a [`ping`] (mark 1, to the service as `to`) from `sock` to the service's `udpin` link at
/// `port` on the loopback, and waits for the answer on `sock`: the service has then taken
/// everything `sock` sent it before. Frames arriving meanwhile go to `other`.
///
/// # Panics
/// When no answer comes within `within`.
pub async fn taken(
    sock: &tokio::net::UdpSocket,
    port: u16,
    to: (u8, u8),
    within: std::time::Duration,
    mut other: impl FnMut(&crate::io::decode::Frame),
) {
    const MARK: u8 = 1;
    sock.send_to(&ping(MARK, to), ("127.0.0.1", port))
        .await
        .expect("send the ping");
    let mut dec = crate::io::decode::FrameDecoder::new();
    let mut buf = vec![0u8; 65_536];
    let until = tokio::time::Instant::now() + within;
    loop {
        let Ok(got) = tokio::time::timeout_at(until, sock.recv_from(&mut buf)).await else {
            panic!("no answer to the ping within {within:?}");
        };
        let (n, _) = got.expect("receive");
        for f in dec.push(&buf[..n]) {
            if pong(&f) == Some(MARK) {
                return;
            }
            other(&f);
        }
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

    #[test]
    fn an_absent_resource_is_skipped_or_fails_under_its_switch() {
        // A switch of this test's own: no other test reads it.
        const SWITCH: &str = "IMUCALD_REQUIRE_TESTDATA_SELF_CHECK";
        std::env::remove_var(SWITCH);
        assert_eq!(
            super::absent::<()>("the thing", SWITCH, "how to get it"),
            None
        );
        std::env::set_var(SWITCH, "1");
        let failed = std::panic::catch_unwind(|| super::absent::<()>("the thing", SWITCH, "how"));
        std::env::remove_var(SWITCH);
        let message = failed.expect_err("fails under the switch");
        let text = message
            .downcast_ref::<String>()
            .cloned()
            .unwrap_or_default();
        assert!(
            text.contains("the thing is absent") && text.contains(SWITCH),
            "{text}"
        );
    }
}
