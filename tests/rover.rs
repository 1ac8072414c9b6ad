//! The 2-D (planar) magnetometer calibration through `replay` on a simulated rover (the `rover`
//! scenario: loops and figure-eights on gently rolling ground, the vehicle's attitude at 10 Hz
//! with 0.5 deg of noise, hidden hard iron with a z offset and soft iron): heading against the
//! simulated true heading before and after.

mod common;

use imucald::attitude::angle_diff_deg;
use imucald::calib::magmethod::MagMethod;
use imucald::calib::planar::{points_from_samples, raw_heading_deg, PlanarFit, Undetermined};
use imucald::config::Config;
use imucald::sim::{simulate, Scenario, SimOutput};

/// Heading errors (deg) over the run: per reading, and averaged over 1 s blocks (the sensor noise
/// of a single reading is about 0.4 deg).
struct Errors {
    rms_deg: f64,
    max_deg: f64,
    block_max_deg: f64,
}

fn errors(
    out: &SimOutput,
    heading: &dyn Fn(&imucald::calib::planar::PlanarPoint) -> f64,
) -> Errors {
    let pts = points_from_samples(&out.samples, &|s| *s);
    assert_eq!(pts.len(), out.samples.len());
    let e: Vec<f64> = pts
        .iter()
        .zip(&out.true_attitude)
        .map(|(p, a)| angle_diff_deg(heading(p), a[2]))
        .collect();
    let block = out.truth.rate_hz.round() as usize;
    let block_max_deg = e
        .chunks(block)
        .map(|c| (c.iter().sum::<f64>() / c.len() as f64).abs())
        .fold(0.0, f64::max);
    Errors {
        rms_deg: (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt(),
        max_deg: e.iter().fold(0.0, |m, x| m.max(x.abs())),
        block_max_deg,
    }
}

fn replay_rover(out: &SimOutput) -> imucald::report::Report {
    common::replay_samples(&out.samples, &Config::from_toml_str("").unwrap()).report
}

#[test]
fn rover_heading_within_1_deg_after_the_planar_calibration() {
    let sc = Scenario::named("rover").unwrap();
    let out = simulate(&sc, 1);
    let r = replay_rover(&out);
    let m = &r.calibration.mag;
    let choice = m.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Planar, "{}", choice.method_reason);
    assert!(
        choice
            .method_reason
            .contains("turns about the vertical only")
            && choice.method_reason.contains("z offset (held at 0)"),
        "{}",
        choice.method_reason
    );
    let fit: &PlanarFit = choice.planar.as_ref().unwrap();
    assert!(fit.undetermined.contains(&Undetermined::OffsetZ), "{fit:?}");
    assert!(fit.undetermined.contains(&Undetermined::SoftIronZ));
    assert!(!fit.undetermined.contains(&Undetermined::HeadingDeviation));
    // The z offset is held at nominal in the published calibration, never guessed.
    assert_eq!(m.offset[2], 0.0);
    assert_eq!(m.status, imucald::report::CalStatus::Ok);

    let after = errors(&out, &|p| fit.heading_deg(p));
    let before = errors(&out, &raw_heading_deg);
    eprintln!(
        "after: rms {:.3} max {:.3} 1-s max {:.3}; before: rms {:.1} max {:.1}; fit {fit:?}",
        after.rms_deg, after.max_deg, after.block_max_deg, before.rms_deg, before.max_deg
    );
    // Measured (seed 1): RMS 0.47 deg, 1-s block max 0.28 deg, single reading max 1.80 deg (the
    // magnetometer's 0.15 uT noise on a 21.6 uT horizontal field). The RMS bound is the 1 deg
    // asked for.
    assert!(after.rms_deg < 1.0, "rms {}", after.rms_deg);
    assert!(
        after.block_max_deg < 0.85,
        "1-s max {}",
        after.block_max_deg
    );
    assert!(after.max_deg < 5.0, "max {}", after.max_deg);
    // Before: the raw tilt-compensated heading, RMS 65.5 deg, max 180 deg (the hard iron is
    // larger than the horizontal field).
    assert!(before.rms_deg > 20.0, "before rms {}", before.rms_deg);
}

#[test]
fn without_an_attitude_the_course_over_ground_is_the_reference() {
    let sc = Scenario::named("rover").unwrap();
    let mut out = simulate(&sc, 2);
    for s in out.samples.iter_mut() {
        s.ref_q = None;
    }
    let r = replay_rover(&out);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Planar, "{}", choice.method_reason);
    let fit = choice.planar.as_ref().unwrap();
    let dev = fit
        .deviation
        .as_ref()
        .expect("a deviation curve from the course");
    assert_eq!(
        dev.source,
        imucald::calib::planar::ReferenceKind::CourseOverGround
    );
    let after = errors(&out, &|p| fit.heading_deg(p));
    eprintln!(
        "course: rms {:.3} max {:.3} 1-s max {:.3}; {dev:?}",
        after.rms_deg, after.max_deg, after.block_max_deg
    );
    // Measured (seed 2): RMS 0.46 deg, 1-s block max 0.22 deg, single reading max 2.05 deg.
    assert!(after.rms_deg < 1.0, "rms {}", after.rms_deg);
    assert!(
        after.block_max_deg < 0.65,
        "1-s max {}",
        after.block_max_deg
    );

    // Neither attitude nor position: the ellipse only, the deviation named as unknown.
    for s in out.samples.iter_mut() {
        s.position = None;
    }
    let r = replay_rover(&out);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Planar, "{}", choice.method_reason);
    let fit = choice.planar.as_ref().unwrap();
    assert!(fit.deviation.is_none());
    assert!(fit.undetermined.contains(&Undetermined::HeadingDeviation));
    assert!(choice
        .method_reason
        .contains("heading deviation (no heading reference)"));
}

#[test]
fn a_banking_aircraft_without_attitude_or_position_is_not_taken_for_a_rover() {
    // The cruise's coordinated turns (banks 18-26 deg) read level on the accelerometer when the
    // speed is unknown; the pitch rate through the turns gives the bank away (measured 18.5 deg).
    let sc = Scenario::named("cruise").unwrap();
    let mut out = simulate(&sc, 3);
    for s in out.samples.iter_mut() {
        s.ref_q = None;
        s.position = None;
    }
    let r = replay_rover(&out);
    let choice = r.calibration.mag.method.as_ref().unwrap();
    assert_eq!(choice.method, MagMethod::Sphere, "{}", choice.method_reason);
    assert!(
        choice
            .method_reason
            .contains("planar not taken: the turns are banked"),
        "{}",
        choice.method_reason
    );
}

/// The exports of `out` replayed: (ArduPilot `.parm`, PX4 `.params`, Fusion header).
fn exports(samples: &[imucald::types::Sample]) -> (String, String, String) {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("log.csv");
    imucald::io::samplelog::write_csv(&log, samples).unwrap();
    let opts = imucald::app::replay::ReplayOptions {
        export_dir: Some(dir.path().join("out")),
        ..Default::default()
    };
    imucald::app::replay::replay(&log, &Config::default(), &opts, &mut |_, _| {}).unwrap();
    let read = |n: &str| std::fs::read_to_string(dir.path().join("out").join(n)).unwrap();
    (read("ardupilot.parm"), read("px4.params"), read("fusion.h"))
}

/// A value of a `.parm` text, if written.
fn parm(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .find_map(|l| l.strip_prefix(&format!("{name} "))?.trim().parse().ok())
}

/// On level ground the body-z offset and soft iron are never seen from another side: they are not
/// written (the vehicle keeps its own), and a comment says why. The truth's z offset is 40 uT
/// (COMPASS_OFS_Z -400); before, -0.000000 was exported. A fixed-wing flight whose banked turns
/// and climbs do determine z exports it, near the truth.
#[test]
fn undetermined_terms_are_never_exported() {
    let rover = simulate(&Scenario::named("rover").unwrap(), 1);
    let (ap, px, fu) = exports(&rover.samples);
    for n in [
        "COMPASS_OFS_Z",
        "COMPASS_DIA_Z",
        "COMPASS_ODI_Y",
        "COMPASS_ODI_Z",
    ] {
        assert_eq!(parm(&ap, n), None, "{n} written:\n{ap}");
        assert!(ap.contains(&format!("# {n} not written")), "{ap}");
    }
    assert!(parm(&ap, "COMPASS_OFS_X").is_some(), "{ap}");
    assert!(!px.contains("CAL_MAG0_ZOFF\t"), "{px}");
    assert!(px.contains("CAL_MAG0_XOFF\t"), "{px}");
    assert!(fu.contains("magnetometer not written"), "{fu}");
    assert!(!fu.contains("hardIronOffset"), "{fu}");

    let cruise = simulate(&Scenario::named("cruise").unwrap(), 1);
    let (ap, _, fu) = exports(&cruise.samples);
    let z = parm(&ap, "COMPASS_OFS_Z").expect("the fixed-wing flight determines z");
    // Truth 40 uT: -400 mGauss. Measured -399.95.
    assert!((z + 400.0).abs() < 15.0, "COMPASS_OFS_Z {z}");
    assert!(fu.contains("hardIronOffset"), "{fu}");
}
