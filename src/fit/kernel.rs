//! The hot loops of the norm fit, laid out for SIMD: points in structure-of-arrays form padded to a
//! multiple of [`LANES`] (padding lanes carry weight 0), Jacobian columns written per point, normal
//! equations as blocked dot products of columns. Compiled twice, for the baseline target and for
//! AVX2+FMA, and picked at run time; both give the same result to rounding.
//!
//! Pure math: no I/O.

use crate::model::ModelKind;
use crate::types::Vec3;
use nalgebra::{Matrix3, SMatrix, SVector};

/// Points processed together; the padding of every column is a multiple of this.
pub const LANES: usize = 8;

/// Model kinds as const-generic tags, so each kind's per-point code has no branch in the loop.
pub const SPHERE: u8 = 0;
pub const DIAG6: u8 = 1;
pub const SYM9: u8 = 2;
pub const FULL12: u8 = 3;

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
pub struct Soa {
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
        for i in n..padded {
            s.x[i] = s.x[0];
            s.y[i] = s.y[0];
            s.z[i] = s.z[0];
        }
        s
    }

    /// Re-centre and re-scale in place: `(p - centre) / scale`.
    pub fn renormalise(&mut self, centre: [f64; 3], scale: f64) {
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

/// Columns per side of a tile in the AVX2 Gram product: 3 x 3 accumulators plus 6 loaded chunks
/// fit in the 16 vector registers.
const TILE: usize = 3;

/// Gram matrix of `m` columns (each `padded` long, one after the other): `out[a][b] = cols_a .
/// cols_b` for b >= a. Portable version: one dot product at a time with [`LANES`] partial sums.
#[inline(always)]
fn gram_portable<const M: usize>(cols: &[f64], padded: usize) -> [[f64; M]; M] {
    let col = |k: usize| &cols[k * padded..(k + 1) * padded];
    let mut out = [[0.0f64; M]; M];
    for a in 0..M {
        for b in a..M {
            let mut acc = [0.0f64; LANES];
            for (ca, cb) in col(a).chunks_exact(LANES).zip(col(b).chunks_exact(LANES)) {
                for l in 0..LANES {
                    acc[l] += ca[l] * cb[l];
                }
            }
            out[a][b] = acc.iter().sum();
        }
    }
    out
}

/// As [`gram_portable`], with AVX2 and FMA by 3 x 3 tiles of columns, so each loaded chunk of four
/// feeds three multiply-adds. `M` must be a multiple of [`TILE`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn gram_avx2<const M: usize>(cols: &[f64], padded: usize) -> [[f64; M]; M] {
    use std::arch::x86_64::*;
    assert!(M % TILE == 0 && padded % 4 == 0 && cols.len() >= M * padded);
    let mut out = [[0.0f64; M]; M];
    let ptr = cols.as_ptr();
    for ta in (0..M).step_by(TILE) {
        for tb in (ta..M).step_by(TILE) {
            let mut acc = [[_mm256_setzero_pd(); TILE]; TILE];
            let mut base = 0;
            while base < padded {
                // SAFETY: (ta + i) * padded + base + 4 <= M * padded <= cols.len(), asserted above.
                let load = |k: usize| unsafe { _mm256_loadu_pd(ptr.add(k * padded + base)) };
                let av = [load(ta), load(ta + 1), load(ta + 2)];
                let bv = [load(tb), load(tb + 1), load(tb + 2)];
                for i in 0..TILE {
                    for j in 0..TILE {
                        acc[i][j] = _mm256_fmadd_pd(av[i], bv[j], acc[i][j]);
                    }
                }
                base += 4;
            }
            for i in 0..TILE {
                for j in 0..TILE {
                    let mut lanes = [0.0f64; 4];
                    // SAFETY: `lanes` holds four f64.
                    unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), acc[i][j]) };
                    out[ta + i][tb + j] = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
                }
            }
        }
    }
    out
}

/// Gram matrix of `M` columns, by the AVX2 tiles when the CPU has them.
fn gram_tiled<const M: usize>(cols: &[f64], padded: usize) -> [[f64; M]; M] {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU was just checked for the features `gram_avx2` was compiled for.
        return unsafe { gram_avx2::<M>(cols, padded) };
    }
    gram_portable::<M>(cols, padded)
}

/// Normal equations of the first `N` columns against column `N` (the right-hand side):
/// returns (rhs.rhs, cols^T cols, cols^T rhs). `M` is `N + 1` rounded up to a multiple of [`TILE`];
/// columns past `N` must be zero.
fn gram<const N: usize, const M: usize>(
    cols: &[f64],
    padded: usize,
) -> (f64, SMatrix<f64, N, N>, SVector<f64, N>) {
    let g = gram_tiled::<M>(cols, padded);
    let mut m = SMatrix::<f64, N, N>::zeros();
    let mut v = SVector::<f64, N>::zeros();
    for a in 0..N {
        v[a] = g[a][N];
        for b in a..N {
            m[(a, b)] = g[a][b];
            m[(b, a)] = g[a][b];
        }
    }
    (g[N][N], m, v)
}

/// Residuals `r_i = w_i (|A (x_i - p)| - 1)` and their gradients (Jacobian columns) at `params`.
#[inline(always)]
fn norm_columns_body<const K: u8, const N: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    cols: &mut [f64],
) {
    let p = params;
    let a: Matrix3<f64> = crate::model::a_from_params(kind(K), &p.as_slice()[3..]);
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
    let cols = &mut cols[..(N + 1) * padded];
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
        cols[N * padded + base..N * padded + base + LANES].copy_from_slice(&rr);
        for (k, gk) in g.iter().enumerate() {
            cols[k * padded + base..k * padded + base + LANES].copy_from_slice(gk);
        }
    }
}

/// Design columns of the linear sphere fit |x|^2 = 2 c.x + k (columns 2x, 2y, 2z, 1; rhs |x|^2).
#[inline(always)]
fn sphere_design_body(pts: &Soa, cols: &mut [f64]) {
    let p = pts.padded;
    for i in 0..p {
        let (x, y, z, w) = (pts.x[i], pts.y[i], pts.z[i], pts.w[i]);
        cols[i] = 2.0 * x * w;
        cols[p + i] = 2.0 * y * w;
        cols[2 * p + i] = 2.0 * z * w;
        cols[3 * p + i] = w;
        cols[4 * p + i] = (x * x + y * y + z * z) * w;
    }
}

/// Design columns of the algebraic ellipsoid fit x^T Q x + 2 g.x = 1.
#[inline(always)]
fn ellipsoid_design_body(pts: &Soa, cols: &mut [f64]) {
    let p = pts.padded;
    for i in 0..p {
        let (x, y, z, w) = (pts.x[i], pts.y[i], pts.z[i], pts.w[i]);
        cols[i] = x * x * w;
        cols[p + i] = y * y * w;
        cols[2 * p + i] = z * z * w;
        cols[3 * p + i] = 2.0 * x * y * w;
        cols[4 * p + i] = 2.0 * x * z * w;
        cols[5 * p + i] = 2.0 * y * z * w;
        cols[6 * p + i] = 2.0 * x * w;
        cols[7 * p + i] = 2.0 * y * w;
        cols[8 * p + i] = 2.0 * z * w;
        cols[9 * p + i] = w;
    }
}

/// One entry point per loop, dispatched to the AVX2+FMA build when the CPU has it.
macro_rules! dispatch {
    ($(#[$doc:meta])* fn $name:ident<$($g:ident : $gt:ty),*>($($arg:ident : $ty:ty),*) -> $ret:ty = $body:ident;) => {
        $(#[$doc])*
        pub fn $name<$(const $g: $gt),*>($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn fast<$(const $g: $gt),*>($($arg: $ty),*) -> $ret {
                    $body::<$($g),*>($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU was just checked for the features `fast` was compiled for.
                    return unsafe { fast::<$($g),*>($($arg),*) };
                }
            }
            $body::<$($g),*>($($arg),*)
        }
    };
}

dispatch! {
    /// See [`norm_columns_body`].
    fn norm_columns<K: u8, N: usize>(params: &SVector<f64, N>, pts: &Soa, cols: &mut [f64]) -> () = norm_columns_body;
}

dispatch! {
    /// See [`sphere_design_body`].
    fn sphere_design<>(pts: &Soa, cols: &mut [f64]) -> () = sphere_design_body;
}

dispatch! {
    /// See [`ellipsoid_design_body`].
    fn ellipsoid_design<>(pts: &Soa, cols: &mut [f64]) -> () = ellipsoid_design_body;
}

/// Scratch space for one fit: up to nine Jacobian or design columns, the residual or right-hand
/// side after them, and zero columns up to a whole tile (12 columns in all).
pub struct Scratch {
    pub cols: Vec<f64>,
}

impl Scratch {
    pub fn new(padded: usize) -> Scratch {
        Scratch {
            cols: vec![0.0; 12 * padded],
        }
    }

    /// Zero the columns from `from` on (left over from a wider product).
    pub fn clear_from(&mut self, from: usize, padded: usize) {
        self.cols[from * padded..].fill(0.0);
    }
}

/// Sum of squared residuals, J^T J and J^T r of the norm residual at `params`.
pub fn norm_normal_equations<const K: u8, const N: usize, const M: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, N, N>, SVector<f64, N>) {
    norm_columns::<K, N>(params, pts, &mut scratch.cols);
    gram::<N, M>(&scratch.cols, pts.padded)
}

/// Normal equations of the linear sphere fit on `pts`.
pub fn sphere_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 4, 4>, SVector<f64, 4>) {
    scratch.clear_from(5, pts.padded);
    sphere_design(pts, &mut scratch.cols);
    gram::<4, 6>(&scratch.cols, pts.padded)
}

/// Normal equations of the algebraic ellipsoid fit on `pts`.
pub fn ellipsoid_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 9, 9>, SVector<f64, 9>) {
    scratch.clear_from(10, pts.padded);
    ellipsoid_design(pts, &mut scratch.cols);
    gram::<9, 12>(&scratch.cols, pts.padded)
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

    #[test]
    fn avx2_gram_equals_portable_gram() {
        for n in [1usize, 7, 8, 9, 300, 301] {
            let soa = Soa::normalised(&random_points(n, n as u64), [0.1, -0.2, 0.3], 1.5);
            let mut s = Scratch::new(soa.padded);
            s.clear_from(10, soa.padded);
            ellipsoid_design(&soa, &mut s.cols);
            let a = gram_portable::<12>(&s.cols, soa.padded);
            let b = gram_tiled::<12>(&s.cols, soa.padded);
            for i in 0..12 {
                for j in i..12 {
                    let tol = 1e-12 * (1.0 + a[i][j].abs());
                    assert!(
                        (a[i][j] - b[i][j]).abs() <= tol,
                        "n {n} ({i},{j}): {} vs {}",
                        a[i][j],
                        b[i][j]
                    );
                }
            }
            // Padding carries no weight: the constant column sums to the number of points.
            assert_eq!(a[9][9], n as f64);
        }
    }

    /// The kernel's residuals and gradients against the per-point reference in `model` (whose
    /// gradients are checked against numerical derivatives there).
    fn check_against_reference<const K: u8, const N: usize, const M: usize>(params: &[f64]) {
        let pts = random_points(37, 5);
        let soa = Soa::normalised(&pts, [0.0; 3], 1.0);
        let mut s = Scratch::new(soa.padded);
        s.clear_from(N + 1, soa.padded);
        let p = SVector::<f64, N>::from_column_slice(params);
        let (ssr, jtj, jtr) = norm_normal_equations::<K, N, M>(&p, &soa, &mut s);
        let a = crate::model::a_from_params(kind(K), &params[3..]);
        let (mut ssr2, mut jtj2, mut jtr2) = (
            0.0,
            SMatrix::<f64, N, N>::zeros(),
            SVector::<f64, N>::zeros(),
        );
        for x in &pts {
            let mut g = [0.0; 9];
            let r = crate::model::norm_residual_grad_with(
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
        check_against_reference::<SPHERE, 4, 6>(&[0.1, -0.2, 0.05, 1.1]);
        check_against_reference::<DIAG6, 6, 9>(&[0.1, -0.2, 0.05, 1.1, 0.9, 1.05]);
        let nine = [0.1, -0.2, 0.05, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05];
        check_against_reference::<SYM9, 9, 12>(&nine);
        check_against_reference::<FULL12, 9, 12>(&nine);
    }
}
