//! Forward sensor model and scenario generator, plus writers of CSV and `.tlog` logs.
//!
//! The truth of every sensor is a calibration in the report's convention (`calibrated = M (raw - o)`),
//! so the simulated raw reading is `raw = M^-1 * true + o + noise` and a perfect fit recovers `M`, `o`.
//! Frames: body FRD, world NED, attitude body -> NED (ZYX Euler: yaw, pitch, roll). The accelerometer
//! reads specific force `R^T (a_ned - g_ned)`: (0, 0, -g) at rest and level.

use crate::error::Error;
use crate::model::{mat_to_rows, rows_to_mat, Calibration, ModelKind};
use crate::types::{Sample, Sensor, Vec3, STANDARD_GRAVITY_MPS2};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// True calibration of one sensor: `raw = matrix^-1 * true + offset + noise`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorTruth {
    /// Offset (bias / hard iron) in raw units.
    pub offset: [f64; 3],
    /// Row-major correction matrix (the `M` of `calibrated = M (raw - offset)`).
    pub matrix: [[f64; 3]; 3],
    /// Standard deviation of the white noise added to each raw axis, raw units.
    pub noise_sd: f64,
}

impl SensorTruth {
    /// A sensor with no error and no noise.
    pub fn ideal() -> Self {
        SensorTruth { offset: [0.0; 3], matrix: mat_to_rows(&Matrix3::identity()), noise_sd: 0.0 }
    }

    /// The raw reading (without noise) of a true vector: `matrix^-1 * v + offset`.
    pub fn forward(&self, v: &Vec3) -> Vec3 {
        let m = rows_to_mat(&self.matrix);
        let inv = m.try_inverse().unwrap_or_else(Matrix3::identity);
        let r = inv * Vector3::new(v[0], v[1], v[2]);
        [r[0] + self.offset[0], r[1] + self.offset[1], r[2] + self.offset[2]]
    }

    /// The smallest model that represents this truth exactly (diagonal -> diag6, symmetric -> sym9).
    pub fn model_kind(&self) -> ModelKind {
        let m = &self.matrix;
        let off = [m[0][1], m[0][2], m[1][0], m[1][2], m[2][0], m[2][1]];
        if off.iter().all(|x| *x == 0.0) {
            if m[0][0] == m[1][1] && m[1][1] == m[2][2] {
                ModelKind::Sphere
            } else {
                ModelKind::Diag6
            }
        } else if m[0][1] == m[1][0] && m[0][2] == m[2][0] && m[1][2] == m[2][1] {
            ModelKind::Sym9
        } else {
            ModelKind::Full12
        }
    }

    /// The true calibration as a [`Calibration`].
    pub fn calibration(&self) -> Calibration {
        Calibration { model: self.model_kind(), offset: self.offset, matrix: self.matrix }
    }

    fn validate(&self, key: &str) -> Result<(), Error> {
        let bad = |message: String| Err(Error::Config { key: key.to_string(), message });
        if !self.offset.iter().all(|x| x.is_finite()) {
            return bad("offset must be finite".into());
        }
        if !self.matrix.iter().flatten().all(|x| x.is_finite()) {
            return bad("matrix must be finite".into());
        }
        let det = rows_to_mat(&self.matrix).determinant();
        if det.abs() < 1e-9 {
            return bad(format!("matrix is singular (det {det})"));
        }
        if !(self.noise_sd.is_finite() && self.noise_sd >= 0.0) {
            return bad(format!("noise_sd must be >= 0, got {}", self.noise_sd));
        }
        Ok(())
    }
}

/// The environment: Earth field and gravity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct World {
    /// Earth magnetic field in NED, uT.
    pub field_ned_ut: [f64; 3],
    /// Gravity magnitude, m/s^2 (down).
    pub gravity_mps2: f64,
}

impl Default for World {
    /// 48 uT, inclination 60 deg, declination 0; standard gravity.
    fn default() -> Self {
        World { field_ned_ut: [24.0, 0.0, 41.57], gravity_mps2: STANDARD_GRAVITY_MPS2 }
    }
}

impl World {
    pub fn field_strength_ut(&self) -> f64 {
        crate::types::norm(&self.field_ned_ut)
    }
    /// Inclination (dip), degrees, positive down.
    pub fn inclination_deg(&self) -> f64 {
        let f = &self.field_ned_ut;
        f[2].atan2((f[0] * f[0] + f[1] * f[1]).sqrt()).to_degrees()
    }
    /// Declination, degrees, east positive.
    pub fn declination_deg(&self) -> f64 {
        self.field_ned_ut[1].atan2(self.field_ned_ut[0]).to_degrees()
    }
}

/// One static pose of a scenario (a pause on the turntable or in the hand).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseTruth {
    pub t_start: f64,
    pub t_end: f64,
    pub roll_deg: f64,
    pub pitch_deg: f64,
    /// Heading from true north (ZYX Euler, body FRD -> NED), [0, 360).
    pub yaw_deg: f64,
}

/// Everything a simulation is made from (dumped as `truth.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    pub accel: SensorTruth,
    pub mag: SensorTruth,
    pub gyro: SensorTruth,
    pub world: World,
    pub rate_hz: f64,
    /// Static poses; filled by [`simulate`] (random scenarios choose them from the seed).
    pub poses: Vec<PoseTruth>,
}

impl Truth {
    pub fn sensor(&self, s: Sensor) -> &SensorTruth {
        match s {
            Sensor::Accel => &self.accel,
            Sensor::Mag => &self.mag,
            Sensor::Gyro => &self.gyro,
        }
    }
}

/// The base trajectory of a scenario.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryKind {
    /// Seed 000's experiment: 32 static attitudes on a turntable, 1000 samples each, short slews.
    Turntable,
    /// A hand tumble: random static pauses over the sphere joined by smooth rotations, hand tremor.
    Tumble,
    /// A short flight: ground, take-off, hover with small tilts and full yaw turns, landing.
    Flight,
}

impl TrajectoryKind {
    pub fn name(self) -> &'static str {
        match self {
            TrajectoryKind::Turntable => "turntable",
            TrajectoryKind::Tumble => "tumble",
            TrajectoryKind::Flight => "flight",
        }
    }
    pub fn parse(s: &str) -> Option<TrajectoryKind> {
        match s {
            "turntable" => Some(TrajectoryKind::Turntable),
            "tumble" => Some(TrajectoryKind::Tumble),
            "flight" => Some(TrajectoryKind::Flight),
            _ => None,
        }
    }
}

const SCENARIO_NAMES: [&str; 3] = ["turntable", "tumble", "flight"];

/// A named simulation scenario: truth parameters plus the trajectory and its knobs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scenario {
    pub name: String,
    pub truth: Truth,
    pub kind: TrajectoryKind,
    /// Stop the simulation at this time (flight: the flight's total length). `None`: the trajectory's own end.
    pub duration_s: Option<f64>,
    /// Number of static pauses (tumble).
    pub pauses: usize,
    /// Range of a pause's length, s (tumble).
    pub pause_s: [f64; 2],
    /// Range of a slew's length between poses, s (turntable, tumble).
    pub slew_s: [f64; 2],
    /// Samples per static pose (turntable).
    pub samples_per_pose: usize,
    /// Hand tremor amplitude, degrees (tumble; 0 = none).
    pub tremor_deg: f64,
    /// Temperature at the start, deg C.
    pub temp_c: f64,
    /// Slow temperature drift reached asymptotically (time constant 120 s), deg C.
    pub temp_drift_c: f64,
    /// Explicit static attitudes `[roll, pitch, yaw]` deg, replacing the scenario's own (turntable, tumble).
    pub attitudes: Option<Vec<[f64; 3]>>,
}

fn g() -> f64 {
    STANDARD_GRAVITY_MPS2
}

/// Default (tumble and flight) sensor errors: sym9 matrices, biases, noise.
fn default_accel() -> SensorTruth {
    SensorTruth {
        offset: [0.08, -0.05, 0.12],
        matrix: [[1.006, 0.003, -0.002], [0.003, 0.993, 0.004], [-0.002, 0.004, 1.008]],
        noise_sd: 0.02,
    }
}

fn default_mag() -> SensorTruth {
    SensorTruth {
        offset: [12.0, -25.0, 40.0],
        matrix: [[1.03, 0.02, -0.015], [0.02, 0.97, 0.025], [-0.015, 0.025, 1.01]],
        noise_sd: 0.15,
    }
}

fn default_gyro() -> SensorTruth {
    SensorTruth { offset: [0.01, -0.02, 0.005], matrix: [[1.004, 0.0, 0.0], [0.0, 0.997, 0.0], [0.0, 0.0, 1.002]], noise_sd: 0.002 }
}

impl Scenario {
    /// The scenario names [`Scenario::named`] knows.
    pub fn names() -> &'static [&'static str] {
        &SCENARIO_NAMES
    }

    /// A built-in scenario by name.
    pub fn named(name: &str) -> Option<Scenario> {
        let kind = TrajectoryKind::parse(name)?;
        let mut truth = Truth {
            accel: default_accel(),
            mag: default_mag(),
            gyro: default_gyro(),
            world: World::default(),
            rate_hz: 100.0,
            poses: Vec::new(),
        };
        let mut sc = Scenario {
            name: name.to_string(),
            truth: truth.clone(),
            kind,
            duration_s: None,
            pauses: 30,
            pause_s: [2.0, 4.0],
            slew_s: [1.0, 2.0],
            samples_per_pose: 1000,
            tremor_deg: 0.05,
            temp_c: 25.0,
            temp_drift_c: 3.0,
            attitudes: None,
        };
        match kind {
            TrajectoryKind::Turntable => {
                // Seed 000, Tables I and II: a = S (V - O), S the scale factors, O the bias.
                truth.accel = SensorTruth {
                    offset: [0.016 * g(), 0.0017 * g(), 0.0013 * g()],
                    matrix: [[1.0036, 0.0, 0.0], [0.0, 1.0019, 0.0], [0.0, 0.0, 0.9992]],
                    noise_sd: 0.02,
                };
                // Gauss -> uT: x100.
                truth.mag = SensorTruth {
                    offset: [0.0007 * 100.0, 0.0139 * 100.0, -0.1121 * 100.0],
                    matrix: [[0.9647, 0.0, 0.0], [0.0, 0.9715, 0.0], [0.0, 0.0, 1.1232]],
                    noise_sd: 0.15,
                };
                sc.slew_s = [0.5, 1.0];
                sc.tremor_deg = 0.0;
                sc.pauses = 32;
            }
            TrajectoryKind::Tumble => {}
            TrajectoryKind::Flight => {
                sc.tremor_deg = 0.0;
                sc.duration_s = Some(80.0);
            }
        }
        sc.truth = truth;
        Some(sc)
    }
}

// ---------------------------------------------------------------------------------------------
// Scenario TOML

/// Partial override of a [`SensorTruth`] in a scenario file.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SensorOverride {
    offset: Option<[f64; 3]>,
    matrix: Option<[[f64; 3]; 3]>,
    noise_sd: Option<f64>,
}

impl SensorOverride {
    fn apply(&self, t: &mut SensorTruth) {
        if let Some(o) = self.offset {
            t.offset = o;
        }
        if let Some(m) = self.matrix {
            t.matrix = m;
        }
        if let Some(n) = self.noise_sd {
            t.noise_sd = n;
        }
    }
}

/// Partial override of the [`World`].
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct WorldOverride {
    field_ned_ut: Option<[f64; 3]>,
    gravity_mps2: Option<f64>,
}

/// A scenario file: `name` picks the base trajectory; everything else overrides its defaults.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioFile {
    name: String,
    rate_hz: Option<f64>,
    duration_s: Option<f64>,
    pauses: Option<usize>,
    pause_s: Option<[f64; 2]>,
    slew_s: Option<[f64; 2]>,
    samples_per_pose: Option<usize>,
    tremor_deg: Option<f64>,
    temp_c: Option<f64>,
    temp_drift_c: Option<f64>,
    attitudes: Option<Vec<[f64; 3]>>,
    accel: Option<SensorOverride>,
    mag: Option<SensorOverride>,
    gyro: Option<SensorOverride>,
    world: Option<WorldOverride>,
}

/// The key a toml/serde error message names (`unknown field `x``), if any.
fn key_in_message(msg: &str) -> Option<String> {
    let i = msg.find("unknown field `")? + "unknown field `".len();
    let rest = &msg[i..];
    let j = rest.find('`')?;
    Some(rest[..j].to_string())
}

impl Scenario {
    /// Parse a scenario file (see the module docs): `name = "tumble"` plus optional overrides
    /// `rate_hz`, `duration_s`, `pauses`, `pause_s = [min, max]`, `slew_s`, `samples_per_pose`,
    /// `tremor_deg`, `temp_c`, `temp_drift_c`, `attitudes = [[roll, pitch, yaw], ...]` and tables
    /// `[accel]`/`[mag]`/`[gyro]` (offset, matrix, noise_sd) and `[world]` (field_ned_ut, gravity_mps2).
    /// Unknown keys are an error naming the key.
    pub fn from_toml_str(s: &str) -> Result<Scenario, Error> {
        let f: ScenarioFile = toml::from_str(s).map_err(|e| {
            let message = e.message().to_string();
            let key = key_in_message(&message).unwrap_or_else(|| "scenario".to_string());
            Error::Config { key, message: e.to_string().trim().to_string() }
        })?;
        let mut sc = Scenario::named(&f.name).ok_or_else(|| Error::Config {
            key: "name".into(),
            message: format!("unknown scenario `{}`; expected one of {}", f.name, SCENARIO_NAMES.join(", ")),
        })?;
        if let Some(r) = f.rate_hz {
            sc.truth.rate_hz = r;
        }
        if f.duration_s.is_some() {
            sc.duration_s = f.duration_s;
        }
        if let Some(p) = f.pauses {
            sc.pauses = p;
        }
        if let Some(p) = f.pause_s {
            sc.pause_s = p;
        }
        if let Some(p) = f.slew_s {
            sc.slew_s = p;
        }
        if let Some(n) = f.samples_per_pose {
            sc.samples_per_pose = n;
        }
        if let Some(x) = f.tremor_deg {
            sc.tremor_deg = x;
        }
        if let Some(x) = f.temp_c {
            sc.temp_c = x;
        }
        if let Some(x) = f.temp_drift_c {
            sc.temp_drift_c = x;
        }
        if f.attitudes.is_some() {
            sc.attitudes = f.attitudes;
        }
        if let Some(o) = &f.accel {
            o.apply(&mut sc.truth.accel);
        }
        if let Some(o) = &f.mag {
            o.apply(&mut sc.truth.mag);
        }
        if let Some(o) = &f.gyro {
            o.apply(&mut sc.truth.gyro);
        }
        if let Some(w) = &f.world {
            if let Some(v) = w.field_ned_ut {
                sc.truth.world.field_ned_ut = v;
            }
            if let Some(v) = w.gravity_mps2 {
                sc.truth.world.gravity_mps2 = v;
            }
        }
        sc.validate()?;
        Ok(sc)
    }

    /// Check the parameters are usable.
    pub fn validate(&self) -> Result<(), Error> {
        let bad = |key: &str, message: String| Err(Error::Config { key: key.to_string(), message });
        self.truth.accel.validate("accel")?;
        self.truth.mag.validate("mag")?;
        self.truth.gyro.validate("gyro")?;
        let r = self.truth.rate_hz;
        if !(r.is_finite() && r > 0.0 && r <= 100_000.0) {
            return bad("rate_hz", format!("must be in (0, 100000], got {r}"));
        }
        if let Some(d) = self.duration_s {
            if !(d.is_finite() && d > 0.0 && d <= 86_400.0) {
                return bad("duration_s", format!("must be in (0, 86400], got {d}"));
            }
        }
        for (key, rg) in [("pause_s", self.pause_s), ("slew_s", self.slew_s)] {
            if !(rg[0].is_finite() && rg[1].is_finite() && rg[0] > 0.0 && rg[0] <= rg[1] && rg[1] <= 3600.0) {
                return bad(key, format!("must be [min, max] with 0 < min <= max <= 3600, got {rg:?}"));
            }
        }
        if self.kind == TrajectoryKind::Tumble && self.attitudes.is_none() && !(1..=10_000).contains(&self.pauses) {
            return bad("pauses", format!("must be in 1..=10000, got {}", self.pauses));
        }
        if !(1..=10_000_000).contains(&self.samples_per_pose) {
            return bad("samples_per_pose", format!("must be in 1..=10000000, got {}", self.samples_per_pose));
        }
        if !(self.tremor_deg.is_finite() && (0.0..=10.0).contains(&self.tremor_deg)) {
            return bad("tremor_deg", format!("must be in [0, 10], got {}", self.tremor_deg));
        }
        if !self.temp_c.is_finite() || !self.temp_drift_c.is_finite() {
            return bad("temp_c", "must be finite".into());
        }
        let w = &self.truth.world;
        if !w.field_ned_ut.iter().all(|x| x.is_finite()) || w.field_strength_ut() <= 0.0 {
            return bad("world.field_ned_ut", format!("must be a finite non-zero vector, got {:?}", w.field_ned_ut));
        }
        if !(w.gravity_mps2.is_finite() && w.gravity_mps2 > 0.0) {
            return bad("world.gravity_mps2", format!("must be > 0, got {}", w.gravity_mps2));
        }
        if let Some(a) = &self.attitudes {
            if a.is_empty() {
                return bad("attitudes", "must not be empty".into());
            }
            if !a.iter().flatten().all(|x| x.is_finite()) {
                return bad("attitudes", "must be finite".into());
            }
        }
        Ok(())
    }
}
