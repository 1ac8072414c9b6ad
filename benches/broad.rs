//! `cargo bench --bench broad` (or `scripts/bench`, which also installs the Python peer): imucald's
//! orientation filter against VQF (PyPI `vqf`, default parameters, 9D) on the BROAD trials in
//! `../shared/data/broad`, both evaluated by `imucald::eval` (BROAD's total / heading / inclination
//! RMSE over the movement phase). Prints a per-trial table and the means; figures, not assertions.
//! VQF runs through `scripts/vqf_peer.py` with `$IMUCALD_PYTHON` or `.venv/bin/python`.
//! Needs `[[bench]] name = "broad" harness = false` in Cargo.toml (without it cargo builds this file
//! under the test harness, which never calls `main`: hence the allow below).

#![allow(dead_code)]

use imucald::config::Config;
use imucald::eval::{evaluate, EvalResult};
use imucald::fusion::{run, FusionConfig, WorldFrame};
use imucald::sources::read_log;
use nalgebra::{Quaternion, UnitQuaternion};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

fn python() -> Option<String> {
    let p = std::env::var("IMUCALD_PYTHON")
        .unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/.venv/bin/python").to_string());
    let ok = Command::new(&p)
        .args(["-c", "import vqf"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        Some(p)
    } else {
        println!(
            "peer: no Python with the `vqf` package at {p} (scripts/bench installs it); reporting imucald alone."
        );
        None
    }
}

fn read_quats(path: &Path) -> Result<Vec<UnitQuaternion<f64>>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    text.lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|e| format!("{}: {e}", path.display()))?;
            if v.len() != 4 {
                return Err(format!("{}: expected qw,qx,qy,qz", path.display()));
            }
            Ok(UnitQuaternion::from_quaternion(Quaternion::new(
                v[0], v[1], v[2], v[3],
            )))
        })
        .collect()
}

fn run_vqf(py: &str, trial: &Path, out_dir: &Path) -> Result<Vec<UnitQuaternion<f64>>, String> {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/vqf_peer.py");
    let out = out_dir.join("vqf.csv");
    let o = Command::new(py)
        .arg(script)
        .arg(trial)
        .arg(&out)
        .output()
        .map_err(|e| format!("cannot run {py}: {e}"))?;
    if !o.status.success() {
        return Err(format!(
            "vqf_peer.py failed: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        ));
    }
    read_quats(&out)
}

fn fmt(e: &EvalResult) -> String {
    format!(
        "{:6.2} {:6.2} {:6.2}",
        e.total_rmse_deg, e.heading_rmse_deg, e.inclination_rmse_deg
    )
}

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let dir = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/broad"));
    if !dir.is_dir() {
        println!(
            "broad: {} is absent; nothing to benchmark (the BROAD trials live in shared/data).",
            dir.display()
        );
        return;
    }
    let mut trials: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.to_string_lossy().ends_with(".csv.gz"))
                .collect()
        })
        .unwrap_or_default();
    trials.sort();
    if trials.is_empty() {
        println!("broad: no .csv.gz trial in {}", dir.display());
        return;
    }
    let py = python();
    let tmp = tempfile::tempdir().expect("a temporary directory");
    let cfg = FusionConfig {
        world: WorldFrame::Enu,
        ..FusionConfig::default()
    };
    println!(
        "== BROAD: total / heading / inclination RMSE (deg) over moving == 1, reference as published"
    );
    println!(
        "{:<44} {:>20}   {:>20}   {:>6} {:>9}",
        "trial", "imucald", "VQF 9D (defaults)", "ratio", "imucald"
    );
    let mut ours = Vec::new();
    let mut theirs = Vec::new();
    for t in &trials {
        let name = t
            .file_name()
            .map(|n| n.to_string_lossy().trim_end_matches(".csv.gz").to_string())
            .unwrap_or_default();
        let log = match read_log(t, None, &Config::default()) {
            Ok(l) => l,
            Err(e) => {
                println!("{name:<44} cannot read: {e}");
                continue;
            }
        };
        let start = Instant::now();
        let q: Vec<_> = run(&log.samples, &cfg).iter().map(|o| o.q).collect();
        let secs = start.elapsed().as_secs_f64();
        let e = evaluate(&log.samples, &q);
        let v = py.as_deref().map(|py| {
            run_vqf(py, t, tmp.path()).map(|vq| {
                if vq.len() != log.samples.len() {
                    eprintln!(
                        "broad: {name}: VQF gave {} quaternions for {} samples",
                        vq.len(),
                        log.samples.len()
                    );
                }
                evaluate(&log.samples, &vq)
            })
        });
        let rate = log.samples.len() as f64 / secs.max(1e-9) / 1e6;
        match v {
            Some(Ok(v)) => {
                println!(
                    "{name:<44} {}   {}   {:6.2} {:6.1} MS/s",
                    fmt(&e),
                    fmt(&v),
                    e.total_rmse_deg / v.total_rmse_deg,
                    rate
                );
                theirs.push(v);
            }
            Some(Err(err)) => println!("{name:<44} {}   VQF: {err}", fmt(&e)),
            None => println!(
                "{name:<44} {}   {:>20}   {:>6} {rate:6.1} MS/s",
                fmt(&e),
                "-",
                "-"
            ),
        }
        ours.push(e);
    }
    let mean = |v: &[EvalResult], f: fn(&EvalResult) -> f64| {
        v.iter().map(f).sum::<f64>() / v.len().max(1) as f64
    };
    let row = |v: &[EvalResult]| {
        format!(
            "{:6.2} {:6.2} {:6.2}",
            mean(v, |e| e.total_rmse_deg),
            mean(v, |e| e.heading_rmse_deg),
            mean(v, |e| e.inclination_rmse_deg)
        )
    };
    if theirs.len() == ours.len() && !ours.is_empty() {
        println!(
            "{:<44} {}   {}",
            format!("mean of {} trials", ours.len()),
            row(&ours),
            row(&theirs)
        );
        let m_ours = mean(&ours, |e| e.total_rmse_deg);
        let m_theirs = mean(&theirs, |e| e.total_rmse_deg);
        let worst = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| a.total_rmse_deg / b.total_rmse_deg)
            .fold(0.0, f64::max);
        println!(
            "mean total RMSE imucald {m_ours:.2} vs VQF {m_theirs:.2} deg ({}); worst trial ratio {worst:.2} (target <= 1.5: {})",
            if m_ours <= m_theirs { "imucald <= VQF" } else { "imucald > VQF" },
            if worst <= 1.5 { "met" } else { "NOT met" }
        );
    } else {
        println!(
            "{:<44} {}",
            format!("mean of {} trials", ours.len()),
            row(&ours)
        );
    }
}
