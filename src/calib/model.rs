//! Calibration models as pure functions: `apply` is separate from fitting (x-io Fusion style).
//!
//! Every model has the report's form `calibrated = M (raw - o)`: `o` is the hard-iron / bias offset in raw
//! units, `M` the 3x3 correction. The models differ in which entries of `M` are free:
//!
//! | model    | free parameters                                       | count |
//! |----------|-------------------------------------------------------|-------|
//! | `sphere` | offset, one scale (M = a I)                           | 4     |
//! | `diag6`  | offset, per-axis scale (Ren and Liu eq. 5-6; Camps et al.) | 6 |
//! | `sym9`   | offset, symmetric M (ArduPilot DIA/ODI, PX4)          | 9     |
//! | `full12` | offset, full M = R S, R fixed by a second reference   | 12    |
//!
//! Ren and Liu, "Calibration of MEMS Accelerometers and Magnetometers for Rotor UAV Attitude
//! Estimation"; Camps, Harasse and Monin, "Numerical calibration for 3-axis accelerometers and
//! magnetometers" (2009).
//!
//! Norm-only data (|M (raw - o)| = const) determine M only up to a rotation on the left, so `full12`
//! cannot come from norms alone: for the magnetometer the rotation is fixed by the gravity-field angle
//! (dip) against the calibrated accelerometer at static poses; for the accelerometer by the convention
//! that it defines the body frame (upper-triangular M, as imu_tk).

use crate::types::Vec3;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// The 3x3 identity (no soft iron, no scale).
pub(crate) const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Which model a calibration uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    Sphere,
    Diag6,
    Sym9,
    Full12,
}

impl ModelKind {
    /// Number of free parameters, offset included.
    pub(crate) fn n_params(self) -> usize {
        match self {
            ModelKind::Sphere => 4,
            ModelKind::Diag6 => 6,
            ModelKind::Sym9 => 9,
            ModelKind::Full12 => 12,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Sphere => "sphere",
            ModelKind::Diag6 => "diag6",
            ModelKind::Sym9 => "sym9",
            ModelKind::Full12 => "full12",
        }
    }
    pub fn parse(s: &str) -> Option<ModelKind> {
        match s {
            "sphere" => Some(ModelKind::Sphere),
            "diag6" => Some(ModelKind::Diag6),
            "sym9" => Some(ModelKind::Sym9),
            "full12" | "12" => Some(ModelKind::Full12),
            _ => None,
        }
    }
}

/// The model a calibration result names (`calibration.*.model` in the report): one of the norm
/// models, or how the result was made when it is not one (`six_position`, `planar`), or `auto`
/// when nothing was fitted under the automatic choice. Read back from a file, a name this build
/// does not know reads as `full12`, which applies the stored matrix as it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CalModel {
    /// Nothing fitted; the automatic choice was asked.
    Auto,
    Sphere,
    Diag6,
    Sym9,
    Full12,
    /// Six static poses near the axes (accelerometer).
    SixPosition,
    /// The horizontal-plane fit of a ground vehicle ([`crate::calib::planar`]).
    Planar,
}

impl CalModel {
    /// The name in the report and the files.
    pub fn name(self) -> &'static str {
        match self {
            CalModel::Auto => "auto",
            CalModel::SixPosition => "six_position",
            CalModel::Planar => "planar",
            m => m.kind().name(),
        }
    }

    /// The model from its name; `None` for a name this build does not know.
    pub fn parse(s: &str) -> Option<CalModel> {
        match s {
            "auto" => Some(CalModel::Auto),
            "six_position" => Some(CalModel::SixPosition),
            "planar" => Some(CalModel::Planar),
            _ => ModelKind::parse(s).map(CalModel::from),
        }
    }

    /// The norm model whose `apply` the result's matrix and offset take: its own, else full12
    /// (the stored matrix as it is).
    pub fn kind(self) -> ModelKind {
        match self {
            CalModel::Sphere => ModelKind::Sphere,
            CalModel::Diag6 => ModelKind::Diag6,
            CalModel::Sym9 => ModelKind::Sym9,
            CalModel::Full12 | CalModel::Auto | CalModel::SixPosition | CalModel::Planar => {
                ModelKind::Full12
            }
        }
    }
}

impl From<ModelKind> for CalModel {
    fn from(k: ModelKind) -> CalModel {
        match k {
            ModelKind::Sphere => CalModel::Sphere,
            ModelKind::Diag6 => CalModel::Diag6,
            ModelKind::Sym9 => CalModel::Sym9,
            ModelKind::Full12 => CalModel::Full12,
        }
    }
}

impl std::fmt::Display for CalModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Serialize for CalModel {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for CalModel {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<CalModel, D::Error> {
        let name = String::deserialize(d)?;
        Ok(CalModel::parse(&name).unwrap_or(CalModel::Full12))
    }
}

/// A calibration: `calibrated = matrix * (raw - offset)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub model: ModelKind,
    /// Offset in raw units (hard iron for mag, bias for accel).
    pub offset: Vec3,
    /// Row-major correction matrix.
    pub matrix: [[f64; 3]; 3],
}

impl Calibration {
    /// The identity calibration (no correction).
    pub fn identity() -> Self {
        Calibration {
            model: ModelKind::Sphere,
            offset: [0.0; 3],
            matrix: mat_to_rows(&Matrix3::identity()),
        }
    }

    /// Apply to one raw vector.
    #[inline]
    pub fn apply(&self, raw: &Vec3) -> Vec3 {
        let m = &self.matrix;
        let v = [
            raw[0] - self.offset[0],
            raw[1] - self.offset[1],
            raw[2] - self.offset[2],
        ];
        [
            m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
            m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
            m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
        ]
    }

    pub(crate) fn matrix3(&self) -> Matrix3<f64> {
        rows_to_mat(&self.matrix)
    }

    /// Matrix divided by cbrt(det): the shape of the correction without its overall scale.
    pub fn normalised_matrix(&self) -> Matrix3<f64> {
        let m = self.matrix3();
        let d = m.determinant();
        m / d.abs().cbrt()
    }
}

pub fn rows_to_mat(r: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::new(
        r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
    )
}

pub fn mat_to_rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ]
}

/// Parameter vector layout used by the fitter for norm-only models:
/// `[p0, p1, p2, a...]`, where the calibrated vector is `u = A (x - p)` and the residual `|u| - 1`.
/// `A` is built from the `a` entries by the model:
/// sphere `[a]`, diag6 `[a11 a22 a33]`, sym9 `[a11 a22 a33 a12 a13 a23]`,
/// full12 (upper triangular) `[a11 a22 a33 a12 a13 a23]` with a21 = a31 = a32 = 0.
pub(crate) fn a_from_params(kind: ModelKind, a: &[f64]) -> Matrix3<f64> {
    match kind {
        ModelKind::Sphere => Matrix3::identity() * a[0],
        ModelKind::Diag6 => Matrix3::from_diagonal(&Vector3::new(a[0], a[1], a[2])),
        ModelKind::Sym9 => Matrix3::new(a[0], a[3], a[4], a[3], a[1], a[5], a[4], a[5], a[2]),
        ModelKind::Full12 => Matrix3::new(a[0], a[3], a[4], 0.0, a[1], a[5], 0.0, 0.0, a[2]),
    }
}

/// Inverse of [`a_from_params`]: the model's entries of a matrix (off-model entries are dropped).
pub(crate) fn params_from_a(kind: ModelKind, m: &Matrix3<f64>) -> Vec<f64> {
    match kind {
        ModelKind::Sphere => vec![m.trace() / 3.0],
        ModelKind::Diag6 => vec![m[(0, 0)], m[(1, 1)], m[(2, 2)]],
        ModelKind::Sym9 => vec![
            m[(0, 0)],
            m[(1, 1)],
            m[(2, 2)],
            0.5 * (m[(0, 1)] + m[(1, 0)]),
            0.5 * (m[(0, 2)] + m[(2, 0)]),
            0.5 * (m[(1, 2)] + m[(2, 1)]),
        ],
        ModelKind::Full12 => vec![
            m[(0, 0)],
            m[(1, 1)],
            m[(2, 2)],
            m[(0, 1)],
            m[(0, 2)],
            m[(1, 2)],
        ],
    }
}

/// Number of fitted parameters for the norm-only fit (the rotation of `full12` is not among them).
pub(crate) fn n_norm_params(kind: ModelKind) -> usize {
    3 + match kind {
        ModelKind::Sphere => 1,
        ModelKind::Diag6 => 3,
        ModelKind::Sym9 | ModelKind::Full12 => 6,
    }
}

/// Residual `|A (x - p)| - 1` and its gradient with respect to the parameter vector
/// (`grad` must have length `n_norm_params(kind)`). Returns the residual.
#[inline]
pub fn norm_residual_grad(kind: ModelKind, params: &[f64], x: &Vec3, grad: &mut [f64]) -> f64 {
    let a = a_from_params(kind, &params[3..]);
    norm_residual_grad_with(kind, &a, &a.transpose(), params, x, grad)
}

/// [`norm_residual_grad`] with `A` (from `params`) and its transpose already built.
#[inline]
pub fn norm_residual_grad_with(
    kind: ModelKind,
    a: &Matrix3<f64>,
    at: &Matrix3<f64>,
    params: &[f64],
    x: &Vec3,
    grad: &mut [f64],
) -> f64 {
    let v = Vector3::new(x[0] - params[0], x[1] - params[1], x[2] - params[2]);
    let u = a * v;
    let n = u.norm().max(1e-300);
    let inv = 1.0 / n;
    let gp = -(at * u) * inv;
    grad[0] = gp[0];
    grad[1] = gp[1];
    grad[2] = gp[2];
    // d|u|/dA_jk = u_j v_k / n
    let d = |j: usize, k: usize| u[j] * v[k] * inv;
    match kind {
        ModelKind::Sphere => grad[3] = (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]) * inv,
        ModelKind::Diag6 => {
            grad[3] = d(0, 0);
            grad[4] = d(1, 1);
            grad[5] = d(2, 2);
        }
        ModelKind::Sym9 => {
            grad[3] = d(0, 0);
            grad[4] = d(1, 1);
            grad[5] = d(2, 2);
            grad[6] = d(0, 1) + d(1, 0);
            grad[7] = d(0, 2) + d(2, 0);
            grad[8] = d(1, 2) + d(2, 1);
        }
        ModelKind::Full12 => {
            grad[3] = d(0, 0);
            grad[4] = d(1, 1);
            grad[5] = d(2, 2);
            grad[6] = d(0, 1);
            grad[7] = d(0, 2);
            grad[8] = d(1, 2);
        }
    }
    n - 1.0
}

/// Rotation matrix from a rotation vector (axis * angle, rad).
pub fn rotation_from_vector(w: &Vector3<f64>) -> Matrix3<f64> {
    *nalgebra::Rotation3::new(*w).matrix()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_jacobian(kind: ModelKind) {
        let params: Vec<f64> = match kind {
            ModelKind::Sphere => vec![0.1, -0.2, 0.3, 1.1],
            ModelKind::Diag6 => vec![0.1, -0.2, 0.3, 1.1, 0.9, 1.05],
            _ => vec![0.1, -0.2, 0.3, 1.1, 0.9, 1.05, 0.03, -0.02, 0.05],
        };
        let xs = [[1.0, 0.2, -0.3], [-0.5, 0.8, 0.4], [0.1, -0.9, 0.6]];
        for x in xs.iter() {
            let mut g = vec![0.0; params.len()];
            norm_residual_grad(kind, &params, x, &mut g);
            for i in 0..params.len() {
                let h = 1e-6;
                let mut pp = params.clone();
                pp[i] += h;
                let mut pm = params.clone();
                pm[i] -= h;
                let mut scratch = vec![0.0; params.len()];
                let rp = norm_residual_grad(kind, &pp, x, &mut scratch);
                let rm = norm_residual_grad(kind, &pm, x, &mut scratch);
                let num = (rp - rm) / (2.0 * h);
                assert!(
                    (num - g[i]).abs() < 1e-7,
                    "{kind:?} param {i}: analytic {} numeric {}",
                    g[i],
                    num
                );
            }
        }
    }

    #[test]
    fn jacobian_sphere() {
        check_jacobian(ModelKind::Sphere)
    }
    #[test]
    fn jacobian_diag6() {
        check_jacobian(ModelKind::Diag6)
    }
    #[test]
    fn jacobian_sym9() {
        check_jacobian(ModelKind::Sym9)
    }
    #[test]
    fn jacobian_full12() {
        check_jacobian(ModelKind::Full12)
    }

    #[test]
    fn apply_is_matrix_times_raw_minus_offset() {
        let c = Calibration {
            model: ModelKind::Sym9,
            offset: [1.0, 2.0, 3.0],
            matrix: [[2.0, 0.0, 0.0], [0.0, 1.0, 0.5], [0.0, 0.5, 1.0]],
        };
        assert_eq!(c.apply(&[2.0, 2.0, 5.0]), [2.0, 1.0, 2.0]);
    }
}
