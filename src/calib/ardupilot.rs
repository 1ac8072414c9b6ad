//! ArduPilot's compass correction, in one place: its parameter names, the matrix it builds from
//! them, the scale bounds, applying and undoing it, and the map between it and imucald's model.
//! Pure math and names; the readers of telemetry and logs (`io::ardupilot`, `io::flightlog`),
//! the parameter writer (`io::mavout`) and the parameter files ([`crate::calib::export`]) use it.
//!
//! Convention (ArduPilot's `AP_Compass_Backend::correct_field`): for compass k the field it logs
//! and streams, in mGauss, is
//!
//! `mag = S (scale (raw + OFS)) + MOT`
//!
//! * OFS = COMPASS_OFS{,2,3}_X/Y/Z, mGauss, **added**;
//! * scale = COMPASS_SCALE{,2,3}, applied only within [`SCALE_RANGE`] (1/1.5 to 1.5), else 1
//!   (its default 0 is "none");
//! * S the symmetric soft-iron matrix [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z],
//!   [ODI_Y, ODI_Z, DIA_Z]] of COMPASS_DIA{,2,3}_X/Y/Z and COMPASS_ODI{,2,3}_X/Y/Z, a DIA of all
//!   zeros read as 1 on each axis ([`soft_iron`]);
//! * MOT the motor term (COMPASS_MOT{,2,3}_X/Y/Z times throttle or current, COMPASS_MOTCT), added
//!   after S.
//!
//! imucald's model is `calibrated = M (raw - offset)` in uT (1 uT = 10 mGauss, [`MGAUSS_PER_UT`]),
//! so ArduPilot's correction is offset = -OFS / 10 uT and M = scale S ([`Correction::model`]),
//! and a calibration is written as OFS = -10 offset, S = the symmetric part of M
//! ([`Correction::from_model`], [`Correction::params`]). ArduPilot keeps a calibration for three
//! compasses ([`COMPASSES`]); a compass index beyond them has no parameter names (`None`).

use crate::types::Vec3;
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;

/// Compasses ArduPilot keeps a calibration for (COMPASS_OFS, COMPASS_OFS2, COMPASS_OFS3).
pub(crate) const COMPASSES: u8 = 3;

/// ArduPilot applies COMPASS_SCALE only within these bounds (COMPASS_MIN/MAX_SCALE_FACTOR).
pub(crate) const SCALE_RANGE: (f64, f64) = (1.0 / 1.5, 1.5);

/// mGauss (ArduPilot's unit) per uT (imucald's).
pub(crate) const MGAUSS_PER_UT: f64 = 10.0;

/// The axis letters of the three-axis parameters, in order.
pub(crate) const AXES: [&str; 3] = ["X", "Y", "Z"];

/// The motor compensation type, one for all compasses (2: current-based, mGauss/A).
pub(crate) const MOTCT: &str = "COMPASS_MOTCT";

/// A three-axis parameter of one compass (`COMPASS_OFS2_X` ...).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Triple {
    /// COMPASS_OFS: hard-iron offsets, mGauss, added.
    Ofs,
    /// COMPASS_DIA: the soft-iron matrix's diagonal.
    Dia,
    /// COMPASS_ODI: the soft-iron matrix's off-diagonal (xy, xz, yz).
    Odi,
    /// COMPASS_MOT: motor compensation, mGauss per unit of COMPASS_MOTCT's measure.
    Mot,
}

impl Triple {
    fn base(self) -> &'static str {
        match self {
            Triple::Ofs => "OFS",
            Triple::Dia => "DIA",
            Triple::Odi => "ODI",
            Triple::Mot => "MOT",
        }
    }
}

/// A single-valued parameter of one compass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Single {
    /// COMPASS_SCALE{,2,3}: see [`SCALE_RANGE`].
    Scale,
    /// COMPASS_ORIENT{,2,3}: the mounting rotation.
    Orient,
    /// COMPASS_DEV_ID{,2,3}: the device the calibration belongs to.
    DevId,
    /// COMPASS_EXTERNAL, COMPASS_EXTERN2, COMPASS_EXTERN3.
    External,
    /// COMPASS_USE{,2,3}.
    Use,
}

/// The parameter suffix of compass k: `COMPASS_OFS_X`, `COMPASS_OFS2_X`, `COMPASS_OFS3_X`.
pub(crate) fn suffix(k: u8) -> Option<&'static str> {
    ["", "2", "3"].get(k as usize).copied()
}

/// The X, Y, Z names of compass k's parameter `t`: `triple(Triple::Ofs, 1)` is
/// `COMPASS_OFS2_X/Y/Z`.
pub(crate) fn triple(t: Triple, k: u8) -> Option<[String; 3]> {
    let s = suffix(k)?;
    Some(AXES.map(|a| format!("COMPASS_{}{s}_{a}", t.base())))
}

/// The name of compass k's parameter `p`: `single(Single::Scale, 2)` is `COMPASS_SCALE3`.
pub fn single(p: Single, k: u8) -> Option<String> {
    let s = suffix(k)?;
    Some(match p {
        Single::External if k == 0 => "COMPASS_EXTERNAL".into(),
        Single::External => format!("COMPASS_EXTERN{s}"),
        Single::Scale => format!("COMPASS_SCALE{s}"),
        Single::Orient => format!("COMPASS_ORIENT{s}"),
        Single::DevId => format!("COMPASS_DEV_ID{s}"),
        Single::Use => format!("COMPASS_USE{s}"),
    })
}

/// The parameters [`correction`] reads for compass k, in `correct_field` order: OFS X Y Z,
/// DIA X Y Z, ODI X Y Z, then SCALE.
pub(crate) fn correction_names(k: u8) -> Option<[String; 10]> {
    let [o, d, i] = [Triple::Ofs, Triple::Dia, Triple::Odi].map(|t| triple(t, k));
    let names: Vec<String> = [o?, d?, i?]
        .into_iter()
        .flatten()
        .chain([single(Single::Scale, k)?])
        .collect();
    names.try_into().ok()
}

/// Compass k's parameters that describe it: OFS, DIA, ODI, MOT, orientation, device id, external,
/// scale and use (empty beyond [`COMPASSES`]).
pub(crate) fn param_names(k: u8) -> Vec<String> {
    let triples = [Triple::Ofs, Triple::Dia, Triple::Odi, Triple::Mot]
        .into_iter()
        .filter_map(|t| triple(t, k))
        .flatten();
    let singles = [
        Single::Orient,
        Single::DevId,
        Single::External,
        Single::Scale,
        Single::Use,
    ]
    .into_iter()
    .filter_map(|p| single(p, k));
    triples.chain(singles).collect()
}

/// Compass k's device id (COMPASS_DEV_ID{,2,3}), when set.
pub(crate) fn dev_id(params: &BTreeMap<String, f64>, k: u8) -> Option<u32> {
    params
        .get(&single(Single::DevId, k)?)
        .filter(|v| **v > 0.0 && **v < u32::MAX as f64)
        .map(|v| *v as u32)
}

/// The symmetric matrix of diagonal `d` and off-diagonal (xy, xz, yz) `o`: ArduPilot's
/// DIA/ODI layout, which PX4's CAL_MAGn_[XYZ]SCALE / [XYZ]ODIAG share.
pub fn symmetric(d: [f64; 3], o: [f64; 3]) -> Matrix3<f64> {
    Matrix3::new(d[0], o[0], o[1], o[0], d[1], o[2], o[1], o[2], d[2])
}

/// The diagonal and off-diagonal (xy, xz, yz) of the symmetric part of `m` (rows): the inverse
/// of [`symmetric`] for a symmetric matrix.
pub(crate) fn diagonal_off_diagonal(m: &[[f64; 3]; 3]) -> ([f64; 3], [f64; 3]) {
    let sym = |i: usize, j: usize| 0.5 * (m[i][j] + m[j][i]);
    (
        [m[0][0], m[1][1], m[2][2]],
        [sym(0, 1), sym(0, 2), sym(1, 2)],
    )
}

/// ArduPilot's soft-iron matrix from COMPASS_DIA `dia` and COMPASS_ODI `odi`: a DIA of all zeros
/// (never calibrated) reads as 1 on each axis.
pub fn soft_iron(dia: [f64; 3], odi: [f64; 3]) -> Matrix3<f64> {
    let d = if dia.iter().all(|d| *d == 0.0) {
        [1.0; 3]
    } else {
        dia
    };
    symmetric(d, odi)
}

/// COMPASS_SCALE as ArduPilot applies it: `scale` within [`SCALE_RANGE`], else 1.
pub(crate) fn applied_scale(scale: Option<f64>) -> f64 {
    match scale {
        Some(v) if (SCALE_RANGE.0..=SCALE_RANGE.1).contains(&v) => v,
        _ => 1.0,
    }
}

/// ArduPilot's correction of one compass, as it applies it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correction {
    /// COMPASS_OFS, mGauss.
    pub ofs_mg: [f64; 3],
    /// The soft-iron matrix S from COMPASS_DIA/ODI ([`soft_iron`]).
    pub s: Matrix3<f64>,
    /// COMPASS_SCALE as applied ([`applied_scale`]).
    pub scale: f64,
}

impl Correction {
    /// Offsets only (S identity, scale 1).
    pub(crate) fn offsets_only(ofs_mg: [f64; 3]) -> Correction {
        Correction {
            ofs_mg,
            s: Matrix3::identity(),
            scale: 1.0,
        }
    }

    /// The correction that makes imucald's calibration (offset uT, matrix rows; calibrated =
    /// matrix (raw - offset)): OFS = -10 offset, S = the symmetric part of the matrix, scale 1.
    /// An asymmetric matrix is not representable; its symmetric part is taken.
    pub(crate) fn from_model(offset_ut: &Vec3, matrix: &[[f64; 3]; 3]) -> Correction {
        let (d, o) = diagonal_off_diagonal(matrix);
        Correction {
            ofs_mg: offset_ut.map(|x| -x * MGAUSS_PER_UT),
            s: symmetric(d, o),
            scale: 1.0,
        }
    }

    /// In imucald's model: (offset uT, matrix rows), calibrated = matrix (raw - offset) in uT.
    pub fn model(&self) -> (Vec3, [[f64; 3]; 3]) {
        (
            self.ofs_mg.map(|o| -o / MGAUSS_PER_UT),
            crate::calib::model::mat_to_rows(&(self.s * self.scale)),
        )
    }

    /// ArduPilot's forward correction (raw uT in, corrected mGauss out, no motor term).
    pub fn apply(&self, raw_ut: Vec3) -> Vec3 {
        let m = Vector3::from(raw_ut) * MGAUSS_PER_UT + Vector3::from(self.ofs_mg);
        let c = self.s * m * self.scale;
        [c.x, c.y, c.z]
    }

    /// The raw field (uT) behind a corrected one (mGauss) with the motor term `mot_mg` removed:
    /// raw = (S^-1 (mag - MOT)) / scale - OFS. `None` when S is singular or a value not finite.
    pub(crate) fn undo(&self, mag_mg: Vec3, mot_mg: Option<Vec3>) -> Option<Vec3> {
        let inv = self.s.try_inverse()?;
        let c = Vector3::from(mag_mg) - Vector3::from(mot_mg.unwrap_or([0.0; 3]));
        let u = inv * c / self.scale;
        let raw = [0, 1, 2].map(|i| (u[i] - self.ofs_mg[i]) / MGAUSS_PER_UT);
        raw.iter().all(|x| x.is_finite()).then_some(raw)
    }

    /// COMPASS_DIA and COMPASS_ODI (xy, xz, yz) that make this correction with COMPASS_SCALE unset
    /// (0, its default) or 1: the symmetric part of scale S.
    pub(crate) fn dia_odi(&self) -> ([f64; 3], [f64; 3]) {
        diagonal_off_diagonal(&crate::calib::model::mat_to_rows(&(self.s * self.scale)))
    }

    /// Compass k's parameters that make this correction with COMPASS_SCALE unset (0, its default)
    /// or 1 ([`Correction::dia_odi`]), in `correct_field` order: OFS X Y Z, DIA X Y Z,
    /// ODI X Y Z (COMPASS_SCALE left as the vehicle has it). `None` beyond [`COMPASSES`].
    pub fn params(&self, k: u8) -> Option<Vec<(String, f64)>> {
        let names = correction_names(k)?;
        let (d, o) = self.dia_odi();
        let values = self.ofs_mg.into_iter().chain(d).chain(o);
        Some(names.into_iter().zip(values).collect())
    }
}

/// Compass k's correction from its parameters. COMPASS_OFS is needed; COMPASS_DIA/ODI/SCALE
/// missing are taken as ArduPilot's defaults (none) only when `absent_is_default` (the whole
/// parameter list is known, so a missing one is missing from the firmware), else `None`; so is a
/// value that is not finite.
pub fn correction(
    params: &BTreeMap<String, f64>,
    k: u8,
    absent_is_default: bool,
) -> Option<Correction> {
    let names = correction_names(k)?;
    if names
        .iter()
        .any(|n| params.get(n).is_some_and(|v| !v.is_finite()))
    {
        return None;
    }
    let get3 = |t: Triple| -> Option<[f64; 3]> {
        let [x, y, z] = triple(t, k)?.map(|n| params.get(&n).copied());
        Some([x?, y?, z?])
    };
    let or_default = |t: Triple, d: [f64; 3]| match get3(t) {
        Some(v) => Some(v),
        None if absent_is_default => Some(d),
        None => None,
    };
    let ofs_mg = get3(Triple::Ofs)?;
    let dia = or_default(Triple::Dia, [1.0; 3])?;
    let odi = or_default(Triple::Odi, [0.0; 3])?;
    let scale = params.get(&names[9]).copied();
    Some(Correction {
        ofs_mg,
        s: soft_iron(dia, odi),
        scale: applied_scale(scale),
    })
}

/// Compass 2's parameters of a real vehicle (offsets, soft iron), for tests.
#[cfg(test)]
pub(crate) fn example_compass2() -> BTreeMap<String, f64> {
    [
        ("COMPASS_OFS2_X", -171.9),
        ("COMPASS_OFS2_Y", 546.3),
        ("COMPASS_OFS2_Z", -565.6),
        ("COMPASS_DIA2_X", 1.02),
        ("COMPASS_DIA2_Y", 0.98),
        ("COMPASS_DIA2_Z", 1.14),
        ("COMPASS_ODI2_X", -0.01),
        ("COMPASS_ODI2_Y", 0.007),
        ("COMPASS_ODI2_Z", 0.014),
    ]
    .iter()
    .map(|(n, v)| (n.to_string(), *v))
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn max_abs_diff(a: Vec3, b: Vec3) -> f64 {
        (0..3).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max)
    }

    fn close(a: Vec3, b: Vec3, tol: f64) -> bool {
        max_abs_diff(a, b) < tol
    }

    /// Compass k's parameters: OFS, DIA, ODI (X Y Z each) and, when given, SCALE.
    fn params_of(k: u8, v: [f64; 9], scale: Option<f64>) -> BTreeMap<String, f64> {
        let names = correction_names(k).unwrap();
        let mut p: BTreeMap<String, f64> = names.iter().cloned().zip(v).collect();
        if let Some(s) = scale {
            p.insert(names[9].clone(), s);
        }
        p
    }

    #[test]
    fn ardupilot_names_per_compass() {
        assert_eq!(
            triple(Triple::Ofs, 0).unwrap(),
            ["COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z"]
        );
        assert_eq!(triple(Triple::Odi, 2).unwrap()[2], "COMPASS_ODI3_Z");
        assert_eq!(triple(Triple::Mot, 1).unwrap()[0], "COMPASS_MOT2_X");
        assert_eq!(single(Single::External, 0).unwrap(), "COMPASS_EXTERNAL");
        assert_eq!(single(Single::External, 2).unwrap(), "COMPASS_EXTERN3");
        assert_eq!(single(Single::DevId, 1).unwrap(), "COMPASS_DEV_ID2");
        assert_eq!(single(Single::Orient, 0).unwrap(), "COMPASS_ORIENT");
        let n = correction_names(1).unwrap();
        assert_eq!(
            (n[0].as_str(), n[9].as_str()),
            ("COMPASS_OFS2_X", "COMPASS_SCALE2")
        );
        assert_eq!(param_names(2).len(), 17);
        assert!(triple(Triple::Ofs, 3).is_none() && single(Single::Use, 3).is_none());
        assert!(correction_names(3).is_none() && param_names(3).is_empty());
        let p = BTreeMap::from([("COMPASS_DEV_ID3".to_string(), 97539.0)]);
        assert_eq!(dev_id(&p, 2), Some(97539));
        assert_eq!(dev_id(&p, 0), None);
    }

    /// correct_field written out on its own, mGauss: S (scale (raw + OFS)), DIA all zero read
    /// as 1, scale outside the bounds as 1.
    fn correct_field(raw_ut: Vec3, v: [f64; 9], scale: f64) -> Vec3 {
        let d = if v[3..6].iter().all(|x| *x == 0.0) {
            [1.0; 3]
        } else {
            [v[3], v[4], v[5]]
        };
        let s = [[d[0], v[6], v[7]], [v[6], d[1], v[8]], [v[7], v[8], d[2]]];
        let sc = if (1.0 / 1.5..=1.5).contains(&scale) {
            scale
        } else {
            1.0
        };
        let m = [0, 1, 2].map(|i| sc * (raw_ut[i] * 10.0 + v[i]));
        [0, 1, 2].map(|i| (0..3).map(|j| s[i][j] * m[j]).sum())
    }

    #[test]
    fn apply_matches_correct_field_and_undo_returns_the_raw_field() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let (mut worst_fwd_mg, mut worst_back_ut) = (0.0f64, 0.0f64);
        for case in 0..200 {
            // Off-diagonals within +-0.2 of diagonals from 0.5 keep S positive definite.
            let mut v: [f64; 9] = std::array::from_fn(|i| match i {
                0..3 => rng.random_range(-1800.0..1800.0),
                3..6 => rng.random_range(0.5..1.8),
                _ => rng.random_range(-0.2..0.2),
            });
            if case % 4 == 0 {
                v[3..6].fill(0.0);
            }
            // In bounds, out of bounds either side, and the default 0 (none).
            let scale = [1.2, 0.6, 1.6, 0.0, 0.8][case % 5];
            let k = (case % 3) as u8;
            let c = correction(&params_of(k, v, Some(scale)), k, false).unwrap();
            let raw: Vec3 = std::array::from_fn(|_| rng.random_range(-200.0..200.0));
            let fwd = c.apply(raw);
            let want = correct_field(raw, v, scale);
            worst_fwd_mg = worst_fwd_mg.max(max_abs_diff(fwd, want));
            let mot: Vec3 = std::array::from_fn(|_| rng.random_range(-50.0..50.0));
            let streamed = [0, 1, 2].map(|i| fwd[i] + mot[i]);
            let back = c.undo(streamed, Some(mot)).unwrap();
            worst_back_ut = worst_back_ut.max(max_abs_diff(back, raw));
        }
        // Measured: 9.1e-13 mGauss forward (fields near 1e4 mGauss), 1.4e-13 uT back.
        assert!(worst_fwd_mg < 3e-12, "{worst_fwd_mg}");
        assert!(worst_back_ut < 5e-13, "{worst_back_ut}");
    }

    #[test]
    fn zero_diagonal_reads_as_one_and_scale_only_within_bounds() {
        let c = correction(&params_of(0, [0.0; 9], None), 0, false).unwrap();
        assert_eq!(c.s, Matrix3::identity());
        let c = correction(
            &params_of(0, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0], None),
            0,
            false,
        )
        .unwrap();
        assert_eq!((c.s[(0, 0)], c.s[(0, 1)]), (1.0, 0.1));
        for (s, applied) in [
            (1.5, 1.5),
            (1.51, 1.0),
            (0.67, 0.67),
            (0.66, 1.0),
            (-1.2, 1.0),
        ] {
            assert_eq!(applied_scale(Some(s)), applied, "{s}");
        }
        assert_eq!(applied_scale(None), 1.0);
        // A singular S cannot be undone; a value not finite is no correction.
        let c = correction(
            &params_of(0, [0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0], None),
            0,
            false,
        );
        assert!(c.unwrap().undo([5.0, 1.0, 2.0], None).is_none());
        let mut v = [0.0; 9];
        v[4] = f64::NAN;
        assert!(correction(&params_of(0, v, None), 0, true).is_none());
    }

    #[test]
    fn undo_inverts_a_real_vehicles_correction_missing_soft_iron_unknown_unless_the_list_is_whole()
    {
        let mut p = example_compass2();
        let c = correction(&p, 1, false).unwrap();
        let raw = [12.0, -30.0, 41.0];
        assert!(close(c.undo(c.apply(raw), None).unwrap(), raw, 1e-9));
        assert!(correction(&p, 0, true).is_none(), "no COMPASS_OFS");
        assert!(correction(&p, 3, true).is_none());
        p.remove("COMPASS_DIA2_Y");
        assert!(correction(&p, 1, false).is_none());
        let c = correction(&p, 1, true).unwrap();
        assert_eq!((c.s[(1, 1)], c.s[(0, 0)], c.s[(0, 1)]), (1.0, 1.0, -0.01));
    }

    #[test]
    fn forward_map_then_reading_the_parameters_back_gives_the_calibration() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (mut worst_model, mut worst_field_mg) = (0.0f64, 0.0f64);
        for case in 0..100 {
            let offset: Vec3 = std::array::from_fn(|_| rng.random_range(-150.0..150.0));
            let mut m = [[0.0; 3]; 3];
            for i in 0..3 {
                m[i][i] = rng.random_range(0.6..1.6);
                for j in 0..i {
                    m[i][j] = rng.random_range(-0.2..0.2);
                    m[j][i] = m[i][j];
                }
            }
            let k = (case % 3) as u8;
            let p: BTreeMap<String, f64> = Correction::from_model(&offset, &m)
                .params(k)
                .unwrap()
                .into_iter()
                .collect();
            let names = correction_names(k).unwrap();
            assert_eq!(p.len(), 9);
            assert!(names[..9].iter().all(|n| p.contains_key(n)));
            let (o2, m2) = correction(&p, k, true).unwrap().model();
            worst_model = worst_model.max(max_abs_diff(o2, offset));
            for i in 0..3 {
                worst_model = worst_model.max(max_abs_diff(m2[i], m[i]));
            }
            // The parameters correct a raw reading as the calibration does (mGauss vs uT).
            let raw: Vec3 = std::array::from_fn(|_| rng.random_range(-100.0..100.0));
            let ours = crate::calib::model::Calibration {
                model: crate::calib::model::ModelKind::Sym9,
                offset,
                matrix: m,
            }
            .apply(&raw)
            .map(|x| x * 10.0);
            let theirs = correct_field(raw, std::array::from_fn(|i| p[&names[i]]), 0.0);
            worst_field_mg = worst_field_mg.max(max_abs_diff(ours, theirs));
        }
        // Measured: 1.4e-14 (uT and matrix elements), 9.1e-13 mGauss.
        assert!(worst_model < 5e-14, "{worst_model}");
        assert!(worst_field_mg < 3e-12, "{worst_field_mg}");
        // The scale is folded into DIA/ODI; an asymmetric matrix gives its symmetric part.
        let c = Correction {
            ofs_mg: [10.0, 20.0, 30.0],
            s: symmetric([1.0, 1.1, 0.9], [0.1, 0.0, -0.1]),
            scale: 1.2,
        };
        let p: BTreeMap<String, f64> = c.params(0).unwrap().into_iter().collect();
        assert!((p["COMPASS_DIA_Y"] - 1.32).abs() < 1e-12);
        assert!((p["COMPASS_ODI_Z"] + 0.12).abs() < 1e-12);
        assert_eq!(p["COMPASS_OFS_Z"], 30.0);
        let asym = [[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let c = Correction::from_model(&[0.0; 3], &asym);
        assert_eq!((c.s[(0, 1)], c.s[(1, 0)]), (0.1, 0.1));
        assert!(c.params(3).is_none());
    }
}
