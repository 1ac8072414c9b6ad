//! Levenberg-Marquardt least squares over a dynamic-size parameter vector with a forward-difference
//! Jacobian, for the fits where the parameter count is known only at run time or speed does not
//! matter: `diagnose`'s joint forward model and the gyro scale/misalignment fit (`gyro`).
//!
//! One damping strategy (Marquardt's scaling of the diagonal): the normal matrix J^T J gets
//! `lambda * diag(J^T J)` added; a step that lowers the sum of squares is taken and `lambda` multiplied by
//! [`DAMPING_DOWN`], otherwise `lambda` is multiplied by [`DAMPING_UP`] and the step retried. The fit
//! stops when a step gains less than [`STOP_REL_GAIN`] of the sum of squares, when `lambda` exceeds
//! [`MAX_DAMPING`] (no descent left) or after `max_iter` Jacobians.
//!
//! Pure: no I/O. The fixed-size, analytic-gradient solver of the calibration fits lives in `fit`.

use nalgebra::{DMatrix, DVector};

/// Damping at the start, relative to the diagonal of J^T J.
pub const INITIAL_DAMPING: f64 = 1e-3;
/// Factor the damping grows by after a step that does not lower the sum of squares.
pub const DAMPING_UP: f64 = 10.0;
/// Factor the damping is multiplied by after an accepted step.
pub const DAMPING_DOWN: f64 = 0.1;
/// Smallest damping (relative to the diagonal).
pub const MIN_DAMPING: f64 = 1e-12;
/// Above this damping no descent direction is left: the fit stops.
pub const MAX_DAMPING: f64 = 1e12;
/// An accepted step that lowers the sum of squares by less than this fraction ends the fit.
pub const STOP_REL_GAIN: f64 = 1e-11;
/// Forward-difference step, relative to max(|p_i|, typical size of p_i).
pub const DIFF_REL_STEP: f64 = 1e-6;
/// Floor of a diagonal entry of J^T J when it scales the damping (a column without influence).
const DIAG_FLOOR: f64 = 1e-30;

/// Residual function: parameters in, residuals written to the (cleared or overwritten) vector.
pub type Residuals<'a> = &'a dyn Fn(&[f64], &mut Vec<f64>);

/// The result of [`minimise`].
#[derive(Debug, Clone)]
pub struct LmFit {
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
pub fn jacobian(f: Residuals, p: &DVector<f64>, r0: &[f64], typ: &[f64]) -> DMatrix<f64> {
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

/// Minimise the sum of squares of `f` from `p0` (at most `max_iter` Jacobians).
pub fn minimise(f: Residuals, p0: DVector<f64>, typ: &[f64], max_iter: usize) -> LmFit {
    let mut p = p0;
    let mut r = Vec::new();
    f(p.as_slice(), &mut r);
    let mut ssr = ssr_of(&r);
    let mut lambda = INITIAL_DAMPING;
    let n = p.len();
    let mut r_new = Vec::new();
    'outer: for _ in 0..max_iter {
        let j = jacobian(f, &p, &r, typ);
        let jtj = j.transpose() * &j;
        let jtr = j.transpose() * DVector::from_column_slice(&r);
        loop {
            let mut a = jtj.clone();
            for k in 0..n {
                a[(k, k)] += lambda * jtj[(k, k)].max(DIAG_FLOOR);
            }
            let step = match a.cholesky() {
                Some(ch) => ch.solve(&(-&jtr)),
                None => {
                    lambda *= DAMPING_UP;
                    if lambda > MAX_DAMPING {
                        break 'outer;
                    }
                    continue;
                }
            };
            let p_new = &p + &step;
            f(p_new.as_slice(), &mut r_new);
            let ssr_new = ssr_of(&r_new);
            if ssr_new.is_finite() && ssr_new <= ssr {
                let gain = ssr - ssr_new;
                p = p_new;
                std::mem::swap(&mut r, &mut r_new);
                ssr = ssr_new;
                lambda = (lambda * DAMPING_DOWN).max(MIN_DAMPING);
                if gain <= STOP_REL_GAIN * ssr.max(1e-300) {
                    break 'outer;
                }
                break;
            }
            lambda *= DAMPING_UP;
            if lambda > MAX_DAMPING {
                break 'outer;
            }
        }
    }
    let j = jacobian(f, &p, &r, typ);
    LmFit {
        jtj: j.transpose() * &j,
        p,
        ssr,
        r,
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
}
