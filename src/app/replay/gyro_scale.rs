//! The gyro scale of a replay: on the samples kept when they are the whole log, else on the
//! rotations between its static poses read again from the file ([`gyro_spans`]).

use super::{Run, GYRO_SPAN_SAMPLES_MAX};
use crate::app::replay::ReplayOptions;
use crate::calib::pipeline::Pipeline;
use crate::config::Config;
use crate::error::Error;
use crate::report::CalStatus;
use std::path::Path;

/// The gyro scale fitted or why none, and the samples it was fitted on.
pub(super) type GyroScaleOutcome = (
    Option<crate::report::GyroScaleReport>,
    Option<crate::calib::gyro::ScaleFailure>,
    usize,
);

/// The gyro scale ([`gyro_scale`]) of a run: on the samples kept when they are every one, else on
/// the rotations [`gyro_spans`] reads again; with the samples it was fitted on.
pub(super) fn gyro_scale_of(
    path: &Path,
    cfg: &Config,
    opts: &ReplayOptions,
    run: &Run,
    fits: GyroFits<'_>,
) -> Result<GyroScaleOutcome, Error> {
    if fits.gyro.status != CalStatus::Ok {
        return Ok((None, None, 0));
    }
    let pipe = &run.pipe;
    let ((scale, failure), span_samples) = if run.whole {
        // Only the samples from one pose's middle to the next's are integrated
        // ([`crate::calib::gyro::fit_scale`] finds each rotation's by bisection on time), so only
        // those are turned into body axes, or none when the sensor's axes are the body's.
        let poses = pipe.poses();
        let samples = &run.log.samples[..];
        let spans: Vec<std::ops::Range<usize>> = rotation_pairs(poses)
            .map(|i| {
                let (from_s, to_s) = pose_mids(poses, i);
                let i0 = samples.partition_point(|s| s.t_s < from_s);
                i0..samples.partition_point(|s| s.t_s < to_s).max(i0)
            })
            .collect();
        let span_samples = spans.iter().map(|r| r.len()).sum();
        let fitted = if pipe.sensor_is_body() {
            gyro_scale(samples, poses, pipe, fits)
        } else {
            let turned = spans.into_iter().flat_map(|r| &samples[r]);
            let rates: Vec<crate::calib::gyro::Rate> =
                turned.map(|s| (&pipe.to_body(s)).into()).collect();
            gyro_scale(&rates, poses, pipe, fits)
        };
        (fitted, span_samples)
    } else {
        let (rates, poses) = gyro_spans(path, cfg, opts, run)?;
        (gyro_scale(&rates, &poses, pipe, fits), rates.len())
    };
    Ok((scale, failure, span_samples))
}

/// What the gyro scale needs of a run's fits: the gyroscope's bias fit and the accelerometer's.
#[derive(Clone, Copy)]
pub(super) struct GyroFits<'a> {
    pub gyro: &'a crate::calib::outcome::GyroCalibration,
    pub accel: &'a crate::calib::outcome::SensorResult,
}

/// The rotations between consecutive static poses of a log too long to keep whole: every pair
/// of poses that [`crate::calib::gyro::fit_scale`] could use (same time segment, gap at most its
/// `max_gap_s`), or an evenly spread choice of them when their samples would be more than
/// [`GYRO_SPAN_SAMPLES_MAX`]; the samples from one pose's middle to the next's read again from
/// the file, in body axes, each kept as the part the fit reads ([`crate::calib::gyro::Rate`], a
/// quarter of a sample). Each chosen pair comes back as two poses of a time segment of its own
/// (its samples relabelled alike, those of another segment set apart), so the fit integrates
/// within pairs only, as it does on the whole log.
fn gyro_spans(
    path: &Path,
    cfg: &Config,
    opts: &ReplayOptions,
    run: &Run,
) -> Result<(Vec<crate::calib::gyro::Rate>, Vec<crate::calib::gate::Pose>), Error> {
    let poses = run.pipe.poses();
    let pairs: Vec<usize> = rotation_pairs(poses).collect();
    let rate_hz = run.primary_seen as f64 / run.duration_s.max(f64::MIN_POSITIVE);
    let expected: f64 = pairs
        .iter()
        .map(|&i| {
            let (from_s, to_s) = pose_mids(poses, i);
            (to_s - from_s) * rate_hz
        })
        .sum();
    let every = (expected / GYRO_SPAN_SAMPLES_MAX as f64).ceil().max(1.0) as usize;
    // (from, to, time segment) of each chosen rotation, in time order.
    let spans: Vec<(f64, f64, u32)> = pairs
        .iter()
        .step_by(every)
        .map(|&i| {
            let (from_s, to_s) = pose_mids(poses, i);
            (from_s, to_s, poses[i].segment)
        })
        .collect();
    let (mut body, mut k, mut whole) = (Vec::new(), 0usize, spans.len());
    crate::io::sources::decode_file_batched(path, opts.format, &cfg.input, &mut |b| {
        for s in &b.samples {
            while k < spans.len() && s.t_s >= spans[k].1 {
                k += 1;
            }
            if k >= whole || s.t_s < spans[k].0 {
                continue;
            }
            if body.len() >= GYRO_SPAN_SAMPLES_MAX {
                // Full: the rotation under way is left out, and those after it.
                whole = k;
                continue;
            }
            let mut x = crate::calib::gyro::Rate::from(&run.pipe.to_body(s));
            x.segment = if s.segment == spans[k].2 {
                k as u32
            } else {
                u32::MAX
            };
            body.push(x);
        }
    })?;
    let chosen = pairs.iter().step_by(every).take(whole);
    let relabelled = chosen.enumerate().flat_map(|(j, &i)| {
        [&poses[i], &poses[i + 1]].map(|p| crate::calib::gate::Pose {
            segment: j as u32,
            ..*p
        })
    });
    Ok((body, relabelled.collect()))
}

/// The first pose of every pair of consecutive poses that [`crate::calib::gyro::fit_scale`] could
/// use: the same time segment, a gap of at most its `max_gap_s`.
fn rotation_pairs(poses: &[crate::calib::gate::Pose]) -> impl Iterator<Item = usize> + '_ {
    let max_gap_s = crate::calib::gyro::ScaleOptions::default().max_gap_s;
    (1..poses.len())
        .filter(move |&i| {
            let (a, b) = (&poses[i - 1], &poses[i]);
            a.segment == b.segment && b.t_start - a.t_end <= max_gap_s
        })
        .map(|i| i - 1)
}

/// The rotation from pose `i` to pose `i + 1`: from the middle of one to the middle of the other, s.
fn pose_mids(poses: &[crate::calib::gate::Pose], i: usize) -> (f64, f64) {
    let mid = |p: &crate::calib::gate::Pose| 0.5 * (p.t_start + p.t_end);
    (mid(&poses[i]), mid(&poses[i + 1]))
}

/// Gyro scale and misalignment from the rotations between `poses` (see
/// [`crate::calib::gyro::fit_scale`]), `body` the samples in body axes; the bias from all the
/// pipeline's poses. `(None, None)` when the log has no gyro; a refusal says why. Without
/// an accelerometer calibration the rotations are still looked at (with the raw accelerometer
/// directions): about one axis or in one plane only, the scale could not be determined with one.
pub(super) fn gyro_scale(
    body: &[impl crate::calib::gyro::RateReading],
    poses: &[crate::calib::gate::Pose],
    pipe: &Pipeline,
    fits: GyroFits<'_>,
) -> (
    Option<crate::report::GyroScaleReport>,
    Option<crate::calib::gyro::ScaleFailure>,
) {
    if fits.gyro.status != CalStatus::Ok {
        return (None, None);
    }
    let Some(bias) = crate::calib::gyro::bias_from_poses(pipe.poses(), &Default::default()) else {
        return (None, None);
    };
    let opt = crate::calib::gyro::ScaleOptions {
        raw_in_counts: fits.gyro.units == crate::types::CalUnits::Counts,
        ..Default::default()
    };
    let Some(accel) = fits.accel.calibration.as_ref() else {
        let raw = crate::calib::model::Calibration {
            model: crate::calib::model::ModelKind::Sphere,
            offset: [0.0; 3],
            matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let span = crate::calib::gyro::rotation_axes(body, poses, &bias, &raw, &opt);
        let failure = match span.and_then(|(s, n)| s.failure(n)) {
            Some(f) => f,
            None => crate::calib::gyro::ScaleFailure {
                failure: crate::calib::fit::FitFailure::NeedsCalibration,
                detail: "needs an accelerometer calibration (the gravity directions of the poses)"
                    .into(),
                held_out: None,
            },
        };
        return (None, Some(failure));
    };
    match crate::calib::gyro::fit_scale(body, poses, &bias, accel, &opt) {
        Ok(f) => (
            Some(crate::report::GyroScaleReport {
                matrix: f.matrix,
                segments: f.segments,
                rms_before_deg: f.rms_before_deg,
                rms_after_deg: f.rms_after_deg,
                held_out: f.held_out,
                conditioning: f.conditioning,
            }),
            None,
        ),
        Err(e) => (None, Some(e)),
    }
}
