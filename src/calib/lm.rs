//! Levenberg-Marquardt least squares: the one solver of every nonlinear fit in the crate, over a
//! parameter vector of fixed size (the calibration fits of `fit`, `nalgebra`'s `Const<N>`) or of a
//! size known only at run time (`diagnose`'s joint forward model, the gyro scale fit: `Dyn`).
//!
//! A problem hands the iteration its normal equations ([`Problem`]): the calibration fits build
//! them from analytic gradients in one pass over the points ([`minimise_normal`],
//! [`minimise_pointwise`]), the others from residuals with a forward-difference Jacobian
//! ([`minimise`]).
//!
//! One damping strategy (Marquardt's scaling of the diagonal, as in Ren and Liu, "Calibration of
//! MEMS Accelerometers and Magnetometers for Rotor UAV Attitude Estimation", eq. 13): the normal
//! matrix J^T J gets `lambda * diag(J^T J)` added; a step that lowers the sum of squares is taken
//! and `lambda` multiplied by [`DAMPING_DOWN`], otherwise `lambda` is multiplied by [`DAMPING_UP`]
//! and the step retried. The fit stops when a step gains, or the linear model predicts it would
//! gain, at most [`LmOptions::stop_rel_gain`] of the sum of squares, when a step is negligible
//! against the parameters, when `lambda` exceeds [`MAX_DAMPING`] (no descent left) or after
//! [`LmOptions::max_iter`] steps tried.
//!
//! [`cholesky`] is the one factorisation the fits solve and invert with.
//!
//! Pure: no I/O.

use nalgebra::allocator::Allocator;
use nalgebra::{
    Cholesky, DMatrix, DVector, DefaultAllocator, Dim, Dyn, OMatrix, OVector, SMatrix, SVector,
};

/// Damping at the start, relative to the diagonal of J^T J.
pub(crate) const INITIAL_DAMPING: f64 = 1e-3;
/// Factor the damping grows by after a step that does not lower the sum of squares.
pub(crate) const DAMPING_UP: f64 = 10.0;
/// Factor the damping is multiplied by after an accepted step.
pub(crate) const DAMPING_DOWN: f64 = 0.1;
/// Smallest damping (relative to the diagonal).
pub(crate) const MIN_DAMPING: f64 = 1e-15;
/// Above this damping no descent direction is left: the fit stops.
pub(crate) const MAX_DAMPING: f64 = 1e12;
/// [`minimise`]'s [`LmOptions::stop_rel_gain`]: its residuals come through finite differences.
pub(crate) const STOP_REL_GAIN: f64 = 1e-11;
/// A step shorter than this, relative to the parameter vector, ends the fit.
pub(crate) const STOP_REL_STEP: f64 = 1e-12;
/// Forward-difference step, relative to max(|p_i|, typical size of p_i).
pub(crate) const DIFF_REL_STEP: f64 = 1e-6;
/// Floor of a diagonal entry of J^T J when it scales the damping (a column without influence).
const DIAG_FLOOR: f64 = 1e-30;

/// The Cholesky factor `L L^T = a` of a symmetric positive-definite matrix (its lower triangle is
/// read). `None` unless every entry is finite and every pivot positive, i.e. unless `a` is positive
/// definite to working precision (nalgebra refuses a pivot that is not positive; from finite
/// entries a pivot cannot grow past the diagonal entry it starts from, so the factor is then
/// finite).
pub(crate) fn cholesky<D: Dim>(a: &OMatrix<f64, D, D>) -> Option<Cholesky<f64, D>>
where
    DefaultAllocator: Allocator<D, D>,
{
    if !a.iter().all(|v| v.is_finite()) {
        return None;
    }
    a.clone().cholesky()
}

/// The normal equations at a point: J^T J (`None`: the iteration goes on with an earlier one) and
/// J^T r.
pub struct Normal<D: Dim>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    pub jtj: Option<OMatrix<f64, D, D>>,
    pub jtr: OVector<f64, D>,
}

/// A least-squares problem as the iteration sees it: the sum of squares at a point, and the normal
/// equations at a point the iteration keeps.
pub(crate) trait Problem<D: Dim>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    /// The sum of squared residuals at `x`. `with_jtj`: J^T J is wanted should the iteration keep
    /// `x` (otherwise it goes on with an earlier one).
    fn ssr(&mut self, x: &OVector<f64, D>, with_jtj: bool) -> f64;
    /// J^T J (when it was asked for, else `None`) and J^T r at the point last given to
    /// [`Problem::ssr`], which the iteration keeps.
    fn normal(&mut self) -> Normal<D>;
    /// Whether `x`, a point the iteration kept, still stands for a solution the problem can have;
    /// when not, the run ends there, not converged. Every point does by default.
    fn plausible(&self, _x: &OVector<f64, D>) -> bool {
        true
    }
}

/// Work a run may skip near the solution, where it would only confirm what the linear model
/// already says. Both 0 (the default) skip nothing.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct LmShortcuts {
    /// When the reduction the linear model predicts for the next step is at most this fraction of
    /// the sum of squares, the step is taken without evaluating where it lands, and the sum of
    /// squares becomes the predicted one. Norm fits pass `1e-6 / dof`: the step is then at most a
    /// thousandth of a standard error long (`predicted / s^2 = step^T J^T J step / s^2`), where the
    /// quadratic model is exact to far below anything a fit can resolve, so the evaluation would
    /// only confirm it.
    pub last_step: f64,
    /// While the parameters are within this distance (largest component, summed over the steps
    /// taken since) of the point where J^T J was last formed, evaluations form only the sum of
    /// squares and J^T r, and the steps use that J^T J. The steps then still lead to the point where
    /// J^T r = 0, the same minimum; J^T J, and so the covariance, comes from a point this close to
    /// it, which for parameters of order 1 changes it by a relative amount of about this size.
    pub reuse_jtj: f64,
}

/// When a run stops.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LmOptions {
    /// Most steps tried (taken or refused).
    pub max_iter: usize,
    /// A step that lowers the sum of squares by at most this fraction of it (or that the linear
    /// model predicts would) ends the fit, converged.
    pub stop_rel_gain: f64,
    pub shortcuts: LmShortcuts,
}

impl LmOptions {
    /// Stop at `max_iter` steps or a relative gain of `stop_rel_gain`; no shortcuts.
    pub fn new(max_iter: usize, stop_rel_gain: f64) -> Self {
        LmOptions {
            max_iter,
            stop_rel_gain,
            shortcuts: LmShortcuts::default(),
        }
    }
}

/// Outcome of a run.
#[derive(Debug, Clone)]
pub(crate) struct LmOutcome<D: Dim>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    pub params: OVector<f64, D>,
    /// Sum of squared residuals at the solution.
    pub ssr: f64,
    /// Steps tried.
    pub iterations: usize,
    /// J^T J at the solution (for uncertainties), or with [`LmShortcuts`] at a point within
    /// `reuse_jtj` plus the last, unevaluated step of it.
    pub jtj: OMatrix<f64, D, D>,
    pub converged: bool,
}

/// The Levenberg-Marquardt iteration on `problem` from `x0`.
pub(crate) fn solve<D: Dim, P: Problem<D> + ?Sized>(
    x0: OVector<f64, D>,
    opts: &LmOptions,
    problem: &mut P,
) -> LmOutcome<D>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    let (n, _) = x0.shape_generic();
    let mut x = x0;
    let mut ssr = problem.ssr(&x, true);
    let Normal { jtj: jtj0, mut jtr } = problem.normal();
    let mut jtj = jtj0.unwrap_or_else(|| OMatrix::zeros_generic(n, n));
    // Distance walked since J^T J was formed.
    let mut drift = 0.0;
    let mut lambda = INITIAL_DAMPING;
    let mut converged = false;
    let mut it = 0;
    while it < opts.max_iter {
        it += 1;
        let mut a = jtj.clone();
        for k in 0..a.nrows() {
            a[(k, k)] += lambda * jtj[(k, k)].max(DIAG_FLOOR);
        }
        let step = match cholesky(&a) {
            Some(ch) => ch.solve(&(-&jtr)),
            None => {
                lambda *= DAMPING_UP;
                if lambda > MAX_DAMPING {
                    break;
                }
                continue;
            }
        };
        // Reduction the linear model predicts for the step: when even that is below the tolerance,
        // we are at the minimum to working precision and another evaluation would not move us.
        let predicted = -(2.0 * step.dot(&jtr) + (&jtj * &step).dot(&step));
        if predicted.abs() <= opts.stop_rel_gain * ssr.max(1e-300) {
            converged = true;
            break;
        }
        if predicted >= 0.0 && predicted <= opts.shortcuts.last_step * ssr && lambda <= 1e-2 {
            x += &step;
            ssr = (ssr - predicted).max(0.0);
            converged = true;
            break;
        }
        let x_new = &x + &step;
        let reuse = drift + step.amax() <= opts.shortcuts.reuse_jtj;
        let ssr_new = problem.ssr(&x_new, !reuse);
        if ssr_new.is_finite() && ssr_new <= ssr {
            let small_step = step.norm() <= STOP_REL_STEP * (x.norm() + 1e-12);
            let small_gain = ssr - ssr_new <= opts.stop_rel_gain * ssr.max(1e-300);
            let Normal {
                jtj: jtj_new,
                jtr: jtr_new,
            } = problem.normal();
            x = x_new;
            ssr = ssr_new;
            jtr = jtr_new;
            match jtj_new {
                Some(m) => {
                    jtj = m;
                    drift = 0.0;
                }
                None => drift += step.amax(),
            }
            lambda = (lambda * DAMPING_DOWN).max(MIN_DAMPING);
            if !problem.plausible(&x) {
                break;
            }
            if small_step || small_gain || ssr == 0.0 {
                converged = true;
                break;
            }
        } else {
            lambda *= DAMPING_UP;
            if lambda > MAX_DAMPING {
                // No descent direction left: we are at a minimum to working precision.
                converged = jtr.norm() <= 1e-8 * (1.0 + ssr.sqrt());
                break;
            }
        }
    }
    LmOutcome {
        params: x,
        ssr,
        iterations: it,
        jtj,
        converged,
    }
}

/// Normal equations built whole at each point by `eval(x, with_jtj) -> (ssr, J^T J when asked,
/// J^T r)`, as a [`Problem`] whose plausible points are those `plausible` accepts.
struct Batch<D: Dim, F, G>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    eval: F,
    plausible: G,
    /// The normal equations of the last point evaluated.
    last: Option<Normal<D>>,
}

impl<D: Dim, F, G> Problem<D> for Batch<D, F, G>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
    F: FnMut(&OVector<f64, D>, bool) -> (f64, Option<OMatrix<f64, D, D>>, OVector<f64, D>),
    G: Fn(&OVector<f64, D>) -> bool,
{
    fn plausible(&self, x: &OVector<f64, D>) -> bool {
        (self.plausible)(x)
    }

    fn ssr(&mut self, x: &OVector<f64, D>, with_jtj: bool) -> f64 {
        let (ssr, jtj, jtr) = (self.eval)(x, with_jtj);
        self.last = Some(Normal { jtj, jtr });
        ssr
    }

    fn normal(&mut self) -> Normal<D> {
        self.last.take().expect("normal() follows ssr()")
    }
}

/// [`solve`] on normal equations that `eval(p, with_jtj)` builds whole: the sum of squared
/// residuals, J^T J (when `with_jtj`; `None` keeps the earlier one) and J^T r at `p`.
pub(crate) fn minimise_normal<D: Dim>(
    x0: OVector<f64, D>,
    opts: &LmOptions,
    eval: impl FnMut(&OVector<f64, D>, bool) -> (f64, Option<OMatrix<f64, D, D>>, OVector<f64, D>),
) -> LmOutcome<D>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    minimise_normal_within(x0, opts, eval, |_| true)
}

/// [`minimise_normal`] that ends, not converged, at the first point it keeps that `plausible`
/// refuses ([`Problem::plausible`]).
pub(crate) fn minimise_normal_within<D: Dim>(
    x0: OVector<f64, D>,
    opts: &LmOptions,
    eval: impl FnMut(&OVector<f64, D>, bool) -> (f64, Option<OMatrix<f64, D, D>>, OVector<f64, D>),
    plausible: impl Fn(&OVector<f64, D>) -> bool,
) -> LmOutcome<D>
where
    DefaultAllocator: Allocator<D> + Allocator<D, D>,
{
    solve(
        x0,
        opts,
        &mut Batch {
            eval,
            plausible,
            last: None,
        },
    )
}

/// [`solve`] on residuals given point by point: `prepare(p)` runs once per parameter vector and
/// its result is handed to every `resid(prepared, p, i, grad)` call (a matrix built from the
/// parameters, say), which returns residual `i` and writes its gradient. The normal equations are
/// accumulated point by point, so memory is O(N^2) whatever the number of points.
pub(crate) fn minimise_pointwise<const N: usize, P>(
    x0: SVector<f64, N>,
    n_points: usize,
    opts: &LmOptions,
    prepare: impl Fn(&SVector<f64, N>) -> P,
    resid: impl Fn(&P, &SVector<f64, N>, usize, &mut SVector<f64, N>) -> f64,
) -> LmOutcome<nalgebra::Const<N>> {
    let eval = |x: &SVector<f64, N>, _with_jtj: bool| {
        // (J^T J is summed in the same loop as J^T r, so it is always formed.)
        let mut jtj = SMatrix::<f64, N, N>::zeros();
        let mut jtr = SVector::<f64, N>::zeros();
        let mut g = SVector::<f64, N>::zeros();
        let mut ssr = 0.0;
        let prep = prepare(x);
        for i in 0..n_points {
            let r = resid(&prep, x, i, &mut g);
            ssr += r * r;
            jtr += g * r;
            // Symmetric rank-1 update, upper triangle only.
            for c in 0..N {
                let gc = g[c];
                for rr in 0..=c {
                    jtj[(rr, c)] += g[rr] * gc;
                }
            }
        }
        for c in 0..N {
            for rr in 0..c {
                jtj[(c, rr)] = jtj[(rr, c)];
            }
        }
        (ssr, Some(jtj), jtr)
    };
    minimise_normal(x0, opts, eval)
}

/// Residual function: parameters in, residuals written to the (cleared or overwritten) vector.
pub(crate) type Residuals<'a> = &'a dyn Fn(&[f64], &mut Vec<f64>);

/// The result of [`minimise`].
#[derive(Debug, Clone)]
pub(crate) struct LmFit {
    pub p: DVector<f64>,
    /// Sum of squared residuals at `p`.
    pub ssr: f64,
    /// J^T J at `p` (forward differences).
    pub jtj: DMatrix<f64>,
    /// Residuals at `p`.
    pub r: Vec<f64>,
}

/// Forward-difference Jacobian of `f` at `p` (`r0` = f(p)); `typ` gives each parameter's typical size,
/// which sets the step where the parameter is near zero.
pub(crate) fn jacobian(f: Residuals, p: &DVector<f64>, r0: &[f64], typ: &[f64]) -> DMatrix<f64> {
    let m = r0.len();
    let n = p.len();
    let mut j = DMatrix::zeros(m, n);
    let mut pp = p.clone();
    let mut r = Vec::with_capacity(m);
    for c in 0..n {
        let h = DIFF_REL_STEP * p[c].abs().max(typ[c]);
        pp[c] = p[c] + h;
        f(pp.as_slice(), &mut r);
        pp[c] = p[c];
        for i in 0..m.min(r.len()) {
            j[(i, c)] = (r[i] - r0[i]) / h;
        }
    }
    j
}

fn ssr_of(r: &[f64]) -> f64 {
    r.iter().map(|x| x * x).sum()
}

/// Residuals with a forward-difference Jacobian, as a [`Problem`].
struct Differenced<'a> {
    f: Residuals<'a>,
    typ: &'a [f64],
    /// The last point evaluated and its residuals.
    x: DVector<f64>,
    r: Vec<f64>,
    /// The residuals at the last point the iteration kept.
    kept: Vec<f64>,
}

impl Problem<Dyn> for Differenced<'_> {
    fn ssr(&mut self, x: &DVector<f64>, _with_jtj: bool) -> f64 {
        self.x.clone_from(x);
        (self.f)(x.as_slice(), &mut self.r);
        ssr_of(&self.r)
    }

    fn normal(&mut self) -> Normal<Dyn> {
        let j = jacobian(self.f, &self.x, &self.r, self.typ);
        let jtr = j.tr_mul(&DVector::from_column_slice(&self.r));
        self.kept.clone_from(&self.r);
        Normal {
            jtj: Some(j.tr_mul(&j)),
            jtr,
        }
    }
}

/// Minimise the sum of squares of `f` from `p0` (at most `max_iter` steps tried), differencing
/// the Jacobian with steps set by `typ`, the typical size of each parameter.
pub(crate) fn minimise(f: Residuals, p0: DVector<f64>, typ: &[f64], max_iter: usize) -> LmFit {
    let mut problem = Differenced {
        f,
        typ,
        x: p0.clone(),
        r: Vec::new(),
        kept: Vec::new(),
    };
    let out = solve(p0, &LmOptions::new(max_iter, STOP_REL_GAIN), &mut problem);
    LmFit {
        p: out.params,
        ssr: out.ssr,
        jtj: out.jtj,
        r: problem.kept,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_an_exponential_decay() {
        // y = a exp(-b x) + c at 30 points, no noise: the fit must return (a, b, c).
        let truth = [2.5, 0.7, -0.3];
        let xs: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let f = |p: &[f64], out: &mut Vec<f64>| {
            out.clear();
            for &x in &xs {
                let y = truth[0] * (-truth[1] * x).exp() + truth[2];
                out.push(p[0] * (-p[1] * x).exp() + p[2] - y);
            }
        };
        let fit = minimise(&f, DVector::from_vec(vec![1.0, 0.1, 0.0]), &[1.0; 3], 100);
        for k in 0..3 {
            // Measured: error below 1e-9 on each parameter.
            assert!((fit.p[k] - truth[k]).abs() < 1e-7, "{:?}", fit.p);
        }
        assert!(fit.ssr < 1e-18, "{}", fit.ssr);
        assert_eq!(fit.jtj.shape(), (3, 3));
    }

    #[test]
    fn a_residual_that_does_not_depend_on_a_parameter_does_not_break_the_fit() {
        // p[1] has no influence: its column is zero, the damped normal matrix stays solvable.
        let f = |p: &[f64], out: &mut Vec<f64>| {
            out.clear();
            out.extend([p[0] - 3.0, 2.0 * (p[0] - 3.0)]);
        };
        let fit = minimise(&f, DVector::from_vec(vec![0.0, 5.0]), &[1.0; 2], 50);
        assert!((fit.p[0] - 3.0).abs() < 1e-9, "{:?}", fit.p);
        assert_eq!(fit.p[1], 5.0);
    }

    /// Not positive definite, or not finite: no factor.
    #[test]
    fn cholesky_refuses_what_is_not_positive_definite() {
        let mut a = SMatrix::<f64, 4, 4>::identity();
        a[(2, 2)] = 0.0;
        assert!(cholesky(&a).is_none());
        a[(2, 2)] = -1.0;
        assert!(cholesky(&a).is_none());
        a[(2, 2)] = f64::NAN;
        assert!(cholesky(&a).is_none());
        a[(2, 2)] = f64::INFINITY;
        assert!(cholesky(&a).is_none());
        let mut b = SMatrix::<f64, 4, 4>::identity();
        b[(3, 1)] = f64::NAN;
        b[(1, 3)] = f64::NAN;
        assert!(cholesky(&b).is_none());
        // Finite entries whose factor would overflow.
        let c = SMatrix::<f64, 2, 2>::new(1e-300, 0.0, 1e300, 1.0);
        assert!(cholesky(&c).is_none());
        assert!(cholesky(&SMatrix::<f64, 4, 4>::identity()).is_some());
    }
}
