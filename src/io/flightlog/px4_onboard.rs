//! PX4's onboard magnetometer calibration in a ULog's parameters: CAL_MAGn (offsets, scales,
//! rotation) matched to the compasses by device id, undone from the corrected field, and the
//! report of the CAL_MAGn and CAL_ACCn the log holds.

use super::{finite3, rows};
use crate::io::onboard::{OnboardCal, OnboardReport};
use crate::types::Vec3;
use nalgebra::{Matrix3, Vector3};
use std::collections::{BTreeMap, BTreeSet};

/// PX4's rotation enum for the ids this reader undoes: 0-7 yaw by 45 deg steps, 8-15 roll 180
/// then yaw.
fn px4_rotation(id: i64) -> Option<Matrix3<f64>> {
    let name = match id {
        0 => "NONE".to_string(),
        1..=7 => format!("YAW_{}", id * 45),
        8 => "ROLL_180".to_string(),
        9..=15 => format!("ROLL_180_YAW_{}", (id - 8) * 45),
        _ => return None,
    };
    crate::attitude::sensor_rotation(&name).ok()
}

/// PX4's magnetometer calibration n: (OFF gauss, S, device id), or why the log's parameters do not
/// give it, naming them (absent, CAL_MAGn_ID 0, a value not finite). Firmware without the scale or
/// off-diagonal parameters applied none: 1 and 0 stand for those.
fn px4_mag_cal(
    params: &BTreeMap<String, f64>,
    n: u8,
) -> Result<([f64; 3], Matrix3<f64>, u32), String> {
    let name = |s: &str| format!("CAL_MAG{n}_{s}");
    let p = |s: &str| params.get(&name(s)).copied();
    let id = match p("ID") {
        None => return Err(format!("{} not in the log", name("ID"))),
        Some(v) if v > 0.0 && v < u32::MAX as f64 => v as u32,
        Some(v) => {
            return Err(format!(
                "{} is {v} (no compass calibrated in that slot)",
                name("ID")
            ))
        }
    };
    let missing: Vec<String> = ["XOFF", "YOFF", "ZOFF"]
        .iter()
        .filter(|s| p(s).is_none())
        .map(|s| name(s))
        .collect();
    if !missing.is_empty() {
        return Err(format!("{} not in the log", missing.join(", ")));
    }
    let get = |s: &str, default: f64| p(s).unwrap_or(default);
    let named = [
        ("XOFF", get("XOFF", 0.0)),
        ("YOFF", get("YOFF", 0.0)),
        ("ZOFF", get("ZOFF", 0.0)),
        ("XSCALE", get("XSCALE", 1.0)),
        ("YSCALE", get("YSCALE", 1.0)),
        ("ZSCALE", get("ZSCALE", 1.0)),
        ("XODIAG", get("XODIAG", 0.0)),
        ("YODIAG", get("YODIAG", 0.0)),
        ("ZODIAG", get("ZODIAG", 0.0)),
    ];
    let bad: Vec<String> = named
        .iter()
        .filter(|(_, v)| !v.is_finite())
        .map(|(s, _)| name(s))
        .collect();
    if !bad.is_empty() {
        return Err(format!("{} not finite", bad.join(", ")));
    }
    let v = named.map(|(_, v)| v);
    let off = [v[0], v[1], v[2]];
    let s = crate::calib::ardupilot::symmetric([v[3], v[4], v[5]], [v[6], v[7], v[8]]);
    Ok((off, s, id))
}

/// The rotation PX4 applies to calibration n's compass (CAL_MAGn_ROT, -1: the board's
/// SENS_BOARD_ROT), or why it is not one this reader undoes.
fn px4_mag_rotation(params: &BTreeMap<String, f64>, n: u8) -> Result<Matrix3<f64>, String> {
    let own = format!("CAL_MAG{n}_ROT");
    let rot = params.get(&own).copied().unwrap_or(-1.0);
    let (name, id) = if rot < 0.0 {
        let board = params.get("SENS_BOARD_ROT").copied().unwrap_or(0.0);
        ("SENS_BOARD_ROT".to_string(), board)
    } else {
        (own, rot)
    };
    Some(id)
        .filter(|v| v.is_finite() && v.fract() == 0.0)
        .and_then(|v| px4_rotation(v as i64))
        .ok_or_else(|| {
            format!(
                "{name} is {id}, not a rotation this reader undoes (0-15: yaw in 45 deg steps, roll 180 then yaw)"
            )
        })
}

/// The calibration slot of the prime compass by the parameters (CAL_MAG_PRIME = CAL_MAGn_ID;
/// without CAL_MAG_PRIME, slot 0), for a corrected field whose records name no device; or why
/// there is none.
fn px4_prime_slot(params: &BTreeMap<String, f64>) -> Result<u8, String> {
    let id = |n: u8| params.get(&format!("CAL_MAG{n}_ID")).copied();
    match params.get("CAL_MAG_PRIME").copied() {
        Some(p) if p != 0.0 => (0..4u8)
            .find(|n| id(*n) == Some(p))
            .ok_or_else(|| format!("CAL_MAG_PRIME is {p}, the CAL_MAGn_ID of no slot")),
        _ if id(0).is_some() => Ok(0),
        _ => Err("neither CAL_MAG_PRIME nor CAL_MAG0_ID in the log".into()),
    }
}

/// The PX4 correction of slot n undone: gauss (corrected, body) in, uT out.
#[derive(Debug)]
pub(crate) struct Px4Undo {
    inv: Matrix3<f64>,
    /// R OFF, gauss.
    off_body: Vector3<f64>,
}

impl Px4Undo {
    /// Slot n's correction to undo, or why the parameters do not allow it.
    fn new(params: &BTreeMap<String, f64>, n: u8) -> Result<Px4Undo, String> {
        let (off, s, _) = px4_mag_cal(params, n)?;
        let r = px4_mag_rotation(params, n)?;
        let inv = (r * s * r.transpose())
            .try_inverse()
            .ok_or_else(|| format!("CAL_MAG{n}'s scale matrix is singular"))?;
        Ok(Px4Undo {
            inv,
            off_body: r * Vector3::from(off),
        })
    }

    /// `None` when the reading is not finite.
    pub(crate) fn apply(&self, m_ga: Vec3) -> Option<Vec3> {
        let u = self.inv * Vector3::from(m_ga) + self.off_body;
        finite3([u[0] * 100.0, u[1] * 100.0, u[2] * 100.0])
    }
}

/// PX4's magnetometer calibrations as the log's parameters give them, each to undo or not.
#[derive(Debug)]
pub(crate) struct Px4Cals {
    /// Slot n's correction (CAL_MAGn_*) to undo, or why it cannot be.
    slots: Vec<Result<Px4Undo, String>>,
    /// The slot of each device id (CAL_MAGn_ID, complete or not; the first where two share one).
    by_device: BTreeMap<u32, u8>,
    /// The prime compass's slot for a corrected field whose records name no device
    /// ([`px4_prime_slot`]).
    prime: Result<u8, String>,
}

impl Px4Cals {
    pub(crate) fn new(params: &BTreeMap<String, f64>) -> Px4Cals {
        let mut by_device = BTreeMap::new();
        for n in 0..4u8 {
            let id = params.get(&format!("CAL_MAG{n}_ID")).copied();
            if let Some(id) = id.filter(|v| *v > 0.0 && *v < u32::MAX as f64) {
                by_device.entry(id as u32).or_insert(n);
            }
        }
        Px4Cals {
            slots: (0..4u8).map(|n| Px4Undo::new(params, n)).collect(),
            by_device,
            prime: px4_prime_slot(params),
        }
    }

    /// The slot a corrected reading was corrected with: by the device id its record names (the
    /// compass PX4 selected for that reading), else, for the prime compass's stream
    /// (`prime`), by the parameters; or why none is known.
    pub(crate) fn slot(&self, device_id: Option<u32>, prime: bool) -> Result<u8, String> {
        match device_id.filter(|d| *d != 0) {
            Some(d) => self
                .by_device
                .get(&d)
                .copied()
                .ok_or_else(|| format!("its device id {d} is no CAL_MAGn_ID")),
            None if prime => self.prime.clone(),
            None => Err("its records name no device id to find its CAL_MAGn by".into()),
        }
    }

    /// Slot n's correction, or why it cannot be undone.
    pub(crate) fn undo(&self, n: u8) -> Result<&Px4Undo, String> {
        match self.slots.get(n as usize) {
            Some(Ok(u)) => Ok(u),
            Some(Err(why)) => Err(why.clone()),
            None => Err(format!("no slot CAL_MAG{n}")),
        }
    }
}

pub(crate) fn px4_onboard(
    params: &BTreeMap<String, f64>,
    mag_ids: &BTreeMap<u8, u32>,
    accel_ids: &BTreeMap<u8, u32>,
    prime_source: Option<&str>,
    prime_slots: &BTreeSet<u8>,
) -> OnboardReport {
    let mut r = OnboardReport {
        stack: "px4".into(),
        ..Default::default()
    };
    let pick = |prefix: &str| -> BTreeMap<String, f64> {
        params
            .range(prefix.to_string()..)
            .take_while(|(k, _)| k.starts_with(prefix))
            .map(|(k, v)| (k.clone(), *v))
            .collect()
    };
    for n in 0..4u8 {
        let Ok((off, s, id)) = px4_mag_cal(params, n) else {
            continue;
        };
        let mut sources: Vec<String> = mag_ids
            .iter()
            .filter(|(_, d)| **d == id)
            .map(|(k, _)| format!("sensor_mag[{k}]"))
            .collect();
        if prime_slots.contains(&n) {
            sources.extend(prime_source.map(String::from));
        }
        r.mag.push(OnboardCal {
            instance: n,
            device_id: Some(id),
            sources,
            offset: off.map(|o| o * 100.0),
            matrix: rows(&s),
            units: crate::types::CalUnits::Ut,
            params: pick(&format!("CAL_MAG{n}_")),
        });
    }
    for n in 0..4u8 {
        let p = |s: &str| params.get(&format!("CAL_ACC{n}_{s}")).copied();
        let Some(id) = p("ID").filter(|v| *v > 0.0 && *v < u32::MAX as f64) else {
            continue;
        };
        let (Some(x), Some(y), Some(z)) = (p("XOFF"), p("YOFF"), p("ZOFF")) else {
            continue;
        };
        let d = [
            p("XSCALE").unwrap_or(1.0),
            p("YSCALE").unwrap_or(1.0),
            p("ZSCALE").unwrap_or(1.0),
        ];
        let id = id as u32;
        r.accel.push(OnboardCal {
            instance: n,
            device_id: Some(id),
            sources: accel_ids
                .iter()
                .filter(|(_, d)| **d == id)
                .map(|(k, _)| format!("sensor_accel[{k}]"))
                .collect(),
            offset: [x, y, z],
            matrix: rows(&Matrix3::from_diagonal(&Vector3::from(d))),
            units: crate::types::CalUnits::Mps2,
            params: pick(&format!("CAL_ACC{n}_")),
        });
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn px4_undo_with_board_rotation() {
        let mut p = BTreeMap::new();
        for (n, v) in [
            ("CAL_MAG0_ID", 1234.0),
            ("CAL_MAG0_ROT", -1.0),
            ("SENS_BOARD_ROT", 4.0),
            ("CAL_MAG0_XOFF", 0.1),
            ("CAL_MAG0_YOFF", -0.2),
            ("CAL_MAG0_ZOFF", 0.3),
            ("CAL_MAG0_XSCALE", 1.1),
            ("CAL_MAG0_YSCALE", 0.9),
            ("CAL_MAG0_ZSCALE", 1.0),
            ("CAL_MAG0_XODIAG", 0.05),
            ("CAL_MAG_PRIME", 1234.0),
        ] {
            p.insert(n.to_string(), v);
        }
        let raw_sensor = Vector3::new(0.2, 0.1, -0.4);
        let (off, s, _) = px4_mag_cal(&p, 0).unwrap();
        let r = px4_mag_rotation(&p, 0).unwrap();
        let corrected = r * (s * (raw_sensor - Vector3::from(off)));
        let u = Px4Undo::new(&p, px4_prime_slot(&p).unwrap()).unwrap();
        let back = u.apply([corrected[0], corrected[1], corrected[2]]).unwrap();
        let want = r * raw_sensor * 100.0;
        for i in 0..3 {
            assert!((back[i] - want[i]).abs() < 1e-9, "{back:?} {want:?}");
        }
    }

    #[test]
    fn px4_undo_names_what_the_parameters_lack() {
        let params = |kv: &[(&str, f64)]| -> BTreeMap<String, f64> {
            kv.iter().map(|(k, v)| (k.to_string(), *v)).collect()
        };
        let why = |p: &BTreeMap<String, f64>| Px4Undo::new(p, 0).unwrap_err();
        assert_eq!(why(&params(&[])), "CAL_MAG0_ID not in the log");
        assert_eq!(
            why(&params(&[("CAL_MAG0_ID", 0.0)])),
            "CAL_MAG0_ID is 0 (no compass calibrated in that slot)"
        );
        let partial = [("CAL_MAG0_ID", 7.0), ("CAL_MAG0_YOFF", 0.1)];
        assert_eq!(
            why(&params(&partial)),
            "CAL_MAG0_XOFF, CAL_MAG0_ZOFF not in the log"
        );
        let complete = [
            ("CAL_MAG0_ID", 7.0),
            ("CAL_MAG0_XOFF", 0.1),
            ("CAL_MAG0_YOFF", 0.1),
            ("CAL_MAG0_ZOFF", 0.1),
        ];
        let mut p = params(&complete);
        p.insert("CAL_MAG0_XSCALE".into(), f64::NAN);
        assert_eq!(why(&p), "CAL_MAG0_XSCALE not finite");
        let mut p = params(&complete);
        p.insert("CAL_MAG0_ROT".into(), 38.0);
        assert!(
            why(&p).starts_with("CAL_MAG0_ROT is 38, not a rotation"),
            "{}",
            why(&p)
        );
        let mut p = params(&complete);
        p.insert("SENS_BOARD_ROT".into(), 20.0);
        assert!(why(&p).starts_with("SENS_BOARD_ROT is 20,"), "{}", why(&p));
        assert!(Px4Undo::new(&params(&complete), 0).is_ok());
        let mut p = params(&complete);
        p.insert("CAL_MAG_PRIME".into(), 5.0);
        assert_eq!(
            px4_prime_slot(&p).unwrap_err(),
            "CAL_MAG_PRIME is 5, the CAL_MAGn_ID of no slot"
        );
    }
}
