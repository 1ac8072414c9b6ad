//! ArduPilot's onboard calibration in a DataFlash log: the report of the compasses' and
//! accelerometers' parameters as the log began, and each MAG record's correction undone
//! (COMPASS_OFS/DIA/ODI/SCALE, the record's own offsets where they changed in flight, the logged
//! motor term).

use super::rows;
use crate::io::onboard::{OnboardCal, OnboardReport};
use crate::types::Vec3;
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;

pub(crate) fn ap_onboard(
    params: &BTreeMap<String, f64>,
    sources: &BTreeMap<(u8, u8), String>,
) -> OnboardReport {
    let mut r = OnboardReport {
        stack: "ardupilot".into(),
        ..Default::default()
    };
    for k in 0..crate::calib::ardupilot::COMPASSES {
        let Some(c) = crate::calib::ardupilot::correction(params, k, true) else {
            continue;
        };
        let sources = sources.get(&(0, k)).cloned().into_iter().collect();
        r.mag
            .push(crate::io::ardupilot::onboard_cal(params, k, &c, sources));
    }
    for k in 0..3u8 {
        let s = ["", "2", "3"][k as usize];
        let get3 = |what: &str| -> Option<[f64; 3]> {
            let mut v = [0.0; 3];
            for (i, ax) in ["X", "Y", "Z"].iter().enumerate() {
                v[i] = *params.get(&format!("INS_ACC{s}{what}_{ax}"))?;
            }
            Some(v)
        };
        let Some(offs) = get3("OFFS") else {
            continue;
        };
        let scal = get3("SCAL").unwrap_or([1.0; 3]);
        let mut p = BTreeMap::new();
        for what in ["OFFS", "SCAL"] {
            for ax in ["X", "Y", "Z"] {
                let n = format!("INS_ACC{s}{what}_{ax}");
                if let Some(v) = params.get(&n) {
                    p.insert(n, *v);
                }
            }
        }
        // AP_InertialSensor: accel = scale * (raw - offset), per axis.
        r.accel.push(OnboardCal {
            instance: k,
            device_id: None,
            sources: sources.get(&(1, k)).cloned().into_iter().collect(),
            offset: offs,
            matrix: rows(&Matrix3::from_diagonal(&Vector3::from(scal))),
            units: crate::types::CalUnits::Mps2,
            params: p,
        });
    }
    r
}

/// Undo ArduPilot's correction of one MAG record (mGauss in, uT out). `rec_ofs` is the record's
/// OfsX/Y/Z and `mofs` its MOfsX/Y/Z when logged.
#[cfg(test)]
fn ap_undo(
    params: &BTreeMap<String, f64>,
    k: u8,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    ap_undo_with(
        crate::calib::ardupilot::correction(params, k, true),
        mag_mg,
        rec_ofs,
        mofs,
    )
}

/// [`ap_undo`] with the compass's correction from its parameters, when they give one.
#[cfg(test)]
fn ap_undo_with(
    correction: Option<crate::calib::ardupilot::Correction>,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    ap_undo_cached(correction.map(ApUndo::new).as_ref(), mag_mg, rec_ofs, mofs)
}

/// The inverse of the identity soft iron, for records undone with their own offsets alone.
fn identity_undo() -> &'static ApUndo {
    static ID: std::sync::OnceLock<ApUndo> = std::sync::OnceLock::new();
    ID.get_or_init(|| ApUndo::new(crate::calib::ardupilot::Correction::offsets_only([0.0; 3])))
}

/// Undo a MAG record's correction: the compass's from its parameters (`correction`, with its
/// inverse), else the record's offsets `rec_ofs` with no soft iron; the record's offsets stand in
/// for the parameter's where they differ by more than 1 mGauss (an offset changed in flight).
pub(crate) fn ap_undo_cached(
    correction: Option<&ApUndo>,
    mag_mg: Vec3,
    rec_ofs: Option<Vec3>,
    mofs: Option<Vec3>,
) -> Option<Vec3> {
    let (undo, mut ofs) = match correction {
        Some(c) => (c, c.correction.ofs_mg),
        // No parameters: the record's offsets, no soft iron.
        None => (identity_undo(), rec_ofs?),
    };
    if let Some(r) = rec_ofs {
        if (0..3).any(|i| (r[i] - ofs[i]).abs() > 1.0) {
            ofs = r;
        }
    }
    undo.undo(&ofs, mag_mg, mofs)
}

/// ArduPilot's correction of a compass with the inverse of its soft iron, worked out once per
/// correction rather than once per reading: [`ApUndo::undo`] gives what
/// [`crate::calib::ardupilot::Correction::undo`] gives, to the bit (the same inverse, the same
/// operations in the same order).
#[derive(Debug, Clone, Copy)]
pub(crate) struct ApUndo {
    correction: crate::calib::ardupilot::Correction,
    /// S^-1; `None` when S is singular (nothing can be undone).
    inverse: Option<Matrix3<f64>>,
}

impl ApUndo {
    pub(crate) fn new(correction: crate::calib::ardupilot::Correction) -> ApUndo {
        ApUndo {
            correction,
            inverse: correction.s.try_inverse(),
        }
    }

    /// The raw field (uT) behind a corrected one (mGauss) with the motor term `mot_mg` removed,
    /// the offsets `ofs_mg` in place of the correction's: raw = (S^-1 (mag - MOT)) / scale - OFS.
    /// `None` when S is singular or a value not finite.
    fn undo(&self, ofs_mg: &Vec3, mag_mg: Vec3, mot_mg: Option<Vec3>) -> Option<Vec3> {
        use crate::calib::ardupilot::MGAUSS_PER_UT;
        let inv = self.inverse?;
        let c = Vector3::from(mag_mg) - Vector3::from(mot_mg.unwrap_or([0.0; 3]));
        let u = inv * c / self.correction.scale;
        let raw = [0, 1, 2].map(|i| (u[i] - ofs_mg[i]) / MGAUSS_PER_UT);
        raw.iter().all(|x| x.is_finite()).then_some(raw)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ardupilot_undo_inverts_its_correction() {
        let p = crate::calib::ardupilot::example_compass2();
        let raw_ut = [12.0, -30.0, 41.0];
        let c = crate::calib::ardupilot::correction(&p, 1, true)
            .unwrap()
            .apply(raw_ut);
        let back = ap_undo(&p, 1, [c[0], c[1], c[2]], None, None).unwrap();
        for i in 0..3 {
            assert!((back[i] - raw_ut[i]).abs() < 1e-9, "{back:?}");
        }
        // The onboard model in imucald's convention gives the corrected field back from raw.
        let r = ap_onboard(&p, &BTreeMap::new());
        let cal = &r.mag[0];
        assert_eq!(cal.instance, 1);
        let mm = crate::calib::model::rows_to_mat(&cal.matrix);
        let d = Vector3::new(
            raw_ut[0] - cal.offset[0],
            raw_ut[1] - cal.offset[1],
            raw_ut[2] - cal.offset[2],
        );
        let cal_ut = mm * d;
        for i in 0..3 {
            assert!((cal_ut[i] * 10.0 - c[i]).abs() < 1e-9);
        }
    }
}
