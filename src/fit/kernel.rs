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

thread_local! {
    /// Column buffers of finished fits, kept for the next fit on the same thread (a refit loop
    /// fits again and again): no allocation and no zeroing per fit. A handful at most.
    static POOL: std::cell::RefCell<Vec<Vec<f64>>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// A buffer of `len` values from the pool, or a new one. Its contents are unspecified: every user
/// writes what it reads.
fn take_buffer(len: usize) -> Vec<f64> {
    // The shortest pooled buffer that is long enough: shortening costs nothing, lengthening zeroes.
    let pooled = POOL.with(|p| {
        let mut p = p.borrow_mut();
        let best = (0..p.len())
            .filter(|&i| p[i].len() >= len)
            .min_by_key(|&i| p[i].len());
        best.map(|i| p.swap_remove(i))
    });
    match pooled {
        Some(mut v) => {
            v.truncate(len);
            v
        }
        None => vec![0.0; len],
    }
}

fn give_buffer(v: Vec<f64>) {
    // At most 8 buffers of at most 1 MB each are kept per thread (one fit of up to 14 000
    // points uses five): a few MB at worst, held by the threads that fit.
    if v.capacity() > 0 && v.capacity() <= 1 << 17 {
        POOL.with(|p| {
            let mut p = p.borrow_mut();
            if p.len() < 8 {
                p.push(v);
            }
        });
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
            x: take_buffer(padded),
            y: take_buffer(padded),
            z: take_buffer(padded),
            w: take_buffer(padded),
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

impl Drop for Soa {
    fn drop(&mut self) {
        for v in [&mut self.x, &mut self.y, &mut self.z, &mut self.w] {
            give_buffer(std::mem::take(v));
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
            // SAFETY: (ta + i) * padded + base + 4 <= M * padded <= cols.len(), asserted above.
            let load =
                |k: usize, base: usize| unsafe { _mm256_loadu_pd(ptr.add(k * padded + base)) };
            if ta == tb {
                // A tile on the diagonal: three columns against themselves, upper triangle only.
                while base < padded {
                    let av = [load(ta, base), load(ta + 1, base), load(ta + 2, base)];
                    for i in 0..TILE {
                        for j in i..TILE {
                            acc[i][j] = _mm256_fmadd_pd(av[i], av[j], acc[i][j]);
                        }
                    }
                    base += 4;
                }
            } else {
                while base < padded {
                    let av = [load(ta, base), load(ta + 1, base), load(ta + 2, base)];
                    let bv = [load(tb, base), load(tb + 1, base), load(tb + 2, base)];
                    for i in 0..TILE {
                        for j in 0..TILE {
                            acc[i][j] = _mm256_fmadd_pd(av[i], bv[j], acc[i][j]);
                        }
                    }
                    base += 4;
                }
            }
            for i in 0..TILE {
                for j in 0..TILE {
                    if ta == tb && j < i {
                        continue;
                    }
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

/// Gram matrix `cols^T cols` of the first `N` columns. `M` is `N` rounded up to a multiple of
/// [`TILE`]; columns past `N` must be zero. (The right-hand sides are accumulated while the columns
/// are written, so no tile is spent on them.)
fn gram<const N: usize, const M: usize>(cols: &[f64], padded: usize) -> SMatrix<f64, N, N> {
    let g = gram_tiled::<M>(cols, padded);
    let mut m = SMatrix::<f64, N, N>::zeros();
    for a in 0..N {
        for b in a..N {
            m[(a, b)] = g[a][b];
            m[(b, a)] = g[a][b];
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
#[inline(always)]
fn norm_columns_body<const K: u8, const N: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    cols: &mut [f64],
) -> (f64, SVector<f64, N>) {
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
#[inline(always)]
fn sphere_design_body(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 4>) {
    design_columns::<4>(pts, cols, |x, y, z, w| {
        (
            [2.0 * x * w, 2.0 * y * w, 2.0 * z * w, w],
            (x * x + y * y + z * z) * w,
        )
    })
}

/// Design columns of the algebraic ellipsoid fit x^T Q x + 2 g.x = 1; returns `(b.b, A^T b)` for
/// the right-hand side `b = 1` (the weight: 0 on padding).
#[inline(always)]
fn ellipsoid_design_body(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 9>) {
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
    fn norm_columns<K: u8, N: usize>(params: &SVector<f64, N>, pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, N>) = norm_columns_body;
}

dispatch! {
    /// See [`sphere_design_body`].
    fn sphere_design<>(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 4>) = sphere_design_body;
}

dispatch! {
    /// See [`ellipsoid_design_body`].
    fn ellipsoid_design<>(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 9>) = ellipsoid_design_body;
}

/// Scratch space for one fit: up to nine Jacobian or design columns and zero columns up to a whole
/// tile.
pub struct Scratch {
    pub cols: Vec<f64>,
}

impl Scratch {
    /// Columns for `padded` points; their contents are unspecified until written.
    pub fn new(padded: usize) -> Scratch {
        Scratch {
            cols: take_buffer(9 * padded),
        }
    }

    /// Zero the columns `from..to` (the ones a product reads past those it writes).
    pub fn clear(&mut self, from: usize, to: usize, padded: usize) {
        self.cols[from * padded..to * padded].fill(0.0);
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        give_buffer(std::mem::take(&mut self.cols));
    }
}

/// [`norm_columns_body`] for `sym9` (the model refits use most), in AVX2 and FMA four points at a
/// time; `params` are the nine `sym9` parameters. Returns `(sum r^2, J^T r)`; writes the columns
/// only when `STORE` (a pass that needs no J^T J skips the stores).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn sym9_columns_avx2<const STORE: bool>(
    params: &[f64],
    pts: &Soa,
    cols: &mut [f64],
) -> (f64, [f64; 9]) {
    use std::arch::x86_64::*;
    let p = pts.padded;
    assert!(params.len() == 9 && p % 4 == 0 && cols.len() >= 9 * p);
    assert!(pts.x.len() >= p && pts.y.len() >= p && pts.z.len() >= p && pts.w.len() >= p);
    let a = crate::model::a_from_params(ModelKind::Sym9, &params[3..]);
    let bc = _mm256_set1_pd;
    let m = [0, 1, 2].map(|i| [0, 1, 2].map(|j| bc(a[(i, j)])));
    let neg = [0, 1, 2].map(|i| [0, 1, 2].map(|j| bc(-a[(i, j)])));
    let (c0, c1, c2) = (bc(params[0]), bc(params[1]), bc(params[2]));
    let (one, tiny) = (bc(1.0), bc(1e-300));
    let out = cols.as_mut_ptr();
    let mut jtr = [_mm256_setzero_pd(); 9];
    let mut ssr = _mm256_setzero_pd();
    let mut i = 0;
    while i < p {
        // SAFETY: i + 4 <= p <= the length of every column read and of each of the nine column
        // slots written (asserted above).
        unsafe {
            let vx = _mm256_sub_pd(_mm256_loadu_pd(pts.x.as_ptr().add(i)), c0);
            let vy = _mm256_sub_pd(_mm256_loadu_pd(pts.y.as_ptr().add(i)), c1);
            let vz = _mm256_sub_pd(_mm256_loadu_pd(pts.z.as_ptr().add(i)), c2);
            let w = _mm256_loadu_pd(pts.w.as_ptr().add(i));
            let row = |r: &[__m256d; 3], a: __m256d, b: __m256d, c: __m256d| {
                _mm256_fmadd_pd(r[0], a, _mm256_fmadd_pd(r[1], b, _mm256_mul_pd(r[2], c)))
            };
            // u = A v
            let ux = row(&m[0], vx, vy, vz);
            let uy = row(&m[1], vx, vy, vz);
            let uz = row(&m[2], vx, vy, vz);
            let n2 = _mm256_fmadd_pd(ux, ux, _mm256_fmadd_pd(uy, uy, _mm256_mul_pd(uz, uz)));
            let n = _mm256_max_pd(_mm256_sqrt_pd(n2), tiny);
            let inv = _mm256_div_pd(w, n);
            let r = _mm256_mul_pd(w, _mm256_sub_pd(n, one));
            // e = w u / n: then d r / d p = -(A^T e) = (-A) e (A symmetric: its columns are its
            // rows) and d r / d A_jk = e_j v_k, symmetric pairs together.
            let (ex, ey, ez) = (
                _mm256_mul_pd(ux, inv),
                _mm256_mul_pd(uy, inv),
                _mm256_mul_pd(uz, inv),
            );
            let g = [
                row(&neg[0], ex, ey, ez),
                row(&neg[1], ex, ey, ez),
                row(&neg[2], ex, ey, ez),
                _mm256_mul_pd(ex, vx),
                _mm256_mul_pd(ey, vy),
                _mm256_mul_pd(ez, vz),
                _mm256_fmadd_pd(ex, vy, _mm256_mul_pd(ey, vx)),
                _mm256_fmadd_pd(ex, vz, _mm256_mul_pd(ez, vx)),
                _mm256_fmadd_pd(ey, vz, _mm256_mul_pd(ez, vy)),
            ];
            for k in 0..9 {
                if STORE {
                    _mm256_storeu_pd(out.add(k * p + i), g[k]);
                }
                jtr[k] = _mm256_fmadd_pd(g[k], r, jtr[k]);
            }
            ssr = _mm256_fmadd_pd(r, r, ssr);
        }
        i += 4;
    }
    (hsum(ssr), jtr.map(|v| hsum(v)))
}

/// Sum of squared residuals, J^T J and J^T r of the norm residual at `params`; J^T J only when
/// `with_jtj` (without it, a pass costs the residuals and gradients alone). `M` is `N` rounded up to
/// a multiple of 3, and the scratch columns from `N` to `M` must be zero ([`Scratch::clear`]).
pub fn norm_normal_equations<const K: u8, const N: usize, const M: usize>(
    params: &SVector<f64, N>,
    pts: &Soa,
    scratch: &mut Scratch,
    with_jtj: bool,
) -> (f64, Option<SMatrix<f64, N, N>>, SVector<f64, N>) {
    #[cfg(target_arch = "x86_64")]
    if K == SYM9
        && N == 9
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
    {
        let (p, cols) = (params.as_slice(), &mut scratch.cols);
        // SAFETY: the CPU was just checked for the features the function was compiled for.
        let (ssr, jtr) = unsafe {
            if with_jtj {
                sym9_columns_avx2::<true>(p, pts, cols)
            } else {
                sym9_columns_avx2::<false>(p, pts, cols)
            }
        };
        let jtr = SVector::<f64, N>::from_fn(|k, _| jtr[k]);
        let jtj = with_jtj.then(|| gram::<N, M>(&scratch.cols, pts.padded));
        return (ssr, jtj, jtr);
    }
    let (ssr, jtr) = norm_columns::<K, N>(params, pts, &mut scratch.cols);
    let jtj = with_jtj.then(|| gram::<N, M>(&scratch.cols, pts.padded));
    (ssr, jtj, jtr)
}

/// Sum of the four lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn hsum(v: std::arch::x86_64::__m256d) -> f64 {
    let mut l = [0.0f64; 4];
    // SAFETY: `l` holds four f64.
    unsafe { std::arch::x86_64::_mm256_storeu_pd(l.as_mut_ptr(), v) };
    (l[0] + l[1]) + (l[2] + l[3])
}

/// The sphere design columns, by [`sphere_design_avx2`] when the CPU has AVX2 and FMA.
fn sphere_design_fast(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 4>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU was just checked for the features the function was compiled for.
        return unsafe { sphere_design_avx2(pts, cols) };
    }
    sphere_design(pts, cols)
}

/// Normal equations of the linear sphere fit on `pts`: `(b.b, A^T A, A^T b)`.
pub fn sphere_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 4, 4>, SVector<f64, 4>) {
    scratch.clear(4, 6, pts.padded);
    let (bb, ab) = sphere_design_fast(pts, &mut scratch.cols);
    (bb, gram::<4, 6>(&scratch.cols, pts.padded), ab)
}

/// A design-column loop in AVX2 and FMA, four points at a time (the compiler's own vectorisation
/// of the generic loops ran at a fraction of this speed): `$row` maps the point lanes `x, y, z, w`
/// to the `$k` column vectors and the right-hand side; the function writes the columns and returns
/// `(b.b, A^T b)` like the generic body it stands for.
macro_rules! design_avx2 {
    ($(#[$doc:meta])* fn $name:ident -> $k:literal = |$x:ident, $y:ident, $z:ident, $w:ident| $row:block) => {
        $(#[$doc])*
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma")]
        fn $name(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, $k>) {
            use std::arch::x86_64::*;
            let p = pts.padded;
            assert!(p % 4 == 0 && cols.len() >= $k * p);
            assert!(pts.x.len() >= p && pts.y.len() >= p && pts.z.len() >= p && pts.w.len() >= p);
            let out = cols.as_mut_ptr();
            let mut ab = [_mm256_setzero_pd(); $k];
            let mut bb = _mm256_setzero_pd();
            let mut i = 0;
            while i < p {
                // SAFETY: i + 4 <= p <= the length of every column read and of each column slot
                // written (asserted above).
                unsafe {
                    let $x = _mm256_loadu_pd(pts.x.as_ptr().add(i));
                    let $y = _mm256_loadu_pd(pts.y.as_ptr().add(i));
                    let $z = _mm256_loadu_pd(pts.z.as_ptr().add(i));
                    let $w = _mm256_loadu_pd(pts.w.as_ptr().add(i));
                    let (c, b): ([__m256d; $k], __m256d) = $row;
                    for k in 0..$k {
                        _mm256_storeu_pd(out.add(k * p + i), c[k]);
                        ab[k] = _mm256_fmadd_pd(c[k], b, ab[k]);
                    }
                    bb = _mm256_fmadd_pd(b, b, bb);
                }
                i += 4;
            }
            (hsum(bb), SVector::<f64, $k>::from_fn(|k, _| hsum(ab[k])))
        }
    };
}

design_avx2! {
    /// [`sphere_design_body`] in AVX2.
    fn sphere_design_avx2 -> 4 = |x, y, z, w| {
        let (xw, yw, zw) = (_mm256_mul_pd(x, w), _mm256_mul_pd(y, w), _mm256_mul_pd(z, w));
        let r2 = _mm256_fmadd_pd(x, x, _mm256_fmadd_pd(y, y, _mm256_mul_pd(z, z)));
        (
            [_mm256_add_pd(xw, xw), _mm256_add_pd(yw, yw), _mm256_add_pd(zw, zw), w],
            _mm256_mul_pd(r2, w),
        )
    }
}

design_avx2! {
    /// [`ellipsoid_design_body`] in AVX2.
    fn ellipsoid_design_avx2 -> 9 = |x, y, z, w| {
        let (xw, yw, zw) = (_mm256_mul_pd(x, w), _mm256_mul_pd(y, w), _mm256_mul_pd(z, w));
        let (x2, y2) = (_mm256_add_pd(x, x), _mm256_add_pd(y, y));
        (
            [
                _mm256_mul_pd(x, xw),
                _mm256_mul_pd(y, yw),
                _mm256_mul_pd(z, zw),
                _mm256_mul_pd(x2, yw),
                _mm256_mul_pd(x2, zw),
                _mm256_mul_pd(y2, zw),
                _mm256_add_pd(xw, xw),
                _mm256_add_pd(yw, yw),
                _mm256_add_pd(zw, zw),
            ],
            w,
        )
    }
}

/// The ellipsoid design columns, by [`ellipsoid_design_avx2`] when the CPU has AVX2 and FMA.
fn ellipsoid_design_fast(pts: &Soa, cols: &mut [f64]) -> (f64, SVector<f64, 9>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU was just checked for the features the function was compiled for.
        return unsafe { ellipsoid_design_avx2(pts, cols) };
    }
    ellipsoid_design(pts, cols)
}

/// Normal equations of the algebraic ellipsoid fit on `pts`: `(b.b, A^T A, A^T b)`.
pub fn ellipsoid_normal_equations(
    pts: &Soa,
    scratch: &mut Scratch,
) -> (f64, SMatrix<f64, 9, 9>, SVector<f64, 9>) {
    let (bb, ab) = ellipsoid_design_fast(pts, &mut scratch.cols);
    (bb, gram::<9, 9>(&scratch.cols, pts.padded), ab)
}

/// Largest eigenvalue of the symmetric positive semi-definite `m` (`N` <= 12) in AVX2 and FMA: the
/// same power iteration as [`crate::fit`]'s portable one, on rows held as three vectors of four
/// (zero beyond `N`), so each product row is a run of broadcast multiply-adds instead of the
/// register-starved scalar loops the baseline build makes of it. `None` where the portable one
/// returns early (trace not positive and finite, or an iterate that vanishes).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub fn largest_eigenvalue_avx2<const N: usize>(m: &SMatrix<f64, N, N>) -> Option<f64> {
    use std::arch::x86_64::*;
    type Rows = [[f64; 12]; 12];
    assert!(N <= 12);
    // (Helpers rather than closures, so they are compiled for the same features and inlined.)
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn load(r: &[f64; 12], k: usize) -> __m256d {
        let c: &[f64; 4] = r[4 * k..4 * k + 4].try_into().expect("four lanes");
        // SAFETY: `c` holds four f64.
        unsafe { _mm256_loadu_pd(c.as_ptr()) }
    }
    /// Row combination `sum_k c[k] a[k]` (for a symmetric `a`, `a` times `c`).
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn combine<const N: usize>(a: &Rows, c: &[f64; 12]) -> [f64; 12] {
        let mut acc = [_mm256_setzero_pd(); 3];
        for k in 0..N {
            let b = _mm256_set1_pd(c[k]);
            for (l, acc) in acc.iter_mut().enumerate().take(N.div_ceil(4)) {
                *acc = _mm256_fmadd_pd(b, load(&a[k], l), *acc);
            }
        }
        let mut out = [0.0f64; 12];
        for (l, acc) in acc.iter().enumerate().take(N.div_ceil(4)) {
            let c: &mut [f64; 4] = (&mut out[4 * l..4 * l + 4]).try_into().expect("four lanes");
            // SAFETY: `c` holds four f64.
            unsafe { _mm256_storeu_pd(c.as_mut_ptr(), *acc) }
        }
        out
    }
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn square<const N: usize>(a: &Rows) -> Rows {
        let mut out = [[0.0f64; 12]; 12];
        for i in 0..N {
            out[i] = combine::<N>(a, &a[i]);
        }
        out
    }
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn dot<const N: usize>(a: &[f64; 12], b: &[f64; 12]) -> f64 {
        let mut acc = _mm256_setzero_pd();
        for l in 0..N.div_ceil(4) {
            acc = _mm256_fmadd_pd(load(a, l), load(b, l), acc);
        }
        hsum(acc)
    }
    let trace: f64 = (0..N).map(|i| m[(i, i)]).sum();
    if !(trace > 0.0) || !trace.is_finite() {
        return None;
    }
    let inv_trace = 1.0 / trace;
    let mut s: Rows = [[0.0f64; 12]; 12];
    for (i, row) in s.iter_mut().enumerate().take(N) {
        for (j, v) in row.iter_mut().enumerate().take(N) {
            *v = m[(j, i)] * inv_trace;
        }
    }
    let s4 = square::<N>(&square::<N>(&s));
    let k = (0..N).fold(0, |b, i| if s[i][i] > s[b][b] { i } else { b });
    let mut v = [0.0f64; 12];
    for i in 0..N {
        v[i] = s[k][i] + 1e-3 * s[k][k];
    }
    // (No normalising between products: see the portable version.)
    for _ in 0..6 {
        v = combine::<N>(&s4, &v);
    }
    let vv = dot::<N>(&v, &v);
    if !(vv > 0.0) || !vv.is_finite() {
        return None;
    }
    Some(trace * dot::<N>(&v, &combine::<N>(&s, &v)) / vv)
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
            let (bb, ab) = ellipsoid_design(&soa, &mut s.cols);
            let a = gram_portable::<9>(&s.cols, soa.padded);
            let b = gram_tiled::<9>(&s.cols, soa.padded);
            for i in 0..9 {
                for j in i..9 {
                    let tol = 1e-12 * (1.0 + a[i][j].abs());
                    assert!(
                        (a[i][j] - b[i][j]).abs() <= tol,
                        "n {n} ({i},{j}): {} vs {}",
                        a[i][j],
                        b[i][j]
                    );
                }
            }
            // Padding carries no weight: the right-hand side (1 per point) sums to the number of
            // points, and its products with the columns are their sums over the points.
            assert_eq!(bb, n as f64);
            let xs: f64 = soa.x[..n].iter().map(|x| 2.0 * x).sum();
            assert!((ab[6] - xs).abs() <= 1e-12 * (1.0 + xs.abs()), "n {n}");
        }
    }

    /// The first `k` columns and the sums of two column writers agree, over sizes that do and do
    /// not fill the last lane block.
    fn assert_same_columns<const K: usize>(
        seed: u64,
        k: usize,
        tol_sums: f64,
        generic: impl Fn(&Soa, &mut [f64]) -> (f64, SVector<f64, K>),
        fast: impl Fn(&Soa, &mut [f64]) -> (f64, SVector<f64, K>),
    ) {
        for n in [1usize, 7, 8, 9, 300, 301] {
            let soa = Soa::normalised(&random_points(n, seed + n as u64), [0.1, -0.2, 0.3], 1.5);
            let (mut s1, mut s2) = (Scratch::new(soa.padded), Scratch::new(soa.padded));
            let (bb1, ab1) = generic(&soa, &mut s1.cols);
            let (bb2, ab2) = fast(&soa, &mut s2.cols);
            assert!((bb1 - bb2).abs() <= tol_sums * (1.0 + bb1.abs()), "n {n}");
            assert!((ab1 - ab2).norm() <= tol_sums * (1.0 + ab1.norm()), "n {n}");
            let p = soa.padded;
            for (e, (a, b)) in s1.cols[..k * p].iter().zip(&s2.cols[..k * p]).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-15 * (1.0 + a.abs()),
                    "n {n} entry {e}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn avx2_designs_equal_the_generic_ones() {
        assert_same_columns::<9>(40, 9, 1e-12, ellipsoid_design_body, ellipsoid_design_fast);
        assert_same_columns::<4>(80, 4, 1e-12, sphere_design_body, sphere_design_fast);
    }

    #[test]
    fn avx2_sym9_columns_equal_the_generic_ones() {
        let params = [0.1, -0.2, 0.05, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05];
        let pv = SVector::<f64, 9>::from_column_slice(&params);
        for n in [1usize, 7, 8, 9, 300, 301] {
            let mut pts = random_points(n, 120 + n as u64);
            // Points far from the others, and one at the model's centre.
            if n >= 8 {
                pts[3] = [1e20, -3e19, 2e18];
                pts[5] = [1e-20, 0.0, 0.0];
                pts[6] = [0.25, -0.5, 0.375];
            }
            let soa = Soa::normalised(&pts, [0.1, -0.2, 0.3], 1.5);
            let (mut s1, mut s2) = (Scratch::new(soa.padded), Scratch::new(soa.padded));
            let (ssr1, jtr1) = norm_columns_body::<SYM9, 9>(&pv, &soa, &mut s1.cols);

            let mut s3 = Scratch::new(soa.padded);
            let (ssr3, none, jtr3) = norm_normal_equations::<SYM9, 9, 9>(&pv, &soa, &mut s3, false);
            let (ssr2, _, jtr2) = norm_normal_equations::<SYM9, 9, 9>(&pv, &soa, &mut s2, true);
            assert!((ssr1 - ssr2).abs() <= 1e-12 * (1.0 + ssr1), "n {n}");
            assert!((jtr1 - jtr2).norm() <= 1e-12 * (1.0 + jtr1.norm()), "n {n}");
            // Without J^T J: the same sums, no matrix.
            assert!(none.is_none() && ssr3 == ssr2 && jtr3 == jtr2, "n {n}");
            let p = soa.padded;
            for (k, (a, b)) in s1.cols[..9 * p].iter().zip(&s2.cols[..9 * p]).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-13 * (1.0 + a.abs()),
                    "n {n} entry {k}: {a} vs {b}"
                );
            }
        }
    }

    /// The kernel's residuals and gradients against the per-point reference in `model` (whose
    /// gradients are checked against numerical derivatives there).
    fn check_against_reference<const K: u8, const N: usize, const M: usize>(params: &[f64]) {
        let pts = random_points(37, 5);
        let soa = Soa::normalised(&pts, [0.0; 3], 1.0);
        let mut s = Scratch::new(soa.padded);
        s.clear(N, M, soa.padded);
        let p = SVector::<f64, N>::from_column_slice(params);
        let (ssr, jtj, jtr) = norm_normal_equations::<K, N, M>(&p, &soa, &mut s, true);
        let jtj = jtj.expect("asked for J^T J");
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
        check_against_reference::<DIAG6, 6, 6>(&[0.1, -0.2, 0.05, 1.1, 0.9, 1.05]);
        let nine = [0.1, -0.2, 0.05, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05];
        check_against_reference::<SYM9, 9, 9>(&nine);
        check_against_reference::<FULL12, 9, 9>(&nine);
    }
}
