//! Cholesky factorisation of small symmetric positive-definite matrices of a size fixed at compile
//! time (the normal equations of the fits, 4 to 9 parameters), with the solve and the inverse the
//! fits need. Plain arrays the compiler unrolls: several times faster at these sizes than the
//! generic routines of a linear-algebra crate, which is what a fit of a few hundred points spends a
//! noticeable share of its time in.
//!
//! Pure math: no I/O.

use nalgebra::{SMatrix, SVector};

/// The lower-triangular factor `L` of `A = L L^T`, and the reciprocals of its diagonal.
pub struct Cholesky<const N: usize> {
    l: [[f64; N]; N],
    inv_diag: [f64; N],
}

impl<const N: usize> Cholesky<N> {
    /// Factor `a` (its lower triangle is read). `None` unless every pivot is positive and finite,
    /// i.e. unless `a` is positive definite to working precision.
    pub fn new(a: &SMatrix<f64, N, N>) -> Option<Cholesky<N>> {
        let mut l = [[0.0f64; N]; N];
        let mut inv_diag = [0.0f64; N];
        for j in 0..N {
            let mut d = a[(j, j)];
            for k in 0..j {
                d -= l[j][k] * l[j][k];
            }
            if !(d > 0.0) || !d.is_finite() {
                return None;
            }
            let ljj = d.sqrt();
            l[j][j] = ljj;
            inv_diag[j] = 1.0 / ljj;
            for i in j + 1..N {
                let mut v = a[(i, j)];
                for k in 0..j {
                    v -= l[i][k] * l[j][k];
                }
                l[i][j] = v * inv_diag[j];
            }
        }
        Some(Cholesky { l, inv_diag })
    }

    /// `x` with `A x = b`.
    pub fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N> {
        let l = &self.l;
        // L y = b, then L^T x = y.
        let mut y = [0.0f64; N];
        for i in 0..N {
            let mut v = b[i];
            for k in 0..i {
                v -= l[i][k] * y[k];
            }
            y[i] = v * self.inv_diag[i];
        }
        let mut x = [0.0f64; N];
        for i in (0..N).rev() {
            let mut v = y[i];
            for k in i + 1..N {
                v -= l[k][i] * x[k];
            }
            x[i] = v * self.inv_diag[i];
        }
        SVector::<f64, N>::from_fn(|i, _| x[i])
    }

    /// `A^-1`, as `L^-T L^-1`.
    pub fn inverse(&self) -> SMatrix<f64, N, N> {
        let l = &self.l;
        // M = L^-1, lower triangular, column by column.
        let mut m = [[0.0f64; N]; N];
        for j in 0..N {
            m[j][j] = self.inv_diag[j];
            for i in j + 1..N {
                let mut v = 0.0;
                for k in j..i {
                    v -= l[i][k] * m[k][j];
                }
                m[i][j] = v * self.inv_diag[i];
            }
        }
        // (M^T M)_ab = sum over k >= max(a, b) of M_ka M_kb.
        let mut inv = SMatrix::<f64, N, N>::zeros();
        for a in 0..N {
            for b in a..N {
                let mut v = 0.0;
                for mk in m.iter().skip(b) {
                    v += mk[a] * mk[b];
                }
                inv[(a, b)] = v;
                inv[(b, a)] = v;
            }
        }
        inv
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_spd<const N: usize>(
        rng: &mut rand_chacha::ChaCha8Rng,
        spread: f64,
    ) -> SMatrix<f64, N, N> {
        let b = SMatrix::<f64, N, N>::from_fn(|_, _| rng.random_range(-1.0..1.0));
        let d = SMatrix::<f64, N, N>::from_diagonal(&SVector::<f64, N>::from_fn(|_, _| {
            spread.powf(rng.random_range(0.0..1.0))
        }));
        let m = b * d * b.transpose();
        (m + m.transpose()) * 0.5
    }

    /// Factor, solve and inverse agree with nalgebra's to rounding, for each size a fit uses.
    #[test]
    fn agrees_with_nalgebra() {
        fn check<const N: usize>(rng: &mut rand_chacha::ChaCha8Rng) {
            for case in 0..50 {
                let spread = [1.0, 1e3, 1e6][case % 3];
                let a = random_spd::<N>(rng, spread);
                let b = SVector::<f64, N>::from_fn(|_, _| rng.random_range(-1.0..1.0));
                let (ours, theirs) = (Cholesky::new(&a), a.cholesky());
                let (Some(ours), Some(theirs)) = (ours, theirs) else {
                    panic!("N {N} case {case}: factorisations disagree on definiteness");
                };
                // Relative to the conditioning: both are backward stable, neither exact.
                let cond = {
                    let e = nalgebra::DMatrix::<f64>::from_fn(N, N, |i, j| a[(i, j)])
                        .symmetric_eigenvalues();
                    e.max() / e.min()
                };
                let tol = 1e-14 * cond.max(1.0) * N as f64;
                let (x, y) = (ours.solve(&b), theirs.solve(&b));
                assert!((x - y).amax() <= tol * y.amax(), "N {N} case {case} solve");
                let (p, q) = (ours.inverse(), theirs.inverse());
                assert!(
                    (p - q).amax() <= tol * q.amax(),
                    "N {N} case {case} inverse"
                );
                assert!(((a * x) - b).amax() <= tol * b.amax() * 10.0);
            }
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        check::<4>(&mut rng);
        check::<6>(&mut rng);
        check::<9>(&mut rng);
    }

    /// Not positive definite, or not finite: no factor.
    #[test]
    fn refuses_what_is_not_positive_definite() {
        let mut a = SMatrix::<f64, 4, 4>::identity();
        a[(2, 2)] = 0.0;
        assert!(Cholesky::new(&a).is_none());
        a[(2, 2)] = -1.0;
        assert!(Cholesky::new(&a).is_none());
        a[(2, 2)] = f64::NAN;
        assert!(Cholesky::new(&a).is_none());
        a[(2, 2)] = f64::INFINITY;
        assert!(Cholesky::new(&a).is_none());
        let mut b = SMatrix::<f64, 4, 4>::identity();
        b[(3, 1)] = f64::NAN;
        b[(1, 3)] = f64::NAN;
        assert!(Cholesky::new(&b).is_none());
        assert!(Cholesky::new(&SMatrix::<f64, 4, 4>::identity()).is_some());
    }
}
