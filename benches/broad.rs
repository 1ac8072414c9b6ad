//! `cargo bench --bench broad` (or `scripts/bench`, which also installs the Python peer): imucald's
//! orientation filter against VQF (PyPI `vqf`, default parameters, 9D) on the BROAD trials in
//! `../shared/data/broad`, both evaluated by `imucald::attitude::eval` (BROAD's total / heading / inclination
//! RMSE over the movement phase). Prints a per-trial table, a per-class table, the means and ratios,
//! and the cost per sample of both filters (imucald's `OrientationFilter::update_sample` against
//! VQF's C++ batch update on the same data); figures, not assertions.
//!
//! imucald's filter sees each trial's magnetometer through the calibration `imucald replay` of
//! that trial picks ([`replay_pick`]: the library's `replay` with the default configuration, the
//! primary compass's calibration when its load decision is to load it), so the bench scores what
//! a user of replay gets; the table names it per trial (`none: <reason>` when the replay offers
//! none, and the filter then runs on the raw field). A vector calibration comes with the field it
//! was fitted against, whose declination (against the attitude's north) the filter takes
//! ([`MagPick::declination_deg`]). VQF gets the raw field, as the trials carry it.
//! A second table sets the heading error at rest (`moving == 0`) through that calibration beside
//! the one on the raw field: the calibration must not put a heading offset there ([`RestHeading`]).
//! VQF runs through `scripts/vqf_peer.py` with `$IMUCALD_PYTHON` or `.venv/bin/python`.
//!
//! `cargo bench --bench broad -- --tune` is the procedure that chose the filter's defaults (see
//! [`tune`]): a coordinate search over the settings in [`TUNED`] (within [`lower_bound`] and
//! [`upper_bound`]), from two fixed start points ([`start_point`], [`weak_mag_start`]) and then
//! from the better end moved to the [`low_pass`] settings, scored against VQF on the trials it may
//! see. It deals the trials into folds (`--folds K`, default 3; each class's trials in turn), runs
//! it once per fold on the other folds' trials and scores that run only on the fold it did not see
//! (the cross-validated figures), then once on all trials: that last result is what
//! `FusionConfig::default()` holds.
//! `--cv-only` stops after the cross-validated figures.
//!
//! `IMUCALD_BROAD_SWEEP="key=v1,v2;key2=v3" cargo bench --bench broad` scores one setting at a
//! time over all trials (see [`sweep`]).
//!
//! `cargo bench --bench broad -- --dump NAME OUT.csv` writes the per-sample errors (deg) of both
//! filters on the trial whose name contains NAME, with imucald's state (rest, disturbance, bias,
//! sensor -> ENU quaternion) and the signed heading errors of imucald, of imucald on the raw field
//! and of VQF, for a look at where they fail.
//!
//! Needs `[[bench]] name = "broad" harness = false` in Cargo.toml (without it cargo builds this file
//! under the test harness, which never calls `main`: hence the allow below).

#![allow(dead_code)]

#[path = "../tests/common/python.rs"]
mod python;
#[path = "../tests/common/untuned.rs"]
mod untuned;

use imucald::app::replay::{replay, ReplayOptions};
use imucald::attitude::eval::{errors, evaluate, reference, EvalResult};
use imucald::attitude::fusion::{
    median_dt, FusionConfig, HeadingConfig, OrientationFilter, TiltConfig, WorldFrame,
};
use imucald::calib::model::Calibration;
use imucald::calib::outcome::MagMethod;
use imucald::config::Config;
use imucald::io::sources::read_log;
use imucald::types::{Sample, Vec3};
use nalgebra::{Quaternion, UnitQuaternion};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// BROAD's motion classes, as the trial names spell them, and how the tables print them.
const CLASSES: [(&str, &str); 9] = [
    ("slow_rotation", "slow rotation"),
    ("fast_rotation", "fast rotation"),
    ("slow_translation", "slow translation"),
    ("fast_translation", "fast translation"),
    ("combined", "combined"),
    ("tapping", "tapping"),
    ("vibration", "vibration"),
    ("stationary_magnet", "stationary magnet"),
    ("attached_magnet", "attached magnet"),
];

fn class_of(name: &str) -> usize {
    CLASSES
        .iter()
        .position(|(k, _)| name.contains(k))
        .unwrap_or(CLASSES.len() - 1)
}

struct Trial {
    name: String,
    class: usize,
    /// The trial's samples, the magnetometer through [`Trial::cal`] (raw where it is none): what
    /// imucald's filter is scored on.
    samples: Vec<Sample>,
    /// The magnetometer as the trial carries it, one per sample: the raw field the calibration is
    /// compared with at rest.
    raw_mag_ut: Vec<Option<Vec3>>,
    /// The magnetometer calibration `imucald replay` of the trial picks.
    cal: MagPick,
    /// VQF's metrics and its batch-update time, s.
    vqf: Option<(EvalResult, f64)>,
    vqf_q: Vec<UnitQuaternion<f64>>,
}

/// The magnetometer calibration `imucald replay` of a trial picks for its (only, primary) compass.
struct MagPick {
    /// What the table says: the model and method (`full12 vector`), or `none: <reason>`.
    label: String,
    /// The calibration applied before the filter; `None` leaves the field raw.
    cal: Option<Calibration>,
    /// The declination of the earth field the calibration was fitted against (deg east of the
    /// attitude's north: the report's `earth_field`, a vector or planar calibration's), which the
    /// filter's heading takes; 0 otherwise (magnetic north, BROAD's reference north). A vector
    /// calibration maps a reading to `R^T B`, the fitted field `B` seen in the body: its
    /// horizontal part points at `B`'s declination, not at the attitude's north, so a filter
    /// that takes the calibrated field's azimuth for north (declination 0) is off by that
    /// declination everywhere, at rest included; the field and the calibration are one fit.
    declination_deg: f64,
}

/// What `imucald replay TRIAL` (no configuration file: `Config::default()`) picks for the primary
/// compass, through the library's own `replay`: its reported calibration when the report's load
/// decision for that compass is to load it (what the exports write as values), with the
/// declination of the field a vector or planar calibration was fitted against; else none, with
/// the decision's reason (`none: the fit failed (did_not_converge)`).
fn replay_pick(path: &Path) -> MagPick {
    let out = match replay(
        path,
        &Config::default(),
        &ReplayOptions::default(),
        &mut |_, _| {},
    ) {
        Ok(o) => o,
        Err(e) => {
            return MagPick {
                label: format!("none: replay failed: {e}"),
                cal: None,
                declination_deg: 0.0,
            }
        }
    };
    let r = &out.report;
    let primary_id = r
        .instances
        .iter()
        .find(|i| i.primary)
        .map_or(0, |i| i.compass_id);
    let mag = &r.calibration.mag;
    match r.load.iter().find(|d| d.compass_id == primary_id) {
        Some(d) if d.load => match mag.calibration() {
            Some(cal) => {
                let field = mag
                    .method
                    .as_ref()
                    .filter(|m| matches!(m.method, MagMethod::Vector | MagMethod::Planar))
                    .and_then(|m| m.earth_field.as_ref());
                MagPick {
                    label: format!(
                        "{}{}{}",
                        mag.model.name(),
                        mag.method
                            .as_ref()
                            .map_or(String::new(), |m| format!(" {}", m.method.name())),
                        field.map_or(String::new(), |f| format!(
                            ", field {} decl {:+.1} deg",
                            serde_json::to_value(f.model)
                                .ok()
                                .and_then(|v| v.as_str().map(str::to_string))
                                .unwrap_or_default(),
                            f.declination_deg
                        ))
                    ),
                    cal: Some(cal),
                    declination_deg: field.map_or(0.0, |f| f.declination_deg),
                }
            }
            None => MagPick {
                label: "none: to load, but no calibration passed".into(),
                cal: None,
                declination_deg: 0.0,
            },
        },
        Some(d) => MagPick {
            label: format!(
                "none: {}{}",
                d.reason.words(),
                mag.failure
                    .map_or(String::new(), |f| format!(" ({})", f.name()))
            ),
            cal: None,
            declination_deg: 0.0,
        },
        None => MagPick {
            label: "none: no load decision for the primary compass".into(),
            cal: None,
            declination_deg: 0.0,
        },
    }
}

fn python() -> Option<String> {
    let p = python::python_importing("vqf");
    if p.is_none() {
        println!(
            "peer: no Python with the `vqf` package at {} (scripts/bench installs it); reporting imucald alone.",
            python::python_path()
        );
    }
    p
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

/// VQF's quaternions for a trial and the time of its batch update, s.
fn run_vqf(
    py: &str,
    trial: &Path,
    out_dir: &Path,
) -> Result<(Vec<UnitQuaternion<f64>>, f64), String> {
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
    let stdout = String::from_utf8_lossy(&o.stdout);
    let batch_s = stdout
        .split("batch_s=")
        .nth(1)
        .and_then(|s| s.trim().parse::<f64>().ok())
        .ok_or_else(|| format!("vqf_peer.py printed no batch_s: {stdout}"))?;
    Ok((read_quats(&out)?, batch_s))
}

fn fmt(e: &EvalResult) -> String {
    format!(
        "{:6.2} {:6.2} {:6.2}",
        e.total_rmse_deg, e.heading_rmse_deg, e.inclination_rmse_deg
    )
}

/// imucald's filter over a trial: the estimates (sensor -> ENU) and the time the updates took, s.
fn run_ours(samples: &[Sample], cfg: &FusionConfig) -> (Vec<UnitQuaternion<f64>>, f64) {
    let cfg = FusionConfig {
        world: WorldFrame::Enu,
        ..*cfg
    };
    let dt = median_dt(samples);
    let mut f = OrientationFilter::new(cfg);
    let mut q = Vec::with_capacity(samples.len());
    let start = Instant::now();
    for s in samples {
        f.update_sample(s, dt);
        q.push(f.quaternion_enu());
    }
    (q, start.elapsed().as_secs_f64())
}

/// imucald's filter over a trial as scored: its samples through the replay's calibration, with
/// that calibration's declination ([`MagPick::declination_deg`]).
fn run_trial(t: &Trial, cfg: &FusionConfig) -> (Vec<UnitQuaternion<f64>>, f64) {
    let cfg = FusionConfig {
        declination_deg: t.cal.declination_deg,
        ..*cfg
    };
    run_ours(&t.samples, &cfg)
}

fn score(t: &Trial, cfg: &FusionConfig) -> EvalResult {
    evaluate(&t.samples, &run_trial(t, cfg).0)
}

fn load(dir: &Path, py: Option<&str>) -> Vec<Trial> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.to_string_lossy().ends_with(".csv.gz"))
                .collect()
        })
        .unwrap_or_default();
    paths.sort();
    let tmp = tempfile::tempdir().expect("a temporary directory");
    let mut trials = Vec::new();
    for p in &paths {
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().trim_end_matches(".csv.gz").to_string())
            .unwrap_or_default();
        let log = match read_log(p, None, &Default::default()) {
            Ok(l) => l,
            Err(e) => {
                println!("{name:<44} cannot read: {e}");
                continue;
            }
        };
        let (vqf, vqf_q) = match py.map(|py| run_vqf(py, p, tmp.path())) {
            Some(Ok((q, secs))) if q.len() == log.samples.len() => {
                (Some((evaluate(&log.samples, &q), secs)), q)
            }
            Some(Ok((q, _))) => {
                println!(
                    "{name}: VQF gave {} quaternions for {} samples; left out",
                    q.len(),
                    log.samples.len()
                );
                (None, vec![])
            }
            Some(Err(e)) => {
                println!("{name}: VQF: {e}");
                (None, vec![])
            }
            None => (None, vec![]),
        };
        let cal = replay_pick(p);
        let raw_mag_ut: Vec<Option<Vec3>> = log.samples.iter().map(|s| s.mag_ut).collect();
        let mut samples = log.samples;
        if let Some(c) = &cal.cal {
            for s in &mut samples {
                s.mag_ut = s.mag_ut.map(|m| c.apply(&m));
            }
        }
        trials.push(Trial {
            class: class_of(&name),
            name,
            samples,
            raw_mag_ut,
            cal,
            vqf,
            vqf_q,
        });
    }
    trials
}

/// The signed heading error of an estimate against the reference (both sensor -> ENU), rad: the
/// angle of `q_est q_ref^-1` about the vertical (its twist about z), positive counter-clockwise
/// seen from above. [`errors`] gives its size alone.
fn heading_signed(q_est: &UnitQuaternion<f64>, q_ref: &UnitQuaternion<f64>) -> f64 {
    let e = (q_est * q_ref.inverse()).into_inner();
    let s = if e.w < 0.0 { -1.0 } else { 1.0 };
    2.0 * (s * e.k).atan2(s * e.w)
}

/// The heading error at rest (`moving == 0`) of one run of the filter over a trial: what the
/// field alone sets the heading to when nothing moves (the gyro integrates nothing then), so a
/// constant offset the calibration puts on the field shows there undiluted.
#[derive(Debug, Clone, Copy)]
struct RestHeading {
    /// The mean signed heading error of each rest phase (a run of `moving == 0` samples with a
    /// reference), deg, in time order: the first is the rest before the movement.
    phase_means_deg: [Option<f64>; 2],
    /// The RMS heading error over every rest sample, deg.
    rms_deg: f64,
}

/// [`RestHeading`] of the estimates `q` (one per sample) over the rests of `samples`;
/// `phase_means_deg` holds the first and the last rest phase.
fn rest_heading(samples: &[Sample], q: &[UnitQuaternion<f64>]) -> RestHeading {
    let mut phases: Vec<(f64, usize)> = Vec::new();
    let mut in_rest = false;
    let (mut sum_sq, mut n) = (0.0, 0usize);
    for (s, e) in samples.iter().zip(q) {
        let rest = s.moving == Some(false);
        let Some(r) = reference(s).filter(|_| rest) else {
            in_rest &= rest;
            continue;
        };
        let h = heading_signed(e, &r).to_degrees();
        if !in_rest {
            phases.push((0.0, 0));
            in_rest = true;
        }
        let p = phases.last_mut().expect("a phase started");
        p.0 += h;
        p.1 += 1;
        sum_sq += h * h;
        n += 1;
    }
    let phase_mean = |p: Option<&(f64, usize)>| p.map(|(s, n)| s / (*n).max(1) as f64);
    RestHeading {
        phase_means_deg: [phase_mean(phases.first()), phase_mean(phases.last())],
        rms_deg: (sum_sq / n.max(1) as f64).sqrt(),
    }
}

/// The trial's samples with the magnetometer as the trial carries it (no calibration).
fn raw_samples(t: &Trial) -> Vec<Sample> {
    t.samples
        .iter()
        .zip(&t.raw_mag_ut)
        .map(|(s, m)| Sample { mag_ut: *m, ..*s })
        .collect()
}

/// The most a calibration may add to the first rest's |mean heading error|, deg: the error the
/// raw field leaves there (0.99 deg, the mean over the trials the replay calibrates), so that an
/// offset the calibration puts in the heading stands out of what the reference and the filter
/// leave at rest.
const REST_ADDED_MAX_DEG: f64 = 1.0;

/// The heading at rest through the replay's calibration beside the one on the raw field
/// (declination 0), per trial (`cal`: the runs on the calibrated samples, as scored), with the
/// movement phase's total RMSE of both. The first rest is where the calibration alone shows:
/// the filter's heading there comes from the field and nothing else (no motion yet); the last
/// rest also carries what the motion left. "Added" is the growth of the first rest's |mean
/// heading error| and of the RMS over every rest, the calibration's against the raw field's.
fn rest_table(trials: &[&Trial], cal: &[(EvalResult, RestHeading)], cfg: &FusionConfig) {
    println!("== heading error at rest (moving == 0), deg: mean signed over the first rest / the last rest, RMS over every rest; total RMSE over moving == 1");
    println!(
        "{:<44} {:>27}   {:>27}   {:>13}",
        "trial", "raw field (decl 0)", "replay's calibration", "added: first, RMS"
    );
    let f = |r: &RestHeading, e: &EvalResult| {
        let p = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:+.2}"));
        format!(
            "{:>6} {:>6} {:>5.2} {:>6.2}",
            p(r.phase_means_deg[0]),
            p(r.phase_means_deg[1]),
            r.rms_deg,
            e.total_rmse_deg
        )
    };
    let first = |h: &RestHeading| h.phase_means_deg[0].map_or(0.0, f64::abs);
    let (mut first_raw, mut first_cal, mut rms_raw, mut rms_cal) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut worst: Option<(f64, &str)> = None;
    for (t, (e_cal, h_cal)) in trials.iter().zip(cal) {
        let (e_raw, h_raw) = if t.cal.cal.is_some() {
            let raw = raw_samples(t);
            let q = run_ours(&raw, cfg).0;
            (evaluate(&raw, &q), rest_heading(&raw, &q))
        } else {
            (*e_cal, *h_cal)
        };
        let added_first = first(h_cal) - first(&h_raw);
        let added_rms = h_cal.rms_deg - h_raw.rms_deg;
        if t.cal.cal.is_some() {
            first_raw.push(first(&h_raw));
            first_cal.push(first(h_cal));
            rms_raw.push(h_raw.rms_deg);
            rms_cal.push(h_cal.rms_deg);
            if worst.is_none_or(|(w, _)| added_first > w) {
                worst = Some((added_first, &t.name));
            }
        }
        println!(
            "{:<44} {}   {}   {:>+6.2} {:>+6.2}   {}",
            t.name,
            f(&h_raw, &e_raw),
            f(h_cal, e_cal),
            added_first,
            added_rms,
            t.cal.label
        );
    }
    let n = first_raw.len();
    println!(
        "over the {n} trials the replay calibrated: first rest |mean heading error| raw field {:.2}, replay's calibration {:.2} deg (most added {}; target <= {REST_ADDED_MAX_DEG} deg: {}); RMS over every rest {:.2} and {:.2} deg",
        mean(first_raw.into_iter()),
        mean(first_cal.into_iter()),
        worst.map_or("-".into(), |(w, name)| format!("{w:+.2} deg, {name}")),
        if worst.is_none_or(|(w, _)| w <= REST_ADDED_MAX_DEG) {
            "met"
        } else {
            "not met"
        },
        mean(rms_raw.into_iter()),
        mean(rms_cal.into_iter()),
    );
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

/// Mean total, heading, inclination RMSE of a set of results.
fn means(v: &[EvalResult]) -> String {
    format!(
        "{:6.2} {:6.2} {:6.2}",
        mean(v.iter().map(|e| e.total_rmse_deg)),
        mean(v.iter().map(|e| e.heading_rmse_deg)),
        mean(v.iter().map(|e| e.inclination_rmse_deg))
    )
}

/// Per-trial, per-class and overall tables of `ours` (one result per trial) against VQF; returns the
/// ratio of the mean total RMSEs and the worst per-trial ratio (when VQF ran on every trial).
fn report(title: &str, trials: &[&Trial], ours: &[EvalResult]) -> Option<(f64, f64)> {
    println!("== {title}: total / heading / inclination RMSE (deg) over moving == 1");
    println!(
        "{:<44} {:>20}   {:>20}   {:>6}   magnetometer calibration (imucald; VQF: raw)",
        "trial", "imucald", "VQF 9D (defaults)", "ratio"
    );
    for (t, e) in trials.iter().zip(ours) {
        match &t.vqf {
            Some((v, _)) => println!(
                "{:<44} {}   {}   {:6.2}   {}",
                t.name,
                fmt(e),
                fmt(v),
                e.total_rmse_deg / v.total_rmse_deg,
                t.cal.label
            ),
            None => println!(
                "{:<44} {}   {:>20}   {:>6}   {}",
                t.name,
                fmt(e),
                "",
                "",
                t.cal.label
            ),
        }
    }
    let all_vqf = trials.iter().all(|t| t.vqf.is_some());
    let theirs: Vec<EvalResult> = trials.iter().filter_map(|t| t.vqf.map(|v| v.0)).collect();
    println!("-- per class (mean over its trials)");
    for (c, (_, label)) in CLASSES.iter().enumerate() {
        let idx: Vec<usize> = (0..trials.len())
            .filter(|&i| trials[i].class == c)
            .collect();
        if idx.is_empty() {
            continue;
        }
        let o: Vec<EvalResult> = idx.iter().map(|&i| ours[i]).collect();
        if all_vqf {
            let v: Vec<EvalResult> = idx.iter().map(|&i| theirs[i]).collect();
            let r =
                mean(o.iter().map(|e| e.total_rmse_deg)) / mean(v.iter().map(|e| e.total_rmse_deg));
            println!(
                "{:<44} {}   {}   {r:6.2}",
                format!("{label} ({})", idx.len()),
                means(&o),
                means(&v)
            );
        } else {
            println!("{:<44} {}", format!("{label} ({})", idx.len()), means(&o));
        }
    }
    let label = format!("mean of {} trials", ours.len());
    if !all_vqf || ours.is_empty() {
        println!("{label:<44} {}", means(ours));
        return None;
    }
    let m_ours = mean(ours.iter().map(|e| e.total_rmse_deg));
    let m_theirs = mean(theirs.iter().map(|e| e.total_rmse_deg));
    let ratio = m_ours / m_theirs;
    println!(
        "{label:<44} {}   {}   {ratio:6.2}",
        means(ours),
        means(&theirs)
    );
    let worst = ours
        .iter()
        .zip(&theirs)
        .map(|(a, b)| a.total_rmse_deg / b.total_rmse_deg)
        .fold(0.0, f64::max);
    println!(
        "mean total RMSE imucald {m_ours:.2} vs VQF {m_theirs:.2} deg: ratio {ratio:.2} (target <= 0.8: {}); worst trial ratio {worst:.2} (target <= 1.5: {})",
        if ratio <= 0.8 { "met" } else { "NOT met" },
        if worst <= 1.5 { "met" } else { "NOT met" }
    );
    Some((ratio, worst))
}

// ---------------------------------------------------------------------------------------------
// The tuning procedure.

/// The settings the procedure tunes (all positive; searched by factors). The magnetic
/// disturbance thresholds (`mag_norm_tol`, `mag_dip_tol_deg`) are not among them: they stay at
/// VQF's published values (0.1 and 10 deg). BROAD has one to three disturbed trials per class, so
/// a fold can fit a threshold to the one trial of a class it sees: the dip tolerance tuned to
/// 5 deg on the 2 cm attached magnet cost the held-out 4 cm one 1.71x VQF's error (1.23x at
/// 10 deg). The heading gate's floor (`mag_gate_deg`) is tuned and shows the same weakness with
/// six folds: the fold that sees only the 2 cm magnet narrows it to 28 deg, and the held-out 4 cm
/// one scores 2.86x VQF's error (1.38x with the floor at 56 deg); with three folds it does not.
const TUNED: [&str; 16] = [
    "gyro_noise_density",
    "gyro_rate_noise",
    "intensity_tau_s",
    "bias_walk",
    "acc_noise_mps2",
    "acc_rest_noise_mps2",
    "acc_lin_tau_s",
    "acc_lp_tau_s",
    "mag_heading_noise_deg",
    "mag_rest_heading_noise_deg",
    "mag_new_field_s",
    "mag_gate_deg",
    "mag_gate_timeout_s",
    "rest_gyro_rad_s",
    "gyro_scale_sigma",
    "gyro_scale_path_sd",
];

/// Where every tuning run starts: fixed here, so that no run starts from values another run (on
/// other trials) found. The settings' values before any tuning on BROAD.
fn start_point() -> FusionConfig {
    FusionConfig {
        world: WorldFrame::Enu,
        ..untuned::untuned_fusion()
    }
}

fn get(cfg: &FusionConfig, key: &str) -> f64 {
    serde_json::to_value(cfg).expect("config to JSON")[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} is not a number setting"))
}

fn set(cfg: &FusionConfig, key: &str, v: f64) -> FusionConfig {
    let mut j = serde_json::to_value(cfg).expect("config to JSON");
    j[key] = serde_json::json!(v);
    serde_json::from_value(j).expect("config from JSON")
}

/// What the search minimises on a set of trials: the ratio of imucald's mean total RMSE to VQF's,
/// plus the excess of the worst per-trial ratio over 1.2 (so that no class is given up for the
/// mean).
fn objective(trials: &[&Trial], cfg: &FusionConfig) -> f64 {
    let (ratio, worst) = ratios(trials, &score_all(trials, cfg));
    ratio + (worst - 1.2).max(0.0)
}

/// The ratio of `ours`' mean total RMSE to VQF's over the trials, and the worst per-trial ratio
/// (VQF must have run on every trial).
fn ratios(trials: &[&Trial], ours: &[EvalResult]) -> (f64, f64) {
    let m_ours = mean(ours.iter().map(|e| e.total_rmse_deg));
    let m_vqf = mean(
        trials
            .iter()
            .map(|t| t.vqf.expect("VQF ran").0.total_rmse_deg),
    );
    let worst = ours
        .iter()
        .zip(trials)
        .map(|(e, t)| e.total_rmse_deg / t.vqf.expect("VQF ran").0.total_rmse_deg)
        .fold(0.0, f64::max);
    (m_ours / m_vqf, worst)
}

/// The trials scored on two threads (the machine's other work permitting), each taking the next
/// trial not yet scored.
fn score_all(trials: &[&Trial], cfg: &FusionConfig) -> Vec<EvalResult> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Mutex;
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<EvalResult>>> = Mutex::new(vec![None; trials.len()]);
    let work = || loop {
        let i = next.fetch_add(1, Ordering::Relaxed);
        let Some(t) = trials.get(i) else { break };
        let e = score(t, cfg);
        out.lock().expect("no panic while scoring")[i] = Some(e);
    };
    std::thread::scope(|s| {
        s.spawn(work);
        work();
    });
    out.into_inner()
        .expect("no panic while scoring")
        .into_iter()
        .map(|e| e.expect("scored"))
        .collect()
}

/// The largest value the search may give a setting. The rest detector's gyro threshold stays at
/// or below 4 deg/s: the detector also takes a steady turn slower than the threshold (plus the
/// largest bias) for rest, and learns it as bias. BROAD's rests are true rests, so the trials alone
/// would let it grow (the search took it to 11 deg/s), which a vehicle turning slowly would pay for.
fn upper_bound(key: &str) -> f64 {
    match key {
        "rest_gyro_rad_s" => 4f64.to_radians(),
        _ => f64::INFINITY,
    }
}

/// The smallest value the search may give a setting. The rest detector's gyro threshold stays at
/// or above 2 deg/s: one sample beyond it restarts the detector's clock, and a flight controller's
/// gyro at 1 kHz reads a few tenths of a degree per second of noise at rest (more with a running
/// fan or pump nearby). BROAD's IMU at 286 Hz is quieter, so the trials alone could let a fold
/// shrink it; over all trials it does not pay at the defaults
/// (`IMUCALD_BROAD_SWEEP="rest_gyro_rad_s=0.008727,0.034907"`: mean ratio 0.732 at 0.5 deg/s and
/// 0.735 at 2 deg/s, against 0.708 at the default 4 deg/s).
fn lower_bound(key: &str) -> f64 {
    match key {
        "rest_gyro_rad_s" => 2f64.to_radians(),
        _ => 0.0,
    }
}

/// The second start of the search: [`start_point`] with the heading measurement noises 4x (a
/// magnetometer trusted a quarter as much). The objective has two basins: one where the heading
/// follows the field, and one where it holds what the gyro integrates from a well-measured start
/// (right where the field in motion is off by a few degrees, as in BROAD's laboratory). A search
/// from one start stays in the basin it starts in.
fn weak_mag_start() -> FusionConfig {
    let s = start_point();
    FusionConfig {
        heading: HeadingConfig {
            mag_heading_noise_deg: s.heading.mag_heading_noise_deg * 4.0,
            mag_rest_heading_noise_deg: s.heading.mag_rest_heading_noise_deg * 4.0,
            ..s.heading
        },
        ..s
    }
}

/// The last start: `base` (the better end of the first two searches) moved to VQF's split of the
/// work, the low-pass (`acc_lp_tau_s` 1.5 s) rejecting the linear acceleration and the Kalman
/// update following its output closely (`acc_noise_mps2` 1). A search from a fixed start lowers the low-pass's
/// time constant early (a short low-pass serves a loose Kalman update better) and does not come
/// back to this basin one setting at a time, though sweeps over all trials show it lower; from
/// a fixed start with these settings the search goes astray (a narrow innovation gate, a tiny
/// rest threshold) while the other settings are still far off. So it starts from where the
/// others ended, and holds the low-pass's two settings through the first wide pass
/// ([`LOW_PASS_HELD`]) so that the rest adapt to them before they are judged.
fn low_pass(base: FusionConfig) -> FusionConfig {
    FusionConfig {
        tilt: TiltConfig {
            acc_lp_tau_s: 1.5,
            acc_noise_mps2: 1.0,
            ..base.tilt
        },
        ..base
    }
}

/// Coordinate search from [`start_point`] and [`weak_mag_start`], then from the better end moved
/// by [`low_pass`], keeping the one of the three that ends lowest. From a start, each setting in
/// turn is multiplied by each factor of a pass, and a change is kept when it lowers [`objective`]
/// by more than 0.002. Wide passes (factors 0.25, 0.5, 0.7, 1.4, 2, 4) repeat until one changes
/// nothing (at most three), then fine passes (0.8, 1.25) likewise (at most four).
fn tune(trials: &[&Trial], quiet: bool) -> FusionConfig {
    let (mut j_best, mut best) = search(trials, start_point(), &[], quiet, "fixed");
    let (j, cfg) = search(trials, weak_mag_start(), &[], quiet, "weak magnetometer");
    if j < j_best {
        (j_best, best) = (j, cfg);
    }
    let (j, cfg) = search(trials, low_pass(best), &LOW_PASS_HELD, quiet, "low-pass");
    if j < j_best {
        best = cfg;
    }
    best
}

/// The settings the [`low_pass`] start holds through the first wide pass.
const LOW_PASS_HELD: [&str; 2] = ["acc_lp_tau_s", "acc_noise_mps2"];

/// One coordinate search from `start` (see [`tune`]); the settings in `held` stay at their start
/// values through the first wide pass.
fn search(
    trials: &[&Trial],
    start: FusionConfig,
    held: &[&str],
    quiet: bool,
    label: &str,
) -> (f64, FusionConfig) {
    let mut best = start;
    let mut first = true;
    let mut j_best = objective(trials, &best);
    if !quiet {
        println!("  start ({label}): objective {j_best:.4}");
    }
    let wide = &[0.25, 0.5, 0.7, 1.4, 2.0, 4.0][..];
    let fine = &[0.8, 1.25][..];
    for (factors, passes) in [(wide, 3), (fine, 4)] {
        for _ in 0..passes {
            let j_pass = j_best;
            let holding = std::mem::take(&mut first) && !held.is_empty();
            for key in TUNED {
                if holding && held.contains(&key) {
                    continue;
                }
                let v0 = get(&best, key);
                for f in factors {
                    if v0 * f > upper_bound(key) || v0 * f < lower_bound(key) {
                        continue;
                    }
                    let cand = set(&best, key, v0 * f);
                    let j = objective(trials, &cand);
                    if j < j_best - 0.002 {
                        j_best = j;
                        best = cand;
                        if !quiet {
                            println!("  {key} = {:.6} -> objective {j:.4}", v0 * f);
                        }
                    }
                }
            }
            if j_pass - j_best < 0.002 && !holding {
                break;
            }
        }
    }
    if !quiet {
        println!("  end ({label}): objective {j_best:.4}");
    }
    (j_best, best)
}

fn print_settings(cfg: &FusionConfig) {
    for key in TUNED {
        println!("  {key} = {}", get(cfg, key));
    }
}

/// `--tune [--folds K] [--cv-only]`: the cross-validated figures over K folds (default 3), then
/// (unless `--cv-only`) the search on all trials that chose the defaults.
fn tune_mode(trials: &[Trial], folds: usize, cv_only: bool) {
    if trials.iter().any(|t| t.vqf.is_none()) {
        println!("broad --tune: needs VQF's results on every trial (scripts/bench installs it)");
        return;
    }
    // K folds, each class's trials dealt in turn (name order) so every fold has a mix.
    let mut fold = vec![0usize; trials.len()];
    let mut next = 0;
    for c in 0..CLASSES.len() {
        for (i, t) in trials.iter().enumerate() {
            if t.class == c {
                fold[i] = next % folds;
                next += 1;
            }
        }
    }
    let mut held_out: Vec<Option<EvalResult>> = vec![None; trials.len()];
    for k in 0..folds {
        let train: Vec<&Trial> = (0..trials.len())
            .filter(|&i| fold[i] != k)
            .map(|i| &trials[i])
            .collect();
        let test: Vec<usize> = (0..trials.len()).filter(|&i| fold[i] == k).collect();
        println!(
            "== fold {k}: tuned on {} trials, scored on {}",
            train.len(),
            test.iter()
                .map(|&i| trials[i].name.split('_').next().unwrap_or(""))
                .collect::<Vec<_>>()
                .join(" ")
        );
        let cfg = tune(&train, false);
        print_settings(&cfg);
        for i in test {
            held_out[i] = Some(score(&trials[i], &cfg));
        }
    }
    let all: Vec<&Trial> = trials.iter().collect();
    let cv: Vec<EvalResult> = held_out.into_iter().map(|e| e.expect("scored")).collect();
    let cv_fig = report(
        &format!("cross-validated ({folds} folds): each trial scored by the settings tuned on the other folds"),
        &all,
        &cv,
    );
    let summary = cv_fig.map(|(r, w)| {
        format!("cross-validated ({folds} folds): mean total RMSE ratio {r:.2}, worst trial ratio {w:.2}")
    });
    if cv_only {
        summary.iter().for_each(|l| println!("{l}"));
        return;
    }
    println!("== tuned on all {} trials (the defaults)", trials.len());
    let cfg = tune(&all, false);
    print_settings(&cfg);
    let defaults = FusionConfig {
        world: WorldFrame::Enu,
        ..FusionConfig::default()
    };
    let same = TUNED
        .iter()
        .all(|k| (get(&cfg, k) / get(&defaults, k) - 1.0).abs() < 1e-9);
    println!(
        "FusionConfig::default() {} these settings",
        if same { "holds" } else { "does NOT hold" }
    );
    summary.iter().for_each(|l| println!("{l}"));
}

/// `FusionConfig::default()` with the settings of `$IMUCALD_BROAD_SET` (`key=value,key=value`), for
/// trying values by hand; the figures of record use none.
fn configured() -> FusionConfig {
    let mut cfg = FusionConfig::default();
    if let Ok(v) = std::env::var("IMUCALD_BROAD_SET") {
        for kv in v.split(',').filter(|s| !s.trim().is_empty()) {
            match kv
                .split_once('=')
                .map(|(k, v)| (k.trim(), v.trim().parse::<f64>()))
            {
                Some((k, Ok(x))) => {
                    cfg = set(&cfg, k, x);
                    println!("setting {k} = {x}");
                }
                _ => println!("IMUCALD_BROAD_SET: cannot read {kv}"),
            }
        }
    }
    cfg
}

/// `IMUCALD_BROAD_SWEEP="key=v1,v2;key2=v3"`: one line per value of each key (each on top of
/// [`configured`], one key changed at a time) with the mean total RMSE ratio to VQF, the worst
/// trial's ratio, the mean heading and inclination RMSE and every trial's ratio: a look at one
/// setting's effect across all trials at once, for deciding what the tuning should search; the
/// defaults come from [`tune`] only.
fn sweep(trials: &[Trial], spec: &str) {
    if trials.iter().any(|t| t.vqf.is_none()) {
        println!(
            "IMUCALD_BROAD_SWEEP: needs VQF's results on every trial (scripts/bench installs it)"
        );
        return;
    }
    let all: Vec<&Trial> = trials.iter().collect();
    let base = FusionConfig {
        world: WorldFrame::Enu,
        ..configured()
    };
    let vqf = |t: &Trial| t.vqf.map_or(f64::NAN, |v| v.0.total_rmse_deg);
    let line = |label: &str, cfg: &FusionConfig| {
        let ours = score_all(&all, cfg);
        let r: Vec<f64> = ours
            .iter()
            .zip(&all)
            .map(|(e, t)| e.total_rmse_deg / vqf(t))
            .collect();
        let m = mean(ours.iter().map(|e| e.total_rmse_deg)) / mean(all.iter().map(|t| vqf(t)));
        println!(
            "{label:<36} mean {m:.3} worst {:.2} heading {:.2} incl {:.2} | {}",
            r.iter().cloned().fold(0.0, f64::max),
            mean(ours.iter().map(|e| e.heading_rmse_deg)),
            mean(ours.iter().map(|e| e.inclination_rmse_deg)),
            r.iter()
                .map(|x| format!("{x:.2}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
    };
    line("as configured", &base);
    for part in spec.split(';').filter(|s| !s.trim().is_empty()) {
        let Some((key, values)) = part.split_once('=') else {
            println!("IMUCALD_BROAD_SWEEP: cannot read {part} (key=v1,v2)");
            continue;
        };
        let key = key.trim();
        if serde_json::to_value(base).expect("config to JSON")[key]
            .as_f64()
            .is_none()
        {
            println!("IMUCALD_BROAD_SWEEP: {key} is not a number setting of FusionConfig");
            continue;
        }
        for v in values.split(',') {
            match v.trim().parse::<f64>() {
                Ok(x) => line(&format!("{key}={x}"), &set(&base, key, x)),
                Err(e) => println!("IMUCALD_BROAD_SWEEP: {key}={v}: {e}"),
            }
        }
    }
}

fn dump(trials: &[Trial], pattern: &str, out: &Path) {
    let Some(t) = trials.iter().find(|t| t.name.contains(pattern)) else {
        println!("broad --dump: no trial matches {pattern}");
        return;
    };
    let cfg = FusionConfig {
        world: WorldFrame::Enu,
        declination_deg: t.cal.declination_deg,
        ..configured()
    };
    let dt = median_dt(&t.samples);
    let mut flt = OrientationFilter::new(cfg);
    // The same filter on the raw field (declination 0), for the signed heading beside ours.
    let raw = raw_samples(t);
    let raw_q = run_ours(
        &raw,
        &FusionConfig {
            declination_deg: 0.0,
            ..cfg
        },
    )
    .0;
    let mut s = String::from(
        "t,moving,ours_total,ours_heading,ours_incl,vqf_total,vqf_heading,vqf_incl,rest,mag_disturbed,bias_x,bias_y,bias_z,qw,qx,qy,qz,ours_heading_signed,raw_heading_signed,vqf_heading_signed\n",
    );
    for (i, smp) in t.samples.iter().enumerate() {
        flt.update_sample(smp, dt);
        let Some(r) = reference(smp) else { continue };
        let (a, b, c) = errors(&flt.quaternion_enu(), &r);
        let signed = |q: Option<&UnitQuaternion<f64>>| {
            q.map_or(f64::NAN, |q| heading_signed(q, &r).to_degrees())
        };
        let signed = [
            signed(Some(&flt.quaternion_enu())),
            signed(raw_q.get(i)),
            signed(t.vqf_q.get(i)),
        ];
        let v = t.vqf_q.get(i).map(|v| errors(v, &r));
        let (d, e, f) = v.unwrap_or((f64::NAN, f64::NAN, f64::NAN));
        let bias = flt.bias();
        let q = flt.quaternion_enu();
        s += &format!(
            "{:.4},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{:.6},{:.6},{:.6},{:.7},{:.7},{:.7},{:.7},{:.4},{:.4},{:.4}\n",
            smp.t_s,
            u8::from(smp.moving == Some(true)),
            a.to_degrees(),
            b.to_degrees(),
            c.to_degrees(),
            d.to_degrees(),
            e.to_degrees(),
            f.to_degrees(),
            u8::from(flt.at_rest()),
            u8::from(flt.mag_disturbed()),
            bias[0],
            bias[1],
            bias[2],
            q.w,
            q.i,
            q.j,
            q.k,
            signed[0],
            signed[1],
            signed[2]
        );
    }
    match std::fs::write(out, s) {
        Ok(()) => println!("broad --dump: {} -> {}", t.name, out.display()),
        Err(e) => println!("broad --dump: {}: {e}", out.display()),
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if !args.iter().any(|a| a == "--bench") {
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
    let py = python();
    let trials = load(&dir, py.as_deref());
    if trials.is_empty() {
        println!("broad: no .csv.gz trial in {}", dir.display());
        return;
    }
    if args.iter().any(|a| a == "--tune") {
        let folds = match args.iter().position(|a| a == "--folds") {
            Some(i) => match args.get(i + 1).and_then(|v| v.parse::<usize>().ok()) {
                Some(k) if k >= 2 && k <= trials.len() => k,
                _ => {
                    println!(
                        "broad --tune --folds K: K is a whole number from 2 to {}",
                        trials.len()
                    );
                    return;
                }
            },
            None => 3,
        };
        tune_mode(&trials, folds, args.iter().any(|a| a == "--cv-only"));
        return;
    }
    if let Ok(spec) = std::env::var("IMUCALD_BROAD_SWEEP") {
        sweep(&trials, &spec);
        return;
    }
    if let Some(i) = args.iter().position(|a| a == "--dump") {
        match (args.get(i + 1), args.get(i + 2)) {
            (Some(p), Some(o)) => dump(&trials, p, Path::new(o)),
            _ => println!("broad --dump NAME OUT.csv"),
        }
        return;
    }
    // One trial after the other on this thread, so the times are the filter's alone.
    let cfg = configured();
    let mut ours = Vec::new();
    let mut rest = Vec::new();
    let (mut secs, mut n) = (0.0, 0usize);
    for t in &trials {
        // The fastest of three runs, as for VQF (scripts/vqf_peer.py): the machine's other work
        // only ever adds time.
        let (q, s) = run_trial(t, &cfg);
        let s = (0..2).fold(s, |best, _| best.min(run_trial(t, &cfg).1));
        secs += s;
        n += t.samples.len();
        let e = evaluate(&t.samples, &q);
        ours.push(e);
        rest.push((e, rest_heading(&t.samples, &q)));
    }
    let all: Vec<&Trial> = trials.iter().collect();
    report(
        &format!(
            "BROAD, {} trials, default settings, the magnetometer through the replay's calibration",
            trials.len()
        ),
        &all,
        &ours,
    );
    rest_table(&all, &rest, &cfg);
    print!(
        "cost per sample: imucald {:.2} us ({n} samples, one thread)",
        secs / n as f64 * 1e6
    );
    if trials.iter().all(|t| t.vqf.is_some()) {
        let v: f64 = trials.iter().map(|t| t.vqf.expect("VQF ran").1).sum();
        println!(
            ", VQF batch update {:.2} us: ratio {:.2}",
            v / n as f64 * 1e6,
            secs / v
        );
    } else {
        println!();
    }
    // The same trials with the settings before any tuning: what the tuning gained on the data it
    // saw, to set beside what it gains on data it never saw (tests/stress.rs, tests/mocap_flights.rs).
    if trials.iter().all(|t| t.vqf.is_some()) {
        let untuned = score_all(&all, &start_point());
        let (ratio, worst) = ratios(&all, &untuned);
        println!(
            "untuned settings (the tuning's start point): {} deg, ratio {ratio:.2}, worst trial {worst:.2}",
            means(&untuned)
        );
    }
}
