//! `cargo bench --bench fit` (or `scripts/bench`, which also installs the Python peers): prints time per
//! `sym9` fit on 300 and 3000 points against SciPy `least_squares` (LM) on the same points in the same
//! run, and replay throughput against pymavlink parsing the same tlog. Figures, not assertions.
//! `IMUCALD_BENCH_ONLY=fit` or `=replay` runs one of the two.

#[path = "../tests/common/python.rs"]
mod python;

use imucald::calib::fit::{fit_norm, NormFitOptions};
use imucald::calib::model::ModelKind;
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use std::process::Command;
use std::time::Instant;

fn points(n: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, 0.15).unwrap();
    let m = Matrix3::new(1.04, 0.02, -0.01, 0.02, 0.97, 0.03, -0.01, 0.03, 1.0);
    let minv = m.try_inverse().unwrap();
    let o = Vector3::new(12.0, -25.0, 40.0);
    (0..n)
        .map(|_| {
            let u = loop {
                let v = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                if v.norm() > 0.1 && v.norm() < 1.0 {
                    break v.normalize();
                }
            };
            let r = minv * (u * 48.0)
                + o
                + Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                );
            [r[0], r[1], r[2]]
        })
        .collect()
}

fn python() -> Option<String> {
    let p = python::python_importing("scipy, pymavlink");
    if p.is_none() {
        println!(
            "peer: no Python with scipy+pymavlink at {}; run scripts/bench to install it. Reporting imucald alone.",
            python::python_path()
        );
    }
    p
}

fn bench_fit(py: Option<&str>) {
    println!("== sym9 fit (ellipsoid, noise 0.15 uT, radius 48 uT)");
    println!(
        "{:>6} {:>14} {:>14} {:>8} {:>22}",
        "points", "imucald us/fit", "scipy us/fit", "ratio", "max |offset diff| uT"
    );
    // IMUCALD_BENCH_POINTS=N times one size only (for profiling).
    let sizes: Vec<usize> = match std::env::var("IMUCALD_BENCH_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        Some(n) => vec![n],
        None => vec![300, 3000],
    };
    for &n in &sizes {
        let pts = points(n, n as u64);
        let opts = NormFitOptions::default();
        let first = fit_norm(&pts, ModelKind::Sym9, &opts).expect("fit");
        // Best of 100 batches on each side (the figure least disturbed by whatever else the
        // machine is doing, as Python's timeit recommends), in three rounds that alternate
        // imucald and the peer, so a slow spell of the machine cannot favour one side.
        let reps = if n <= 300 { 100 } else { 15 };
        let time_ours = || {
            (0..100)
                .map(|_| {
                    let t0 = Instant::now();
                    for _ in 0..reps {
                        std::hint::black_box(
                            fit_norm(std::hint::black_box(&pts), ModelKind::Sym9, &opts)
                                .expect("fit"),
                        );
                    }
                    t0.elapsed().as_secs_f64() / reps as f64
                })
                .fold(f64::INFINITY, f64::min)
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let f = dir.path().join("points.csv");
        let text: String = pts
            .iter()
            .map(|p| format!("{:.17e},{:.17e},{:.17e}\n", p[0], p[1], p[2]))
            .collect();
        std::fs::write(&f, text).expect("write");
        // (seconds per fit, offset) from the peer.
        let time_peer = |py: &str| -> (f64, Vec<f64>) {
            let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/peer_fit.py");
            let out = Command::new(py)
                .args([
                    script,
                    f.to_str().unwrap(),
                    if n <= 300 { "3" } else { "1" },
                    "100",
                ])
                .output()
                .expect("python");
            let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|_| {
                panic!("peer failed: {}", String::from_utf8_lossy(&out.stderr))
            });
            let off = v["offset"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            (v["seconds_per_fit"].as_f64().unwrap(), off)
        };
        let (mut ours, mut peer, mut diff) = (f64::INFINITY, None::<f64>, None::<f64>);
        for _ in 0..3 {
            ours = ours.min(time_ours());
            if let Some(py) = py {
                let (t, off) = time_peer(py);
                peer = Some(peer.map_or(t, |p| p.min(t)));
                diff = Some(
                    (0..3)
                        .map(|k| (off[k] - first.calibration.offset[k]).abs())
                        .fold(0.0, f64::max),
                );
            }
        }
        println!(
            "{:>6} {:>14.1} {:>14} {:>8} {:>22}",
            n,
            ours * 1e6,
            peer.map(|p| format!("{:.1}", p * 1e6))
                .unwrap_or("-".into()),
            peer.map(|p| format!("{:.0}x", p / ours))
                .unwrap_or("-".into()),
            diff.map(|d| format!("{d:.2e}")).unwrap_or("-".into())
        );
    }
}

fn bench_replay(py: Option<&str>) {
    println!("== replay throughput (decode + full pipeline) on a simulated tumble tlog");
    let dir = tempfile::tempdir().expect("tempdir");
    let log = dir.path().join("tumble.tlog");
    let sc = imucald::sim::Scenario::named("tumble").expect("scenario");
    let sim = imucald::sim::simulate(&sc, 7);
    // Repeat the tumble so the run is long enough to time.
    let mut samples = Vec::new();
    let dur = sim.samples.last().map(|s| s.t_s).unwrap_or(0.0) + 0.01;
    for k in 0..5 {
        samples.extend(sim.samples.iter().map(|s| imucald::types::Sample {
            t_s: s.t_s + k as f64 * dur,
            ..*s
        }));
    }
    imucald::io::samplelog::write_tlog(
        &log,
        &samples,
        &imucald::io::samplelog::TlogWriteOptions::default(),
    )
    .expect("write tlog");
    let cfg = imucald::config::Config::default();
    let opts = imucald::app::replay::ReplayOptions::default();
    let mut best = f64::INFINITY;
    let mut n = 0;
    for _ in 0..5 {
        let t0 = Instant::now();
        let out = imucald::app::replay::replay(&log, &cfg, &opts, &mut |_, _| {}).expect("replay");
        best = best.min(t0.elapsed().as_secs_f64());
        n = out.report.input.samples;
    }
    let ours = n as f64 / best;
    let size = std::fs::metadata(&log).map(|m| m.len()).unwrap_or(0);
    print!(
        "{n} IMU samples ({:.1} MB): imucald {:.0} samples/s",
        size as f64 / 1e6,
        ours
    );
    if let Some(py) = py {
        let code = "import sys,time,os\nos.environ['MAVLINK20']='1'\nfrom pymavlink import mavutil\nt=time.perf_counter()\nm=mavutil.mavlink_connection(sys.argv[1],dialect='ardupilotmega')\nn=0\nwhile True:\n  x=m.recv_msg()\n  if x is None: break\n  if x.get_type() in ('HIGHRES_IMU','SCALED_IMU'): n+=1\nprint(n, time.perf_counter()-t)";
        let out = Command::new(py)
            .args(["-c", code, log.to_str().unwrap()])
            .env("MAVLINK20", "1")
            .output()
            .expect("python");
        let s = String::from_utf8_lossy(&out.stdout);
        let parts: Vec<f64> = s
            .split_whitespace()
            .filter_map(|x| x.parse().ok())
            .collect();
        if parts.len() == 2 {
            let peer = parts[0] / parts[1];
            println!(
                ", pymavlink parse only {:.0} samples/s ({} samples) -> ratio {:.0}x",
                peer,
                parts[0],
                ours / peer
            );
        } else {
            println!(
                ", pymavlink failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
    } else {
        println!();
    }
}

fn main() {
    // `cargo bench` passes --bench; `cargo test --benches` passes nothing and expects a quick exit.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    // IMUCALD_BENCH_ONLY=fit|replay runs one part (for profiling).
    let only = std::env::var("IMUCALD_BENCH_ONLY").unwrap_or_default();
    let py = python();
    if only.is_empty() || only == "fit" {
        bench_fit(py.as_deref());
    }
    if only.is_empty() || only == "replay" {
        bench_replay(py.as_deref());
    }
}
