//! Fitting: Levenberg-Marquardt ([`crate::calib::lm`]) on fixed-size normal equations with analytic
//! gradients, an algebraic ellipsoid start that needs no datasheet, parameter uncertainties, acceptance checks and automatic model choice.
//! Pure math: no I/O.
//!
//! The scalar (norm) residual of Ren and Liu, "Calibration of MEMS Accelerometers and Magnetometers
//! for Rotor UAV Attitude Estimation", and of Camps, Harasse and Monin, "Numerical calibration for
//! 3-axis accelerometers and magnetometers" (2009): for each point `r_i = |A (x_i - p)| - 1` on data
//! normalised by the starting centre and radius, so the same tolerances hold for counts, uT or m/s^2.

use crate::calib::lm::{cholesky, LmOptions, LmShortcuts};
use crate::calib::model::{
    a_from_params, mat_to_rows, n_norm_params, params_from_a, Calibration, ModelKind,
};
use crate::types::Vec3;
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

mod kernel;
use serde::{Deserialize, Serialize};

/// Why a fit was refused. The names are the report's `failure` strings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FitFailure {
    NotEnoughSamples,
    NotIdentifiable,
    Coverage,
    Radius,
    Offsets,
    DiagonalScaling,
    Residuals,
    DidNotConverge,
    /// Too many points off the field's ellipsoid (magnetic disturbance while calibrating).
    Disturbed,
    /// An axis is saturated (clipped at one value) or stuck.
    AxisFault,
    /// Worse on data held out of the fit than the simpler model it would replace.
    HeldOut,
    /// Needs another sensor's calibration first (the gyro scale: the accelerometer's).
    NeedsCalibration,
    /// The data say the compass is mounted otherwise than configured ([`crate::calib::mounting`]).
    Orientation,
    /// The readings are not a compass seeing the earth's field ([`crate::calib::plausible`]).
    Implausible,
}

impl std::fmt::Display for FitFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl FitFailure {
    pub fn name(self) -> &'static str {
        match self {
            FitFailure::NotEnoughSamples => "not_enough_samples",
            FitFailure::NotIdentifiable => "not_identifiable",
            FitFailure::Coverage => "coverage",
            FitFailure::Radius => "radius",
            FitFailure::Offsets => "offsets",
            FitFailure::DiagonalScaling => "diagonal_scaling",
            FitFailure::Residuals => "residuals",
            FitFailure::DidNotConverge => "did_not_converge",
            FitFailure::Disturbed => "disturbed",
            FitFailure::AxisFault => "axis_fault",
            FitFailure::HeldOut => "held_out",
            FitFailure::Implausible => "implausible",
            FitFailure::NeedsCalibration => "needs_calibration",
            FitFailure::Orientation => "orientation",
        }
    }
}

/// A starting point: centre `p` and symmetric positive-definite shape `A` with |A (x - p)| ~ 1.
#[derive(Debug, Clone, Copy)]
pub struct Start {
    pub centre: Vector3<f64>,
    pub shape: Matrix3<f64>,
}

/// Linear least-squares sphere fit: |x|^2 = 2 c.x + k.
pub(crate) fn sphere_start(points: &[Vec3]) -> Option<Start> {
    if points.len() < 4 {
        return None;
    }
    let soa = kernel::Soa::normalised(points, [0.0; 3], 1.0);
    let mut scratch = kernel::Scratch::new(soa.padded);
    let (_, ata, atb) = kernel::sphere_normal_equations(&soa, &mut scratch);
    sphere_from_normal_equations(&ata, &atb)
}

pub(crate) fn sphere_from_normal_equations(
    ata: &SMatrix<f64, 4, 4>,
    atb: &SVector<f64, 4>,
) -> Option<Start> {
    let sol = cholesky(ata)?.solve(atb);
    let c = Vector3::new(sol[0], sol[1], sol[2]);
    let r2 = sol[3] + c.norm_squared();
    if !(r2 > 0.0) || !r2.is_finite() {
        return None;
    }
    Some(Start {
        centre: c,
        shape: Matrix3::identity() / r2.sqrt(),
    })
}

/// Mean of `points` and half the largest side of their bounding box (1 when that is not positive),
/// for a first, well-scaled frame; `None` when a coordinate (or a sum of them) is not finite.
fn mean_and_extent(points: &[Vec3]) -> Option<([f64; 3], f64)> {
    if points.is_empty() {
        return Some(([0.0; 3], 1.0));
    }
    let (mut sum, mut lo, mut hi) = ([0.0f64; 3], [f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in points {
        for k in 0..3 {
            sum[k] += p[k];
            // (Plain comparisons: a NaN shows in the sum, so `min`'s NaN rules are not needed.)
            lo[k] = if p[k] < lo[k] { p[k] } else { lo[k] };
            hi[k] = if p[k] > hi[k] { p[k] } else { hi[k] };
        }
    }
    // A NaN or an infinity makes its axis' sum NaN or infinite.
    if !sum.iter().all(|v| v.is_finite()) {
        return None;
    }
    let inv_n = 1.0 / points.len() as f64;
    let half = (0..3).map(|k| 0.5 * (hi[k] - lo[k])).fold(0.0, f64::max);
    Some((
        sum.map(|v| v * inv_n),
        if half > 0.0 && half.is_finite() {
            half
        } else {
            1.0
        },
    ))
}

/// The linear sphere fit's normal equations, read from the ellipsoid fit's: with the ellipsoid
/// design columns `d = [x^2, y^2, z^2, 2xy, 2xz, 2yz, 2x, 2y, 2z]`, the sphere's are
/// `[d6, d7, d8, 1]` and its right-hand side `d0 + d1 + d2`, so every sum it needs is already an
/// entry of the ellipsoid's `D^T D` (`g`), `D^T 1` (`ab`) or the point count `n`.
fn sphere_from_ellipsoid_moments(
    n: f64,
    g: &SMatrix<f64, 9, 9>,
    ab: &SVector<f64, 9>,
) -> (SMatrix<f64, 4, 4>, SVector<f64, 4>) {
    let ata = SMatrix::<f64, 4, 4>::from_fn(|i, j| match (i, j) {
        (3, 3) => n,
        (3, k) | (k, 3) => ab[6 + k],
        (i, j) => g[(6 + i, 6 + j)],
    });
    let atb = SVector::<f64, 4>::from_fn(|i, _| match i {
        3 => ab[0] + ab[1] + ab[2],
        i => g[(6 + i, 0)] + g[(6 + i, 1)] + g[(6 + i, 2)],
    });
    (ata, atb)
}

/// Algebraic ellipsoid fit: the general quadric x^T Q x + 2 g.x = 1, solved linearly; returns `None`
/// when the quadric is not an ellipsoid (poor coverage), so the caller falls back to a sphere.
pub(crate) fn ellipsoid_start(points: &[Vec3]) -> Option<Start> {
    if points.len() < 9 {
        return None;
    }
    let soa = kernel::Soa::normalised(points, [0.0; 3], 1.0);
    let mut scratch = kernel::Scratch::new(soa.padded);
    let (_, ata, atb) = kernel::ellipsoid_normal_equations(&soa, &mut scratch);
    ellipsoid_from_normal_equations(&ata, &atb)
}

fn ellipsoid_from_normal_equations(
    ata: &SMatrix<f64, 9, 9>,
    atb: &SVector<f64, 9>,
) -> Option<Start> {
    let s = cholesky(ata)?.solve(atb);
    let q = Matrix3::new(s[0], s[3], s[4], s[3], s[1], s[5], s[4], s[5], s[2]);
    let g = Vector3::new(s[6], s[7], s[8]);
    let qi = q.try_inverse()?;
    let c = -(qi * g);
    // (x-c)^T Q (x-c) = 1 + c^T Q c
    let k = 1.0 + (c.transpose() * q * c)[0];
    if k == 0.0 || !k.is_finite() {
        return None;
    }
    // k < 0 when the origin lies outside the ellipsoid (Q then came out negative definite).
    let qn = q / k;
    let eig = qn.symmetric_eigen();
    if eig
        .eigenvalues
        .iter()
        .any(|&l| !(l > 0.0) || !l.is_finite())
    {
        return None;
    }
    let sq = eig.eigenvectors
        * Matrix3::from_diagonal(&eig.eigenvalues.map(|l| l.sqrt()))
        * eig.eigenvectors.transpose();
    Some(Start {
        centre: c,
        shape: sq,
    })
}

/// Options for a norm fit.
#[derive(Debug, Clone, Copy)]
pub struct NormFitOptions {
    /// Magnitude the calibrated vectors should have (e.g. g in m/s^2). `None` keeps the raw scale:
    /// the matrix then has determinant 1 and `radius` is the field magnitude in raw units.
    pub target_norm: Option<f64>,
    pub max_iterations: usize,
}

impl Default for NormFitOptions {
    fn default() -> Self {
        NormFitOptions {
            target_norm: None,
            max_iterations: 200,
        }
    }
}

/// Result of a norm fit, before acceptance checks.
#[derive(Debug, Clone)]
pub struct NormFit {
    pub calibration: Calibration,
    /// Field magnitude in calibrated units (the target norm, or the raw-unit radius).
    pub radius: f64,
    /// Radius of the data in raw units (1 / cbrt(det A_raw)).
    pub raw_radius: f64,
    /// RMS of |calibrated| - radius, calibrated units.
    pub rms_residual: f64,
    /// 1-sigma of the offset, raw units.
    pub offset_sigma: Vec3,
    /// 1-sigma of each matrix parameter relative to its value scale (dimensionless).
    pub matrix_sigma_max: f64,
    pub ssr_normalised: f64,
    pub samples_used: usize,
    pub iterations: usize,
    pub converged: bool,
    /// Condition number of the normal matrix (identifiability).
    pub condition: f64,
}

/// What the norm LM hands back: parameters, sum of squares, iterations, convergence, the condition
/// number of J^T J and the diagonal of its inverse (unscaled covariance).
struct NormSolution {
    params: Vec<f64>,
    ssr: f64,
    iterations: usize,
    converged: bool,
    condition: f64,
    cov_diag: Option<Vec<f64>>,
}

/// Largest eigenvalue of a symmetric positive semi-definite matrix by power iteration, as the
/// Rayleigh quotient of `M^24 v0`: never above the true value and, from a start that is not nearly
/// orthogonal to the top eigenvector, within a few per cent of it whatever the eigenvalue gap (the
/// components that converge slowly are those whose eigenvalues are close to the largest, and they
/// pull the quotient down little). `M^24 v0` is `M^4` applied six times, `M^4` by two
/// squarings of `M / trace(M)` (eigenvalues in (0, 1], so nothing overflows): independent
/// multiply-adds instead of a chain of 24 dependent matrix-vector products.
fn largest_eigenvalue<const N: usize>(m: &SMatrix<f64, N, N>) -> f64 {
    let trace: f64 = (0..N).map(|i| m[(i, i)]).sum();
    if !(trace > 0.0) || !trace.is_finite() {
        return 0.0;
    }
    let inv_trace = 1.0 / trace;
    // (The matrix is symmetric, so its columns are its rows.)
    let s: [[f64; N]; N] = std::array::from_fn(|i| std::array::from_fn(|j| m[(j, i)] * inv_trace));
    let square = |a: &[[f64; N]; N]| -> [[f64; N]; N] {
        let mut out = [[0.0; N]; N];
        for i in 0..N {
            for k in 0..N {
                let aik = a[i][k];
                for j in 0..N {
                    out[i][j] += aik * a[k][j];
                }
            }
        }
        out
    };
    let s4 = square(&square(&s));
    let mv = |a: &[[f64; N]; N], v: &[f64; N]| -> [f64; N] {
        std::array::from_fn(|i| a[i].iter().zip(v).map(|(x, y)| x * y).sum())
    };
    let dot = |a: &[f64; N], b: &[f64; N]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    // Start on the column with the largest diagonal entry (plus a little of every axis): it leans
    // towards the largest eigenvector, which keeps the bound below honest.
    let k = (0..N).fold(0, |b, i| if s[i][i] > s[b][b] { i } else { b });
    let mut v: [f64; N] = std::array::from_fn(|i| s[k][i] + 1e-3 * s[k][k]);
    // No normalising between products: the eigenvalues of `s` are at most 1 and the largest at
    // least 1/N, so 24 products shrink `v` by at most N^-24 (1e-26 for twelve parameters), far from
    // underflow, and the quotient below does not depend on the length of `v`.
    for _ in 0..6 {
        v = mv(&s4, &v);
    }
    let vv = dot(&v, &v);
    if !(vv > 0.0) || !vv.is_finite() {
        return 0.0;
    }
    trace * dot(&v, &mv(&s, &v)) / vv
}

/// Condition number of J^T J (largest over smallest eigenvalue) from power iteration on it and on
/// its inverse: an estimate from below, typically within a few per cent, which is all the
/// identifiability check (1e12) and the report need, at a fraction of a full eigen-decomposition
/// (checked against one in the tests).
fn condition_number<const N: usize>(
    jtj: &SMatrix<f64, N, N>,
    inv: Option<&SMatrix<f64, N, N>>,
) -> f64 {
    let Some(inv) = inv else {
        return f64::INFINITY;
    };
    let (lmax, inv_max) = (largest_eigenvalue(jtj), largest_eigenvalue(inv));
    if lmax > 0.0 && inv_max > 0.0 && (lmax * inv_max).is_finite() {
        (lmax * inv_max).max(1.0)
    } else {
        f64::INFINITY
    }
}

/// [`LmShortcuts::reuse_jtj`] for norm fits, in the sphere-normalised frame (centre in radii,
/// matrix near the identity): J^T J, and so the reported uncertainties, from within 1e-4 of the
/// solution. The ellipsoid start usually lands this close, so the last evaluation forms no J^T J.
pub(crate) const NORM_REUSE_JTJ: f64 = 1e-4;

/// [`LmOptions::stop_rel_gain`] of norm fits and the dip rotation fit: analytic gradients, so the
/// fit can go on to a relative gain near rounding.
pub(crate) const NORM_STOP_REL_GAIN: f64 = 1e-14;

/// A norm fit is given up, not converged, once it leaves the normalising sphere fit's frame by
/// this factor: its centre more than this many of that sphere's radii from that sphere's centre,
/// or its radius (`1 / cbrt(det A)`) more than this factor away from that sphere's radius. Where
/// the readings outline a sphere or an ellipsoid, the linear sphere fit through them and the norm
/// fit land close together (the fits from the start of [`NormFitter::fit`] stay within a few
/// tenths of that frame); a norm fit that walks off to a far larger sphere has readings that
/// outline none (a patch a few degrees wide), and there the residual, relative to the fitted
/// radius, keeps shrinking as the radius grows, so the iteration would run to its limit. (On a PX4
/// hover log with readings spanning about 6 deg of the field, every norm fit went 200 iterations,
/// its radius from 7.8 to 131 uT and growing.)
pub(crate) const NORM_RUNAWAY_FACTOR: f64 = 3.0;

/// Whether the norm fit's parameters `p` (centre, then the shape's) are within
/// [`NORM_RUNAWAY_FACTOR`] of the normalising sphere (the unit sphere at the origin).
fn within_frame(kind: ModelKind, p: &[f64]) -> bool {
    let centre = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
    let scale = a_from_params(kind, &p[3..]).determinant().abs().cbrt();
    centre <= NORM_RUNAWAY_FACTOR
        && (1.0 / NORM_RUNAWAY_FACTOR..=NORM_RUNAWAY_FACTOR).contains(&scale)
}

fn solve_norm<const K: u8, const N: usize>(
    kind: ModelKind,
    pts: &kernel::Soa,
    scratch: &mut kernel::Scratch,
    x0: &[f64],
    max_iter: usize,
) -> NormSolution {
    let x0v = SVector::<f64, N>::from_column_slice(x0);
    let dof = pts.n.saturating_sub(N).max(1) as f64;
    let opts = LmOptions {
        max_iter,
        stop_rel_gain: NORM_STOP_REL_GAIN,
        shortcuts: LmShortcuts {
            last_step: 1e-6 / dof,
            reuse_jtj: NORM_REUSE_JTJ,
        },
    };
    let out = crate::calib::lm::minimise_normal_within(
        x0v,
        &opts,
        |p, with_jtj| kernel::norm_normal_equations::<K, N>(p, pts, scratch, with_jtj),
        |p| within_frame(kind, p.as_slice()),
    );
    let inv = cholesky(&out.jtj).map(|c| c.inverse());
    NormSolution {
        params: out.params.as_slice().to_vec(),
        ssr: out.ssr,
        iterations: out.iterations,
        converged: out.converged,
        condition: condition_number(&out.jtj, inv.as_ref()),
        cov_diag: inv.map(|m| (0..N).map(|k| m[(k, k)]).collect()),
    }
}

/// Fit a norm-only model (`sphere`, `diag6`, `sym9`, `full12` upper-triangular) to points in raw units.
pub fn fit_norm(
    points: &[Vec3],
    kind: ModelKind,
    opts: &NormFitOptions,
) -> Result<NormFit, FitFailure> {
    NormFitter::new(points).fit(kind, opts)
}

/// Norm fits of several models to the same points, sharing the work they have in common: the
/// points in fit layout, the normalising sphere fit and the algebraic ellipsoid start.
pub(crate) struct NormFitter {
    frame: Frame,
    scratch: kernel::Scratch,
    outline: Option<Outline>,
}

/// Whether points outline a sphere at all, read from the moments of the linear fits before any
/// iteration: their spread (the standard deviation along their second-widest direction: a cap
/// of a sphere spreads in two directions, a ring or a full sphere in at least two) against their
/// scatter about the closest sphere (the linear sphere fit's RMS distance, its algebraic residual
/// over twice its radius). Readings that scatter about any sphere nearly as far as they spread
/// are a blob, not an outline: no centre, let alone an ellipsoid, is determined by them.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Outline {
    /// Standard deviation of the points along their second-widest direction, raw units.
    pub spread: f64,
    /// RMS distance of the points from the linear sphere fit, raw units.
    pub scatter: f64,
    /// That sphere's radius, raw units.
    pub radius: f64,
}

impl Outline {
    /// From the ellipsoid design's moments (`n`, `g` = D^T D, `ab` = D^T 1, points in a frame
    /// scaled by `scale`) and the sphere fit's normal equations read from them.
    fn from_moments(
        n: f64,
        g: &SMatrix<f64, 9, 9>,
        ab: &SVector<f64, 9>,
        ata: &SMatrix<f64, 4, 4>,
        atb: &SVector<f64, 4>,
        scale: f64,
    ) -> Option<Outline> {
        if !(n > 4.0) {
            return None;
        }
        let sol = cholesky(ata)?.solve(atb);
        // The right-hand side |x|^2 is d0 + d1 + d2: its square sums to these entries of g.
        let btb: f64 = (0..3).flat_map(|i| (0..3).map(move |j| g[(i, j)])).sum();
        let ssr = (btb - sol.dot(atb)).max(0.0);
        let c = Vector3::new(sol[0], sol[1], sol[2]);
        let r = (sol[3] + c.norm_squared()).sqrt();
        // Columns 6..9 are 2x, 2y, 2z.
        let mean = Vector3::from_fn(|i, _| ab[6 + i] / (2.0 * n));
        let cov = Matrix3::from_fn(|i, j| g[(6 + i, 6 + j)] / (4.0 * n) - mean[i] * mean[j]);
        let mut ev: [f64; 3] = cov.symmetric_eigen().eigenvalues.into();
        ev.sort_by(f64::total_cmp);
        let out = Outline {
            spread: ev[1].max(0.0).sqrt() * scale,
            scatter: (ssr / n).sqrt() / (2.0 * r) * scale,
            radius: r * scale,
        };
        (out.spread.is_finite() && out.scatter.is_finite() && r > 0.0).then_some(out)
    }
}

/// What the fits of a [`NormFitter`] share and only read: the points in fit layout, the
/// normalising sphere fit and the ellipsoid start.
struct Frame {
    soa: kernel::Soa,
    /// Normalising sphere fit (centre, radius), raw units; `None` if the points are not enough or
    /// do not define a sphere.
    sphere: Option<(Vector3<f64>, f64)>,
    /// The ellipsoid start in the sphere's frame; `None` with too few points or when the quadric
    /// is not a plausible ellipsoid (the fits then start from the sphere).
    ellipsoid: Option<Start>,
}

/// Points from which [`NormFitter::fit_each`] fits its last model on a second thread: below, a
/// fit takes about as long as starting the thread (tens of microseconds).
pub(crate) const PARALLEL_FIT_MIN_POINTS: usize = 256;

impl NormFitter {
    /// Points with a non-finite coordinate are left out.
    pub fn new(points: &[Vec3]) -> NormFitter {
        let finite = |p: &Vec3| p.iter().all(|v| v.is_finite());
        let filtered: Vec<Vec3>;
        // A first frame, from the mean and the extent of the points, keeps the moments the linear
        // fits sum well scaled; the fits then move everything to the frame of the sphere fit.
        let (pts, (m1, s1)): (&[Vec3], _) = match mean_and_extent(points) {
            Some(frame) => (points, frame),
            None => {
                filtered = points.iter().copied().filter(finite).collect();
                (
                    &filtered,
                    mean_and_extent(&filtered).unwrap_or(([0.0; 3], 1.0)),
                )
            }
        };
        let mut soa = kernel::Soa::normalised(pts, m1, s1);
        let mut scratch = kernel::Scratch::new(soa.padded);
        let mut sphere = None;
        let mut ellipsoid = None;
        let mut outline = None;
        if pts.len() >= 4 {
            // Normalise: centre and scale from the sphere fit (defined when the points are not
            // coplanar). With enough points for the ellipsoid start, its normal equations hold the
            // sphere's, so one pass over the points serves both.
            let with_ellipsoid =
                (pts.len() >= 9).then(|| kernel::ellipsoid_normal_equations(&soa, &mut scratch));
            let (ata, atb) = match &with_ellipsoid {
                Some((n, g, ab)) => sphere_from_ellipsoid_moments(*n, g, ab),
                None => {
                    let (_, ata, atb) = kernel::sphere_normal_equations(&soa, &mut scratch);
                    (ata, atb)
                }
            };
            outline = with_ellipsoid
                .as_ref()
                .and_then(|(n, g, ab)| Outline::from_moments(*n, g, ab, &ata, &atb, s1));
            if let Some(sph) = sphere_from_normal_equations(&ata, &atb) {
                // The sphere in the first frame: centre c1, radius r1.
                let (c1, r1) = (sph.centre, 1.0 / sph.shape[(0, 0)]);
                soa.renormalise([c1[0], c1[1], c1[2]], r1);
                let c0 = Vector3::from(m1) + c1 * s1;
                sphere = Some((c0, r1 * s1));
                // The ellipsoid start, moved to the sphere's frame (x1 = c1 + r1 x).
                ellipsoid = with_ellipsoid.and_then(|(_, g, ab)| {
                    ellipsoid_from_normal_equations(&g, &ab)
                        .map(|e| Start {
                            centre: (e.centre - c1) / r1,
                            shape: e.shape * r1,
                        })
                        .filter(|s| s.centre.norm() < 1.0 && s.shape.iter().all(|v| v.abs() < 10.0))
                });
            }
        }
        NormFitter {
            frame: Frame {
                soa,
                sphere,
                ellipsoid,
            },
            scratch,
            outline,
        }
    }

    /// How far the points spread against how far they scatter about the closest sphere, from
    /// the moments the set-up summed ([`Outline`]); `None` under nine points.
    pub(crate) fn outline(&self) -> Option<Outline> {
        self.outline
    }

    /// Centre of the plain sphere fit, raw units.
    pub(crate) fn sphere_centre(&self) -> Option<Vec3> {
        self.frame.sphere.map(|(c, _)| [c[0], c[1], c[2]])
    }

    /// Fit one model.
    pub fn fit(&mut self, kind: ModelKind, opts: &NormFitOptions) -> Result<NormFit, FitFailure> {
        self.frame.fit(&mut self.scratch, kind, opts)
    }

    /// Fit each of `kinds`, in order: the last on a second thread (scratch space of its own)
    /// while this one fits the others, from [`PARALLEL_FIT_MIN_POINTS`] points on. Each fit
    /// reads only the shared frame, so the results are those of fitting one after the other.
    pub(crate) fn fit_each(
        &mut self,
        kinds: &[ModelKind],
        opts: &NormFitOptions,
    ) -> Vec<Result<NormFit, FitFailure>> {
        let NormFitter { frame, scratch, .. } = self;
        let frame = &*frame;
        match kinds.split_last() {
            Some((last, first)) if !first.is_empty() && frame.soa.n >= PARALLEL_FIT_MIN_POINTS => {
                std::thread::scope(|scope| {
                    let other = scope.spawn(move || {
                        let mut own = kernel::Scratch::new(frame.soa.padded);
                        frame.fit(&mut own, *last, opts)
                    });
                    let mut out: Vec<_> =
                        first.iter().map(|k| frame.fit(scratch, *k, opts)).collect();
                    out.push(
                        other
                            .join()
                            .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
                    );
                    out
                })
            }
            _ => kinds.iter().map(|k| frame.fit(scratch, *k, opts)).collect(),
        }
    }
}

impl Frame {
    /// Fit one model, `scratch` its working space.
    fn fit(
        &self,
        scratch: &mut kernel::Scratch,
        kind: ModelKind,
        opts: &NormFitOptions,
    ) -> Result<NormFit, FitFailure> {
        let np = n_norm_params(kind);
        if self.soa.n < np + 3 {
            return Err(FitFailure::NotEnoughSamples);
        }
        let (c0, s0) = self.sphere.ok_or(FitFailure::NotIdentifiable)?;
        let unit = Start {
            centre: Vector3::zeros(),
            shape: Matrix3::identity(),
        };
        let start = match kind {
            ModelKind::Sphere => unit,
            _ => self.ellipsoid.unwrap_or(unit),
        };
        let soa = &self.soa;
        let shape0 = if kind == ModelKind::Full12 {
            // Upper-triangular factor R with R^T R = S^T S (Cholesky of S^2 = L L^T, R = L^T).
            let s2 = start.shape.transpose() * start.shape;
            cholesky(&s2)
                .map(|c| c.l().transpose())
                .unwrap_or(Matrix3::identity())
        } else {
            start.shape
        };
        let mut x0 = vec![start.centre[0], start.centre[1], start.centre[2]];
        x0.extend(params_from_a(kind, &shape0));
        let (sc, it) = (scratch, opts.max_iterations);
        let sol = match kind {
            ModelKind::Sphere => solve_norm::<{ kernel::SPHERE }, 4>(kind, soa, sc, &x0, it),
            ModelKind::Diag6 => solve_norm::<{ kernel::DIAG6 }, 6>(kind, soa, sc, &x0, it),
            ModelKind::Sym9 => solve_norm::<{ kernel::SYM9 }, 9>(kind, soa, sc, &x0, it),
            ModelKind::Full12 => solve_norm::<{ kernel::FULL12 }, 9>(kind, soa, sc, &x0, it),
        };
        let p = &sol.params;
        if p.iter().any(|v| !v.is_finite()) {
            return Err(FitFailure::DidNotConverge);
        }
        let a = a_from_params(kind, &p[3..]);
        let offset = [c0[0] + s0 * p[0], c0[1] + s0 * p[1], c0[2] + s0 * p[2]];
        let a_raw = a / s0;
        let det = a_raw.determinant();
        if !(det.abs() > 0.0) {
            return Err(FitFailure::NotIdentifiable);
        }
        let raw_radius = 1.0 / det.abs().cbrt();
        let radius = opts.target_norm.unwrap_or(raw_radius);
        let mut m = a_raw * radius;
        // Keep a proper (det > 0) matrix: a reflection cannot be told apart by norms.
        if m.determinant() < 0.0 {
            m = -m;
        }
        let n = soa.n;
        let dof = (n - np).max(1) as f64;
        let s2 = sol.ssr / dof;
        let (offset_sigma, matrix_sigma_max) = match &sol.cov_diag {
            Some(c) => {
                let os = [
                    s0 * (c[0] * s2).max(0.0).sqrt(),
                    s0 * (c[1] * s2).max(0.0).sqrt(),
                    s0 * (c[2] * s2).max(0.0).sqrt(),
                ];
                let ms = (3..np)
                    .map(|k| (c[k] * s2).max(0.0).sqrt())
                    .fold(0.0, f64::max);
                (os, ms)
            }
            None => ([f64::INFINITY; 3], f64::INFINITY),
        };
        Ok(NormFit {
            calibration: Calibration {
                model: kind,
                offset,
                matrix: mat_to_rows(&m),
            },
            radius,
            raw_radius,
            rms_residual: (sol.ssr / n as f64).sqrt() * radius,
            offset_sigma,
            matrix_sigma_max,
            ssr_normalised: sol.ssr,
            samples_used: n,
            iterations: sol.iterations,
            converged: sol.converged,
            condition: sol.condition,
        })
    }
}

/// Upper 0.999 quantile of chi-square with `df` degrees of freedom, used for the nested-model test
/// of automatic model choice.
pub(crate) fn chi2_quantile_999(df: usize) -> f64 {
    use statrs::distribution::{ChiSquared, ContinuousCDF};
    ChiSquared::new(df.max(1) as f64).map_or(f64::INFINITY, |d| d.inverse_cdf(0.999))
}

/// Is the more complex nested fit a significant improvement? F-test in its chi-square form, plus a
/// floor on the relative improvement so that numerically tiny gains on huge samples do not count.
pub(crate) fn significantly_better(
    simple_ssr: f64,
    complex_ssr: f64,
    extra_params: usize,
    n: usize,
    complex_params: usize,
) -> bool {
    if complex_ssr >= simple_ssr || n <= complex_params {
        return false;
    }
    let s2 = complex_ssr / (n - complex_params) as f64;
    if s2 <= 0.0 {
        return true;
    }
    let stat = (simple_ssr - complex_ssr) / s2;
    stat > chi2_quantile_999(extra_params) && (simple_ssr - complex_ssr) > 0.005 * simple_ssr
}

/// Accelerometer calibration from static poses near the six axis directions (Chu et al., "Magnetic Orientation System Based on Magnetometer, Accelerometer and Gyroscope", Ren and Liu
/// section IV): the linear 12-parameter model raw = K f + b, solved by least squares against the
/// nominal specific force of each pose (+-g on one axis). Returns `None` unless every one of the six
/// directions has a pose within `max_angle_deg`.
pub(crate) fn six_position(pose_means: &[Vec3], g: f64, max_angle_deg: f64) -> Option<Calibration> {
    if pose_means.len() < 6 {
        return None;
    }
    let sph = sphere_start(pose_means)?;
    let c = sph.centre;
    let mut rows: Vec<(Vector3<f64>, Vector3<f64>)> = Vec::new();
    let mut seen = [false; 6];
    let cos_max = max_angle_deg.to_radians().cos();
    for p in pose_means {
        let v = Vector3::new(p[0], p[1], p[2]) - c;
        let d = v.normalize();
        let (mut best, mut best_dot) = (0usize, -2.0);
        for axis in 0..3 {
            for (s_i, s) in [1.0, -1.0].iter().enumerate() {
                let dot = s * d[axis];
                if dot > best_dot {
                    best_dot = dot;
                    best = axis * 2 + s_i;
                }
            }
        }
        if best_dot < cos_max {
            continue;
        }
        seen[best] = true;
        let mut f = Vector3::zeros();
        f[best / 2] = if best % 2 == 0 { g } else { -g };
        rows.push((f, Vector3::new(p[0], p[1], p[2])));
    }
    if !seen.iter().all(|&s| s) {
        return None;
    }
    // raw_j = sum_k K_jk f_k + b_j for each axis j: a 4-unknown least-squares problem per row of K.
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    for (f, _) in &rows {
        let r = nalgebra::Vector4::new(f[0], f[1], f[2], 1.0);
        ata += r * r.transpose();
    }
    let ch = cholesky(&ata)?;
    let mut k = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for j in 0..3 {
        let mut atb = nalgebra::Vector4::zeros();
        for (f, raw) in &rows {
            atb += nalgebra::Vector4::new(f[0], f[1], f[2], 1.0) * raw[j];
        }
        let s = ch.solve(&atb);
        k[(j, 0)] = s[0];
        k[(j, 1)] = s[1];
        k[(j, 2)] = s[2];
        b[j] = s[3];
    }
    let m = k.try_inverse()?;
    Some(Calibration {
        model: ModelKind::Full12,
        offset: [b[0], b[1], b[2]],
        matrix: mat_to_rows(&m),
    })
}

/// Rotation between the magnetometer and accelerometer frames from the gravity-field angle: at each
/// static pose the angle between calibrated gravity direction `g_i` (unit, down) and calibrated field
/// `m_i` (unit) is the same (the dip). Finds the rotation `R` (applied to the field) and the dip that
/// make `g_i . (R m_i) = sin(dip)` hold best. Returns (R, dip_rad, rms, condition).
pub(crate) fn fit_dip_rotation(
    gravity_dirs: &[Vec3],
    field_dirs: &[Vec3],
) -> Option<(Matrix3<f64>, f64, f64, f64)> {
    let n = gravity_dirs.len().min(field_dirs.len());
    if n < 6 {
        return None;
    }
    let g: Vec<Vector3<f64>> = gravity_dirs[..n]
        .iter()
        .map(|v| Vector3::new(v[0], v[1], v[2]).normalize())
        .collect();
    let m: Vec<Vector3<f64>> = field_dirs[..n]
        .iter()
        .map(|v| Vector3::new(v[0], v[1], v[2]).normalize())
        .collect();
    let mean_dot = g.iter().zip(&m).map(|(a, b)| a.dot(b)).sum::<f64>() / n as f64;
    let x0 = SVector::<f64, 4>::new(0.0, 0.0, 0.0, mean_dot);
    let out = crate::calib::lm::minimise_pointwise::<4, _>(
        x0,
        n,
        &LmOptions::new(100, NORM_STOP_REL_GAIN),
        |p| crate::calib::model::rotation_from_vector(&Vector3::new(p[0], p[1], p[2])),
        |r, p, i, grad| {
            let rm = r * m[i];
            // Small-angle derivative about the current rotation: d(R m)/dw ~ -[R m]x
            let dw = rm.cross(&g[i]);
            grad[0] = dw[0];
            grad[1] = dw[1];
            grad[2] = dw[2];
            grad[3] = -1.0;
            g[i].dot(&rm) - p[3]
        },
    );
    let w = Vector3::new(out.params[0], out.params[1], out.params[2]);
    let eig = out.jtj.symmetric_eigen();
    let lmin = eig
        .eigenvalues
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min);
    let lmax = eig.eigenvalues.iter().cloned().fold(0.0, f64::max);
    let cond = if lmin > 0.0 {
        lmax / lmin
    } else {
        f64::INFINITY
    };
    Some((
        crate::calib::model::rotation_from_vector(&w),
        out.params[3].clamp(-1.0, 1.0).asin(),
        (out.ssr / n as f64).sqrt(),
        cond,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn sphere_points(n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| loop {
                let v = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                let l = v.norm();
                if l > 0.1 && l < 1.0 {
                    break v / l;
                }
            })
            .collect()
    }

    #[test]
    fn condition_estimate_is_close_to_the_eigenvalue_ratio() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for case in 0..200 {
            // Random orthogonal basis and a spread of spectra: clustered, geometric, one tiny.
            let q = nalgebra::SMatrix::<f64, 9, 9>::from_fn(|_, _| rng.random_range(-1.0..1.0))
                .qr()
                .q();
            let spread = [1.0, 4.0, 1e3, 1e8, 1e13][case % 5];
            let d = SVector::<f64, 9>::from_fn(|i, _| {
                if case % 7 == 0 && i == 0 {
                    1.0 / spread
                } else {
                    spread.powf(rng.random_range(0.0..1.0))
                }
            });
            let m = q * SMatrix::<f64, 9, 9>::from_diagonal(&d) * q.transpose();
            let m = (m + m.transpose()) * 0.5;
            let exact = {
                let e = m.symmetric_eigenvalues();
                if e.min() > 0.0 {
                    e.max() / e.min()
                } else {
                    f64::INFINITY
                }
            };
            let inv = cholesky(&m).map(|c| c.inverse());
            let est = condition_number(&m, inv.as_ref());
            if exact > 1e12 {
                assert!(est > 1e11, "case {case}: {est:e} vs {exact:e}");
                continue;
            }
            assert!(
                // (The reference itself is only good to about eps * condition.)
                est <= exact * (1.0 + 1e-14 * exact) && est >= 0.9 * exact,
                "case {case}: {est:e} vs {exact:e}"
            );
        }
    }

    /// Nothing to iterate on (a zero or non-finite matrix): 0, for each size a fit uses.
    #[test]
    fn largest_eigenvalue_of_nothing_is_zero() {
        fn check<const N: usize>() {
            assert_eq!(largest_eigenvalue(&SMatrix::<f64, N, N>::zeros()), 0.0);
            let nan = SMatrix::<f64, N, N>::from_element(f64::NAN);
            assert_eq!(largest_eigenvalue(&nan), 0.0);
        }
        check::<4>();
        check::<6>();
        check::<9>();
    }

    /// 300 points on a slightly sheared, shifted unit sphere with uniform noise of `noise`.
    fn noisy_ellipsoid(seed: u64, noise: f64, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<Vec3> {
        let m = Matrix3::new(1.06, 0.03, -0.02, 0.03, 0.95, 0.04, -0.02, 0.04, 1.02);
        sphere_points(300, seed)
            .iter()
            .map(|u| {
                let x = m * u + Vector3::new(0.05, -0.03, 0.02);
                [0, 1, 2].map(|k| x[k] + noise * rng.random_range(-1.0..1.0))
            })
            .collect()
    }

    /// A `sym9` LM run on `pts` (raw frame) from `x0`: the outcome, the evaluations, and how many
    /// of them formed J^T J.
    fn sym9_run(
        pts: &[Vec3],
        x0: &SVector<f64, 9>,
        shortcuts: LmShortcuts,
    ) -> (
        crate::calib::lm::LmOutcome<nalgebra::Const<9>>,
        usize,
        usize,
    ) {
        let soa = kernel::Soa::normalised(pts, [0.0; 3], 1.0);
        let mut scratch = kernel::Scratch::new(soa.padded);
        let (mut evals, mut formed) = (0, 0);
        let opts = LmOptions {
            max_iter: 200,
            stop_rel_gain: NORM_STOP_REL_GAIN,
            shortcuts,
        };
        let out = crate::calib::lm::minimise_normal(*x0, &opts, |p, with_jtj| {
            evals += 1;
            formed += usize::from(with_jtj);
            kernel::norm_normal_equations::<{ kernel::SYM9 }, 9>(p, &soa, &mut scratch, with_jtj)
        });
        (out, evals, formed)
    }

    /// Taking the last, tiny step unevaluated lands where evaluating every step does, with fewer
    /// evaluations.
    #[test]
    fn unevaluated_last_step_lands_where_evaluating_would() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        for case in 0..20 {
            let noise = [0.0, 1e-3, 5e-3, 2e-2][case % 4];
            let pts = noisy_ellipsoid(100 + case as u64, noise, &mut rng);
            let x0 = SVector::<f64, 9>::from_column_slice(&[
                0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0,
            ]);
            let run = |tol: f64| {
                let shortcuts = LmShortcuts {
                    last_step: tol,
                    reuse_jtj: 0.0,
                };
                let (out, evals, formed) = sym9_run(&pts, &x0, shortcuts);
                assert_eq!(evals, formed, "J^T J is formed at every evaluation");
                (out, evals)
            };
            let (every, every_evals) = run(0.0);
            let (last, last_evals) = run(1e-6 / (300.0 - 9.0));
            assert!(every.converged && last.converged, "case {case}");
            let d = (every.params - last.params).norm();
            assert!(d < 1e-9, "case {case}: parameters differ by {d:e}");
            assert!(
                (every.ssr - last.ssr).abs() <= 1e-9 * every.ssr + 1e-24,
                "case {case}: ssr {} vs {}",
                every.ssr,
                last.ssr
            );
            assert!(
                last_evals <= every_evals,
                "case {case}: {last_evals} vs {every_evals}"
            );
            if noise > 0.0 {
                assert!(
                    last_evals < every_evals,
                    "case {case}: {last_evals} vs {every_evals}"
                );
            }
        }
    }

    /// Reusing J^T J near the solution lands on the same minimum, with J^T J (and so the
    /// covariance) within about the reuse distance of the one at the solution, and forms fewer.
    #[test]
    fn reused_jtj_lands_where_forming_it_every_time_would() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(23);
        let mut reused_somewhere = false;
        for case in 0..20 {
            let noise = [0.0, 1e-3, 5e-3, 2e-2][case % 4];
            let pts = noisy_ellipsoid(300 + case as u64, noise, &mut rng);
            // From the algebraic start, as the norm fits do (the first step is then short).
            let fitter = NormFitter::new(&pts);
            let start = fitter.frame.ellipsoid.expect("ellipsoid start");
            let (c, s) = fitter.frame.sphere.expect("sphere");
            let centre = Vector3::from(c) + start.centre * s;
            let mut x0v = vec![centre[0], centre[1], centre[2]];
            x0v.extend(params_from_a(ModelKind::Sym9, &(start.shape / s)));
            let x0 = SVector::<f64, 9>::from_column_slice(&x0v);
            let run = |reuse: f64| {
                let shortcuts = LmShortcuts {
                    last_step: 1e-6 / 291.0,
                    reuse_jtj: reuse,
                };
                let (out, _, formed) = sym9_run(&pts, &x0, shortcuts);
                (out, formed)
            };
            let (every, every_formed) = run(0.0);
            let reuse = 1e-2;
            let (some, some_formed) = run(reuse);
            assert!(every.converged && some.converged, "case {case}");
            let d = (every.params - some.params).amax();
            assert!(d < 1e-9, "case {case}: parameters differ by {d:e}");
            assert!(
                (every.ssr - some.ssr).abs() <= 1e-9 * every.ssr + 1e-24,
                "case {case}: ssr {} vs {}",
                every.ssr,
                some.ssr
            );
            let rel = (every.jtj - some.jtj).amax() / every.jtj.amax();
            assert!(rel <= 5.0 * reuse, "case {case}: J^T J differs by {rel:e}");
            assert!(some_formed <= every_formed, "case {case}");
            reused_somewhere |= some_formed < every_formed;
        }
        assert!(reused_somewhere, "no case reused J^T J");
    }

    #[test]
    fn recovers_sym9_exactly_without_noise() {
        let m_true = Matrix3::new(1.05, 0.02, -0.01, 0.02, 0.97, 0.03, -0.01, 0.03, 1.01);
        let o = Vector3::new(12.0, -30.0, 45.0);
        let radius = 48.0;
        let minv = m_true.try_inverse().unwrap();
        let raw: Vec<Vec3> = sphere_points(400, 1)
            .iter()
            .map(|u| {
                let r = minv * (u * radius) + o;
                [r[0], r[1], r[2]]
            })
            .collect();
        let fit = fit_norm(&raw, ModelKind::Sym9, &NormFitOptions::default()).unwrap();
        for k in 0..3 {
            assert!(
                (fit.calibration.offset[k] - o[k]).abs() < 1e-6,
                "offset {:?}",
                fit.calibration.offset
            );
        }
        let mn = fit.calibration.normalised_matrix();
        let tn = m_true / m_true.determinant().cbrt();
        assert!((mn - tn).abs().max() < 1e-8, "{mn} vs {tn}");
        assert!(fit.rms_residual < 1e-6);
    }

    #[test]
    fn ellipsoid_start_matches_truth() {
        let pts: Vec<Vec3> = sphere_points(200, 2)
            .iter()
            .map(|u| [u[0] * 2.0 + 1.0, u[1] * 1.0 - 1.0, u[2] * 0.5])
            .collect();
        let s = ellipsoid_start(&pts).unwrap();
        assert!((s.centre - Vector3::new(1.0, -1.0, 0.0)).norm() < 1e-9);
        assert!((s.shape[(0, 0)] - 0.5).abs() < 1e-9 && (s.shape[(2, 2)] - 2.0).abs() < 1e-9);
    }

    /// The models fitted with the last on a second thread ([`NormFitter::fit_each`]) are the
    /// models fitted one after the other, bit for bit, on a well-posed set and on a narrow patch
    /// (fits that run off and fail).
    #[test]
    fn fitting_on_two_threads_gives_what_one_after_the_other_does() {
        let kinds = [ModelKind::Sphere, ModelKind::Diag6, ModelKind::Sym9];
        let opts = NormFitOptions::default();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let tumble = noisy_ellipsoid(7, 1e-2, &mut rng);
        // A cap of about 8 deg around +z: too little of the sphere to outline an ellipsoid.
        let patch: Vec<Vec3> = sphere_points(300, 11)
            .iter()
            .map(|u| {
                let v = Vector3::new(0.07 * u.x, 0.07 * u.y, 1.0).normalize();
                [0, 1, 2].map(|k| 40.0 * v[k] + 0.2 * rng.random_range(-1.0..1.0))
            })
            .collect();
        for pts in [tumble, patch] {
            assert!(pts.len() >= PARALLEL_FIT_MIN_POINTS);
            let both = NormFitter::new(&pts).fit_each(&kinds, &opts);
            let mut one = NormFitter::new(&pts);
            assert_eq!(both.len(), kinds.len());
            for (k, got) in kinds.iter().zip(&both) {
                let want = one.fit(*k, &opts);
                match (got, &want) {
                    (Ok(a), Ok(b)) => {
                        assert_eq!(a.calibration, b.calibration, "{k:?}");
                        assert_eq!(a.ssr_normalised.to_bits(), b.ssr_normalised.to_bits());
                        assert_eq!((a.iterations, a.converged), (b.iterations, b.converged));
                    }
                    (Err(a), Err(b)) => assert_eq!(a, b),
                    _ => panic!("{k:?}: {got:?} against {want:?}"),
                }
            }
        }
    }

    #[test]
    fn auto_test_prefers_simple_when_equal() {
        assert!(!significantly_better(1.0, 0.9999, 3, 1000, 9));
        assert!(significantly_better(1.0, 0.5, 3, 1000, 9));
        // Standard tables: 10.828 (1 df), 16.266 (3), 32.909 (12).
        for (df, q) in [(1, 10.828), (3, 16.266), (12, 32.909)] {
            assert!(
                (chi2_quantile_999(df) - q).abs() < 2e-3,
                "{df}: {}",
                chi2_quantile_999(df)
            );
        }
    }

    #[test]
    fn six_position_recovers_bias_and_scale() {
        let k = Matrix3::new(1.01, 0.0, 0.0, 0.0, 0.98, 0.0, 0.0, 0.0, 1.02);
        let b = Vector3::new(0.1, -0.05, 0.2);
        let g = 9.81;
        let mut poses = vec![];
        for axis in 0..3 {
            for s in [1.0, -1.0] {
                let mut f = Vector3::zeros();
                f[axis] = s * g;
                let r = k * f + b;
                poses.push([r[0], r[1], r[2]]);
            }
        }
        let c = six_position(&poses, g, 20.0).unwrap();
        let a = c.apply(&poses[0]);
        assert!((a[0] - g).abs() < 1e-9 && a[1].abs() < 1e-9);
        assert!((c.offset[2] - 0.2).abs() < 1e-9);
    }

    #[test]
    fn dip_rotation_recovers_misalignment() {
        let dip = 60f64.to_radians();
        let r_true = crate::calib::model::rotation_from_vector(&Vector3::new(0.02, -0.01, 0.03));
        let mut gs = vec![];
        let mut ms = vec![];
        for (i, u) in sphere_points(30, 3).iter().enumerate() {
            // body attitude: random rotation taking world to body
            let q = crate::calib::model::rotation_from_vector(&(u * (0.3 + 0.1 * i as f64)));
            let g_w = Vector3::new(0.0, 0.0, 1.0);
            let m_w = Vector3::new(dip.cos(), 0.0, dip.sin());
            let gb = q * g_w;
            let mb = r_true.transpose() * (q * m_w);
            gs.push([gb[0], gb[1], gb[2]]);
            ms.push([mb[0], mb[1], mb[2]]);
        }
        let (r, d, rms, _) = fit_dip_rotation(&gs, &ms).unwrap();
        assert!(rms < 1e-9, "rms {rms}");
        assert!((d - dip).abs() < 1e-8);
        // Rotation about gravity is free only when all poses share one gravity direction; here it is not.
        assert!((r - r_true).abs().max() < 1e-6, "{r} vs {r_true}");
    }
}
