//! Temperature calibrations as flight-stack parameters, names, scales and ranges as the stacks
//! define them:
//!
//! * ArduPilot (`AP_InertialSensor_tempcal.cpp`): INS_TCAL{n}_ENABLE (0 disabled, 1 enabled,
//!   2 learn), INS_TCAL{n}_TMIN/TMAX (deg C, range -70..80, TMAX at least 10 above TMIN),
//!   INS_TCAL{n}_ACC{k}_{X,Y,Z} and GYR{k} (k = 1..3, the coefficient of (T - 35)^k times 1e6),
//!   n = 1..3 for IMU instance 0..2.
//! * PX4 (`temp_comp_params_{accel,gyro}*.yaml`): TC_A_ENABLE and TC_G_ENABLE (boolean),
//!   TC_A{n}_ID / TC_G{n}_ID (int32, the sensor's device id), TC_*{n}_TREF/TMIN/TMAX (deg C,
//!   float), TC_*{n}_X{k}_{0,1,2} (float, the coefficient of (T - TREF)^k for axis x, y, z,
//!   unscaled), n = 0..3.
//!
//! Pure formatting: the caller writes the text.

use super::{TempCal, TempOutcome, ARDUPILOT_SCALE};
use crate::calib::export::Param;

/// ArduPilot's IMU instances with a temperature calibration (INS_TCAL1..3).
pub const ARDUPILOT_INSTANCES: usize = 3;
/// PX4's accelerometer and gyro slots (TC_A0..3, TC_G0..3).
pub const PX4_SLOTS: usize = 4;

/// One IMU instance to export: its 0-based instance number (ArduPilot's INS_TCAL{index + 1}, PX4's
/// slot `index`), its name, the device id of its sensors where the log gives it, and its outcome.
#[derive(Debug, Clone, Copy)]
pub struct InstanceExport<'a> {
    pub index: usize,
    pub name: &'a str,
    pub device_id: Option<u32>,
    pub outcome: &'a TempOutcome,
}

/// ArduPilot's INS_TCAL{index + 1}_* of a calibration (`None` past INS_TCAL3).
pub fn ardupilot_params(index: usize, c: &TempCal) -> Option<Vec<Param>> {
    if index >= ARDUPILOT_INSTANCES {
        return None;
    }
    let n = index + 1;
    let mut out: Vec<Param> = vec![
        (format!("INS_TCAL{n}_ENABLE"), 1.0),
        (format!("INS_TCAL{n}_TMIN"), c.tmin_c),
        (format!("INS_TCAL{n}_TMAX"), c.tmax_c),
    ];
    for (s, curves) in [("ACC", &c.accel), ("GYR", &c.gyro)] {
        for k in 1..=3 {
            for (a, axis) in ["X", "Y", "Z"].iter().enumerate() {
                out.push((
                    format!("INS_TCAL{n}_{s}{k}_{axis}"),
                    curves.axes[a].ardupilot[k] * ARDUPILOT_SCALE,
                ));
            }
        }
    }
    Some(out)
}

/// PX4's TC_A{slot}_* and TC_G{slot}_* of a calibration, each with whether it is an int32 (`None`
/// past slot 3). The id is 0 (no sensor) when the log gives none.
pub fn px4_params(slot: usize, device_id: Option<u32>, c: &TempCal) -> Option<Vec<(Param, bool)>> {
    if slot >= PX4_SLOTS {
        return None;
    }
    let mut out = vec![];
    for (s, curves) in [('A', &c.accel), ('G', &c.gyro)] {
        out.push((
            (format!("TC_{s}{slot}_ID"), device_id.map_or(0.0, f64::from)),
            true,
        ));
        out.push(((format!("TC_{s}{slot}_TREF"), c.px4_tref_c), false));
        out.push(((format!("TC_{s}{slot}_TMIN"), c.tmin_c), false));
        out.push(((format!("TC_{s}{slot}_TMAX"), c.tmax_c), false));
        for k in 0..4 {
            for a in 0..3 {
                out.push((
                    (format!("TC_{s}{slot}_X{k}_{a}"), curves.axes[a].px4[k]),
                    false,
                ));
            }
        }
    }
    Some(out)
}

/// The range ArduPilot's or PX4's parameter definitions document for a temperature-calibration
/// parameter (min, max); the others are float32 with no documented range (finite, within f32).
pub fn documented_range(name: &str) -> (f64, f64) {
    let f32_max = f64::from(f32::MAX);
    if name.starts_with("INS_TCAL") {
        if name.ends_with("_ENABLE") {
            return (0.0, 2.0);
        }
        if name.ends_with("_TMIN") || name.ends_with("_TMAX") {
            return (-70.0, 80.0);
        }
    }
    if name == "TC_A_ENABLE" || name == "TC_G_ENABLE" {
        return (0.0, 1.0);
    }
    if name.starts_with("TC_") && name.ends_with("_ID") {
        return (f64::from(i32::MIN), f64::from(i32::MAX));
    }
    (-f32_max, f32_max)
}

/// A value as the stacks store it (float32), in the shortest text that reads back the same.
fn value(v: f64) -> String {
    format!("{}", v as f32)
}

fn refusal_line(comment: &str, i: &InstanceExport<'_>, reason: &dyn std::fmt::Display) -> String {
    format!(
        "{comment} IMU {} ({}): no temperature calibration: {reason}\n",
        i.index, i.name
    )
}

/// ArduPilot `.parm` text ("NAME VALUE" per line): every calibrated instance's INS_TCALn_*, the
/// others as comments with the reason.
pub fn ardupilot_file(instances: &[InstanceExport<'_>]) -> String {
    let mut out = String::from("# imucald temperature calibration for ArduPilot (load with a GCS or `param load`, then reboot)\n# bias = c1 x + c2 x^2 + c3 x^3 with x = T - 35 C; INS_TCALn_ACCk/GYRk = ck * 1e6 (m/s^2, rad/s per C^k)\n");
    for i in instances {
        match i.outcome {
            TempOutcome::Refused(r) => out += &refusal_line("#", i, r),
            TempOutcome::Calibrated(c) => match ardupilot_params(i.index, c) {
                Some(params) => {
                    for (n, v) in params {
                        out += &format!("{n} {}\n", value(v));
                    }
                }
                None => out += &format!("# IMU {} ({}): ArduPilot has INS_TCAL1..{ARDUPILOT_INSTANCES} only: not written\n", i.index, i.name),
            },
        }
    }
    out
}

/// PX4/QGroundControl `.params` text (vehicle, component, name, value, type: 6 int32, 9 float):
/// TC_A_ENABLE and TC_G_ENABLE once, then every calibrated instance's slot.
pub fn px4_file(instances: &[InstanceExport<'_>]) -> String {
    let mut out = String::from("# imucald temperature calibration for PX4 (QGroundControl parameter file; reboot, then calibrate the accelerometer and gyro again)\n# offset = X0 + X1 dT + X2 dT^2 + X3 dT^3, dT = clip(T, TMIN, TMAX) - TREF, subtracted from the reading\n# Vehicle-Id\tComponent-Id\tName\tValue\tType\n");
    let line = |n: &str, v: f64, int: bool| {
        if int {
            format!("1\t1\t{n}\t{}\t6\n", v as i64)
        } else {
            format!("1\t1\t{n}\t{}\t9\n", value(v))
        }
    };
    if instances
        .iter()
        .any(|i| matches!(i.outcome, TempOutcome::Calibrated(_)))
    {
        out += &line("TC_A_ENABLE", 1.0, true);
        out += &line("TC_G_ENABLE", 1.0, true);
    }
    for i in instances {
        match i.outcome {
            TempOutcome::Refused(r) => out += &refusal_line("#", i, r),
            TempOutcome::Calibrated(c) => match px4_params(i.index, i.device_id, c) {
                Some(params) => {
                    if i.device_id.is_none() {
                        out += &format!("# IMU {} ({}): the log gives no device id: set TC_A{0}_ID and TC_G{0}_ID to the sensors' before loading\n", i.index, i.name);
                    }
                    for ((n, v), int) in params {
                        out += &line(&n, v, int);
                    }
                }
                None => {
                    out += &format!(
                        "# IMU {} ({}): PX4 has TC_A0..{} only: not written\n",
                        i.index,
                        i.name,
                        PX4_SLOTS - 1
                    )
                }
            },
        }
    }
    out
}
