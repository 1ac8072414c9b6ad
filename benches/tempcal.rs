//! Temperature calibration on simulated warm-ups (`sim::warmup`, 15 to 40 C, three IMU instances,
//! 20 seeds) against numpy's `polyfit` (degree 3, as ArduPilot's and PX4's log tools fit) on the
//! same binned points, through `benches/peer_tempcal.py` with `$IMUCALD_PYTHON` or
//! `.venv/bin/python`.
//!
//! Per sensor: the largest error of the fitted bias over the calibrated range (the accelerometer's
//! relative to its value at 35 C, as ArduPilot's has no constant; the gyro's whole), against the
//! noise of a bin's mean (its standard error); and the held-out shrink (the bias variation about
//! a constant over that about the cubic, on alternate 1 C bands), both fits scored the same way.
//!
//! `cargo bench --bench tempcal`. Needs `[[bench]] name = "tempcal" harness = false`.

#[path = "../tests/common/python.rs"]
mod python;

use imucald::calib::tempcal::poly::Cubic;
use imucald::calib::tempcal::{binned_points, calibrate, TempCalSettings, TempOutcome};
use imucald::sim::warmup::{simulate, WarmupSettings};
use std::fmt::Write as _;

const SEEDS: u64 = 20;

/// One (seed, instance)'s fitted curves: six channels' c0..c3 in (T - 35 C), the range, and the
/// held-out before/after per channel.
struct Fitted {
    c: [[f64; 4]; 6],
    range: [f64; 2],
    held: [[f64; 2]; 6],
}

fn largest_error(f: &Fitted, truth: &imucald::sim::warmup::InstanceTruth, ch: usize) -> f64 {
    let cubic = Cubic {
        ref_c: 35.0,
        c: f.c[ch],
    };
    let (gyro, a) = (ch >= 3, ch % 3);
    (0..=100)
        .map(|k| {
            let t = f.range[0] + (f.range[1] - f.range[0]) * k as f64 / 100.0;
            if gyro {
                (cubic.eval(t) - truth.bias(true, a, t)).abs()
            } else {
                let fit = cubic.eval(t) - cubic.eval(35.0);
                (fit - (truth.bias(false, a, t) - truth.bias(false, a, 35.0))).abs()
            }
        })
        .fold(0.0, f64::max)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn quantiles(v: &[f64]) -> String {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    format!(
        "median {:.2e}, 90% {:.2e}, max {:.2e}",
        s[s.len() / 2],
        s[(s.len() * 9) / 10],
        s[s.len() - 1]
    )
}

fn main() {
    let set = TempCalSettings::default();
    let mut csv = String::from("seed,instance,channel,temp_c,value,se\n");
    let mut ours = vec![];
    let mut truths = vec![];
    let mut se_all: [Vec<f64>; 2] = [vec![], vec![]];
    let started = std::time::Instant::now();
    for seed in 0..SEEDS {
        let w = simulate(&WarmupSettings::default(), seed);
        for (k, samples) in w.instances.iter().enumerate() {
            let r = calibrate(samples, &set);
            let TempOutcome::Calibrated(c) = &r.outcome else {
                panic!("seed {seed} instance {k}: {:?}", r.outcome);
            };
            let axes: Vec<_> = c.accel.axes.iter().chain(&c.gyro.axes).collect();
            ours.push(Fitted {
                c: std::array::from_fn(|ch| axes[ch].ardupilot),
                range: [c.tmin_c, c.tmax_c],
                held: std::array::from_fn(|ch| {
                    axes[ch]
                        .held_out
                        .map_or([f64::NAN; 2], |h| [h.before, h.after])
                }),
            });
            for (ch, a) in axes.iter().enumerate() {
                se_all[ch / 3].push(a.point_se);
            }
            for p in binned_points(samples, &set) {
                for (ch, q) in p.iter().enumerate() {
                    let _ = writeln!(csv, "{seed},{k},{ch},{},{},{}", q.temp_c, q.value, q.se);
                }
            }
            truths.push(w.truth[k].clone());
        }
    }
    let ours_s = started.elapsed().as_secs_f64();
    let peer = run_peer(&csv, &ours);
    println!(
        "temperature calibration: {SEEDS} simulated warm-ups x 3 IMU instances (15-40 C, 1500 s at 50 Hz), simulated and fitted in {ours_s:.1} s"
    );
    for (sensor, unit, chs) in [("accel", "m/s^2", 0..3), ("gyro", "rad/s", 3..6)] {
        let s = if sensor == "accel" { 0 } else { 1 };
        let err = |fits: &[Fitted]| -> Vec<f64> {
            fits.iter()
                .zip(&truths)
                .flat_map(|(f, t)| chs.clone().map(move |ch| largest_error(f, t, ch)))
                .collect()
        };
        let shrink = |fits: &[Fitted]| -> Vec<f64> {
            fits.iter()
                .flat_map(|f| chs.clone().map(move |ch| f.held[ch][0] / f.held[ch][1]))
                .collect()
        };
        let se = median(se_all[s].clone());
        println!("{sensor} ({unit}): a bin's standard error, median {se:.2e}");
        let (e_ours, sh_ours) = (err(&ours), shrink(&ours));
        println!(
            "  imucald  largest bias error over the range: {} ({:.1}x the bin error at the median)",
            quantiles(&e_ours),
            median(e_ours.clone()) / se
        );
        println!(
            "           held-out shrink: median {:.1}x, min {:.1}x, axes under 5x: {} of {}",
            median(sh_ours.clone()),
            sh_ours.iter().cloned().fold(f64::INFINITY, f64::min),
            sh_ours.iter().filter(|x| **x < 5.0).count(),
            sh_ours.len()
        );
        if let Some(peer) = &peer {
            let (e_peer, sh_peer) = (err(peer), shrink(peer));
            println!("  numpy    largest bias error over the range: {} ({:.1}x the bin error at the median)", quantiles(&e_peer), median(e_peer.clone()) / se);
            println!(
                "           held-out shrink: median {:.1}x, min {:.1}x, axes under 5x: {} of {}",
                median(sh_peer.clone()),
                sh_peer.iter().cloned().fold(f64::INFINITY, f64::min),
                sh_peer.iter().filter(|x| **x < 5.0).count(),
                sh_peer.len()
            );
            let better = e_ours.iter().zip(&e_peer).filter(|(a, b)| a <= b).count();
            println!(
                "  imucald's error at most numpy's on {better} of {} axes",
                e_ours.len()
            );
        }
    }
}

/// numpy's fits of the same points, in the same order as `ours` (`None` without the peer).
fn run_peer(csv: &str, ours: &[Fitted]) -> Option<Vec<Fitted>> {
    let Some(py) = python::python_importing("numpy") else {
        println!("numpy peer: SKIPPED (no Python with numpy: set IMUCALD_PYTHON)");
        return None;
    };
    let dir = std::env::temp_dir().join(format!("imucald-tempcal-{}", std::process::id()));
    std::fs::create_dir_all(&dir).ok()?;
    let points = dir.join("points.csv");
    std::fs::write(&points, csv).ok()?;
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/peer_tempcal.py");
    let out = std::process::Command::new(py)
        .arg(script)
        .arg(&points)
        .output()
        .ok()?;
    let _ = std::fs::remove_dir_all(&dir);
    if !out.status.success() {
        println!(
            "numpy peer failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        return None;
    }
    let mut fits: Vec<Fitted> = ours
        .iter()
        .map(|f| Fitted {
            c: [[f64::NAN; 4]; 6],
            range: f.range,
            held: [[f64::NAN; 2]; 6],
        })
        .collect();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let v: serde_json::Value = serde_json::from_str(line).ok()?;
        let i = v["seed"].as_u64()? as usize * 3 + v["instance"].as_u64()? as usize;
        let ch = v["channel"].as_u64()? as usize;
        let c: Vec<f64> = v["c"]
            .as_array()?
            .iter()
            .filter_map(|x| x.as_f64())
            .collect();
        fits[i].c[ch] = [c[0], c[1], c[2], c[3]];
        fits[i].held[ch] = [v["before"].as_f64()?, v["after"].as_f64()?];
    }
    Some(fits)
}
