//! A temperature calibration the flight controller applied before logging, read from its
//! parameters, and undone: the readings as the sensor gave them.

use super::{ARDUPILOT_SCALE, ARDUPILOT_TREF_C};
use crate::types::Sample;
use std::collections::BTreeMap;

/// The correction a flight controller subtracted from an IMU's readings: per sensor and axis a
/// cubic in (clamped T - `ref_c`), `c[k]` in the sensor's unit per C^k, less its value at the
/// calibration temperature where the stack does so.
#[derive(Debug, Clone, PartialEq)]
pub struct Applied {
    pub tmin_c: f64,
    pub tmax_c: f64,
    pub ref_c: f64,
    /// [axis][k]: accelerometer m/s^2 per C^k, gyro rad/s per C^k.
    pub accel: [[f64; 4]; 3],
    pub gyro: [[f64; 4]; 3],
    /// The temperature whose correction is added back (ArduPilot's INS_ACCn_CALTEMP /
    /// INS_GYRn_CALTEMP), deg C: accelerometer, gyro.
    pub cal_temp_c: [Option<f64>; 2],
}

fn cubic(c: &[f64; 4], x: f64) -> f64 {
    c[0] + x * (c[1] + x * (c[2] + x * c[3]))
}

impl Applied {
    /// ArduPilot's INS_TCAL{instance + 1}_* when INS_TCAL{n}_ENABLE is 1 (enabled, not learning).
    pub fn ardupilot(params: &BTreeMap<String, f64>, instance: usize) -> Option<Applied> {
        let n = instance + 1;
        let p = |name: String| params.get(&name).copied().filter(|v| v.is_finite());
        if p(format!("INS_TCAL{n}_ENABLE"))? != 1.0 {
            return None;
        }
        let coeffs = |s: &str| -> [[f64; 4]; 3] {
            std::array::from_fn(|a| {
                let axis = ["X", "Y", "Z"][a];
                let mut c = [0.0; 4];
                for (k, ck) in c.iter_mut().enumerate().skip(1) {
                    *ck = p(format!("INS_TCAL{n}_{s}{k}_{axis}")).unwrap_or(0.0) / ARDUPILOT_SCALE;
                }
                c
            })
        };
        Some(Applied {
            tmin_c: p(format!("INS_TCAL{n}_TMIN")).unwrap_or(0.0),
            tmax_c: p(format!("INS_TCAL{n}_TMAX")).unwrap_or(70.0),
            ref_c: ARDUPILOT_TREF_C,
            accel: coeffs("ACC"),
            gyro: coeffs("GYR"),
            cal_temp_c: [
                p(format!("INS_ACC{n}_CALTEMP")).filter(|t| *t > -80.0),
                p(format!("INS_GYR{n}_CALTEMP")).filter(|t| *t > -80.0),
            ],
        })
    }

    /// PX4's TC_A* slot whose TC_An_ID is `accel_id` when TC_A_ENABLE is 1, and TC_G* slot whose
    /// TC_Gn_ID is `gyro_id` when TC_G_ENABLE is 1 (the accelerometer's and the gyro's device ids
    /// differ); a sensor whose correction is not enabled keeps zero coefficients. `None` when
    /// neither is enabled, or when one enabled finds no slot of its device id (nothing can be
    /// undone: see [`Applied::px4_enabled`]).
    pub fn px4(
        params: &BTreeMap<String, f64>,
        accel_id: Option<u32>,
        gyro_id: Option<u32>,
    ) -> Option<Applied> {
        let p = |name: String| params.get(&name).copied().filter(|v| v.is_finite());
        type Slot = ([[f64; 4]; 3], [f64; 3]);
        // Not enabled: Some(None); enabled and found: Some(Some(slot)); enabled, not found: None.
        let slot = |s: char, id: Option<u32>| -> Option<Option<Slot>> {
            if p(format!("TC_{s}_ENABLE")) != Some(1.0) {
                return Some(None);
            }
            let id = f64::from(id?);
            let j = (0..4).find(|j| p(format!("TC_{s}{j}_ID")) == Some(id))?;
            let c = std::array::from_fn(|a| {
                std::array::from_fn(|k| p(format!("TC_{s}{j}_X{k}_{a}")).unwrap_or(0.0))
            });
            let range = [
                p(format!("TC_{s}{j}_TMIN")).unwrap_or(0.0),
                p(format!("TC_{s}{j}_TMAX")).unwrap_or(100.0),
                p(format!("TC_{s}{j}_TREF")).unwrap_or(25.0),
            ];
            Some(Some((c, range)))
        };
        let (a, g) = (slot('A', accel_id)?, slot('G', gyro_id)?);
        // One range for both: the slots a PX4 tool writes share it; the gyro's wins.
        let range = g.as_ref().or(a.as_ref()).map(|s| s.1)?;
        Some(Applied {
            tmin_c: range[0],
            tmax_c: range[1],
            ref_c: range[2],
            accel: a.map_or([[0.0; 4]; 3], |s| s.0),
            gyro: g.map_or([[0.0; 4]; 3], |s| s.0),
            cal_temp_c: [None, None],
        })
    }

    /// Whether PX4's parameters enable a temperature correction (TC_A_ENABLE or TC_G_ENABLE 1).
    pub fn px4_enabled(params: &BTreeMap<String, f64>) -> bool {
        ["TC_A_ENABLE", "TC_G_ENABLE"]
            .iter()
            .any(|n| params.get(*n) == Some(&1.0))
    }

    /// What was subtracted at `temp_c`: accelerometer (m/s^2) and gyro (rad/s) per axis.
    pub fn correction(&self, temp_c: f64) -> ([f64; 3], [f64; 3]) {
        let clamp = |t: f64| t.clamp(self.tmin_c.min(self.tmax_c), self.tmax_c.max(self.tmin_c));
        let x = clamp(temp_c) - self.ref_c;
        let at = |c: &[[f64; 4]; 3], cal: Option<f64>| {
            std::array::from_fn(|a| {
                cubic(&c[a], x) - cal.map_or(0.0, |t| cubic(&c[a], clamp(t) - self.ref_c))
            })
        };
        (
            at(&self.accel, self.cal_temp_c[0]),
            at(&self.gyro, self.cal_temp_c[1]),
        )
    }

    /// The sample as the sensor gave it: the correction added back.
    pub fn undo(&self, s: &Sample) -> Sample {
        let Some(t) = s.temp_c else {
            return *s;
        };
        let (ca, cg) = self.correction(t);
        let add =
            |v: Option<[f64; 3]>, c: [f64; 3]| v.map(|v| [v[0] + c[0], v[1] + c[1], v[2] + c[2]]);
        Sample {
            accel_mps2: add(s.accel_mps2, ca),
            gyro_rad_s: add(s.gyro_rad_s, cg),
            ..*s
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_enabled_ardupilot_calibration_is_added_back_and_a_disabled_one_is_none() {
        let mut p = BTreeMap::new();
        p.insert("INS_TCAL2_ENABLE".to_string(), 1.0);
        p.insert("INS_TCAL2_TMIN".to_string(), 20.0);
        p.insert("INS_TCAL2_TMAX".to_string(), 45.0);
        p.insert("INS_TCAL2_GYR1_Z".to_string(), 150.0);
        p.insert("INS_TCAL2_ACC2_X".to_string(), -8.0);
        let a = Applied::ardupilot(&p, 1).unwrap();
        let (ca, cg) = a.correction(40.0);
        // 150e-6 * 5 and -8e-6 * 25.
        assert!((cg[2] - 7.5e-4).abs() < 1e-15, "{cg:?}");
        assert!((ca[0] + 2e-4).abs() < 1e-15, "{ca:?}");
        // Clamped at TMAX.
        assert_eq!(a.correction(60.0), a.correction(45.0));
        let s = Sample {
            temp_c: Some(40.0),
            gyro_rad_s: Some([0.0; 3]),
            ..Default::default()
        };
        assert!((a.undo(&s).gyro_rad_s.unwrap()[2] - 7.5e-4).abs() < 1e-15);
        assert!(Applied::ardupilot(&p, 0).is_none());
        p.insert("INS_TCAL2_ENABLE".to_string(), 2.0);
        assert!(Applied::ardupilot(&p, 1).is_none());
    }

    #[test]
    fn a_px4_slot_is_found_by_its_device_id() {
        let mut p = BTreeMap::new();
        for (n, v) in [
            ("TC_G_ENABLE", 1.0),
            ("TC_G1_ID", 2_490_378.0),
            ("TC_G1_TREF", 30.0),
            ("TC_G1_TMIN", 15.0),
            ("TC_G1_TMAX", 45.0),
            ("TC_G1_X0_1", 0.01),
            ("TC_G1_X1_1", 1e-4),
        ] {
            p.insert(n.to_string(), v);
        }
        let a = Applied::px4(&p, Some(1_310_988), Some(2_490_378)).unwrap();
        let (ca, cg) = a.correction(40.0);
        assert!((cg[1] - 0.011).abs() < 1e-15, "{cg:?}");
        // TC_A_ENABLE absent: the accelerometer keeps its readings.
        assert_eq!(ca, [0.0; 3]);
        assert!(Applied::px4(&p, None, Some(7)).is_none());
        assert!(Applied::px4(&p, None, None).is_none());
        assert!(Applied::px4_enabled(&p));
        p.insert("TC_G_ENABLE".to_string(), 0.0);
        assert!(Applied::px4(&p, None, Some(7)).is_none());
        assert!(!Applied::px4_enabled(&p));
    }
}
