//! Reading ArduPilot's compass correction from what a vehicle sends and logs, and undoing it
//! from its readings, for every reader of ArduPilot data (DataFlash `MAG` records, telemetry).
//! The correction itself (names, matrix, bounds, apply, undo, imucald's model) is
//! [`crate::calib::ardupilot`].
//!
//! Telemetry ([`Telemetry`]): ArduPilot fills RAW_IMU and SCALED_IMU2/3 with the field *after* that
//! correction (mGauss, body axes), so a fit of the stream as it arrives fits a residual. The
//! vehicle's PARAM_VALUE messages give the correction in force; each reading is undone with the
//! values known at its own time (a calibration run on the vehicle mid-log applies from then on).
//! SENSOR_OFFSETS (compass 0's offsets) stands in where the parameters never arrived. Pure.

use crate::calib::ardupilot::{
    correction, dev_id, param_names, suffix, triple, Correction, Triple, COMPASSES,
};
use crate::io::onboard::OnboardCal;
use crate::types::Vec3;
use mavlink::dialects::ardupilotmega::MavMessage;
use std::collections::BTreeMap;

/// Compass k's onboard calibration in imucald's model, with the parameters it was made from.
pub(crate) fn onboard_cal(
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
pub(crate) enum CorrectionSource {
    /// The vehicle's PARAM_VALUE messages.
    Params,
    /// SENSOR_OFFSETS' `mag_ofs` (compass 0's offsets only; no soft iron known).
    SensorOffsets,
}

/// One change of a compass's correction seen in a telemetry log.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CorrectionChange {
    /// The time of the first reading undone with the new values, s (the instance's clock).
    pub t_s: f64,
    pub compass: u8,
    pub before_ofs_mg: [f64; 3],
    pub after_ofs_mg: [f64; 3],
}

/// An ArduPilot vehicle's compass corrections as its telemetry gives them, kept as they change,
/// to undo them from each magnetometer reading at its time.
#[derive(Debug, Clone, Default)]
pub(crate) struct Telemetry {
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
    pub(crate) fn absorb(&mut self, msg: &MavMessage) -> bool {
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

    /// Whether compass k is external (COMPASS_EXTERNAL, COMPASS_EXTERN2, ...: non-zero), when
    /// the vehicle has sent that parameter.
    pub(crate) fn compass_external(&self, k: u8) -> Option<bool> {
        let name = crate::calib::ardupilot::single(crate::calib::ardupilot::Single::External, k)?;
        self.params.get(&name).map(|v| *v != 0.0)
    }

    /// Every parameter of the vehicle's list has arrived.
    pub(crate) fn list_complete(&self) -> bool {
        self.param_count
            .is_some_and(|n| self.indices_seen == n as usize)
    }

    /// The correction of compass k in force now, and where it comes from.
    pub fn current(&self, k: u8) -> Option<(Correction, CorrectionSource)> {
        if let Some(c) = correction(&self.params, k, self.list_complete()) {
            return Some((c, CorrectionSource::Params));
        }
        match (k, self.sensor_offsets_mg) {
            (0, Some(o)) if !self.has_compass0_offsets() => {
                Some((Correction::offsets_only(o), CorrectionSource::SensorOffsets))
            }
            _ => None,
        }
    }

    /// Whether COMPASS_OFS_X has arrived (the parameters then describe compass 0, not
    /// SENSOR_OFFSETS).
    fn has_compass0_offsets(&self) -> bool {
        triple(Triple::Ofs, 0).is_some_and(|[x, _, _]| self.params.contains_key(&x))
    }

    /// The raw field (uT) behind compass k's reading `mag_mg` (mGauss, as streamed) at time
    /// `t_s`, undone with the correction in force now. `None` (counted in `held`) until one is
    /// known.
    pub(crate) fn undo(&mut self, k: u8, mag_mg: Vec3, t_s: f64) -> Option<Vec3> {
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
    pub(crate) fn last_used(&self, k: u8) -> Option<(Correction, CorrectionSource)> {
        self.in_use.get(k as usize).copied().flatten()
    }

    /// The onboard calibrations used, one per compass undone: the one in force at the log's end
    /// (the vehicle flies with it afterwards), with the vehicle's parameters.
    pub(crate) fn onboard_cals(&self, sources: &BTreeMap<u8, String>) -> Vec<OnboardCal> {
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
    pub(crate) fn describe(&self, sources: &BTreeMap<u8, String>) -> (Vec<String>, Vec<String>) {
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
        let names = crate::calib::ardupilot::correction_names(0).unwrap();
        names.into_iter().zip(v).collect()
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
