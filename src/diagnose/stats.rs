//! The statistics of the decisions: F and t tail probabilities, the sum of squares a set of
//! regressors explains, column selection and the condition number of a normal matrix.

use super::layout::Layout;
use super::Effect;
use nalgebra::{DMatrix, DVector};

/// Singular values below this fraction of the largest count as zero (rank of a regressor set).
const RANK_REL_TOL: f64 = 1e-8;

/// Mean and sample standard deviation (NaN when undefined).
pub(super) fn mean_sd(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    if xs.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let m = xs.iter().sum::<f64>() / n;
    let v = if xs.len() > 1 {
        xs.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)
    } else {
        f64::NAN
    };
    (m, v.sqrt())
}

pub(super) fn ln_gamma(x: f64) -> f64 {
    // Lanczos approximation (g = 7, 9 terms), reflection for x < 0.5.
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Continued fraction of the incomplete beta function (modified Lentz).
fn beta_cf(a: f64, b: f64, x: f64) -> f64 {
    let tiny = 1e-300;
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 - qab * x / qap;
    if d.abs() < tiny {
        d = tiny;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..400 {
        let m = m as f64;
        let m2 = 2.0 * m;
        let aa = m * (b - m) * x / ((qam + m2) * (a + m2));
        d = 1.0 + aa * d;
        if d.abs() < tiny {
            d = tiny;
        }
        c = 1.0 + aa / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        h *= d * c;
        let aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2));
        d = 1.0 + aa * d;
        if d.abs() < tiny {
            d = tiny;
        }
        c = 1.0 + aa / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-14 {
            break;
        }
    }
    h
}

/// Regularised incomplete beta function I_x(a, b).
fn inc_beta(a: f64, b: f64, x: f64) -> f64 {
    if !(x > 0.0) {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let front = ln_front.exp();
    if x < (a + 1.0) / (a + b + 2.0) {
        front * beta_cf(a, b, x) / a
    } else {
        1.0 - front * beta_cf(b, a, 1.0 - x) / b
    }
}

/// Upper tail P(F > f) of the F distribution with (d1, d2) degrees of freedom.
pub(super) fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if !(f > 0.0) || !(d1 > 0.0) || !(d2 > 0.0) {
        return 1.0;
    }
    inc_beta(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * f)).clamp(0.0, 1.0)
}

/// Upper tail P(T > t) of Student's t with `dof` degrees of freedom.
pub(super) fn t_sf(t: f64, dof: f64) -> f64 {
    if !t.is_finite() {
        return if t > 0.0 { 0.0 } else { 1.0 };
    }
    let tail = 0.5 * inc_beta(0.5 * dof, 0.5, dof / (dof + t * t));
    if t > 0.0 {
        tail
    } else {
        1.0 - tail
    }
}

/// Sum of squares of `r` explained by the column space of `b` (columns normalised, rank-revealing SVD).
/// Also returns an orthonormal basis of that space.
pub(super) fn explained(b: &DMatrix<f64>, r: &DVector<f64>) -> (f64, DMatrix<f64>) {
    let (m, n) = b.shape();
    if n == 0 || m == 0 {
        return (0.0, DMatrix::zeros(m, 0));
    }
    let mut bn = b.clone();
    for c in 0..n {
        let s = bn.column(c).norm();
        if s > 0.0 {
            bn.column_mut(c).scale_mut(1.0 / s);
        }
    }
    let svd = bn.svd(true, false);
    let u = svd.u.expect("u requested");
    let smax = svd.singular_values.max();
    let keep: Vec<usize> = (0..svd.singular_values.len())
        .filter(|&i| svd.singular_values[i] > RANK_REL_TOL * smax.max(1e-300))
        .collect();
    let basis = DMatrix::from_fn(m, keep.len(), |i, j| u[(i, keep[j])]);
    let proj = basis.transpose() * r;
    (proj.norm_squared(), basis)
}

/// Columns of `lay` that belong to the effect `e`.
pub(super) fn columns(lay: &Layout, e: Effect) -> Vec<usize> {
    lay.block(e)
        .map(|b| (b.start..b.start + b.len).collect())
        .unwrap_or_default()
}

pub(super) fn select_cols(j: &DMatrix<f64>, cols: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(j.nrows(), cols.len(), |i, k| j[(i, cols[k])])
}

/// Condition number of the column-normalised normal matrix of the effect's columns plus the base.
pub(super) fn condition(jtj: &DMatrix<f64>) -> f64 {
    let n = jtj.nrows();
    let mut s = jtj.clone();
    for i in 0..n {
        for j in 0..n {
            let d = (jtj[(i, i)] * jtj[(j, j)]).sqrt();
            s[(i, j)] = if d > 0.0 { jtj[(i, j)] / d } else { 0.0 };
        }
    }
    let e = s.symmetric_eigen();
    let mx = e.eigenvalues.max();
    let mn = e.eigenvalues.min();
    if mn > 0.0 {
        mx / mn
    } else {
        f64::INFINITY
    }
}
