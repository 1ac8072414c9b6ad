//! Every effect a diagnosis names ends in its fix: the flight controller's own parameters that
//! remove it (ArduPilot `.parm`, PX4 `.params`), each with the held-out shrink it brings, or, where
//! no parameter of either stack compensates the effect, the calibration or the physical change
//! that does. Pure: the report in, the files' text out (the caller writes them).
//!
//! * Motor field (`motor_interference`, raw += k x driver): ArduPilot adds COMPASS_MOT x throttle
//!   (0..1, COMPASS_MOTCT 1) or x current (A, COMPASS_MOTCT 2) after the soft-iron matrix, in
//!   mGauss per full throttle or per ampere (AP_Compass parameter docs), so COMPASS_MOT =
//!   -(M k) x 10 ([`crate::calib::export::ardupilot_motor`]), M the fitted matrix scaled to unit
//!   determinant. PX4 adds CAL_MAGn_[XYZ]COMP x power
//!   to the raw reading before the offset, in gauss per unit throttle (CAL_MAG_COMP_TYP 1) or
//!   gauss per kiloampere (CAL_MAG_COMP_TYP 2) (PX4's magnetometer calibration parameters), so
//!   XCOMP = -k x 0.01 G/uT for throttle and -k x 10 for current
//!   ([`crate::calib::export::px4_motor`]).
//! * Misalignment between magnetometer and accelerometer (body = R mag): the compass's mounting,
//!   COMPASS_ORIENT / CAL_MAG0_ROT when R is a rotation of the stacks' table, else a custom
//!   rotation: ArduPilot COMPASS_ORIENT 101 (Custom 1) with CUST_ROT_ENABLE 1 and
//!   CUST_ROT1_ROLL/PITCH/YAW, PX4 CAL_MAG0_ROT 100 (ROTATION_CUSTOM) with
//!   CAL_MAG0_ROLL/PITCH/YAW (both Euler angles in degrees, R = Rz(yaw) Ry(pitch) Rx(roll)).
//! * Cross-axis terms: the off-diagonal soft-iron terms COMPASS_ODI_X/Y/Z and
//!   CAL_MAG0_[XYZ]ODIAG (ArduPilot's DIA/ODI layout, relative to the diagonal).
//! * Temperature: no compass parameter; the temperature calibration is the fix (ArduPilot
//!   INS_TCAL1_ENABLE and the INS_TCALn_* it learns, PX4 TC_A_ENABLE / TC_G_ENABLE / TC_M_ENABLE).
//! * Heading offset, cubic scale, gyro drift: no parameter removes them; the text names the
//!   change that does.
//!
//! A parameter the data leave under 3 sigma from zero is written as 0 (with a comment).

use super::report::{DiagnosisReport, EffectShrink, ParamEstimate};
use super::{Effect, MIN_SIZE_SIGMAS};
use crate::calib::export::{ardupilot_motor, px4_motor};
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// ArduPilot's COMPASS_MOT range (AP_Compass parameter docs), mGauss per unit.
pub const ARDUPILOT_MOT_LIMIT_MGAUSS: f64 = 1000.0;
/// ArduPilot's COMPASS_ORIENT value of a custom rotation (Custom 1).
pub const ARDUPILOT_CUSTOM_ORIENT: f64 = 101.0;
/// PX4's CAL_MAGn_ROT value of a custom rotation (ROTATION_CUSTOM).
pub const PX4_CUSTOM_ROT: f64 = 100.0;
/// gauss per uT.
const GAUSS_PER_UT: f64 = 0.01;

/// What removes an effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Remedy {
    /// The flight controller's parameters (written to the files).
    Parameters,
    /// The temperature calibration (ArduPilot INS_TCAL, PX4 TC_*), no compass parameter.
    TemperatureCalibration,
    /// No parameter of either stack: a physical change or a procedure.
    NoParameter,
}

/// The fix of one named effect.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Fix {
    pub effect: Effect,
    pub remedy: Remedy,
    /// ArduPilot parameters (name, value).
    pub ardupilot: Vec<(String, f64)>,
    /// PX4 parameters (name, value).
    pub px4: Vec<(String, f64)>,
    /// What else to know or do (comment lines).
    pub notes: Vec<String>,
    /// The held-out residual without and with the effect.
    pub shrink: Option<EffectShrink>,
}

/// A parameter's value, or 0 when it is under [`MIN_SIZE_SIGMAS`] from zero (and a note).
fn determined_value(
    p: &BTreeMap<String, ParamEstimate>,
    name: &str,
    notes: &mut Vec<String>,
) -> f64 {
    let Some(v) = p.get(name) else {
        return 0.0;
    };
    if v.value.abs() >= MIN_SIZE_SIGMAS * v.sigma {
        v.value
    } else {
        notes.push(format!(
            "{name} {:.3} +- {:.3} {} is under {MIN_SIZE_SIGMAS} sigma: written as 0",
            v.value, v.sigma, v.unit
        ));
        0.0
    }
}

fn vec3_of(
    p: &BTreeMap<String, ParamEstimate>,
    names: [&str; 3],
    notes: &mut Vec<String>,
) -> Vector3<f64> {
    Vector3::new(
        determined_value(p, names[0], notes),
        determined_value(p, names[1], notes),
        determined_value(p, names[2], notes),
    )
}

/// The final model's magnetometer matrix scaled to unit determinant (ArduPilot's DIA near 1; the
/// field's overall scale is the vehicle's own, which a calibration holds in its radius), identity
/// when there is none.
fn unit_determinant(m: Option<[[f64; 3]; 3]>) -> [[f64; 3]; 3] {
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let Some(m) = m else { return id };
    let mm = Matrix3::from_fn(|r, c| m[r][c]);
    let d = mm.determinant();
    if !(d > 0.0) {
        return id;
    }
    let n = mm / d.cbrt();
    std::array::from_fn(|r| std::array::from_fn(|c| n[(r, c)]))
}

/// The motor field's parameters.
fn motor_fix(r: &DiagnosisReport, p: &BTreeMap<String, ParamEstimate>, fix: &mut Fix) {
    let k = vec3_of(p, ["k_x", "k_y", "k_z"], &mut fix.notes);
    let current = r.evidence.driver.as_deref() == Some("current");
    let m = unit_determinant(r.mag_matrix);
    let kk = [k.x, k.y, k.z];
    let mut ap = ardupilot_motor(&kk, &m, 0);
    if !current {
        // Same values per full throttle; only the measure differs.
        for (n, v) in ap.iter_mut() {
            if n == "COMPASS_MOTCT" {
                *v = 1.0;
            }
        }
    }
    if ap
        .iter()
        .any(|(n, v)| n.starts_with("COMPASS_MOT_") && v.abs() > ARDUPILOT_MOT_LIMIT_MGAUSS)
    {
        fix.notes.push(format!(
            "a COMPASS_MOT value is beyond ArduPilot's range of +-{ARDUPILOT_MOT_LIMIT_MGAUSS} mGauss: move the compass away from the power leads"
        ));
    }
    let mut px = if current {
        px4_motor(&kk, 0)
    } else {
        // px4_motor takes uT/A and writes gauss per kA (x 10); per unit throttle PX4 wants gauss
        // (x 0.01), so the field per unit is handed over scaled by 0.01 / 10.
        let scaled = kk.map(|x| x * GAUSS_PER_UT / 10.0);
        px4_motor(&scaled, 0)
    };
    if !current {
        for (n, v) in px.iter_mut() {
            if n == "CAL_MAG_COMP_TYP" {
                *v = 1.0;
            }
        }
    }
    // No "-0" in the files.
    fix.ardupilot = ap.into_iter().map(|(n, v)| (n, v + 0.0)).collect();
    fix.px4 = px.into_iter().map(|(n, v)| (n, v + 0.0)).collect();
    fix.notes.push(format!(
        "field per {}: {:.2}, {:.2}, {:.2} uT, in the axes the readings were logged in (PX4 applies it before CAL_MAG0_ROT: with a rotation set, turn it into the sensor's axes); moving the compass away from the power leads removes it at the source",
        if current { "ampere" } else { "unit throttle" },
        k.x,
        k.y,
        k.z
    ));
}

/// The compass mounting that takes the misalignment out.
fn misalignment_fix(p: &BTreeMap<String, ParamEstimate>, fix: &mut Fix) {
    let v = vec3_of(
        p,
        ["rotation_x_deg", "rotation_y_deg", "rotation_z_deg"],
        &mut fix.notes,
    );
    let r: Matrix3<f64> = crate::calib::model::rotation_from_vector(&v.map(f64::to_radians));
    let angle = v.norm();
    let table = crate::calib::mounting::Mounting::of_matrix(&r)
        .map(|m| m.ardupilot_compass_orient())
        .filter(|&n| n != 0);
    if let Some(n) = table {
        // A rotation of the table (never for a misalignment inside its range; kept for clarity).
        fix.ardupilot = vec![("COMPASS_ORIENT".into(), n as f64)];
        fix.px4 = vec![("CAL_MAG0_ROT".into(), n as f64)];
    } else {
        let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(r).euler_angles();
        let [roll, pitch, yaw] = [roll, pitch, yaw].map(f64::to_degrees);
        fix.ardupilot = vec![
            ("COMPASS_ORIENT".into(), ARDUPILOT_CUSTOM_ORIENT),
            ("CUST_ROT_ENABLE".into(), 1.0),
            ("CUST_ROT1_ROLL".into(), roll),
            ("CUST_ROT1_PITCH".into(), pitch),
            ("CUST_ROT1_YAW".into(), yaw),
        ];
        fix.px4 = vec![
            ("CAL_MAG0_ROT".into(), PX4_CUSTOM_ROT),
            ("CAL_MAG0_ROLL".into(), roll),
            ("CAL_MAG0_PITCH".into(), pitch),
            ("CAL_MAG0_YAW".into(), yaw),
        ];
        fix.notes.push(format!(
            "the compass is turned {angle:.2} deg against the accelerometer, none of the table's rotations: a custom rotation, relative to the mounting the readings were logged in (compose it with the vehicle's own COMPASS_ORIENT / CAL_MAG0_ROT when that is not none; ArduPilot's CUST_ROT1 is shared with any other custom rotation)"
        ));
    }
}

/// The off-diagonal soft-iron terms of the final model's matrix, relative to its mean diagonal.
fn cross_axis_fix(r: &DiagnosisReport, fix: &mut Fix) {
    let Some(m) = r.mag_matrix else {
        fix.remedy = Remedy::NoParameter;
        fix.notes.push("no magnetometer matrix: the accelerometer's cross-axis terms have no parameter in either stack; a six-position accelerometer calibration with cross-axis terms (not offered onboard) removes them".into());
        return;
    };
    let d = (m[0][0] + m[1][1] + m[2][2]) / 3.0;
    let s = |a: usize, b: usize| (m[a][b] + m[b][a]) / 2.0 / d;
    fix.ardupilot = vec![
        ("COMPASS_ODI_X".into(), s(0, 1)),
        ("COMPASS_ODI_Y".into(), s(0, 2)),
        ("COMPASS_ODI_Z".into(), s(1, 2)),
    ];
    fix.px4 = vec![
        ("CAL_MAG0_XODIAG".into(), s(0, 1)),
        ("CAL_MAG0_YODIAG".into(), s(0, 2)),
        ("CAL_MAG0_ZODIAG".into(), s(1, 2)),
    ];
    fix.notes.push("off-diagonal terms relative to the diagonal; they go with the vehicle's own offsets and diagonal only when those came from a full (ellipsoid) calibration: `imucald replay LOG --export` writes the whole set".into());
}

/// The fix of effect `e` as named in report `r`.
fn fix_of(r: &DiagnosisReport, e: Effect) -> Fix {
    let mut fix = Fix {
        effect: e,
        remedy: Remedy::Parameters,
        ardupilot: vec![],
        px4: vec![],
        notes: vec![],
        shrink: r.effect_shrink.get(e.name()).cloned(),
    };
    let empty = BTreeMap::new();
    let p = r.effects.get(e.name()).unwrap_or(&empty);
    match e {
        Effect::MotorInterference => motor_fix(r, p, &mut fix),
        Effect::MagAccelMisalignment => misalignment_fix(p, &mut fix),
        Effect::CrossAxis => cross_axis_fix(r, &mut fix),
        Effect::TemperatureBias => {
            fix.remedy = Remedy::TemperatureCalibration;
            fix.notes.push("no compass parameter compensates temperature: the temperature calibration is the fix (ArduPilot INS_TCAL1_ENABLE = 2 learns INS_TCALn_* on the next warm-up; PX4 TC_A_ENABLE / TC_G_ENABLE / TC_M_ENABLE with its thermal calibration)".into());
        }
        Effect::HeadingOffset => {
            fix.remedy = Remedy::NoParameter;
            fix.notes.push("no calibration parameter: the reference attitude and the sensors disagree in heading; align the reference (the external heading source or the autopilot's board orientation AHRS_ORIENTATION / SENS_BOARD_ROT) with the vehicle, checked against a known heading".into());
        }
        Effect::ScaleNonlinearity => {
            fix.remedy = Remedy::NoParameter;
            fix.notes.push("no parameter of either stack models a nonlinear scale: keep the sensor within its linear range (a wider range setting, or the compass further from strong fields such as magnets and steel)".into());
        }
        Effect::GyroBiasDrift => {
            fix.remedy = Remedy::NoParameter;
            fix.notes.push("no parameter holds a drifting gyro bias: let the vehicle warm up before arming (the gyro calibration at start-up, INS_GYR_CAL / the EKF's bias estimate, then starts from the warm bias), or the temperature calibration when it follows the temperature (INS_TCAL1_ENABLE, TC_G_ENABLE)".into());
        }
    }
    fix
}

/// The fixes of every effect the diagnosis named, in the order named.
pub fn fixes(r: &DiagnosisReport) -> Vec<Fix> {
    r.found.iter().map(|e| fix_of(r, *e)).collect()
}

/// The shrink an effect brings, as a comment.
fn shrink_comment(s: &Option<EffectShrink>, field_ut: f64) -> String {
    match s {
        Some(s) if s.mag_norm_with_ut.is_finite() && field_ut > 0.0 => format!(
            "held-out field-magnitude residual {:.2} -> {:.2} uT ({:.2} -> {:.2} % of the {:.1} uT field) with this effect; all channels {:.2} -> {:.2} noise units",
            s.mag_norm_without_ut,
            s.mag_norm_with_ut,
            100.0 * s.mag_norm_without_ut / field_ut,
            100.0 * s.mag_norm_with_ut / field_ut,
            field_ut,
            s.rms_without,
            s.rms_with
        ),
        Some(s) => format!(
            "held-out residual {:.2} -> {:.2} noise units with this effect",
            s.rms_without, s.rms_with
        ),
        None => "held-out shrink unknown".to_string(),
    }
}

/// A value as the files and the terminal show it: whole numbers (types, rotations, switches)
/// without decimals, others with `decimals`.
fn shown(v: f64, decimals: usize) -> String {
    if v.fract() == 0.0 && v.abs() < 1e6 {
        format!("{v:.0}")
    } else {
        format!("{v:.decimals$}")
    }
}

/// Integer-valued PX4 parameters (QGroundControl type 6, else 9: float).
fn px4_type(name: &str) -> u8 {
    if name.ends_with("_TYP") || name.ends_with("_ROT") {
        6
    } else {
        9
    }
}

/// The ArduPilot `.parm` text of the fixes.
pub fn ardupilot_text(r: &DiagnosisReport, fixes: &[Fix]) -> String {
    let mut out = String::from(
        "# imucald diagnose: parameters that remove the effects named (compass 1; load with a GCS or `param load`)\n",
    );
    for f in fixes {
        out += &format!(
            "# {}: {}\n",
            f.effect.name(),
            shrink_comment(&f.shrink, r.field_ut)
        );
        for n in &f.notes {
            out += &format!("# {n}\n");
        }
        for (n, v) in &f.ardupilot {
            out += &format!("{n} {}\n", shown(*v, 6));
        }
    }
    out
}

/// The PX4 `.params` text (QGroundControl parameter file) of the fixes.
pub fn px4_text(r: &DiagnosisReport, fixes: &[Fix]) -> String {
    let mut out = String::from(
        "# imucald diagnose: parameters that remove the effects named (CAL_MAG0; QGroundControl parameter file)\n# Vehicle-Id\tComponent-Id\tName\tValue\tType\n",
    );
    for f in fixes {
        out += &format!(
            "# {}: {}\n",
            f.effect.name(),
            shrink_comment(&f.shrink, r.field_ut)
        );
        for n in &f.notes {
            out += &format!("# {n}\n");
        }
        for (n, v) in &f.px4 {
            let t = px4_type(n);
            if t == 6 {
                out += &format!("1\t1\t{n}\t{}\t{t}\n", v.round() as i64);
            } else {
                out += &format!("1\t1\t{n}\t{v:.9}\t{t}\n");
            }
        }
    }
    out
}

/// The file names of the exports.
pub const ARDUPILOT_FILE: &str = "diagnose.parm";
pub const PX4_FILE: &str = "diagnose.params";

/// The files to write: (file name, text) for ArduPilot and PX4.
pub fn export_files(r: &DiagnosisReport) -> Vec<(&'static str, String)> {
    let f = fixes(r);
    vec![
        (ARDUPILOT_FILE, ardupilot_text(r, &f)),
        (PX4_FILE, px4_text(r, &f)),
    ]
}

/// The terminal's last lines: what to load and what the held-out residual becomes (uT and % of
/// the field); when nothing is named, what the residual follows. `exported` names the directory
/// the files were written to, if any.
pub fn closing_lines(r: &DiagnosisReport, exported: Option<&str>) -> String {
    let mut s = String::new();
    let fx = fixes(r);
    let field = r.field_ut;
    let mag = r.rms_channels.get("mag_norm");
    let with_params: Vec<&Fix> = fx.iter().filter(|f| !f.ardupilot.is_empty()).collect();
    for f in &fx {
        let ap: Vec<String> = f
            .ardupilot
            .iter()
            .map(|(n, v)| format!("{n} {}", shown(*v, 3)))
            .collect();
        let px: Vec<String> = f
            .px4
            .iter()
            .map(|(n, v)| format!("{n} {}", shown(*v, 5)))
            .collect();
        s += &format!(
            "fix {}: {}\n",
            f.effect.name(),
            shrink_comment(&f.shrink, field)
        );
        if !ap.is_empty() {
            s += &format!("  ArduPilot: {}\n  PX4: {}\n", ap.join(", "), px.join(", "));
        }
        if f.remedy != Remedy::Parameters {
            for n in &f.notes {
                s += &format!("  {n}\n");
            }
        }
    }
    match (with_params.is_empty(), exported) {
        (false, Some(dir)) => {
            s += &format!("load {dir}/{ARDUPILOT_FILE} (ArduPilot) or {dir}/{PX4_FILE} (PX4)\n")
        }
        (false, None) => s += "write the parameters to load with --export DIR\n",
        (true, _) if !fx.is_empty() => s += "no parameter to load: see the fixes above\n",
        _ => s += "nothing named: no parameter to load\n",
    }
    if let Some(c) = mag.filter(|c| c.before.is_finite() && field > 0.0) {
        let pct = |x: f64| 100.0 * x / field;
        if r.found.is_empty() {
            s += &format!(
                "held-out field-magnitude residual: {:.2} uT ({:.2} % of the {field:.1} uT field the readings give); nothing named changes it\n",
                c.before,
                pct(c.before)
            );
        } else {
            s += &format!(
                "held-out field-magnitude residual: {:.2} uT ({:.2} % of the {field:.1} uT field the readings give) -> {:.2} uT ({:.2} %) with the effects named\n",
                c.before,
                pct(c.before),
                c.after,
                pct(c.after)
            );
        }
    }
    s += &trace_lines(r);
    s
}

/// What the residual follows, when some channel is still above its noise.
fn trace_lines(r: &DiagnosisReport) -> String {
    let last = r.rounds.last().map(|x| x.decision);
    if last != Some(super::Decision::Unexplained) {
        return String::new();
    }
    let t = &r.residual_trace;
    let top: Vec<String> = t
        .follows
        .iter()
        .take(4)
        .map(|f| {
            format!(
                "{} R {:.2} ({}, {} points, p {:.1e})",
                f.regressor.name(),
                f.r,
                f.channel,
                f.n,
                f.p_value
            )
        })
        .collect();
    if top.is_empty() {
        return "the residual left: nothing to correlate it with\n".to_string();
    }
    let mut s = format!("the residual left follows: {}\n", top.join("; "));
    match t.reading {
        Some(x) => s += &format!("it reads as {x}\n"),
        None => {
            s += &format!(
                "no correlation reaches R {:.1} at p < {:.0e}: it follows none of them clearly\n",
                super::MIN_NAMING_R,
                super::MAX_NAMING_P
            )
        }
    }
    s
}
