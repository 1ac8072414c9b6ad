//! ArduPilot's compass correction: one place for its parameter names, its matrix and bounds, and
//! undoing it, for every reader of ArduPilot data (DataFlash `MAG` records, telemetry).
//!
//! Convention (ArduPilot's `Compass::correct_field`, fields in mGauss): the field it logs and streams
//! is `mag = S (scale (raw + OFS)) + MOT`, with OFS = COMPASS_OFS{,2,3}_X/Y/Z, S the symmetric
//! matrix of COMPASS_DIA (diagonal; all zero read as 1) and COMPASS_ODI (xy, xz, yz), scale =
//! COMPASS_SCALE{,2,3} when within 1/1.5..1.5 (else 1) and MOT the motor term. In imucald's model
//! (calibrated = M (raw - offset), uT) that is offset = -OFS / 10 and M = S scale.
//!
//! Telemetry ([`Telemetry`]): ArduPilot fills RAW_IMU and SCALED_IMU2/3 with the field *after* that
//! correction (mGauss, body axes), so a fit of the stream as it arrives fits a residual. The
//! vehicle's PARAM_VALUE messages give the correction in force; each reading is undone with the
//! values known at its own time (a calibration run on the vehicle mid-log applies from then on).
//! SENSOR_OFFSETS (compass 0's offsets) stands in where the parameters never arrived. Pure.

use crate::io::onboard::OnboardCal;
use crate::types::Vec3;
use mavlink::dialects::ardupilotmega::MavMessage;
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;

/// Compasses ArduPilot keeps a calibration for (COMPASS_OFS, COMPASS_OFS2, COMPASS_OFS3).
pub const COMPASSES: u8 = 3;

/// ArduPilot applies COMPASS_SCALE only within these bounds (COMPASS_MIN/MAX_SCALE_FACTOR).
pub const SCALE_RANGE: (f64, f64) = (1.0 / 1.5, 1.5);

/// The parameter suffix of compass k: `COMPASS_OFS_X`, `COMPASS_OFS2_X`, `COMPASS_OFS3_X`.
pub fn suffix(k: u8) -> Option<&'static str> {
    ["", "2", "3"].get(k as usize).copied()
}

/// The name of one of compass k's parameters: `param("OFS", 1, "X")` is `COMPASS_OFS2_X`.
pub fn param(base: &str, k: u8, axis: &str) -> String {
    format!("COMPASS_{base}{}_{axis}", suffix(k).unwrap_or(""))
}

/// ArduPilot's correction of one compass, as it applies it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correction {
    /// COMPASS_OFS, mGauss.
    pub ofs_mg: [f64; 3],
    /// The soft-iron matrix S from COMPASS_DIA/ODI.
    pub s: Matrix3<f64>,
    /// COMPASS_SCALE as applied (1 outside [`SCALE_RANGE`]).
    pub scale: f64,
}

impl Correction {
    /// No correction at all (offsets zero, S identity).
    pub fn offsets_only(ofs_mg: [f64; 3]) -> Correction {
        Correction {
            ofs_mg,
            s: Matrix3::identity(),
            scale: 1.0,
        }
    }

    /// The raw field (uT) behind a corrected one (mGauss) with the motor term `mot_mg` removed:
    /// raw = (S^-1 (mag - MOT)) / scale - OFS. `None` when S is singular or a value not finite.
    pub fn undo(&self, mag_mg: Vec3, mot_mg: Option<Vec3>) -> Option<Vec3> {
        let inv = self.s.try_inverse()?;
        let m = mot_mg.unwrap_or([0.0; 3]);
        let c = Vector3::new(mag_mg[0] - m[0], mag_mg[1] - m[1], mag_mg[2] - m[2]);
        let u = inv * c / self.scale;
        let raw = [0, 1, 2].map(|i| (u[i] - self.ofs_mg[i]) / 10.0);
        raw.iter().all(|x| x.is_finite()).then_some(raw)
    }

    /// ArduPilot's forward correction (raw uT in, corrected mGauss out, no motor term).
    pub fn apply(&self, raw_ut: Vec3) -> Vec3 {
        let m = Vector3::new(
            raw_ut[0] * 10.0 + self.ofs_mg[0],
            raw_ut[1] * 10.0 + self.ofs_mg[1],
            raw_ut[2] * 10.0 + self.ofs_mg[2],
        );
        let c = self.s * m * self.scale;
        [c.x, c.y, c.z]
    }

    /// In imucald's model: (offset uT, matrix rows), calibrated = matrix (raw - offset) in uT.
    pub fn model(&self) -> (Vec3, [[f64; 3]; 3]) {
        (
            self.ofs_mg.map(|o| -o / 10.0),
            crate::calib::model::mat_to_rows(&(self.s * self.scale)),
        )
    }
}

/// The symmetric soft-iron matrix: diagonal `d`, off-diagonal (xy, xz, yz) `o`.
fn soft_iron(d: [f64; 3], o: [f64; 3]) -> Matrix3<f64> {
    Matrix3::new(d[0], o[0], o[1], o[0], d[1], o[2], o[1], o[2], d[2])
}

/// Compass k's correction from its parameters. COMPASS_OFS is needed; COMPASS_DIA/ODI/SCALE
/// missing are taken as ArduPilot's defaults (none) only when `absent_is_default` (the whole
/// parameter list is known, so a missing one is missing from the firmware), else `None`.
pub fn correction(
    params: &BTreeMap<String, f64>,
    k: u8,
    absent_is_default: bool,
) -> Option<Correction> {
    suffix(k)?;
    let get3 = |what: &str| -> Option<[f64; 3]> {
        let mut v = [0.0; 3];
        for (i, ax) in ["X", "Y", "Z"].iter().enumerate() {
            v[i] = *params.get(&param(what, k, ax))?;
        }
        v.iter().all(|x| x.is_finite()).then_some(v)
    };
    let ofs_mg = get3("OFS")?;
    let or_default = |v: Option<[f64; 3]>, d: [f64; 3]| match v {
        Some(v) => Some(v),
        None if absent_is_default => Some(d),
        None => None,
    };
    let mut dia = or_default(get3("DIA"), [1.0; 3])?;
    if dia.iter().all(|d| *d == 0.0) {
        dia = [1.0; 3];
    }
    let odi = or_default(get3("ODI"), [0.0; 3])?;
    let scale = match params.get(&format!("COMPASS_SCALE{}", suffix(k)?)) {
        Some(&v) if (SCALE_RANGE.0..=SCALE_RANGE.1).contains(&v) => v,
        _ => 1.0,
    };
    Some(Correction {
        ofs_mg,
        s: soft_iron(dia, odi),
        scale,
    })
}

/// Compass k's parameters that describe it: OFS, DIA, ODI, MOT, orientation, device id, external,
/// scale and use.
pub fn param_names(k: u8) -> Vec<String> {
    let Some(s) = suffix(k) else {
        return Vec::new();
    };
    let mut n = Vec::new();
    for what in ["OFS", "DIA", "ODI", "MOT"] {
        for ax in ["X", "Y", "Z"] {
            n.push(param(what, k, ax));
        }
    }
    let (orient, dev, ext) = match k {
        0 => ("COMPASS_ORIENT", "COMPASS_DEV_ID", "COMPASS_EXTERNAL"),
        1 => ("COMPASS_ORIENT2", "COMPASS_DEV_ID2", "COMPASS_EXTERN2"),
        _ => ("COMPASS_ORIENT3", "COMPASS_DEV_ID3", "COMPASS_EXTERN3"),
    };
    n.extend(
        [orient, dev, ext]
            .iter()
            .map(|x| x.to_string())
            .chain([format!("COMPASS_SCALE{s}"), format!("COMPASS_USE{s}")]),
    );
    n
}

/// Compass k's device id (COMPASS_DEV_ID{,2,3}), when set.
pub fn dev_id(params: &BTreeMap<String, f64>, k: u8) -> Option<u32> {
    let n = match k {
        0 => "COMPASS_DEV_ID",
        1 => "COMPASS_DEV_ID2",
        _ => "COMPASS_DEV_ID3",
    };
    params
        .get(n)
        .filter(|v| **v > 0.0 && **v < u32::MAX as f64)
        .map(|v| *v as u32)
}

/// Compass k's onboard calibration in imucald's model, with the parameters it was made from.
pub fn onboard_cal(
    params: &BTreeMap<String, f64>,
    k: u8,
    c: &Correction,
    sources: Vec<String>,
) -> OnboardCal {
    let (offset, matrix) = c.model();
    OnboardCal {
        instance: k,
        device_id: dev_id(params, k),
        sources,
        offset,
        matrix,
        units: crate::types::CalUnits::Ut,
        params: param_names(k)
            .into_iter()
            .filter_map(|n| params.get(&n).map(|v| (n, *v)))
            .collect(),
    }
}

/// Where a telemetry correction came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorrectionSource {
    /// The vehicle's PARAM_VALUE messages.
    Params,
    /// SENSOR_OFFSETS' `mag_ofs` (compass 0's offsets only; no soft iron known).
    SensorOffsets,
}

/// One change of a compass's correction seen in a telemetry log.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectionChange {
    /// The time of the first reading undone with the new values, s (the instance's clock).
    pub t_s: f64,
    pub compass: u8,
    pub before_ofs_mg: [f64; 3],
    pub after_ofs_mg: [f64; 3],
}

/// An ArduPilot vehicle's compass corrections as its telemetry gives them, kept as they change,
/// to undo them from each magnetometer reading at its time.
#[derive(Debug, Clone, Default)]
pub struct Telemetry {
    /// Every parameter received so far (the vehicle's, newest value).
    params: BTreeMap<String, f64>,
    /// PARAM_VALUE's `param_count` and the indices received: when every index has arrived the
    /// list is whole and a parameter missing from it is missing from the firmware.
    param_count: Option<u16>,
    indices: Vec<bool>,
    indices_seen: usize,
    /// SENSOR_OFFSETS' `mag_ofs`, mGauss.
    sensor_offsets_mg: Option<[f64; 3]>,
    /// Per compass: the correction used for its last reading, and where from.
    in_use: [Option<(Correction, CorrectionSource)>; COMPASSES as usize],
    /// Per compass: [`Telemetry::current`] as of the last message absorbed (`None`: not yet
    /// worked out), so a reading costs no parameter look-ups.
    cached: [Option<Option<(Correction, CorrectionSource)>>; COMPASSES as usize],
    /// Changes of a compass's offsets between readings.
    pub changes: Vec<CorrectionChange>,
    /// Readings that could not be undone (no correction known yet), per compass.
    pub held: [u64; COMPASSES as usize],
}

impl Telemetry {
    /// Take a PARAM_VALUE or SENSOR_OFFSETS message; true when it was one. SENSOR_OFFSETS is
    /// deprecated in the dialect, but the firmware of older logs sends it and nothing else.
    #[allow(deprecated)]
    pub fn absorb(&mut self, msg: &MavMessage) -> bool {
        self.cached = Default::default();
        match msg {
            MavMessage::PARAM_VALUE(p) => {
                let bytes: &[u8; 16] = &p.param_id;
                let end = bytes.iter().position(|&b| b == 0).unwrap_or(16);
                let name = String::from_utf8_lossy(&bytes[..end]).into_owned();
                if p.param_value.is_finite() && !name.is_empty() {
                    self.params.insert(name, f64::from(p.param_value));
                }
                self.count_index(p.param_count, p.param_index);
                true
            }
            MavMessage::SENSOR_OFFSETS(d) => {
                self.sensor_offsets_mg =
                    Some([d.mag_ofs_x, d.mag_ofs_y, d.mag_ofs_z].map(f64::from));
                true
            }
            _ => false,
        }
    }

    fn count_index(&mut self, count: u16, index: u16) {
        if count == 0 || count == u16::MAX || index >= count {
            return;
        }
        if self.param_count != Some(count) {
            self.param_count = Some(count);
            self.indices = vec![false; count as usize];
            self.indices_seen = 0;
        }
        if !std::mem::replace(&mut self.indices[index as usize], true) {
            self.indices_seen += 1;
        }
    }

    /// Every parameter of the vehicle's list has arrived.
    pub fn list_complete(&self) -> bool {
        self.param_count
            .is_some_and(|n| self.indices_seen == n as usize)
    }

    /// The correction of compass k in force now, and where it comes from.
    pub fn current(&self, k: u8) -> Option<(Correction, CorrectionSource)> {
        if let Some(c) = correction(&self.params, k, self.list_complete()) {
            return Some((c, CorrectionSource::Params));
        }
        match (k, self.sensor_offsets_mg) {
            (0, Some(o)) if !self.params.contains_key(&param("OFS", 0, "X")) => {
                Some((Correction::offsets_only(o), CorrectionSource::SensorOffsets))
            }
            _ => None,
        }
    }

    /// The raw field (uT) behind compass k's reading `mag_mg` (mGauss, as streamed) at time
    /// `t_s`, undone with the correction in force now. `None` (counted in `held`) until one is
    /// known.
    pub fn undo(&mut self, k: u8, mag_mg: Vec3, t_s: f64) -> Option<Vec3> {
        let ki = k as usize;
        if ki >= COMPASSES as usize {
            return None;
        }
        let current = match self.cached[ki] {
            Some(c) => c,
            None => *self.cached[ki].insert(self.current(k)),
        };
        let Some((c, src)) = current else {
            self.held[ki] += 1;
            return None;
        };
        match self.in_use[ki] {
            Some((old, _)) if old.ofs_mg != c.ofs_mg => self.changes.push(CorrectionChange {
                t_s,
                compass: k,
                before_ofs_mg: old.ofs_mg,
                after_ofs_mg: c.ofs_mg,
            }),
            _ => {}
        }
        self.in_use[ki] = Some((c, src));
        c.undo(mag_mg, None)
    }

    /// Compass k's correction used for its last reading, and where it came from.
    pub fn last_used(&self, k: u8) -> Option<(Correction, CorrectionSource)> {
        self.in_use.get(k as usize).copied().flatten()
    }

    /// The onboard calibrations used, one per compass undone: the one in force at the log's end
    /// (the vehicle flies with it afterwards), with the vehicle's parameters.
    pub fn onboard_cals(&self, sources: &BTreeMap<u8, String>) -> Vec<OnboardCal> {
        (0..COMPASSES)
            .filter_map(|k| {
                let (c, _) = self.last_used(k)?;
                Some(onboard_cal(
                    &self.params,
                    k,
                    &c,
                    sources.get(&k).cloned().into_iter().collect(),
                ))
            })
            .collect()
    }

    /// What was undone, per compass, in words for the report (`onboard.undone`), and what could
    /// not be (`onboard.not_undone`).
    pub fn describe(&self, sources: &BTreeMap<u8, String>) -> (Vec<String>, Vec<String>) {
        let mut undone = Vec::new();
        let mut not = Vec::new();
        for k in 0..COMPASSES {
            let ki = k as usize;
            let src = sources
                .get(&k)
                .cloned()
                .unwrap_or_else(|| format!("compass {k}"));
            match self.in_use[ki] {
                Some((_, from)) => {
                    let what = match from {
                        CorrectionSource::Params if self.list_complete() => {
                            "COMPASS_OFS/DIA/ODI/SCALE from the vehicle's PARAM_VALUE (whole list; absent ones are ArduPilot's defaults)"
                        }
                        CorrectionSource::Params => {
                            "COMPASS_OFS/DIA/ODI/SCALE from the vehicle's PARAM_VALUE"
                        }
                        CorrectionSource::SensorOffsets => {
                            "offsets from SENSOR_OFFSETS (no COMPASS_* parameters in the log; soft iron taken as none)"
                        }
                    };
                    let changes: Vec<String> = self
                        .changes
                        .iter()
                        .filter(|c| c.compass == k)
                        .map(|c| {
                            format!(
                                "at {:.1} s COMPASS_OFS went from {} to {} mGauss",
                                c.t_s,
                                fmt3(&c.before_ofs_mg),
                                fmt3(&c.after_ofs_mg)
                            )
                        })
                        .collect();
                    let mut s = format!("{src}: {what} undone from each reading as in force at its time");
                    if !changes.is_empty() {
                        s += &format!("; {}", changes.join("; "));
                    }
                    if self.held[ki] > 0 {
                        s += &format!(
                            "; {} readings before the correction was known left out",
                            self.held[ki]
                        );
                    }
                    undone.push(s);
                }
                None if self.held[ki] > 0 => not.push(format!(
                    "{src}: streamed with ArduPilot's correction applied and the log never gives it (no COMPASS_OFS{}_* PARAM_VALUE{}): its {} readings are left out, nothing is fitted or exported for it",
                    suffix(k).unwrap_or(""),
                    if k == 0 { " nor SENSOR_OFFSETS" } else { "" },
                    self.held[ki]
                )),
                None => {}
            }
        }
        (undone, not)
    }
}

fn fmt3(v: &[f64; 3]) -> String {
    format!("[{:.1}, {:.1}, {:.1}]", v[0], v[1], v[2])
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
    #[allow(deprecated)]
    use mavlink::dialects::ardupilotmega::{MavParamType, PARAM_VALUE_DATA, SENSOR_OFFSETS_DATA};

    fn pv(name: &str, v: f32, index: u16, count: u16) -> MavMessage {
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: v,
            param_count: count,
            param_index: index,
            param_id: mavlink::types::CharArray::from(name),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
        })
    }

    #[test]
    fn undo_inverts_the_correction() {
        let mut p = example_compass2();
        let c = correction(&p, 1, false).unwrap();
        let raw = [12.0, -30.0, 41.0];
        let back = c.undo(c.apply(raw), None).unwrap();
        for i in 0..3 {
            assert!((back[i] - raw[i]).abs() < 1e-9, "{back:?}");
        }
        // Missing DIA/ODI: unknown unless the list is whole.
        p.remove("COMPASS_DIA2_Y");
        assert!(correction(&p, 1, false).is_none());
        assert_eq!(correction(&p, 1, true).unwrap().s[(1, 1)], 1.0);
    }

    #[test]
    #[allow(deprecated)]
    fn telemetry_undoes_with_the_values_in_force_at_each_reading() {
        let mut t = Telemetry::default();
        let raw = [20.0, -5.0, 40.0];
        // Nothing known: held.
        assert!(t.undo(0, raw, 0.0).is_none());
        assert_eq!(t.held[0], 1);
        // SENSOR_OFFSETS stands in for compass 0.
        t.absorb(&MavMessage::SENSOR_OFFSETS(SENSOR_OFFSETS_DATA {
            mag_ofs_x: -33,
            mag_ofs_y: -65,
            mag_ofs_z: -37,
            ..Default::default()
        }));
        let c0 = Correction::offsets_only([-33.0, -65.0, -37.0]);
        let back = t.undo(0, c0.apply(raw), 1.0).unwrap();
        assert!((back[0] - raw[0]).abs() < 1e-9);
        assert_eq!(t.last_used(0).unwrap().1, CorrectionSource::SensorOffsets);
        // The whole list of a firmware without DIA/ODI (4 parameters): the params take over.
        for (i, (n, v)) in [
            ("COMPASS_OFS_X", -100.0),
            ("COMPASS_OFS_Y", 50.0),
            ("COMPASS_OFS_Z", 10.0),
            ("COMPASS_DEC", 0.05),
        ]
        .iter()
        .enumerate()
        {
            t.absorb(&pv(n, *v, i as u16, 4));
        }
        assert!(t.list_complete());
        let c1 = Correction::offsets_only([-100.0, 50.0, 10.0]);
        let back = t.undo(0, c1.apply(raw), 2.0).unwrap();
        for i in 0..3 {
            assert!((back[i] - raw[i]).abs() < 1e-4, "{back:?}");
        }
        assert_eq!(t.changes.len(), 1);
        assert_eq!(t.changes[0].t_s, 2.0);
        // A new offset mid-log (the vehicle's own calibration) applies from then on.
        t.absorb(&pv("COMPASS_OFS_X", -120.0, 0, 4));
        let c2 = Correction::offsets_only([-120.0, 50.0, 10.0]);
        let back = t.undo(0, c2.apply(raw), 3.0).unwrap();
        assert!((back[0] - raw[0]).abs() < 1e-4, "{back:?}");
        assert_eq!(t.changes.len(), 2);
        let (undone, not) = t.describe(&BTreeMap::from([(0, "raw_imu:0".to_string())]));
        assert!(
            undone[0].contains(
                "at 3.0 s COMPASS_OFS went from [-100.0, 50.0, 10.0] to [-120.0, 50.0, 10.0]"
            ),
            "{undone:?}"
        );
        assert!(not.is_empty());
        // Compass 1 never described: held, said so.
        assert!(t.undo(1, raw, 4.0).is_none());
        let (_, not) = t.describe(&BTreeMap::new());
        assert!(not[0].contains("COMPASS_OFS2_*"), "{not:?}");
        // The onboard calibration reported is the one in force at the end.
        let cals = t.onboard_cals(&BTreeMap::new());
        assert_eq!(cals.len(), 1);
        assert_eq!(cals[0].offset, [12.0, -5.0, -1.0]);
    }

    /// A telemetry state that has read `values` (name, value) as PARAM_VALUE, list length unknown.
    fn read(values: &[(String, f64)]) -> Telemetry {
        let mut t = Telemetry::default();
        for (n, v) in values {
            assert!(t.absorb(&pv(n, *v as f32, 0, 0)));
        }
        t
    }

    fn compass0(v: [f64; 9]) -> Vec<(String, f64)> {
        let names = ["OFS", "DIA", "ODI"]
            .iter()
            .flat_map(|b| ["X", "Y", "Z"].map(|a| param(b, 0, a)));
        names.zip(v).collect()
    }

    #[test]
    fn telemetry_undoes_correct_field_and_what_export_writes() {
        let mut t = Telemetry::default();
        assert!(!t.absorb(&crate::io::mavout::named_float("COMPASS_OF", 0, 1.0)));
        assert!(t.undo(0, [1.0, 2.0, 3.0], 0.0).is_none());
        let mut t = read(&compass0([
            -120.0, 300.0, -450.0, 1.05, 0.97, 1.01, 0.02, -0.01, 0.04,
        ]));
        assert!(t.current(0).is_some() && t.current(1).is_none());
        let raw = [40.0, 5.0, -20.0];
        // ArduPilot's correct_field, written out in mGauss.
        let m = [400.0 - 120.0, 50.0 + 300.0, -200.0 - 450.0];
        let s = [[1.05, 0.02, -0.01], [0.02, 0.97, 0.04], [-0.01, 0.04, 1.01]];
        let corrected: Vec3 = [0, 1, 2].map(|i| (0..3).map(|j| s[i][j] * m[j]).sum());
        let fwd = t.current(0).unwrap().0.apply(raw);
        assert!(
            (0..3).all(|i| (fwd[i] - corrected[i]).abs() < 1e-3),
            "{fwd:?}"
        );
        let back = t.undo(0, corrected, 0.0).unwrap();
        assert!((0..3).all(|i| (back[i] - raw[i]).abs() < 1e-4), "{back:?}");

        // COMPASS_SCALE is applied when ArduPilot would (within 1/1.5..1.5).
        t.absorb(&pv("COMPASS_SCALE", 1.2, 0, 0));
        let c = t.current(0).unwrap().0.apply(raw);
        assert!((c[0] - 1.2 * corrected[0]).abs() < 1e-2);
        let back = t.undo(0, c, 1.0).unwrap();
        assert!((0..3).all(|i| (back[i] - raw[i]).abs() < 1e-4));
        t.absorb(&pv("COMPASS_SCALE", 3.0, 0, 0));
        assert!((t.current(0).unwrap().0.apply(raw)[0] - corrected[0]).abs() < 1e-3);

        // The undone field is what our own calibration with export's parameters corrects, for
        // the second compass too, apart from the first's.
        let cal = crate::calib::model::Calibration {
            model: crate::calib::model::ModelKind::Sym9,
            offset: [12.0, -30.0, 45.0],
            matrix: s,
        };
        for k in [0u8, 1] {
            let (exp, _) = crate::calib::export::ardupilot_mag(&cal, k as usize);
            for (n, v) in exp.iter() {
                t.absorb(&pv(n, *v as f32, 0, 0));
            }
            let c = cal.apply(&raw).map(|v| v * 10.0);
            let u = t.undo(k, c, 2.0).unwrap();
            assert!((0..3).all(|i| (u[i] - raw[i]).abs() < 1e-3), "{k}: {u:?}");
        }
    }

    #[test]
    fn zero_diagonals_read_as_one_singular_and_incomplete_are_refused() {
        let mut t = read(&compass0([10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]));
        let u = t.undo(0, [50.0, 10.0, 20.0], 0.0).unwrap();
        assert!(
            (0..3).all(|i| (u[i] - [4.0, 1.0, 2.0][i]).abs() < 1e-12),
            "{u:?}"
        );
        let mut t = read(&compass0([0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]));
        assert!(t.undo(0, [5.0, 1.0, 2.0], 0.0).is_none());
        let mut v = compass0([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
        let mut t = read(&v);
        assert!(t.undo(0, [f64::NAN, 0.0, 0.0], 0.0).is_none());
        v.pop();
        assert!(read(&v).current(0).is_none(), "COMPASS_ODI_Z unknown");
    }
}
