//! An external attitude reference (optical motion capture) aligned with a log, for scoring the
//! attitude estimates of the log against it. Pure math, no I/O.
//!
//! A capture system and a flight controller share neither a clock nor axes. Four constants separate
//! the capture's rigid-body rotation `q_m(tau)` (rigid body -> capture world) from the log's sensor
//! attitude:
//!
//! 1. the clock offset: log time `t = tau + time_offset_s`. Found by the normalised
//!    cross-correlation of the rotation-rate magnitudes `|omega|` of the gyro and of the capture
//!    (both frame-free), on a common 100 Hz grid ([`offset_by_rate_correlation`]), then refined to
//!    the millisecond by the residual of step 2;
//! 2. the body rotation `B` (capture rigid body -> log sensor axes): `omega_log = B omega_m + bias`
//!    for the paired angular velocities, a least-squares rotation -- Wahba's problem (G. Wahba, "A
//!    Least Squares Estimate of Satellite Attitude", SIAM Review, 1965), solved through the SVD of
//!    the cross-covariance as Kabsch does (W. Kabsch, "A solution for the best rotation to relate
//!    two sets of vectors", Acta Cryst., 1976). The vectors are centred first, so the constant
//!    difference (the gyro's bias) is fitted with it; pairs far off the fit (a capture glitch) are
//!    left out ([`fit_body_rotation`]);
//! 3. the tilt of the capture world: the mean specific force of the resting instants, rotated
//!    into the capture world, points up; the shortest rotation taking it to +z makes a z-up world
//!    ([`world_tilt`]). OptiTrack Motive's world is Y-up, a ground plane set a little off level
//!    shows here;
//! 4. the heading of the capture world about the vertical, which the capture alone does not
//!    observe (its X axis is not north). It is *not* estimated here: [`evaluate_against_reference`]
//!    removes a constant heading offset per estimator, as [`eval::Alignment::Heading`] does.
//!
//! The reference of a log sample at time `t` (sensor -> a z-up world, ENU up to heading) is then
//! `T q_m(t - time_offset_s) B^-1`, with `q_m` interpolated (slerp) between capture frames and
//! none where the capture has a gap ([`reference_quaternions`]).
//!
//! Rates are taken the same way on both sides, so that they are filtered alike: the gyro's mean
//! over a 20 ms window, and the capture's rotation across the same window divided by its length.

use crate::attitude::eval::{self, Alignment, EvalResult, FilterEvaluation};
use crate::attitude::fusion::FusionConfig;
use crate::error::Error;
use crate::types::Sample;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// One capture frame: the rigid body's rotation into the capture world at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Capture time, s.
    pub t_s: f64,
    /// Rigid body -> capture world.
    pub q: UnitQuaternion<f64>,
}

/// Grid of the rate series, Hz.
pub(crate) const GRID_HZ: f64 = 100.0;
/// Half the window a rate is averaged over, s.
pub(crate) const RATE_HALF_WINDOW_S: f64 = 0.01;
/// Longest interval between capture frames still interpolated, s (default of
/// [`AlignOptions::max_gap_s`]).
pub const MAX_GAP_S: f64 = 0.05;
/// Least overlap of the two series at a tried offset, s; and at least half the shorter series.
const MIN_OVERLAP_S: f64 = 5.0;
/// Rate pairs farther off the fit than this many robust sigmas (1.4826 median) are left out.
const OUTLIER_SIGMAS: f64 = 3.0;
/// ... but never closer than this, rad/s (2 deg/s).
const OUTLIER_FLOOR_RAD_S: f64 = 0.034_906_585;
/// Passes of the fit with outliers left out.
const OUTLIER_PASSES: usize = 5;
/// The refinement of the offset tries this far either side of the correlation peak, s ...
const REFINE_SPAN_S: f64 = 0.015;
/// ... in steps of this, s.
const REFINE_STEP_S: f64 = 0.001;
/// The fitted rates must turn about more than one axis: second singular value of the
/// cross-covariance over the first at least this.
const MIN_SPAN_RATIO: f64 = 0.01;
/// Least rate pairs for a fit.
const MIN_RATE_PAIRS: usize = 50;
/// A resting instant for the world tilt: gyro below this, rad/s (3 deg/s) ...
const STILL_RATE_RAD_S: f64 = 0.052_359_878;
/// ... and the specific force's norm within this of its median, m/s^2.
const STILL_FORCE_TOLERANCE_MPS2: f64 = 0.5;
/// Fewer resting instants than this: the tilt is taken from every instant the capture covers (the
/// mean specific force over a flight is gravity plus the velocity change over its length).
const MIN_STILL_SAMPLES: usize = 100;

/// Settings of [`align_to_log`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignOptions {
    /// Offsets (log time - capture time, s) the correlation searches; `None`: every offset at which
    /// the two overlap enough.
    pub offset_window_s: Option<(f64, f64)>,
    /// Longest interval between capture frames that is interpolated, s.
    pub max_gap_s: f64,
}

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            offset_window_s: None,
            max_gap_s: MAX_GAP_S,
        }
    }
}

/// Angular velocities on an even time grid (`None` where a side has no data).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RateSeries {
    /// Time of the first grid point, s.
    pub t0_s: f64,
    /// Grid step, s.
    pub step_s: f64,
    /// One per grid point, rad/s.
    pub rates_rad_s: Vec<Option<Vector3<f64>>>,
}

/// The gyro readings of a log (time, rate), in time order, with their running integral.
struct GyroTrack {
    t_s: Vec<f64>,
    rate: Vec<Vector3<f64>>,
    /// `integral[i]`: the integral of the piecewise-linear rate from the first reading to the
    /// `i`-th (trapezoids), rad.
    integral: Vec<Vector3<f64>>,
}

impl GyroTrack {
    fn new(samples: &[Sample]) -> GyroTrack {
        let mut g = GyroTrack {
            t_s: Vec::new(),
            rate: Vec::new(),
            integral: Vec::new(),
        };
        for s in samples {
            let Some(w) = s.gyro_rad_s else { continue };
            if !w.iter().all(|x| x.is_finite()) || !s.t_s.is_finite() {
                continue;
            }
            let w = Vector3::new(w[0], w[1], w[2]);
            let acc = match (g.t_s.last(), g.rate.last(), g.integral.last()) {
                (Some(&t0), Some(w0), Some(i0)) => {
                    if s.t_s <= t0 {
                        continue;
                    }
                    i0 + (w0 + w) * (0.5 * (s.t_s - t0))
                }
                _ => Vector3::zeros(),
            };
            g.t_s.push(s.t_s);
            g.rate.push(w);
            g.integral.push(acc);
        }
        g
    }

    /// The integral of the rate up to `t` and the interval between the readings around it;
    /// `None` outside the readings.
    fn integral_at(&self, t: f64) -> Option<(Vector3<f64>, f64)> {
        let i = self.t_s.partition_point(|&x| x <= t);
        if i == 0 {
            return None;
        }
        let (t0, w0, i0) = (self.t_s[i - 1], self.rate[i - 1], self.integral[i - 1]);
        if t == t0 {
            return Some((i0, 0.0));
        }
        let t1 = *self.t_s.get(i)?;
        let s = (t - t0) / (t1 - t0);
        let w = w0 + (self.rate[i] - w0) * s;
        Some((i0 + (w0 + w) * (0.5 * (t - t0)), t1 - t0))
    }

    /// Mean rate over `[a, b]` (the integral of the rate, linear between readings, over the
    /// window's length), when readings cover it without an interval longer than `max_gap_s`.
    fn mean(&self, a: f64, b: f64, max_gap_s: f64) -> Option<Vector3<f64>> {
        if !(b > a) {
            return None;
        }
        let (ia, ga) = self.integral_at(a)?;
        let (ib, gb) = self.integral_at(b)?;
        // A gap longer than the window holds one of its ends.
        if ga > max_gap_s || gb > max_gap_s {
            return None;
        }
        Some((ib - ia) / (b - a))
    }
}

/// The gyro's rates of a log on a grid of `step_s`, each the mean over `+-half_window_s` (the
/// integral of the rate, linear between readings, over the window's length: the same average the
/// capture's rotation across the window gives).
pub(crate) fn gyro_rates(samples: &[Sample], step_s: f64, half_window_s: f64) -> RateSeries {
    let g = GyroTrack::new(samples);
    let (Some(&first), Some(&last)) = (g.t_s.first(), g.t_s.last()) else {
        return RateSeries {
            t0_s: 0.0,
            step_s,
            rates_rad_s: Vec::new(),
        };
    };
    let n = grid_len(first, last, step_s);
    let rates_rad_s = (0..n)
        .map(|i| {
            let t = first + i as f64 * step_s;
            g.mean(t - half_window_s, t + half_window_s, MAX_GAP_S)
        })
        .collect();
    RateSeries {
        t0_s: first,
        step_s,
        rates_rad_s,
    }
}

/// Points of a grid of `step_s` from `first` to `last`.
fn grid_len(first: f64, last: f64, step_s: f64) -> usize {
    if !(step_s > 0.0) || !(last >= first) {
        return 0;
    }
    ((last - first) / step_s).floor() as usize + 1
}

/// The capture's rigid-body rates (in the rigid body's axes) on a grid of `step_s`: the rotation
/// from `tau - half_window_s` to `tau + half_window_s` over its duration.
pub(crate) fn mocap_rates(
    poses: &[Pose],
    step_s: f64,
    half_window_s: f64,
    max_gap_s: f64,
) -> RateSeries {
    let (Some(first), Some(last)) = (poses.first(), poses.last()) else {
        return RateSeries {
            t0_s: 0.0,
            step_s,
            rates_rad_s: Vec::new(),
        };
    };
    let n = grid_len(first.t_s, last.t_s, step_s);
    let rates_rad_s = (0..n)
        .map(|i| {
            let t = first.t_s + i as f64 * step_s;
            let a = interpolate(poses, t - half_window_s, max_gap_s)?;
            let b = interpolate(poses, t + half_window_s, max_gap_s)?;
            Some((a.inverse() * b).scaled_axis() / (2.0 * half_window_s))
        })
        .collect();
    RateSeries {
        t0_s: first.t_s,
        step_s,
        rates_rad_s,
    }
}

/// The capture's rotation at `t_s`, interpolated (slerp, the shorter way) between the frames
/// around it; `None` before the first, after the last, or where they are more than `max_gap_s`
/// apart.
pub(crate) fn interpolate(poses: &[Pose], t_s: f64, max_gap_s: f64) -> Option<UnitQuaternion<f64>> {
    if !t_s.is_finite() {
        return None;
    }
    let i = poses.partition_point(|p| p.t_s <= t_s);
    if i == 0 {
        return None;
    }
    let a = &poses[i - 1];
    if a.t_s == t_s {
        return Some(a.q);
    }
    let b = poses.get(i)?;
    let dt = b.t_s - a.t_s;
    if !(dt > 0.0) || dt > max_gap_s {
        return None;
    }
    let s = (t_s - a.t_s) / dt;
    Some(a.q * (a.q.inverse() * b.q).powf(s))
}

/// The clock offset found by [`offset_by_rate_correlation`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct OffsetEstimate {
    /// Log time minus capture time, s.
    pub time_offset_s: f64,
    /// Normalised correlation (Pearson) of the rate magnitudes at the peak.
    pub correlation: f64,
    /// Length the two series overlap at the peak, s.
    pub overlap_s: f64,
}

/// The clock offset (log time = capture time + offset) that maximises the normalised
/// cross-correlation of the rate magnitudes `|omega|` of `log` and `mocap` (same grid step), over
/// the offsets in `window_s` (default: every offset at which they overlap by at least 5 s and half
/// the shorter series). The peak is refined between grid steps by a parabola through it and its
/// neighbours.
pub(crate) fn offset_by_rate_correlation(
    log: &RateSeries,
    mocap: &RateSeries,
    window_s: Option<(f64, f64)>,
) -> Result<OffsetEstimate, Error> {
    if !(log.step_s > 0.0) || (log.step_s - mocap.step_s).abs() > 1e-9 * log.step_s {
        return Err(Error::Other(format!(
            "rate series on different grids ({} s and {} s)",
            log.step_s, mocap.step_s
        )));
    }
    let step = log.step_s;
    let mag = |s: &RateSeries| -> Vec<Option<f64>> {
        s.rates_rad_s.iter().map(|w| w.map(|w| w.norm())).collect()
    };
    let (x, y) = (mag(log), mag(mocap));
    let valid = |v: &[Option<f64>]| v.iter().filter(|a| a.is_some()).count();
    let shorter = valid(&x).min(valid(&y));
    let min_n = ((MIN_OVERLAP_S / step).ceil() as usize).max(shorter / 2);
    if shorter < min_n || shorter == 0 {
        return Err(Error::Other(format!(
            "too little data to correlate: {:.1} s of gyro rates and {:.1} s of capture rates \
             (at least {MIN_OVERLAP_S} s each)",
            valid(&x) as f64 * step,
            valid(&y) as f64 * step
        )));
    }
    // Capture index j pairs with log index j + k; offset = log.t0 - mocap.t0 + k step.
    let base = log.t0_s - mocap.t0_s;
    let (nx, ny) = (x.len() as i64, y.len() as i64);
    let (mut k_lo, mut k_hi) = (-(ny - 1), nx - 1);
    if let Some((lo, hi)) = window_s {
        if !(lo <= hi) {
            return Err(Error::Other(format!(
                "offset window {lo} to {hi} s is empty"
            )));
        }
        k_lo = k_lo.max(((lo - base) / step).floor() as i64);
        k_hi = k_hi.min(((hi - base) / step).ceil() as i64);
    }
    let corr = |k: i64| -> Option<(f64, usize)> {
        let j0 = (-k).max(0);
        let j1 = ny.min(nx - k);
        let (mut n, mut sx, mut sy, mut sxx, mut syy, mut sxy) = (0usize, 0.0, 0.0, 0.0, 0.0, 0.0);
        for j in j0..j1 {
            if let (Some(a), Some(b)) = (x[(j + k) as usize], y[j as usize]) {
                n += 1;
                sx += a;
                sy += b;
                sxx += a * a;
                syy += b * b;
                sxy += a * b;
            }
        }
        if n < min_n {
            return None;
        }
        let nf = n as f64;
        let den = ((nf * sxx - sx * sx) * (nf * syy - sy * sy)).sqrt();
        (den > 0.0 && den.is_finite()).then(|| ((nf * sxy - sx * sy) / den, n))
    };
    let mut best: Option<(i64, f64, usize)> = None;
    for k in k_lo..=k_hi {
        if let Some((r, n)) = corr(k) {
            if best.is_none_or(|(_, b, _)| r > b) {
                best = Some((k, r, n));
            }
        }
    }
    let Some((k, r, n)) = best else {
        return Err(Error::Other(format!(
            "the log and the capture never overlap by {:.1} s within the offsets searched",
            min_n as f64 * step
        )));
    };
    let frac = match (corr(k - 1), corr(k + 1)) {
        (Some((a, _)), Some((c, _))) => {
            let d = a - 2.0 * r + c;
            if d < 0.0 {
                (0.5 * (a - c) / d).clamp(-0.5, 0.5)
            } else {
                0.0
            }
        }
        _ => 0.0,
    };
    Ok(OffsetEstimate {
        time_offset_s: base + (k as f64 + frac) * step,
        correlation: r,
        overlap_s: n as f64 * step,
    })
}

/// The body rotation fitted by [`fit_body_rotation`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct RateFit {
    /// `B`: capture rigid body -> log sensor axes (`omega_log = B omega_m + bias`).
    pub rotation: UnitQuaternion<f64>,
    /// The constant difference fitted with it (the gyro's bias), rad/s.
    pub gyro_bias_rad_s: Vector3<f64>,
    /// RMS of `|omega_log - B omega_m - bias|` over the pairs used, rad/s.
    pub residual_rms_rad_s: f64,
    /// Pairs used.
    pub used: usize,
    /// Pairs left out as outliers.
    pub rejected: usize,
}

/// Least-squares rotation and offset with `y ~ B x + c` over the pairs where `mask` holds, by the
/// SVD of the centred cross-covariance (Kabsch's solution of Wahba's problem; a reflection is
/// turned into the nearest rotation). Errors when the vectors do not span two directions.
fn kabsch(pairs: &[RatePair], mask: &[bool]) -> Result<(Rotation3<f64>, Vector3<f64>), Error> {
    let used: Vec<&(Vector3<f64>, Vector3<f64>)> = pairs
        .iter()
        .zip(mask)
        .filter_map(|(p, &m)| m.then_some(p))
        .collect();
    if used.len() < MIN_RATE_PAIRS {
        return Err(Error::Other(format!(
            "{} rate pairs: at least {MIN_RATE_PAIRS} are needed for the body rotation",
            used.len()
        )));
    }
    let n = used.len() as f64;
    let mx = used.iter().map(|p| p.0).sum::<Vector3<f64>>() / n;
    let my = used.iter().map(|p| p.1).sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (x, y) in &used {
        h += (x - mx) * (y - my).transpose();
    }
    if !h.iter().all(|v| v.is_finite()) {
        return Err(Error::Other("rate pairs are not finite".into()));
    }
    let svd = h
        .try_svd(true, true, 1e-12, 1000)
        .ok_or_else(|| Error::Other("the SVD of the rate cross-covariance failed".into()))?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(Error::Other("the SVD gave no singular vectors".into()));
    };
    let mut sv: Vec<f64> = svd.singular_values.iter().copied().collect();
    sv.sort_by(|a, b| b.total_cmp(a));
    if !(sv[0] > 0.0) || sv[1] < MIN_SPAN_RATIO * sv[0] {
        return Err(Error::Other(
            "the rotation rates turn about one axis only: the body rotation is not determined \
             (rotate the vehicle about more than one axis while it is captured)"
                .into(),
        ));
    }
    // H = U S V^T with H = sum x y^T: B = V diag(1, 1, det(V U^T)) U^T.
    let v = v_t.transpose();
    let d = (v * u.transpose()).determinant().signum();
    let b = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    let r = Rotation3::from_matrix_eps(&b, 1e-12, 100, Rotation3::identity());
    Ok((r, my - r * mx))
}

/// The rotation `B` and the bias with `omega_log ~ B omega_m + bias` over `pairs` of
/// `(omega_m, omega_log)` (rad/s), fitted by least squares (Kabsch, Wahba; see the module docs)
/// with pairs more than three robust sigmas (and 2 deg/s) off the fit left out, refitted until the
/// set stays the same.
pub(crate) fn fit_body_rotation(pairs: &[RatePair]) -> Result<RateFit, Error> {
    let mut mask = vec![true; pairs.len()];
    let mut fit = kabsch(pairs, &mask)?;
    for _ in 0..OUTLIER_PASSES {
        let res = residuals(pairs, &fit);
        let mut kept: Vec<f64> = res
            .iter()
            .zip(&mask)
            .filter_map(|(r, &m)| m.then_some(*r))
            .collect();
        kept.sort_by(f64::total_cmp);
        let median = kept.get(kept.len() / 2).copied().unwrap_or(0.0);
        let limit = (OUTLIER_SIGMAS * 1.4826 * median).max(OUTLIER_FLOOR_RAD_S);
        let next: Vec<bool> = res.iter().map(|&r| r <= limit).collect();
        if next == mask {
            break;
        }
        mask = next;
        fit = kabsch(pairs, &mask)?;
    }
    Ok(rate_fit(pairs, &mask, fit))
}

fn residuals(pairs: &[RatePair], fit: &(Rotation3<f64>, Vector3<f64>)) -> Vec<f64> {
    pairs
        .iter()
        .map(|(x, y)| (y - fit.0 * x - fit.1).norm())
        .collect()
}

fn rate_fit(pairs: &[RatePair], mask: &[bool], fit: (Rotation3<f64>, Vector3<f64>)) -> RateFit {
    let res = residuals(pairs, &fit);
    let used = mask.iter().filter(|&&m| m).count();
    let ss: f64 = res
        .iter()
        .zip(mask)
        .filter_map(|(r, &m)| m.then_some(r * r))
        .sum();
    RateFit {
        rotation: UnitQuaternion::from_rotation_matrix(&fit.0),
        gyro_bias_rad_s: fit.1,
        residual_rms_rad_s: (ss / used.max(1) as f64).sqrt(),
        used,
        rejected: pairs.len() - used,
    }
}

/// The rotation taking the capture world to a z-up world: the shortest one taking `up_in_mocap`
/// (the direction of the specific force at rest, in capture-world axes) to +z. Its heading about
/// the vertical is arbitrary (the capture does not observe north).
pub(crate) fn world_tilt(up_in_mocap: &Vector3<f64>) -> Result<UnitQuaternion<f64>, Error> {
    let n = up_in_mocap.norm();
    if !(n > 0.0) || !n.is_finite() {
        return Err(Error::Other(
            "no direction of gravity in the capture world".into(),
        ));
    }
    let u = up_in_mocap / n;
    Ok(
        UnitQuaternion::rotation_between(&u, &Vector3::z()).unwrap_or_else(|| {
            // Antiparallel: any half turn about a horizontal axis.
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
        }),
    )
}

/// The direction of the specific force at rest in the capture world (unit vector), from the log's
/// accelerometer rotated by `B^-1` and the capture's rotation at each sample's time, and how many
/// samples gave it. Resting samples (gyro below 3 deg/s, specific force within 0.5 m/s^2 of its
/// median norm) when there are at least 100; every captured sample otherwise.
pub(crate) fn up_in_mocap_world(
    samples: &[Sample],
    poses: &[Pose],
    time_offset_s: f64,
    body_rotation: &UnitQuaternion<f64>,
    max_gap_s: f64,
) -> Result<(Vector3<f64>, usize), Error> {
    let b_inv = body_rotation.inverse();
    let mut all: Vec<(Vector3<f64>, bool)> = Vec::new();
    for s in samples {
        let Some(f) = s.accel_mps2 else { continue };
        let f = Vector3::new(f[0], f[1], f[2]);
        if !f.iter().all(|x| x.is_finite()) {
            continue;
        }
        let Some(q) = interpolate(poses, s.t_s - time_offset_s, max_gap_s) else {
            continue;
        };
        let still = s
            .gyro_rad_s
            .is_some_and(|g| Vector3::new(g[0], g[1], g[2]).norm() < STILL_RATE_RAD_S);
        all.push((q * (b_inv * f), still));
    }
    let mut norms: Vec<f64> = all.iter().map(|(f, _)| f.norm()).collect();
    norms.sort_by(f64::total_cmp);
    let Some(&median) = norms.get(norms.len() / 2) else {
        return Err(Error::Other(
            "no accelerometer reading while the capture covers the log".into(),
        ));
    };
    let still: Vec<Vector3<f64>> = all
        .iter()
        .filter(|(f, s)| *s && (f.norm() - median).abs() < STILL_FORCE_TOLERANCE_MPS2)
        .map(|(f, _)| *f)
        .collect();
    let used: Vec<Vector3<f64>> = if still.len() >= MIN_STILL_SAMPLES {
        still
    } else {
        all.iter().map(|(f, _)| *f).collect()
    };
    let mean = used.iter().sum::<Vector3<f64>>() / used.len().max(1) as f64;
    let n = mean.norm();
    if !(n > 0.0) || !n.is_finite() {
        return Err(Error::Other(
            "the mean specific force is zero: no direction of gravity".into(),
        ));
    }
    Ok((mean / n, used.len()))
}

/// The capture aligned with a log: everything [`reference_quaternions`] needs, and how well the
/// rates agreed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MocapAlignment {
    /// Log time minus capture time, s (log `t_s = tau + time_offset_s`).
    pub time_offset_s: f64,
    /// `B`: capture rigid body -> log sensor axes (`omega_log = B omega_m`), as w, x, y, z.
    #[serde(with = "quat_wxyz")]
    pub body_rotation: UnitQuaternion<f64>,
    /// Capture world -> a z-up world (ENU up to an unknown heading), as w, x, y, z.
    #[serde(with = "quat_wxyz")]
    pub world_tilt: UnitQuaternion<f64>,
    /// The direction of the specific force at rest in capture-world axes (Motive: about +Y).
    pub up_in_mocap: [f64; 3],
    /// Samples that gave `up_in_mocap`.
    pub up_samples: usize,
    /// RMS of `|omega_log - B omega_m - bias|` over the pairs used, deg/s.
    pub rate_residual_rms_deg_s: f64,
    /// Normalised correlation of the rate magnitudes at the peak.
    pub correlation: f64,
    /// The offset where the correlation peaked, before its refinement by the rate residual, s.
    pub correlation_offset_s: f64,
    /// Rate pairs (100 Hz) in the fit of `B`.
    pub pairs_used: usize,
    /// Rate pairs left out as outliers (capture glitches).
    pub pairs_rejected: usize,
    /// The gyro's bias fitted with `B`, rad/s.
    pub gyro_bias_rad_s: [f64; 3],
}

impl MocapAlignment {
    /// `B` as roll, pitch, yaw (deg; `B = Rz(yaw) Ry(pitch) Rx(roll)`).
    pub fn body_rotation_rpy_deg(&self) -> [f64; 3] {
        let (r, p, y) = self.body_rotation.euler_angles();
        [r.to_degrees(), p.to_degrees(), y.to_degrees()]
    }

    /// `B` as a rotation vector, deg.
    pub fn body_rotation_vector_deg(&self) -> [f64; 3] {
        let v = self.body_rotation.scaled_axis();
        [v[0].to_degrees(), v[1].to_degrees(), v[2].to_degrees()]
    }

    /// Angle between the capture world's tilt and the nearest of its axes taken as up, deg (how
    /// far the capture's ground plane is from level, with the accelerometer's errors).
    pub(crate) fn tilt_from_nearest_axis_deg(&self) -> f64 {
        let m = self
            .up_in_mocap
            .iter()
            .fold(0.0f64, |a, x| a.max(x.abs()))
            .clamp(0.0, 1.0);
        m.acos().to_degrees()
    }

    /// True when the rates agree as those of one motion do: correlation at least 0.8 and rate
    /// residual at most 10 deg/s (the takes that belong to the shared PX4 flights: 0.997 and
    /// 1.1-2.1 deg/s; the unrelated pairings: 0.44-0.63 and 41-213 deg/s).
    pub fn is_plausible(&self) -> bool {
        self.correlation >= PLAUSIBLE_CORRELATION
            && self.rate_residual_rms_deg_s <= PLAUSIBLE_RESIDUAL_DEG_S
    }

    /// Plain-text summary, one item a line.
    pub fn to_text(&self) -> String {
        let [r, p, y] = self.body_rotation_rpy_deg();
        let u = self.up_in_mocap;
        let b = self.gyro_bias_rad_s.map(f64::to_degrees);
        let mut s = String::from("alignment of the capture with the log:\n");
        s += &format!(
            "  time offset        {:.3} s (log time = capture time + offset; correlation peak at {:.3} s)\n",
            self.time_offset_s, self.correlation_offset_s
        );
        s += &format!(
            "  rate correlation   {:.3} (|omega| of the gyro against the capture's)\n",
            self.correlation
        );
        s += &format!(
            "  body rotation B    roll {r:.2}, pitch {p:.2}, yaw {y:.2} deg (rigid body -> log sensor axes)\n"
        );
        s += &format!(
            "  rate residual      {:.2} deg/s RMS over {} pairs at {GRID_HZ} Hz ({} left out)\n",
            self.rate_residual_rms_deg_s, self.pairs_used, self.pairs_rejected
        );
        s += &format!(
            "  gyro bias          {:.3} {:.3} {:.3} deg/s (fitted with B)\n",
            b[0], b[1], b[2]
        );
        s += &format!(
            "  up in capture axes ({:.4}, {:.4}, {:.4}) from {} samples: {:.2} deg off the nearest axis\n",
            u[0], u[1], u[2], self.up_samples, self.tilt_from_nearest_axis_deg()
        );
        if !self.is_plausible() {
            s += "  WARNING: the rates disagree: this capture does not seem to record this log's motion\n";
        }
        s
    }
}

/// Least rate correlation of a capture that records the log's motion ([`MocapAlignment::is_plausible`]).
const PLAUSIBLE_CORRELATION: f64 = 0.8;
/// Largest rate residual of such a capture, deg/s.
const PLAUSIBLE_RESIDUAL_DEG_S: f64 = 10.0;

/// Serde of a unit quaternion as `[w, x, y, z]`.
mod quat_wxyz {
    use nalgebra::{Quaternion, UnitQuaternion};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub(crate) fn serialize<S: Serializer>(
        q: &UnitQuaternion<f64>,
        s: S,
    ) -> Result<S::Ok, S::Error> {
        [q.w, q.i, q.j, q.k].serialize(s)
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<UnitQuaternion<f64>, D::Error> {
        let [w, x, y, z] = <[f64; 4]>::deserialize(d)?;
        let q = Quaternion::new(w, x, y, z);
        if !(q.norm() > 0.5) || !q.norm().is_finite() {
            return Err(serde::de::Error::custom("not a unit quaternion"));
        }
        Ok(UnitQuaternion::from_quaternion(q))
    }
}

/// A capture rate and the gyro's at the same instant, `(omega_m, omega_log)`, rad/s.
pub(crate) type RatePair = (Vector3<f64>, Vector3<f64>);

/// Rate pairs `(omega_m, omega_log)` at the capture's grid points (their indices kept) with the
/// log's gyro window shifted by `offset_s`.
fn rate_pairs(
    gyro: &GyroTrack,
    mocap: &RateSeries,
    offset_s: f64,
    only: Option<&[usize]>,
) -> (Vec<usize>, Vec<RatePair>) {
    let mut idx = Vec::new();
    let mut pairs = Vec::new();
    let mut visit = |j: usize| {
        let Some(Some(wm)) = mocap.rates_rad_s.get(j) else {
            return;
        };
        let t = mocap.t0_s + j as f64 * mocap.step_s + offset_s;
        if let Some(wl) = gyro.mean(t - RATE_HALF_WINDOW_S, t + RATE_HALF_WINDOW_S, MAX_GAP_S) {
            idx.push(j);
            pairs.push((*wm, wl));
        }
    };
    match only {
        Some(js) => js.iter().for_each(|&j| visit(j)),
        None => (0..mocap.rates_rad_s.len()).for_each(&mut visit),
    }
    (idx, pairs)
}

/// Align a capture with a log: the clock offset (rate-magnitude correlation, refined to 1 ms by
/// the rate residual), the body rotation `B` and the gyro bias (least squares on the paired rates),
/// and the tilt of the capture world (gravity). See the module docs.
pub fn align_to_log(
    samples: &[Sample],
    poses: &[Pose],
    opts: &AlignOptions,
) -> Result<MocapAlignment, Error> {
    if poses.len() < 2 {
        return Err(Error::Other(format!(
            "the capture has {} tracked frames",
            poses.len()
        )));
    }
    let step = 1.0 / GRID_HZ;
    let log_rates = gyro_rates(samples, step, RATE_HALF_WINDOW_S);
    let m_rates = mocap_rates(poses, step, RATE_HALF_WINDOW_S, opts.max_gap_s);
    let coarse = offset_by_rate_correlation(&log_rates, &m_rates, opts.offset_window_s)?;
    let gyro = GyroTrack::new(samples);
    let (idx, pairs) = rate_pairs(&gyro, &m_rates, coarse.time_offset_s, None);
    let first = fit_body_rotation(&pairs)?;
    // The pairs the first fit kept, tried at offsets around the peak with that set held fixed.
    let keep: Vec<usize> = {
        let fit = (first.rotation.to_rotation_matrix(), first.gyro_bias_rad_s);
        let res = residuals(&pairs, &fit);
        let limit = (first.residual_rms_rad_s * OUTLIER_SIGMAS).max(OUTLIER_FLOOR_RAD_S);
        idx.iter()
            .zip(&res)
            .filter_map(|(&j, &r)| (r <= limit).then_some(j))
            .collect()
    };
    let steps = (REFINE_SPAN_S / REFINE_STEP_S).round() as i64;
    let mut best = (coarse.time_offset_s, f64::INFINITY);
    for i in -steps..=steps {
        let off = coarse.time_offset_s + i as f64 * REFINE_STEP_S;
        let (_, p) = rate_pairs(&gyro, &m_rates, off, Some(&keep));
        let Ok(fit) = kabsch(&p, &vec![true; p.len()]) else {
            continue;
        };
        let res = residuals(&p, &fit);
        let rms = (res.iter().map(|r| r * r).sum::<f64>() / res.len().max(1) as f64).sqrt();
        if rms < best.1 {
            best = (off, rms);
        }
    }
    let time_offset_s = best.0;
    let (_, pairs) = rate_pairs(&gyro, &m_rates, time_offset_s, None);
    let fit = fit_body_rotation(&pairs)?;
    let (up, up_samples) =
        up_in_mocap_world(samples, poses, time_offset_s, &fit.rotation, opts.max_gap_s)?;
    let world_tilt = world_tilt(&up)?;
    Ok(MocapAlignment {
        time_offset_s,
        body_rotation: fit.rotation,
        world_tilt,
        up_in_mocap: [up[0], up[1], up[2]],
        up_samples,
        rate_residual_rms_deg_s: fit.residual_rms_rad_s.to_degrees(),
        correlation: coarse.correlation,
        correlation_offset_s: coarse.time_offset_s,
        pairs_used: fit.used,
        pairs_rejected: fit.rejected,
        gyro_bias_rad_s: [
            fit.gyro_bias_rad_s[0],
            fit.gyro_bias_rad_s[1],
            fit.gyro_bias_rad_s[2],
        ],
    })
}

/// The index of the alignment with the highest rate correlation among candidate captures (the
/// take that belongs to the log), `None` when none aligned.
pub fn best_alignment(candidates: &[Result<MocapAlignment, Error>]) -> Option<usize> {
    candidates
        .iter()
        .enumerate()
        .filter_map(|(i, a)| a.as_ref().ok().map(|a| (i, a.correlation)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// The reference attitude (sensor -> a z-up world, ENU up to heading) at each of `times_s` (log
/// time): `T q_m(t - offset) B^-1`, with `q_m` interpolated between capture frames; `None` outside
/// the capture and where its frames are more than `max_gap_s` apart.
pub(crate) fn reference_quaternions(
    times_s: &[f64],
    poses: &[Pose],
    alignment: &MocapAlignment,
    max_gap_s: f64,
) -> Vec<Option<UnitQuaternion<f64>>> {
    let b_inv = alignment.body_rotation.inverse();
    times_s
        .iter()
        .map(|&t| {
            interpolate(poses, t - alignment.time_offset_s, max_gap_s)
                .map(|q| alignment.world_tilt * q * b_inv)
        })
        .collect()
}

/// A log's samples prepared for scoring against a capture: the same samples with `ref_q` the
/// capture's reference where it is scored (none elsewhere, no `moving` flag), and the flight
/// controller's own attitude (the `ref_q` the log carried, interpolated between its changes) at
/// each.
#[derive(Debug, Clone)]
pub struct ReferenceSamples {
    /// The log's samples with the capture's reference.
    pub samples: Vec<Sample>,
    /// The log's own attitude per sample (sensor -> ENU), when it had one.
    pub flight_controller: Vec<Option<UnitQuaternion<f64>>>,
    /// Samples the capture covers.
    pub with_reference: usize,
}

/// Replace the samples' reference with the capture's. With `flight_controller` true, the `ref_q`
/// the log carried is the flight controller's attitude estimate: it is kept aside, and only samples
/// that have both are scored (so every estimator is scored on the same samples).
pub fn reference_samples(
    samples: &[Sample],
    poses: &[Pose],
    alignment: &MocapAlignment,
    max_gap_s: f64,
    flight_controller: bool,
) -> ReferenceSamples {
    let times: Vec<f64> = samples.iter().map(|s| s.t_s).collect();
    let refs = reference_quaternions(&times, poses, alignment, max_gap_s);
    let fc: Vec<Option<UnitQuaternion<f64>>> = if flight_controller {
        held_attitude_interpolated(samples)
    } else {
        vec![None; samples.len()]
    };
    let with_reference = refs.iter().filter(|r| r.is_some()).count();
    let out = samples
        .iter()
        .zip(&refs)
        .zip(&fc)
        .map(|((s, r), f)| {
            let scored = r.filter(|_| !flight_controller || f.is_some());
            Sample {
                ref_q: scored.map(|q| [q.w, q.i, q.j, q.k]),
                moving: None,
                ..*s
            }
        })
        .collect();
    ReferenceSamples {
        samples: out,
        flight_controller: fc,
        with_reference,
    }
}

/// Longest time between two changes of a held attitude that is interpolated, s.
const MAX_HOLD_S: f64 = 0.2;

/// The attitude a log carries in `ref_q`, interpolated between the samples where it changes. A
/// flight-controller log carries its attitude as the newest reading, held over the samples that
/// follow (PX4 logs `vehicle_attitude` at about 20 Hz, the IMU at 200 Hz): held, it lags the
/// motion by half a reading interval on average (PX4's inclination RMSE against the capture of
/// `px4_fmuv5_indoor_a.ulg` in the shared data: 0.66 deg held, 0.32 deg interpolated). A change is taken at the first sample that carries it (at most one
/// sample interval after the reading); where changes are more than 0.2 s apart the value is held.
fn held_attitude_interpolated(samples: &[Sample]) -> Vec<Option<UnitQuaternion<f64>>> {
    // (time, attitude) where the carried value changes.
    let mut knots: Vec<Pose> = Vec::new();
    let mut last: Option<[f64; 4]> = None;
    for s in samples {
        match (s.ref_q, eval::reference(s)) {
            (Some(r), Some(q)) if last != Some(r) => {
                last = Some(r);
                knots.push(Pose { t_s: s.t_s, q });
            }
            (Some(_), Some(_)) => {}
            _ => last = None,
        }
    }
    samples
        .iter()
        .map(|s| {
            let held = eval::reference(s)?;
            Some(interpolate(&knots, s.t_s, MAX_HOLD_S).unwrap_or(held))
        })
        .collect()
}

/// The scores of a log's estimators against a capture (`imucald eval LOG --reference CAPTURE`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ReferenceEvaluation {
    /// How the capture was aligned with the log.
    pub alignment: MocapAlignment,
    /// imucald's orientation filter.
    pub filter: FilterEvaluation,
    /// The flight controller's own attitude (PX4 `vehicle_attitude`, ArduPilot `ATT`, MAVLink
    /// ATTITUDE) against the same reference, when the log has it: its name and scores.
    pub flight_controller: Option<(String, EvalResult)>,
    /// Samples the capture covers.
    pub samples_with_reference: usize,
}

impl ReferenceEvaluation {
    /// Plain-text summary: the alignment, then the RMSE lines of each estimator.
    pub fn to_text(&self) -> String {
        let mut s = self.alignment.to_text();
        s += "the capture world's heading is not observable: a constant heading offset is removed \
              per estimator before its RMSE\n";
        s += &self.filter.to_text();
        if let Some((name, m)) = &self.flight_controller {
            s += &format!(
                "{name} against the same reference, over {} samples:\n",
                m.samples
            );
            s += &format!("  total RMSE        {:.3} deg\n", m.total_rmse_deg);
            s += &format!("  heading RMSE      {:.3} deg\n", m.heading_rmse_deg);
            s += &format!("  inclination RMSE  {:.3} deg\n", m.inclination_rmse_deg);
            s += &format!(
                "  removed offsets: heading {:.2} deg, misalignment {:.2} deg\n",
                m.heading_offset_deg, m.misalignment_deg
            );
        }
        s
    }
}

/// Score imucald's orientation filter (`fusion`) and, when `flight_controller` names it, the
/// attitude the log carries in `ref_q`, against the capture aligned by `alignment`, on the same
/// samples. `align` must remove at least the heading (the capture's heading is unknown).
pub fn evaluate_against_reference(
    samples: &[Sample],
    poses: &[Pose],
    alignment: &MocapAlignment,
    fusion: &FusionConfig,
    align: Alignment,
    flight_controller: Option<&str>,
) -> Result<ReferenceEvaluation, Error> {
    if align == Alignment::None {
        return Err(Error::Other(
            "the capture world's heading is not known: align at least the heading \
             (--align heading or heading-and-misalignment)"
                .into(),
        ));
    }
    let has_fc =
        flight_controller.is_some() && samples.iter().any(|s| eval::reference(s).is_some());
    let prepared = reference_samples(samples, poses, alignment, MAX_GAP_S, has_fc);
    let filter = eval::evaluate_filter(&prepared.samples, fusion, align).ok_or_else(|| {
        Error::Other(format!(
            "no sample of the log falls inside the capture at offset {:.3} s",
            alignment.time_offset_s
        ))
    })?;
    let fc = match flight_controller {
        Some(name) if has_fc => {
            let est: Vec<UnitQuaternion<f64>> = prepared
                .flight_controller
                .iter()
                .map(|q| q.unwrap_or_else(UnitQuaternion::identity))
                .collect();
            Some((
                name.to_string(),
                eval::evaluate_with(&prepared.samples, &est, align),
            ))
        }
        _ => None,
    };
    Ok(ReferenceEvaluation {
        alignment: *alignment,
        filter,
        flight_controller: fc,
        samples_with_reference: prepared.with_reference,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// The capture body's angular velocity (its own axes), rad/s: still until 3 s and from 30 to
    /// 33 s, a turn about every axis between.
    fn omega(t: f64) -> Vector3<f64> {
        let ramp = |a: f64| {
            (a.clamp(0.0, 1.0) * std::f64::consts::PI / 2.0)
                .sin()
                .powi(2)
        };
        let env = ramp((t - 3.0) / 2.0) * (1.0 - ramp((t - 28.0) / 2.0) + ramp((t - 33.0) / 2.0));
        env * Vector3::new(
            0.9 * (0.9 * t).sin() + 0.3 * (2.3 * t + 1.0).sin(),
            0.6 * (1.3 * t + 0.5).sin() + 0.2 * (3.1 * t).cos(),
            0.8 * (0.7 * t + 2.0).sin() + 0.25 * (1.9 * t + 0.3).sin(),
        )
    }

    struct Scenario {
        poses: Vec<Pose>,
        samples: Vec<Sample>,
        offset_s: f64,
        b: UnitQuaternion<f64>,
        up: Vector3<f64>,
    }

    /// A capture at 180 Hz over 0..60 s (Y-up world, a little off level, 0.01 deg of noise) and a
    /// log at 200 Hz over 0..80 s whose clock is the capture's plus `offset_s`: the gyro sees
    /// `B omega + bias` with noise, the accelerometer gravity.
    fn scenario() -> Scenario {
        let offset_s = 7.3137;
        let b = UnitQuaternion::from_euler_angles(-1.52, -0.11, 1.73);
        let up = Vector3::new(-0.035, 1.0, -0.007).normalize();
        let bias = Vector3::new(0.001, -0.008, -0.004);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 1.0).unwrap();
        // Integrate the rotation at 1 kHz from tau = -10 s to 75 s.
        let dt = 1e-3;
        let (t_start, n) = (-10.0, 85_000);
        let mut fine = Vec::with_capacity(n + 1);
        let mut q = UnitQuaternion::from_euler_angles(0.1, 0.4, -0.2);
        for k in 0..=n {
            let t = t_start + k as f64 * dt;
            fine.push(Pose { t_s: t, q });
            q *= UnitQuaternion::from_scaled_axis(omega(t + dt / 2.0) * dt);
        }
        let at = |t: f64| interpolate(&fine, t, 1.0).unwrap();
        let sigma = 0.01f64.to_radians();
        let poses: Vec<Pose> = (0..=(60 * 180))
            .map(|j| {
                let t = j as f64 / 180.0;
                let e = Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                ) * sigma;
                Pose {
                    t_s: t,
                    q: at(t) * UnitQuaternion::from_scaled_axis(e),
                }
            })
            .collect();
        let samples: Vec<Sample> = (0..(80 * 200))
            .map(|i| {
                let t = i as f64 / 200.0;
                let tau = t - offset_s;
                let w = b * omega(tau)
                    + bias
                    + Vector3::new(
                        noise.sample(&mut rng),
                        noise.sample(&mut rng),
                        noise.sample(&mut rng),
                    ) * 0.005;
                let f = b * (at(tau).inverse() * (up * 9.81));
                Sample {
                    t_s: t,
                    gyro_rad_s: Some([w[0], w[1], w[2]]),
                    accel_mps2: Some([f[0], f[1], f[2]]),
                    ..Default::default()
                }
            })
            .collect();
        Scenario {
            poses,
            samples,
            offset_s,
            b,
            up,
        }
    }

    #[test]
    fn known_offset_rotation_and_tilt_are_recovered() {
        let s = scenario();
        let a = align_to_log(&s.samples, &s.poses, &AlignOptions::default()).unwrap();
        // Measured (seed 7): offset error 0.51 ms (the refinement steps 1 ms), B 0.0137 deg, up
        // 0.0053 deg, residual 1.04 deg/s (the capture's 0.01 deg of noise across a 20 ms window,
        // the gyro's 0.005 rad/s), correlation 0.99964. Tolerances about three times those.
        let off_err = (a.time_offset_s - s.offset_s).abs();
        let b_err = a.body_rotation.angle_to(&s.b).to_degrees();
        let up_err = Vector3::from(a.up_in_mocap).angle(&s.up).to_degrees();
        eprintln!(
            "offset error {:.2} ms, B error {b_err:.4} deg, up error {up_err:.4} deg, residual {:.3} deg/s, \
             correlation {:.5}, pairs {} ({} left out)",
            off_err * 1e3,
            a.rate_residual_rms_deg_s,
            a.correlation,
            a.pairs_used,
            a.pairs_rejected
        );
        assert!(off_err < 1.5e-3, "{a:?}");
        assert!(b_err < 0.04, "{a:?}");
        assert!(up_err < 0.016, "{a:?}");
        assert!(a.rate_residual_rms_deg_s < 3.1, "{a:?}");
        assert!(a.correlation > 0.99, "{a:?}");
        assert!((a.gyro_bias_rad_s[1] + 0.008).abs() < 3e-4, "{a:?}");
        // The reference maps the specific force to +z (up) and covers the capture's span.
        let times: Vec<f64> = s.samples.iter().map(|x| x.t_s).collect();
        let refs = reference_quaternions(&times, &s.poses, &a, MAX_GAP_S);
        let mut worst = 0.0f64;
        for (x, r) in s.samples.iter().zip(&refs) {
            let inside = (0.0..=60.0).contains(&(x.t_s - s.offset_s));
            assert_eq!(r.is_some(), inside, "t {}", x.t_s);
            if let (Some(r), Some(f)) = (r, x.accel_mps2) {
                worst = worst.max((r * Vector3::from(f)).angle(&Vector3::z()).to_degrees());
            }
        }
        // Measured 0.077 deg at worst (the capture's noise on single poses).
        eprintln!("gravity off +z by at most {worst:.4} deg");
        assert!(worst < 0.23, "gravity off +z by {worst} deg");
    }

    #[test]
    fn search_window_limits_the_offset() {
        let s = scenario();
        let opts = AlignOptions {
            offset_window_s: Some((-2.0, 2.0)),
            ..Default::default()
        };
        // The true 7.3 s lies outside: whatever is found lies inside and correlates worse.
        let a = align_to_log(&s.samples, &s.poses, &opts);
        if let Ok(a) = a {
            assert!(a.correlation_offset_s.abs() <= 2.0 + 0.01, "{a:?}");
            assert!(a.correlation < 0.9, "{a:?}");
        }
    }

    #[test]
    fn glitches_are_left_out_and_gaps_give_no_reference() {
        let mut s = scenario();
        // A capture glitch: 0.1 s held, then a jump of 8 deg that decays (as in real takes).
        let kick = UnitQuaternion::from_euler_angles(0.14, 0.0, 0.0);
        for p in s.poses.iter_mut().filter(|p| (20.0..20.5).contains(&p.t_s)) {
            p.q *= kick;
        }
        // A gap of 0.2 s.
        s.poses.retain(|p| !(40.0..40.2).contains(&p.t_s));
        let a = align_to_log(&s.samples, &s.poses, &AlignOptions::default()).unwrap();
        eprintln!(
            "with a glitch: B error {:.4} deg, {} pairs left out, offset error {:.2} ms",
            a.body_rotation.angle_to(&s.b).to_degrees(),
            a.pairs_rejected,
            (a.time_offset_s - s.offset_s).abs() * 1e3
        );
        // Measured: 52 pairs left out, B error 0.0125 deg, offset error 0.41 ms.
        assert!(a.pairs_rejected > 0, "{a:?}");
        assert!(a.body_rotation.angle_to(&s.b).to_degrees() < 0.04, "{a:?}");
        assert!((a.time_offset_s - s.offset_s).abs() < 1.5e-3, "{a:?}");
        let t = 40.1 + a.time_offset_s;
        assert!(reference_quaternions(&[t], &s.poses, &a, MAX_GAP_S)[0].is_none());
        let t = 39.0 + a.time_offset_s;
        assert!(reference_quaternions(&[t], &s.poses, &a, MAX_GAP_S)[0].is_some());
    }

    #[test]
    fn one_axis_rotation_is_refused() {
        let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = (0..200)
            .map(|i| {
                let w = Vector3::new(0.0, 0.0, (i as f64 * 0.1).sin());
                (w, w)
            })
            .collect();
        let e = fit_body_rotation(&pairs).unwrap_err();
        assert!(e.to_string().contains("one axis"), "{e}");
        assert!(fit_body_rotation(&pairs[..10]).is_err());
    }

    #[test]
    fn interpolation_takes_the_short_way_and_stops_at_gaps() {
        let a = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.1);
        let b = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3);
        // b with the opposite sign: the same rotation.
        let b_neg = UnitQuaternion::new_unchecked(-b.into_inner());
        let poses = [
            Pose { t_s: 0.0, q: a },
            Pose {
                t_s: 0.01,
                q: b_neg,
            },
            Pose { t_s: 0.2, q: b },
        ];
        let m = interpolate(&poses, 0.005, MAX_GAP_S).unwrap();
        assert!((m.euler_angles().2 - 0.2).abs() < 1e-12);
        assert!(interpolate(&poses, 0.1, MAX_GAP_S).is_none());
        assert!(interpolate(&poses, -0.1, MAX_GAP_S).is_none());
        assert!(interpolate(&poses, 0.3, MAX_GAP_S).is_none());
        assert!(interpolate(&poses, 0.2, MAX_GAP_S).is_some());
        assert!(interpolate(&poses, f64::NAN, MAX_GAP_S).is_none());
    }

    #[test]
    fn tilt_takes_up_to_z() {
        let u = Vector3::new(-0.035, 1.0, -0.007);
        let t = world_tilt(&u).unwrap();
        assert!((t * u.normalize() - Vector3::z()).norm() < 1e-12);
        let t = world_tilt(&-Vector3::z()).unwrap();
        assert!((t * -Vector3::z() - Vector3::z()).norm() < 1e-12);
        assert!(world_tilt(&Vector3::zeros()).is_err());
    }
}
