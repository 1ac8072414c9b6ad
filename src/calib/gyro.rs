//! Gyroscope calibration from static poses and the rotations between them. Pure math, no I/O.
//!
//! * **Bias** from static poses: the mean gyro reading of each still pose is the bias at that pose's
//!   temperature. With temperatures that vary (spread >= `min_temp_span_c` over >= 3 poses), a weighted
//!   linear fit `bias(T) = b0 + k (T - T_ref)` per axis gives the drift; otherwise the weighted mean.
//! * **Scale and misalignment** (the 12-parameter model of Chu et al., "Magnetic Orientation System Based on
//!   Magnetometer, Accelerometer and Gyroscope": `omega = K (raw - b)`: a general 3x3 `K`
//!   plus the bias, the same `calibrated = M (raw - o)` convention as the other sensors): between two
//!   static poses the calibrated gyro is integrated and the rotation it gives must carry the gravity
//!   direction measured at the first pose onto the one measured at the next (the method of imu_tk:
//!   Tedaldi, Pretto, Menegatti, ICRA 2014). The bias comes from the poses; `K` (9 parameters) is the
//!   Levenberg-Marquardt least-squares solution over all pose pairs. The gravity directions tie `K` to
//!   the accelerometer's axes, so all 9 entries are determined when the rotations between poses
//!   turn about varied axes; with too few or too similar rotations the fit reports failure.
//!
//! `K` is published only when it is checked: the rotation axes must span all three directions (about
//! one axis, or axes in one plane, the scale about the others cannot be determined), and a second
//! fit on every other rotation must carry gravity over the rotations it did not see at least about
//! as well as the bias alone ([`HELD_OUT_MARGIN`]); otherwise a named failure ([`ScaleFailure`]).
//!
//! The accelerometer readings should be calibrated first (the directions matter, not the norm): pass
//! the accelerometer calibration, or identity when the readings are already calibrated.

use crate::calib::fit::FitFailure;
use crate::calib::gate::{GateConfig, Pose, StaticDetector};
use crate::calib::model::Calibration;
use crate::types::{Sample, Vec3};
use nalgebra::{Matrix3, SMatrix, SVector, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Gyro bias, possibly temperature dependent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GyroBias {
    /// Bias at `temp_ref_c` (or the mean over the poses), rad/s (raw units).
    pub bias: Vec3,
    /// Drift per deg C, when fitted.
    pub temp_coeff: Option<Vec3>,
    /// Reference temperature of `bias`, deg C (the weighted mean pose temperature).
    pub temp_ref_c: Option<f64>,
    /// 1-sigma of `bias` per axis from the scatter of the poses, rad/s.
    pub bias_sigma: Vec3,
    /// Poses used.
    pub poses: usize,
}

impl GyroBias {
    /// The bias at a temperature (the constant bias when no drift was fitted or no temperature given).
    pub fn at(&self, temp_c: Option<f64>) -> Vec3 {
        match (self.temp_coeff, self.temp_ref_c, temp_c) {
            (Some(k), Some(t0), Some(t)) => [
                self.bias[0] + k[0] * (t - t0),
                self.bias[1] + k[1] * (t - t0),
                self.bias[2] + k[2] * (t - t0),
            ],
            _ => self.bias,
        }
    }
}

/// Settings of [`bias_from_poses`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct BiasOptions {
    /// Smallest temperature spread over the poses that allows a drift fit, deg C.
    pub min_temp_span_c: f64,
    /// Smallest number of poses with a temperature for a drift fit.
    pub min_temp_poses: usize,
}

impl Default for BiasOptions {
    fn default() -> Self {
        BiasOptions {
            min_temp_span_c: 1.0,
            min_temp_poses: 3,
        }
    }
}

/// Bias (and its temperature drift when temperatures vary) from the static poses' mean gyro readings,
/// each weighted by its sample count, the poses at rest only ([`Pose::at_rest`]: a steady turn
/// holds the gyro steady too). `None` without a pose at rest that has gyro data.
pub(crate) fn bias_from_poses(poses: &[Pose], opt: &BiasOptions) -> Option<GyroBias> {
    let pts: Vec<(Vec3, f64, Option<f64>)> = poses
        .iter()
        .filter(|p| p.at_rest())
        .filter_map(|p| p.gyro.map(|g| (g, p.samples.max(1) as f64, p.temp_c)))
        .filter(|(g, _, _)| crate::types::is_finite3(g))
        .collect();
    if pts.is_empty() {
        return None;
    }
    let wsum: f64 = pts.iter().map(|p| p.1).sum();
    let mean = |k: usize| pts.iter().map(|p| p.0[k] * p.1).sum::<f64>() / wsum;
    let m = [mean(0), mean(1), mean(2)];
    let temps: Vec<(f64, f64)> = pts
        .iter()
        .filter_map(|p| p.2.filter(|t| t.is_finite()).map(|t| (t, p.1)))
        .collect();
    let span = temps.iter().map(|t| t.0).fold(f64::NEG_INFINITY, f64::max)
        - temps.iter().map(|t| t.0).fold(f64::INFINITY, f64::min);
    let n = pts.len() as f64;
    if temps.len() == pts.len() && temps.len() >= opt.min_temp_poses && span >= opt.min_temp_span_c
    {
        // Weighted linear regression per axis on (T - T_ref).
        let t0 = temps.iter().map(|t| t.0 * t.1).sum::<f64>() / wsum;
        let stt: f64 = pts.iter().map(|p| p.1 * (p.2.unwrap() - t0).powi(2)).sum();
        let mut b = [0.0; 3];
        let mut k = [0.0; 3];
        let mut sig = [0.0; 3];
        for ax in 0..3 {
            let sgt: f64 = pts
                .iter()
                .map(|p| p.1 * (p.2.unwrap() - t0) * (p.0[ax] - m[ax]))
                .sum();
            k[ax] = sgt / stt;
            b[ax] = m[ax];
            let res: f64 = pts
                .iter()
                .map(|p| p.1 * (p.0[ax] - b[ax] - k[ax] * (p.2.unwrap() - t0)).powi(2))
                .sum::<f64>()
                / wsum;
            sig[ax] = (res / (n - 2.0).max(1.0)).sqrt();
        }
        return Some(GyroBias {
            bias: b,
            temp_coeff: Some(k),
            temp_ref_c: Some(t0),
            bias_sigma: sig,
            poses: pts.len(),
        });
    }
    let mut sig = [0.0; 3];
    for ax in 0..3 {
        let var = pts
            .iter()
            .map(|p| p.1 * (p.0[ax] - m[ax]).powi(2))
            .sum::<f64>()
            / wsum;
        sig[ax] = (var / (n - 1.0).max(1.0)).sqrt();
    }
    Some(GyroBias {
        bias: m,
        temp_coeff: None,
        temp_ref_c: temps.first().map(|t| t.0),
        bias_sigma: sig,
        poses: pts.len(),
    })
}

/// Static poses of a log by the project's static detector on the accelerometer.
pub fn static_poses(samples: &[Sample], cfg: &GateConfig) -> Vec<Pose> {
    let mut det = StaticDetector::new(*cfg);
    let mut poses = Vec::new();
    for s in samples {
        if let Some(a) = s.accel_mps2 {
            poses.extend(det.push(s, &a));
        }
    }
    poses.extend(det.finish());
    poses
}

/// The 12-parameter gyro calibration `omega = matrix (raw - bias)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GyroFit {
    /// Row-major scale/misalignment matrix `K`.
    pub matrix: [[f64; 3]; 3],
    /// The bias used (from the poses), raw units.
    pub bias: GyroBias,
    /// RMS angle between predicted and measured gravity directions, before and after, degrees.
    pub rms_before_deg: f64,
    pub rms_after_deg: f64,
    /// Pose pairs (rotations) used.
    pub segments: usize,
    /// Smallest singular value of the normal matrix relative to the largest: how well the
    /// rotations determine all 9 entries (near 0: badly).
    pub conditioning: f64,
    /// Error on rotations held out of a second fit ([`fit_scale`] returns no fit without it).
    pub held_out: Option<HeldOut>,
}

impl GyroFit {
    /// The fit as a [`Calibration`] (offset = constant bias, model full12).
    pub fn calibration(&self) -> Calibration {
        Calibration {
            model: crate::calib::model::ModelKind::Full12,
            offset: self.bias.bias,
            matrix: self.matrix,
        }
    }

    /// Apply to a raw reading at a temperature.
    pub fn apply(&self, raw: &Vec3, temp_c: Option<f64>) -> Vec3 {
        let b = self.bias.at(temp_c);
        let k = crate::calib::model::rows_to_mat(&self.matrix);
        let w = k * Vector3::new(raw[0] - b[0], raw[1] - b[1], raw[2] - b[2]);
        [w.x, w.y, w.z]
    }
}

/// Settings of [`fit_scale`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ScaleOptions {
    /// Fewest pose pairs.
    pub min_segments: usize,
    /// Smallest rotation between two poses that is used, degrees (smaller ones carry little scale
    /// information).
    pub min_rotation_deg: f64,
    /// Longest motion between two poses, s (longer gaps are likely missing data).
    pub max_gap_s: f64,
    /// Largest accepted relative conditioning of the normal matrix.
    pub min_conditioning: f64,
    /// The gyro reads raw counts: start from the best isotropic scale instead of the identity.
    pub raw_in_counts: bool,
}

impl Default for ScaleOptions {
    fn default() -> Self {
        ScaleOptions {
            min_segments: 6,
            min_rotation_deg: 20.0,
            max_gap_s: 30.0,
            min_conditioning: 1e-4,
            raw_in_counts: false,
        }
    }
}

/// One rotation between two static poses: raw gyro samples (with their time steps) and the gravity
/// directions at both ends.
#[derive(Clone)]
struct Segment {
    steps: Vec<(Vec3, f64)>,
    up0: Vector3<f64>,
    up1: Vector3<f64>,
}

fn unit(v: &Vec3) -> Option<Vector3<f64>> {
    let u = Vector3::new(v[0], v[1], v[2]);
    let n = u.norm();
    (n > 0.0 && n.is_finite()).then(|| u / n)
}

/// Steps of rotation (gyro samples) from which a pass of the scale fit over its segments is split
/// over two threads. A step costs about 25 ns to carry and starting a thread about 20 us, so below
/// this the second thread would save little.
const PARALLEL_MIN_STEPS: usize = 20_000;

/// `f` of every item, in order: the items from `at` on on a second thread when `at` splits them.
/// Each result is the one `f` gives alone, so the list is the one a single thread makes, to the
/// bit.
fn map_split<T: Sync, U: Send>(items: &[T], at: usize, f: impl Fn(&T) -> U + Sync) -> Vec<U> {
    if at == 0 || at >= items.len() {
        return items.iter().map(f).collect();
    }
    let (first, later) = items.split_at(at);
    let f = &f;
    std::thread::scope(|scope| {
        let later = scope.spawn(move || later.iter().map(f).collect::<Vec<U>>());
        let mut out: Vec<U> = Vec::with_capacity(items.len());
        out.extend(first.iter().map(f));
        out.extend(
            later
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
        );
        out
    })
}

/// `f` of every segment, in order ([`map_split`]), split where half of the steps are done when
/// there are at least [`PARALLEL_MIN_STEPS`].
fn map_segments<U: Send>(segs: &[&Segment], f: impl Fn(&Segment) -> U + Sync) -> Vec<U> {
    let total: usize = segs.iter().map(|s| s.steps.len()).sum();
    let at = if total >= PARALLEL_MIN_STEPS {
        let mut done = 0;
        segs.iter()
            .position(|s| {
                done += s.steps.len();
                2 * done >= total
            })
            .map_or(0, |i| i + 1)
    } else {
        0
    };
    map_split(segs, at, |s| f(s))
}

/// The rotation of one step, `exp` of the rotation vector `v`: cos(t/2) + sin(t/2)/t v; Taylor
/// below 0.1 rad (error < 1e-11), which saves the sin/cos at IMU rates.
fn step_rotation(v: &Vector3<f64>) -> nalgebra::Quaternion<f64> {
    let t2 = v.norm_squared();
    let (c, s) = if t2 < 0.01 {
        (
            1.0 - t2 / 8.0 + t2 * t2 / 384.0,
            0.5 - t2 / 48.0 + t2 * t2 / 3840.0,
        )
    } else {
        let t = t2.sqrt();
        ((0.5 * t).cos(), (0.5 * t).sin() / t)
    };
    nalgebra::Quaternion::new(c, s * v.x, s * v.y, s * v.z)
}

/// Integrate `K (raw - bias)` over a segment: the rotation from the end sensor frame to the start one.
fn integrate(seg: &Segment, k: &Matrix3<f64>) -> UnitQuaternion<f64> {
    let mut q = nalgebra::Quaternion::identity();
    for (w, dt) in &seg.steps {
        q *= step_rotation(&(k * Vector3::new(w[0], w[1], w[2]) * *dt));
    }
    UnitQuaternion::from_quaternion(q)
}

/// The left Jacobian of SO(3) at the rotation vector `v`: `exp(v + d) ~ exp(J_l d) exp(v)`,
/// `J_l = I + (1 - cos t)/t^2 [v]x + (t - sin t)/t^3 [v]x^2` (Taylor below 0.1 rad), built as
/// `(1 - b t^2) I + a [v]x + b v v^T` (`[v]x^2 = v v^T - t^2 I`: no matrix product).
fn left_jacobian(v: &Vector3<f64>) -> Matrix3<f64> {
    let t2 = v.norm_squared();
    let (a, b) = if t2 < 0.01 {
        (
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
        )
    } else {
        let t = t2.sqrt();
        ((1.0 - t.cos()) / t2, (t - t.sin()) / (t2 * t))
    };
    let c = 1.0 - b * t2;
    let (x, y, z) = (v.x, v.y, v.z);
    let (bx, by, bz) = (b * x, b * y, b * z);
    let (ax, ay, az) = (a * x, a * y, a * z);
    Matrix3::new(
        c + bx * x,
        bx * y - az,
        bx * z + ay,
        by * x + az,
        c + by * y,
        by * z - ax,
        bz * x - ay,
        bz * y + ax,
        c + bz * z,
    )
}

/// [`integrate`] with the derivative of the rotation over the entries of `K` (row-major): `G`
/// such that the rotation with `K + dK` is `exp(G dk) q`, to first order. A step's rotation
/// vector `K a` moves by `dK a`, which turns the whole rotation by `P J_l(K a) dK a`, `P` the
/// rotation of the steps before it; the sum over the steps is `G dk`. One pass, in place of one
/// integration per entry of `K` that a differenced Jacobian takes.
fn integrate_with_derivative(
    seg: &Segment,
    k: &Matrix3<f64>,
) -> (UnitQuaternion<f64>, SMatrix<f64, 3, 9>) {
    let mut q = nalgebra::Quaternion::<f64>::identity();
    let mut g = SMatrix::<f64, 3, 9>::zeros();
    for (w, dt) in &seg.steps {
        let a = Vector3::new(w[0], w[1], w[2]) * *dt;
        let v = k * a;
        // The rotation so far (unit to the Taylor's 1e-11: only the derivative uses it).
        let before = UnitQuaternion::new_unchecked(q).to_rotation_matrix();
        let m = before.matrix() * left_jacobian(&v);
        for r in 0..3 {
            for s in 0..3 {
                for i in 0..3 {
                    g[(i, 3 * r + s)] += m[(i, r)] * a[s];
                }
            }
        }
        q *= step_rotation(&v);
    }
    (UnitQuaternion::from_quaternion(q), g)
}

/// Residual of one segment: measured end direction minus the start direction carried by the rotation.
fn residual(seg: &Segment, k: &Matrix3<f64>) -> Vector3<f64> {
    let q = integrate(seg, k);
    // A world-fixed vector: v_end = q^-1 v_start.
    let pred = q.inverse() * seg.up0;
    seg.up1 - pred
}

/// One segment carried with one `K`: the integrated rotation, the [`residual`] and its Jacobian
/// over the entries of `K` (row-major).
#[derive(Debug, Clone, Copy)]
struct Carried {
    rotation: UnitQuaternion<f64>,
    r: Vector3<f64>,
    j: SMatrix<f64, 3, 9>,
}

/// [`Carried`] of a segment: with the rotation turned by `exp(G dk)`, the carried direction
/// `q^-1 up0` moves by `q^-1 (up0 x G dk)`.
fn carry(seg: &Segment, k: &Matrix3<f64>) -> Carried {
    let (q, g) = integrate_with_derivative(seg, k);
    let inv = q.inverse();
    let r = seg.up1 - inv * seg.up0;
    let j = -(inv.to_rotation_matrix().matrix() * seg.up0.cross_matrix()) * g;
    Carried { rotation: q, r, j }
}

/// The normal equations of carried segments: sum of squared residuals, J^T J and J^T r.
type Normal9 = (f64, SMatrix<f64, 9, 9>, SVector<f64, 9>);

fn normal_of(carried: impl Iterator<Item = Carried>) -> Normal9 {
    let mut jtj = SMatrix::<f64, 9, 9>::zeros();
    let mut jtr = SVector::<f64, 9>::zeros();
    let mut ssr = 0.0;
    for c in carried {
        ssr += c.r.norm_squared();
        jtj += c.j.transpose() * c.j;
        jtr += c.j.transpose() * c.r;
    }
    (ssr, jtj, jtr)
}

fn k_from(p: &[f64]) -> Matrix3<f64> {
    Matrix3::new(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8])
}

/// RMS angle (deg) between the measured end gravity directions and the start directions carried by
/// the integrated rotations.
fn rms_deg(segs: &[&Segment], k: &Matrix3<f64>) -> f64 {
    let rotations = map_segments(segs, |s| integrate(s, k));
    rms_deg_of(segs.iter().copied().zip(rotations))
}

/// [`rms_deg`] of segments with their rotations already integrated.
fn rms_deg_of<'a>(
    carried: impl ExactSizeIterator<Item = (&'a Segment, UnitQuaternion<f64>)>,
) -> f64 {
    let n = carried.len();
    if n == 0 {
        return f64::NAN;
    }
    let s: f64 = carried
        .map(|(s, q)| (q.inverse() * s.up0).angle(&s.up1).powi(2))
        .sum();
    (s / n as f64).sqrt().to_degrees()
}

/// The part of a sample the scale fit reads: its time (s), time segment, angular rate (rad/s, or
/// counts) and temperature (deg C); a quarter of a whole sample, for the rotations of a log too
/// long to keep whole.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Rate {
    pub t_s: f64,
    pub segment: u32,
    pub gyro_rad_s: Option<Vec3>,
    pub temp_c: Option<f64>,
}

impl From<&Sample> for Rate {
    fn from(s: &Sample) -> Rate {
        Rate {
            t_s: s.t_s,
            segment: s.segment,
            gyro_rad_s: s.gyro_rad_s,
            temp_c: s.temp_c,
        }
    }
}

/// What the scale fit reads: a whole [`Sample`], or its [`Rate`] alone (shared with the thread of
/// [`map_split`]).
pub(crate) trait RateReading: Sync {
    fn rate(&self) -> Rate;
}

impl RateReading for Sample {
    fn rate(&self) -> Rate {
        self.into()
    }
}

impl RateReading for Rate {
    fn rate(&self) -> Rate {
        *self
    }
}

/// The rotations between consecutive static poses, bias removed. With at least
/// [`PARALLEL_MIN_STEPS`] samples, the later half of the pose pairs on a second thread
/// ([`map_split`]).
fn segments(
    samples: &[impl RateReading],
    poses: &[Pose],
    bias: &GyroBias,
    accel: &Calibration,
    opt: &ScaleOptions,
) -> Vec<Segment> {
    let pairs: Vec<&[Pose]> = poses.windows(2).collect();
    let at = if samples.len() >= PARALLEL_MIN_STEPS {
        pairs.len() / 2
    } else {
        0
    };
    map_split(&pairs, at, |pair| {
        segment(samples, (&pair[0], &pair[1]), bias, accel, opt)
    })
    .into_iter()
    .flatten()
    .collect()
}

/// The rotation from pose `p0` to the next, `p1` ([`segments`]): `None` across a break in the
/// source's time, below [`ScaleOptions::min_rotation_deg`] or without a step.
fn segment(
    samples: &[impl RateReading],
    (p0, p1): (&Pose, &Pose),
    bias: &GyroBias,
    accel: &Calibration,
    opt: &ScaleOptions,
) -> Option<Segment> {
    // No rotation is integrated across a break in the source's time.
    if p0.segment != p1.segment || p1.t_start - p0.t_end > opt.max_gap_s {
        return None;
    }
    let up0 = unit(&accel.apply(&p0.accel))?;
    let up1 = unit(&accel.apply(&p1.accel))?;
    if up0.angle(&up1).to_degrees() < opt.min_rotation_deg {
        return None;
    }
    // From the middle of one pose to the middle of the next.
    let ta = 0.5 * (p0.t_start + p0.t_end);
    let tb = 0.5 * (p1.t_start + p1.t_end);
    // Sample times never decrease (`crate::io::clock`), so the span is found by bisection; a
    // caller's unsorted samples give an empty span, never a bad slice.
    let i0 = samples.partition_point(|s| s.rate().t_s < ta);
    let i1 = samples.partition_point(|s| s.rate().t_s < tb).max(i0);
    let mut steps = Vec::with_capacity(i1 - i0);
    let mut prev: Option<(Vec3, f64)> = None;
    for s in samples[i0..i1].iter().map(RateReading::rate) {
        if s.segment != p0.segment {
            prev = None;
            continue;
        }
        let Some(g) = s.gyro_rad_s else { continue };
        if !crate::types::is_finite3(&g) {
            continue;
        }
        let b = bias.at(s.temp_c);
        let w = [g[0] - b[0], g[1] - b[1], g[2] - b[2]];
        if let Some((wp, tp)) = prev {
            let dt = s.t_s - tp;
            if dt > 0.0 && dt < 1.0 {
                // Midpoint rate over the step.
                let m = [
                    0.5 * (w[0] + wp[0]),
                    0.5 * (w[1] + wp[1]),
                    0.5 * (w[2] + wp[2]),
                ];
                steps.push((m, dt));
            }
        }
        prev = Some((w, s.t_s));
    }
    (!steps.is_empty()).then_some(Segment { steps, up0, up1 })
}

/// The isotropic scale `s` (K = s I) that best carries the gravity directions: a log-spaced scan
/// from 1e-6 to 10 (raw counts to rad/s included), then a golden-section refinement. The cost is
/// multimodal in `s` (an over-scaled rotation wraps around), hence the scan first.
fn isotropic_scale(segs: &[&Segment]) -> f64 {
    let cost = |s: f64| -> f64 {
        let k = Matrix3::identity() * s;
        let squares = map_segments(segs, |g| residual(g, &k).norm_squared());
        squares.iter().sum()
    };
    let (lo, hi, n) = (1e-6f64.ln(), 10f64.ln(), 240);
    let step = (hi - lo) / n as f64;
    let mut best = (f64::INFINITY, lo);
    for i in 0..=n {
        let x = lo + step * i as f64;
        let c = cost(x.exp());
        if c < best.0 {
            best = (c, x);
        }
    }
    // Golden section on [x - step, x + step].
    let (mut a, mut b) = (best.1 - step, best.1 + step);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..40 {
        let (c1, c2) = (b - g * (b - a), a + g * (b - a));
        if cost(c1.exp()) < cost(c2.exp()) {
            b = c2;
        } else {
            a = c1;
        }
    }
    (0.5 * (a + b)).exp()
}

/// Most Jacobians of the Levenberg-Marquardt fit of `K`.
const K_FIT_MAX_ITER: usize = 50;

/// Levenberg-Marquardt ([`crate::calib::lm`]) on the 9 entries of `K` from `k0`, the residuals being every
/// segment's end-direction error, with their analytic Jacobian ([`carry`]). `start`: the normal
/// equations at `k0` when the caller has them (the iteration's first evaluation, which is at
/// `k0`, then takes them). Returns `K` and the relative conditioning of the normal matrix at the
/// solution (smallest over largest singular value).
fn fit_k(segs: &[&Segment], k0: &Matrix3<f64>, start: Option<Normal9>) -> (Matrix3<f64>, f64) {
    let mut start = start;
    let eval = |p: &SVector<f64, 9>, _with_jtj: bool| {
        let (ssr, jtj, jtr) = start.take().unwrap_or_else(|| {
            let k = k_from(p.as_slice());
            normal_of(map_segments(segs, |s| carry(s, &k)).into_iter())
        });
        (ssr, Some(jtj), jtr)
    };
    let p0 = SVector::<f64, 9>::from_iterator(k0.transpose().iter().copied());
    let opts = crate::calib::lm::LmOptions::new(K_FIT_MAX_ITER, crate::calib::lm::STOP_REL_GAIN);
    let fit = crate::calib::lm::minimise_normal(p0, &opts, eval);
    let sv = fit.jtj.singular_values();
    let (smax, smin) = (sv.max(), sv.min());
    let conditioning = if smax > 0.0 { smin / smax } else { 0.0 };
    (k_from(fit.params.as_slice()), conditioning)
}

/// Gravity-direction error on rotations that the fit did not see.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeldOut {
    /// Rotations held out (every other one, in time order).
    pub segments: usize,
    /// RMS angle with the bias-only model `K = s I` (`s` = 1 for a gyro in rad/s, otherwise the best
    /// isotropic scale of the fitting half), degrees.
    pub rms_before_deg: f64,
    /// RMS angle with `K` fitted on the other half, degrees.
    pub rms_after_deg: f64,
}

/// Why no gyro scale is published, with the held-out figures when the check was made.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScaleFailure {
    pub failure: FitFailure,
    pub detail: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out: Option<HeldOut>,
}

impl ScaleFailure {
    fn new(failure: FitFailure, detail: String) -> ScaleFailure {
        ScaleFailure {
            failure,
            detail,
            held_out: None,
        }
    }
}

impl std::fmt::Display for ScaleFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.failure.name(), self.detail)
    }
}

/// The fitted `K` may do this much worse (relative RMS) than the bias-only model on the held-out
/// rotations and still be published (the half fit is noisier than the full one).
pub(crate) const HELD_OUT_MARGIN: f64 = 0.1;

/// Rotations off the main axis (or off the main plane) below this share of the RMS rotation count as
/// none: about 6 degrees of spread.
pub(crate) const MIN_AXIS_SPREAD: f64 = 0.1;

/// Which directions the rotations between poses turn about.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum AxisSpan {
    /// About one axis only (unit vector, sensor axes).
    OneAxis(Vec3),
    /// About axes in one plane only (its normal).
    OnePlane(Vec3),
    /// All three directions.
    Full,
}

impl AxisSpan {
    /// The failure a scale fit on such rotations has, if any.
    pub fn failure(&self, rotations: usize) -> Option<ScaleFailure> {
        let f = |v: &Vec3| format!("[{:.2}, {:.2}, {:.2}]", v[0], v[1], v[2]);
        let detail = match self {
            AxisSpan::OneAxis(a) => format!(
                "rotations about one axis only ({rotations} rotations about {}): the scale about the other axes cannot be determined; turn about other axes too",
                f(a)
            ),
            AxisSpan::OnePlane(n) => format!(
                "rotations about axes in one plane only ({rotations} rotations, none about {}): the scale about it cannot be determined; turn about it too",
                f(n)
            ),
            AxisSpan::Full => return None,
        };
        Some(ScaleFailure::new(FitFailure::NotIdentifiable, detail))
    }
}

/// The span of the rotation vectors (axis times angle, of the rotations the gyro integrates to
/// between poses): the eigenvalues of their scatter matrix against [`MIN_AXIS_SPREAD`].
fn axis_span(rotations: impl Iterator<Item = UnitQuaternion<f64>>) -> AxisSpan {
    let mut m = Matrix3::zeros();
    for q in rotations {
        let r = q.scaled_axis();
        m += r * r.transpose();
    }
    let e = m.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| e.eigenvalues[b].total_cmp(&e.eigenvalues[a]));
    let l = order.map(|i| e.eigenvalues[i].max(0.0));
    let v = |i: usize| {
        let c = e.eigenvectors.column(order[i]);
        [c[0], c[1], c[2]]
    };
    let small = |x: f64| !(x > MIN_AXIS_SPREAD * MIN_AXIS_SPREAD * l[0]);
    if small(l[1]) {
        AxisSpan::OneAxis(v(0))
    } else if small(l[2]) {
        AxisSpan::OnePlane(v(2))
    } else {
        AxisSpan::Full
    }
}

/// The span of the rotations between the static poses ([`AxisSpan`]), with the bias and the
/// accelerometer calibration (identity for raw directions) that select them, as [`fit_scale`] does.
/// `None` without rotations.
pub(crate) fn rotation_axes(
    samples: &[impl RateReading],
    poses: &[Pose],
    bias: &GyroBias,
    accel: &Calibration,
    opt: &ScaleOptions,
) -> Option<(AxisSpan, usize)> {
    let segs = segments(samples, poses, bias, accel, opt);
    if segs.is_empty() {
        return None;
    }
    let segs: Vec<&Segment> = segs.iter().collect();
    let k0 = start_k(&segs, opt);
    Some((
        axis_span(segs.iter().map(|s| integrate(s, &k0))),
        segs.len(),
    ))
}

/// The starting `K`: identity for a gyro in rad/s, else the best isotropic scale.
fn start_k(segs: &[&Segment], opt: &ScaleOptions) -> Matrix3<f64> {
    if opt.raw_in_counts {
        Matrix3::identity() * isotropic_scale(segs)
    } else {
        Matrix3::identity()
    }
}

/// The held-out check of [`fit_scale`]: `K` fitted on every other rotation (from its own
/// starting `K`) and scored on the rest against that start ([`HeldOut`]). `at_k0`: every
/// segment carried with the full fit's starting `K`, which serve when the half starts from the
/// same `K` (a gyro in rad/s).
fn held_out_check(
    segs: &[&Segment],
    k0: &Matrix3<f64>,
    at_k0: &[Carried],
    opt: &ScaleOptions,
) -> HeldOut {
    let fit: Vec<&Segment> = segs.iter().step_by(2).copied().collect();
    let test: Vec<&Segment> = segs.iter().skip(1).step_by(2).copied().collect();
    let k0h = start_k(&fit, opt);
    let same = k0h == *k0;
    let start = same.then(|| normal_of(at_k0.iter().step_by(2).copied()));
    let (kf, _) = fit_k(&fit, &k0h, start);
    let rms_before_deg = if same {
        let odd = segs.iter().zip(at_k0).skip(1).step_by(2);
        rms_deg_of(odd.map(|(s, c)| (*s, c.rotation)))
    } else {
        rms_deg(&test, &k0h)
    };
    HeldOut {
        segments: test.len(),
        rms_before_deg,
        rms_after_deg: rms_deg(&test, &kf),
    }
}

/// Scale and misalignment from the rotations between consecutive static poses (`poses` in time order,
/// from [`static_poses`] or the pipeline), with the bias from [`bias_from_poses`] and the accelerometer
/// calibration that makes the pose means into directions.
///
/// `K` starts from the identity when `raw_in_counts` is false, otherwise from the best isotropic
/// scale (a raw-count gyro, e.g. imu_tk's Xsens at about 6258 counts per rad/s, needs no nominal
/// sensitivity). "Before" figures use that same starting `K`. It needs `2 * min_segments`
/// rotations about all three directions ([`AxisSpan`]); a second fit on every other rotation is
/// scored on the rest ([`GyroFit::held_out`]) and must not be worse than the starting `K` there by
/// more than [`HELD_OUT_MARGIN`]. Each refusal is a [`ScaleFailure`] naming its reason.
pub(crate) fn fit_scale(
    samples: &[impl RateReading],
    poses: &[Pose],
    bias: &GyroBias,
    accel: &Calibration,
    opt: &ScaleOptions,
) -> Result<GyroFit, ScaleFailure> {
    let segs = segments(samples, poses, bias, accel, opt);
    if segs.len() < 2 * opt.min_segments {
        return Err(ScaleFailure::new(
            FitFailure::NotEnoughSamples,
            format!(
                "{} rotations of at least {} deg between static poses; {} needed (half of them held out to check the fit)",
                segs.len(),
                opt.min_rotation_deg,
                2 * opt.min_segments
            ),
        ));
    }
    let segs: Vec<&Segment> = segs.iter().collect();
    let k0 = start_k(&segs, opt);
    // Every segment carried once with the starting `K`: the axis check, the "before" figures and
    // the first evaluation of both fits read it.
    let at_k0: Vec<Carried> = map_segments(&segs, |s| carry(s, &k0));
    if let Some(f) = axis_span(at_k0.iter().map(|c| c.rotation)).failure(segs.len()) {
        return Err(f);
    }
    // The fit on all rotations and the check on every other one are independent: the check (a
    // fit on half the rotations, scored on the rest) runs on a second thread meanwhile. Each sums
    // in the same order as alone, so the results are the same.
    let ((k, conditioning), held_out) = std::thread::scope(|scope| {
        let check = scope.spawn(|| held_out_check(&segs, &k0, &at_k0, opt));
        let full = fit_k(&segs, &k0, Some(normal_of(at_k0.iter().copied())));
        let check = check
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (full, check)
    });
    let rms_before_deg = rms_deg_of(segs.iter().zip(&at_k0).map(|(s, c)| (*s, c.rotation)));
    if conditioning < opt.min_conditioning {
        return Err(ScaleFailure::new(
            FitFailure::NotIdentifiable,
            format!(
                "the rotations between poses do not determine all 9 scale/misalignment terms (conditioning {conditioning:.1e}); turn about more varied axes"
            ),
        ));
    }
    if !(held_out.rms_after_deg <= held_out.rms_before_deg * (1.0 + HELD_OUT_MARGIN)) {
        return Err(ScaleFailure {
            failure: FitFailure::HeldOut,
            detail: format!(
                "on {} rotations held out of the fit the gravity direction is carried {:.2} deg off with the fitted scale, {:.2} deg with the bias alone: the rotations do not determine the scale (turn about more varied axes)",
                held_out.segments, held_out.rms_after_deg, held_out.rms_before_deg
            ),
            held_out: Some(held_out),
        });
    }
    Ok(GyroFit {
        matrix: crate::calib::model::mat_to_rows(&k),
        bias: *bias,
        rms_before_deg,
        rms_after_deg: rms_deg(&segs, &k),
        segments: segs.len(),
        conditioning,
        held_out: Some(held_out),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{simulate, Scenario};

    fn tumble(seed: u64) -> (Vec<Sample>, crate::sim::Truth) {
        tumble_with(seed, |_| {})
    }

    /// The part of the samples the fit reads ([`Rate`]) fits as the whole samples do, to the
    /// last bit.
    #[test]
    fn rates_alone_fit_as_whole_samples() {
        let (samples, truth) = tumble(12);
        let poses = static_poses(&samples, &GateConfig::default());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        let (accel, opt) = (truth.accel.calibration(), ScaleOptions::default());
        let rates: Vec<Rate> = samples.iter().map(Rate::from).collect();
        let whole = fit_scale(&samples, &poses, &bias, &accel, &opt).unwrap();
        let part = fit_scale(&rates, &poses, &bias, &accel, &opt).unwrap();
        assert_eq!(format!("{whole:?}"), format!("{part:?}"));
    }

    /// Split over two threads ([`map_split`]), the passes over the segments give what one
    /// thread gives, to the last bit: the segments themselves and their carrying.
    #[test]
    fn passes_split_over_two_threads_are_those_of_one() {
        let items: Vec<u32> = (0..10).collect();
        let tripled: Vec<u32> = items.iter().map(|x| 3 * x).collect();
        for at in [0, 1, 5, 9, 10, 11] {
            assert_eq!(map_split(&items, at, |x| 3 * x), tripled, "split at {at}");
        }
        // At 250 Hz: enough samples and steps that both passes do split.
        let (samples, truth) = tumble_with(12, |sc| sc.truth.rate_hz = 250.0);
        let poses = static_poses(&samples, &GateConfig::default());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        let (accel, opt) = (truth.accel.calibration(), ScaleOptions::default());
        assert!(samples.len() >= PARALLEL_MIN_STEPS, "{}", samples.len());
        let split = segments(&samples, &poses, &bias, &accel, &opt);
        let one: Vec<Segment> = poses
            .windows(2)
            .filter_map(|p| segment(&samples, (&p[0], &p[1]), &bias, &accel, &opt))
            .collect();
        assert_eq!(split.len(), one.len());
        for (a, b) in split.iter().zip(&one) {
            assert!(a.steps == b.steps && a.up0 == b.up0 && a.up1 == b.up1);
        }
        let segs: Vec<&Segment> = split.iter().collect();
        let steps: usize = segs.iter().map(|s| s.steps.len()).sum();
        assert!(steps >= PARALLEL_MIN_STEPS, "{steps}");
        let k = Matrix3::new(1.01, 0.02, -0.01, 0.005, 0.99, 0.03, -0.02, 0.01, 1.02);
        let carried = map_segments(&segs, |s| carry(s, &k));
        let alone: Vec<Carried> = segs.iter().map(|s| carry(s, &k)).collect();
        assert_eq!(format!("{carried:?}"), format!("{alone:?}"));
    }

    #[test]
    fn the_analytic_jacobian_matches_central_differences() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        // 2 s at 100 Hz of rates up to 3 rad/s (steps up to 0.05 rad), and one step past the
        // Taylor range (0.3 rad).
        let mut steps: Vec<(Vec3, f64)> = (0..200)
            .map(|_| {
                let w = [0.0; 3].map(|_: f64| rng.random_range(-3.0..3.0));
                (w, 0.01)
            })
            .collect();
        steps.push(([2.0, -1.0, 1.5], 0.1));
        let seg = Segment {
            steps,
            up0: Vector3::new(0.1, -0.2, 1.0).normalize(),
            up1: Vector3::new(-0.3, 0.5, 0.8).normalize(),
        };
        let k = Matrix3::new(1.01, 0.02, -0.01, 0.005, 0.99, 0.03, -0.02, 0.01, 1.02);
        let Carried { r, j, .. } = carry(&seg, &k);
        assert!((r - residual(&seg, &k)).norm() < 1e-15);
        let h = 1e-6;
        let mut worst: f64 = 0.0;
        for c in 0..9 {
            let (mut a, mut b) = (k, k);
            a[(c / 3, c % 3)] += h;
            b[(c / 3, c % 3)] -= h;
            let d = (residual(&seg, &a) - residual(&seg, &b)) / (2.0 * h);
            worst = worst.max((d - j.column(c)).amax());
        }
        // Entries are of order 1; measured 1.2e-10 (the differences' own error).
        assert!(worst < 1e-8, "{worst:e}");
    }

    fn tumble_with(seed: u64, f: impl Fn(&mut Scenario)) -> (Vec<Sample>, crate::sim::Truth) {
        let mut sc = Scenario::named("tumble").unwrap();
        f(&mut sc);
        sc.pauses = 24;
        // A gyro with misalignment as well as scale.
        sc.truth.gyro.matrix = [
            [1.004, 0.003, -0.002],
            [-0.001, 0.997, 0.004],
            [0.002, -0.003, 1.002],
        ];
        let out = simulate(&sc, seed);
        (out.samples, out.truth)
    }

    #[test]
    fn bias_and_scale_from_a_simulated_tumble() {
        let (samples, truth) = tumble(11);
        let poses = static_poses(&samples, &GateConfig::default());
        assert!(poses.len() >= 15, "{} poses", poses.len());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        for k in 0..3 {
            assert!(
                (bias.bias[k] - truth.gyro.offset[k]).abs() < 0.002,
                "bias {:?} vs {:?}",
                bias.bias,
                truth.gyro.offset
            );
        }
        let fit = fit_scale(
            &samples,
            &poses,
            &bias,
            &truth.accel.calibration(),
            &ScaleOptions::default(),
        )
        .unwrap();
        eprintln!(
            "gyro fit: {} segments, rms {:.3} -> {:.4} deg, K {:?}",
            fit.segments, fit.rms_before_deg, fit.rms_after_deg, fit.matrix
        );
        for i in 0..3 {
            let s = fit.matrix[i][i];
            let t = truth.gyro.matrix[i][i];
            assert!((s / t - 1.0).abs() < 0.002, "scale {i}: {s} vs {t}");
            for j in 0..3 {
                assert!(
                    (fit.matrix[i][j] - truth.gyro.matrix[i][j]).abs() < 0.002,
                    "K[{i}][{j}] {} vs {}",
                    fit.matrix[i][j],
                    truth.gyro.matrix[i][j]
                );
            }
        }
        assert!(fit.rms_after_deg < fit.rms_before_deg / 3.0);
    }

    #[test]
    fn bias_drift_with_temperature_is_fitted() {
        // A warming sensor (10 deg C over the run) held still between poses.
        let (mut samples, truth) = tumble_with(12, |sc| {
            sc.temp_drift_c = 10.0;
            sc.tremor_deg = 0.0;
        });
        // Drift of (0.001, -0.0005, 0.0002) rad/s per deg C about 25 deg C.
        let k = [0.001, -0.0005, 0.0002];
        for s in samples.iter_mut() {
            let t = s.temp_c.unwrap();
            if let Some(g) = s.gyro_rad_s.as_mut() {
                for a in 0..3 {
                    g[a] += k[a] * (t - 25.0);
                }
            }
        }
        let poses = static_poses(&samples, &GateConfig::default());
        let b = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        let kf = b.temp_coeff.expect("a drift fit");
        for a in 0..3 {
            assert!((kf[a] - k[a]).abs() < 2e-4, "drift {kf:?} vs {k:?}");
            let at25 = b.at(Some(25.0));
            assert!(
                (at25[a] - truth.gyro.offset[a]).abs() < 0.002,
                "{at25:?} vs {:?}",
                truth.gyro.offset
            );
        }
        // Constant temperature: no drift fit, the mean.
        let flat: Vec<Pose> = poses
            .iter()
            .map(|p| Pose {
                temp_c: Some(25.0),
                ..*p
            })
            .collect();
        assert!(bias_from_poses(&flat, &BiasOptions::default())
            .unwrap()
            .temp_coeff
            .is_none());
    }

    #[test]
    fn raw_counts_start_from_the_best_isotropic_scale() {
        // The same tumble read in counts: 5000 counts per rad/s and an offset of 32768 counts.
        let (mut samples, truth) = tumble(14);
        let poses0 = static_poses(&samples, &GateConfig::default());
        for s in samples.iter_mut() {
            if let Some(g) = s.gyro_rad_s.as_mut() {
                for v in g.iter_mut() {
                    *v = *v * 5000.0 + 32768.0;
                }
            }
        }
        let poses = static_poses(&samples, &GateConfig::default());
        assert_eq!(poses.len(), poses0.len());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        let opt = ScaleOptions {
            raw_in_counts: true,
            ..Default::default()
        };
        let fit = fit_scale(&samples, &poses, &bias, &truth.accel.calibration(), &opt).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let k = fit.matrix[i][j] * 5000.0;
                assert!(
                    (k - truth.gyro.matrix[i][j]).abs() < 0.002,
                    "K[{i}][{j}] {k} vs {}",
                    truth.gyro.matrix[i][j]
                );
            }
        }
        // Starting from the identity instead, LM does not find its way to 1/5000.
        let bad = fit_scale(
            &samples,
            &poses,
            &bias,
            &truth.accel.calibration(),
            &Default::default(),
        );
        assert!(bad.map_or(true, |f| (f.matrix[0][0] * 5000.0 - 1.0).abs() > 0.01));
        let h = fit.held_out.expect("24 poses give enough rotations");
        assert!(h.rms_after_deg < h.rms_before_deg, "{h:?}");
    }

    /// A turntable scenario's log through the static detector: poses, bias, the true accel calibration.
    fn turntable(attitudes: Vec<[f64; 3]>) -> (Vec<Sample>, Vec<Pose>, GyroBias, Calibration) {
        let mut sc = Scenario::named("turntable").unwrap();
        sc.attitudes = Some(attitudes);
        let out = simulate(&sc, 3);
        let poses = static_poses(&out.samples, &GateConfig::default());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        (out.samples, poses, bias, out.truth.accel.calibration())
    }

    /// Two turns about the body x axis in 40 deg steps, the axis tilted 20 deg from level.
    fn about_x() -> Vec<[f64; 3]> {
        (0..18)
            .map(|i| [((i * 40) % 360) as f64 - 180.0, 20.0, 0.0])
            .collect()
    }

    #[test]
    fn rotations_about_one_axis_do_not_determine_the_scale() {
        let (samples, poses, bias, accel) = turntable(about_x());
        let opt = ScaleOptions::default();
        let (span, n) = rotation_axes(&samples, &poses, &bias, &accel, &opt).unwrap();
        let AxisSpan::OneAxis(a) = span else {
            panic!("{span:?}")
        };
        assert!(a[0].abs() > 0.99, "{a:?}");
        assert!(n >= 12, "{n} rotations");
        let e = fit_scale(&samples, &poses, &bias, &accel, &opt).unwrap_err();
        assert_eq!(e.failure, FitFailure::NotIdentifiable, "{e}");
        assert!(e.detail.contains("one axis only"), "{e}");
        // Turned about x and about y, never about z: the plane's normal is z.
        let seg = |w: [f64; 3]| Segment {
            steps: vec![(w, 1.0)],
            up0: Vector3::z(),
            up1: Vector3::z(),
        };
        let xy: Vec<Segment> = (0..12)
            .map(|i| {
                if i % 3 == 0 {
                    seg([0.0, 0.7, 0.01])
                } else {
                    seg([0.9, 0.0, -0.01])
                }
            })
            .collect();
        let k = Matrix3::identity();
        let span = axis_span(xy.iter().map(|s| integrate(s, &k)));
        let AxisSpan::OnePlane(n) = span else {
            panic!("{span:?}")
        };
        assert!(n[2].abs() > 0.99, "{n:?}");
        let f = span.failure(12).unwrap();
        assert_eq!(f.failure, FitFailure::NotIdentifiable);
        assert!(f.detail.contains("one plane only"), "{f}");
        // And about z too: all three.
        let mut xyz = xy;
        xyz.push(seg([0.0, 0.0, 0.5]));
        assert_eq!(
            axis_span(xyz.iter().map(|s| integrate(s, &k))),
            AxisSpan::Full
        );
    }

    #[test]
    fn a_scale_that_fails_its_held_out_check_is_refused() {
        // Six positions (gravity along each axis), then three turns about x: all three directions
        // are turned about, but most rotations about one, and the half fits cannot place the rest.
        let att = crate::sim::six_positions_then_turns_about_x();
        let (samples, poses, bias, accel) = turntable(att);
        let opt = ScaleOptions::default();
        let (span, _) = rotation_axes(&samples, &poses, &bias, &accel, &opt).unwrap();
        assert_eq!(span, AxisSpan::Full);
        let e = fit_scale(&samples, &poses, &bias, &accel, &opt).unwrap_err();
        assert_eq!(e.failure, FitFailure::HeldOut, "{e}");
        let h = e.held_out.expect("the check was made");
        eprintln!(
            "held out {:.2} -> {:.2} deg over {}",
            h.rms_before_deg, h.rms_after_deg, h.segments
        );
        assert!(h.rms_after_deg > h.rms_before_deg * (1.0 + HELD_OUT_MARGIN));
    }

    #[test]
    fn too_few_rotations_is_an_error() {
        let (samples, truth) = tumble(13);
        let poses = static_poses(&samples, &GateConfig::default());
        let bias = bias_from_poses(&poses, &BiasOptions::default()).unwrap();
        let e = fit_scale(
            &samples,
            &poses[..8],
            &bias,
            &truth.accel.calibration(),
            &ScaleOptions::default(),
        )
        .unwrap_err();
        // Seven rotations: enough for a fit, not for a fit and its held-out check.
        assert_eq!(e.failure, FitFailure::NotEnoughSamples, "{e}");
    }
}
