//! `cargo bench --bench real_quality`: every compass of the real logs (`../shared/data/real`)
//! and the flight-controller logs with motion (`../shared/data/flightlogs`) fitted on alternate
//! 20 s blocks and scored on the others, by the vehicle's own calibration, three peers and
//! imucald (with the rung of its model ladder taken), side by side. Prints a Markdown table;
//! figures, not assertions. The third peer is a bounded least-squares fit of our own
//! ([`bounded_peer`]: MAGFit's parameters and bounds, against the earth field of the place).
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

const LOGS: [&str; 15] = [
    "real/apm_copter_2013_a.tlog",
    "real/apm_copter_2013_b.tlog",
    "real/apm_copter_2013_c.tlog",
    "real/copter_2017_two_compasses.bin",
    "real/ardusub_rov_gps.tlog",
    "real/ardusub_rov_two_mags.bin",
    "real/ardusub_rov_bad_crc.tlog",
    "real/px4_fmuv5_indoor_a.ulg",
    "real/px4_fmuv5_indoor_b.ulg",
    "real/px4_v6c_battery_brownout.ulg",
    "real/px4_tropic_ekf_failure.ulg",
    "real/px4_cuav_gps_interference.ulg",
    "flightlogs/px4_auav_x21.ulg",
    "flightlogs/px4_cubeorange_two_mags.ulg",
    "flightlogs/ardupilot_plane_pixracer.bin",
];

/// One row of a quality file: (t, fitting block, raw body field uT, body -> NED).
type Row = (bool, Vector3<f64>, UnitQuaternion<f64>);

/// A quality file: its instance, rows, the earth field (NED, uT) when the file gives it, and
/// the field through the vehicle's own calibration per row, when the log has one.
struct Points {
    instance: String,
    rows: Vec<Row>,
    field_ned_ut: Option<Vector3<f64>>,
    onboard: Vec<Option<Vector3<f64>>>,
}

fn read_points(p: &Path) -> Points {
    let text = std::fs::read_to_string(p).expect("quality file");
    let instance = text
        .lines()
        .find_map(|l| l.strip_prefix("# instance "))
        .unwrap_or("?")
        .to_string();
    let field_ned_ut = text
        .lines()
        .find_map(|l| l.strip_prefix("# place "))
        .and_then(|l| l.split("earth field NED ").nth(1))
        .and_then(|f| {
            let v: Vec<f64> = f
                .trim_end_matches(" uT")
                .split_whitespace()
                .filter_map(|x| x.parse().ok())
                .collect();
            (v.len() == 3).then(|| Vector3::new(v[0], v[1], v[2]))
        });
    let mut rows = Vec::new();
    let mut onboard = Vec::new();
    for l in text.lines().filter(|l| !l.starts_with('#')).skip(1) {
        let c: Vec<f64> = l
            .split(',')
            .map(|x| x.parse().unwrap_or(f64::NAN))
            .collect();
        let q = nalgebra::Quaternion::new(c[5], c[6], c[7], c[8]);
        rows.push((
            c[1] == 1.0,
            Vector3::new(c[2], c[3], c[4]),
            UnitQuaternion::from_quaternion(q),
        ));
        onboard.push(
            (c.len() >= 12 && c[9..12].iter().all(|v| v.is_finite()))
                .then(|| Vector3::new(c[9], c[10], c[11])),
        );
    }
    Points {
        instance,
        rows,
        field_ned_ut,
        onboard,
    }
}

/// The bounds of the bounded peer, MAGFit's: diagonal 0.8..1.2, off-diagonal -0.2..0.2, scale
/// 0.8..1.2, offsets within ArduPilot's COMPASS_OFFS_MAX (1800 mGauss, 180 uT).
const PEER_LOW: [f64; 10] = [-180.0, -180.0, -180.0, 0.8, 0.8, 0.8, -0.2, -0.2, -0.2, 0.8];
const PEER_HIGH: [f64; 10] = [180.0, 180.0, 180.0, 1.2, 1.2, 1.2, 0.2, 0.2, 0.2, 1.2];

/// The bounded peer's calibration of its parameters (o x y z, DIA x y z, ODI xy xz yz, scale):
/// calibrated = scale S (raw - o), S symmetric.
fn peer_calibration(x: &[f64; 10]) -> (Matrix3<f64>, Vector3<f64>) {
    let s = Matrix3::new(x[3], x[6], x[7], x[6], x[4], x[8], x[7], x[8], x[5]);
    (s * x[9], Vector3::new(x[0], x[1], x[2]))
}

/// A bounded least-squares fit of our own, as MAGFit fits: offsets, diagonal, off-diagonal and
/// scale of `scale S (raw - o) = R^T B` over the fitting rows, the earth field `B` of the place,
/// each parameter kept within [`PEER_LOW`]..[`PEER_HIGH`] (projected Levenberg-Marquardt with a
/// forward-difference Jacobian), started from the vehicle's own calibration (fitted exactly from
/// the rows' raw and onboard fields) where the log has one.
fn bounded_peer(p: &Points) -> Result<(Matrix3<f64>, Vector3<f64>), String> {
    let b = p.field_ned_ut.ok_or("no place: no earth field")?;
    let fit: Vec<(Vector3<f64>, Vector3<f64>)> = p
        .rows
        .iter()
        .filter(|r| r.0)
        .map(|(_, raw, q)| (*raw, q.inverse_transform_vector(&b)))
        .collect();
    if fit.len() < 50 {
        return Err(format!("{} fitting readings, need 50", fit.len()));
    }
    let mut x = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    // The vehicle's own: onboard = A raw + c, solved from the rows by least squares.
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = p
        .rows
        .iter()
        .zip(&p.onboard)
        .filter_map(|(r, o)| Some((r.1, (*o)?)))
        .collect();
    if pairs.len() >= 12 {
        let n = pairs.len();
        let mut a = nalgebra::DMatrix::<f64>::zeros(n, 4);
        let mut y = nalgebra::DMatrix::<f64>::zeros(n, 3);
        for (i, (raw, on)) in pairs.iter().enumerate() {
            a.row_mut(i).copy_from_slice(&[raw.x, raw.y, raw.z, 1.0]);
            y.row_mut(i).copy_from_slice(&[on.x, on.y, on.z]);
        }
        if let Ok(sol) = a.clone().svd(true, true).solve(&y, 1e-12) {
            let m = Matrix3::from_fn(|i, j| sol[(j, i)]);
            let c = Vector3::new(sol[(3, 0)], sol[(3, 1)], sol[(3, 2)]);
            if let Some(inv) = m.try_inverse() {
                let o = -(inv * c);
                let sym = (m + m.transpose()) / 2.0;
                x = [
                    o.x,
                    o.y,
                    o.z,
                    sym[(0, 0)],
                    sym[(1, 1)],
                    sym[(2, 2)],
                    sym[(0, 1)],
                    sym[(0, 2)],
                    sym[(1, 2)],
                    1.0,
                ];
            }
        }
    }
    let clamp = |x: &mut [f64; 10]| {
        for i in 0..10 {
            x[i] = x[i].clamp(PEER_LOW[i], PEER_HIGH[i]);
        }
    };
    clamp(&mut x);
    let residuals = |x: &[f64; 10]| -> nalgebra::DVector<f64> {
        let (m, o) = peer_calibration(x);
        let mut r = nalgebra::DVector::zeros(3 * fit.len());
        for (i, (raw, h)) in fit.iter().enumerate() {
            let e = m * (raw - o) - h;
            r[3 * i] = e.x;
            r[3 * i + 1] = e.y;
            r[3 * i + 2] = e.z;
        }
        r
    };
    let mut r = residuals(&x);
    let mut cost = r.norm_squared();
    let mut lambda = 1e-3;
    for _ in 0..100 {
        let mut j = nalgebra::DMatrix::<f64>::zeros(r.len(), 10);
        for k in 0..10 {
            let mut xk = x;
            let h = 1e-6 * x[k].abs().max(1e-3);
            xk[k] += h;
            j.set_column(k, &((residuals(&xk) - &r) / h));
        }
        let jt = j.transpose();
        let g = &jt * &r;
        let mut n = &jt * &j;
        let mut improved = false;
        for _ in 0..10 {
            let mut a = n.clone();
            for k in 0..10 {
                a[(k, k)] += lambda * n[(k, k)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let mut xn = x;
            for k in 0..10 {
                xn[k] += step[k];
            }
            clamp(&mut xn);
            let rn = residuals(&xn);
            let cn = rn.norm_squared();
            if cn < cost {
                let done = (cost - cn) < 1e-10 * cost;
                x = xn;
                r = rn;
                cost = cn;
                lambda = (lambda / 10.0).max(1e-12);
                improved = !done;
                break;
            }
            lambda *= 10.0;
        }
        n.fill(0.0);
        if !improved {
            break;
        }
    }
    Ok(peer_calibration(&x))
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
    score_affine(
        rows,
        &Matrix3::from_fn(|i, j| m[i][j]),
        &Vector3::new(o[0], o[1], o[2]),
    )
}

/// A calibration `m (raw - o)` scored on the held-out rows.
fn score_affine(rows: &[Row], m: &Matrix3<f64>, o: &Vector3<f64>) -> Result<HeldOut, String> {
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
    println!("| log | compass | scored readings | vehicle's own | bounded fit (ours) | least squares, B fitted | MAGFit (magfit_WMM.py) | imucald | rung | imucald against the better of the vehicle's and the bounded fit | imucald against the best other |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
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
                println!("| {short} | - | - | - | - | - | - | - | - | - | replay failed: {e} |");
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
            println!("| {short} | - | - | - | - | - | - | - | - | - | {why} |");
            continue;
        }
        for q in &r.quality {
            let file = files.iter().find(|f| read_points(f).instance == q.instance);
            let (points, peers) = match file {
                Some(f) => {
                    let points = read_points(f);
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
                    (Some(points), json)
                }
                None => (None, serde_json::json!({})),
            };
            let rows = points.as_ref().map_or(&[][..], |p| &p.rows[..]);
            let lsq = score(rows, &peers["lsq"]);
            let magfit = score(rows, &peers["magfit_wmm"]);
            let bounded = points
                .as_ref()
                .ok_or_else(|| "no readings".to_string())
                .and_then(bounded_peer)
                .and_then(|(m, o)| score_affine(rows, &m, &o));
            // The measure of the acceptance: the better of the vehicle's own and the bounded fit.
            let pair: Vec<&HeldOut> = [q.onboard.as_ref(), bounded.as_ref().ok()]
                .into_iter()
                .flatten()
                .collect();
            let within = |h: &HeldOut| {
                let n = pair
                    .iter()
                    .map(|p| p.norm_spread_pct)
                    .fold(f64::INFINITY, f64::min);
                let d = pair
                    .iter()
                    .map(|p| p.dip_spread_deg)
                    .fold(f64::INFINITY, f64::min);
                format!(
                    "{:.2}x / {:.2}x",
                    h.norm_spread_pct / n,
                    h.dip_spread_deg / d
                )
            };
            let against_pair = match (&q.imucald, pair.is_empty()) {
                (Some(h), false) => within(h),
                (Some(_), true) => "nothing to compare".into(),
                (None, _) if bounded.is_err() => "failed, as the bounded fit".into(),
                (None, _) => "failed".into(),
            };
            let others: Vec<&HeldOut> = [
                q.onboard.as_ref(),
                lsq.as_ref().ok(),
                magfit.as_ref().ok(),
                bounded.as_ref().ok(),
            ]
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
            let bounded_cell = peer_cell(&bounded, "bounded fit");
            let scored = q
                .imucald
                .or(q.onboard)
                .map_or("-".to_string(), |h| h.readings.to_string());
            let rung = q.rung.map_or("-".to_string(), |r| r.to_string());
            println!(
                "| {short} | {} | {scored} | {} | {bounded_cell} | {lsq_cell} | {magfit_cell} | {} | {rung} | {against_pair} | {against} |",
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
