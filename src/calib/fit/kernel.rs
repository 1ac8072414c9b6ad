//! The hot loops of the norm fit: points in structure-of-arrays form padded to a multiple of
//! [`LANES`] (padding lanes carry weight 0), Jacobian columns written per point with J^T r summed as
//! they are written, normal equations as dot products of columns. Plain Rust with per-lane partial
//! sums, which the compiler vectorises for whatever CPU it targets.
//!
//! Pure math: no I/O.

use crate::calib::model::ModelKind;
use crate::types::Vec3;
use nalgebra::{Matrix3, SMatrix, SVector};

/// Points processed together; the padding of every column is a multiple of this.
pub(crate) const LANES: usize = 8;

/// Model kinds as const-generic tags, so each kind's per-point code has no branch in the loop.
pub(crate) const SPHERE: u8 = 0;
pub(crate) const DIAG6: u8 = 1;
pub(crate) const SYM9: u8 = 2;
pub(crate) const FULL12: u8 = 3;

/// The model a tag stands for.
pub const fn kind(tag: u8) -> ModelKind {
    match tag {
        SPHERE => ModelKind::Sphere,
        DIAG6 => ModelKind::Diag6,
        SYM9 => ModelKind::Sym9,
        _ => ModelKind::Full12,
    }
}

/// Points as three padded columns plus a weight column (1 for a point, 0 for padding).
#[derive(Debug, Clone)]
pub(crate) struct Soa {
    pub n: usize,
    pub padded: usize,
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub z: Vec<f64>,
    pub w: Vec<f64>,
}

impl Soa {
    /// `(p - centre) / scale` for each point; padding repeats the first point with weight 0 so
    /// nothing in the padding can be NaN.
    pub fn normalised(points: &[Vec3], centre: [f64; 3], scale: f64) -> Soa {
        let n = points.len();
        let padded = n.div_ceil(LANES).max(1) * LANES;
        let inv = 1.0 / scale;
        let mut s = Soa {
            n,
            padded,
            x: vec![0.0; padded],
            y: vec![0.0; padded],
            z: vec![0.0; padded],
            w: vec![0.0; padded],
        };
        for (i, p) in points.iter().enumerate() {
            s.x[i] = (p[0] - centre[0]) * inv;
            s.y[i] = (p[1] - centre[1]) * inv;
            s.z[i] = (p[2] - centre[2]) * inv;
            s.w[i] = 1.0;
        }
        let first = [0, 1, 2].map(|k| points.first().map_or(0.0, |p| (p[k] - centre[k]) * inv));
        for i in n..padded {
            s.x[i] = first[0];
            s.y[i] = first[1];
            s.z[i] = first[2];
            s.w[i] = 0.0;
        }
        s
    }

    /// Re-centre and re-scale in place: `(p - centre) / scale`.
    pub(crate) fn renormalise(&mut self, centre: [f64; 3], scale: f64) {
        let inv = 1.0 / scale;
        for (col, c) in [&mut self.x, &mut self.y, &mut self.z]
            .into_iter()
            .zip(centre)
        {
            for v in col.iter_mut() {
                *v = (*v - c) * inv;
            }
        }
    }
}

/// Gram matrix `cols^T cols` of the first `N` columns (each `padded` long, one after the other),
/// one dot product at a time with [`LANES`] partial sums. (The right-hand sides are accumulated
/// while the columns are written, so no product is spent on them.)
fn gram<const N: usize>(cols: &[f64], padded: usize) -> SMatrix<f64, N, N> {
    let col = |k: usize| &cols[k * padded..(k + 1) * padded];
    let mut m = SMatrix::<f64, N, N>::zeros();
    for a in 0..N {
        for b in a..N {
            let mut acc = [0.0f64; LANES];
            for (ca, cb) in col(a).chunks_exact(LANES).zip(col(b).chunks_exact(LANES)) {
                for l in 0..LANES {
                    acc[l] += ca[l] * cb[l];
                }
            }
            let v = lane_sum(&acc);
            m[(a, b)] = v;
            m[(b, a)] = v;
        }
    }
    m
}

/// Per-lane sums, added up at the end of a pass.
#[inline(always)]
fn lane_sum(acc: &[f64; LANES]) -> f64 {
    ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
}

/// Gradients of the residuals `r_i = w_i (|A (x_i - p)| - 1)` at `params` as Jacobian columns;
/// returns `(sum r_i^2, J^T r)`.
fn norm_columns<const K: u8, const N: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    cols: &mut [f64],
) -> (f64, SVector<f64, N>) {
    let p = params;
    let a: Matrix3<f64> = crate::calib::model::a_from_params(kind(K), &p.as_slice()[3..]);
    let (c0, c1, c2) = (p[0], p[1], p[2]);
    let (a00, a01, a02, a10, a11, a12, a20, a21, a22) = (
        a[(0, 0)],
        a[(0, 1)],
        a[(0, 2)],
        a[(1, 0)],
        a[(1, 1)],
        a[(1, 2)],
        a[(2, 0)],
        a[(2, 1)],
        a[(2, 2)],
    );
    let padded = pts.padded;
    let cols = &mut cols[..N * padded];
    let mut ssr_acc = [0.0f64; LANES];
    let mut jtr_acc = [[0.0f64; LANES]; N];
    for base in (0..padded).step_by(LANES) {
        let mut g = [[0.0f64; LANES]; N];
        let mut rr = [0.0f64; LANES];
        let xs = &pts.x[base..base + LANES];
        let ys = &pts.y[base..base + LANES];
        let zs = &pts.z[base..base + LANES];
        let ws = &pts.w[base..base + LANES];
        for l in 0..LANES {
            let (vx, vy, vz) = (xs[l] - c0, ys[l] - c1, zs[l] - c2);
            let ux = a00 * vx + a01 * vy + a02 * vz;
            let uy = a10 * vx + a11 * vy + a12 * vz;
            let uz = a20 * vx + a21 * vy + a22 * vz;
            let n = (ux * ux + uy * uy + uz * uz).sqrt().max(1e-300);
            let w = ws[l];
            let inv = w / n;
            rr[l] = w * (n - 1.0);
            // d r / d p = -(A^T u) / n
            g[0][l] = -(a00 * ux + a10 * uy + a20 * uz) * inv;
            g[1][l] = -(a01 * ux + a11 * uy + a21 * uz) * inv;
            g[2][l] = -(a02 * ux + a12 * uy + a22 * uz) * inv;
            // d r / d A_jk = u_j v_k / n
            match K {
                SPHERE => g[3][l] = (ux * vx + uy * vy + uz * vz) * inv,
                DIAG6 => {
                    g[3][l] = ux * vx * inv;
                    g[4][l] = uy * vy * inv;
                    g[5][l] = uz * vz * inv;
                }
                SYM9 => {
                    g[3][l] = ux * vx * inv;
                    g[4][l] = uy * vy * inv;
                    g[5][l] = uz * vz * inv;
                    g[6][l] = (ux * vy + uy * vx) * inv;
                    g[7][l] = (ux * vz + uz * vx) * inv;
                    g[8][l] = (uy * vz + uz * vy) * inv;
                }
                _ => {
                    g[3][l] = ux * vx * inv;
                    g[4][l] = uy * vy * inv;
                    g[5][l] = uz * vz * inv;
                    g[6][l] = ux * vy * inv;
                    g[7][l] = ux * vz * inv;
                    g[8][l] = uy * vz * inv;
                }
            }
        }
        for l in 0..LANES {
            ssr_acc[l] += rr[l] * rr[l];
        }
        for (k, gk) in g.iter().enumerate() {
            for l in 0..LANES {
                jtr_acc[k][l] += gk[l] * rr[l];
            }
            cols[k * padded + base..k * padded + base + LANES].copy_from_slice(gk);
        }
    }
    (
        lane_sum(&ssr_acc),
        SVector::<f64, N>::from_fn(|k, _| lane_sum(&jtr_acc[k])),
    )
}

/// Design columns of the linear sphere fit |x|^2 = 2 c.x + k (columns 2x, 2y, 2z, 1); returns
/// `(b.b, A^T b)` for the right-hand side `b = |x|^2`.
fn sphere_design(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 4>) {
    design_columns::<4>(pts, cols, |x, y, z, w| {
        (
            [2.0 * x * w, 2.0 * y * w, 2.0 * z * w, w],
            (x * x + y * y + z * z) * w,
        )
    })
}

/// Design columns of the algebraic ellipsoid fit x^T Q x + 2 g.x = 1; returns `(b.b, A^T b)` for
/// the right-hand side `b = 1` (the weight: 0 on padding).
fn ellipsoid_design(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 9>) {
    design_columns::<9>(pts, cols, |x, y, z, w| {
        let (xw, yw, zw) = (x * w, y * w, z * w);
        (
            [
                x * xw,
                y * yw,
                z * zw,
                2.0 * x * yw,
                2.0 * x * zw,
                2.0 * y * zw,
                2.0 * xw,
                2.0 * yw,
                2.0 * zw,
            ],
            w,
        )
    })
}

/// Writes the `K` design columns `row(x, y, z, w).0` of a linear least-squares problem and returns
/// `(b.b, A^T b)` for its right-hand side `row(..).1`, summed lane by lane so the loop vectorises.
#[inline(always)]
fn design_columns<const K: usize>(
    pts: &Soa,
    cols: &mut [f64],
    row: impl Fn(f64, f64, f64, f64) -> ([f64; K], f64),
) -> (f64, SVector<f64, K>) {
    let p = pts.padded;
    let (xs, ys, zs, ws) = (&pts.x[..p], &pts.y[..p], &pts.z[..p], &pts.w[..p]);
    let columns: [&mut [f64]; K] = {
        let mut rest = &mut cols[..K * p];
        std::array::from_fn(|_| {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(p);
            rest = tail;
            head
        })
    };
    let mut bb = [0.0f64; LANES];
    let mut ab = [[0.0f64; LANES]; K];
    for base in (0..p).step_by(LANES) {
        for l in 0..LANES {
            let i = base + l;
            let (ck, b) = row(xs[i], ys[i], zs[i], ws[i]);
            bb[l] += b * b;
            for k in 0..K {
                columns[k][i] = ck[k];
                ab[k][l] += ck[k] * b;
            }
        }
    }
    (
        lane_sum(&bb),
        SVector::<f64, K>::from_fn(|k, _| lane_sum(&ab[k])),
    )
}

/// Scratch space for one fit: up to nine Jacobian or design columns, owned by the caller (a
/// [`crate::calib::fit::NormFitter`] keeps one for all the models it fits).
pub(crate) struct Scratch {
    pub cols: Vec<f64>,
}

impl Scratch {
    /// Columns for `padded` points; their contents are unspecified until written.
    pub fn new(padded: usize) -> Scratch {
        Scratch {
            cols: vec![0.0; 9 * padded],
        }
    }
}

/// Sum of squared residuals, J^T J and J^T r of the norm residual at `params`; J^T J only when
/// `with_jtj` (without it, a pass costs the residuals and gradients alone).
pub(crate) fn norm_normal_equations<const K: u8, const N: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    scratch: &mut Scratch,
    with_jtj: bool,
) -> (f64, Option<SMatrix<f64, N, N>>, SVector<f64, N>) {
    let (ssr, jtr) = norm_columns::<K, N>(params, pts, &mut scratch.cols);
    let jtj = with_jtj.then(|| gram::<N>(&scratch.cols, pts.padded));
    (ssr, jtj, jtr)
}

/// Normal equations of the linear sphere fit on `pts`: `(b.b, A^T A, A^T b)`.
pub(crate) fn sphere_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 4, 4>, SVector<f64, 4>) {
    let (bb, ab) = sphere_design(pts, &mut scratch.cols);
    (bb, gram::<4>(&scratch.cols, pts.padded), ab)
}

/// Normal equations of the algebraic ellipsoid fit on `pts`: `(b.b, A^T A, A^T b)`.
pub(crate) fn ellipsoid_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 9, 9>, SVector<f64, 9>) {
    let (bb, ab) = ellipsoid_design(pts, &mut scratch.cols);
    (bb, gram::<9>(&scratch.cols, pts.padded), ab)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_points(n: usize, seed: u64) -> Vec<Vec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                [
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                ]
            })
            .collect()
    }

    /// The Gram product equals the sum over the points of the outer products of their design rows,
    /// and padding carries no weight: the right-hand side (1 per point) sums to the number of
    /// points, and its products with the columns are their sums over the points.
    #[test]
    fn gram_sums_the_points_and_ignores_the_padding() {
        for n in [1usize, 7, 8, 9, 300, 301] {
            let pts = random_points(n, n as u64);
            let soa = Soa::normalised(&pts, [0.1, -0.2, 0.3], 1.5);
            let mut s = Scratch::new(soa.padded);
            let (bb, ata, ab) = ellipsoid_normal_equations(&soa, &mut s);
            let mut reference = SMatrix::<f64, 9, 9>::zeros();
            for i in 0..n {
                let (x, y, z) = (soa.x[i], soa.y[i], soa.z[i]);
                let d = SVector::<f64, 9>::from_column_slice(&[
                    x * x,
                    y * y,
                    z * z,
                    2.0 * x * y,
                    2.0 * x * z,
                    2.0 * y * z,
                    2.0 * x,
                    2.0 * y,
                    2.0 * z,
                ]);
                reference += d * d.transpose();
            }
            let err = (ata - reference).amax();
            assert!(err <= 1e-12 * (1.0 + reference.amax()), "n {n}: {err:e}");
            assert_eq!(bb, n as f64);
            let xs: f64 = soa.x[..n].iter().map(|x| 2.0 * x).sum();
            assert!((ab[6] - xs).abs() <= 1e-12 * (1.0 + xs.abs()), "n {n}");
        }
    }

    /// A pass without J^T J gives the same sums as one with it, and no matrix; points far from the
    /// others and one at the model's centre give finite sums.
    #[test]
    fn pass_without_jtj_gives_the_same_sums() {
        let params = [0.1, -0.2, 0.05, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05];
        let pv = SVector::<f64, 9>::from_column_slice(&params);
        for n in [1usize, 7, 8, 9, 300, 301] {
            let mut pts = random_points(n, 120 + n as u64);
            if n >= 8 {
                pts[3] = [1e20, -3e19, 2e18];
                pts[5] = [1e-20, 0.0, 0.0];
                pts[6] = [0.25, -0.5, 0.375];
            }
            let soa = Soa::normalised(&pts, [0.1, -0.2, 0.3], 1.5);
            let (mut s1, mut s2) = (Scratch::new(soa.padded), Scratch::new(soa.padded));
            let (ssr1, none, jtr1) = norm_normal_equations::<SYM9, 9>(&pv, &soa, &mut s1, false);
            let (ssr2, jtj, jtr2) = norm_normal_equations::<SYM9, 9>(&pv, &soa, &mut s2, true);
            assert!(none.is_none() && jtj.is_some(), "n {n}");
            assert!(ssr1 == ssr2 && jtr1 == jtr2, "n {n}");
            assert!(
                ssr1.is_finite() && jtr1.iter().all(|v| v.is_finite()),
                "n {n}"
            );
        }
    }

    /// The kernel's residuals and gradients against the per-point reference in `model` (whose
    /// gradients are checked against numerical derivatives there).
    fn check_against_reference<const K: u8, const N: usize>(params: &[f64]) {
        let pts = random_points(37, 5);
        let soa = Soa::normalised(&pts, [0.0; 3], 1.0);
        let mut s = Scratch::new(soa.padded);
        let p = SVector::<f64, N>::from_column_slice(params);
        let (ssr, jtj, jtr) = norm_normal_equations::<K, N>(&p, &soa, &mut s, true);
        let jtj = jtj.expect("asked for J^T J");
        let a = crate::calib::model::a_from_params(kind(K), &params[3..]);
        let (mut ssr2, mut jtj2, mut jtr2) = (
            0.0,
            SMatrix::<f64, N, N>::zeros(),
            SVector::<f64, N>::zeros(),
        );
        for x in &pts {
            let mut g = [0.0; 9];
            let r = crate::calib::model::norm_residual_grad_with(
                kind(K),
                &a,
                &a.transpose(),
                params,
                x,
                &mut g,
            );
            let g = SVector::<f64, N>::from_column_slice(&g[..N]);
            ssr2 += r * r;
            jtr2 += g * r;
            jtj2 += g * g.transpose();
        }
        let what = format!("{:?}", kind(K));
        assert!((ssr - ssr2).abs() < 1e-10 * ssr2, "{what}");
        assert!((jtr - jtr2).norm() < 1e-10 * (1.0 + jtr2.norm()), "{what}");
        assert!((jtj - jtj2).norm() < 1e-10 * jtj2.norm(), "{what}");
    }

    #[test]
    fn normal_equations_match_the_per_point_residual() {
        check_against_reference::<SPHERE, 4>(&[0.1, -0.2, 0.05, 1.1]);
        check_against_reference::<DIAG6, 6>(&[0.1, -0.2, 0.05, 1.1, 0.9, 1.05]);
        let nine = [0.1, -0.2, 0.05, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05];
        check_against_reference::<SYM9, 9>(&nine);
        check_against_reference::<FULL12, 9>(&nine);
    }
}
