//! Vector magnetometer calibration: from the attitude and the earth field instead of the field's
//! norm alone, so that an ordinary flight (legs, banked turns, no tumble) is enough.
//!
//! Model, in body axes and uT: `raw = A h + o + k c + noise`, with `h = R^T B` the earth field `B`
//! (NED, from the World Magnetic Model at the place and date) seen by the body at the attitude `R`
//! (body -> NED), `o` the hard iron, `A` the soft iron (with the scale and any small misalignment of
//! the compass against the attitude's body frame; the report's matrix is `A^-1`, calibrated =
//! `A^-1 (raw - o)`), and `k` the field per ampere of battery current `c` (optional). Given the
//! attitudes the model is linear in `(A, o, k)`: each raw axis `j` is a linear regression of
//! `raw_j - h_j` on the same regressors `u = (h / |B|, 1, c / c_max)`, so one normal matrix
//! `N = mean(u u^T)` serves all three axes and the fit is linear least squares (no iteration).
//! That forward fit gives the offset the calibration is then centred on; the calibration itself
//! comes from the reverse regression, the expected field on the reading,
//! `h = M (raw - o_ref) + d + k' c` (`A = M^-1`), with the same rules on what is determined: least
//! squares puts the error in the variable regressed, and the attitude's error (a degree is 0.9 uT
//! of a 50 uT field) is larger than a compass's (tenths of a uT), so the expected field is the one
//! regressed (see `reverse`). On the three APM-era telemetry logs of `../shared/data/real/` the
//! held-out spread of the field's norm went from 4.74, 3.06 and 3.43 % (forward) to 4.47, 2.83 and
//! 2.64 % (`cargo bench --bench real_quality`).
//! The same measurement model, with the orientation known from inertial sensors, is the one of
//! Kok and Schön, "Magnetometer calibration using inertial sensors" (2016); what is added here is
//! the explicit verdict on what the attitudes seen determine.
//!
//! Identifiability. The eigenvectors of `N` are combinations of the terms (soft iron against the
//! field along body x, y, z; offset; current); the square root of an eigenvalue is how much the data
//! vary that combination (RMS, relative to the field strength). A combination varied less than
//! [`MIN_SPREAD`] is not determined by the attitudes seen: attitude errors of a degree or two move
//! the expected field as much. Such a direction is left out of the fit and named; along it the
//! soft iron and current terms are held at their nominal values (identity, zero) and the offset
//! takes the rest. The offset is then only as good as that assumption: it is called identifiable
//! only when a soft-iron error of [`SOFT_IRON_PRIOR`] along the unidentified directions would move it
//! by less than [`OFFSET_ASSUMPTION_LIMIT_UT`]. Level flight turning about the vertical only is the
//! typical case: the body-z field stays at `B_down`, so the z column of the soft iron and the offset
//! cannot be told apart.
//!
//! Pure: no I/O.

use crate::types::Vec3;
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// The smallest RMS spread (relative to the field strength) of a combination of terms that the
/// fit takes as determined: 0.03 of the field is the field change of a 1.7 deg attitude error.
pub(crate) const MIN_SPREAD: f64 = 0.03;
/// The size of a soft-iron element assumed when judging what an unidentified direction does to the
/// offset (a compass near ferrous parts: a few percent).
pub(crate) const SOFT_IRON_PRIOR: f64 = 0.05;
/// Above this the offset depends on what was assumed: not identifiable, uT.
pub(crate) const OFFSET_ASSUMPTION_LIMIT_UT: f64 = 0.5;
/// Fewest points the fit takes.
pub(crate) const MIN_POINTS: usize = 50;
/// Points whose residual is beyond this many robust standard deviations are left out (once).
pub(crate) const OUTLIER_SIGMAS: f64 = 5.0;
/// The current term is fitted only when the logged current varies at least this much (standard
/// deviation, A): a constant current cannot be told from the offset.
pub(crate) const MIN_CURRENT_SD_A: f64 = 1.0;

/// One magnetometer reading with the field the attitude says it should see.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VectorPoint {
    /// The reading, body axes, uT.
    pub raw_ut: Vec3,
    /// `R^T B`: the earth field in body axes at the reading's attitude, uT.
    pub expected_ut: Vec3,
    /// Battery current, A (used when the fit includes the current term).
    pub current_a: Option<f64>,
}

/// A combination of the fit's terms, an eigenvector of the normal matrix.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Direction {
    /// Weights over [`VectorFit::terms`], unit length.
    pub weights: Vec<f64>,
    /// RMS of the combination over the data, relative to the field strength.
    pub spread: f64,
    pub identifiable: bool,
    /// The combination in words, its largest weights first (`+0.75 offset -0.66 soft iron (body-z field)`).
    pub description: String,
}

/// The result of [`fit`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VectorFit {
    /// Hard iron, body axes, uT, and its 1-sigma uncertainty from the data.
    pub offset_ut: Vec3,
    pub offset_sigma_ut: Vec3,
    /// How far the offset could be off through what was held at nominal along the unidentified
    /// directions (a soft-iron error of [`SOFT_IRON_PRIOR`]), uT; 0 when everything is determined.
    pub offset_assumption_ut: f64,
    pub offset_identifiable: bool,
    /// `A` of `raw = A h + o`, and its 1-sigma uncertainty.
    pub soft_iron: [[f64; 3]; 3],
    pub soft_iron_sigma: [[f64; 3]; 3],
    /// Per column of `A` (the response to the field along body x, y, z): fitted from the data, or
    /// held at the identity because the attitudes do not determine it.
    pub soft_iron_fitted: [bool; 3],
    /// `A^-1`: calibrated = matrix (raw - offset).
    pub matrix: [[f64; 3]; 3],
    /// The rotation within `A` (its polar factor), deg: the turn between the compass's axes and the
    /// attitude's body frame (a mounting not given in the configuration).
    pub rotation_deg: f64,
    /// Field per ampere of battery current, uT/A, with its 1-sigma uncertainty and whether the
    /// data determine it (when the fit includes the current term).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_ut_per_a: Option<Vec3>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_sigma_ut_per_a: Option<Vec3>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_identifiable: Option<bool>,
    /// Mean strength of the expected field, uT.
    pub field_ut: f64,
    /// RMS of `raw - (A h + o + k c)` over the points kept, per axis, uT.
    pub rms_residual_ut: f64,
    pub points: usize,
    pub outliers_rejected: usize,
    /// The terms the weights of `directions` refer to.
    pub terms: Vec<String>,
    /// Every eigen-direction of the normal matrix, the least determined first.
    pub directions: Vec<Direction>,
}

impl VectorFit {
    /// The directions the attitudes did not determine.
    pub fn unidentified(&self) -> impl Iterator<Item = &Direction> {
        self.directions.iter().filter(|d| !d.identifiable)
    }
}

/// Why [`fit`] gave no result.
#[derive(Debug, Clone, PartialEq)]
pub enum VectorFailure {
    NotEnoughPoints {
        have: usize,
        need: usize,
    },
    /// The expected field is zero or not finite.
    NoField,
    /// The normal equations could not be solved (no direction determined, or a degenerate one).
    Singular,
    /// The attitudes turn too little for any earth field to determine the offset
    /// ([`AttitudeSums::turn_spread`]): `spread` is what they give, `need` [`MIN_SPREAD`].
    TooLittleTurning {
        spread: f64,
        need: f64,
    },
}

impl std::fmt::Display for VectorFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VectorFailure::NotEnoughPoints { have, need } => {
                write!(f, "{have} readings with an attitude, need {need}")
            }
            VectorFailure::NoField => write!(f, "the expected earth field is zero or not finite"),
            VectorFailure::Singular => write!(f, "the normal equations are singular"),
            VectorFailure::TooLittleTurning { spread, need } => write!(
                f,
                "the attitudes turn too little to tell the offset from the soft iron, whatever the field: the field seen in body axes varies along its own direction by at most {spread:.4} of its strength, need {need:.2} (turns of about {:.0} deg from the mean attitude)",
                (1.0 - need).acos().to_degrees()
            ),
        }
    }
}

const SOFT_IRON_TERMS: [&str; 3] = [
    "soft iron (body-x field)",
    "soft iron (body-y field)",
    "soft iron (body-z field)",
];
const OFFSET: usize = 3;

/// Fit the model to `points`; with `fit_current`, the current term too (points without a current
/// are then left out). Points with a non-finite value are left out. One pass of outlier rejection
/// ([`OUTLIER_SIGMAS`]) follows the first fit.
pub fn fit(points: &[VectorPoint], fit_current: bool) -> Result<VectorFit, VectorFailure> {
    let usable = |p: &&VectorPoint| {
        crate::types::is_finite3(&p.raw_ut)
            && crate::types::is_finite3(&p.expected_ut)
            && (!fit_current || p.current_a.is_some_and(f64::is_finite))
    };
    let kept: Vec<VectorPoint> = points.iter().filter(usable).copied().collect();
    fit_with_cut(
        || solve_batch(&kept, fit_current),
        |first| residual_norms(&kept, first),
        |keep| {
            let within: Vec<VectorPoint> = kept
                .iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .map(|(p, _)| *p)
                .collect();
            solve_batch(&within, fit_current)
        },
    )
}

/// The fit of all readings (`solve_all`); when some of their residual norms (`residuals`) are
/// beyond [`OUTLIER_SIGMAS`] robust standard deviations, the fit of those within
/// (`solve_kept`, given which are).
fn fit_with_cut(
    solve_all: impl FnOnce() -> Result<VectorFit, VectorFailure>,
    residuals: impl FnOnce(&VectorFit) -> Vec<f64>,
    solve_kept: impl FnOnce(&[bool]) -> Result<VectorFit, VectorFailure>,
) -> Result<VectorFit, VectorFailure> {
    let first = solve_all()?;
    let r = residuals(&first);
    let mut sorted = r.clone();
    let mid = sorted.len() / 2;
    // The median of a 3-D residual norm is 1.54 sigma per axis (chi with 3 degrees of freedom).
    let sigma = *sorted.select_nth_unstable_by(mid, f64::total_cmp).1 / 1.538;
    let limit = OUTLIER_SIGMAS * 3f64.sqrt() * sigma;
    let keep: Vec<bool> = r.iter().map(|x| *x <= limit).collect();
    let rejected = keep.iter().filter(|k| !**k).count();
    if rejected == 0 {
        return Ok(first);
    }
    let mut f = solve_kept(&keep)?;
    f.outliers_rejected = rejected;
    Ok(f)
}

/// Readings with their attitudes, summed so that the vector fit (no current term) for any earth
/// field `b` (NED, uT) needs no sums over the readings: with `e = R^T b` the expected field, every
/// sum the fit takes ([`VectorAccumulator`]) is a fixed combination of `b` and the sums of `R`,
/// `R (x) R`, `R (x) raw`, `raw` and `raw raw^T`. Only the outlier cut still looks at each
/// reading. For fits that try many fields on the same readings
/// (`crate::calib::magmethod::fit_with_field`).
pub(crate) struct AttitudeSums {
    /// The readings (body axes, uT) and their attitudes (body -> NED), finite ones only.
    raw: Vec<nalgebra::Vector3<f64>>,
    rot: Vec<nalgebra::Matrix3<f64>>,
    totals: Sums,
}

/// The sums of [`AttitudeSums`].
#[derive(Debug, Clone, Default)]
struct Sums {
    n: f64,
    /// Sum of R.
    r: nalgebra::Matrix3<f64>,
    /// Sum of R[p][a] R[q][c] at (3p + a, 3q + c).
    rr: nalgebra::SMatrix<f64, 9, 9>,
    /// Sum of R[p][a] raw[j] at (3p + a, j).
    r_raw: nalgebra::SMatrix<f64, 9, 3>,
    raw: nalgebra::Vector3<f64>,
    raw_raw: nalgebra::Matrix3<f64>,
}

impl Sums {
    /// Add (`sign` 1) or take out (-1) one reading. `rr` is symmetric and only its upper
    /// triangle (row <= column) is summed here, half the work per reading; [`Sums::mirror`]
    /// copies it to the lower one once the readings are in. The lower entries it gives are
    /// those a full sum would give, to the bit: entry (i, j) adds `(sign R_i) R_j` and (j, i)
    /// adds `(sign R_j) R_i`, the same product (`sign` is +-1, which scales exactly).
    fn add_upper(&mut self, rot: &nalgebra::Matrix3<f64>, raw: &nalgebra::Vector3<f64>, sign: f64) {
        self.n += sign;
        self.r += rot * sign;
        // R's entries by (3p + a): rv[3p + a] = R[p][a].
        let rv: [f64; 9] = std::array::from_fn(|i| rot[(i / 3, i % 3)]);
        for (i, &ri) in rv.iter().enumerate() {
            let x = sign * ri;
            for (j, &rj) in rv.iter().enumerate().skip(i) {
                self.rr[(i, j)] += x * rj;
            }
            for j in 0..3 {
                self.r_raw[(i, j)] += x * raw[j];
            }
        }
        self.raw += raw * sign;
        self.raw_raw += raw * raw.transpose() * sign;
    }

    /// Fill `rr`'s lower triangle from its upper one ([`Sums::add_upper`]).
    fn mirror(&mut self) {
        for i in 0..9 {
            for j in 0..i {
                self.rr[(i, j)] = self.rr[(j, i)];
            }
        }
    }
}

impl AttitudeSums {
    /// From (reading in body axes, uT; body -> NED attitude) pairs; pairs with a value that is
    /// not finite are left out.
    pub(crate) fn new(
        pairs: impl Iterator<Item = (nalgebra::Vector3<f64>, nalgebra::Matrix3<f64>)>,
    ) -> AttitudeSums {
        // Room for as many pairs as may come, so the lists are not copied as they grow (each
        // copy touches fresh pages).
        let room = pairs.size_hint().1.unwrap_or(0);
        let mut out = AttitudeSums {
            raw: Vec::with_capacity(room),
            rot: Vec::with_capacity(room),
            totals: Sums::default(),
        };
        for (raw, rot) in pairs {
            if raw.iter().chain(rot.iter()).all(|v| v.is_finite()) {
                out.totals.add_upper(&rot, &raw, 1.0);
                out.raw.push(raw);
                out.rot.push(rot);
            }
        }
        out.totals.mirror();
        out
    }

    /// Readings summed.
    pub(crate) fn len(&self) -> usize {
        self.raw.len()
    }

    /// How far the attitudes turn, as the most that any earth field seen in body axes can vary
    /// along its own direction: the RMS over the readings of `1 - cos theta`, `theta` the angle of
    /// a reading's attitude `R` from the mean attitude `R0` (the rotation nearest the mean of the
    /// `R`). For a unit field `b` and `f = R0^T b`, the body field `e = R^T b` has
    /// `e.f = b^T (R R0^T) b >= cos theta` (`R R0^T` turns by `theta`), so `0 <= 1 - e.f <=
    /// 1 - cos theta`: the standard deviation of `e.f`, at most its RMS distance from 1, is at most
    /// this, whatever `b` is. Below [`MIN_SPREAD`] that combination (the soft
    /// iron along the field against the offset) is not determined for any field, and the offset
    /// rests on the assumed soft iron by about [`SOFT_IRON_PRIOR`] times the field's strength.
    /// From the sums alone: `cos theta = (<R0, R> - 1) / 2` (Frobenius product), whose square
    /// summed is `vec(R0)^T (sum R (x) R) vec(R0)`. `None` with no readings or no mean attitude.
    pub(crate) fn turn_spread(&self) -> Option<f64> {
        let t = &self.totals;
        if !(t.n > 0.0) {
            return None;
        }
        let r0 = nearest_rotation(&(t.r / t.n))?;
        // Sums of <R0, R> and of its square.
        let v = nalgebra::SVector::<f64, 9>::from_fn(|i, _| r0[(i / 3, i % 3)]);
        let s1: f64 = (0..9).map(|i| v[i] * t.r[(i / 3, i % 3)]).sum();
        let s2 = (v.transpose() * t.rr * v)[(0, 0)];
        // 1 - cos theta = (3 - <R0, R>) / 2.
        let sq = (9.0 * t.n - 6.0 * s1 + s2) / 4.0;
        Some((sq.max(0.0) / t.n).sqrt())
    }

    /// The mean over the readings of `R m (raw - o)`: the readings calibrated by `m`, `o` and
    /// turned into NED.
    pub(crate) fn mean_ned(
        &self,
        m: &nalgebra::Matrix3<f64>,
        o: &nalgebra::Vector3<f64>,
    ) -> nalgebra::Vector3<f64> {
        let t = &self.totals;
        // sum R m raw: component x is sum over a, j of m[a][j] (sum R[x][a] raw[j]).
        let r_m_raw = nalgebra::Vector3::from_fn(|x, _| {
            let mut v = 0.0;
            for a in 0..3 {
                for j in 0..3 {
                    v += m[(a, j)] * t.r_raw[(3 * x + a, j)];
                }
            }
            v
        });
        (r_m_raw - t.r * (m * o)) / t.n
    }

    /// [`fit`] (no current term) of the readings against the earth field `b`: what it gives for
    /// points with `expected_ut = R^T b`, to rounding.
    pub(crate) fn fit(&self, b: &nalgebra::Vector3<f64>) -> Result<VectorFit, VectorFailure> {
        fit_with_cut(
            || accumulator_of(&self.totals, b)?.solve(),
            |first| self.residual_norms(first, b),
            |keep| {
                let mut s = self.totals.clone();
                for (i, _) in keep.iter().enumerate().filter(|(_, k)| !**k) {
                    s.add_upper(&self.rot[i], &self.raw[i], -1.0);
                }
                s.mirror();
                accumulator_of(&s, b)?.solve()
            },
        )
    }

    /// [`residual_norms`] of the readings against `b`.
    fn residual_norms(&self, f: &VectorFit, b: &nalgebra::Vector3<f64>) -> Vec<f64> {
        let a = crate::calib::model::rows_to_mat(&f.soft_iron);
        let o = nalgebra::Vector3::from(f.offset_ut);
        self.raw
            .iter()
            .zip(&self.rot)
            .map(|(raw, rot)| (raw - a * (rot.transpose() * b) - o).norm())
            .collect()
    }
}

/// The accumulator (no current term) that pushing every reading of `s` against the field `b`
/// would give: the regressors' scale is `|b|` (the mean strength of `R^T b`).
fn accumulator_of(
    s: &Sums,
    b: &nalgebra::Vector3<f64>,
) -> Result<VectorAccumulator, VectorFailure> {
    let need = MIN_POINTS.max(2 * 4);
    if s.n < need as f64 {
        return Err(VectorFailure::NotEnoughPoints {
            have: s.n.max(0.0).round() as usize,
            need,
        });
    }
    let f = b.norm();
    let mut acc = VectorAccumulator::new(f, None)?;
    // Sums of e, e e^T and e raw^T, with e = R^T b.
    let se = s.r.transpose() * b;
    let see = nalgebra::Matrix3::from_fn(|a, c| {
        let mut v = 0.0;
        for p in 0..3 {
            for q in 0..3 {
                v += b[p] * b[q] * s.rr[(3 * p + a, 3 * q + c)];
            }
        }
        v
    });
    let ser = nalgebra::Matrix3::<f64>::from_fn(|a, j| {
        (0..3).map(|p| b[p] * s.r_raw[(3 * p + a, j)]).sum::<f64>()
    });
    for a in 0..3 {
        for c in 0..3 {
            acc.nm[(a, c)] = see[(a, c)] / (f * f);
            acc.nm_r[(a, c)] = s.raw_raw[(a, c)] / (f * f);
        }
        acc.nm[(a, OFFSET)] = se[a] / f;
        acc.nm[(OFFSET, a)] = se[a] / f;
        acc.nm_r[(a, OFFSET)] = s.raw[a] / f;
        acc.nm_r[(OFFSET, a)] = s.raw[a] / f;
    }
    acc.nm[(OFFSET, OFFSET)] = s.n;
    acc.nm_r[(OFFSET, OFFSET)] = s.n;
    for j in 0..3 {
        for a in 0..3 {
            // Push adds u y^T with u = (e / f, 1), y = raw - e; reverse: -(raw / f, 1) y^T.
            acc.g[(a, j)] = (ser[(a, j)] - see[(a, j)]) / f;
            acc.g_r[(a, j)] = -(s.raw_raw[(a, j)] - ser[(j, a)]) / f;
        }
        acc.g[(OFFSET, j)] = s.raw[j] - se[j];
        acc.g_r[(OFFSET, j)] = -(s.raw[j] - se[j]);
        let yy = s.raw_raw[(j, j)] - 2.0 * ser[(j, j)] + see[(j, j)];
        acc.yy[j] = yy;
        acc.yy_r[j] = yy;
    }
    acc.weight = s.n;
    acc.points = s.n.max(0.0).round() as usize;
    Ok(acc)
}

/// The points' scales (mean field strength, largest current), then their sums.
fn solve_batch(points: &[VectorPoint], fit_current: bool) -> Result<VectorFit, VectorFailure> {
    let need = MIN_POINTS.max(2 * if fit_current { 5 } else { 4 });
    if points.len() < need {
        return Err(VectorFailure::NotEnoughPoints {
            have: points.len(),
            need,
        });
    }
    let n = points.len() as f64;
    let field_ut = points
        .iter()
        .map(|p| crate::types::norm(&p.expected_ut))
        .sum::<f64>()
        / n;
    let current_max_a = points
        .iter()
        .filter_map(|p| p.current_a)
        .fold(0.0f64, |a, c| a.max(c.abs()))
        .max(1e-9);
    let mut acc = VectorAccumulator::new(field_ut, fit_current.then_some(current_max_a))?;
    for p in points {
        acc.push(p);
    }
    acc.solve()
}

/// The fit's sufficient statistics: the normal matrix and right-hand sides of the linear least
/// squares, summed point by point, so a fit needs no stored points. [`fit`] fills one from a batch
/// of points; the live service keeps one per compass and adds each reading as it comes
/// (recursive least squares), with [`VectorAccumulator::forget`] discounting old readings.
/// Memory and the cost of [`VectorAccumulator::solve`] do not grow with the points.
#[derive(Debug, Clone, PartialEq)]
pub struct VectorAccumulator {
    reg: Regressors,
    /// Sum of the points' weights.
    weight: f64,
    /// Points added (weights aside).
    points: usize,
    /// `sum w u u^T`, `sum w u y^T` (one column per raw axis) and `sum w y_j^2`, with
    /// `y = raw - h`.
    nm: DMatrix<f64>,
    g: DMatrix<f64>,
    yy: Vec3,
    /// The same sums of the reverse regression ([`reverse`]): regressors `(raw / |B|, 1, c)`
    /// and `y = h - raw`.
    nm_r: DMatrix<f64>,
    g_r: DMatrix<f64>,
    yy_r: Vec3,
}

impl VectorAccumulator {
    /// An empty accumulator for fields of about `field_ut` (the regressors' scale, uT) and, with
    /// `current_scale_a` (A, the largest current expected), the current term.
    pub fn new(field_ut: f64, current_scale_a: Option<f64>) -> Result<Self, VectorFailure> {
        if !(field_ut.is_finite() && field_ut > 0.0) {
            return Err(VectorFailure::NoField);
        }
        let current_max_a = current_scale_a.filter(|c| c.is_finite() && *c > 0.0);
        let k = if current_scale_a.is_some() { 5 } else { 4 };
        Ok(VectorAccumulator {
            reg: Regressors {
                field_ut,
                current_max_a: current_max_a.unwrap_or(1.0),
                k,
            },
            weight: 0.0,
            points: 0,
            nm: DMatrix::zeros(k, k),
            g: DMatrix::zeros(k, 3),
            yy: [0.0; 3],
            nm_r: DMatrix::zeros(k, k),
            g_r: DMatrix::zeros(k, 3),
            yy_r: [0.0; 3],
        })
    }

    /// Add one reading. Returns false (and adds nothing) when a value is not finite or, with the
    /// current term, the reading has no current.
    pub fn push(&mut self, p: &VectorPoint) -> bool {
        let with_current = self.reg.k > 4;
        if !(crate::types::is_finite3(&p.raw_ut)
            && crate::types::is_finite3(&p.expected_ut)
            && (!with_current || p.current_a.is_some_and(f64::is_finite)))
        {
            return false;
        }
        let k = self.reg.k;
        let u = self.reg.of(p.expected_ut, p.current_a);
        let u_r = self.reg.of(p.raw_ut, p.current_a);
        // In place: no temporaries per reading.
        for c in 0..k {
            for r in 0..k {
                self.nm[(r, c)] += u[r] * u[c];
                self.nm_r[(r, c)] += u_r[r] * u_r[c];
            }
        }
        for j in 0..3 {
            let y = p.raw_ut[j] - p.expected_ut[j];
            for r in 0..k {
                self.g[(r, j)] += u[r] * y;
                self.g_r[(r, j)] -= u_r[r] * y;
            }
            self.yy[j] += y * y;
            self.yy_r[j] += y * y;
        }
        self.weight += 1.0;
        self.points += 1;
        true
    }

    /// Discount everything added so far by `factor` (0..=1): a reading's weight halves every
    /// ln 2 / -ln factor calls. Identifiability and uncertainties follow the weights left.
    pub(crate) fn forget(&mut self, factor: f64) {
        let f = factor.clamp(0.0, 1.0);
        self.nm *= f;
        self.g *= f;
        self.yy = self.yy.map(|v| v * f);
        self.nm_r *= f;
        self.g_r *= f;
        self.yy_r = self.yy_r.map(|v| v * f);
        self.weight *= f;
    }

    /// Readings added so far (before any discount).
    pub fn points(&self) -> usize {
        self.points
    }

    /// The weight of the readings left after discounting (the number of readings without it).
    pub fn weight(&self) -> f64 {
        self.weight
    }

    /// The fit of what was added: a small eigen-decomposition and solve of the `k x k` normal
    /// matrix (k = 4 or 5), whatever the number of readings.
    pub(crate) fn solve(&self) -> Result<VectorFit, VectorFailure> {
        reverse(self, &solve(self)?)
    }
}

/// The model's parameters: per raw axis, the coefficients of `raw_j - h_j` on the regressors.
#[derive(Debug, Clone, PartialEq)]
struct Regressors {
    field_ut: f64,
    current_max_a: f64,
    k: usize,
}

impl Regressors {
    /// The regressors of a point: the field `v` (the expected one, or the reading in the reverse
    /// regression) over the field strength, 1, and the current over its scale (0 past `k`).
    fn of(&self, v: Vec3, current_a: Option<f64>) -> [f64; 5] {
        let mut u = [0.0; 5];
        for c in 0..3 {
            u[c] = v[c] / self.field_ut;
        }
        u[OFFSET] = 1.0;
        if self.k > 4 {
            u[4] = current_a.unwrap_or(0.0) / self.current_max_a;
        }
        u
    }
}

fn residual_norms(points: &[VectorPoint], f: &VectorFit) -> Vec<f64> {
    let a = crate::calib::model::rows_to_mat(&f.soft_iron);
    let k = f.current_ut_per_a.unwrap_or([0.0; 3]);
    points
        .iter()
        .map(|p| {
            let h = nalgebra::Vector3::from(p.expected_ut);
            let m = a * h;
            let c = p.current_a.unwrap_or(0.0);
            (0..3)
                .map(|j| {
                    let r = p.raw_ut[j] - m[j] - f.offset_ut[j] - k[j] * c;
                    r * r
                })
                .sum::<f64>()
                .sqrt()
        })
        .collect()
}

fn describe(weights: &[f64], terms: &[String]) -> String {
    let mut idx: Vec<usize> = (0..weights.len()).collect();
    idx.sort_by(|a, b| weights[*b].abs().total_cmp(&weights[*a].abs()));
    // Sign fixed so the largest weight is positive.
    let s = if weights[idx[0]] < 0.0 { -1.0 } else { 1.0 };
    idx.iter()
        .filter(|&&i| weights[i].abs() >= 0.1)
        .map(|&i| format!("{:+.2} {}", s * weights[i], terms[i]))
        .collect::<Vec<_>>()
        .join(" ")
}

fn solve(acc: &VectorAccumulator) -> Result<VectorFit, VectorFailure> {
    let k = acc.reg.k;
    let fit_current = k > 4;
    let need = MIN_POINTS.max(2 * k);
    // With discounting, the weight left is what counts.
    let have = acc.weight.min(acc.points as f64);
    if have < need as f64 {
        return Err(VectorFailure::NotEnoughPoints {
            have: have as usize,
            need,
        });
    }
    let n = acc.weight;
    let (field_ut, current_max_a) = (acc.reg.field_ut, acc.reg.current_max_a);
    // Normal matrix and right-hand sides (one column per raw axis), both divided by n.
    let nm = &acc.nm / n;
    let g = &acc.g / n;
    let eig = nalgebra::SymmetricEigen::new(nm.clone());
    let mut order: Vec<usize> = (0..k).collect();
    order.sort_by(|a, b| eig.eigenvalues[*a].total_cmp(&eig.eigenvalues[*b]));
    let mut terms: Vec<String> = SOFT_IRON_TERMS.iter().map(|s| s.to_string()).collect();
    terms.push("offset".into());
    if fit_current {
        terms.push("current".into());
    }
    let mut directions = Vec::with_capacity(k);
    let (mut q, mut v_un) = (DMatrix::<f64>::zeros(k, k), Vec::new());
    for &i in &order {
        let lam = eig.eigenvalues[i].max(0.0);
        let v = eig.eigenvectors.column(i).into_owned();
        let spread = lam.sqrt();
        let identifiable = spread >= MIN_SPREAD;
        if identifiable {
            q += &v * v.transpose() / lam;
        } else {
            v_un.push(v.clone());
        }
        directions.push(Direction {
            weights: v.iter().copied().collect(),
            spread,
            identifiable,
            description: describe(v.as_slice(), &terms),
        });
    }
    if v_un.len() == k {
        return Err(VectorFailure::Singular);
    }
    // Along the unidentified directions, hold the soft-iron and current terms at nominal (least
    // squares over them), the offset free: beta = L beta_id.
    let mut s = DMatrix::<f64>::identity(k, k);
    s[(OFFSET, OFFSET)] = 0.0;
    let mut l = DMatrix::<f64>::identity(k, k);
    let mut offset_assumption_ut = 0.0f64;
    if !v_un.is_empty() {
        let vu = DMatrix::from_columns(&v_un);
        let m = vu.transpose() * &s * &vu;
        let mi = m.try_inverse().ok_or(VectorFailure::Singular)?;
        l -= &vu * mi * vu.transpose() * &s;
        for v in &v_un {
            let sv = (&s * v).norm();
            if sv < 1e-9 {
                return Err(VectorFailure::Singular);
            }
            let o = SOFT_IRON_PRIOR * field_ut * v[OFFSET].abs() / sv;
            offset_assumption_ut = offset_assumption_ut.hypot(o);
        }
    }
    let beta = &l * &q * &g;
    // Residuals per axis with the final parameters, from the sums:
    // sum (y - b.u)^2 = sum y^2 - 2 b.(sum u y) + b^T (sum u u^T) b.
    let mut ssr = [0.0; 3];
    for j in 0..3 {
        let b = beta.column(j);
        let quad = (b.transpose() * &acc.nm * b)[(0, 0)];
        ssr[j] = (acc.yy[j] - 2.0 * b.dot(&acc.g.column(j)) + quad).max(0.0);
    }
    let dof = (n - (k - v_un.len()) as f64).max(1.0);
    let cov_unit = &l * &q * l.transpose() / n;
    let mut fitted = [true; 3];
    for v in &v_un {
        for c in 0..3 {
            if v[c].abs() >= 0.1 {
                fitted[c] = false;
            }
        }
    }
    let (mut a, mut a_sd) = ([[0.0; 3]; 3], [[0.0; 3]; 3]);
    let (mut o, mut o_sd, mut kc, mut kc_sd) = ([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]);
    for j in 0..3 {
        let var = ssr[j] / dof;
        for c in 0..3 {
            a[j][c] = if j == c { 1.0 } else { 0.0 } + beta[(c, j)] / field_ut;
            a_sd[j][c] = (var * cov_unit[(c, c)]).max(0.0).sqrt() / field_ut;
        }
        o[j] = beta[(OFFSET, j)];
        o_sd[j] = (var * cov_unit[(OFFSET, OFFSET)]).max(0.0).sqrt();
        if fit_current {
            kc[j] = beta[(4, j)] / current_max_a;
            kc_sd[j] = (var * cov_unit[(4, 4)]).max(0.0).sqrt() / current_max_a;
        }
    }
    let am = crate::calib::model::rows_to_mat(&a);
    let matrix = am.try_inverse().ok_or(VectorFailure::Singular)?;
    let rotation_deg = polar_rotation_deg(&am);
    let current_identifiable = fit_current.then(|| v_un.iter().all(|v| v[4].abs() < 0.1));
    Ok(VectorFit {
        offset_ut: o,
        offset_sigma_ut: o_sd,
        offset_assumption_ut,
        offset_identifiable: offset_assumption_ut <= OFFSET_ASSUMPTION_LIMIT_UT,
        soft_iron: a,
        soft_iron_sigma: a_sd,
        soft_iron_fitted: fitted,
        matrix: crate::calib::model::mat_to_rows(&matrix),
        rotation_deg,
        current_ut_per_a: fit_current.then_some(kc),
        current_sigma_ut_per_a: fit_current.then_some(kc_sd),
        current_identifiable,
        field_ut,
        rms_residual_ut: ((ssr[0] + ssr[1] + ssr[2]) / (3.0 * n)).sqrt(),
        points: acc.points,
        outliers_rejected: 0,
        terms,
        directions,
    })
}

/// The calibration from the reverse regression: the expected field on the reading,
/// `h = M (raw - o_ref) + d + k' c`, with the same identifiability rules, centred on the forward
/// fit's offset `o_ref` (so the regressors vary about zero as the forward ones do).
///
/// Why the reverse: least squares puts all the error in the variable regressed. A compass reads
/// to a few tenths of a uT, while the expected field `R^T B` carries the attitude's error (a
/// degree is 0.9 uT of a 50 uT field; a flight controller's heading is good to a few degrees at
/// best) and the field model's. Regressing the reading on a regressor with that much error shrinks
/// each soft-iron column by the share of its spread the error makes up (attenuation), most where
/// the attitudes vary least (the vertical on a level flight), which skews the matrix; regressing
/// the expected field on the reading, the near error-free side, does not. With an exact attitude
/// (a simulation, motion capture) the two agree to the compass noise's share of the spread.
fn reverse(acc: &VectorAccumulator, fwd: &VectorFit) -> Result<VectorFit, VectorFailure> {
    let k = acc.reg.k;
    let f = acc.reg.field_ut;
    let o_ref = fwd.offset_ut;
    // u' = T u: the field regressors less o_ref / |B| times the constant.
    let mut t = DMatrix::<f64>::identity(k, k);
    for c in 0..3 {
        t[(c, OFFSET)] = -o_ref[c] / f;
    }
    // y' = h - (raw - o_ref) = y + o_ref.
    let sum_u = acc.nm_r.column(OFFSET).into_owned();
    let mut g = acc.g_r.clone();
    let mut yy = acc.yy_r;
    for j in 0..3 {
        let sum_y = acc.g_r[(OFFSET, j)];
        for r in 0..k {
            g[(r, j)] += sum_u[r] * o_ref[j];
        }
        yy[j] += 2.0 * o_ref[j] * sum_y + acc.nm_r[(OFFSET, OFFSET)] * o_ref[j] * o_ref[j];
    }
    // Scaled by the readings' own RMS strength about o_ref (not the expected field's), so a
    // combination's spread means the same share of the field as in the forward fit.
    let n = acc.nm_r[(OFFSET, OFFSET)];
    let sq: f64 = (0..3)
        .map(|c| {
            f * f * (acc.nm_r[(c, c)] - 2.0 * o_ref[c] / f * acc.nm_r[(c, OFFSET)])
                + n * o_ref[c] * o_ref[c]
        })
        .sum();
    let reading_ut = (sq / n.max(1e-12)).sqrt();
    if !(reading_ut.is_finite() && reading_ut > 0.0) {
        return Err(VectorFailure::Singular);
    }
    for c in 0..3 {
        for r in 0..k {
            t[(c, r)] *= f / reading_ut;
        }
    }
    let centred = VectorAccumulator {
        nm: &t * &acc.nm_r * t.transpose(),
        g: &t * g,
        yy,
        reg: Regressors {
            field_ut: reading_ut,
            ..acc.reg.clone()
        },
        ..acc.clone()
    };
    // Read as the forward fit: `soft_iron` is M, `offset` d, `current` k'.
    let r = solve(&centred)?;
    let m = crate::calib::model::rows_to_mat(&r.soft_iron);
    let a = m.try_inverse().ok_or(VectorFailure::Singular)?;
    let d = nalgebra::Vector3::from(r.offset_ut);
    let o = nalgebra::Vector3::from(o_ref) - a * d;
    // Uncertainties through A (close to the identity), the soft iron's as M's.
    let through_a = |sd: Vec3| -> Vec3 {
        let mut out = [0.0; 3];
        for (j, o) in out.iter_mut().enumerate() {
            *o = (0..3)
                .map(|c| (a[(j, c)] * sd[c]).powi(2))
                .sum::<f64>()
                .sqrt();
        }
        out
    };
    let current = r.current_ut_per_a.map(|kc| {
        let v = -(a * nalgebra::Vector3::from(kc));
        [v.x, v.y, v.z]
    });
    // What the attitudes determine is the forward fit's verdict (their spread, as the module
    // documents it); the values are the reverse fit's.
    Ok(VectorFit {
        offset_ut: [o.x, o.y, o.z],
        offset_sigma_ut: through_a(r.offset_sigma_ut),
        soft_iron: crate::calib::model::mat_to_rows(&a),
        matrix: crate::calib::model::mat_to_rows(&m),
        rotation_deg: polar_rotation_deg(&a),
        current_ut_per_a: current,
        current_sigma_ut_per_a: r.current_sigma_ut_per_a.map(through_a),
        field_ut: fwd.field_ut,
        offset_assumption_ut: fwd.offset_assumption_ut,
        offset_identifiable: fwd.offset_identifiable,
        soft_iron_fitted: fwd.soft_iron_fitted,
        current_identifiable: fwd.current_identifiable,
        directions: fwd.directions.clone(),
        ..r
    })
}

/// The rotation nearest `m` (Frobenius): `U diag(1, 1, det(U V^T)) V^T` of `m = U S V^T`.
fn nearest_rotation(m: &nalgebra::Matrix3<f64>) -> Option<nalgebra::Matrix3<f64>> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let d = (u * vt).determinant().signum();
    let r = u * nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, d)) * vt;
    r.iter().all(|x| x.is_finite()).then_some(r)
}

/// Angle of the rotation `U V^T` of `a = U S V^T` (the orthogonal factor of `a = R P`), deg.
fn polar_rotation_deg(a: &nalgebra::Matrix3<f64>) -> f64 {
    let svd = a.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return f64::NAN;
    };
    let r = u * vt;
    ((r.trace() - 1.0) / 2.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The earth field `b_ned` (uT) in body axes at the attitude `q_body_ned` (body -> NED): `R^T B`.
pub(crate) fn expected_field(q_body_ned: &nalgebra::UnitQuaternion<f64>, b_ned: &Vec3) -> Vec3 {
    let h = q_body_ned.inverse() * nalgebra::Vector3::from(*b_ned);
    [h.x, h.y, h.z]
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const B: Vec3 = [20.0, 1.5, 43.0];
    const A: [[f64; 3]; 3] = [[1.04, 0.02, -0.03], [0.01, 0.96, 0.02], [-0.02, 0.03, 1.02]];
    const O: Vec3 = [12.0, -25.0, 40.0];
    const K: Vec3 = [0.3, -0.2, 0.45];

    /// Readings at the given attitudes (roll, pitch, yaw deg) with noise `sd` uT and, with
    /// `current`, a current drawn in 0..60 A.
    fn points(att: &[[f64; 3]], sd: f64, current: bool, rng: &mut ChaCha8Rng) -> Vec<VectorPoint> {
        use rand_distr::Distribution;
        let a = crate::calib::model::rows_to_mat(&A);
        att.iter()
            .map(|e| {
                let q = crate::sim::quat_from_euler_deg(e[0], e[1], e[2]);
                let h = expected_field(&q, &B);
                let c = if current {
                    rng.random_range(0.0..60.0)
                } else {
                    0.0
                };
                let m = a * nalgebra::Vector3::from(h);
                let mut raw = [0.0; 3];
                for j in 0..3 {
                    let z: f64 = rand_distr::StandardNormal.sample(rng);
                    raw[j] = m[j] + O[j] + K[j] * c + sd * z;
                }
                VectorPoint {
                    raw_ut: raw,
                    expected_ut: h,
                    current_a: current.then_some(c),
                }
            })
            .collect()
    }

    fn sphere(n: usize, rng: &mut ChaCha8Rng) -> Vec<[f64; 3]> {
        (0..n)
            .map(|_| {
                [
                    rng.random_range(-180.0..180.0),
                    rng.random_range(-90.0..90.0),
                    rng.random_range(0.0..360.0),
                ]
            })
            .collect()
    }

    /// The rotation matrices of attitudes given as Euler angles, deg.
    fn rotations_of(att: &[[f64; 3]]) -> Vec<nalgebra::Matrix3<f64>> {
        att.iter()
            .map(|e| {
                crate::sim::quat_from_euler_deg(e[0], e[1], e[2])
                    .to_rotation_matrix()
                    .into_inner()
            })
            .collect()
    }

    /// The attitudes' turn spread from the sums, against `1 - cos theta` reading by reading.
    fn turn_spread_of(att: &[[f64; 3]]) -> (f64, f64) {
        let rots = rotations_of(att);
        let sums = AttitudeSums::new(rots.iter().map(|r| (nalgebra::Vector3::zeros(), *r)));
        let mean = rots.iter().sum::<nalgebra::Matrix3<f64>>() / rots.len() as f64;
        let r0 = nearest_rotation(&mean).unwrap();
        let direct = (rots
            .iter()
            .map(|r| (1.0 - ((r0.transpose() * r).trace() - 1.0) / 2.0).powi(2))
            .sum::<f64>()
            / rots.len() as f64)
            .sqrt();
        (sums.turn_spread().unwrap(), direct)
    }

    #[test]
    fn a_barely_turning_set_has_a_small_turn_spread_and_a_tumble_a_large_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let small: Vec<[f64; 3]> = (0..500)
            .map(|_| {
                [
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    30.0 + rng.random_range(-3.0..3.0),
                ]
            })
            .collect();
        let (s, direct) = turn_spread_of(&small);
        eprintln!("turn spread of a few degrees: {s:.5}");
        // Measured 0.0015: turns of a few degrees.
        assert!(s < 0.005, "{s}");
        assert!((s - direct).abs() < 1e-9, "{s} {direct}");
        // Such a set leaves the offset undetermined in the full fit too.
        let pts = points(&small, 0.1, false, &mut rng);
        let f = fit(&pts, false).unwrap();
        assert!(!f.offset_identifiable, "{}", f.offset_assumption_ut);
        let tumble = sphere(500, &mut rng);
        let (s, direct) = turn_spread_of(&tumble);
        eprintln!("turn spread of a tumble: {s:.3}");
        // Measured 1.56 (a tumble: turns of 90 deg and more from the mean attitude).
        assert!(s > 0.5, "{s}");
        assert!((s - direct).abs() < 1e-9, "{s} {direct}");
    }

    #[test]
    fn the_half_summed_products_are_the_full_sums_to_the_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let att = sphere(700, &mut rng);
        let rots = rotations_of(&att);
        let raws: Vec<nalgebra::Vector3<f64>> = sphere(700, &mut rng)
            .iter()
            .map(|v| nalgebra::Vector3::new(40.0 * v[0] + 3.0, 40.0 * v[1] - 7.0, 40.0 * v[2]))
            .collect();
        let sums = AttitudeSums::new(raws.iter().copied().zip(rots.iter().copied()));
        // Every product summed in full, in the same order.
        let mut rr = nalgebra::SMatrix::<f64, 9, 9>::zeros();
        for r in &rots {
            for i in 0..9 {
                for j in 0..9 {
                    rr[(i, j)] += r[(i / 3, i % 3)] * r[(j / 3, j % 3)];
                }
            }
        }
        assert_eq!(sums.totals.rr, rr);
        // Readings taken out again, as the outlier cut does.
        let mut s = sums.totals.clone();
        for k in (0..rots.len()).step_by(7) {
            s.add_upper(&rots[k], &raws[k], -1.0);
            for i in 0..9 {
                for j in 0..9 {
                    rr[(i, j)] += -rots[k][(i / 3, i % 3)] * rots[k][(j / 3, j % 3)];
                }
            }
        }
        s.mirror();
        assert_eq!(s.rr, rr);
    }

    #[test]
    fn the_sums_give_the_fit_of_the_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let att = sphere(1500, &mut rng);
        let mut pts = points(&att, 0.3, false, &mut rng);
        // A few wild readings, so the outlier cut takes some out.
        for p in pts.iter_mut().step_by(100) {
            p.raw_ut[0] += 30.0;
        }
        let rots = rotations_of(&att);
        let sums = AttitudeSums::new(
            pts.iter()
                .zip(&rots)
                .map(|(p, r)| (nalgebra::Vector3::from(p.raw_ut), *r)),
        );
        let b = nalgebra::Vector3::from(B);
        // The points' expected field is R^T B.
        assert!(rots
            .iter()
            .zip(&pts)
            .all(
                |(r, p)| (r.transpose() * b - nalgebra::Vector3::from(p.expected_ut)).amax() < 1e-9
            ));
        let (direct, summed) = (fit(&pts, false).unwrap(), sums.fit(&b).unwrap());
        assert_eq!(direct.outliers_rejected, 15);
        assert_eq!(summed.outliers_rejected, direct.outliers_rejected);
        assert_eq!(summed.points, direct.points);
        // Rounding apart: measured 1e-12 uT.
        for j in 0..3 {
            assert!(
                (summed.offset_ut[j] - direct.offset_ut[j]).abs() < 1e-9,
                "{summed:?}"
            );
            for c in 0..3 {
                assert!((summed.matrix[j][c] - direct.matrix[j][c]).abs() < 1e-11);
            }
        }
        assert!((summed.rms_residual_ut - direct.rms_residual_ut).abs() < 1e-9);
        // The mean of R m (raw - o) over the readings.
        let (m, o) = (
            nalgebra::Matrix3::new(1.1, 0.1, 0.0, -0.05, 0.9, 0.02, 0.0, 0.03, 1.0),
            nalgebra::Vector3::new(3.0, -2.0, 1.0),
        );
        let mean = pts
            .iter()
            .zip(&rots)
            .map(|(p, r)| r * (m * (nalgebra::Vector3::from(p.raw_ut) - o)))
            .sum::<nalgebra::Vector3<f64>>()
            / pts.len() as f64;
        assert!((sums.mean_ned(&m, &o) - mean).amax() < 1e-9);
    }

    #[test]
    fn everything_recovered_from_attitudes_over_the_sphere() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let att = sphere(2000, &mut rng);
        let f = fit(&points(&att, 0.2, true, &mut rng), true).unwrap();
        assert!(
            f.directions.iter().all(|d| d.identifiable),
            "{:?}",
            f.directions
        );
        assert!(f.offset_identifiable && f.offset_assumption_ut == 0.0);
        assert_eq!(f.soft_iron_fitted, [true; 3]);
        assert_eq!(f.current_identifiable, Some(true));
        let k = f.current_ut_per_a.unwrap();
        let ks = f.current_sigma_ut_per_a.unwrap();
        for j in 0..3 {
            // Within 4 of their own sigmas (measured: 0.0087 uT for the offset).
            assert!(
                (f.offset_ut[j] - O[j]).abs() < 4.0 * f.offset_sigma_ut[j],
                "{f:?}"
            );
            assert!(f.offset_sigma_ut[j] < 0.03, "{:?}", f.offset_sigma_ut);
            assert!((k[j] - K[j]).abs() < 4.0 * ks[j], "{k:?} {ks:?}");
            for c in 0..3 {
                assert!((f.soft_iron[j][c] - A[j][c]).abs() < 4.0 * f.soft_iron_sigma[j][c]);
            }
        }
        assert!(
            (f.rms_residual_ut - 0.2).abs() < 0.02,
            "{}",
            f.rms_residual_ut
        );
        // matrix is the inverse of the soft iron.
        let p = crate::calib::model::rows_to_mat(&f.matrix)
            * crate::calib::model::rows_to_mat(&f.soft_iron);
        assert!((p - nalgebra::Matrix3::identity()).norm() < 1e-9);
    }

    #[test]
    fn level_yaw_only_names_offset_against_the_body_z_soft_iron() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let att: Vec<[f64; 3]> = (0..1000).map(|i| [0.0, 0.0, i as f64 * 0.36]).collect();
        let f = fit(&points(&att, 0.2, false, &mut rng), false).unwrap();
        let un: Vec<&Direction> = f.unidentified().collect();
        assert_eq!(un.len(), 1, "{:?}", f.directions);
        assert!(un[0].spread < 1e-6, "{}", un[0].spread);
        let d = &un[0].description;
        assert!(
            d.contains("offset") && d.contains("soft iron (body-z field)"),
            "{d}"
        );
        assert_eq!(f.soft_iron_fitted, [true, true, false]);
        // Held at the identity; the offset then carries the z column's error (A_jz - I_jz) B_z,
        // so it is named as an assumption: SOFT_IRON_PRIOR x B_down = 0.05 x 43 uT = 2.15 uT.
        for j in 0..3 {
            let nominal = if j == 2 { 1.0 } else { 0.0 };
            // Held along the unidentified direction, which the readings' noise turns slightly
            // (measured within 0.0015).
            assert!(
                (f.soft_iron[j][2] - nominal).abs() < 0.005,
                "{:?}",
                f.soft_iron
            );
        }
        assert!(!f.offset_identifiable);
        assert!(
            (f.offset_assumption_ut - 2.15).abs() < 1e-6,
            "{}",
            f.offset_assumption_ut
        );
        // The horizontal columns are determined.
        assert!(
            (f.soft_iron[0][0] - A[0][0]).abs() < 0.005,
            "{:?}",
            f.soft_iron
        );
        assert!(
            (f.soft_iron[1][1] - A[1][1]).abs() < 0.005,
            "{:?}",
            f.soft_iron
        );
    }

    #[test]
    fn a_turned_reference_shows_as_the_rotation_within_the_soft_iron() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let att = sphere(1000, &mut rng);
        let f0 = fit(&points(&att, 0.2, false, &mut rng), false).unwrap();
        // The truth's A is not quite symmetric (0.01-0.02 off the diagonal): measured 0.51 deg.
        assert!(f0.rotation_deg < 1.5, "{}", f0.rotation_deg);
        // The compass mounted turned 10 deg in yaw against the attitude's body frame: the
        // readings stay, the expected field is the one of a body turned by -10 deg.
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 10f64.to_radians());
        let mut p = points(&att, 0.2, false, &mut rng);
        for (x, e) in p.iter_mut().zip(&att) {
            let q0 = crate::sim::quat_from_euler_deg(e[0], e[1], e[2]);
            x.expected_ut = expected_field(&(q0 * q), &B);
        }
        let f = fit(&p, false).unwrap();
        // Measured 9.71 deg (the truth's own turn on top).
        assert!((f.rotation_deg - 10.0).abs() < 1.0, "{}", f.rotation_deg);
        // The offset does not depend on the frame.
        for j in 0..3 {
            assert!((f.offset_ut[j] - O[j]).abs() < 0.1, "{:?}", f.offset_ut);
        }
    }

    #[test]
    fn constant_current_is_not_identifiable() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let att = sphere(500, &mut rng);
        let mut p = points(&att, 0.2, false, &mut rng);
        for x in p.iter_mut() {
            x.current_a = Some(20.0);
        }
        let f = fit(&p, true).unwrap();
        assert_eq!(f.current_identifiable, Some(false));
        assert!(f.unidentified().any(|d| d.description.contains("current")));
    }

    #[test]
    fn outliers_left_out_bad_points_skipped_too_few_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let att = sphere(400, &mut rng);
        let mut p = points(&att, 0.2, false, &mut rng);
        for x in p.iter_mut().step_by(40) {
            x.raw_ut[1] += 30.0;
        }
        p[1].raw_ut[0] = f64::NAN;
        p[2].expected_ut[2] = f64::INFINITY;
        let f = fit(&p, false).unwrap();
        assert_eq!(f.outliers_rejected, 10);
        assert_eq!(f.points, 388);
        for j in 0..3 {
            assert!((f.offset_ut[j] - O[j]).abs() < 0.1, "{:?}", f.offset_ut);
        }
        assert_eq!(
            fit(&p[..40], false).unwrap_err(),
            VectorFailure::NotEnoughPoints {
                have: 38,
                need: MIN_POINTS
            }
        );
        // Current asked for, none logged: no point usable.
        assert!(matches!(
            fit(&p, true),
            Err(VectorFailure::NotEnoughPoints { have: 0, .. })
        ));
    }
}
