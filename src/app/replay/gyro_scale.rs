//! The gyro scale of a replay: on the samples kept when they are the whole log, else on an
//! evenly spread choice of the rotations between its static poses, kept as the log was read
//! ([`SpanRates`]).

use super::{Run, GYRO_SPAN_SAMPLES_MAX};
use crate::calib::gate::Pose;
use crate::calib::gyro::Rate;
use crate::calib::pipeline::Pipeline;
use crate::report::CalStatus;

/// The gyro scale fitted or why none, and the samples it was fitted on.
pub(super) type GyroScaleOutcome = (
    Option<crate::report::GyroScaleReport>,
    Option<crate::calib::gyro::ScaleFailure>,
    usize,
);

/// The gyro scale ([`gyro_scale`]) of a run: on the samples kept when they are every one, else on
/// the rotations kept as the log was read ([`SpanRates`]); with the samples it was fitted on.
pub(super) fn gyro_scale_of(run: &Run, fits: GyroFits<'_>) -> GyroScaleOutcome {
    if fits.gyro.status != CalStatus::Ok {
        return (None, None, 0);
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
            let rates: Vec<Rate> = turned.map(|s| pipe.rate_in_body(s)).collect();
            gyro_scale(&rates, poses, pipe, fits)
        };
        (fitted, span_samples)
    } else {
        let (rates, poses) = run.span_rates.rotations();
        (gyro_scale(rates, &poses, pipe, fits), rates.len())
    };
    (scale, failure, span_samples)
}

/// What the gyro scale needs of a run's fits: the gyroscope's bias fit and the accelerometer's.
#[derive(Clone, Copy)]
pub(super) struct GyroFits<'a> {
    pub gyro: &'a crate::calib::outcome::GyroCalibration,
    pub accel: &'a crate::calib::outcome::SensorResult,
}

/// Most rates [`SpanRates`] holds of the rotation under way, as many as it keeps in all: a
/// longer rotation (or one that starts before the first pose is found this long after it) is
/// not kept.
const PENDING_RATES_MAX: usize = GYRO_SPAN_SAMPLES_MAX;

/// The rotations between the static poses of a log too long to keep whole, kept as it is read
/// for its gyro scale, so that it is read once: every `stride`-th rotation that
/// [`crate::calib::gyro::fit_scale`] could use ([`rotation_pairs`]), counted from the start of
/// the log, with its two poses and its rates in body axes (each the part of a sample the fit
/// reads, [`Rate`], a quarter of it). When they would be more than [`GYRO_SPAN_SAMPLES_MAX`]
/// rates the stride doubles and every other rotation kept is let go, so the choice stays evenly
/// spread over the log, as the samples kept are ([`super::Thinned`]).
///
/// It starts when the log outgrows what is kept of it whole ([`SpanRates::start`], from the
/// samples kept until then); a rotation is kept when the pipeline finds its second pose.
#[derive(Default)]
pub(super) struct SpanRates {
    started: bool,
    /// Rates from the middle of the newest pose on (from the first sample, before the first
    /// pose): the rotation under way, at most [`PENDING_RATES_MAX`].
    pending: std::collections::VecDeque<Rate>,
    /// The time of the latest rate let go from `pending` for room, s: a rotation that starts at
    /// or before it is not kept.
    dropped_until_s: Option<f64>,
    /// The newest pose the pipeline had.
    newest: Option<Pose>,
    /// Rotations seen, kept or not, and the stride of those kept.
    seen: u64,
    stride: u64,
    /// The rotations kept: the index of each in the log, its two poses and its rates in
    /// `rates`, at most [`GYRO_SPAN_SAMPLES_MAX`] of them. After [`SpanRates::finish`], each
    /// rotation's rates and poses are in a time segment of their own ([`SpanRates::rotations`]).
    kept: Vec<(u64, [Pose; 2], std::ops::Range<usize>)>,
    rates: Vec<Rate>,
}

impl SpanRates {
    /// Start with `held`, the rate in body axes of every sample of the log until now
    /// ([`Pipeline::rate_in_body`]), at most [`GYRO_SPAN_SAMPLES_MAX`], and the poses `pipe` found
    /// in them: the rotations between those poses, and the rates from the middle of the newest on.
    /// Every rotation of them is kept (they are no more rates than are kept), each moved up in
    /// `held`, which then holds the rates kept.
    pub(super) fn start(&mut self, mut held: Vec<Rate>, pipe: &Pipeline) {
        assert!(held.len() <= GYRO_SPAN_SAMPLES_MAX);
        self.started = true;
        self.stride = 1;
        let poses = pipe.poses();
        let index = |held: &[Rate], t_s: f64| held.partition_point(|x| x.t_s < t_s);
        self.newest = poses.last().copied();
        let from = index(
            &held,
            self.newest.as_ref().map_or(f64::NEG_INFINITY, pose_mid),
        );
        let room = held.len().saturating_sub(PENDING_RATES_MAX);
        if room > from {
            self.dropped_until_s = Some(held[room - 1].t_s);
        }
        self.pending = held[from.max(room)..].iter().copied().collect();
        // The rotations in time order, each after the one before: each is moved up to where the
        // one before ends.
        let mut at = 0;
        for i in rotation_pairs(poses) {
            let (from_s, to_s) = pose_mids(poses, i);
            let span = index(&held, from_s)..index(&held, to_s);
            let n = span.len();
            self.kept
                .push((self.seen, [poses[i], poses[i + 1]], at..at + n));
            self.seen += 1;
            held.copy_within(span, at);
            at += n;
        }
        held.truncate(at);
        // Room for all the rates kept, taken up only as they come.
        held.reserve_exact(GYRO_SPAN_SAMPLES_MAX - at);
        self.rates = held;
    }

    /// Take a sample the pipeline `pipe` was just given (once started), and the rotation that
    /// ends when it found a new pose with it.
    pub(super) fn push(&mut self, s: &crate::types::Sample, pipe: &Pipeline) {
        if !self.started {
            return;
        }
        if self.pending.len() >= PENDING_RATES_MAX {
            if let Some(r) = self.pending.pop_front() {
                self.dropped_until_s = Some(r.t_s);
            }
        }
        self.pending.push_back(pipe.rate_in_body(s));
        self.look_at_poses(pipe);
    }

    /// After the last sample: the rotation ended by the pose `pipe` found when the log ended, if
    /// any, then each rotation's rates and poses put in a time segment of their own
    /// ([`SpanRates::rotations`]).
    pub(super) fn finish(&mut self, pipe: &Pipeline) {
        if !self.started {
            return;
        }
        self.look_at_poses(pipe);
        self.pending = Default::default();
        for (k, (_, poses, range)) in self.kept.iter_mut().enumerate() {
            let segment = poses[0].segment;
            for r in &mut self.rates[range.clone()] {
                r.segment = if r.segment == segment {
                    k as u32
                } else {
                    u32::MAX
                };
            }
            for p in poses.iter_mut() {
                p.segment = k as u32;
            }
        }
    }

    /// When `pipe` has a new pose: the rotation from the one before to it, then on from it.
    fn look_at_poses(&mut self, pipe: &Pipeline) {
        let Some(&pose) = pipe.poses().last() else {
            return;
        };
        if self.newest.is_some_and(|n| same_pose(&n, &pose)) {
            return;
        }
        if let Some(prev) = self.newest.filter(|n| is_rotation_pair(n, &pose)) {
            let (from_s, to_s) = (pose_mid(&prev), pose_mid(&pose));
            let i0 = self.pending.partition_point(|r| r.t_s < from_s);
            let i1 = self.pending.partition_point(|r| r.t_s < to_s).max(i0);
            // Some of its rates let go for room: not kept, but counted.
            let whole = !self.dropped_until_s.is_some_and(|d| from_s <= d);
            if self.room_for([prev, pose], if whole { i1 - i0 } else { usize::MAX }) {
                self.rates.extend(self.pending.range(i0..i1).copied());
            }
        }
        // What comes before the middle of the newest pose is in no rotation still to come.
        let to_s = pose_mid(&pose);
        let done = self.pending.partition_point(|r| r.t_s < to_s);
        self.pending.drain(..done);
        self.newest = Some(pose);
    }

    /// The next rotation of the log, from pose `poses[0]` to `poses[1]`, with `n` rates: true
    /// when it is to be kept (its turn, and room for it once the stride has doubled as often as
    /// needed), its entry made; its `n` rates are then to be appended to `rates`.
    fn room_for(&mut self, poses: [Pose; 2], n: usize) -> bool {
        let index = self.seen;
        self.seen += 1;
        if n > GYRO_SPAN_SAMPLES_MAX {
            return false;
        }
        loop {
            if !index.is_multiple_of(self.stride) {
                return false;
            }
            if self.rates.len() + n <= GYRO_SPAN_SAMPLES_MAX {
                let at = self.rates.len();
                self.kept.push((index, poses, at..at + n));
                return true;
            }
            self.double_stride();
        }
    }

    /// Every other rotation kept let go (those off the doubled stride), the rates of the others
    /// moved up.
    fn double_stride(&mut self) {
        self.stride *= 2;
        let mut to = 0;
        let stride = self.stride;
        self.kept.retain_mut(|(index, _, range)| {
            if !index.is_multiple_of(stride) {
                return false;
            }
            let n = range.len();
            self.rates.copy_within(range.clone(), to);
            *range = to..to + n;
            to += n;
            true
        });
        self.rates.truncate(to);
    }

    /// The rates of the rotations kept, and their poses, each rotation in a time segment of its
    /// own (rates of another segment in none, `u32::MAX`), so the fit integrates within rotations
    /// only, as it does on the whole log. Once [`SpanRates::finish`]ed.
    fn rotations(&self) -> (&[Rate], Vec<Pose>) {
        let poses = self.kept.iter().flat_map(|(_, poses, _)| *poses);
        (&self.rates, poses.collect())
    }
}

/// The same pose of a pipeline (its newest, looked at again).
fn same_pose(a: &Pose, b: &Pose) -> bool {
    (a.t_start, a.t_end, a.samples) == (b.t_start, b.t_end, b.samples)
}

/// The first pose of every pair of consecutive poses that [`crate::calib::gyro::fit_scale`] could
/// use: the same time segment, a gap of at most its `max_gap_s`.
fn rotation_pairs(poses: &[Pose]) -> impl Iterator<Item = usize> + '_ {
    (1..poses.len())
        .filter(move |&i| is_rotation_pair(&poses[i - 1], &poses[i]))
        .map(|i| i - 1)
}

/// Pose `a` and the next, `b`, are of the same time segment, at most
/// [`crate::calib::gyro::ScaleOptions::max_gap_s`] apart.
fn is_rotation_pair(a: &Pose, b: &Pose) -> bool {
    let max_gap_s = crate::calib::gyro::ScaleOptions::default().max_gap_s;
    a.segment == b.segment && b.t_start - a.t_end <= max_gap_s
}

/// The middle of a pose, s: where a rotation to or from it starts or ends.
fn pose_mid(p: &Pose) -> f64 {
    0.5 * (p.t_start + p.t_end)
}

/// The rotation from pose `i` to pose `i + 1`: from the middle of one to the middle of the other, s.
fn pose_mids(poses: &[Pose], i: usize) -> (f64, f64) {
    (pose_mid(&poses[i]), pose_mid(&poses[i + 1]))
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

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t_s: f64) -> Pose {
        Pose::still(t_s, t_s + 1.0, 100, [0.0, 0.0, 9.8])
    }

    /// Past [`GYRO_SPAN_SAMPLES_MAX`] rates, the rotations kept are every `stride`-th of the
    /// log, the stride a power of two, and their rates follow one another in order.
    #[test]
    fn the_rotations_kept_are_evenly_spread_and_fit() {
        let mut spans = SpanRates {
            started: true,
            stride: 1,
            ..Default::default()
        };
        // 1000 rotations of 1000 to 1999 rates each, about 12 times the cap.
        for i in 0..1000u64 {
            let n = 1000 + (i as usize * 7919) % 1000;
            if spans.room_for([pose(i as f64), pose(i as f64 + 2.0)], n) {
                spans.rates.extend((0..n).map(|_| Rate {
                    t_s: i as f64,
                    segment: 0,
                    gyro_rad_s: None,
                    temp_c: None,
                }));
            }
            assert!(spans.rates.len() <= GYRO_SPAN_SAMPLES_MAX);
            let mut at = 0;
            for (index, poses, range) in &spans.kept {
                assert!(
                    index.is_multiple_of(spans.stride),
                    "{index} {}",
                    spans.stride
                );
                assert_eq!(poses[0].t_start, *index as f64);
                assert_eq!(range.start, at);
                assert!(spans.rates[range.clone()]
                    .iter()
                    .all(|r| r.t_s == *index as f64));
                at = range.end;
            }
            assert_eq!(at, spans.rates.len());
        }
        assert!(
            spans.stride.is_power_of_two() && spans.stride >= 8,
            "{}",
            spans.stride
        );
        // Every rotation on the stride is kept, and with them at least half the cap.
        assert_eq!(spans.kept.len() as u64, 1000u64.div_ceil(spans.stride));
        assert!(
            spans.rates.len() > GYRO_SPAN_SAMPLES_MAX / 2,
            "{}",
            spans.rates.len()
        );
    }
}
