//! The statistics of the decisions: F and t tail probabilities (`statrs`), the sum of squares a set of
//! regressors explains, column selection and the condition number of a normal matrix.

use super::layout::Layout;
use super::Effect;
use nalgebra::{DMatrix, DVector};
use statrs::distribution::{ContinuousCDF, FisherSnedecor, StudentsT};

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

/// Upper tail P(F > f) of the F distribution with (d1, d2) degrees of freedom (1 when the test has
/// no content: f, d1 or d2 not positive).
pub(super) fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if !(f > 0.0) || !(d1 > 0.0) || !(d2 > 0.0) {
        return 1.0;
    }
    match FisherSnedecor::new(d1, d2) {
        Ok(d) => d.sf(f).clamp(0.0, 1.0),
        Err(_) => 1.0,
    }
}

/// Upper tail P(T > t) of Student's t with `dof` degrees of freedom (1 when `dof` is not positive).
/// The nested F statistic of `q` added parameters that lower the weighted sum of squares by
/// `drop` to `s1`, with `dof` residual degrees of freedom, both deflated by `defl` (1: none; the
/// autocorrelation's (1 - rho) / (1 + rho)), and its p-value. (0, 1) without degrees of freedom.
pub(super) fn nested_f(drop: f64, s1: f64, q: usize, dof: f64, defl: f64) -> (f64, f64) {
    let dof2 = dof * defl;
    if !(dof2 > 0.0) {
        return (0.0, 1.0);
    }
    let f = (drop / q as f64) / (s1 / dof) * defl;
    (f, f_sf(f, q as f64, dof2))
}

pub(super) fn t_sf(t: f64, dof: f64) -> f64 {
    if !t.is_finite() {
        return if t > 0.0 { 0.0 } else { 1.0 };
    }
    match StudentsT::new(0.0, 1.0, dof) {
        Ok(d) => d.sf(t).clamp(0.0, 1.0),
        Err(_) => 1.0,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distributions_match_known_values() {
        // F(3, 100) upper 5% point 2.696; F(1, 10) upper 1% point 10.04; t(inf) 1.645 -> 5%.
        assert!((f_sf(2.696, 3.0, 100.0) - 0.05).abs() < 1e-3);
        assert!((f_sf(10.04, 1.0, 10.0) - 0.01).abs() < 2e-4);
        assert!((t_sf(1.645, 1e6) - 0.05).abs() < 1e-3);
        assert!((t_sf(2.015, 5.0) - 0.05).abs() < 1e-3);
        assert_eq!(f_sf(0.0, 3.0, 10.0), 1.0);
        assert_eq!(f_sf(2.0, 0.0, 10.0), 1.0);
        assert_eq!(t_sf(f64::INFINITY, 5.0), 0.0);
        assert_eq!(t_sf(f64::NEG_INFINITY, 5.0), 1.0);
        assert_eq!(t_sf(1.0, 0.0), 1.0);
    }

    /// P-values of the hand-written Lanczos / incomplete-beta code that `statrs` replaced, over the
    /// range the rounds use (1 to 6 extra parameters, 5 to 5000 degrees of freedom, tails down to
    /// 1e-65): the decisions compare them with alpha / m, so they must agree to many digits.
    #[test]
    fn p_values_agree_with_the_former_hand_written_ones() {
        let f_table = [
            (0.5_f64, 1_f64, 5_f64, 5.110840804302808e-1),
            (2_f64, 1_f64, 5_f64, 2.1643722926968567e-1),
            (5_f64, 1_f64, 5_f64, 7.558681842161243e-2),
            (20_f64, 1_f64, 5_f64, 6.566271827563014e-3),
            (80_f64, 1_f64, 5_f64, 2.9114225193906064e-4),
            (0.5_f64, 3_f64, 40_f64, 6.844137766191427e-1),
            (2_f64, 3_f64, 40_f64, 1.294416979542816e-1),
            (5_f64, 3_f64, 40_f64, 4.877171443192418e-3),
            (20_f64, 3_f64, 40_f64, 4.44627274211772e-8),
            (80_f64, 3_f64, 40_f64, 5.98768875249735e-17),
            (0.5_f64, 6_f64, 400_f64, 8.083803039483823e-1),
            (2_f64, 6_f64, 400_f64, 6.464444779550269e-2),
            (5_f64, 6_f64, 400_f64, 5.896283412030664e-5),
            (20_f64, 6_f64, 400_f64, 1.8180403377458087e-20),
            (80_f64, 6_f64, 400_f64, 1.995719027653382e-65),
            (0.5_f64, 3_f64, 5000_f64, 6.822876389645351e-1),
            (2_f64, 3_f64, 5000_f64, 1.1175615558073662e-1),
            (5_f64, 3_f64, 5000_f64, 1.8346467549230632e-3),
            (20_f64, 3_f64, 5000_f64, 6.986698266895222e-13),
            (80_f64, 3_f64, 5000_f64, 1.51537887837345e-50),
            (0.5_f64, 1_f64, 12.5_f64, 4.9247263151915943e-1),
            (2_f64, 1_f64, 12.5_f64, 1.8172081336667611e-1),
            (5_f64, 1_f64, 12.5_f64, 4.428008789485829e-2),
            (20_f64, 1_f64, 12.5_f64, 6.909145990445101e-4),
            (80_f64, 1_f64, 12.5_f64, 8.690798489612345e-7),
        ];
        let t_table = [
            (-1_f64, 2_f64, 7.886751345948133e-1),
            (0.5_f64, 2_f64, 3.3333333333333304e-1),
            (1.645_f64, 2_f64, 1.2085198061245228e-1),
            (3_f64, 2_f64, 4.7732983133354626e-2),
            (10_f64, 2_f64, 4.926228511662854e-3),
            (-1_f64, 5_f64, 8.183912661754383e-1),
            (0.5_f64, 5_f64, 3.191494358204644e-1),
            (1.645_f64, 5_f64, 8.044469373342686e-2),
            (3_f64, 5_f64, 1.5049623948731276e-2),
            (10_f64, 5_f64, 8.547378787148176e-5),
            (-1_f64, 30_f64, 8.373456922869869e-1),
            (0.5_f64, 30_f64, 3.1036150244256283e-1),
            (1.645_f64, 30_f64, 5.520464247643919e-2),
            (3_f64, 30_f64, 2.694982032825985e-3),
            (10_f64, 30_f64, 2.2876257041148155e-11),
            (-1_f64, 1000000_f64, 8.41344625220537e-1),
            (0.5_f64, 1000000_f64, 3.085375936522023e-1),
            (1.645_f64, 1000000_f64, 4.9985062519683876e-2),
            (3_f64, 1000000_f64, 1.3499312712472959e-3),
            (10_f64, 1000000_f64, 7.639305386945562e-24),
        ];
        let mut worst: f64 = 0.0;
        for (f, d1, d2, p_old) in f_table {
            let p = f_sf(f, d1, d2);
            let rel = (p - p_old).abs() / p_old;
            worst = worst.max(rel);
        }
        for (t, dof, p_old) in t_table {
            let p = t_sf(t, dof);
            let rel = (p - p_old).abs() / p_old;
            worst = worst.max(rel);
        }
        eprintln!("largest relative difference of the p-values: {worst:.2e}");
        // Measured: 1.2e-12.
        assert!(worst < 4e-12, "{worst:e}");
    }
}
