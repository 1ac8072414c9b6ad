//! A replay's memory does not grow with the log's length: a log ten times longer (ten times as
//! many simulated tumbles joined) keeps at most the same bounded number of samples
//! (`ReplayOutcome::kept`), fits the same calibration, and still writes a calibrated row for
//! every sample (read again from the file for those rows).

use imucald::app::replay::{replay, ReplayOptions, ReplayOutcome};
use imucald::config::Config;
use imucald::io::samplelog::{write_tlog, TlogWriteOptions};
use imucald::report::CalStatus;
use imucald::sim::{simulate, Scenario, Truth};
use std::path::Path;

/// The simulated tumbles of seeds `1..=n` joined into one log at `path` (as `cat` joins logs),
/// and the truth of the scenario (the same sensors whatever the seed).
fn joined_tumbles(n: u64, dir: &Path, path: &Path) -> Truth {
    let mut joined = Vec::new();
    let mut truth = None;
    for seed in 1..=n {
        let sim = simulate(&Scenario::named("tumble").unwrap(), seed);
        let one = dir.join(format!("s{seed}.tlog"));
        write_tlog(&one, &sim.samples, &TlogWriteOptions::default()).unwrap();
        joined.extend(std::fs::read(&one).unwrap());
        truth = Some(sim.truth);
    }
    std::fs::write(path, joined).unwrap();
    truth.unwrap()
}

fn run(path: &Path, calibrated: Option<&Path>) -> ReplayOutcome {
    let opts = ReplayOptions {
        calibrated_out: calibrated.map(Path::to_path_buf),
        ..Default::default()
    };
    replay(path, &Config::default(), &opts, &mut |_, _| {})
        .unwrap_or_else(|e| panic!("replay {}: {e}", path.display()))
}

#[test]
fn a_log_ten_times_longer_keeps_no_more_and_fits_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let (short, long) = (dir.path().join("short.tlog"), dir.path().join("long.tlog"));
    joined_tumbles(2, dir.path(), &short);
    let truth = joined_tumbles(20, dir.path(), &long);
    let rows = dir.path().join("long.csv");
    let a = run(&short, None);
    let b = run(&long, Some(&rows));
    eprintln!("short {:?}\nlong {:?}", a.kept, b.kept);

    // The short log is kept whole; the long one thinned to the same cap, whatever its length.
    assert_eq!(a.kept.held as u64, a.kept.seen);
    assert!(a.kept.held < a.kept.cap);
    assert!(b.kept.seen >= 9 * a.kept.seen, "{:?} {:?}", a.kept, b.kept);
    assert_eq!(b.kept.seen, b.report.input.samples);
    assert!(b.kept.largest <= b.kept.cap && b.kept.held <= b.kept.cap);
    assert!((b.kept.held as u64) < b.kept.seen / 2, "{:?}", b.kept);
    assert!(b.kept.gyro_span_samples <= b.kept.cap, "{:?}", b.kept);
    assert!(b.kept.gyro_span_samples > 0);

    // The same calibration.
    let (ma, mb) = (&a.report.calibration.mag, &b.report.calibration.mag);
    assert_eq!(ma.status, CalStatus::Ok);
    assert_eq!(mb.status, CalStatus::Ok);
    let off = |m: &imucald::report::SensorCalibration| {
        (0..3)
            .map(|k| (m.offset[k] - truth.mag.offset[k]).abs())
            .fold(0.0, f64::max)
    };
    let scale = |r: &ReplayOutcome| {
        let g = r.report.calibration.gyro.scale.as_ref();
        let g = g.unwrap_or_else(|| panic!("{:?}", r.report.calibration.gyro.scale_failure));
        (0..3)
            .flat_map(|i| (0..3).map(move |j| (i, j)))
            .map(|(i, j)| (truth.gyro.matrix[i][j] - g.matrix[i][j]).abs())
            .fold(0.0, f64::max)
    };
    let (off_a, off_b, scale_a, scale_b) = (off(ma), off(mb), scale(&a), scale(&b));
    eprintln!(
        "from the truth: mag offset {off_a:.2e} -> {off_b:.2e} uT, gyro scale {scale_a:.2e} -> {scale_b:.2e}"
    );
    // Measured: mag offset 4.2e-3 (short) and 2.1e-2 uT (long), gyro scale 3.3e-4 and 2.9e-4
    // (the long log's from an evenly spread choice of its rotations, kept as it was read).
    assert!(off_b < 0.06, "{off_b}");
    assert!(scale_b < 7e-4, "{scale_b}");

    // A calibrated row for every sample of the long log (a header line first).
    let text = std::fs::read_to_string(&rows).unwrap();
    assert_eq!(
        text.lines().count() as u64 - 1,
        b.report.input.samples,
        "calibrated rows"
    );
}
