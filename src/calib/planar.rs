//! Magnetometer calibration for a vehicle that turns about the vertical only (a rover, a boat):
//! the hard and soft iron in the horizontal plane, then a heading deviation curve against a true
//! heading reference when there is one. Pure math: no I/O.
//!
//! Each reading is tilt-compensated with the accelerometer: roll and pitch from the specific force
//! (the turn's centripetal acceleration `omega x v` taken out when the ground speed is known), then
//! the field in the level frame (x forward along the heading, z down) is
//!
//! ```text
//! b = S (m_xy - o_xy)                                   body x, y after the 2-D calibration
//! l_x = (b_x + sin(pitch) V) / cos(pitch)
//! l_y = (b_y - sin(roll) (sin(pitch) l_x + cos(pitch) V)) / cos(roll)
//! heading = atan2(-l_y, l_x)
//! ```
//!
//! with S a symmetric 2x2 soft iron, o_xy the horizontal hard iron and V the field's vertical
//! component. The body-z reading is not used at all: rotations about the vertical leave its offset
//! and its soft-iron terms unobservable (they would only be seen through large tilts), so heading
//! does not rest on them, and they are reported as [`Undetermined`], held at nominal. V is fitted
//! from how the horizontal field changes with the terrain's tilt, and held at the World Magnetic
//! Model's value (or 0 without a place) when the tilts do not determine it.
//!
//! The fit makes |l_xy| the horizontal intensity H (the World Magnetic Model's when the place is
//! known, else the ellipse's mean radius, so the units stay the sensor's): an algebraic ellipse fit
//! of the raw (x, y) readings starts a Gauss-Newton fit of (o_x, o_y, S, V), one pass of outlier
//! rejection follows. What the symmetric S cannot hold (a rotation, a mounting yaw, the
//! declination when the place is unknown) and any remaining heading-dependent error is taken by
//! the classic deviation curve of the compass swing,
//!
//! ```text
//! deviation(h) = A + B sin h + C cos h + D sin 2h + E cos 2h     (deg, h the compass heading)
//! ```
//!
//! (National Geospatial-Intelligence Agency, "Handbook of Magnetic Compass Adjustment", formerly
//! Pub. No. 226, 2004, chapter V: the deviation curve and its approximate coefficients), fitted by
//! least squares to reference minus compass heading. The reference is the logged attitude's yaw,
//! else the GNSS course over ground on straight stretches. Five coefficients rather than a table
//! per heading bin: they need no bin to be filled, they are the physical terms (constant,
//! semicircular from hard iron, quadrantal from soft iron), and they interpolate smoothly.

use crate::attitude::{angle_diff_deg, wrap360};
use crate::types::{GeoPoint, Sample, Vec3};
use nalgebra::{DMatrix, Matrix2, SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// Default largest tilt from level of a reading the fit uses, deg (the rest are left out, counted).
pub(crate) const DEFAULT_MAX_TILT_DEG: f64 = 20.0;
/// Default least number of readings.
pub(crate) const DEFAULT_MIN_POINTS: usize = 200;
/// Default outlier cut: residuals beyond this many robust standard deviations are left out.
pub(crate) const DEFAULT_OUTLIER_SIGMAS: f64 = 5.0;
/// Default: V counts as determined when its 1-sigma is at most this fraction of the horizontal
/// intensity (1 deg of heading per degree of tilt at this fraction).
pub(crate) const DEFAULT_MAX_VERTICAL_SIGMA_FRACTION: f64 = 0.02;
/// Default least number of readings with a heading reference for the deviation curve.
pub(crate) const DEFAULT_MIN_REFERENCE_POINTS: usize = 50;
/// Default least number of the [`YAW_SECTORS`] sectors the calibrated headings must visit.
pub(crate) const DEFAULT_MIN_YAW_SECTORS: usize = 10;
/// Default least number of sectors the referenced readings must visit for the deviation curve
/// (five coefficients; a course over ground comes from straight stretches only).
pub(crate) const DEFAULT_MIN_REFERENCE_SECTORS: usize = 6;

/// The circle of headings is split into this many equal sectors (30 deg each) for coverage.
pub(crate) const YAW_SECTORS: usize = 12;
/// Readings turning at least this fast give the turn axis's tilt, rad/s.
pub(crate) const MIN_TURN_RATE_RAD_S: f64 = 0.1;
/// A specific force below this is no tilt reference (free fall, a broken reading), m/s^2.
pub(crate) const MIN_SPECIFIC_FORCE_MPS2: f64 = 4.0;
/// Gauss-Newton stops when the step changes no parameter by more than this fraction of the
/// horizontal intensity.
const STEP_TOL_FRACTION: f64 = 1e-9;
/// Relative damping added to the normal matrix's diagonal in each Gauss-Newton step.
const DAMPING: f64 = 1e-10;
/// Gauss-Newton iterations at most.
const MAX_ITERATIONS: usize = 60;
/// Normal-approximation factor from the median absolute deviation to a standard deviation.
const MAD_TO_SIGMA: f64 = 1.4826;

/// Course over ground: the displacement between GNSS fixes at least this far apart, s.
pub(crate) const COURSE_BASELINE_S: f64 = 1.0;
/// A ground track is used for a reading at most this far from its time, s.
pub(crate) const MAX_TRACK_AGE_S: f64 = 1.0;
/// The course over ground is a heading reference only above this ground speed, m/s.
pub(crate) const MIN_COURSE_SPEED_MPS: f64 = 1.0;
/// ... and only while turning slower than this, rad/s (a straight stretch: 3 deg/s).
pub(crate) const MAX_COURSE_YAW_RATE_RAD_S: f64 = 0.052;
/// The earth's mean radius for the local north/east displacement between fixes, m.
const EARTH_RADIUS_M: f64 = 6_371_000.0;

/// Knobs of [`fit`]; every default is a named constant above.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PlanarSettings {
    /// Readings tilted more than this from level are left out, deg. Default 20.
    pub max_tilt_deg: f64,
    /// Least number of usable readings. Default 200.
    pub min_points: usize,
    /// Outlier cut in robust standard deviations of the residual. Default 5.
    pub outlier_sigmas: f64,
    /// V is determined when its 1-sigma is at most this fraction of H. Default 0.02.
    pub max_vertical_sigma_fraction: f64,
    /// Least number of referenced readings for the deviation curve. Default 50.
    pub min_reference_points: usize,
    /// Least number of the 12 heading sectors the calibrated headings visit. Default 10.
    pub min_yaw_sectors: usize,
    /// Least number of sectors the referenced readings visit for the deviation curve. Default 6.
    pub min_reference_sectors: usize,
}

impl PlanarSettings {
    pub(crate) const DEFAULT: PlanarSettings = PlanarSettings {
        max_tilt_deg: DEFAULT_MAX_TILT_DEG,
        min_points: DEFAULT_MIN_POINTS,
        outlier_sigmas: DEFAULT_OUTLIER_SIGMAS,
        max_vertical_sigma_fraction: DEFAULT_MAX_VERTICAL_SIGMA_FRACTION,
        min_reference_points: DEFAULT_MIN_REFERENCE_POINTS,
        min_yaw_sectors: DEFAULT_MIN_YAW_SECTORS,
        min_reference_sectors: DEFAULT_MIN_REFERENCE_SECTORS,
    };
}

impl Default for PlanarSettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Where a true heading reference came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReferenceKind {
    /// The logged attitude's yaw (ATTITUDE / ATTITUDE_QUATERNION, ATT, `vehicle_attitude`).
    Attitude,
    /// The GNSS course over ground on straight stretches.
    CourseOverGround,
}

/// One reading in body axes (FRD).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanarPoint {
    pub t_s: f64,
    /// Magnetometer, body axes, the sensor's units.
    pub mag: Vec3,
    /// Specific force, body axes, m/s^2 (reads (0, 0, -g) level at rest).
    pub accel_mps2: Vec3,
    /// Angular rate, body axes, rad/s (for the centripetal acceleration).
    pub gyro_rad_s: Option<Vec3>,
    /// Ground speed along the body x axis, m/s.
    pub ground_speed_mps: Option<f64>,
    /// True heading of the body x axis, deg clockwise from true north, and where it came from.
    pub reference: Option<(f64, ReferenceKind)>,
}

impl PlanarPoint {
    /// The specific force of gravity alone: the measured one minus the acceleration of a turn at
    /// the ground speed (`omega x v`, v along body x), when both are known.
    pub(crate) fn gravity_force(&self) -> Vec3 {
        let f = self.accel_mps2;
        match (self.gyro_rad_s, self.ground_speed_mps) {
            (Some(w), Some(v)) if w.iter().all(|x| x.is_finite()) && v.is_finite() => {
                [f[0], f[1] - w[2] * v, f[2] + w[1] * v]
            }
            _ => f,
        }
    }

    /// Roll and pitch, rad, from [`PlanarPoint::gravity_force`].
    pub(crate) fn roll_pitch_rad(&self) -> (f64, f64) {
        let f = self.gravity_force();
        let pitch = f[0].atan2((f[1] * f[1] + f[2] * f[2]).sqrt());
        let roll = (-f[1]).atan2(-f[2]);
        (roll, pitch)
    }

    /// Angle between the body z axis and the vertical, deg.
    pub(crate) fn tilt_deg(&self) -> f64 {
        let f = self.gravity_force();
        let n = crate::types::norm(&f);
        (-f[2] / n).clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// Whether [`PlanarPoint::tilt_deg`] is at most `max_deg`, told by the cosine (no `acos`).
    pub(crate) fn within_tilt(&self, max_deg: f64) -> bool {
        if !(max_deg >= 0.0) {
            return false;
        }
        if max_deg >= 180.0 {
            return true;
        }
        let f = self.gravity_force();
        let n = crate::types::norm(&f);
        (-f[2] / n).clamp(-1.0, 1.0) >= max_deg.to_radians().cos()
    }

    fn usable(&self) -> bool {
        crate::types::is_finite3(&self.mag)
            && crate::types::is_finite3(&self.accel_mps2)
            && crate::types::norm(&self.gravity_force()) >= MIN_SPECIFIC_FORCE_MPS2
    }
}

/// The earth field at the place (World Magnetic Model), in the magnetometer's units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanarEarth {
    pub horizontal: f64,
    /// Down component (positive in the northern hemisphere).
    pub vertical: f64,
    pub declination_deg: f64,
}

/// What rotations about the vertical cannot determine; held as said, never guessed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Undetermined {
    /// The body-z hard iron: held at nominal (0). Heading does not use the body-z reading.
    OffsetZ,
    /// The z row and column of the soft iron (z scale, xz and yz terms): held at identity; on
    /// level ground the xz/yz terms act as part of the horizontal hard iron.
    SoftIronZ,
    /// The field's vertical component: the tilts seen were too small; held at the World Magnetic
    /// Model's value (or 0 without a place).
    FieldVertical,
    /// No heading reference: the constant deviation (mounting yaw, declination without a place)
    /// and the remaining deviation curve are not known.
    HeadingDeviation,
}

impl Undetermined {
    pub(crate) fn describe(self) -> &'static str {
        match self {
            Undetermined::OffsetZ => "z offset (held at 0)",
            Undetermined::SoftIronZ => "z soft iron (held at identity)",
            Undetermined::FieldVertical => {
                "vertical field (tilts too small; held at the model's value, 0 without a place)"
            }
            Undetermined::HeadingDeviation => "heading deviation (no heading reference)",
        }
    }
}

/// The deviation curve `A + B sin h + C cos h + D sin 2h + E cos 2h`, deg.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Deviation {
    /// [A, B, C, D, E], deg.
    pub coefficients_deg: [f64; 5],
    /// Their 1-sigma, deg.
    pub sigma_deg: [f64; 5],
    /// RMS of reference minus corrected heading over the referenced readings, deg.
    pub rms_deg: f64,
    /// Largest |reference minus corrected heading|, deg.
    pub max_deg: f64,
    /// RMS of reference minus compass heading before the curve, deg.
    pub rms_before_deg: f64,
    pub points: usize,
    pub outliers_rejected: usize,
    pub source: ReferenceKind,
}

impl Deviation {
    /// The deviation at compass heading `h_deg`, deg.
    pub fn at(&self, h_deg: f64) -> f64 {
        let h = h_deg.to_radians();
        let c = &self.coefficients_deg;
        c[0] + c[1] * h.sin() + c[2] * h.cos() + c[3] * (2.0 * h).sin() + c[4] * (2.0 * h).cos()
    }
}

/// The 2-D calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanarFit {
    /// Horizontal hard iron (body x, y), the sensor's units.
    pub offset_xy: [f64; 2],
    pub offset_sigma_xy: [f64; 2],
    /// Symmetric soft iron of the body x, y readings: calibrated_xy = S (raw_xy - offset_xy).
    pub soft_iron_xy: [[f64; 2]; 2],
    /// The field's vertical component used for the tilt compensation, calibrated units.
    pub vertical: f64,
    /// Its 1-sigma (None when held).
    pub vertical_sigma: Option<f64>,
    /// The horizontal intensity the readings are scaled to.
    pub horizontal: f64,
    /// RMS of |level field| - horizontal.
    pub rms_residual: f64,
    pub points: usize,
    pub outliers_rejected: usize,
    /// Readings left out for a tilt above the settings' limit.
    pub too_tilted: usize,
    /// Tilt from level over the usable readings: 95th percentile and largest, deg.
    pub tilt_p95_deg: f64,
    pub tilt_max_deg: f64,
    /// Mean bank of the turns, deg: atan(sum of the body pitch rate / sum of |yaw rate|) over the
    /// readings turning faster than [`MIN_TURN_RATE_RAD_S`]. An aircraft in a coordinated turn
    /// pitches up through the turn either way (q = r tan(bank)), and its accelerometer reads level
    /// when its speed is not known; a ground vehicle's pitch rates from the terrain average out
    /// (the pitch-rate bias is taken out as the median on straight stretches). None without gyro
    /// readings in turns.
    pub turn_bank_deg: Option<f64>,
    /// Heading sectors (of [`YAW_SECTORS`]) the calibrated headings visit.
    pub yaw_sectors: usize,
    /// Declination added to the magnetic heading (the place's), deg; None: unknown, and then a
    /// deviation curve's A holds it.
    pub declination_deg: Option<f64>,
    pub deviation: Option<Deviation>,
    /// Why the deviation curve was not fitted although there were references.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation_skipped: Option<String>,
    pub undetermined: Vec<Undetermined>,
}

impl PlanarFit {
    /// calibrated body (x, y).
    pub(crate) fn calibrated_xy(&self, mag: &Vec3) -> [f64; 2] {
        let s = &self.soft_iron_xy;
        let (dx, dy) = (mag[0] - self.offset_xy[0], mag[1] - self.offset_xy[1]);
        [s[0][0] * dx + s[0][1] * dy, s[1][0] * dx + s[1][1] * dy]
    }

    /// Magnetic heading of the compass (before the deviation curve), deg in [0, 360).
    pub(crate) fn compass_heading_deg(&self, p: &PlanarPoint) -> f64 {
        let (roll, pitch) = p.roll_pitch_rad();
        let l = level_xy(self.calibrated_xy(&p.mag), roll, pitch, self.vertical);
        wrap360((-l[1]).atan2(l[0]).to_degrees())
    }

    /// Heading of the body x axis, deg in [0, 360): the compass heading with the deviation curve
    /// and the declination applied (from true north when the declination is known; otherwise from
    /// the reference's north if a deviation curve was fitted, else magnetic).
    pub fn heading_deg(&self, p: &PlanarPoint) -> f64 {
        let h = self.compass_heading_deg(p);
        let dev = self.deviation.as_ref().map_or(0.0, |d| d.at(h));
        wrap360(h + dev + self.declination_deg.unwrap_or(0.0))
    }

    /// The 3-D calibration it stands for (calibrated = matrix (raw - offset)), the undetermined z
    /// terms at nominal.
    pub fn calibration(&self) -> ([f64; 3], [[f64; 3]; 3]) {
        let s = &self.soft_iron_xy;
        (
            [self.offset_xy[0], self.offset_xy[1], 0.0],
            [
                [s[0][0], s[0][1], 0.0],
                [s[1][0], s[1][1], 0.0],
                [0.0, 0.0, 1.0],
            ],
        )
    }
}

/// Why [`fit`] gave no result.
#[derive(Debug, Clone, PartialEq)]
pub enum PlanarFailure {
    NotEnoughPoints {
        have: usize,
        need: usize,
    },
    /// The (x, y) readings do not lie on an ellipse (no turn, or a degenerate spread).
    NotAnEllipse,
    /// The readings visit too few heading sectors.
    NarrowYaw {
        sectors: usize,
        need: usize,
    },
    /// The fitted 2x2 soft iron is not a calibration: its eigenvalues, normalised to their
    /// geometric mean, are not both within [`SOFT_IRON_EIGEN_BOUNDS`] (a negative one mirrors the
    /// heading).
    SoftIron {
        eigenvalues: [f64; 2],
    },
}

/// Bounds on the eigenvalues of the fitted 2x2 soft iron normalised to unit determinant (or,
/// when the determinant is not positive, to the larger eigenvalue's size): the bounds ArduPilot's
/// CompassCalibrator puts on the diagonal of its normalised soft iron (0.2 to 5). Outside, the
/// fit has found a mirror or a degenerate ellipse, not the soft iron of a board.
pub(crate) const SOFT_IRON_EIGEN_BOUNDS: (f64, f64) = (0.2, 5.0);

/// The eigenvalues of the symmetric 2x2 `s`, normalised (see [`SOFT_IRON_EIGEN_BOUNDS`]).
fn normalised_eigenvalues(s: &[[f64; 2]; 2]) -> [f64; 2] {
    let (a, b, d) = (s[0][0], s[0][1], s[1][1]);
    let mean = 0.5 * (a + d);
    let r = (0.25 * (a - d).powi(2) + b * b).sqrt();
    let (l1, l2) = (mean + r, mean - r);
    let det = l1 * l2;
    let scale = if det > 0.0 {
        det.sqrt()
    } else {
        l1.abs().max(l2.abs()).max(1e-300)
    };
    [l1 / scale, l2 / scale]
}

impl std::fmt::Display for PlanarFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlanarFailure::NotEnoughPoints { have, need } => {
                write!(f, "{have} usable readings, need {need}")
            }
            PlanarFailure::NotAnEllipse => {
                write!(f, "the horizontal readings do not lie on an ellipse")
            }
            PlanarFailure::NarrowYaw { sectors, need } => write!(
                f,
                "the headings visit {sectors} of {YAW_SECTORS} sectors, need {need}"
            ),
            PlanarFailure::SoftIron { eigenvalues } => write!(
                f,
                "the fitted horizontal soft iron is not a calibration (normalised eigenvalues {:.3} and {:.3}, a calibration's are within {}..{}{})",
                eigenvalues[0],
                eigenvalues[1],
                SOFT_IRON_EIGEN_BOUNDS.0,
                SOFT_IRON_EIGEN_BOUNDS.1,
                if eigenvalues.iter().any(|e| *e <= 0.0) {
                    "; a negative one mirrors the heading"
                } else {
                    ""
                }
            ),
        }
    }
}

/// The level-frame horizontal field from calibrated body (x, y), roll, pitch (rad) and V.
fn level_xy(b: [f64; 2], roll: f64, pitch: f64, vertical: f64) -> [f64; 2] {
    level_xy_of(b, &Tilt::of(roll, pitch), vertical)
}

/// Sines and cosines of a reading's roll and pitch, computed once per reading.
#[derive(Debug, Clone, Copy)]
struct Tilt {
    sin_roll: f64,
    cos_roll: f64,
    sin_pitch: f64,
    cos_pitch: f64,
}

impl Tilt {
    fn of(roll_rad: f64, pitch_rad: f64) -> Tilt {
        let (sin_roll, cos_roll) = roll_rad.sin_cos();
        let (sin_pitch, cos_pitch) = pitch_rad.sin_cos();
        Tilt {
            sin_roll,
            cos_roll,
            sin_pitch,
            cos_pitch,
        }
    }
}

/// [`level_xy`] with the tilt's sines and cosines given.
fn level_xy_of(b: [f64; 2], t: &Tilt, vertical: f64) -> [f64; 2] {
    let lx = (b[0] + t.sin_pitch * vertical) / t.cos_pitch;
    let ly = (b[1] - t.sin_roll * (t.sin_pitch * lx + t.cos_pitch * vertical)) / t.cos_roll;
    [lx, ly]
}

/// Parameters of the Gauss-Newton fit: o_x, o_y, s11, s12, s22, V.
type Params = SVector<f64, 6>;

/// A reading reduced to what the fit needs: the horizontal raw field and the tilt.
#[derive(Debug, Clone, Copy)]
struct Reduced {
    m: [f64; 2],
    tilt: Tilt,
}

fn residual(p: &Params, r: &Reduced, horizontal: f64) -> f64 {
    let (dx, dy) = (r.m[0] - p[0], r.m[1] - p[1]);
    let b = [p[2] * dx + p[3] * dy, p[3] * dx + p[4] * dy];
    let l = level_xy_of(b, &r.tilt, p[5]);
    (l[0] * l[0] + l[1] * l[1]).sqrt() - horizontal
}

/// [`residual`] and its gradient over the parameters (o_x, o_y, s11, s12, s22, V), analytic:
/// through the level field `l` (`d|l| = l / |l| . dl`), `l_x` linear in `b_x` and V, `l_y` in
/// `b_y`, `l_x` and V, and `b = S (m - o)`.
fn residual_and_gradient(p: &Params, r: &Reduced, horizontal: f64) -> (f64, Params) {
    let t = &r.tilt;
    let (dx, dy) = (r.m[0] - p[0], r.m[1] - p[1]);
    let b = [p[2] * dx + p[3] * dy, p[3] * dx + p[4] * dy];
    let l = level_xy_of(b, t, p[5]);
    let norm = (l[0] * l[0] + l[1] * l[1]).sqrt();
    if !(norm > 0.0) {
        return (norm - horizontal, Params::zeros());
    }
    let (ux, uy) = (l[0] / norm, l[1] / norm);
    // d|l|/db_x, d|l|/db_y and d|l|/dV.
    let cos_both = t.cos_roll * t.cos_pitch;
    let g_bx = ux / t.cos_pitch - uy * t.sin_roll * t.sin_pitch / cos_both;
    let g_by = uy / t.cos_roll;
    let g_v = ux * t.sin_pitch / t.cos_pitch - uy * t.sin_roll / cos_both;
    let grad = Params::new(
        -(g_bx * p[2] + g_by * p[3]),
        -(g_bx * p[3] + g_by * p[4]),
        g_bx * dx,
        g_bx * dy + g_by * dx,
        g_by * dy,
        g_v,
    );
    (norm - horizontal, grad)
}

/// Algebraic ellipse through the (x, y) readings: offset and the symmetric S mapping it onto a
/// circle of radius `horizontal` (None: the ellipse's mean radius, returned as the second value).
fn ellipse_start(pts: &[Reduced], horizontal: Option<f64>) -> Option<(Params, f64)> {
    let n = pts.len() as f64;
    let cx = pts.iter().map(|p| p.m[0]).sum::<f64>() / n;
    let cy = pts.iter().map(|p| p.m[1]).sum::<f64>() / n;
    let sc = pts
        .iter()
        .map(|p| ((p.m[0] - cx).powi(2) + (p.m[1] - cy).powi(2)).sqrt())
        .sum::<f64>()
        / n;
    if !(sc > 0.0) || !sc.is_finite() {
        return None;
    }
    // a x^2 + b xy + c y^2 + d x + e y = 1 on centred, scaled coordinates.
    let mut ata = SMatrix::<f64, 5, 5>::zeros();
    let mut atb = SVector::<f64, 5>::zeros();
    for p in pts {
        let (x, y) = ((p.m[0] - cx) / sc, (p.m[1] - cy) / sc);
        let row = SVector::<f64, 5>::new(x * x, x * y, y * y, x, y);
        ata += row * row.transpose();
        atb += row;
    }
    let k = ata.cholesky()?.solve(&atb);
    let q = Matrix2::new(k[0], k[1] / 2.0, k[1] / 2.0, k[2]);
    let c = q.try_inverse()? * nalgebra::Vector2::new(k[3], k[4]) * -0.5;
    let level = 1.0 + (c.transpose() * q * c)[0];
    let qn = q / level;
    let eig = qn.symmetric_eigen();
    if !(eig.eigenvalues.iter().all(|e| *e > 0.0)) {
        return None;
    }
    // S0 = sqrt(qn) maps the ellipse (scaled coordinates) onto the unit circle.
    let sqrt = eig.eigenvectors
        * Matrix2::from_diagonal(&eig.eigenvalues.map(f64::sqrt))
        * eig.eigenvectors.transpose();
    let s0 = sqrt / sc;
    let mean_radius = 1.0 / s0.determinant().sqrt();
    let h = horizontal.unwrap_or(mean_radius);
    let s = s0 * h;
    let p = Params::new(
        cx + c[0] * sc,
        cy + c[1] * sc,
        s[(0, 0)],
        s[(0, 1)],
        s[(1, 1)],
        0.0,
    );
    Some((p, h))
}

/// The normal equations (J^T J, J^T r) of the readings at `p`; with V held (`fit_vertical`
/// false) its row and column are zero.
fn normal_equations(
    pts: &[Reduced],
    p: &Params,
    horizontal: f64,
    fit_vertical: bool,
) -> (SMatrix<f64, 6, 6>, Params) {
    let mut jtj = SMatrix::<f64, 6, 6>::zeros();
    let mut jtr = Params::zeros();
    for r in pts {
        let (f0, mut row) = residual_and_gradient(p, r, horizontal);
        if !fit_vertical {
            row[5] = 0.0;
        }
        // Symmetric rank-1 update, upper triangle (mirrored below).
        for c in 0..6 {
            for k in 0..=c {
                jtj[(k, c)] += row[k] * row[c];
            }
        }
        jtr += row * f0;
    }
    for c in 0..6 {
        for k in 0..c {
            jtj[(c, k)] = jtj[(k, c)];
        }
    }
    (jtj, jtr)
}

/// Gauss-Newton on (o, S, V) with V held when `fit_vertical` is false; returns the parameters and
/// the normal matrix of the last step (analytic Jacobian, [`residual_and_gradient`]), 6x6 or,
/// with V held, 5x5.
fn gauss_newton(
    pts: &[Reduced],
    start: Params,
    horizontal: f64,
    fit_vertical: bool,
) -> (Params, DMatrix<f64>) {
    let np = if fit_vertical { 6 } else { 5 };
    let mut p = start;
    let mut jtj = SMatrix::<f64, 6, 6>::zeros();
    for _ in 0..MAX_ITERATIONS {
        let jtr;
        (jtj, jtr) = normal_equations(pts, &p, horizontal, fit_vertical);
        // A whisper of damping keeps a direction the readings do not move (V on level ground)
        // from making the step singular; it then stays where it started. (A held V has a zero
        // row: its step is exactly 0.)
        let mut damped = jtj;
        let scale = damped.diagonal().amax().max(f64::MIN_POSITIVE);
        for j in 0..6 {
            damped[(j, j)] += DAMPING * scale;
        }
        let Some(step) = damped.cholesky().map(|c| c.solve(&jtr)) else {
            break;
        };
        p -= step;
        if step.amax() <= STEP_TOL_FRACTION * horizontal {
            break;
        }
    }
    (p, DMatrix::from_fn(np, np, |i, j| jtj[(i, j)]))
}

fn rms(r: &[f64]) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    (r.iter().map(|x| x * x).sum::<f64>() / r.len() as f64).sqrt()
}

/// The element at index `len / 2` of the sorted values (0 when empty), found in linear time.
fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, f64::total_cmp).1
}

/// The 95th percentile (None when empty), found in linear time.
fn p95(mut v: Vec<f64>) -> Option<f64> {
    let k = ((v.len() as f64 * 0.95) as usize).min(v.len().checked_sub(1)?);
    Some(*v.select_nth_unstable_by(k, f64::total_cmp).1)
}

fn sectors(headings_deg: impl Iterator<Item = f64>) -> usize {
    let mut seen = [false; YAW_SECTORS];
    for h in headings_deg {
        let k = (wrap360(h) / (360.0 / YAW_SECTORS as f64)) as usize;
        seen[k.min(YAW_SECTORS - 1)] = true;
    }
    seen.iter().filter(|s| **s).count()
}

/// The tilts seen (95th percentile and largest, deg) and the mean bank of the turns (deg, from the
/// pitch rate against the yaw rate while turning; `None` without turns).
/// The 95th percentile of the usable points' tilt from level, deg (0 with none): the
/// [`PlanarFit::tilt_p95_deg`] that [`fit`] reports of the same points (an order statistic, so
/// the same in any order), known before fitting.
pub fn tilt_p95_deg(points: impl Iterator<Item = PlanarPoint>) -> f64 {
    p95(points
        .filter(|p| p.usable())
        .map(|p| p.tilt_deg())
        .collect())
    .unwrap_or(0.0)
}

/// Whether [`tilt_p95_deg`] of `points` is beyond `limit_deg`, told by counting the usable
/// points within the limit by their tilt's cosine (no arc cosine per point): the percentile is
/// beyond it when fewer than its rank are within. `None` when points within 1e-9 of the limit's
/// cosine could decide (rounding then matters: ask [`tilt_p95_deg`]).
pub fn tilt_p95_beyond(points: impl Iterator<Item = PlanarPoint>, limit_deg: f64) -> Option<bool> {
    let limit = limit_deg.to_radians().cos();
    let (mut n, mut surely_within, mut maybe_within) = (0usize, 0usize, 0usize);
    for p in points.filter(|p| p.usable()) {
        let f = p.gravity_force();
        let c = (-f[2] / crate::types::norm(&f)).clamp(-1.0, 1.0);
        n += 1;
        surely_within += usize::from(c > limit + 1e-9);
        maybe_within += usize::from(c >= limit - 1e-9);
    }
    // The percentile's rank, as [`p95`] takes it (none without points: a tilt of 0).
    let Some(last) = n.checked_sub(1) else {
        return Some(false);
    };
    let rank = ((n as f64 * 0.95) as usize).min(last) + 1;
    if maybe_within < rank {
        Some(true)
    } else if surely_within >= rank {
        Some(false)
    } else {
        None
    }
}

fn tilt_and_bank(usable: &[&PlanarPoint]) -> (f64, f64, Option<f64>) {
    let tilts: Vec<f64> = usable.iter().map(|p| p.tilt_deg()).collect();
    let tilt_p95_deg = p95(tilts.clone()).unwrap_or(0.0);
    let tilt_max_deg = tilts.iter().copied().fold(0.0, f64::max);
    let rates: Vec<Vec3> = usable
        .iter()
        .filter_map(|p| p.gyro_rad_s)
        .filter(crate::types::is_finite3)
        .collect();
    // The pitch-rate bias from the straight stretches (median), so it does not read as a bank.
    let straight: Vec<f64> = rates
        .iter()
        .filter(|w| w[2].abs() < 0.5 * MIN_TURN_RATE_RAD_S)
        .map(|w| w[1])
        .collect();
    let pitch_bias = if straight.is_empty() {
        0.0
    } else {
        median(straight)
    };
    let (mut pitch_rate, mut yaw_rate) = (0.0, 0.0);
    for w in rates.iter().filter(|w| w[2].abs() >= MIN_TURN_RATE_RAD_S) {
        pitch_rate += w[1] - pitch_bias;
        yaw_rate += w[2].abs();
    }
    let turn_bank_deg = (yaw_rate > 0.0).then(|| pitch_rate.atan2(yaw_rate).to_degrees());
    (tilt_p95_deg, tilt_max_deg, turn_bank_deg)
}

/// The heading sectors the logged attitude visits over `points`, when at least
/// [`PlanarSettings::min_reference_points`] of them carry its heading. The fitted headings can be
/// spread by the fit itself (a mirror, a degenerate ellipse): where the logged attitude gives the
/// true heading all along, the calibrated headings must have turned through as many sectors. (A
/// course over ground is only taken on straight stretches, so it visits fewer and is not used.)
fn attitude_sectors(points: &[&PlanarPoint], settings: &PlanarSettings) -> Option<usize> {
    let by_attitude = || {
        points
            .iter()
            .filter_map(|p| p.reference)
            .filter(|r| r.1 == ReferenceKind::Attitude && r.0.is_finite())
            .map(|r| r.0)
    };
    (by_attitude().count() >= settings.min_reference_points).then(|| sectors(by_attitude()))
}

/// Fit the horizontal calibration, then the deviation curve against the references: the level
/// readings ([`level_points`]), a first fit from the ellipse, its outliers left out
/// ([`without_outliers`]), the fit again on the rest ([`solve`]), the headings' spread and the
/// soft iron checked ([`check_shape`]), and the deviation curve ([`add_deviation`]).
pub fn fit(
    points: &[PlanarPoint],
    earth: Option<&PlanarEarth>,
    settings: &PlanarSettings,
) -> Result<PlanarFit, PlanarFailure> {
    let usable: Vec<&PlanarPoint> = points.iter().filter(|p| p.usable()).collect();
    let level = level_points(&usable, settings)?;
    let too_tilted = usable.len() - level.len();
    let (tilt_p95_deg, tilt_max_deg, turn_bank_deg) = tilt_and_bank(&usable);
    let kept: Vec<Reduced> = level.iter().map(|p| reduce(p)).collect();
    let (mut start, horizontal) =
        ellipse_start(&kept, earth.map(|e| e.horizontal)).ok_or(PlanarFailure::NotAnEllipse)?;
    start[5] = earth.map_or(0.0, |e| e.vertical);
    let (first, _) = gauss_newton(&kept, start, horizontal, true);
    let (level, kept, outliers_rejected) =
        without_outliers(level, kept, &first, horizontal, settings)?;
    let s = solve(&kept, first, horizontal, earth, settings);
    let mut fit = PlanarFit {
        offset_xy: [s.p[0], s.p[1]],
        offset_sigma_xy: [s.cov[(0, 0)].max(0.0).sqrt(), s.cov[(1, 1)].max(0.0).sqrt()],
        soft_iron_xy: [[s.p[2], s.p[3]], [s.p[3], s.p[4]]],
        vertical: s.p[5],
        vertical_sigma: s.vertical_sigma,
        horizontal,
        rms_residual: s.rms_residual,
        points: kept.len(),
        outliers_rejected,
        too_tilted,
        tilt_p95_deg,
        tilt_max_deg,
        turn_bank_deg,
        yaw_sectors: 0,
        declination_deg: earth.map(|e| e.declination_deg),
        deviation: None,
        deviation_skipped: None,
        undetermined: s.undetermined,
    };
    let referenced: Vec<&PlanarPoint> = level
        .iter()
        .copied()
        .filter(|p| p.reference.is_some_and(|r| r.0.is_finite()))
        .collect();
    check_shape(&mut fit, &level, &referenced, settings)?;
    add_deviation(&mut fit, &referenced, settings);
    Ok(fit)
}

/// Fewest level readings a fit needs: [`PlanarSettings::min_points`], at least 7.
fn min_points(settings: &PlanarSettings) -> usize {
    settings.min_points.max(7)
}

/// The readings level enough to fit (within [`PlanarSettings::max_tilt_deg`]), or why there are
/// too few of them, or why no fit can pass: when the logged attitude's headings already visit
/// too few sectors, no calibration can claim more ([`attitude_sectors`]), and the fit is not run.
fn level_points<'a>(
    usable: &[&'a PlanarPoint],
    settings: &PlanarSettings,
) -> Result<Vec<&'a PlanarPoint>, PlanarFailure> {
    let level: Vec<&PlanarPoint> = usable
        .iter()
        .copied()
        .filter(|p| p.within_tilt(settings.max_tilt_deg))
        .collect();
    let need = min_points(settings);
    if level.len() < need {
        return Err(PlanarFailure::NotEnoughPoints {
            have: level.len(),
            need,
        });
    }
    if let Some(sectors) = attitude_sectors(&level, settings) {
        if sectors < settings.min_yaw_sectors {
            return Err(PlanarFailure::NarrowYaw {
                sectors,
                need: settings.min_yaw_sectors,
            });
        }
    }
    Ok(level)
}

/// A reading reduced to the horizontal raw field and the tilt.
fn reduce(p: &PlanarPoint) -> Reduced {
    let (roll, pitch) = p.roll_pitch_rad();
    Reduced {
        m: [p.mag[0], p.mag[1]],
        tilt: Tilt::of(roll, pitch),
    }
}

/// One pass of outlier rejection on the first fit's residuals (beyond
/// [`PlanarSettings::outlier_sigmas`] robust sigmas): the readings kept, reduced and as given,
/// and how many were left out; an error when too few are left.
fn without_outliers<'a>(
    level: Vec<&'a PlanarPoint>,
    kept: Vec<Reduced>,
    first: &Params,
    horizontal: f64,
    settings: &PlanarSettings,
) -> Result<(Vec<&'a PlanarPoint>, Vec<Reduced>, usize), PlanarFailure> {
    let res: Vec<f64> = kept
        .iter()
        .map(|r| residual(first, r, horizontal))
        .collect();
    let sigma = MAD_TO_SIGMA * median(res.iter().map(|r| r.abs()).collect());
    let cut = settings.outlier_sigmas * sigma.max(1e-12 * horizontal);
    let before = kept.len();
    let mut keep_idx = Vec::with_capacity(before);
    for (i, r) in res.iter().enumerate() {
        if r.abs() <= cut {
            keep_idx.push(i);
        }
    }
    let level: Vec<&PlanarPoint> = keep_idx.iter().map(|&i| level[i]).collect();
    let kept: Vec<Reduced> = keep_idx.iter().map(|&i| kept[i]).collect();
    let outliers_rejected = before - kept.len();
    let need = min_points(settings);
    if kept.len() < need {
        return Err(PlanarFailure::NotEnoughPoints {
            have: kept.len(),
            need,
        });
    }
    Ok((level, kept, outliers_rejected))
}

/// The fit on the kept readings: its parameters, their covariance, the RMS residual, the
/// vertical field's sigma (`None` when held) and what it leaves undetermined.
struct Solved {
    p: Params,
    cov: DMatrix<f64>,
    rms_residual: f64,
    vertical_sigma: Option<f64>,
    undetermined: Vec<Undetermined>,
}

/// The fit again from `first` on the kept readings; when the vertical field comes out less
/// certain than [`PlanarSettings::max_vertical_sigma_fraction`] of the horizontal, it is held at
/// the earth's (or 0) and the fit made again without it.
fn solve(
    kept: &[Reduced],
    first: Params,
    horizontal: f64,
    earth: Option<&PlanarEarth>,
    settings: &PlanarSettings,
) -> Solved {
    let (mut p, mut jtj) = gauss_newton(kept, first, horizontal, true);
    let (mut s2, mut rms_residual) = residual_variance(kept, &p, horizontal, 6);
    let mut cov = covariance(&jtj, s2);
    let mut vertical_sigma = Some(cov[(5, 5)].max(0.0).sqrt());
    let mut undetermined = vec![Undetermined::OffsetZ, Undetermined::SoftIronZ];
    if !vertical_sigma.is_some_and(|s| s <= settings.max_vertical_sigma_fraction * horizontal) {
        let mut held = p;
        held[5] = earth.map_or(0.0, |e| e.vertical);
        (p, jtj) = gauss_newton(kept, held, horizontal, false);
        (s2, rms_residual) = residual_variance(kept, &p, horizontal, 5);
        cov = covariance(&jtj, s2);
        vertical_sigma = None;
        undetermined.push(Undetermined::FieldVertical);
    }
    Solved {
        p,
        cov,
        rms_residual,
        vertical_sigma,
        undetermined,
    }
}

/// The residuals' variance with `np` parameters fitted, and their RMS.
fn residual_variance(kept: &[Reduced], p: &Params, horizontal: f64, np: usize) -> (f64, f64) {
    let r: Vec<f64> = kept.iter().map(|r| residual(p, r, horizontal)).collect();
    let s2 = r.iter().map(|x| x * x).sum::<f64>() / (r.len().saturating_sub(np)).max(1) as f64;
    (s2, rms(&r))
}

/// The parameters' covariance from the normal matrix and the residual variance; infinite where
/// the matrix is singular.
fn covariance(jtj: &DMatrix<f64>, s2: f64) -> DMatrix<f64> {
    jtj.clone()
        .try_inverse()
        .map(|inv| inv * s2)
        .unwrap_or_else(|| DMatrix::from_element(jtj.nrows(), jtj.ncols(), f64::INFINITY))
}

/// The fit's heading sectors (the calibrated headings', at most the logged attitude's) into
/// `fit.yaw_sectors`, and the checks on the shape: enough sectors, and a soft iron within
/// [`SOFT_IRON_EIGEN_BOUNDS`].
fn check_shape(
    fit: &mut PlanarFit,
    level: &[&PlanarPoint],
    referenced: &[&PlanarPoint],
    settings: &PlanarSettings,
) -> Result<(), PlanarFailure> {
    fit.yaw_sectors = sectors(level.iter().map(|p| fit.compass_heading_deg(p)));
    if let Some(by_attitude) = attitude_sectors(referenced, settings) {
        fit.yaw_sectors = fit.yaw_sectors.min(by_attitude);
    }
    if fit.yaw_sectors < settings.min_yaw_sectors {
        return Err(PlanarFailure::NarrowYaw {
            sectors: fit.yaw_sectors,
            need: settings.min_yaw_sectors,
        });
    }
    let eigenvalues = normalised_eigenvalues(&fit.soft_iron_xy);
    if !eigenvalues
        .iter()
        .all(|e| (SOFT_IRON_EIGEN_BOUNDS.0..=SOFT_IRON_EIGEN_BOUNDS.1).contains(e))
    {
        return Err(PlanarFailure::SoftIron { eigenvalues });
    }
    Ok(())
}

/// The deviation curve against the references ([`deviation`]) when there are enough of them,
/// else why not; without one, the heading deviation is named undetermined.
fn add_deviation(fit: &mut PlanarFit, referenced: &[&PlanarPoint], settings: &PlanarSettings) {
    if referenced.len() >= settings.min_reference_points {
        match deviation(fit, referenced, settings) {
            Ok(d) => fit.deviation = Some(d),
            Err(why) => fit.deviation_skipped = Some(why),
        }
    } else if !referenced.is_empty() {
        fit.deviation_skipped = Some(format!(
            "{} readings with a heading reference, need {}",
            referenced.len(),
            settings.min_reference_points
        ));
    }
    if fit.deviation.is_none() {
        fit.undetermined.push(Undetermined::HeadingDeviation);
    }
}

/// Least squares of the deviation curve to reference minus compass heading (one pass of outlier
/// rejection).
fn deviation(
    fit: &PlanarFit,
    referenced: &[&PlanarPoint],
    settings: &PlanarSettings,
) -> Result<Deviation, String> {
    let decl = fit.declination_deg.unwrap_or(0.0);
    // (compass heading, reference minus compass), deg.
    let data: Vec<(f64, f64)> = referenced
        .iter()
        .filter_map(|p| {
            let h = fit.compass_heading_deg(p);
            let (r, _) = p.reference?;
            Some((h, angle_diff_deg(r - decl, h)))
        })
        .collect();
    let source = referenced
        .iter()
        .filter_map(|p| p.reference.map(|r| r.1))
        .next()
        .unwrap_or(ReferenceKind::Attitude);
    let sectors_seen = sectors(data.iter().map(|d| d.0));
    if sectors_seen < settings.min_reference_sectors {
        return Err(format!(
            "the referenced readings visit {sectors_seen} of {YAW_SECTORS} heading sectors, need {}",
            settings.min_reference_sectors
        ));
    }
    let row = |h: f64| {
        let h = h.to_radians();
        SVector::<f64, 5>::new(1.0, h.sin(), h.cos(), (2.0 * h).sin(), (2.0 * h).cos())
    };
    let solve = |data: &[(f64, f64)]| {
        let mut ata = SMatrix::<f64, 5, 5>::zeros();
        let mut atb = SVector::<f64, 5>::zeros();
        for &(h, d) in data {
            let r = row(h);
            ata += r * r.transpose();
            atb += r * d;
        }
        let k = ata.cholesky().map(|c| c.solve(&atb))?;
        let res: Vec<f64> = data.iter().map(|&(h, d)| d - row(h).dot(&k)).collect();
        Some((k, ata, res))
    };
    let (k, _, res) = solve(&data).ok_or("the deviation's normal equations are singular")?;
    let _ = k;
    let sigma = MAD_TO_SIGMA * median(res.iter().map(|r| r.abs()).collect());
    let cut = settings.outlier_sigmas * sigma.max(1e-9);
    let kept: Vec<(f64, f64)> = data
        .iter()
        .zip(&res)
        .filter(|(_, r)| r.abs() <= cut)
        .map(|(d, _)| *d)
        .collect();
    if kept.len() < settings.min_reference_points {
        return Err(format!(
            "{} referenced readings after outliers, need {}",
            kept.len(),
            settings.min_reference_points
        ));
    }
    let (k, ata, res) = solve(&kept).ok_or("the deviation's normal equations are singular")?;
    let s2 = res.iter().map(|x| x * x).sum::<f64>() / (kept.len().saturating_sub(5)).max(1) as f64;
    let inv = ata
        .try_inverse()
        .unwrap_or_else(|| SMatrix::from_element(f64::INFINITY));
    Ok(Deviation {
        coefficients_deg: [k[0], k[1], k[2], k[3], k[4]],
        sigma_deg: std::array::from_fn(|j| (inv[(j, j)] * s2).max(0.0).sqrt()),
        rms_deg: rms(&res),
        max_deg: res.iter().fold(0.0, |m, r| m.max(r.abs())),
        rms_before_deg: rms(&kept.iter().map(|d| d.1).collect::<Vec<_>>()),
        points: kept.len(),
        outliers_rejected: data.len() - kept.len(),
        source,
    })
}

/// A ground track from GNSS fixes: speed and course over ground at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Track {
    pub t_s: f64,
    pub speed_mps: f64,
    /// Course over ground, deg clockwise from true north.
    pub course_deg: f64,
}

/// Ground tracks from fixes (time, position): each from a fix to the first at least
/// [`COURSE_BASELINE_S`] later, placed at the middle time. Non-finite fixes are skipped.
pub(crate) fn ground_tracks(fixes: &[(f64, GeoPoint)]) -> Vec<Track> {
    let ok: Vec<&(f64, GeoPoint)> = fixes
        .iter()
        .filter(|(t, p)| t.is_finite() && p.lat_deg.is_finite() && p.lon_deg.is_finite())
        .collect();
    let mut out = Vec::new();
    let mut j = 0;
    for i in 0..ok.len() {
        let (t0, a) = ok[i];
        j = j.max(i + 1);
        while j < ok.len() && ok[j].0 < t0 + COURSE_BASELINE_S {
            j += 1;
        }
        let Some(&&(t1, b)) = ok.get(j) else {
            break;
        };
        let north = (b.lat_deg - a.lat_deg).to_radians() * EARTH_RADIUS_M;
        let east =
            (b.lon_deg - a.lon_deg).to_radians() * EARTH_RADIUS_M * a.lat_deg.to_radians().cos();
        let dt = t1 - t0;
        if !(dt > 0.0) {
            continue;
        }
        out.push(Track {
            t_s: 0.5 * (t0 + t1),
            speed_mps: north.hypot(east) / dt,
            course_deg: wrap360(east.atan2(north).to_degrees()),
        });
    }
    out
}

/// The track nearest in time to `t_s`, within [`MAX_TRACK_AGE_S`].
fn track_at(tracks: &[Track], t_s: f64) -> Option<&Track> {
    let k = tracks.partition_point(|tr| tr.t_s < t_s);
    [k.checked_sub(1), Some(k)]
        .into_iter()
        .flatten()
        .filter_map(|i| tracks.get(i))
        .filter(|tr| (tr.t_s - t_s).abs() <= MAX_TRACK_AGE_S)
        .min_by(|a, b| (a.t_s - t_s).abs().total_cmp(&(b.t_s - t_s).abs()))
}

/// The fit's readings from samples: `body` turns a sample into body axes; the reference is the
/// attitude's yaw (`ref_q`) on the samples that have one when the log carries an attitude, else
/// the course over ground on straight stretches above [`MIN_COURSE_SPEED_MPS`] (one kind per run,
/// never mixed). Samples without magnetometer or accelerometer are skipped.
pub fn points_from_samples(
    samples: &[Sample],
    body: &dyn Fn(&Sample) -> Sample,
) -> Vec<PlanarPoint> {
    Readings::new(samples, body).all()
}

/// The fit's readings from samples ([`points_from_samples`]), made one at a time: what needs
/// them all only once (the tilt first, [`tilt_p95_deg`]) holds none of them.
pub struct Readings<'a> {
    samples: &'a [Sample],
    body: &'a dyn Fn(&Sample) -> Sample,
    tracks: Vec<Track>,
    has_attitude: bool,
}

impl<'a> Readings<'a> {
    /// The ground tracks of the samples' fixes, and whether they carry an attitude.
    pub fn new(samples: &'a [Sample], body: &'a dyn Fn(&Sample) -> Sample) -> Readings<'a> {
        let fixes: Vec<(f64, GeoPoint)> = samples
            .iter()
            .filter_map(|s| Some((s.t_s, s.position?)))
            .collect();
        Readings {
            samples,
            body,
            tracks: ground_tracks(&fixes),
            has_attitude: samples.iter().any(|s| s.ref_q.is_some()),
        }
    }

    /// Every point, in the samples' order.
    pub fn all(&self) -> Vec<PlanarPoint> {
        // Room for every sample, so the list is not copied as it grows.
        let mut out = Vec::with_capacity(self.samples.len());
        out.extend(self.points());
        out
    }

    /// The points, in the samples' order.
    pub fn points(&self) -> impl Iterator<Item = PlanarPoint> + '_ {
        self.samples.iter().filter_map(|raw| self.point(raw))
    }

    fn point(&self, raw: &Sample) -> Option<PlanarPoint> {
        let s = (self.body)(raw);
        let track = track_at(&self.tracks, s.t_s);
        let attitude = s
            .ref_q
            .and_then(crate::attitude::body_ned_of_ref_q)
            .map(|q| (crate::attitude::yaw_deg(&q), ReferenceKind::Attitude));
        let straight = s
            .gyro_rad_s
            .is_some_and(|w| w[2].abs() <= MAX_COURSE_YAW_RATE_RAD_S);
        let course = track
            .filter(|tr| !self.has_attitude && straight && tr.speed_mps >= MIN_COURSE_SPEED_MPS)
            .map(|tr| (tr.course_deg, ReferenceKind::CourseOverGround));
        Some(PlanarPoint {
            t_s: s.t_s,
            mag: s.mag_ut?,
            accel_mps2: s.accel_mps2?,
            gyro_rad_s: s.gyro_rad_s,
            ground_speed_mps: track.map(|tr| tr.speed_mps),
            reference: attitude.or(course),
        })
    }
}

/// The classic tilt-compensated heading of an uncalibrated compass (all three raw axes), deg.
pub fn raw_heading_deg(p: &PlanarPoint) -> f64 {
    let (roll, pitch) = p.roll_pitch_rad();
    crate::attitude::heading_deg(&p.mag, roll.to_degrees(), pitch.to_degrees())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Counting by the cosines decides as the percentile of the tilts does: for points tilted up
    /// to several limits, and when every point sits at the limit (then it leaves it to the
    /// percentile).
    #[test]
    fn tilt_counted_by_cosines_decides_as_the_percentile() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let point = |tilt_deg: f64, az: f64| {
            let (t, g) = (tilt_deg.to_radians(), 9.81);
            PlanarPoint {
                t_s: 0.0,
                mag: [20.0, 0.0, 40.0],
                accel_mps2: [g * t.sin() * az.cos(), g * t.sin() * az.sin(), -g * t.cos()],
                gyro_rad_s: None,
                ground_speed_mps: None,
                reference: None,
            }
        };
        for spread in [3.0f64, 10.0, 14.0, 15.0, 16.0, 20.0, 60.0] {
            let pts: Vec<PlanarPoint> = (0..400)
                .map(|_| {
                    point(
                        rng.random_range(0.0..spread),
                        rng.random_range(0.0..std::f64::consts::TAU),
                    )
                })
                .collect();
            let exact = tilt_p95_deg(pts.iter().copied()) > 15.0;
            assert_eq!(
                tilt_p95_beyond(pts.iter().copied(), 15.0),
                Some(exact),
                "{spread}"
            );
        }
        let at = vec![point(15.0, 1.0); 40];
        assert_eq!(tilt_p95_beyond(at.iter().copied(), 15.0), None);
        assert_eq!(tilt_p95_beyond(std::iter::empty(), 15.0), Some(false));
    }

    const H: f64 = 21.0;
    const V: f64 = 42.0;

    /// A compass on a vehicle turning through `turns` full circles with small tilts: raw =
    /// M^-1 R^T b + o, `M` soft iron, `o` hard iron (z included); references with a 1 deg
    /// mounting yaw. No xz/yz soft iron: seen through the tilt, it is what the 2-D model cannot
    /// hold (0.22 deg of heading at most with -0.02/0.04 at 5 deg of tilt).
    fn synth(n: usize, tilt_deg: f64, noise_ut: f64, seed: u64) -> Vec<PlanarPoint> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let m_inv = nalgebra::Matrix3::new(1.05, 0.03, 0.0, 0.03, 0.95, 0.0, 0.0, 0.0, 1.1);
        let o = nalgebra::Vector3::new(8.0, -5.0, 30.0);
        (0..n)
            .map(|i| {
                let yaw = i as f64 / n as f64 * 720.0;
                let roll = tilt_deg * (i as f64 * 0.013).sin();
                let pitch = tilt_deg * (i as f64 * 0.007 + 1.0).cos();
                let q = nalgebra::UnitQuaternion::from_euler_angles(
                    roll.to_radians(),
                    pitch.to_radians(),
                    yaw.to_radians(),
                );
                let b = q.inverse() * nalgebra::Vector3::new(H, 0.0, V);
                let g = q.inverse() * nalgebra::Vector3::new(0.0, 0.0, -9.81);
                let mut m = m_inv * b + o;
                for k in 0..3 {
                    m[k] += noise_ut * rng.random_range(-1.0..1.0);
                }
                PlanarPoint {
                    t_s: i as f64 * 0.01,
                    mag: [m[0], m[1], m[2]],
                    accel_mps2: [g[0], g[1], g[2]],
                    gyro_rad_s: None,
                    ground_speed_mps: None,
                    reference: Some((wrap360(yaw + 1.0), ReferenceKind::Attitude)),
                }
            })
            .collect()
    }

    fn max_heading_error(fit: &PlanarFit, pts: &[PlanarPoint]) -> f64 {
        pts.iter()
            .map(|p| angle_diff_deg(fit.heading_deg(p), p.reference.unwrap().0).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn the_tilt_limit_by_cosine_is_the_tilt_by_angle() {
        let pts = synth(20_000, 40.0, 0.5, 3);
        let mut inside = 0;
        for max in [0.0, 5.0, 12.5, 20.0, 39.0, 90.0, 179.0] {
            for p in &pts {
                let by_angle = p.tilt_deg() <= max;
                assert_eq!(p.within_tilt(max), by_angle, "{:?} at {max}", p.accel_mps2);
                inside += by_angle as usize;
            }
        }
        assert!(inside > 20_000 && inside < 7 * 20_000, "{inside}");
        let p = &pts[0];
        assert!(!p.within_tilt(-1.0) && !p.within_tilt(f64::NAN) && p.within_tilt(180.0));
    }

    #[test]
    fn the_analytic_gradient_matches_central_differences() {
        let r = Reduced {
            m: [31.0, -12.0],
            tilt: Tilt::of(0.2, -0.15),
        };
        let p = Params::new(8.0, -5.0, 1.05, 0.03, 0.95, 42.0);
        let (f, g) = residual_and_gradient(&p, &r, H);
        assert_eq!(f, residual(&p, &r, H));
        for j in 0..6 {
            let h = 1e-6 * p[j].abs().max(1.0);
            let (mut a, mut b) = (p, p);
            a[j] += h;
            b[j] -= h;
            let d = (residual(&a, &r, H) - residual(&b, &r, H)) / (2.0 * h);
            // Measured below 1e-8 (the differences' own error).
            assert!(
                (d - g[j]).abs() < 1e-6 * d.abs().max(1.0),
                "{j}: {d} {}",
                g[j]
            );
        }
    }

    #[test]
    fn recovers_heading_on_tilted_ground_without_the_z_offset() {
        let pts = synth(4000, 4.0, 0.0, 1);
        let earth = PlanarEarth {
            horizontal: H,
            vertical: V,
            declination_deg: 0.0,
        };
        let fit = fit(&pts, Some(&earth), &PlanarSettings::default()).unwrap();
        // Noise-free: the vertical field and heading to numerical precision; the z offset (30)
        // never enters.
        assert!(fit.vertical_sigma.is_some(), "{fit:?}");
        assert!(max_heading_error(&fit, &pts) < 0.01, "{fit:?}");
        assert!(fit.undetermined.contains(&Undetermined::OffsetZ));
        assert!(!fit.undetermined.contains(&Undetermined::HeadingDeviation));
        let d = fit.deviation.as_ref().unwrap();
        // The 1 deg mounting yaw is the constant deviation A.
        assert!((d.coefficients_deg[0] - 1.0).abs() < 0.05, "{d:?}");
        // Without the calibration the heading is far off.
        let raw = pts
            .iter()
            .map(|p| angle_diff_deg(raw_heading_deg(p), p.reference.unwrap().0).abs())
            .fold(0.0, f64::max);
        assert!(raw > 20.0, "{raw}");
    }

    #[test]
    fn level_readings_hold_the_vertical_and_without_references_name_the_deviation() {
        let mut pts = synth(2000, 0.0, 0.05, 2);
        for p in pts.iter_mut() {
            p.reference = None;
        }
        let fit = fit(&pts, None, &PlanarSettings::default()).unwrap();
        assert!(fit.undetermined.contains(&Undetermined::FieldVertical));
        assert!(fit.undetermined.contains(&Undetermined::HeadingDeviation));
        assert_eq!(fit.vertical, 0.0);
        assert!(fit.deviation.is_none());
        assert_eq!(fit.yaw_sectors, YAW_SECTORS);
    }

    #[test]
    fn refuses_few_points_narrow_yaw_and_survives_bad_values() {
        let pts = synth(100, 2.0, 0.05, 3);
        assert!(matches!(
            fit(&pts, None, &PlanarSettings::default()),
            Err(PlanarFailure::NotEnoughPoints { .. })
        ));
        // A quarter turn only.
        let pts: Vec<PlanarPoint> = synth(4000, 2.0, 0.05, 3)
            .into_iter()
            .filter(|p| p.reference.unwrap().0 < 80.0)
            .collect();
        assert!(matches!(
            fit(&pts, None, &PlanarSettings::default()),
            Err(PlanarFailure::NarrowYaw { .. }) | Err(PlanarFailure::NotAnEllipse)
        ));
        let mut pts = synth(1000, 2.0, 0.05, 4);
        pts[3].mag[0] = f64::NAN;
        pts[4].accel_mps2 = [0.0; 3];
        let f = fit(&pts, None, &PlanarSettings::default()).unwrap();
        assert!(f.points <= 998);
    }

    #[test]
    fn tracks_give_speed_and_course_and_the_turn_is_taken_out_of_the_tilt() {
        let start = GeoPoint {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_m: 0.0,
        };
        // 2 m/s towards the north-east, a fix every 0.1 s.
        let fixes: Vec<(f64, GeoPoint)> = (0..50)
            .map(|i| {
                let d = 0.2 * i as f64 / 2f64.sqrt();
                (
                    0.1 * i as f64,
                    GeoPoint {
                        lat_deg: start.lat_deg + (d / EARTH_RADIUS_M).to_degrees(),
                        lon_deg: start.lon_deg
                            + (d / (EARTH_RADIUS_M * 47f64.to_radians().cos())).to_degrees(),
                        alt_m: 0.0,
                    },
                )
            })
            .collect();
        let tr = ground_tracks(&fixes);
        assert!(!tr.is_empty());
        assert!(tr.iter().all(|t| (t.speed_mps - 2.0).abs() < 0.01));
        assert!(tr.iter().all(|t| (t.course_deg - 45.0).abs() < 0.1));
        // Turning right at 0.3 rad/s at 2 m/s: 0.6 m/s^2 to the right on top of gravity.
        let p = PlanarPoint {
            t_s: 0.0,
            mag: [20.0, 0.0, 40.0],
            accel_mps2: [0.0, 0.6, -9.81],
            gyro_rad_s: Some([0.0, 0.0, 0.3]),
            ground_speed_mps: Some(2.0),
            reference: None,
        };
        assert!(p.tilt_deg() < 1e-9);
    }
}
