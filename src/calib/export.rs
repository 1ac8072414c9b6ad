//! Exports of a calibration in flight-stack conventions (from the ArduPilot
//! and PX4 sources' correction code):
//!
//! * ArduPilot: the compass correction and its parameters are [`crate::calib::ardupilot`]
//!   (COMPASS_OFS = -offset in mGauss, COMPASS_DIA/ODI the symmetric part of the matrix).
//!   Accel: (raw - INS_ACCOFFS) * INS_ACCSCAL per axis (m/s^2).
//! * PX4: corrected = S (raw - CAL_MAG0_*OFF) in gauss, S from CAL_MAG0_[XYZ]SCALE and
//!   CAL_MAG0_[XYZ]ODIAG (ArduPilot's DIA/ODI layout, [`crate::calib::ardupilot::symmetric`]).
//!   Accel: (raw - CAL_ACC0_*OFF) * CAL_ACC0_*SCALE.
//! * x-io Fusion: m_c = S (m_u - h) (softIronMatrix, hardIronOffset); inertial
//!   misalignment * ((u - offset) * sensitivity) with accel in g.
//!
//! Pure formatting: the caller writes the text to disk.

use crate::calib::ardupilot;
use crate::calib::model::Calibration;
use crate::calib::mounting::Mounting;
use crate::types::{Vec3, STANDARD_GRAVITY_MPS2};

/// A parameter name and value.
pub(crate) type Param = (String, f64);

/// The parts of a calibration the data did not determine (held at nominal in the fit): they are
/// never exported. A flight-stack file leaves them out, so the vehicle keeps its own value, or
/// writes the vehicle's own value from the log with a comment saying so.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Unknowns {
    /// Offset axes not determined.
    pub offset: [bool; 3],
    /// Matrix rows and columns not determined (the whole row and column of that axis).
    pub axis: [bool; 3],
    /// Why, for the comment (e.g. "turns about the vertical only").
    pub why: String,
}

impl Unknowns {
    /// Whether anything is undetermined.
    pub fn any(&self) -> bool {
        self.offset.iter().chain(&self.axis).any(|&b| b)
    }
    /// Whether the offset of `axis` (0..3) or the matrix element (r, c) is undetermined.
    fn offset_unknown(&self, axis: usize) -> bool {
        self.offset[axis]
    }
    fn matrix_unknown(&self, r: usize, c: usize) -> bool {
        self.axis[r] || self.axis[c]
    }
}

/// One compass to export: its flight-stack index (0 for COMPASS_OFS and CAL_MAG0, 1 for
/// COMPASS_OFS2 and CAL_MAG1 ...), its calibration in uT, what the data did not determine, and
/// the vehicle's own parameters as the log carries them (by name), to keep where ours is unknown.
#[derive(Debug, Clone)]
pub(crate) struct CompassExport {
    pub index: usize,
    pub cal: Calibration,
    pub unknown: Unknowns,
    pub vehicle: std::collections::BTreeMap<String, f64>,
    /// Not a calibration to load, and why: its values are written as comments (or, with
    /// `written_anyway`, as values with the reason in a comment).
    pub withheld: Option<Withheld>,
}

/// Why a compass's calibration is not one to load.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Withheld {
    pub reason: String,
    /// Written as values all the same (`replay --export-all`).
    pub written_anyway: bool,
}

impl CompassExport {
    /// A compass whose every parameter the data determined.
    pub(crate) fn determined(index: usize, cal: Calibration) -> CompassExport {
        CompassExport {
            index,
            cal,
            unknown: Unknowns::default(),
            vehicle: Default::default(),
            withheld: None,
        }
    }
}

/// Which of the nine compass parameters (offset x y z, diagonal x y z, off-diagonal xy xz yz, in
/// the order [`ardupilot_mag`] and [`px4_mag`] list them) the data did not determine.
fn unknown_mask(u: &Unknowns) -> [bool; 9] {
    [
        u.offset_unknown(0),
        u.offset_unknown(1),
        u.offset_unknown(2),
        u.matrix_unknown(0, 0),
        u.matrix_unknown(1, 1),
        u.matrix_unknown(2, 2),
        u.matrix_unknown(0, 1),
        u.matrix_unknown(0, 2),
        u.matrix_unknown(1, 2),
    ]
}

/// The parameters of one compass the data determined (for writing to a flight controller, which
/// then keeps its own value of the rest), in ArduPilot's or PX4's names.
pub(crate) fn determined_mag_params(c: &CompassExport, px4: bool) -> Vec<Param> {
    let params = if px4 {
        px4_mag(&c.cal, c.index).0
    } else {
        ardupilot_mag(&c.cal, c.index).0
    };
    params
        .into_iter()
        .zip(unknown_mask(&c.unknown))
        .filter(|(_, unknown)| !unknown)
        .map(|(p, _)| p)
        .collect()
}

/// The lines of one compass's parameters: the determined ones as they are; an undetermined one
/// as the vehicle's own value when the log has it, else left out; each with a comment saying so.
/// `line` formats one parameter.
fn compass_lines(
    c: &CompassExport,
    params: Vec<Param>,
    comment: &str,
    px4: bool,
    line: &dyn Fn(&str, f64) -> String,
) -> String {
    let mut out = String::new();
    // The compass's device id from the log first, so the values land on that compass only.
    let id = if px4 {
        format!("CAL_MAG{}_ID", c.index)
    } else {
        let suffix = ["", "2", "3"].get(c.index).copied().unwrap_or("");
        format!("COMPASS_DEV_ID{suffix}")
    };
    if let Some(v) = c.vehicle.get(&id).filter(|v| **v > 0.0) {
        out += &line(&id, *v);
    }
    let value = |out: &mut String, n: &str, v: f64| *out += &withheld_line(c, comment, &line(n, v));
    match &c.withheld {
        Some(w) if w.written_anyway => {
            out += &format!(
                "{comment} compass {}: written as values by --export-all, although {}\n",
                c.index, w.reason
            );
        }
        Some(w) => {
            out += &format!(
                "{comment} compass {}: not to load ({}); its values follow as comments\n",
                c.index, w.reason
            );
        }
        None => {}
    }
    let mask = unknown_mask(&c.unknown);
    for ((n, v), unknown) in params.into_iter().zip(mask) {
        if !unknown {
            value(&mut out, &n, v);
        } else if let Some(own) = c.vehicle.get(&n) {
            out += &format!(
                "{comment} {n}: not determined by this log ({}); the vehicle's own value, kept\n",
                c.unknown.why
            );
            value(&mut out, &n, *own);
        } else {
            out += &format!(
                "{comment} {n} not written: not determined by this log ({}); the vehicle keeps its own\n",
                c.unknown.why
            );
        }
    }
    out
}

/// A parameter's line as it is, or as a comment when the compass is not one to load.
fn withheld_line(c: &CompassExport, comment: &str, line: &str) -> String {
    match &c.withheld {
        Some(w) if !w.written_anyway => format!("{comment} not to load: {line}"),
        _ => line.to_string(),
    }
}

/// Warnings about what a target cannot represent (asymmetric matrix, cross-axis terms dropped).
fn representability(cal: &Calibration, allow_offdiag: bool) -> Vec<String> {
    let m = cal.matrix;
    let mut w = vec![];
    let asym = (m[0][1] - m[1][0])
        .abs()
        .max((m[0][2] - m[2][0]).abs())
        .max((m[1][2] - m[2][1]).abs());
    if asym > 1e-6 {
        w.push(format!(
            "matrix is not symmetric (max asymmetry {asym:.2e}); its symmetric part is exported"
        ));
    }
    if !allow_offdiag {
        let off = m[0][1].abs().max(m[0][2].abs()).max(m[1][2].abs());
        if off > 1e-3 {
            w.push(format!(
                "off-diagonal terms up to {off:.4} cannot be stored by this target and are dropped"
            ));
        }
    }
    w
}

/// ArduPilot compass parameters from a magnetometer calibration in uT
/// ([`ardupilot::Correction::from_model`]): OFS X Y Z, DIA X Y Z, ODI X Y Z; none, with a
/// warning, for a compass index ArduPilot keeps no calibration for.
pub(crate) fn ardupilot_mag(cal: &Calibration, compass_index: usize) -> (Vec<Param>, Vec<String>) {
    let correction = ardupilot::Correction::from_model(&cal.offset, &cal.matrix);
    match u8::try_from(compass_index)
        .ok()
        .and_then(|k| correction.params(k))
    {
        Some(params) => (params, representability(cal, true)),
        None => (
            Vec::new(),
            vec![format!(
                "compass index {compass_index} not written: ArduPilot keeps a calibration for compasses 0 to {} only",
                ardupilot::COMPASSES - 1
            )],
        ),
    }
}

/// ArduPilot accelerometer parameters from an accel calibration in m/s^2.
pub(crate) fn ardupilot_accel(cal: &Calibration) -> (Vec<Param>, Vec<String>) {
    let m = &cal.matrix;
    let params = vec![
        ("INS_ACCOFFS_X".into(), cal.offset[0]),
        ("INS_ACCOFFS_Y".into(), cal.offset[1]),
        ("INS_ACCOFFS_Z".into(), cal.offset[2]),
        ("INS_ACCSCAL_X".into(), m[0][0]),
        ("INS_ACCSCAL_Y".into(), m[1][1]),
        ("INS_ACCSCAL_Z".into(), m[2][2]),
    ];
    (params, representability(cal, false))
}

/// PX4 magnetometer parameters of calibration slot `index` (CAL_MAG0_*, CAL_MAG1_* ...; gauss,
/// 1 uT = 0.01 gauss).
pub(crate) fn px4_mag(cal: &Calibration, index: usize) -> (Vec<Param>, Vec<String>) {
    let (d, o) = ardupilot::diagonal_off_diagonal(&cal.matrix);
    let n = |field: &str| format!("CAL_MAG{index}_{field}");
    let params = vec![
        (n("XOFF"), cal.offset[0] * 0.01),
        (n("YOFF"), cal.offset[1] * 0.01),
        (n("ZOFF"), cal.offset[2] * 0.01),
        (n("XSCALE"), d[0]),
        (n("YSCALE"), d[1]),
        (n("ZSCALE"), d[2]),
        (n("XODIAG"), o[0]),
        (n("YODIAG"), o[1]),
        (n("ZODIAG"), o[2]),
    ];
    (params, representability(cal, true))
}

/// PX4 accelerometer parameters (m/s^2).
pub(crate) fn px4_accel(cal: &Calibration) -> (Vec<Param>, Vec<String>) {
    let m = &cal.matrix;
    let params = vec![
        ("CAL_ACC0_XOFF".into(), cal.offset[0]),
        ("CAL_ACC0_YOFF".into(), cal.offset[1]),
        ("CAL_ACC0_ZOFF".into(), cal.offset[2]),
        ("CAL_ACC0_XSCALE".into(), m[0][0]),
        ("CAL_ACC0_YSCALE".into(), m[1][1]),
        ("CAL_ACC0_ZSCALE".into(), m[2][2]),
    ];
    (params, representability(cal, false))
}

/// ArduPilot's motor compensation from the field per ampere of battery current `k_ut_per_a`
/// (the vector fit's `k` of raw = A h + o + k c, uT/A) and the calibration's matrix `m`.
/// ArduPilot adds COMPASS_MOT x current after the soft-iron matrix (mGauss), so
/// COMPASS_MOT = -(M k) x 10 in mGauss/A, with COMPASS_MOTCT = 2 (current-based).
/// None for a compass index ArduPilot has no parameters for.
pub fn ardupilot_motor(k_ut_per_a: &Vec3, m: &[[f64; 3]; 3], compass_index: usize) -> Vec<Param> {
    let Some(names) = u8::try_from(compass_index)
        .ok()
        .and_then(|k| ardupilot::triple(ardupilot::Triple::Mot, k))
    else {
        return Vec::new();
    };
    let mk = |r: usize| (0..3).map(|c| m[r][c] * k_ut_per_a[c]).sum::<f64>();
    let mot = [0, 1, 2].map(|r| -mk(r) * ardupilot::MGAUSS_PER_UT);
    names
        .into_iter()
        .zip(mot)
        .chain([(ardupilot::MOTCT.to_string(), 2.0)])
        .collect()
}

/// PX4's power compensation of slot `index` from the field per ampere `k_ut_per_a` (uT/A). PX4
/// adds CAL_MAGn_[XYZ]COMP x current to the raw reading before the offset is subtracted, in
/// gauss per kiloampere: XCOMP = -k x 10 (1 uT/A = 0.01 G/A = 10 G/kA), with
/// CAL_MAG_COMP_TYP = 2 (current-based).
pub fn px4_motor(k_ut_per_a: &Vec3, index: usize) -> Vec<Param> {
    let n = |axis: &str| format!("CAL_MAG{index}_{axis}COMP");
    vec![
        (n("X"), -k_ut_per_a[0] * 10.0),
        (n("Y"), -k_ut_per_a[1] * 10.0),
        (n("Z"), -k_ut_per_a[2] * 10.0),
        ("CAL_MAG_COMP_TYP".into(), 2.0),
    ]
}

/// Motor (battery current) interference per compass index, uT/A: what [`ardupilot_motor`] and
/// [`px4_motor`] export beside the calibrations.
pub(crate) type CompassMotors = [(usize, Vec3)];

/// A compass the mounting check ([`crate::calib::mounting`]) finds turned against the mounting
/// its readings are in: the mounting to set, offered as a value (as ArduPilot's calibrator sets
/// COMPASS_ORIENTn itself when COMPASS_AUTO_ROT finds a clear rotation). Its calibration was
/// refused, so none is written: the compass is to be calibrated again in its new mounting.
#[derive(Debug, Clone)]
pub(crate) struct MountingFix {
    pub index: usize,
    /// The mounting the data say, relative to the frame the readings were logged in (body = R
    /// readings).
    pub found: Mounting,
    /// The vehicle's own parameters as the log carries them (its COMPASS_ORIENTn / CAL_MAGn_ROT,
    /// which the readings were already turned by).
    pub vehicle: std::collections::BTreeMap<String, f64>,
}

impl MountingFix {
    /// The mounting to set on the vehicle: the one found composed with the vehicle's own (the
    /// readings were turned by the vehicle's rotation first), and the name of its parameter.
    /// `None` for the mounting when the composition is no rotation of the table.
    fn to_set(&self, px4: bool) -> (String, Option<Mounting>) {
        let name = if px4 {
            format!("CAL_MAG{}_ROT", self.index)
        } else {
            u8::try_from(self.index)
                .ok()
                .and_then(|k| ardupilot::single(ardupilot::Single::Orient, k))
                .unwrap_or_else(|| format!("COMPASS_ORIENT{}", self.index + 1))
        };
        let own = self
            .vehicle
            .get(&name)
            .and_then(|v| u8::try_from(*v as i64).ok())
            .and_then(Mounting::standard);
        let total = match &own {
            Some(own) => Mounting::of_matrix(&(self.found.matrix() * own.matrix())),
            None => match self.found {
                Mounting::Standard { .. } => Some(self.found.clone()),
                Mounting::Custom { .. } => None,
            },
        };
        (name, total)
    }
}

/// The lines of a mounting to set: a comment saying why, then the value (or, when the rotation
/// is none of the table's, a comment naming it as a custom mounting).
fn mounting_lines(
    f: &MountingFix,
    px4: bool,
    comment: &str,
    line: &dyn Fn(&str, f64) -> String,
) -> String {
    let (name, total) = f.to_set(px4);
    let own = f
        .vehicle
        .get(&name)
        .map_or(String::new(), |v| format!(" (the vehicle's {name} is {v})"));
    let mut out = format!(
        "{comment} compass {}: the readings fit {} more closely than the mounting they were logged in{own}; set the mounting, then calibrate this compass again (no calibration of it is written)\n",
        f.index,
        f.found.label()
    );
    match total {
        Some(m) => out += &line(&name, m.ardupilot_compass_orient() as f64),
        None => {
            out += &format!(
                "{comment} {name} not written: the rotation is none of the table's, a custom mounting ({})\n",
                f.found.parameters(f.index)
            )
        }
    }
    out
}

/// Magnetometer calibrations to export, one per compass.
pub(crate) type CompassCalibrations = [CompassExport];

/// ArduPilot `.parm` text ("NAME VALUE" per line) with warnings as comments.
pub(crate) fn ardupilot_file(
    mags: &CompassCalibrations,
    mountings: &[MountingFix],
    motors: &CompassMotors,
    accel: Option<&Calibration>,
) -> String {
    let mut out =
        String::from("# imucald calibration for ArduPilot (load with a GCS or `param load`)\n");
    let line = |n: &str, v: f64| format!("{n} {v:.6}\n");
    for c in mags {
        let (params, warns) = ardupilot_mag(&c.cal, c.index);
        for w in warns {
            out += &format!("# warning: {w}\n");
        }
        out += &compass_lines(c, params, "#", false, &line);
        // The motor term is in the calibrated frame (after the matrix): only with a whole matrix.
        for (_, k) in motors.iter().filter(|(i, _)| *i == c.index) {
            if c.unknown.any() {
                out += "# motor compensation not written: the matrix it goes through is not determined\n";
                continue;
            }
            for (n, v) in ardupilot_motor(k, &c.cal.matrix, c.index) {
                out += &withheld_line(c, "#", &line(&n, v));
            }
        }
    }
    for f in mountings {
        out += &mounting_lines(f, false, "#", &line);
    }
    if let Some((params, warns)) = accel.map(ardupilot_accel) {
        for w in warns {
            out += &format!("# warning: {w}\n");
        }
        for (n, v) in params {
            out += &line(&n, v);
        }
    }
    out
}

/// PX4/QGroundControl `.params` text (vehicle, component, name, value, type 9 = float).
pub(crate) fn px4_file(
    mags: &CompassCalibrations,
    mountings: &[MountingFix],
    motors: &CompassMotors,
    accel: Option<&Calibration>,
) -> String {
    let mut out = String::from("# imucald calibration for PX4 (QGroundControl parameter file)\n# Vehicle-Id\tComponent-Id\tName\tValue\tType\n");
    let line = |n: &str, v: f64| format!("1\t1\t{n}\t{v:.9}\t9\n");
    for c in mags {
        let (params, warns) = px4_mag(&c.cal, c.index);
        for w in warns {
            out += &format!("# warning: {w}\n");
        }
        out += &compass_lines(c, params, "#", true, &line);
        for (i, k) in motors.iter().filter(|(i, _)| *i == c.index) {
            for (n, v) in px4_motor(k, *i) {
                out += &withheld_line(c, "#", &line(&n, v));
            }
        }
    }
    for f in mountings {
        out += &mounting_lines(f, true, "#", &line);
    }
    if let Some((params, warns)) = accel.map(px4_accel) {
        for w in warns {
            out += &format!("# warning: {w}\n");
        }
        for (n, v) in params {
            out += &line(&n, v);
        }
    }
    out
}

/// x-io Fusion C snippet: the magnetometer soft/hard iron and the accelerometer inertial model.
/// Fusion takes the whole matrix and offset, so a magnetometer calibration with an undetermined
/// part is left out, with a comment saying why.
pub(crate) fn fusion_file(mag: Option<&CompassExport>, accel: Option<&Calibration>) -> String {
    let mat = |m: &[[f64; 3]; 3]| {
        format!(
            "{{{:.9}f, {:.9}f, {:.9}f, {:.9}f, {:.9}f, {:.9}f, {:.9}f, {:.9}f, {:.9}f}}",
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2]
        )
    };
    let vec = |v: [f64; 3]| format!("{{{:.9}f, {:.9}f, {:.9}f}}", v[0], v[1], v[2]);
    let mut out = String::from("// imucald calibration for x-io Fusion. Magnetometer in the input's units (uT),\n// accelerometer in g: FusionCalibrationInertial(u, accelerometerMisalignment, accelerometerSensitivity, accelerometerOffset).\n");
    match mag {
        Some(c) if c.unknown.any() => {
            out += &format!(
                "// magnetometer not written: this log does not determine all of it ({})\n",
                c.unknown.why
            );
        }
        Some(c) => {
            out += &format!(
                "const FusionMatrix softIronMatrix = {};\n",
                mat(&c.cal.matrix)
            );
            out += &format!(
                "const FusionVector hardIronOffset = {};\n",
                vec(c.cal.offset)
            );
        }
        None => {}
    }
    if let Some(c) = accel {
        out += &format!(
            "const FusionMatrix accelerometerMisalignment = {};\n",
            mat(&c.matrix)
        );
        out += "const FusionVector accelerometerSensitivity = {1.0f, 1.0f, 1.0f};\n";
        out += &format!(
            "const FusionVector accelerometerOffset = {};\n",
            vec(c.offset.map(|o| o / STANDARD_GRAVITY_MPS2))
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::model::ModelKind;

    /// The motor terms by each stack's correction formula: a reading raw = A h + o + k c
    /// (uT, c in A) must come out as the earth field h.
    #[test]
    fn motor_compensation_restores_the_field_in_each_stacks_formula() {
        let a = [[1.04, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.02]];
        let m = crate::calib::model::mat_to_rows(
            &crate::calib::model::rows_to_mat(&a).try_inverse().unwrap(),
        );
        let (o, k, h, c) = (
            [12.0, -30.0, 45.0],
            [0.3, -0.2, 0.45],
            [20.0, 1.5, 43.0],
            37.0,
        );
        let raw: Vec3 =
            std::array::from_fn(|r| (0..3).map(|j| a[r][j] * h[j]).sum::<f64>() + o[r] + k[r] * c);
        let cal = Calibration {
            model: ModelKind::Full12,
            offset: o,
            matrix: m,
        };
        // ArduPilot, mGauss: S (raw + OFS) + MOT c.
        let (p, _) = ardupilot_mag(&cal, 1);
        let mot = ardupilot_motor(&k, &m, 1);
        assert_eq!(get(&mot, "COMPASS_MOTCT"), 2.0);
        let axes = ["X", "Y", "Z"];
        let plus: Vec3 =
            std::array::from_fn(|r| raw[r] * 10.0 + get(&p, &format!("COMPASS_OFS2_{}", axes[r])));
        for r in 0..3 {
            let s_row: f64 = (0..3).map(|j| m[r][j] * plus[j]).sum();
            let got = s_row + get(&mot, &format!("COMPASS_MOT2_{}", axes[r])) * c;
            assert!(
                (got - h[r] * 10.0).abs() < 1e-9,
                "ArduPilot axis {r}: {got}"
            );
        }
        // PX4, gauss: S ((raw + COMP c / 1000) - OFF).
        let (p, _) = px4_mag(&cal, 0);
        let comp = px4_motor(&k, 0);
        assert_eq!(get(&comp, "CAL_MAG_COMP_TYP"), 2.0);
        let inner: Vec3 = std::array::from_fn(|r| {
            raw[r] * 0.01 + get(&comp, &format!("CAL_MAG0_{}COMP", axes[r])) * c / 1000.0
                - get(&p, &format!("CAL_MAG0_{}OFF", axes[r]))
        });
        for r in 0..3 {
            let got: f64 = (0..3).map(|j| m[r][j] * inner[j]).sum();
            assert!((got - h[r] * 0.01).abs() < 1e-12, "PX4 axis {r}: {got}");
        }
        // Both files carry them beside the calibration.
        let ap = ardupilot_file(&[CompassExport::determined(1, cal)], &[], &[(1, k)], None);
        assert!(
            ap.contains("COMPASS_MOT2_X") && ap.contains("COMPASS_MOTCT 2"),
            "{ap}"
        );
        let px = px4_file(&[CompassExport::determined(0, cal)], &[], &[(0, k)], None);
        assert!(
            px.contains("CAL_MAG0_XCOMP") && px.contains("CAL_MAG_COMP_TYP"),
            "{px}"
        );
    }

    fn cal() -> Calibration {
        Calibration {
            model: ModelKind::Sym9,
            offset: [12.0, -30.0, 45.0],
            matrix: [[1.05, 0.02, -0.01], [0.02, 0.97, 0.03], [-0.01, 0.03, 1.01]],
        }
    }

    fn get(p: &[Param], n: &str) -> f64 {
        p.iter()
            .find(|(k, _)| k == n)
            .unwrap_or_else(|| panic!("{n} missing"))
            .1
    }

    #[test]
    fn ardupilot_mag_reproduces_correct_field() {
        let c = cal();
        let (p, w) = ardupilot_mag(&c, 0);
        assert!(w.is_empty());
        let raw_ut = [40.0, 5.0, -20.0];
        // AP_Compass_Backend::correct_field, in mGauss: mag += OFS; mag = S * mag.
        let mut m = raw_ut.map(|v| v * 10.0);
        for (k, a) in ["X", "Y", "Z"].iter().enumerate() {
            m[k] += get(&p, &format!("COMPASS_OFS_{a}"));
        }
        let s = [
            [
                get(&p, "COMPASS_DIA_X"),
                get(&p, "COMPASS_ODI_X"),
                get(&p, "COMPASS_ODI_Y"),
            ],
            [
                get(&p, "COMPASS_ODI_X"),
                get(&p, "COMPASS_DIA_Y"),
                get(&p, "COMPASS_ODI_Z"),
            ],
            [
                get(&p, "COMPASS_ODI_Y"),
                get(&p, "COMPASS_ODI_Z"),
                get(&p, "COMPASS_DIA_Z"),
            ],
        ];
        let ours = c.apply(&raw_ut);
        for i in 0..3 {
            let ap = s[i][0] * m[0] + s[i][1] * m[1] + s[i][2] * m[2];
            assert!(
                (ap - ours[i] * 10.0).abs() < 1e-9,
                "axis {i}: {ap} vs {}",
                ours[i] * 10.0
            );
        }
        let (p2, _) = ardupilot_mag(&c, 1);
        assert!(
            p2.iter().any(|(n, _)| n == "COMPASS_OFS2_X")
                && p2.iter().any(|(n, _)| n == "COMPASS_DIA2_Z")
        );
    }

    #[test]
    fn px4_mag_reproduces_its_correction_in_gauss() {
        let c = cal();
        let (p, _) = px4_mag(&c, 0);
        let raw_g = [0.40, 0.05, -0.20];
        let off = [
            get(&p, "CAL_MAG0_XOFF"),
            get(&p, "CAL_MAG0_YOFF"),
            get(&p, "CAL_MAG0_ZOFF"),
        ];
        let d = [raw_g[0] - off[0], raw_g[1] - off[1], raw_g[2] - off[2]];
        let s = [
            [
                get(&p, "CAL_MAG0_XSCALE"),
                get(&p, "CAL_MAG0_XODIAG"),
                get(&p, "CAL_MAG0_YODIAG"),
            ],
            [
                get(&p, "CAL_MAG0_XODIAG"),
                get(&p, "CAL_MAG0_YSCALE"),
                get(&p, "CAL_MAG0_ZODIAG"),
            ],
            [
                get(&p, "CAL_MAG0_YODIAG"),
                get(&p, "CAL_MAG0_ZODIAG"),
                get(&p, "CAL_MAG0_ZSCALE"),
            ],
        ];
        let ours = c.apply(&raw_g.map(|v| v * 100.0));
        for i in 0..3 {
            let px = s[i][0] * d[0] + s[i][1] * d[1] + s[i][2] * d[2];
            assert!((px * 100.0 - ours[i]).abs() < 1e-9);
        }
    }

    #[test]
    fn accel_exports_subtract_offsets_then_scale_and_warn_on_cross_axis() {
        let c = Calibration {
            model: ModelKind::Diag6,
            offset: [0.1, -0.2, 0.3],
            matrix: [[1.01, 0.0, 0.0], [0.0, 0.99, 0.0], [0.0, 0.0, 1.02]],
        };
        let raw = [0.5, -9.0, 1.0];
        let ours = c.apply(&raw);
        for (params, _) in [ardupilot_accel(&c), px4_accel(&c)] {
            let (o, s): (Vec<f64>, Vec<f64>) = if params[0].0.starts_with("INS") {
                (
                    ["X", "Y", "Z"]
                        .iter()
                        .map(|a| get(&params, &format!("INS_ACCOFFS_{a}")))
                        .collect(),
                    ["X", "Y", "Z"]
                        .iter()
                        .map(|a| get(&params, &format!("INS_ACCSCAL_{a}")))
                        .collect(),
                )
            } else {
                (
                    ["X", "Y", "Z"]
                        .iter()
                        .map(|a| get(&params, &format!("CAL_ACC0_{a}OFF")))
                        .collect(),
                    ["X", "Y", "Z"]
                        .iter()
                        .map(|a| get(&params, &format!("CAL_ACC0_{a}SCALE")))
                        .collect(),
                )
            };
            for i in 0..3 {
                assert!(((raw[i] - o[i]) * s[i] - ours[i]).abs() < 1e-12);
            }
        }
        assert_eq!(ardupilot_accel(&cal()).1.len(), 1);
    }

    #[test]
    fn fusion_snippet_is_row_major_with_offset_subtracted() {
        let t = fusion_file(Some(&CompassExport::determined(0, cal())), None);
        assert!(
            t.contains("softIronMatrix = {1.050000000f, 0.020000000f, -0.010000000f, 0.020000000f"),
            "{t}"
        );
        assert!(t.contains("hardIronOffset = {12.000000000f, -30.000000000f, 45.000000000f}"));
    }

    /// A planar fit's z offset and z soft iron are never written: left out (the vehicle keeps its
    /// own) or, when the log carries the vehicle's value, that value with a comment.
    #[test]
    fn undetermined_parameters_are_never_exported() {
        let mut c = CompassExport::determined(0, cal());
        c.unknown = Unknowns {
            offset: [false, false, true],
            axis: [false, false, true],
            why: "turns about the vertical only".into(),
        };
        let ap = ardupilot_file(std::slice::from_ref(&c), &[], &[], None);
        for n in [
            "COMPASS_OFS_Z",
            "COMPASS_DIA_Z",
            "COMPASS_ODI_Y",
            "COMPASS_ODI_Z",
        ] {
            assert!(!ap.lines().any(|l| l.starts_with(n)), "{n} written:\n{ap}");
            assert!(ap.contains(&format!("# {n} not written")), "{ap}");
        }
        for n in [
            "COMPASS_OFS_X",
            "COMPASS_OFS_Y",
            "COMPASS_DIA_X",
            "COMPASS_ODI_X",
        ] {
            assert!(ap.lines().any(|l| l.starts_with(n)), "{n} missing:\n{ap}");
        }
        let px = px4_file(std::slice::from_ref(&c), &[], &[], None);
        assert!(!px.contains("\tCAL_MAG0_ZOFF\t"), "{px}");
        assert!(px.contains("\tCAL_MAG0_XOFF\t"), "{px}");
        assert!(fusion_file(Some(&c), None).contains("magnetometer not written"));
        // The vehicle's own value, when the log has it, is kept and said so.
        c.vehicle.insert("COMPASS_OFS_Z".into(), -130.0);
        let ap = ardupilot_file(std::slice::from_ref(&c), &[], &[], None);
        assert!(ap.contains("COMPASS_OFS_Z -130.000000"), "{ap}");
        assert!(ap.contains("the vehicle's own value, kept"), "{ap}");
    }
}
