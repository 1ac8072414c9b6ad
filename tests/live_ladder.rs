//! The model ladder in the live service: a simulated flight streamed to `imucald run` as a flight
//! controller sends it (HIGHRES_IMU with ATTITUDE_QUATERNION at 10 Hz with 0.5 deg of noise,
//! GLOBAL_POSITION_INT and BATTERY_STATUS), no `[place]`, no tumble: the sphere fit fails for
//! coverage all flight long, and the rung the ladder takes on the learner's readings (one a second,
//! fitted and scored on alternate 20 s blocks) is installed, stored and reported.

mod common;

use imucald::calib::ladder::Rung;
use imucald::calib::magmethod::MagMethod;
use imucald::report::SensorCalibration;
use imucald::sim::{simulate, Scenario};

use common::{dist, SOFT_IRON};

/// Stream the scenario's flight to a live service over UDP (configured further by `configure`),
/// paced like a fast link, and return the magnetometer calibration it stored, with the JSON
/// lines it published.
async fn stream(
    sc: &Scenario,
    seed: u64,
    configure: impl FnOnce(&mut imucald::config::Config),
) -> (SensorCalibration, Vec<String>) {
    let sim = simulate(sc, seed);
    let dir = tempfile::tempdir().unwrap();
    let (port, mut cfg) = common::udpin_config(dir.path());
    configure(&mut cfg);
    let lines = common::stream_flight(&sim.samples, port, cfg).await;
    let store = imucald::app::daemon::load_store(&dir.path().join("cal"))
        .unwrap()
        .expect("a calibration stored");
    (store.mag.expect("a magnetometer calibration"), lines)
}

/// Banked turns of 18-26 deg with a hidden offset and no soft iron: the offsets rung is taken,
/// and the offset lands within 0.5 uT of the truth.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn banked_turns_with_a_hidden_offset_take_the_offsets_rung_live() {
    let mut sc = Scenario::named("cruise").unwrap();
    sc.truth.mag.matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let (m, lines) = stream(&sc, 1, |_| {}).await;
    let choice = m.method.as_ref().expect("the method is recorded");
    let err = dist(&m.offset, &sc.truth.mag.offset);
    println!(
        "live offsets rung: {:?} against {:?}, {err:.3} uT; {}",
        m.offset, sc.truth.mag.offset, choice.method_reason
    );
    assert_eq!(choice.method, MagMethod::Vector, "{}", choice.method_reason);
    assert_eq!(choice.rung, Some(Rung::Offsets), "{}", choice.method_reason);
    assert!(
        choice.method_reason.contains("learnt live")
            && choice.method_reason.contains("GPS")
            && choice.method_reason.contains("offsets rung")
            && choice
                .method_reason
                .contains("no calibration of the vehicle's to start from"),
        "{}",
        choice.method_reason
    );
    assert!(err < 0.5, "live offset {err} uT off");
    assert!(
        lines.iter().any(|l| l.contains("\"type\":\"calibration\"")
            && l.contains("\"vector\"")
            && l.contains("\"installed\":true")),
        "no installed vector calibration line among {} lines",
        lines.len()
    );
}

/// Banks of 45-70 deg turn the field through every body axis: with a hidden full soft iron the
/// live service takes the full rung, every matrix element within 1 % of the truth. Such banks
/// also cover enough of the sphere for its fit, which the service then installs; here it wants
/// every coverage region (`accept.mag.min_filled_regions = 100`), so the ladder stands in.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn steep_banks_with_a_hidden_full_soft_iron_take_the_full_rung_live() {
    let mut sc = Scenario::named("cruise").unwrap();
    sc.cruise.bank_deg = [45.0, 70.0];
    sc.truth.mag.matrix = SOFT_IRON;
    let (m, _) = stream(&sc, 2, |cfg| cfg.accept.mag.min_filled_regions = 100).await;
    let choice = m.method.as_ref().expect("the method is recorded");
    let worst = common::matrix_dist(&m.matrix, &SOFT_IRON);
    let err = dist(&m.offset, &sc.truth.mag.offset);
    println!(
        "live full rung: matrix within {worst:.4} of the truth, offset {err:.3} uT; {}",
        choice.method_reason
    );
    assert_eq!(choice.rung, Some(Rung::Full), "{}", choice.method_reason);
    assert!(worst < 0.01, "{:?}", m.matrix);
    assert!(err < 0.5, "{:?}", m.offset);
}
