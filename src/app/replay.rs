//! `replay`: a captured log through the same pipeline as the live service, as fast as it goes.

use crate::calib::fit::FitFailure;
use crate::calib::pipeline::{Calibrated, Calibrator, FitResults, Pipeline};
use crate::config::Config;
use crate::error::Error;
use crate::io::decode::Format;
use crate::report::{
    CalStatus, CalibrationReport, CoverageReport, InputReport, PoseReport, Report, SCHEMA,
};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

mod gyro_scale;
mod load;
mod tempcal;
use gyro_scale::{gyro_scale_of, GyroFits, SpanRates};
pub use load::loadable;

/// What to write besides the report.
#[derive(Debug, Clone, Default)]
pub struct ReplayOptions {
    pub format: Option<Format>,
    pub report: Option<PathBuf>,
    pub calibrated_out: Option<PathBuf>,
    pub plot_dir: Option<PathBuf>,
    /// Directory for ArduPilot/PX4/Fusion exports.
    pub export_dir: Option<PathBuf>,
    /// A self-contained HTML page of the result (`crate::app::ui::html`).
    pub html: Option<PathBuf>,
    /// A diagnosis report (imucald.diagnosis/1) to show in the HTML page.
    pub diagnosis: Option<PathBuf>,
    /// Directory for the readings of each compass's held-out check, for a peer's fit on the same
    /// blocks (`write_quality_points`).
    pub quality_points: Option<PathBuf>,
    /// Refit while reading, every `fit.refit_every_s` of data as the live service does, and keep
    /// that history (the report's `refits`). Default false: a replay is a batch, one fit per
    /// sensor on all the data at the end.
    pub refits: bool,
    /// Write every compass's calibration as values to load in the exports, whatever its
    /// verdict ([`crate::report::LoadDecision`]); the files say so. Default false: a compass
    /// not to load is written as comments with the reason.
    pub export_all: bool,
}

pub struct ReplayOutcome {
    pub report: Report,
    pub results: FitResults,
    pub written: Vec<PathBuf>,
    /// What the replay held of the log's samples: bounded, whatever the log's length.
    pub kept: Kept,
}

/// Samples of each instance a replay keeps for the steps after the fit (method choice, mounting
/// check, held-out quality, onboard comparison, plots): 2^17, 22 minutes at 100 Hz. A longer
/// log is thinned evenly in time ([`Thinned`]): those steps judge directions and attitudes, which
/// a vehicle repeats, not every reading. About 36 MB per instance at the most.
pub(crate) const KEPT_SAMPLES_MAX: usize = 1 << 17;

/// Samples of the rotations between static poses the gyro scale is fitted on, at most: as many
/// as [`KEPT_SAMPLES_MAX`] (every rotation of a log that fits in it whole). A longer log gives an
/// evenly spread choice of its rotations, each kept at the full rate as the log is read (the
/// rotation is integrated sample by sample; [`gyro_scale::SpanRates`]), a hundred and more of
/// them for the 9 terms fitted.
pub(crate) const GYRO_SPAN_SAMPLES_MAX: usize = KEPT_SAMPLES_MAX;

/// What a replay held of a log's samples ([`ReplayOutcome::kept`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Kept {
    /// Samples decoded, every instance.
    pub seen: u64,
    /// Samples held for the steps after the fit, every instance.
    pub held: usize,
    /// The most one instance held, and the cap on it ([`KEPT_SAMPLES_MAX`]).
    pub largest: usize,
    pub cap: usize,
    /// Samples of the rotations the gyro scale was fitted on, at most [`GYRO_SPAN_SAMPLES_MAX`].
    pub gyro_span_samples: usize,
}

/// An evenly thinned record of a stream of samples, at most [`KEPT_SAMPLES_MAX`]: every
/// `stride`-th, the stride doubling (and every other sample held dropped) when it is full.
#[derive(Debug, Default)]
struct Thinned {
    samples: Vec<crate::types::Sample>,
    stride: u64,
    seen: u64,
    /// The time of the first sample and of the last, s.
    first_t_s: Option<f64>,
    last_t_s: f64,
}

impl Thinned {
    fn push(&mut self, s: &crate::types::Sample) {
        if self.samples.capacity() == 0 {
            // Room for as many as are kept, taken up only as they come (no copies as it grows).
            self.samples.reserve_exact(KEPT_SAMPLES_MAX);
        }
        self.stride = self.stride.max(1);
        self.first_t_s.get_or_insert(s.t_s);
        self.last_t_s = s.t_s;
        let at = self.seen;
        self.seen += 1;
        if !at.is_multiple_of(self.stride) {
            return;
        }
        if self.samples.len() >= KEPT_SAMPLES_MAX {
            let mut k = 0;
            self.samples.retain(|_| {
                k += 1;
                k % 2 == 1
            });
            self.stride *= 2;
            if !at.is_multiple_of(self.stride) {
                return;
            }
        }
        self.samples.push(*s);
    }

    /// Every sample seen is held.
    fn whole(&self) -> bool {
        self.stride <= 1
    }

    fn duration_s(&self) -> f64 {
        self.first_t_s.map_or(0.0, |t| self.last_t_s - t)
    }
}

/// Run a log through the pipeline. `progress(bytes_done, bytes_total)` is called now and then.
/// The log is read as a stream and what is kept of it is bounded ([`Kept`]); the outputs that
/// need every sample read it again.
pub fn replay(
    path: &Path,
    cfg: &Config,
    opts: &ReplayOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<ReplayOutcome, Error> {
    let started = std::time::Instant::now();
    let mut run = run_pipelines(path, cfg, opts, progress)?;
    let read_s = started.elapsed().as_secs_f64();
    let fin = final_fits(cfg, &mut run);
    tracing::debug!(
        read_ms = 1e3 * read_s,
        fits_ms = 1e3 * (started.elapsed().as_secs_f64() - read_s),
        "replay: log read and gated, then fitted"
    );
    run.pipe.install_final(fin.installed);
    let (mut results, quality, span_samples) = (fin.results, fin.quality, fin.span_samples);
    run.other_mags = other_mag_methods(&mut run, cfg, &quality);
    let mut quality: Vec<crate::report::QualityReport> =
        quality.into_iter().map(|j| j.judged.report).collect();
    judge_sphere_fits(&run, &results.mag, &mut quality);
    mark_implausible(fin.implausible, &mut run, &mut results, &mut quality);
    let declination = cfg.declination_deg()?;
    let mut report = full_report(path, &mut run, &results, declination);
    report.quality = quality;
    report.load = load::decide(&report, cfg.accept.mag.max_rms_ratio);
    report.temperature = tempcal::temperature(&run, &cfg.tempcal);
    let (pipe, log) = (&run.pipe, &run.log);
    let mut written = vec![];
    if let Some(p) = &opts.report {
        crate::io::publish::write_json(p, &report)?;
        written.push(p.clone());
    }
    if let Some(p) = &opts.calibrated_out {
        let out = CalibratedOut {
            pipe,
            results: &results,
            cfg,
            declination,
        };
        write_calibrated(p, path, opts, &out)?;
        written.push(p.clone());
    }
    if let Some(dir) = &opts.export_dir {
        written.extend(write_exports(dir, &report, &results, opts.export_all)?);
        written.extend(tempcal::write_exports(dir, &report.temperature)?);
    }
    if let Some(dir) = &opts.plot_dir {
        written.extend(write_plots(dir, pipe, &log.samples, &results)?);
    }
    if let Some(p) = &opts.html {
        write_html(p, &mut run, &report, &results, opts)?;
        written.push(p.clone());
    }
    if let Some(dir) = &opts.quality_points {
        std::fs::create_dir_all(dir).map_err(|source| Error::Write {
            path: dir.clone(),
            source,
        })?;
        written.extend(write_quality_points(dir, &run, cfg)?);
    }
    let kept = run.kept(span_samples);
    Ok(ReplayOutcome {
        report,
        results,
        written,
        kept,
    })
}

/// What [`final_fits`] gives.
struct FinalFits {
    /// The fits for the primary's pipeline to install ([`Pipeline::install_final`]).
    installed: FitResults,
    /// The same after the magnetometer's method choice, the ladder's rung and the mounting
    /// check, with the gyro scale.
    results: FitResults,
    quality: Vec<CompassJudged>,
    /// The samples the gyro scale was fitted on.
    span_samples: usize,
    /// The compasses that see no earth field ([`implausible`]).
    implausible: Vec<Implausible>,
}

/// The primary's fits at the end of the log, with what does not need the magnetometer's, on
/// threads of their own: the magnetometer fit; the held-out quality of every compass (which uses
/// no fit of the run); every compass's check for the earth's field; the accelerometer and
/// gyro bias fits, then the gyro scale (here, after the rest, when too few poses leave it little
/// to do), while this one gathers the evidence of the magnetometer's method choice (the readings
/// and attitudes alone). The accelerometer's and gyro bias fits are handed on as soon as they
/// are made, so the method choice, the ladder's rung and the mounting check of the primary run
/// here while the gyro scale, which none of them reads, is fitted. Each step does what it did in
/// turn, so the results are the same.
fn final_fits(cfg: &Config, run: &mut Run) -> FinalFits {
    let input = run.pipe.finish_input();
    run.span_rates.finish(&run.pipe);
    let calib = run.pipe.settings().clone();
    let run_ref = &*run;
    let (input, calib) = (&input, &calib);
    std::thread::scope(|scope| {
        let mag = scope.spawn(|| crate::calib::pipeline::fit_mag(input, calib));
        let quality = scope.spawn(|| quality(run_ref, cfg));
        let implausible = scope.spawn(|| implausible(run_ref, cfg));
        let (fits_tx, fits_rx) = std::sync::mpsc::channel();
        let accel_gyro = move || {
            let (accel, gyro) = crate::calib::pipeline::fit_accel_gyro(input, calib);
            // The receiver is there until this is joined.
            let _ = fits_tx.send((accel.clone(), gyro.clone()));
            let fits = GyroFits {
                gyro: &gyro,
                accel: &accel,
            };
            gyro_scale_of(run_ref, fits)
        };
        // The gyro scale takes long only with rotations enough to fit (each from one pose to the
        // next): then on a thread of its own, else here.
        let min_poses = 2 * crate::calib::gyro::ScaleOptions::default().min_segments + 1;
        let (own, here) = if run_ref.pipe.poses().len() >= min_poses {
            (Some(scope.spawn(accel_gyro)), None)
        } else {
            (None, Some(accel_gyro))
        };
        let mag_evidence = mag_method_evidence(run_ref, cfg, input.mag_cal_units());
        let scale_here = here.map(|f| f());
        let Ok((accel, gyro)) = fits_rx.recv() else {
            // The thread ended without them: its panic goes on here.
            own.map(joined);
            unreachable!("the accelerometer and gyro fits end in a result or a panic");
        };
        let quality = joined(quality);
        let installed = crate::calib::pipeline::join_fits(joined(mag), accel, gyro, input, calib);
        let mut results = installed.clone();
        let sphere = crate::calib::magmethod::sphere_words(&results.mag);
        crate::calib::magmethod::choose_with(&mut results.mag, &mag_evidence);
        if let Some(j) = quality.iter().find(|j| j.other.is_none()) {
            install_rung(&mut results.mag, &j.judged, &sphere);
        }
        mounting_check(&mut results, &run_ref.log, &run_ref.pipe, cfg);
        let (scale, failure, span_samples) = match own {
            Some(h) => joined(h),
            None => scale_here.expect("fitted here"),
        };
        results.gyro.scale = scale;
        results.gyro.scale_failure = failure;
        FinalFits {
            installed,
            results,
            quality,
            span_samples,
            implausible: joined(implausible),
        }
    })
}

/// What a scoped thread gave; its panic, if it panicked, goes on here.
fn joined<T>(h: std::thread::ScopedJoinHandle<'_, T>) -> T {
    h.join()
        .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
}

/// The self-contained HTML page of the run at `p` ([`crate::app::ui::html`]).
fn write_html(
    p: &Path,
    run: &mut Run,
    report: &Report,
    results: &FitResults,
    opts: &ReplayOptions,
) -> Result<(), Error> {
    let others = run.log.instances.iter().zip(run.others.iter_mut());
    let others = others.filter_map(|(i, o)| Some((i.name.clone(), o.as_mut()?.finish().clone())));
    let views = crate::app::ui::html::Views::new(report, results, others.collect());
    crate::app::ui::html::write(p, report, &views, opts.diagnosis.as_deref())
}

/// One compass of a log and what judging it needs: its instance, the stream its magnetometer
/// readings come from (to find the vehicle's calibration of it), its samples and pipeline.
struct Compass<'a> {
    /// The index of a further instance (`Run::others`); `None` for the primary.
    other: Option<usize>,
    instance: String,
    source: String,
    samples: &'a [crate::types::Sample],
    pipe: &'a Pipeline,
}

/// Every compass of the run with readings: the primary's first, then each further instance's.
fn compasses(run: &Run) -> Vec<Compass<'_>> {
    let log = &run.log;
    let mut out = Vec::new();
    {
        // A log of one unnamed stream (CSV) is judged under the name `primary`.
        let instance = log
            .instance
            .clone()
            .unwrap_or_else(|| load::PRIMARY.to_string());
        let source = match &log.flight {
            Some(f) => f.primary_mag_source.clone(),
            None => Some(instance.clone()),
        };
        if let Some(source) = source {
            out.push(Compass {
                other: None,
                instance,
                source,
                samples: &log.samples,
                pipe: &run.pipe,
            });
        }
    }
    for (k, p) in run.others.iter().enumerate() {
        let (Some(p), Some(info)) = (p.as_ref(), log.instances.get(k)) else {
            continue;
        };
        let samples = run.other_samples.get(k).map_or(&[][..], |v| &v[..]);
        if !samples.iter().any(|s| s.mag_ut.is_some()) {
            continue;
        }
        // A flight log's instance joins its streams with '+': the magnetometer's is the source.
        let source = info
            .name
            .split('+')
            .find(|p| p.to_ascii_lowercase().contains("mag") || !info.name.contains('+'))
            .unwrap_or(&info.name)
            .to_string();
        out.push(Compass {
            other: Some(k),
            instance: info.name.clone(),
            source,
            samples,
            pipe: p,
        });
    }
    out
}

/// `f` with a compass's field in body axes (raw, any onboard correction undone) and, where the
/// log records one for its stream, the field through the vehicle's own calibration.
fn judge<R>(
    log: &crate::io::sources::Log,
    c: &Compass<'_>,
    f: impl FnOnce(
        &crate::calib::magmethod::FieldOf<'_>,
        Option<&crate::calib::magmethod::FieldOf<'_>>,
        Option<&crate::calib::ladder::Affine>,
    ) -> R,
) -> R {
    let pipe = c.pipe;
    let slot = log
        .onboard()
        .and_then(|o| o.mag.iter().find(|m| m.sources.contains(&c.source)))
        .filter(|m| m.units == crate::types::CalUnits::Ut);
    let body_mag = |s: &crate::types::Sample| pipe.mag_in_body(s);
    let onboard = slot.map(|m| {
        let mat = crate::calib::model::rows_to_mat(&m.matrix);
        let o = nalgebra::Vector3::from(m.offset);
        move |s: &crate::types::Sample| {
            let raw = nalgebra::Vector3::from(s.mag_ut?);
            let v = mat * (raw - o);
            let corrected = crate::types::Sample {
                mag_ut: Some([v.x, v.y, v.z]),
                ..Default::default()
            };
            pipe.mag_in_body(&corrected)
        }
    });
    // The same calibration in body axes: rot M (raw - o) with raw = rot^T u is
    // (rot M rot^T) (u - rot o).
    let start = slot.map(|m| {
        let rot = pipe.sensor_rotation();
        crate::calib::ladder::Affine {
            matrix: rot * crate::calib::model::rows_to_mat(&m.matrix) * rot.transpose(),
            offset: rot * nalgebra::Vector3::from(m.offset),
        }
    });
    f(
        &body_mag,
        onboard
            .as_ref()
            .map(|g| g as &crate::calib::magmethod::FieldOf<'_>),
        start.as_ref(),
    )
}

/// A compass whose calibration is the sphere fit although the log has an attitude (no place,
/// and the vector fit with the field fitted not taken; no ladder ran) is judged on the held-out
/// blocks by that calibration, the one it offers, in place of the vector fit's
/// ([`crate::calib::magmethod::judge_sphere`]).
fn judge_sphere_fits(
    run: &Run,
    primary: &crate::calib::outcome::SensorResult,
    quality: &mut [crate::report::QualityReport],
) {
    for c in compasses(run) {
        let mag = match c.other {
            None => primary,
            Some(k) => match run.other_mags.get(k).and_then(|m| m.as_ref()) {
                Some(m) => m,
                None => continue,
            },
        };
        let sphere = mag.report.method.as_ref().map(|m| m.method)
            == Some(crate::calib::outcome::MagMethod::Sphere);
        let (true, Some(cal)) = (sphere, mag.calibration) else {
            continue;
        };
        let Some(q) = quality
            .iter_mut()
            .find(|q| q.instance == c.instance && q.start.is_none())
        else {
            continue;
        };
        let pipe = c.pipe;
        // In sensor axes, as the pipeline fitted it, then into body axes.
        let ours = |s: &crate::types::Sample| {
            let v = cal.apply(&s.mag_ut?);
            pipe.to_body(&crate::types::Sample {
                mag_ut: Some(v),
                ..*s
            })
            .mag_ut
        };
        *q = judge(&run.log, &c, |body_mag, onboard, _| {
            crate::calib::magmethod::judge_sphere(&c.instance, c.samples, body_mag, onboard, &ours)
        });
    }
}

/// A compass that sees no earth field ([`implausible`]): the index of a further instance
/// (`Run::others`, `None` for the primary), its name and why.
type Implausible = (Option<usize>, String, crate::calib::plausible::Implausible);

/// Every compass's readings checked for a compass seeing the earth's field
/// ([`crate::calib::plausible`]): those that do not ([`mark_implausible`]).
fn implausible(run: &Run, cfg: &Config) -> Vec<Implausible> {
    let log = &run.log;
    let mut found: Vec<Implausible> = Vec::new();
    for c in compasses(run) {
        let field =
            crate::calib::magmethod::earth_field_of(c.samples, log.place(), cfg.place.as_ref());
        let b = field
            .as_ref()
            .map(|f| nalgebra::Vector3::from(f.field_ned_ut()));
        let pipe = c.pipe;
        let n = c.samples.len();
        // Every reading with an accelerometer's (as usual): those readings are all of them.
        let all_with_accel = c
            .samples
            .iter()
            .all(|s| s.mag_ut.is_none() || s.accel_mps2.is_some());
        let mut readings = Vec::with_capacity(n);
        let mut expected = Vec::new();
        let mut with_accel = Vec::new();
        let mut accel = Vec::with_capacity(n);
        for s in c.samples {
            let body = pipe.to_body(s);
            let Some(m) = body.mag_ut else {
                continue;
            };
            let m = nalgebra::Vector3::from(m);
            readings.push(m);
            if let Some(a) = body.accel_mps2 {
                if !all_with_accel {
                    with_accel.push(m);
                }
                accel.push(nalgebra::Vector3::from(a));
            }
            if let (Some(b), Some(q)) = (b, s.ref_q.and_then(crate::attitude::body_ned_of_ref_q)) {
                expected.push((m, q.inverse_transform_vector(&b)));
            }
        }
        let earth = field.as_ref().map(|f| f.total_ut);
        let still = || {
            expected
                .is_empty()
                .then(|| {
                    let with_accel = if all_with_accel {
                        &readings
                    } else {
                        &with_accel
                    };
                    crate::calib::plausible::check_still(with_accel, &accel)
                })
                .flatten()
        };
        if let Some(e) = crate::calib::plausible::check(&readings, &expected, earth).or_else(still)
        {
            found.push((c.other, c.instance.clone(), e));
        }
    }
    found
}

/// The compasses [`implausible`] found fail (`implausible`, with its numbers), and their
/// held-out records say they were not judged.
fn mark_implausible(
    found: Vec<Implausible>,
    run: &mut Run,
    results: &mut FitResults,
    quality: &mut [crate::report::QualityReport],
) {
    for (other, instance, e) in found {
        let mag = match other {
            None => Some(&mut results.mag),
            Some(k) => run.other_mags.get_mut(k).and_then(Option::as_mut),
        };
        if let Some(mag) = mag {
            mag.calibration = None;
            mag.report.status = CalStatus::Failed;
            mag.report.failure = Some(FitFailure::Implausible);
            mag.report.detail = Some(e.to_string());
        }
        if let Some(q) = quality.iter_mut().find(|q| q.instance == instance) {
            q.imucald = None;
            q.rung = None;
            q.imucald_failure = Some(e.to_string());
            q.verdict_kind = Some(crate::calib::outcome::Verdict::Failed);
            q.verdict = format!("not judged: {e}");
        }
    }
}

/// One compass's held-out judgement ([`crate::calib::magmethod::quality`]) and which it is.
struct CompassJudged {
    /// The index of a further instance (`Run::others`); `None` for the primary.
    other: Option<usize>,
    judged: crate::calib::magmethod::Judged,
}

/// The ladder's calibration of a compass ([`crate::calib::ladder`]) as its result, when the
/// ladder took a rung.
/// `sphere`: what the sphere fit made of the readings, said before the method choice.
fn install_rung(
    mag: &mut crate::calib::outcome::SensorResult,
    j: &crate::calib::magmethod::Judged,
    sphere: &str,
) {
    if let (Some(chosen), Some(start)) = (&j.calibration, j.report.start) {
        crate::calib::magmethod::install_rung(
            mag,
            chosen,
            start,
            j.why.as_deref().unwrap_or(""),
            sphere,
        );
    }
}

/// Every compass judged on the blocks of the log it was not fitted on, against the vehicle's own
/// calibration of the same compass ([`crate::calib::magmethod::quality`]); the primary first.
fn quality(run: &Run, cfg: &Config) -> Vec<CompassJudged> {
    let log = &run.log;
    compasses(run)
        .iter()
        .filter_map(|c| {
            judge(log, c, |body_mag, onboard, start| {
                crate::calib::magmethod::quality(
                    &c.instance,
                    c.samples,
                    body_mag,
                    onboard,
                    start,
                    log.place(),
                    cfg.place.as_ref(),
                )
            })
            .map(|judged| CompassJudged {
                other: c.other,
                judged,
            })
        })
        .collect()
}

/// The readings of the held-out check of every compass, one CSV per compass in `dir`
/// (`quality_<instance>.csv`): for a peer's fit on the same blocks. Columns: `t` (s), `fit` (1 in
/// a fitting block, 0 in a scored one), `mx my mz` (body axes, onboard correction undone, uT),
/// `qw qx qy qz` (body -> NED), `onboard_mx ..` (through the vehicle's calibration, uT; empty
/// without one). `#` lines first name the instance and give the earth field of the place and
/// day, when known.
fn write_quality_points(dir: &Path, run: &Run, cfg: &Config) -> Result<Vec<PathBuf>, Error> {
    let log = &run.log;
    let mut written = Vec::new();
    for c in compasses(run) {
        let (points, field) = judge(log, &c, |body_mag, onboard, _| {
            crate::calib::magmethod::quality_points(
                c.samples,
                body_mag,
                onboard,
                log.place(),
                cfg.place.as_ref(),
            )
        });
        if points.is_empty() {
            continue;
        }
        let mut text = format!("# instance {}\n", c.instance);
        if let Some((p, f)) = field {
            let _ = writeln!(
                text,
                "# place {} {} {}; earth field NED {} {} {} uT",
                p.latitude_deg,
                p.longitude_deg,
                p.date.as_deref().unwrap_or("today"),
                f[0],
                f[1],
                f[2]
            );
        }
        text.push_str("t,fit,mx,my,mz,qw,qx,qy,qz,onboard_mx,onboard_my,onboard_mz\n");
        for q in &points {
            let [mx, my, mz] = q.raw_body_ut;
            let [w, x, y, z] = q.body_ned;
            let _ = write!(
                text,
                "{},{},{mx},{my},{mz},{w},{x},{y},{z}",
                q.t_s, q.fit as u8
            );
            match q.onboard_body_ut {
                Some([a, b, c]) => {
                    let _ = writeln!(text, ",{a},{b},{c}");
                }
                None => text.push_str(",,,\n"),
            }
        }
        let name: String = c
            .instance
            .chars()
            .map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' })
            .collect();
        let p = dir.join(format!("quality_{name}.csv"));
        crate::io::publish::write_atomic(&p, text.as_bytes())?;
        written.push(p);
    }
    Ok(written)
}

/// The evidence of the primary magnetometer's method ([`crate::calib::magmethod::Evidence`]):
/// the vector fit when the log carries an attitude and the place is known and it determines the
/// offset, else the planar or the sphere fit ([`crate::calib::magmethod`]).
fn mag_method_evidence(
    run: &Run,
    cfg: &Config,
    units: crate::types::CalUnits,
) -> crate::calib::magmethod::Evidence {
    let pipe = &run.pipe;
    let body = |s: &crate::types::Sample| pipe.to_body(s);
    let body_mag = |s: &crate::types::Sample| pipe.mag_in_body(s);
    crate::calib::magmethod::Evidence::gather(
        &run.log.samples,
        &body,
        &body_mag,
        run.log.place(),
        cfg.place.as_ref(),
        units,
    )
}

/// The primary compass's mounting from the static poses ([`crate::calib::mounting`]), into
/// `calibration.mag.mounting`; a mounting clearly other than `orientation.sensor` refuses the
/// calibration (failure `orientation`) and names the parameter to set. The readings are
/// corrected with the calibration's offset and its soft iron without rotation, and turned back
/// into the compass's axes.
fn mounting_check(
    results: &mut FitResults,
    log: &crate::io::sources::Log,
    pipe: &Pipeline,
    cfg: &Config,
) {
    let index = log
        .instances
        .iter()
        .find(|i| log.instance.as_deref() == Some(i.name.as_str()))
        .map_or(0, |i| i.compass_id as usize);
    let accel = results.accel.calibration;
    check_mounting(
        &mut results.mag,
        accel.as_ref(),
        &log.samples,
        log,
        pipe,
        cfg,
        index,
    );
}

/// [`mounting_check`] of one compass: its result, its instance's accelerometer calibration and
/// samples, its pipeline, and its compass number.
fn check_mounting(
    mag: &mut crate::calib::outcome::SensorResult,
    accel: Option<&crate::calib::model::Calibration>,
    samples: &[crate::types::Sample],
    log: &crate::io::sources::Log,
    pipe: &Pipeline,
    cfg: &Config,
    index: usize,
) {
    let poses = pipe.poses();
    // The attitude nearest each pose's middle (samples and poses both in arrival order).
    let mut att: Vec<Option<(f64, [f64; 4])>> = vec![None; poses.len()];
    let mut k = 0;
    for s in samples {
        while k < poses.len()
            && (s.segment > poses[k].segment
                || (s.segment == poses[k].segment && s.t_s > poses[k].t_end))
        {
            k += 1;
        }
        let (Some(p), Some(q)) = (poses.get(k), s.ref_q) else {
            continue;
        };
        if s.segment == p.segment && s.t_s >= p.t_start {
            let d = (s.t_s - 0.5 * (p.t_start + p.t_end)).abs();
            if att[k].is_none_or(|(best, _)| d < best) {
                att[k] = Some((d, q));
            }
        }
    }
    let att: Vec<_> = att
        .iter()
        .map(|a| a.and_then(|(_, q)| crate::attitude::body_ned_of_ref_q(q)))
        .collect();
    let field = crate::calib::magmethod::earth_field_of(samples, log.place(), cfg.place.as_ref());
    mag.check_mounting(
        accel,
        poses,
        &att,
        field.as_ref(),
        &cfg.orientation.sensor,
        index,
    );
}

/// Every further compass gets the primary's methods: the vector (or planar) fit when its samples
/// carry the vehicle's attitude and the place is known, with its own mounting check. `None` where
/// an instance has no pipeline.
fn other_mag_methods(
    run: &mut Run,
    cfg: &Config,
    judged: &[CompassJudged],
) -> Vec<Option<crate::calib::outcome::SensorResult>> {
    let log = &run.log;
    let mut out = Vec::with_capacity(run.others.len());
    for (k, p) in run.others.iter_mut().enumerate() {
        let Some(p) = p.as_mut() else {
            out.push(None);
            continue;
        };
        let results = p.finish().clone();
        let mut mag = results.mag;
        let sphere = crate::calib::magmethod::sphere_words(&mag);
        let samples = run.other_samples.get(k).map_or(&[][..], |v| &v[..]);
        let p = &*p;
        crate::calib::magmethod::choose(
            &mut mag,
            samples,
            &|s| p.to_body(s),
            log.place(),
            cfg.place.as_ref(),
        );
        if let Some(j) = judged.iter().find(|j| j.other == Some(k)) {
            install_rung(&mut mag, &j.judged, &sphere);
        }
        let index = log.instances.get(k).map_or(k, |i| i.compass_id as usize);
        let accel = results.accel.calibration;
        check_mounting(&mut mag, accel.as_ref(), samples, log, p, cfg, index);
        out.push(Some(mag));
    }
    out
}

/// A log run through the pipelines: the primary's, the other instances' and the decoded log (with
/// the primary's samples).
struct Run {
    pipe: Pipeline,
    /// The other IMU instances of a log, each through a pipeline of its own.
    others: Vec<Option<Pipeline>>,
    /// Their samples as kept ([`Thinned`]), by the same index.
    other_samples: Vec<Vec<crate::types::Sample>>,
    /// Samples seen of every instance, and held.
    seen: u64,
    held: usize,
    largest: usize,
    /// The primary's samples were all held ([`Thinned::whole`]).
    whole: bool,
    /// The rates of the primary's rotations between static poses, for the gyro scale when the
    /// samples were not all held.
    span_rates: SpanRates,
    /// The primary's samples seen, and the time they span, s.
    primary_seen: u64,
    duration_s: f64,
    /// Their magnetometer results after the method choice and mounting check
    /// ([`other_mag_methods`]), by the same index.
    other_mags: Vec<Option<crate::calib::outcome::SensorResult>>,
    log: crate::io::sources::Log,
}

impl Run {
    fn kept(&self, gyro_span_samples: usize) -> Kept {
        Kept {
            seen: self.seen,
            held: self.held,
            largest: self.largest,
            cap: KEPT_SAMPLES_MAX,
            gyro_span_samples,
        }
    }
}

/// The pipeline thread's time on the batches it was handed, and their samples: what the decoding
/// thread weighs its own against ([`Split`]).
#[derive(Default)]
struct Handover {
    busy_ns: std::sync::atomic::AtomicU64,
    samples: std::sync::atomic::AtomicU64,
}

impl Handover {
    fn add(&self, busy: std::time::Duration, samples: usize) {
        use std::sync::atomic::Ordering::Relaxed;
        self.busy_ns.fetch_add(busy.as_nanos() as u64, Relaxed);
        self.samples.fetch_add(samples as u64, Relaxed);
    }

    /// Nanoseconds per sample, once a batch was taken.
    fn per_sample_ns(&self) -> Option<f64> {
        use std::sync::atomic::Ordering::Relaxed;
        let n = self.samples.load(Relaxed);
        (n > 0).then(|| self.busy_ns.load(Relaxed) as f64 / n as f64)
    }
}

/// Which thread keeps the primary's record ([`Thinned`]): the decoding thread from the start,
/// until the share of the log that leaves both threads about as busy (decoding and keeping on
/// one, the pipeline on the other, each timed per sample over the first [`Split::LEARN`]
/// batches); then it goes to the pipeline thread with the batch it was last given. Where it is
/// kept changes nothing in it: each sample is pushed once, in order.
#[derive(Default)]
struct Split {
    /// When the last batch was handed on: what follows until the next is decoding.
    sent: Option<std::time::Instant>,
    decode_ns: u64,
    decoded: u64,
    keep_ns: u64,
    kept: u64,
    batches: u32,
    seen: u64,
    /// Samples after which the record goes to the pipeline thread, once worked out.
    at: Option<u64>,
}

impl Split {
    const LEARN: u32 = 4;

    /// Batch `b`'s samples into the record `kept` while this thread has it; the record when it
    /// is to go with `b` to the pipeline thread (`busy`: its time so far).
    fn batch(
        &mut self,
        b: &crate::io::sources::Batch,
        kept: &mut Option<Thinned>,
        busy: &Handover,
    ) -> Option<Thinned> {
        let now = std::time::Instant::now();
        let n = b.samples.len() as u64;
        self.seen += n;
        if let Some(sent) = self.sent {
            self.decode_ns += (now - sent).as_nanos() as u64;
            self.decoded += n;
        }
        let record = kept.as_mut()?;
        for s in &b.samples {
            record.push(s);
        }
        self.keep_ns += now.elapsed().as_nanos() as u64;
        self.kept += n;
        self.batches += 1;
        if self.at.is_none() && self.batches >= Self::LEARN && self.decoded > 0 && self.kept > 0 {
            if let Some(p) = busy.per_sample_ns() {
                let d = self.decode_ns as f64 / self.decoded as f64;
                let k = self.keep_ns as f64 / self.kept as f64;
                // The share f of the log kept here that makes d + f k = p + (1 - f) k.
                let f = if k > 0.0 {
                    ((p + k - d) / (2.0 * k)).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let total = self.seen as f64 * b.bytes_total as f64 / b.bytes_read.max(1) as f64;
                self.at = Some((f * total) as u64);
            }
        }
        if self.at.is_some_and(|at| self.seen >= at) {
            kept.take()
        } else {
            None
        }
    }

    /// A batch was handed on.
    fn sent(&mut self) {
        self.sent = Some(std::time::Instant::now());
    }
}

/// Read the log at `path` as a stream and push every sample through its instance's pipeline,
/// keeping a bounded, thinned record of each instance's samples ([`Thinned`]).
fn run_pipelines(
    path: &Path,
    cfg: &Config,
    opts: &ReplayOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<Run, Error> {
    let mut pipe = Pipeline::new(&cfg.calib())?;
    // Decoding runs on its own thread and hands samples on in batches over a bounded channel, so
    // the pipeline works on one batch while the next is decoded. The samples reach the pipeline in
    // the same order as from a whole-file decode, so the result is the same. The primary's record
    // ([`Thinned`]) is kept by the decoding thread at first and handed on with a batch to this one
    // where that shares the work evenly ([`Handover`]); either keeps the same record.
    let mut span_rates = SpanRates::default();
    // The rates in body axes of the primary's samples while the log may still be kept whole,
    // for the rotations of a longer one ([`SpanRates::start`]).
    let mut rates: Vec<crate::calib::gyro::Rate> = Vec::new();
    let mut primary_seen: u64 = 0;
    let mut others: Vec<Option<Pipeline>> = Vec::new();
    let mut other_samples: Vec<Thinned> = Vec::new();
    let mut kept_here: Option<Thinned> = None;
    let pipeline_busy = Handover::default();
    let (decoded, kept_there) = std::thread::scope(|scope| {
        type Handed = (crate::io::sources::Batch, Option<Thinned>);
        let (tx, rx) = std::sync::mpsc::sync_channel::<Handed>(4);
        let busy = &pipeline_busy;
        let decoder = scope.spawn(move || {
            let mut samples = Some(Thinned::default());
            let mut split = Split::default();
            let decoded =
                crate::io::sources::decode_file_batched(path, opts.format, &cfg.input, &mut |b| {
                    let handed = split.batch(&b, &mut samples, busy);
                    // The receiver only goes away on a panic; nothing then to hand on to.
                    let _ = tx.send((b, handed));
                    split.sent();
                });
            (decoded, samples)
        });
        let mut first = true;
        for (batch, handed) in rx {
            let started = std::time::Instant::now();
            if first {
                pipe.mag_units = batch.units.mag;
                pipe.gyro_units = batch.units.gyro;
                first = false;
            }
            for s in &batch.samples {
                if pipe.push(s) && opts.refits {
                    pipe.refit();
                }
                if primary_seen < KEPT_SAMPLES_MAX as u64 {
                    if rates.capacity() == 0 {
                        // Room for as many as there may be, taken up only as they come.
                        rates.reserve_exact(GYRO_SPAN_SAMPLES_MAX);
                    }
                    rates.push(pipe.rate_in_body(s));
                } else if primary_seen == KEPT_SAMPLES_MAX as u64 {
                    // Too long to keep whole from here on.
                    span_rates.start(std::mem::take(&mut rates), &pipe);
                }
                span_rates.push(s, &pipe);
                primary_seen += 1;
            }
            if let Some(kept) = kept_here.as_mut() {
                for s in &batch.samples {
                    kept.push(s);
                }
            }
            if handed.is_some() {
                kept_here = handed;
            }
            for &(k, ref s) in &batch.others {
                if let Some(p) = other_pipeline(&mut others, k, &batch, cfg) {
                    if p.push(s) && opts.refits {
                        p.refit();
                    }
                    if other_samples.len() <= k {
                        other_samples.resize_with(k + 1, Thinned::default);
                    }
                    other_samples[k].push(s);
                }
            }
            progress(batch.bytes_read as u64, batch.bytes_total as u64);
            pipeline_busy.add(started.elapsed(), batch.samples.len());
        }
        joined(decoder)
    });
    let Some(samples) = kept_there.or(kept_here) else {
        unreachable!("the record is on one thread or the other")
    };
    drop(rates);
    let mut log = decoded?;
    let all = std::iter::once(&samples).chain(&other_samples);
    let seen = all.clone().map(|t| t.seen).sum();
    let held = all.clone().map(|t| t.samples.len()).sum();
    let largest = all.map(|t| t.samples.len()).max().unwrap_or(0);
    let (whole, primary_seen, duration_s) = (samples.whole(), samples.seen, samples.duration_s());
    log.samples = samples.samples;
    Ok(Run {
        pipe,
        others,
        other_samples: other_samples.into_iter().map(|t| t.samples).collect(),
        other_mags: Vec::new(),
        log,
        seen,
        held,
        largest,
        whole,
        span_rates,
        primary_seen,
        duration_s,
    })
}

/// The report of a run: input, calibrations, the other instances and the onboard comparison.
fn full_report(
    path: &Path,
    run: &mut Run,
    results: &FitResults,
    declination: Option<f64>,
) -> Report {
    let log = &run.log;
    let input = InputReport::new(
        log.format.name(),
        Some(path.display().to_string()),
        log.instance.clone(),
        &log.stats,
        run.primary_seen,
        run.duration_s,
    );
    let mut report = make_report(input, &run.pipe, results, declination);
    report.instances = instance_reports(log, &report, &mut run.others, &run.other_mags);
    if let Some(f) = &log.flight {
        report.input.sensors = f.sensors.clone();
        let mut onboard = f.onboard.clone();
        onboard.comparison = onboard_comparison(f, &onboard, &log.samples, &run.pipe, results);
        report.onboard = Some(onboard);
    } else {
        report.onboard = log.telemetry_onboard.clone();
    }
    report
}

/// What the calibrated CSV is made with.
struct CalibratedOut<'a> {
    pipe: &'a Pipeline,
    results: &'a FitResults,
    cfg: &'a Config,
    declination: Option<f64>,
}

/// The calibrated samples as CSV at `p`, with the attitude from them and the fused attitude: the
/// log at `log_path` read again as a stream, a row written per sample as it comes.
fn write_calibrated(
    p: &Path,
    log_path: &Path,
    opts: &ReplayOptions,
    out: &CalibratedOut<'_>,
) -> Result<(), Error> {
    let mut decoded = Ok(());
    crate::io::publish::write_atomic_with(p, |file| {
        let mut csv = csv::Writer::from_writer(std::io::BufWriter::new(file));
        csv.write_record(CALIBRATED_COLUMNS)?;
        let mut rows = CalibratedRows::new(out);
        let mut failed: Option<csv::Error> = None;
        let r = crate::io::sources::decode_file_batched(
            log_path,
            opts.format,
            &out.cfg.input,
            &mut |b| {
                if failed.is_none() {
                    failed = rows.take(&mut csv, &b.samples).err();
                }
            },
        );
        if let Some(e) = failed {
            return Err(e.into());
        }
        rows.finish(&mut csv)?;
        csv.flush()?;
        decoded = r.map(|_| ());
        Ok(())
    })?;
    decoded
}

/// Samples the step of the fused attitude is found from ([`crate::attitude::fusion::median_dt`]
/// looks at the first 2000 steps).
const STEP_SAMPLES: usize = 2001;

/// The rows of the calibrated CSV, made sample by sample.
struct CalibratedRows<'a> {
    pipe: &'a Pipeline,
    cal: Calibrator,
    /// The gyro scale and the fused attitude's filter, when the gyro is in rad/s or scaled.
    filter: Option<(
        nalgebra::Matrix3<f64>,
        crate::attitude::fusion::OrientationFilter,
    )>,
    /// The first samples, held until the step is known from them.
    pending: Vec<crate::types::Sample>,
    dt: Option<f64>,
}

impl<'a> CalibratedRows<'a> {
    fn new(out: &CalibratedOut<'a>) -> Self {
        let results = out.results;
        // The fused attitude (gyro + accel + mag filter, body FRD -> NED, true north when the place
        // is known): needs the gyro in rad/s, so a raw-count gyro needs its scale fit.
        let gyro_k = match (&results.gyro.scale, results.gyro.units) {
            (Some(k), _) => Some(crate::calib::model::rows_to_mat(&k.matrix)),
            (None, crate::types::CalUnits::RadS) => Some(nalgebra::Matrix3::identity()),
            _ => None,
        };
        let fcfg = out.cfg.fusion_config(out.declination);
        CalibratedRows {
            pipe: out.pipe,
            cal: Calibrator::new(results, out.declination),
            filter: gyro_k.map(|k| (k, crate::attitude::fusion::OrientationFilter::new(fcfg))),
            pending: Vec::with_capacity(STEP_SAMPLES),
            dt: None,
        }
    }

    /// Rows for `samples`, or hold them while the step is not known.
    fn take<W: std::io::Write>(
        &mut self,
        out: &mut csv::Writer<W>,
        samples: &[crate::types::Sample],
    ) -> Result<(), csv::Error> {
        if let Some(dt) = self.dt {
            return samples.iter().try_for_each(|s| self.row(out, s, dt));
        }
        self.pending.extend_from_slice(samples);
        if self.pending.len() >= STEP_SAMPLES {
            self.finish(out)?;
        }
        Ok(())
    }

    /// Rows for the samples held.
    fn finish<W: std::io::Write>(&mut self, out: &mut csv::Writer<W>) -> Result<(), csv::Error> {
        let pending = std::mem::take(&mut self.pending);
        let dt = *self
            .dt
            .get_or_insert_with(|| crate::attitude::fusion::median_dt(&pending));
        pending.iter().try_for_each(|s| self.row(out, s, dt))
    }

    fn row<W: std::io::Write>(
        &mut self,
        out: &mut csv::Writer<W>,
        s: &crate::types::Sample,
        dt: f64,
    ) -> Result<(), csv::Error> {
        let mut c = self.cal.apply(&self.pipe.to_body(s));
        let mut fused = None;
        if let Some((k, f)) = self.filter.as_mut() {
            c.gyro_rad_s = c.gyro_rad_s.map(|g| {
                let w = *k * nalgebra::Vector3::new(g[0], g[1], g[2]);
                [w.x, w.y, w.z]
            });
            f.update_sample(&c.as_sample(), dt);
            fused = f.initialized().then(|| f.orientation());
        }
        write_row(out, &c, fused.as_ref(), s.ref_q)
    }
}

/// ArduPilot, PX4 and Fusion parameter files in `dir`: every compass of the log under its own
/// index (COMPASS_OFS2, CAL_MAG1 ...).
fn write_exports(
    dir: &Path,
    report: &Report,
    results: &FitResults,
    export_all: bool,
) -> Result<Vec<PathBuf>, Error> {
    let a = results.accel.calibration.as_ref();
    let primary_id = report
        .instances
        .iter()
        .find(|i| i.primary)
        .map_or(0, |i| i.compass_id);
    // The vehicle's own compass parameters as the log carries them, by name.
    let vehicle = |k: u8| {
        report
            .onboard
            .iter()
            .flat_map(|o| &o.mag)
            .filter(|c| c.instance == k)
            .flat_map(|c| c.params.clone())
            .collect()
    };
    let export = |instance: &str,
                  k: u8,
                  rep: &crate::report::SensorCalibration,
                  cal: Option<&crate::calib::model::Calibration>| {
        cal.filter(|_| rep.units == crate::types::CalUnits::Ut)
            .map(|c| crate::calib::export::CompassExport {
                index: k as usize,
                cal: *c,
                unknown: rep.unknowns(),
                vehicle: vehicle(k),
                withheld: load::withheld(report, instance, export_all),
            })
    };
    let mut mags: Vec<crate::calib::export::CompassExport> = export(
        &load::primary_instance(report),
        primary_id,
        &report.calibration.mag,
        results.mag.calibration.as_ref(),
    )
    .into_iter()
    .collect();
    for i in report.instances.iter().filter(|i| !i.primary) {
        let m = &i.calibration.mag;
        mags.extend(export(
            &i.instance,
            i.compass_id,
            m,
            m.calibration_ut().as_ref(),
        ));
    }
    let m = mags.first().filter(|c| c.index == primary_id as usize);
    // A compass refused for its mounting: the mounting to set, in place of a calibration.
    let mut records = vec![(primary_id, &report.calibration.mag)];
    for i in report.instances.iter().filter(|i| !i.primary) {
        records.push((i.compass_id, &i.calibration.mag));
    }
    let mountings: Vec<crate::calib::export::MountingFix> = records
        .into_iter()
        .filter(|(_, rep)| rep.failure == Some(crate::calib::fit::FitFailure::Orientation))
        .filter_map(|(k, rep)| match &rep.mounting.as_ref()?.verdict {
            crate::calib::mounting::Verdict::Differs { set } => {
                Some(crate::calib::export::MountingFix {
                    index: k as usize,
                    found: set.mounting.clone(),
                    vehicle: vehicle(k),
                })
            }
            _ => None,
        })
        .collect();
    if mags.is_empty() && mountings.is_empty() && a.is_none() {
        // Nothing passed: no file (nor folder) rather than an empty one a user might load.
        return Ok(vec![]);
    }
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    // Fusion takes one compass, the primary, and only as a value to load.
    let m = m.filter(|c| c.withheld.is_none());
    let motors: Vec<(usize, crate::types::Vec3)> = report
        .calibration
        .mag
        .motor_ut_per_a()
        .map(|k| (primary_id as usize, k))
        .into_iter()
        .collect();
    let mut written = vec![];
    for (name, text) in [
        (
            "ardupilot.parm",
            crate::calib::export::ardupilot_file(&mags, &mountings, &motors, a),
        ),
        (
            "px4.params",
            crate::calib::export::px4_file(&mags, &mountings, &motors, a),
        ),
        ("fusion.h", crate::calib::export::fusion_file(m, a)),
    ] {
        let p = dir.join(name);
        crate::io::publish::write_atomic(&p, text.as_bytes())?;
        written.push(p);
    }
    Ok(written)
}

/// imucald's primary magnetometer calibration against the onboard one of the same compass: the
/// offsets, and the headings the two give for the same raw readings at the flight controller's
/// roll and pitch. `None` unless imucald's fit passed and the compass has an onboard calibration.
fn onboard_comparison(
    f: &crate::io::flightlog::FlightLog,
    onboard: &crate::report::OnboardReport,
    samples: &[crate::types::Sample],
    pipe: &Pipeline,
    results: &FitResults,
) -> Option<crate::report::OnboardComparison> {
    let ours = results.mag.calibration.as_ref()?;
    let source = f.primary_mag_source.clone()?;
    let slot = onboard.mag.iter().find(|c| c.sources.contains(&source))?;
    let theirs = crate::calib::model::Calibration {
        model: crate::calib::model::ModelKind::Full12,
        offset: slot.offset,
        matrix: slot.matrix,
    };
    let (mut sq, mut max, mut n) = (0.0, 0.0f64, 0usize);
    for s in samples {
        let (Some(m), Some(q)) = (pipe.mag_in_body(s), s.ref_q) else {
            continue;
        };
        let Some((roll, pitch)) = crate::io::flightlog::roll_pitch_of_ref_q(q) else {
            continue;
        };
        let a = crate::attitude::heading_deg(&ours.apply(&m), roll, pitch);
        let b = crate::attitude::heading_deg(&theirs.apply(&m), roll, pitch);
        let d = crate::attitude::angle_diff_deg(a, b);
        if d.is_finite() {
            sq += d * d;
            max = max.max(d.abs());
            n += 1;
        }
    }
    Some(crate::report::OnboardComparison {
        instance: slot.instance,
        source,
        offset_diff_ut: [0, 1, 2].map(|i| ours.offset[i] - slot.offset[i]),
        heading_diff_rms_deg: if n > 0 { (sq / n as f64).sqrt() } else { 0.0 },
        heading_diff_max_deg: max,
        samples: n,
    })
}

/// The pipeline of instance `k` (not the primary), made on its first sample with the instance's
/// units; `None` when it cannot be (a configuration the primary's pipeline took, so not here).
fn other_pipeline<'a>(
    pipes: &'a mut Vec<Option<Pipeline>>,
    k: usize,
    batch: &crate::io::sources::Batch,
    cfg: &Config,
) -> Option<&'a mut Pipeline> {
    if pipes.len() <= k {
        pipes.resize_with(k + 1, || None);
    }
    if pipes[k].is_none() {
        let mut p = Pipeline::new(&cfg.calib()).ok()?;
        if let Some(i) = batch.instances.get(k) {
            p.mag_units = i.units.mag;
            p.gyro_units = i.units.gyro;
        }
        pipes[k] = Some(p);
    }
    pipes[k].as_mut()
}

/// A block per IMU instance of the log: the primary's is the report's own calibration, the
/// others' come from their pipelines. Empty when the log has one instance or none.
fn instance_reports(
    log: &crate::io::sources::Log,
    report: &Report,
    others: &mut [Option<Pipeline>],
    other_mags: &[Option<crate::calib::outcome::SensorResult>],
) -> Vec<crate::report::InstanceReport> {
    if log.instances.len() < 2 {
        return Vec::new();
    }
    let primary = log.instance.as_deref();
    log.instances
        .iter()
        .enumerate()
        .filter_map(|(k, i)| {
            let is_primary = primary == Some(i.name.as_str());
            let calibration = if is_primary {
                report.calibration.clone()
            } else {
                let r = others.get_mut(k)?.as_mut()?.finish();
                let mut mag = match other_mags.get(k) {
                    Some(Some(m)) => m.report.clone(),
                    _ => r.mag.report.clone(),
                };
                if let Some(f) = &log.flight {
                    explain_instance_mag(f, i, &mut mag, report.input.duration_s);
                }
                CalibrationReport {
                    mag,
                    accel: r.accel.report.clone(),
                    gyro: r.gyro.clone(),
                }
            };
            Some(crate::report::InstanceReport {
                instance: i.name.clone(),
                compass_id: i.compass_id,
                primary: is_primary,
                samples: i.samples,
                time: i.time.clone(),
                calibration,
            })
        })
        .collect()
}

/// A further instance of a flight-controller log whose magnetometer fit failed: the evidence
/// when the reason is the log's, not the data's. An instance with no magnetometer readings says
/// so; one whose compass is the primary's (the same onboard calibration slot: PX4 logs the raw
/// `sensor_mag` of the compass whose corrected `vehicle_magnetometer` the primary takes) names
/// the rate it was logged at and where that compass is calibrated instead.
fn explain_instance_mag(
    f: &crate::io::flightlog::FlightLog,
    inst: &crate::io::decode::InstanceInfo,
    mag: &mut crate::report::SensorCalibration,
    duration_s: f64,
) {
    if mag.status != CalStatus::Failed {
        return;
    }
    let mine = f.sensors.iter().find(|s| {
        s.sensor == crate::types::Sensor::Mag
            && s.instance == inst.compass_id
            && inst.name.contains(s.source.as_str())
    });
    let Some(stream) = mine else {
        mag.detail = Some(format!(
            "no magnetometer: the log has no compass readings for {} (its accelerometer and gyro only)",
            inst.name
        ));
        return;
    };
    let Some(primary) = f.primary_mag_source.as_deref() else {
        return;
    };
    let shared = f.onboard.mag.iter().any(|slot| {
        slot.sources.iter().any(|s| s == &stream.source)
            && slot.sources.iter().any(|s| s == primary)
    });
    if !shared {
        return;
    }
    let primary_n = f
        .sensors
        .iter()
        .find(|s| s.sensor == crate::types::Sensor::Mag && s.source == primary)
        .map_or(0, |s| s.samples);
    let rate = if duration_s > 0.0 {
        stream.samples as f64 / duration_s
    } else {
        0.0
    };
    let was = mag.detail.take().unwrap_or_default();
    mag.detail = Some(format!(
        "{was}: {} is logged at {rate:.1} Hz ({} readings over {duration_s:.0} s); it is the primary's compass{}, calibrated above from {primary} ({primary_n} readings)",
        stream.source,
        stream.samples,
        stream
            .device_id
            .map_or(String::new(), |d| format!(" (device id {d})")),
    ));
}

/// The report for a pipeline's current state.
pub(crate) fn make_report(
    input: InputReport,
    pipe: &Pipeline,
    results: &FitResults,
    declination_deg: Option<f64>,
) -> Report {
    Report {
        schema: SCHEMA.into(),
        input,
        static_poses: pipe.poses().iter().map(PoseReport::from).collect(),
        coverage: CoverageReport {
            mag: shown_coverage(&results.mag),
            accel: shown_coverage(&results.accel),
        },
        calibration: CalibrationReport {
            mag: results.mag.report.clone(),
            accel: results.accel.report.clone(),
            gyro: results.gyro.clone(),
        },
        declination_deg,
        refits: pipe.refits.clone(),
        instances: Vec::new(),
        outputs: None,
        vehicles: Vec::new(),
        onboard: None,
        quality: Vec::new(),
        load: Vec::new(),
        temperature: Vec::new(),
    }
}

/// Coverage maps (the (theta, phi) projection of Camps, Harasse and Monin, "Numerical calibration
/// for 3-axis accelerometers and magnetometers" (2009), before and after) and residual plots.
fn write_plots(
    dir: &Path,
    pipe: &Pipeline,
    samples: &[crate::types::Sample],
    r: &FitResults,
) -> Result<Vec<PathBuf>, Error> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut out = vec![];
    for (name, s) in [("mag", &r.mag), ("accel", &r.accel)] {
        if s.dirs_before.is_empty() {
            continue;
        }
        for ext in ["png", "svg"] {
            let p = dir.join(format!("{name}_coverage.{ext}"));
            let title = format!(
                "{name} coverage: {} ({}), before and after calibration",
                s.report.model, s.report.status
            );
            crate::app::plot::coverage_map(
                &p,
                &title,
                &s.dirs_before,
                &s.dirs_after,
                &s.coverage_before.filled_mask,
                &s.coverage_after.filled_mask,
            )?;
            out.push(p);
        }
    }
    // Field-magnitude residual of every magnetometer sample over time, and of every accel pose.
    let (mut tm, mut rm) = (vec![], vec![]);
    if let Some(c) = r.mag.calibration {
        for s in samples {
            if let Some(m) = pipe.mag_in_body(s) {
                tm.push(s.t_s);
                rm.push(crate::types::norm(&c.apply(&m)) - r.mag.report.radius);
            }
        }
    }
    let (mut ta, mut ra) = (vec![], vec![]);
    if let Some(c) = r.accel.calibration {
        for p in pipe.poses() {
            ta.push(0.5 * (p.t_start + p.t_end));
            ra.push(crate::types::norm(&c.apply(&p.accel)) - r.accel.report.radius);
        }
    }
    for (name, t, res, unit) in [
        ("mag", &tm, &rm, r.mag.report.units.name()),
        ("accel", &ta, &ra, "m/s^2"),
    ] {
        if t.is_empty() {
            continue;
        }
        for ext in ["png", "svg"] {
            let p = dir.join(format!("{name}_residuals.{ext}"));
            let label = format!("|calibrated| - radius ({unit})");
            let series_name = if name == "mag" {
                "every sample"
            } else {
                "static poses"
            };
            crate::app::plot::residuals(
                &p,
                &format!("{name} norm residual after calibration"),
                &label,
                &[(series_name, t.as_slice(), res.as_slice())],
            )?;
            out.push(p);
        }
    }
    Ok(out)
}

/// Coverage about the calibrated centre when the fit is good, about the raw sphere centre otherwise;
/// none at all where the readings are not the field the sensor should see (implausible, e.g. a
/// compass whose field does not turn): their directions about a centre of their own are noise,
/// not poses.
fn shown_coverage(r: &crate::calib::outcome::SensorResult) -> crate::calib::coverage::Coverage {
    if r.report.failure == Some(crate::calib::fit::FitFailure::Implausible) {
        return crate::calib::coverage::coverage(&[], &[0.0; 3]);
    }
    if r.calibration.is_some() {
        r.coverage_after.clone()
    } else {
        r.coverage_before.clone()
    }
}

/// The columns of the calibrated CSV (`replay --calibrated-out`).
const CALIBRATED_COLUMNS: [&str; 24] = [
    "t",
    "ax",
    "ay",
    "az",
    "gx",
    "gy",
    "gz",
    "mx",
    "my",
    "mz",
    "roll_deg",
    "pitch_deg",
    "heading_deg",
    "qw",
    "qx",
    "qy",
    "qz",
    "fused_roll_deg",
    "fused_pitch_deg",
    "fused_heading_deg",
    "ref_qw",
    "ref_qx",
    "ref_qy",
    "ref_qz",
];

/// One calibrated sample as a row of [`CALIBRATED_COLUMNS`]: empty cells for what it lacks.
fn write_row<W: std::io::Write>(
    out: &mut csv::Writer<W>,
    c: &Calibrated,
    fused: Option<&crate::attitude::fusion::Orientation>,
    ref_q: Option<[f64; 4]>,
) -> Result<(), csv::Error> {
    let mut cells: [Option<(f64, usize)>; 24] = [None; 24];
    // The input's reference attitude, as it came, so `imucald eval` can score the output.
    if let Some(q) = ref_q {
        for (i, v) in q.into_iter().enumerate() {
            cells[20 + i] = Some((v, 9));
        }
    }
    cells[0] = Some((c.t_s, 6));
    for (k, v) in [c.accel_mps2, c.gyro_rad_s, c.mag_ut].iter().enumerate() {
        for i in 0..3 {
            cells[1 + 3 * k + i] = v.map(|v| (v[i], 6));
        }
    }
    for (i, v) in [c.roll_deg, c.pitch_deg, c.heading_deg].iter().enumerate() {
        cells[10 + i] = v.map(|x| (x, 4));
    }
    if let Some(o) = fused {
        let q = o.q.quaternion();
        for (i, v) in [q.w, q.i, q.j, q.k].into_iter().enumerate() {
            cells[13 + i] = Some((v, 7));
        }
        for (i, v) in [o.roll_deg, o.pitch_deg, o.heading_deg]
            .into_iter()
            .enumerate()
        {
            cells[17 + i] = Some((v, 4));
        }
    }
    let mut text = String::new();
    for cell in cells {
        text.clear();
        if let Some((v, digits)) = cell {
            let _ = write!(text, "{v:.digits$}");
        }
        out.write_field(&text)?;
    }
    out.write_record(None::<&[u8]>)
}

/// A terminal summary of a report.
/// The summary's gyro lines: the bias (from the poses at rest) and the scale, or why none.
fn gyro_lines(g: &crate::report::GyroCalibration, s: &mut String) {
    if g.status == CalStatus::Ok {
        let _ = writeln!(
            s,
            "gyro : bias [{:.5}, {:.5}, {:.5}] {} from {} poses at rest{}",
            g.bias[0],
            g.bias[1],
            g.bias[2],
            g.units,
            g.poses_used,
            if g.poses_turning > 0 {
                format!(" ({} steady but turning, left out)", g.poses_turning)
            } else {
                String::new()
            }
        );
        if let Some(k) = &g.scale {
            let _ = write!(
                s,
                "gyro : scale {:.6} {:.6} {:.6} (rad/s per {}), gravity direction between poses {:.2} -> {:.2} deg over {} rotations",
                k.matrix[0][0], k.matrix[1][1], k.matrix[2][2], g.units, k.rms_before_deg, k.rms_after_deg, k.segments
            );
            if let Some(h) = &k.held_out {
                let _ = write!(
                    s,
                    "; held out {:.2} -> {:.2} deg over {}",
                    h.rms_before_deg, h.rms_after_deg, h.segments
                );
            }
            s.push('\n');
        } else if let Some(f) = &g.scale_failure {
            let _ = writeln!(s, "gyro : no scale fit: {f}");
        }
    } else if g.poses_turning > 0 {
        let _ = writeln!(
            s,
            "gyro : no bias claimed: no rest in this log ({} steady segments turned faster than {} deg/s: a steady turn holds the gyro steady too); set the vehicle down still for a few seconds",
            g.poses_turning,
            crate::calib::gate::REST_MAX_RATE_DEG_S
        );
    } else {
        let _ = writeln!(
            s,
            "gyro : no bias claimed: fewer than 2 static poses with the gyro"
        );
    }
}

/// Whether a replay calibrated nothing: no compass, no accelerometer, no gyro bias, no
/// temperature calibration.
pub fn calibrated_nothing(r: &Report) -> bool {
    sensors_calibrated_nothing(r) && !tempcal::calibrated_any(&r.temperature)
}

/// No compass, no accelerometer, no gyro bias (a temperature calibration aside).
fn sensors_calibrated_nothing(r: &Report) -> bool {
    r.calibration.mag.status != CalStatus::Ok
        && r.calibration.accel.status != CalStatus::Ok
        && r.calibration.gyro.status != CalStatus::Ok
        && r.instances
            .iter()
            .all(|i| i.calibration.mag.status != CalStatus::Ok)
}

/// The line after a replay's summary: what to do next with what it found. `asked_export`: the
/// replay was given `--export` (then `next:` never asks for it).
pub fn next_step(r: &Report, written: &[PathBuf], asked_export: bool) -> String {
    let temperature = tempcal::next_words(&r.temperature, written);
    match temperature {
        Some(t) if sensors_calibrated_nothing(r) => format!("next: {t}"),
        Some(t) => format!("{}; {t}", sensors_next_step(r, written, asked_export)),
        None => sensors_next_step(r, written, asked_export),
    }
}

/// [`next_step`] of the compasses and the accelerometer.
fn sensors_next_step(r: &Report, written: &[PathBuf], asked_export: bool) -> String {
    let exported = |name: &str| {
        written
            .iter()
            .find(|p| p.file_name().is_some_and(|f| f == name))
            .map(|p| p.display().to_string())
    };
    if sensors_calibrated_nothing(r) {
        return "next: nothing passed; each FAILED line above says what the data lacked (most often: turn the vehicle through more directions, or give the log's units), then replay again".into();
    }
    let (load, keep) = load::named(r);
    let not = if keep.is_empty() {
        String::new()
    } else {
        format!("; not {}", keep.join("; "))
    };
    match (exported("ardupilot.parm"), exported("px4.params")) {
        (Some(ap), Some(px)) if load.is_empty() && !r.load.is_empty() => format!(
            "next: keep the vehicle's compasses as they are: no compass here is one to load{not} ({ap} and {px} hold the values as comments)"
        ),
        (Some(ap), Some(px)) => {
            let which = if load.is_empty() {
                String::new()
            } else {
                format!(": {}", load.join(", "))
            };
            format!("next: load {ap} (ArduPilot) or {px} (PX4) on the vehicle{which}{not}")
        }
        _ if asked_export => format!(
            "next: no parameter file was written: no compass or accelerometer calibration passed{not}"
        ),
        _ if load.is_empty() && !r.load.is_empty() => format!(
            "next: keep the vehicle's compasses as they are: no compass here is one to load{not}"
        ),
        _ if !load.is_empty() => format!(
            "next: add --export DIR for the ArduPilot, PX4 and Fusion parameter files of {}, --html FILE for a page of plots",
            load.join(", ")
        ),
        _ => "next: add --export DIR for the ArduPilot, PX4 and Fusion parameter files, --html FILE for a page of plots".into(),
    }
}

pub fn summary(r: &Report) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "input: {} ({}), {} samples over {:.1} s{}",
        r.input.path.as_deref().unwrap_or("-"),
        r.input.format,
        r.input.samples,
        r.input.duration_s,
        r.input
            .instance
            .as_ref()
            .map(|i| format!(", instance {i}"))
            .unwrap_or_default()
    );
    if !r.input.skipped.is_empty() {
        let _ = writeln!(
            s,
            "skipped: {}",
            r.input
                .skipped
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let t = &r.input.time;
    if t.segments > 1 || !t.faults.is_empty() {
        let faults: Vec<String> = t.faults.iter().map(|(k, n)| format!("{k:?} {n}")).collect();
        let _ = writeln!(
            s,
            "time: {} segments ({})",
            t.segments,
            faults.join(", ").to_lowercase()
        );
    }
    for i in r.instances.iter().filter(|i| !i.primary) {
        let m = &i.calibration.mag;
        let what = match m.status {
            CalStatus::Ok => format!(
                "offset [{:.4}, {:.4}, {:.4}] {}, rms residual {:.4}",
                m.offset[0], m.offset[1], m.offset[2], m.units, m.rms_residual
            ),
            CalStatus::Failed => format!("FAILED ({})", m.failure.map_or("?", FitFailure::name)),
        };
        let why = match (&m.status, &m.detail) {
            (CalStatus::Failed, Some(d)) => format!(": {d}"),
            _ => String::new(),
        };
        let a = &i.calibration.accel;
        let accel = match a.status {
            CalStatus::Ok => "ok".to_string(),
            CalStatus::Failed => format!("FAILED ({})", a.failure.map_or("?", FitFailure::name)),
        };
        let _ = writeln!(
            s,
            "instance {} (compass {}): {} samples, mag {what}{why}; accel {accel}",
            i.instance, i.compass_id, i.samples
        );
    }
    let _ = writeln!(s, "static poses: {}", r.static_poses.len());
    let _ = writeln!(
        s,
        "coverage: mag {}/100 regions, accel {}/100",
        r.coverage.mag.filled, r.coverage.accel.filled
    );
    for (name, c) in [("mag", &r.calibration.mag), ("accel", &r.calibration.accel)] {
        if c.status == CalStatus::Ok {
            let unknown = c.unknowns();
            let axis = |k: usize| {
                if unknown.offset[k] {
                    "not determined".to_string()
                } else {
                    format!("{:.4}", c.offset[k])
                }
            };
            let _ = writeln!(
                s,
                "{name:5}: ok, model {}, offset [{}, {}, {}] (+-{:.2e}), radius {:.4} {}, rms residual {:.4} {}, {} points",
                c.model, axis(0), axis(1), axis(2), c.offset_sigma.iter().cloned().fold(0.0, f64::max), c.radius, c.units, c.rms_residual, c.units, c.samples_used
            );
            if unknown.any() {
                let _ =
                    writeln!(
                    s,
                    "{:5}  not determined, so not exported (the vehicle keeps its own): {}{}; {}",
                    "",
                    if unknown.offset[2] { "z offset" } else { "" },
                    if unknown.axis[2] { ", z soft iron (scale, xz, yz)" } else { "" },
                    unknown.why
                );
            }
            if let Some(d) = &c.detail {
                let _ = writeln!(s, "{:5}  ({d})", "");
            }
        } else {
            let _ = writeln!(
                s,
                "{name:5}: FAILED ({}): {}",
                c.failure.map_or("?", FitFailure::name),
                c.detail.as_deref().unwrap_or("")
            );
        }
    }
    if let Some(m) = &r.calibration.mag.method {
        let _ = writeln!(s, "mag method: {} ({})", m.method.name(), m.method_reason);
    }
    for q in &r.quality {
        let _ = writeln!(
            s,
            "quality ({}, fitted on alternate {:.0} s blocks, scored on the others): {}",
            q.instance, q.block_s, q.verdict
        );
    }
    gyro_lines(&r.calibration.gyro, &mut s);
    s += &tempcal::summary_lines(&r.temperature);
    s
}

#[cfg(test)]
mod tests {
    use super::gyro_scale::gyro_scale;
    use super::*;

    /// A log too long to keep whole has its rotations kept as it is read: when they all fit,
    /// the gyro scale from them is the one fitted on every sample of the log, to the last bit,
    /// and the log is read once.
    #[test]
    fn a_long_log_keeps_its_rotations_as_it_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("long.tlog");
        // A tumble at 1 kHz: just too long to keep whole, its 28 rotations within the cap.
        let sc = crate::sim::Scenario::from_toml_str(
            "name = \"tumble\"\nrate_hz = 1000.0\npauses = 30\n",
        )
        .unwrap();
        let sim = crate::sim::simulate(&sc, 5);
        assert!(
            sim.samples.len() > KEPT_SAMPLES_MAX,
            "{}",
            sim.samples.len()
        );
        crate::io::samplelog::write_tlog(&path, &sim.samples, &Default::default()).unwrap();
        let (cfg, opts) = (Config::default(), ReplayOptions::default());
        let mut run = run_pipelines(&path, &cfg, &opts, &mut |_, _| {}).unwrap();
        assert!(!run.whole);
        let input = run.pipe.finish_input();
        run.span_rates.finish(&run.pipe);
        let (accel, gyro) = crate::calib::pipeline::fit_accel_gyro(&input, run.pipe.settings());
        let fits = GyroFits {
            gyro: &gyro,
            accel: &accel,
        };
        // Every sample as read; then the file is not there to be read again.
        let log = crate::io::sources::read_log(&path, None, &cfg.input).unwrap();
        std::fs::remove_file(&path).unwrap();
        let (scale, failure, spans) = gyro_scale_of(&run, fits);
        let every: Vec<_> = log.samples.iter().map(|s| run.pipe.to_body(s)).collect();
        let (scale_all, _) = gyro_scale(&every, run.pipe.poses(), &run.pipe, fits);
        let scale = scale.unwrap_or_else(|| panic!("{failure:?}"));
        assert_eq!(scale.segments, 28);
        assert_eq!(format!("{:?}", Some(scale)), format!("{scale_all:?}"));
        assert!(0 < spans && spans < every.len(), "{spans}");
    }

    /// A log kept whole has only the samples of its rotations turned into body axes for the gyro
    /// scale (none when the sensor's axes are the body's), and the scale is the one fitted on
    /// every sample turned, to the last bit, with the sensor mounted turned and not.
    #[test]
    fn the_gyro_scale_from_the_rotations_alone_is_the_one_from_every_sample() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tumble.tlog");
        let sim = crate::sim::simulate(&crate::sim::Scenario::named("tumble").unwrap(), 3);
        crate::io::samplelog::write_tlog(&path, &sim.samples, &Default::default()).unwrap();
        for orientation in ["ROTATION_NONE", "ROTATION_ROLL_180_YAW_90"] {
            let mut cfg = Config::default();
            cfg.orientation.sensor = orientation.into();
            let opts = ReplayOptions::default();
            let mut run = run_pipelines(&path, &cfg, &opts, &mut |_, _| {}).unwrap();
            assert!(run.whole);
            let input = run.pipe.finish_input();
            let (accel, gyro) = crate::calib::pipeline::fit_accel_gyro(&input, run.pipe.settings());
            let fits = GyroFits {
                gyro: &gyro,
                accel: &accel,
            };
            let (scale, failure, spans) = gyro_scale_of(&run, fits);
            let every: Vec<_> = run
                .log
                .samples
                .iter()
                .map(|s| run.pipe.to_body(s))
                .collect();
            let (scale_all, failure_all) = gyro_scale(&every, run.pipe.poses(), &run.pipe, fits);
            assert!(scale.is_some(), "{orientation}: {failure:?}");
            assert_eq!(
                format!("{scale:?}"),
                format!("{scale_all:?}"),
                "{orientation}"
            );
            assert_eq!(format!("{failure:?}"), format!("{failure_all:?}"));
            assert!(
                0 < spans && spans < every.len(),
                "{spans} of {}",
                every.len()
            );
        }
    }
}
