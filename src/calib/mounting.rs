//! Which way a compass is mounted, found from the data, and whether that is the mounting the
//! configuration gives.
//!
//! The readings of a correctly mounted compass, turned into the body frame, keep a fixed angle to
//! gravity however the vehicle is held (90 deg plus the inclination between the field and the
//! accelerometer's "up"), and, when the attitude is known, point where the earth field turned into
//! the body frame points. For each MAV_SENSOR_ORIENTATION rotation `R` (the list MAVLink, ArduPilot
//! and PX4 number alike for 0-40) the readings `R m` are scored against the body frame:
//!
//! * without an attitude: the spread (RMS about the mean, deg) of the angle between `R m` and the
//!   specific force over the static poses; the right `R` leaves only noise, a wrong one turns the
//!   field by a different amount in each pose;
//! * with an attitude (body -> NED) and the earth field: the RMS angle between `R m` and
//!   `C^T B`, the field the attitude says the body should see.
//!
//! A continuous yaw (upright or upside down, a 1-D search) covers mounts between the standard ones
//! (ArduPilot's custom rotation). The best rotation, its runner-up and the configured one are
//! reported with the parameters to set, and a verdict: the data say the configured mounting, say a
//! different one clearly, rule the configured one out while two others still fit alike (early in
//! a live calibration), or cannot tell (too few poses, poses not varied enough, no rotation fits,
//! or two rotations fit alike, the configured among them). Both of the middle two refuse the
//! calibration. Pure: no I/O.

use crate::attitude::EarthField;
use crate::types::Vec3;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// The MAV_SENSOR_ORIENTATION rotations (MAVLink `common.xml`) by number. ArduPilot's
/// COMPASS_ORIENTn and PX4's CAL_MAGn_ROT use these numbers for the same rotations from 0 to 40
/// (ArduPilot `AP_Math/rotations.h`, PX4 `lib/conversion/rotation.h`); past 40 the two flight
/// stacks differ and are left out. 26 (PITCH_180_YAW_90) is the same rotation as 14
/// (ROLL_180_YAW_270), and 27 (PITCH_180_YAW_270) the same as 10 (ROLL_180_YAW_90): a detected
/// rotation is named by the lower number.
pub(crate) const ORIENTATIONS: [(u8, &str); 41] = [
    (0, "ROTATION_NONE"),
    (1, "ROTATION_YAW_45"),
    (2, "ROTATION_YAW_90"),
    (3, "ROTATION_YAW_135"),
    (4, "ROTATION_YAW_180"),
    (5, "ROTATION_YAW_225"),
    (6, "ROTATION_YAW_270"),
    (7, "ROTATION_YAW_315"),
    (8, "ROTATION_ROLL_180"),
    (9, "ROTATION_ROLL_180_YAW_45"),
    (10, "ROTATION_ROLL_180_YAW_90"),
    (11, "ROTATION_ROLL_180_YAW_135"),
    (12, "ROTATION_PITCH_180"),
    (13, "ROTATION_ROLL_180_YAW_225"),
    (14, "ROTATION_ROLL_180_YAW_270"),
    (15, "ROTATION_ROLL_180_YAW_315"),
    (16, "ROTATION_ROLL_90"),
    (17, "ROTATION_ROLL_90_YAW_45"),
    (18, "ROTATION_ROLL_90_YAW_90"),
    (19, "ROTATION_ROLL_90_YAW_135"),
    (20, "ROTATION_ROLL_270"),
    (21, "ROTATION_ROLL_270_YAW_45"),
    (22, "ROTATION_ROLL_270_YAW_90"),
    (23, "ROTATION_ROLL_270_YAW_135"),
    (24, "ROTATION_PITCH_90"),
    (25, "ROTATION_PITCH_270"),
    (26, "ROTATION_PITCH_180_YAW_90"),
    (27, "ROTATION_PITCH_180_YAW_270"),
    (28, "ROTATION_ROLL_90_PITCH_90"),
    (29, "ROTATION_ROLL_180_PITCH_90"),
    (30, "ROTATION_ROLL_270_PITCH_90"),
    (31, "ROTATION_ROLL_90_PITCH_180"),
    (32, "ROTATION_ROLL_270_PITCH_180"),
    (33, "ROTATION_ROLL_90_PITCH_270"),
    (34, "ROTATION_ROLL_180_PITCH_270"),
    (35, "ROTATION_ROLL_270_PITCH_270"),
    (36, "ROTATION_ROLL_90_PITCH_180_YAW_90"),
    (37, "ROTATION_ROLL_90_YAW_270"),
    (38, "ROTATION_ROLL_90_PITCH_68_YAW_293"),
    (39, "ROTATION_PITCH_315"),
    (40, "ROTATION_ROLL_90_PITCH_315"),
];

/// ArduPilot's COMPASS_ORIENTn value of a custom rotation (ROTATION_CUSTOM_1, with the angles in
/// CUST_ROT1_ROLL/PITCH/YAW and CUST_ROT_ENABLE = 1; ArduPilot 4.1 and older used 100,
/// ROTATION_CUSTOM, which newer versions convert to this). PX4's CAL_MAGn_ROT has no custom value.
pub(crate) const ARDUPILOT_CUSTOM_ROTATION: i32 = 101;

/// Fewer static poses with a magnetometer reading than this: undetermined. Count.
pub(crate) const MIN_POSES: usize = 6;

/// The reference directions (gravity, or the expected field with an attitude) in body axes must
/// span at least this largest angle between two poses, deg; less and most rotations cannot be told
/// apart (a vehicle that only turned about the vertical).
pub(crate) const MIN_SPREAD_DEG: f64 = 30.0;

/// The best rotation's score must be below this, deg: above it no rotation fits (a disturbed or
/// uncalibrated compass), and nothing is said about the mounting.
pub(crate) const MAX_BEST_SCORE_DEG: f64 = 6.0;

/// The runner-up (the best rotation that is not the same as the best) must score at least this
/// many times the best's score ...
pub(crate) const MIN_MARGIN_RATIO: f64 = 3.0;

/// ... and at least this many degrees above it; otherwise the two fit alike and the verdict is
/// undetermined. Deg.
pub(crate) const MIN_MARGIN_DEG: f64 = 5.0;

/// A continuous yaw replaces the best standard rotation only when it scores this many times better
/// (a standard rotation seen through noise finds a custom yaw next to it scoring about the same).
pub(crate) const CUSTOM_GAIN_RATIO: f64 = 2.0;

/// Two rotations closer than this are the same mounting (the detected one is the configured one,
/// or two table entries are one rotation), deg.
pub(crate) const SAME_ROTATION_DEG: f64 = 3.0;

/// Grid step of the custom yaw search before the golden-section refinement, deg.
const YAW_GRID_DEG: f64 = 1.0;

/// A static pose's readings: the corrected magnetometer (at least hard iron removed) in the
/// compass's own axes, the specific force in body axes, and the attitude when known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MountPoint {
    pub mag: Vec3,
    pub specific_force_mps2: Vec3,
    /// Body -> NED.
    pub body_to_ned: Option<UnitQuaternion<f64>>,
}

/// A mounting: a MAV_SENSOR_ORIENTATION rotation, or a custom roll (0 or 180 deg) and yaw.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Mounting {
    Standard { number: u8, name: String },
    Custom { roll_deg: f64, yaw_deg: f64 },
}

impl Mounting {
    /// The table entry of a MAV_SENSOR_ORIENTATION number.
    pub fn standard(number: u8) -> Option<Mounting> {
        ORIENTATIONS
            .iter()
            .find(|(n, _)| *n == number)
            .map(|&(number, name)| Mounting::Standard {
                number,
                name: name.into(),
            })
    }

    /// The table entry with the same rotation as `r` (the lowest number), if any.
    pub fn of_matrix(r: &Matrix3<f64>) -> Option<Mounting> {
        ORIENTATIONS
            .iter()
            .map(|&(number, name)| Mounting::Standard {
                number,
                name: name.into(),
            })
            .find(|m| rotation_angle_deg(&m.matrix(), r) < SAME_ROTATION_DEG)
    }

    /// body = R sensor.
    pub fn matrix(&self) -> Matrix3<f64> {
        match *self {
            Mounting::Standard { ref name, .. } => {
                crate::attitude::sensor_rotation(name).unwrap_or_else(|_| Matrix3::identity())
            }
            Mounting::Custom { roll_deg, yaw_deg } => {
                *Rotation3::from_euler_angles(roll_deg.to_radians(), 0.0, yaw_deg.to_radians())
                    .matrix()
            }
        }
    }

    /// ArduPilot's COMPASS_ORIENTn value.
    pub fn ardupilot_compass_orient(&self) -> i32 {
        match self {
            Mounting::Standard { number, .. } => *number as i32,
            Mounting::Custom { .. } => ARDUPILOT_CUSTOM_ROTATION,
        }
    }

    /// PX4's CAL_MAGn_ROT value (none for a custom rotation).
    pub fn px4_cal_mag_rot(&self) -> Option<i32> {
        match self {
            Mounting::Standard { number, .. } => Some(*number as i32),
            Mounting::Custom { .. } => None,
        }
    }

    /// A short name: `ROTATION_YAW_90` or `custom roll 0 yaw 30.2 deg`.
    pub fn label(&self) -> String {
        match self {
            Mounting::Standard { name, .. } => name.clone(),
            Mounting::Custom { roll_deg, yaw_deg } => {
                format!("custom roll {roll_deg:.0} yaw {yaw_deg:.1} deg")
            }
        }
    }

    /// The parameters to set for compass `index` (0 for COMPASS_ORIENT and CAL_MAG0_ROT).
    pub fn parameters(&self, index: usize) -> String {
        use crate::calib::ardupilot::{single, Single};
        let ap = u8::try_from(index)
            .ok()
            .and_then(|k| single(Single::Orient, k));
        let ap = ap
            .as_deref()
            .unwrap_or("COMPASS_ORIENT (none for this compass)");
        match self {
            Mounting::Standard { number, .. } => {
                format!("{ap} = {number} (ArduPilot) or CAL_MAG{index}_ROT = {number} (PX4)")
            }
            Mounting::Custom { roll_deg, yaw_deg } => format!(
                "{ap} = {ARDUPILOT_CUSTOM_ROTATION} with CUST_ROT_ENABLE = 1, CUST_ROT1_ROLL = {roll_deg:.0}, CUST_ROT1_PITCH = 0, CUST_ROT1_YAW = {yaw_deg:.1} (ArduPilot; PX4's CAL_MAG{index}_ROT has no custom rotation)"
            ),
        }
    }
}

/// A mounting with its score and the values to set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scored {
    pub mounting: Mounting,
    /// RMS angle, deg (see [`Basis`]).
    pub score_deg: f64,
    /// ArduPilot COMPASS_ORIENTn.
    pub ardupilot_compass_orient: i32,
    /// PX4 CAL_MAGn_ROT (none for a custom rotation).
    pub px4_cal_mag_rot: Option<i32>,
}

impl Scored {
    fn new(mounting: Mounting, score_deg: f64) -> Scored {
        Scored {
            ardupilot_compass_orient: mounting.ardupilot_compass_orient(),
            px4_cal_mag_rot: mounting.px4_cal_mag_rot(),
            mounting,
            score_deg,
        }
    }
}

/// What a rotation is scored against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Basis {
    /// The spread of the angle between the turned field and the specific force.
    GravityAngle,
    /// The angle between the turned field and the field the attitude says the body sees.
    Attitude,
}

/// Why the data cannot tell the mounting.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "reason")]
pub enum Undetermined {
    /// Fewer poses than [`MIN_POSES`].
    TooFewPoses { poses: usize, needed: usize },
    /// The reference directions span less than [`MIN_SPREAD_DEG`].
    NotVaried { spread_deg: f64, needed_deg: f64 },
    /// Even the best rotation scores above [`MAX_BEST_SCORE_DEG`].
    NoRotationFits { best_deg: f64, limit_deg: f64 },
    /// The runner-up scores too close to the best ([`MIN_MARGIN_RATIO`], [`MIN_MARGIN_DEG`]).
    Ambiguous { best_deg: f64, runner_up_deg: f64 },
}

impl std::fmt::Display for Undetermined {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Undetermined::TooFewPoses { poses, needed } => {
                write!(f, "{poses} static poses with the compass, {needed} needed")
            }
            Undetermined::NotVaried {
                spread_deg,
                needed_deg,
            } => write!(
                f,
                "the poses span {spread_deg:.0} deg, {needed_deg:.0} needed (hold the vehicle in more varied attitudes)"
            ),
            Undetermined::NoRotationFits {
                best_deg,
                limit_deg,
            } => write!(
                f,
                "no rotation fits: the best scores {best_deg:.1} deg (limit {limit_deg:.0})"
            ),
            Undetermined::Ambiguous {
                best_deg,
                runner_up_deg,
            } => write!(
                f,
                "two rotations fit alike ({best_deg:.1} and {runner_up_deg:.1} deg)"
            ),
        }
    }
}

/// The verdict on the configured mounting.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "verdict")]
pub enum Verdict {
    /// The data say the configured mounting.
    Matches,
    /// The data clearly say another mounting: `set` is the one to configure.
    Differs { set: Scored },
    /// The data rule the configured mounting out, but cannot yet tell which of `candidates` (the
    /// best and the runner-up, which fit alike) it is: the configured scores at least
    /// [`MIN_MARGIN_RATIO`] times and [`MIN_MARGIN_DEG`] above both.
    Mismatch { candidates: Vec<Scored> },
    /// The data cannot tell.
    Undetermined { why: Undetermined },
}

/// The report's `calibration.mag.mounting`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MountingReport {
    pub basis: Basis,
    /// Static poses used.
    pub poses: usize,
    /// Largest angle between two poses' reference directions (gravity or the expected field in
    /// body axes), deg.
    pub spread_deg: f64,
    /// The configured mounting's name and score.
    pub configured: String,
    pub configured_score_deg: f64,
    pub best: Scored,
    /// The best rotation that is not the same as `best`.
    pub runner_up: Option<Scored>,
    /// runner_up.score_deg / best.score_deg.
    pub margin_ratio: Option<f64>,
    /// The best continuous yaw (upright or upside down), whether chosen or not.
    pub custom: Option<Scored>,
    /// Mean angle between the turned field and the specific force under `best`, and the angle the
    /// earth field model expects (90 deg + inclination), deg.
    pub field_to_up_deg: f64,
    pub expected_field_to_up_deg: Option<f64>,
    #[serde(flatten)]
    pub verdict: Verdict,
}

fn unit(v: &Vec3) -> Option<Vector3<f64>> {
    let v = Vector3::new(v[0], v[1], v[2]);
    let n = v.norm();
    (n.is_finite() && n > 1e-9).then(|| v / n)
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.dot(b).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The angle of the rotation taking `a` to `b`, deg.
pub(crate) fn rotation_angle_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    (((a.transpose() * b).trace() - 1.0) / 2.0)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The prepared points: unit field (sensor axes), unit "up" (specific force, body axes), the
/// unit expected field in body axes when attitude and field are known.
struct Prepared {
    m: Vec<Vector3<f64>>,
    up: Vec<Vector3<f64>>,
    expected: Option<Vec<Vector3<f64>>>,
}

impl Prepared {
    fn score(&self, r: &Matrix3<f64>) -> f64 {
        let n = self.m.len() as f64;
        match &self.expected {
            Some(e) => {
                let ss: f64 = self
                    .m
                    .iter()
                    .zip(e)
                    .map(|(m, b)| angle_deg(&(r * m), b).powi(2))
                    .sum();
                (ss / n).sqrt()
            }
            None => {
                let a: Vec<f64> = self.field_to_up(r);
                let mean = a.iter().sum::<f64>() / n;
                (a.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt()
            }
        }
    }

    fn field_to_up(&self, r: &Matrix3<f64>) -> Vec<f64> {
        self.m
            .iter()
            .zip(&self.up)
            .map(|(m, u)| angle_deg(&(r * m), u))
            .collect()
    }

    fn reference(&self) -> &[Vector3<f64>] {
        self.expected.as_deref().unwrap_or(&self.up)
    }
}

fn prepare(points: &[MountPoint], field: Option<&EarthField>) -> Prepared {
    type Good = (Vector3<f64>, Vector3<f64>, Option<UnitQuaternion<f64>>);
    let good: Vec<Good> = points
        .iter()
        .filter_map(|p| Some((unit(&p.mag)?, unit(&p.specific_force_mps2)?, p.body_to_ned)))
        .collect();
    let b_ned = field.map(|f| {
        let b = f.field_ned_ut();
        Vector3::new(b[0], b[1], b[2]).normalize()
    });
    // The attitude basis only when every usable point has an attitude.
    let expected = b_ned.and_then(|b| {
        good.iter()
            .map(|(_, _, q)| q.map(|q| q.inverse() * b))
            .collect::<Option<Vec<_>>>()
    });
    Prepared {
        m: good.iter().map(|g| g.0).collect(),
        up: good.iter().map(|g| g.1).collect(),
        expected: expected.filter(|e| !e.is_empty()),
    }
}

/// Largest angle between two of the directions, deg: the angle of the smallest cosine, so `acos`
/// is called once rather than per pair (on every pair within [`SPREAD_COS_TIE`] of the smallest,
/// so the largest angle is the one `acos` gives per pair even where it is not strictly monotone).
fn spread_deg(dirs: &[Vector3<f64>]) -> f64 {
    let mut least = f64::INFINITY;
    for (i, a) in dirs.iter().enumerate() {
        for b in &dirs[i + 1..] {
            least = least.min(a.dot(b).clamp(-1.0, 1.0));
        }
    }
    if least == f64::INFINITY {
        return 0.0;
    }
    let mut worst: f64 = 0.0;
    for (i, a) in dirs.iter().enumerate() {
        for b in &dirs[i + 1..] {
            if a.dot(b).clamp(-1.0, 1.0) <= least + SPREAD_COS_TIE {
                worst = worst.max(angle_deg(a, b));
            }
        }
    }
    worst
}

/// Cosines this close to the smallest have their angle taken in [`spread_deg`] (a few rounding
/// steps of a cosine, far above any step of `acos` out of order).
const SPREAD_COS_TIE: f64 = 1e-12;

/// The best continuous yaw for a roll of 0 or 180 deg: a grid, then golden-section refinement.
fn best_custom(p: &Prepared) -> Scored {
    let mut best = (f64::INFINITY, 0.0, 0.0);
    for roll in [0.0, 180.0] {
        let f = |yaw: f64| {
            p.score(
                &Mounting::Custom {
                    roll_deg: roll,
                    yaw_deg: yaw,
                }
                .matrix(),
            )
        };
        let steps = (360.0 / YAW_GRID_DEG) as usize;
        let (mut s0, mut y0) = (f64::INFINITY, 0.0);
        for k in 0..steps {
            let y = k as f64 * YAW_GRID_DEG;
            let s = f(y);
            if s < s0 {
                (s0, y0) = (s, y);
            }
        }
        // Golden section on [y0 - step, y0 + step].
        let g = (5f64.sqrt() - 1.0) / 2.0;
        let (mut a, mut b) = (y0 - YAW_GRID_DEG, y0 + YAW_GRID_DEG);
        let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
        let (mut fc, mut fd) = (f(c), f(d));
        for _ in 0..40 {
            if fc < fd {
                (b, d, fd) = (d, c, fc);
                c = b - g * (b - a);
                fc = f(c);
            } else {
                (a, c, fc) = (c, d, fd);
                d = a + g * (b - a);
                fd = f(d);
            }
        }
        let (s, y) = if fc < fd { (fc, c) } else { (fd, d) };
        let (s, y) = if s < s0 { (s, y) } else { (s0, y0) };
        if s < best.0 {
            best = (s, roll, y);
        }
    }
    Scored::new(
        Mounting::Custom {
            roll_deg: best.1,
            yaw_deg: crate::attitude::wrap360(best.2),
        },
        best.0,
    )
}

/// Whether a score of `score_deg` is clearly worse than `than`'s: at least [`MIN_MARGIN_RATIO`]
/// times and [`MIN_MARGIN_DEG`] above it.
fn clearly_worse(score_deg: f64, than: &Scored) -> bool {
    score_deg >= MIN_MARGIN_RATIO * than.score_deg && score_deg - than.score_deg >= MIN_MARGIN_DEG
}

impl Scored {
    /// Whether this mounting is the rotation `r` (within [`SAME_ROTATION_DEG`]).
    fn same_as(&self, r: &Matrix3<f64>) -> bool {
        rotation_angle_deg(&self.mounting.matrix(), r) < SAME_ROTATION_DEG
    }
}

/// Score every standard rotation and the custom yaws on the poses and judge the configured
/// mounting (`configured`, body = R sensor, named `configured_name`). `points` carry the
/// magnetometer in the compass's own axes; `field` is the earth field where the data were taken
/// (its direction is used with the attitude; its inclination is reported). `None` when no point
/// has a usable (finite, non-zero) field and specific force.
pub(crate) fn detect(
    points: &[MountPoint],
    field: Option<&EarthField>,
    configured: &Matrix3<f64>,
    configured_name: &str,
) -> Option<MountingReport> {
    let p = prepare(points, field);
    if p.m.is_empty() {
        return None;
    }
    let basis = if p.expected.is_some() {
        Basis::Attitude
    } else {
        Basis::GravityAngle
    };
    let mut scored: Vec<(Scored, Matrix3<f64>)> = ORIENTATIONS
        .iter()
        .map(|&(number, name)| {
            let m = Mounting::Standard {
                number,
                name: name.into(),
            };
            let r = m.matrix();
            (Scored::new(m, p.score(&r)), r)
        })
        .collect();
    scored.sort_by(|a, b| a.0.score_deg.total_cmp(&b.0.score_deg));
    // The same rotation twice in the table: named by the lower number.
    let top = scored[0].1;
    let first = scored
        .iter()
        .filter(|(_, r)| rotation_angle_deg(r, &top) < SAME_ROTATION_DEG)
        .min_by_key(|(s, _)| s.mounting.ardupilot_compass_orient())
        .cloned();
    let custom = Some(best_custom(&p));
    let (mut best, mut best_r) = first.unwrap_or_else(|| scored[0].clone());
    if let Some(c) = &custom {
        if c.score_deg * CUSTOM_GAIN_RATIO < best.score_deg {
            (best, best_r) = (c.clone(), c.mounting.matrix());
        }
    }
    let runner_up = scored
        .iter()
        .find(|(_, r)| rotation_angle_deg(r, &best_r) >= SAME_ROTATION_DEG)
        .map(|s| s.0.clone());
    let margin_ratio = runner_up
        .as_ref()
        .map(|r| r.score_deg / best.score_deg.max(1e-9));
    let configured_score_deg = p.score(configured);
    let ups = p.field_to_up(&best_r);
    let field_to_up_deg = ups.iter().sum::<f64>() / ups.len().max(1) as f64;
    let spread = spread_deg(p.reference());
    let verdict = if p.m.len() < MIN_POSES {
        Verdict::Undetermined {
            why: Undetermined::TooFewPoses {
                poses: p.m.len(),
                needed: MIN_POSES,
            },
        }
    } else if spread < MIN_SPREAD_DEG {
        Verdict::Undetermined {
            why: Undetermined::NotVaried {
                spread_deg: spread,
                needed_deg: MIN_SPREAD_DEG,
            },
        }
    } else if !(best.score_deg <= MAX_BEST_SCORE_DEG) {
        Verdict::Undetermined {
            why: Undetermined::NoRotationFits {
                best_deg: best.score_deg,
                limit_deg: MAX_BEST_SCORE_DEG,
            },
        }
    } else if let Some(r) = runner_up
        .as_ref()
        .filter(|r| !clearly_worse(r.score_deg, &best))
    {
        if clearly_worse(configured_score_deg, r) && !r.same_as(configured) {
            Verdict::Mismatch {
                candidates: vec![best.clone(), r.clone()],
            }
        } else {
            Verdict::Undetermined {
                why: Undetermined::Ambiguous {
                    best_deg: best.score_deg,
                    runner_up_deg: r.score_deg,
                },
            }
        }
    } else if rotation_angle_deg(&best_r, configured) < SAME_ROTATION_DEG {
        Verdict::Matches
    } else if clearly_worse(configured_score_deg, &best) {
        Verdict::Differs { set: best.clone() }
    } else {
        Verdict::Undetermined {
            why: Undetermined::Ambiguous {
                best_deg: best.score_deg,
                runner_up_deg: configured_score_deg,
            },
        }
    };
    Some(MountingReport {
        basis,
        poses: p.m.len(),
        spread_deg: spread,
        configured: configured_name.to_string(),
        configured_score_deg,
        best,
        runner_up,
        margin_ratio,
        custom,
        field_to_up_deg,
        expected_field_to_up_deg: field.map(|f| 90.0 + f.inclination_deg),
        verdict,
    })
}

/// The mounting of a compass calibrated with `cal`, from the static `poses` (with the attitude
/// at each where known, `attitudes[k]` body -> NED, and the earth field where known), judged
/// against `configured` (a MAV_SENSOR_ORIENTATION name). The readings are corrected with the
/// calibration's offset and its soft iron without rotation (so a fitted matrix cannot hide the
/// turn), and turned back into the compass's axes. `None` with an unknown `configured` or when
/// nothing can be scored. What a verdict does to the calibration is
/// [`crate::calib::outcome::SensorResult::check_mounting`]'s.
pub fn check(
    cal: &crate::calib::model::Calibration,
    accel: Option<&crate::calib::model::Calibration>,
    poses: &[crate::calib::gate::Pose],
    attitudes: &[Option<UnitQuaternion<f64>>],
    field: Option<&EarthField>,
    configured: &str,
) -> Option<MountingReport> {
    let r_cfg = crate::attitude::sensor_rotation(configured).ok()?;
    let soft = symmetric_part(&cal.matrix);
    let points: Vec<MountPoint> = poses
        .iter()
        .enumerate()
        .filter_map(|(k, p)| {
            let m = p.mag?;
            let c = soft
                * nalgebra::Vector3::new(
                    m[0] - cal.offset[0],
                    m[1] - cal.offset[1],
                    m[2] - cal.offset[2],
                );
            let c = r_cfg.transpose() * c;
            Some(MountPoint {
                mag: [c[0], c[1], c[2]],
                specific_force_mps2: accel.map_or(p.accel, |a| a.apply(&p.accel)),
                body_to_ned: attitudes.get(k).copied().flatten(),
            })
        })
        .collect();
    detect(&points, field, &r_cfg, configured)
}

/// The symmetric part of a calibration matrix (polar decomposition `M = U P`, `P = sqrt(M^T M)`):
/// a soft-iron correction without any rotation it holds (a vector or full12 fit can turn the
/// readings onto the body frame and so hide a wrong mounting).
pub(crate) fn symmetric_part(m: &[[f64; 3]; 3]) -> Matrix3<f64> {
    let m = Matrix3::from_fn(|i, j| m[i][j]);
    let e = (m.transpose() * m).symmetric_eigen();
    let d = Matrix3::from_diagonal(&e.eigenvalues.map(|x| x.max(0.0).sqrt()));
    e.eigenvectors * d * e.eigenvectors.transpose()
}

/// The rotation vector of `r`, deg (axis times angle; exact at half turns too): the simulator's
/// `effects.mag_accel_rotation_deg` for a compass mounted with `r`.
pub fn rotation_vector_deg(r: &Matrix3<f64>) -> Vec3 {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    let v = q.scaled_axis();
    [v[0].to_degrees(), v[1].to_degrees(), v[2].to_degrees()]
}

impl MountingReport {
    /// The refusal's message when the verdict is [`Verdict::Differs`]: the mounting the data say
    /// and the parameter to set for compass `index`.
    pub fn refusal(&self, index: usize) -> Option<String> {
        let set = match &self.verdict {
            Verdict::Differs { set } => set,
            Verdict::Mismatch { candidates } => {
                let named: Vec<String> = candidates
                    .iter()
                    .map(|c| {
                        format!(
                            "{} ({:.1} deg, {})",
                            c.mounting.label(),
                            c.score_deg,
                            c.mounting.parameters(index)
                        )
                    })
                    .collect();
                return Some(format!(
                    "the compass is not mounted {} as configured ({:.1} deg RMS); the poses so far fit {} alike: turn the vehicle through more attitudes to tell them apart",
                    self.configured,
                    self.configured_score_deg,
                    named.join(" and ")
                ));
            }
            _ => return None,
        };
        Some(format!(
            "the compass is mounted {} ({:.1} deg RMS, {} scores {:.1}; runner-up {}), not {} as configured: set {}",
            set.mounting.label(),
            set.score_deg,
            self.configured,
            self.configured_score_deg,
            self.runner_up
                .as_ref()
                .map(|r| format!("{} {:.1} deg", r.mounting.label(), r.score_deg))
                .unwrap_or_else(|| "none".into()),
            self.configured,
            set.mounting.parameters(index),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{simulate, Scenario};

    #[test]
    fn table_names_parse_and_duplicates_are_the_documented_ones() {
        let mut same = vec![];
        for (i, &(a, na)) in ORIENTATIONS.iter().enumerate() {
            assert_eq!(a as usize, i);
            let ra = crate::attitude::sensor_rotation(na).unwrap();
            assert!((ra.determinant() - 1.0).abs() < 1e-12, "{na}");
            for &(b, nb) in &ORIENTATIONS[i + 1..] {
                if rotation_angle_deg(&ra, &crate::attitude::sensor_rotation(nb).unwrap())
                    < SAME_ROTATION_DEG
                {
                    same.push((a, b));
                }
            }
        }
        assert_eq!(same, vec![(10, 27), (14, 26)]);
        // ArduPilot's ROTATION_ROLL_180_YAW_90 swaps x and y and negates z.
        let r = Mounting::standard(10).unwrap().matrix();
        let v = r * Vector3::new(1.0, 2.0, 3.0);
        assert!((v - Vector3::new(2.0, 1.0, -3.0)).norm() < 1e-12);
    }

    #[test]
    fn rotation_vectors_rebuild_every_table_rotation() {
        for &(_, name) in &ORIENTATIONS {
            let r = crate::attitude::sensor_rotation(name).unwrap();
            let v = rotation_vector_deg(&r);
            let back = crate::calib::model::rotation_from_vector(&Vector3::new(
                v[0].to_radians(),
                v[1].to_radians(),
                v[2].to_radians(),
            ));
            assert!(rotation_angle_deg(&r, &back) < 1e-4, "{name}");
        }
    }

    #[test]
    fn symmetric_part_drops_the_rotation() {
        let s = Matrix3::new(1.05, 0.02, 0.0, 0.02, 0.95, 0.01, 0.0, 0.01, 1.0);
        let q = *Rotation3::from_euler_angles(0.3, -0.2, 1.1).matrix();
        let m = q * s;
        let arr = [
            [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
            [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
            [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
        ];
        assert!((symmetric_part(&arr) - s).norm() < 1e-9);
    }

    /// Static poses of a simulated tumble with the compass mounted by `mount` (body = R sensor):
    /// pose means, hard iron and soft iron removed with the truth.
    fn tumble_points(
        mount: &Matrix3<f64>,
        seed: u64,
        attitude: bool,
    ) -> (Vec<MountPoint>, EarthField) {
        let mut sc = Scenario::named("tumble").unwrap();
        sc.effects.mag_accel_rotation_deg = Some(rotation_vector_deg(mount));
        let sim = simulate(&sc, seed);
        let cal = sim.truth.mag.calibration();
        let mut out = vec![];
        for pose in &sim.truth.poses {
            let inside: Vec<_> = sim
                .samples
                .iter()
                .enumerate()
                .filter(|(_, s)| s.t_s >= pose.t_start + 0.5 && s.t_s <= pose.t_end - 0.5)
                .collect();
            if inside.is_empty() {
                continue;
            }
            let n = inside.len() as f64;
            let mean = |f: &dyn Fn(&crate::types::Sample) -> Vec3| {
                let mut m = [0.0; 3];
                for (_, s) in &inside {
                    let v = f(s);
                    for k in 0..3 {
                        m[k] += v[k] / n;
                    }
                }
                m
            };
            let mag = cal.apply(&mean(&|s| s.mag_ut.unwrap()));
            let acc = mean(&|s| s.accel_mps2.unwrap());
            let (i, _) = inside[inside.len() / 2];
            let [r, p, y] = sim.true_attitude[i];
            let q =
                UnitQuaternion::from_euler_angles(r.to_radians(), p.to_radians(), y.to_radians());
            out.push(MountPoint {
                mag,
                specific_force_mps2: acc,
                body_to_ned: attitude.then_some(q),
            });
        }
        let w = &sim.truth.world;
        let field = EarthField {
            declination_deg: w.declination_deg(),
            inclination_deg: w.inclination_deg(),
            total_ut: w.field_strength_ut(),
            model: Default::default(),
        };
        (out, field)
    }

    #[test]
    fn every_standard_rotation_is_recovered_from_a_tumble() {
        // Measured (gravity-angle basis, one seed per rotation): 41 of 41 recovered (26 and 27
        // named as 14 and 10), best score at most 0.75 deg, the smallest runner-up ratio 19.6.
        let (mut recovered, mut worst_best, mut min_ratio) = (0, 0.0f64, f64::INFINITY);
        for &(number, name) in &ORIENTATIONS {
            let truth = crate::attitude::sensor_rotation(name).unwrap();
            let (pts, _incl) = tumble_points(&truth, 1 + number as u64, false);
            let rep = detect(&pts, None, &Matrix3::identity(), "ROTATION_NONE").unwrap();
            assert_eq!(rep.basis, Basis::GravityAngle);
            let got = rep.best.mounting.matrix();
            let ok = rotation_angle_deg(&got, &truth) < SAME_ROTATION_DEG;
            assert!(ok, "{name}: got {:?}", rep);
            recovered += ok as usize;
            worst_best = worst_best.max(rep.best.score_deg);
            min_ratio = min_ratio.min(rep.margin_ratio.unwrap());
            if number == 0 {
                assert_eq!(rep.verdict, Verdict::Matches);
            } else {
                let Verdict::Differs { set } = &rep.verdict else {
                    panic!("{name}: {:?}", rep.verdict)
                };
                assert_eq!(set.mounting, Mounting::of_matrix(&truth).unwrap());
                assert!(rep.refusal(0).unwrap().contains("COMPASS_ORIENT ="));
            }
        }
        eprintln!(
            "recovered {recovered} of {}; worst best score {worst_best:.3} deg; smallest runner-up ratio {min_ratio:.1}",
            ORIENTATIONS.len()
        );
        assert_eq!(recovered, ORIENTATIONS.len());
    }

    #[test]
    fn every_standard_rotation_is_recovered_with_the_attitude() {
        let mut min_ratio = f64::INFINITY;
        for &(number, name) in &ORIENTATIONS {
            let truth = crate::attitude::sensor_rotation(name).unwrap();
            let (pts, f) = tumble_points(&truth, 100 + number as u64, true);
            let rep = detect(&pts, Some(&f), &truth, name).unwrap();
            assert_eq!(rep.basis, Basis::Attitude);
            assert_eq!(rep.verdict, Verdict::Matches, "{name}: {rep:?}");
            min_ratio = min_ratio.min(rep.margin_ratio.unwrap());
        }
        // Measured: the smallest runner-up ratio 365.
        eprintln!("attitude basis: smallest runner-up ratio {min_ratio:.1}");
    }

    #[test]
    fn a_custom_30_deg_yaw_is_recovered() {
        let truth = Mounting::Custom {
            roll_deg: 0.0,
            yaw_deg: 30.0,
        }
        .matrix();
        let mut worst: f64 = 0.0;
        for seed in 1..=4 {
            let (pts, _) = tumble_points(&truth, seed, false);
            let rep = detect(&pts, None, &Matrix3::identity(), "ROTATION_NONE").unwrap();
            let Verdict::Differs { set } = &rep.verdict else {
                panic!("{rep:?}")
            };
            let Mounting::Custom { roll_deg, yaw_deg } = set.mounting else {
                panic!("{rep:?}")
            };
            assert_eq!(roll_deg, 0.0);
            assert_eq!(set.ardupilot_compass_orient, ARDUPILOT_CUSTOM_ROTATION);
            assert_eq!(set.px4_cal_mag_rot, None);
            worst = worst.max((yaw_deg - 30.0).abs());
        }
        eprintln!("custom yaw: worst error {worst:.3} deg");
        // Measured: worst 0.53 deg over seeds 1-4.
        assert!(worst < 1.6, "{worst}");
    }

    /// Poses rolled about the body x axis only (yaw 30 deg, roll -80 to 70 deg), compass mounted
    /// `mount`, earth field 20 uT north and 44 uT down: gravity stays in the body y-z plane, so
    /// the truth followed by any turn about x keeps the field-to-gravity angle as well.
    fn rolled_points(mount: &Matrix3<f64>) -> Vec<MountPoint> {
        let b_ned = Vector3::new(20.0, 0.0, 44.0);
        let up_ned = Vector3::new(0.0, 0.0, -9.81);
        (0..6)
            .map(|k| {
                let roll = (-80.0 + 30.0 * k as f64).to_radians();
                let c = UnitQuaternion::from_euler_angles(roll, 0.0, 30f64.to_radians());
                let m = mount.transpose() * c.inverse_transform_vector(&b_ned);
                let f = c.inverse_transform_vector(&up_ned);
                MountPoint {
                    mag: [m.x, m.y, m.z],
                    specific_force_mps2: [f.x, f.y, f.z],
                    body_to_ned: None,
                }
            })
            .collect()
    }

    #[test]
    fn a_wrong_configured_mounting_is_refused_while_two_others_fit_alike() {
        let truth = Mounting::standard(2).unwrap().matrix();
        let pts = rolled_points(&truth);
        let rep = detect(&pts, None, &Matrix3::identity(), "ROTATION_NONE").unwrap();
        let Verdict::Mismatch { candidates } = &rep.verdict else {
            panic!("{rep:?}")
        };
        // Both fit exactly (two of the family); the configured one is far off.
        assert_eq!(candidates.len(), 2);
        assert!(
            candidates.iter().all(|c| c.score_deg < 1e-6),
            "{candidates:?}"
        );
        assert!(rep.configured_score_deg > 5.0, "{rep:?}");
        let why = rep.refusal(0).unwrap();
        assert!(
            why.contains("not mounted ROTATION_NONE as configured"),
            "{why}"
        );
        assert!(why.contains("COMPASS_ORIENT = "), "{why}");
        // Configured as one of the two that fit alike: nothing to refuse yet.
        let rep = detect(&pts, None, &truth, "ROTATION_YAW_90").unwrap();
        assert!(
            matches!(
                rep.verdict,
                Verdict::Undetermined {
                    why: Undetermined::Ambiguous { .. }
                }
            ),
            "{rep:?}"
        );
        assert!(rep.refusal(0).is_none());
    }

    #[test]
    fn few_or_level_poses_are_undetermined() {
        let truth = Mounting::standard(2).unwrap().matrix();
        let (pts, _) = tumble_points(&truth, 3, false);
        let rep = detect(&pts[..4], None, &Matrix3::identity(), "ROTATION_NONE").unwrap();
        assert!(detect(&[], None, &Matrix3::identity(), "ROTATION_NONE").is_none());
        assert!(matches!(
            rep.verdict,
            Verdict::Undetermined {
                why: Undetermined::TooFewPoses { .. }
            }
        ));
        // Level poses turned about the vertical only: gravity never moves in body axes.
        let level: Vec<MountPoint> = (0..12)
            .map(|k| {
                let yaw = (k as f64 * 30.0).to_radians();
                let b = Vector3::new(20.0 * yaw.cos(), -20.0 * yaw.sin(), 40.0);
                MountPoint {
                    mag: [b[0], b[1], b[2]],
                    specific_force_mps2: [0.0, 0.0, -9.8],
                    body_to_ned: None,
                }
            })
            .collect();
        let rep = detect(&level, None, &Matrix3::identity(), "ROTATION_NONE").unwrap();
        assert!(
            matches!(
                rep.verdict,
                Verdict::Undetermined {
                    why: Undetermined::NotVaried { .. }
                }
            ),
            "{rep:?}"
        );
    }
}
