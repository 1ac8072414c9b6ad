//! `cargo bench --bench flightlogs`: decoding throughput of flight-controller logs against the
//! reference readers in the same run: pymavlink's `DFReader` on two DataFlash logs (the shared
//! 64 KiB ArduPlane log repeated 64 times, 4 MiB: a record cut by each join is skipped by both; and
//! a simulated 25-minute tumble at 100 Hz, 13 MB, written here by the simulator as `imucald
//! simulate` writes it) and pyulog's `ULog` on `px4_auav_x21.ulg` (4 MB). imucald is timed on what
//! `replay` does with the file before the pipeline: the reader and the conversion to samples of
//! every instance (`sources::decode_log`), best of 5; and on the whole replay in the library (the
//! file read and gated, every fit, the report; `app::replay::replay`, best of 5), which is the
//! process's time but for its start. Python times itself after its imports (best of 3).
//! Prints MB/s and the ratios; figures, not assertions. Python: `$IMUCALD_PYTHON` or
//! `.venv/bin/python` with pymavlink and pyulog (`scripts/test` installs them).
//! Needs `[[bench]] name = "flightlogs" harness = false` in Cargo.toml.

#![allow(dead_code)]

#[path = "../tests/common/python.rs"]
mod python;

use imucald::config::Config;
use imucald::io::decode::Format;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

const PEER: &str = r#"
import sys, time
kind, path = sys.argv[1], sys.argv[2]
best = None
for _ in range(3):
    t = time.perf_counter()
    if kind == "bin":
        from pymavlink import DFReader
        r = DFReader.DFReader_binary(path, zero_time_base=False)
        n = 0
        while r.recv_msg() is not None:
            n += 1
    else:
        from pyulog import ULog
        u = ULog(path)
        n = sum(len(d.data["timestamp"]) for d in u.data_list)
    dt = time.perf_counter() - t
    best = dt if best is None else min(best, dt)
print(best, n)
"#;

fn python_time(kind: &str, path: &Path) -> Option<(f64, u64)> {
    let py = python::python_path();
    let out = Command::new(&py)
        .args(["-c", PEER, kind])
        .arg(path)
        .stderr(Stdio::null())
        .output()
        .ok()?;
    if !out.status.success() {
        println!("peer: {py} could not run pymavlink/pyulog (scripts/test installs them)");
        return None;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut it = text.split_whitespace();
    Some((it.next()?.parse().ok()?, it.next()?.parse().ok()?))
}

/// The simulated tumble: 25 minutes at 100 Hz, long enough for its 150,000 samples to be
/// thinned as a replay keeps them.
const TUMBLE_25_MIN: &str =
    "name = \"tumble\"\nrate_hz = 100.0\nduration_s = 1500.0\npauses = 400\n";

/// Best of 5 of the whole replay of `path` in the library, s.
fn replay_time(path: &Path) -> f64 {
    let cfg = Config::default();
    let opts = imucald::app::replay::ReplayOptions::default();
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t = Instant::now();
        let out = imucald::app::replay::replay(path, &cfg, &opts, &mut |_, _| {}).expect("replays");
        best = best.min(t.elapsed().as_secs_f64());
        std::hint::black_box(&out.report);
    }
    best
}

fn ours(bytes: &[u8], format: Format) -> (f64, usize) {
    let cfg = Config::default();
    let mut best = f64::INFINITY;
    let mut n = 0;
    for _ in 0..5 {
        let t = Instant::now();
        let log =
            imucald::io::sources::decode_log(bytes, Path::new("bench"), Some(format), &cfg.input)
                .expect("decodes");
        best = best.min(t.elapsed().as_secs_f64());
        n = log.samples.len();
    }
    (best, n)
}

fn main() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/flightlogs");
    if !dir.is_dir() {
        println!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let tmp = tempfile::tempdir().expect("temp dir");
    let bin = std::fs::read(dir.join("ardupilot_plane_pixracer.bin")).expect("bin");
    let big = bin.repeat(64);
    let big_path = tmp.path().join("repeated.bin");
    std::fs::write(&big_path, &big).expect("write");
    let ulg_path = dir.join("px4_auav_x21.ulg");
    let ulg = std::fs::read(&ulg_path).expect("ulg");
    let tumble_path = tmp.path().join("tumble25.bin");
    let scenario = imucald::sim::Scenario::from_toml_str(TUMBLE_25_MIN).expect("scenario");
    let sim = imucald::sim::simulate(&scenario, 1);
    imucald::io::flightlog::write::write_flight_log(
        &tumble_path,
        &sim.samples,
        &imucald::io::flightlog::write::OnboardMag::example(),
    )
    .expect("write the tumble");
    let tumble = std::fs::read(&tumble_path).expect("tumble");
    println!("| log | MB | imucald s (MB/s) | reference s (MB/s) | ratio | replay s | ratio |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for (name, bytes, path, format, kind) in [
        (
            "DataFlash x64",
            &big,
            big_path.as_path(),
            Format::Bin,
            "bin",
        ),
        (
            "DataFlash tumble 25 min",
            &tumble,
            tumble_path.as_path(),
            Format::Bin,
            "bin",
        ),
        ("ULog auav", &ulg, ulg_path.as_path(), Format::Ulg, "ulg"),
    ] {
        let mb = bytes.len() as f64 / 1e6;
        let (t, n) = ours(bytes, format);
        let peer = python_time(kind, path);
        let r = replay_time(path);
        let (pt, ratio, replay_ratio) = match peer {
            Some((pt, _)) => (
                format!("{pt:.3} ({:.1})", mb / pt),
                format!("{:.1}x", pt / t),
                format!("{:.1}x", pt / r),
            ),
            None => ("-".into(), "-".into(), "-".into()),
        };
        println!(
            "| {name} | {mb:.2} | {t:.4} ({:.0}), {n} samples | {pt} | {ratio} | {r:.4} | {replay_ratio} |",
            mb / t
        );
    }
}
