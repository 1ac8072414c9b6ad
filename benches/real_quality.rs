//! `cargo bench --bench real_quality`: every compass of the real logs (`../shared/data/real`)
//! and the flight-controller logs with motion (`../shared/data/flightlogs`) fitted on alternate
//! 20 s blocks and scored on the others, by the vehicle's own calibration, two peers and imucald,
//! side by side. Prints a Markdown table; figures, not assertions.
//!
//! imucald's and the vehicle's scores are the report's `quality` block. The peers
//! (`benches/peer_magfit.py`) fit the same readings of the same blocks, written by
//! `replay --quality-points`: SciPy least squares of M (raw - o) = R^T B with M symmetric and the
//! field's direction fitted, and ArduPilot's MAGFit (pymavlink's `magfit_WMM.py --elliptical`,
//! where the log has a place). Every score is the same function (`magmethod::held_out`): the
//! spread of the field's norm (%) and of its dip (deg) over the scored blocks.
//! Python: `$IMUCALD_PYTHON` or `.venv/bin/python` with SciPy and pymavlink (`scripts/bench`).
//! Needs `[[bench]] name = "real_quality" harness = false` in Cargo.toml.

#![allow(dead_code)]

#[path = "../tests/common/python.rs"]
mod python;

use imucald::app::replay::{replay, ReplayOptions};
use imucald::config::Config;
use imucald::report::HeldOut;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use std::path::{Path, PathBuf};
use std::process::Command;

const LOGS: [&str; 8] = [
    "real/apm_copter_2013_a.tlog",
    "real/apm_copter_2013_b.tlog",
    "real/apm_copter_2013_c.tlog",
    "real/px4_fmuv5_indoor_a.ulg",
    "real/px4_fmuv5_indoor_b.ulg",
    "flightlogs/px4_auav_x21.ulg",
    "flightlogs/px4_cubeorange_two_mags.ulg",
    "flightlogs/ardupilot_plane_pixracer.bin",
];

/// One row of a quality file: (t, fitting block, raw body field uT, body -> NED).
type Row = (bool, Vector3<f64>, UnitQuaternion<f64>);

fn read_points(p: &Path) -> (String, Vec<Row>) {
    let text = std::fs::read_to_string(p).expect("quality file");
    let instance = text
        .lines()
        .find_map(|l| l.strip_prefix("# instance "))
        .unwrap_or("?")
        .to_string();
    let rows = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .skip(1)
        .map(|l| {
            let c: Vec<f64> = l
                .split(',')
                .take(9)
                .map(|x| x.parse().unwrap_or(f64::NAN))
                .collect();
            let q = nalgebra::Quaternion::new(c[5], c[6], c[7], c[8]);
            (
                c[1] == 1.0,
                Vector3::new(c[2], c[3], c[4]),
                UnitQuaternion::from_quaternion(q),
            )
        })
        .collect();
    (instance, rows)
}

/// A peer's calibration scored on the held-out rows.
fn score(rows: &[Row], fit: &serde_json::Value) -> Result<HeldOut, String> {
    if let Some(why) = fit.get("skipped").and_then(|v| v.as_str()) {
        return Err(why.to_string());
    }
    let o: Vec<f64> =
        serde_json::from_value(fit["offset_ut"].clone()).map_err(|e| e.to_string())?;
    let m: Vec<Vec<f64>> =
        serde_json::from_value(fit["matrix"].clone()).map_err(|e| e.to_string())?;
    let m = Matrix3::from_fn(|i, j| m[i][j]);
    let o = Vector3::new(o[0], o[1], o[2]);
    let held: Vec<([f64; 3], UnitQuaternion<f64>)> = rows
        .iter()
        .filter(|r| !r.0)
        .map(|(_, raw, q)| {
            let c = m * (raw - o);
            ([c.x, c.y, c.z], *q)
        })
        .collect();
    imucald::calib::magmethod::held_out(&held).ok_or_else(|| "too few scored readings".into())
}

fn cell(h: Option<&HeldOut>) -> String {
    h.map_or("-".into(), |h| {
        format!(
            "{:.2} % / {:.2} / {:.2} deg",
            h.norm_spread_pct, h.dip_spread_deg, h.heading_spread_deg
        )
    })
}

fn main() {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if !data.is_dir() {
        println!("SKIPPED: {} is absent", data.display());
        return;
    }
    let py = python::python_path();
    let peer = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peer_magfit.py");
    println!("held out: spread of the field's norm / of its dip / of its heading against the vehicle's yaw, on the odd 20 s blocks of a fit on the even ones (the ratio: norm and dip)\n");
    println!("| log | compass | scored readings | vehicle's own | least squares, B fitted | MAGFit (magfit_WMM.py) | imucald | imucald against the best other |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    let mut notes = Vec::new();
    for name in LOGS {
        let path = data.join(name);
        let short = Path::new(name)
            .file_name()
            .unwrap()
            .to_string_lossy()
            .to_string();
        let tmp = tempfile::tempdir().expect("temp dir");
        let opts = ReplayOptions {
            quality_points: Some(tmp.path().to_path_buf()),
            ..Default::default()
        };
        let out = match replay(&path, &Config::default(), &opts, &mut |_, _| {}) {
            Ok(o) => o,
            Err(e) => {
                println!("| {short} | - | - | - | - | - | - | replay failed: {e} |");
                continue;
            }
        };
        let r = &out.report;
        let mut files: Vec<PathBuf> = out
            .written
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == "csv"))
            .cloned()
            .collect();
        files.sort();
        if r.quality.is_empty() {
            let why = format!(
                "no held-out check: {:.1} s of log{}",
                r.input.duration_s,
                if r.input.duration_s < 40.0 {
                    " (one fitting and one scored 20 s block need 40 s)"
                } else {
                    ""
                }
            );
            println!("| {short} | - | - | - | - | - | - | {why} |");
            continue;
        }
        for q in &r.quality {
            let file = files.iter().find(|f| read_points(f).0 == q.instance);
            let (rows, peers) = match file {
                Some(f) => {
                    let rows = read_points(f).1;
                    let o = Command::new(&py)
                        .arg(&peer)
                        .arg(f)
                        .output()
                        .expect("python");
                    let json: serde_json::Value = serde_json::from_slice(&o.stdout)
                        .unwrap_or_else(|_| serde_json::json!({
                            "lsq": {"skipped": String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("peer failed").to_string()},
                            "magfit_wmm": {"skipped": "peer failed"}
                        }));
                    (rows, json)
                }
                None => (vec![], serde_json::json!({})),
            };
            let lsq = score(&rows, &peers["lsq"]);
            let magfit = score(&rows, &peers["magfit_wmm"]);
            let others: Vec<&HeldOut> =
                [q.onboard.as_ref(), lsq.as_ref().ok(), magfit.as_ref().ok()]
                    .into_iter()
                    .flatten()
                    .collect();
            let best_norm = others
                .iter()
                .map(|h| h.norm_spread_pct)
                .fold(f64::INFINITY, f64::min);
            let best_dip = others
                .iter()
                .map(|h| h.dip_spread_deg)
                .fold(f64::INFINITY, f64::min);
            let against = match (&q.imucald, others.is_empty()) {
                (Some(h), false) => format!(
                    "{:.2}x / {:.2}x",
                    h.norm_spread_pct / best_norm,
                    h.dip_spread_deg / best_dip
                ),
                (Some(_), true) => "nothing to compare".into(),
                (None, _) => format!("failed: {}", q.imucald_failure.as_deref().unwrap_or("?")),
            };
            let mut peer_cell = |s: &Result<HeldOut, String>, tag: &str| match s {
                Ok(h) => cell(Some(h)),
                Err(e) => {
                    notes.push(format!("{short} {} {tag}: {e}", q.instance));
                    "-".into()
                }
            };
            let lsq_cell = peer_cell(&lsq, "least squares");
            let magfit_cell = peer_cell(&magfit, "MAGFit");
            let scored = q
                .imucald
                .or(q.onboard)
                .map_or("-".to_string(), |h| h.readings.to_string());
            println!(
                "| {short} | {} | {scored} | {} | {lsq_cell} | {magfit_cell} | {} | {against} |",
                q.instance,
                cell(q.onboard.as_ref()),
                cell(q.imucald.as_ref()),
            );
        }
    }
    if !notes.is_empty() {
        println!("\npeers that gave no fit:");
        for n in notes {
            println!("- {n}");
        }
    }
}
