//! Whether a fitted effect's size is determined: an effect is named only when the data pin down
//! how large it is, not merely that the fit improves. Otherwise the round says the effect might be
//! there and what data would decide it ([`Deciding`]).
//!
//! An effect's parameters come in groups that share a unit (the motor field's three axes, the
//! magnetometer's three temperature coefficients ...). A group's size is the length of its vector;
//! it is determined when that length is at least [`MIN_SIZE_SIGMAS`] times the largest 1-sigma
//! of its parameters (so every parameter's 3-sigma interval is narrower than the effect itself:
//! a component near zero is then a determined small component, and a large value with a larger
//! uncertainty, such as a 30 deg rotation +- 19 deg, is not determined). An effect is determined
//! when at least one of its groups is and every parameter lies inside its physical range
//! ([`super::plausible`]). A parameter that alone is under 3 sigma is exported as 0.

use super::layout::Layout;
use super::plausible::OutOfRange;
use super::Effect;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// A group's size must be at least this many times its largest parameter sigma, 1.
pub const MIN_SIZE_SIGMAS: f64 = 3.0;

/// One group of an effect's parameters (the same unit): its size and uncertainty.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroupSize {
    /// The parameters' names.
    pub params: Vec<String>,
    /// Their unit in the fit (`rad` for rotations, `1` for relative terms).
    pub unit: String,
    /// Length of the group's vector, in `unit`.
    pub size: f64,
    /// Largest 1-sigma of the group's parameters, in `unit`.
    pub sigma_max: f64,
}

impl GroupSize {
    /// Size in units of the largest sigma (infinite when the sigma is 0, NaN when unknown).
    pub fn sigmas(&self) -> f64 {
        self.size / self.sigma_max
    }
    pub fn determined(&self) -> bool {
        self.sigmas() >= MIN_SIZE_SIGMAS
    }
}

/// What data would decide an effect whose size is not determined.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Deciding {
    /// Throttle steps held at a still attitude (as ArduPilot's compassmot runs them), or the
    /// battery current logged.
    ThrottleStep,
    /// A longer warm-up: the temperature rising by several degrees while the vehicle rests.
    LongerWarmUp,
    /// Turns through 90 deg about each axis, so the field and gravity meet at other angles.
    TurnThrough90Deg,
    /// A full turn in heading with the reference attitude logged.
    FullHeadingTurn,
    /// A tumble that points the sensor in every direction.
    Tumble,
    /// Still periods spread over a longer log.
    LongerStillPeriods,
}

impl Deciding {
    /// The data that decides effect `e`.
    pub fn for_effect(e: Effect) -> Deciding {
        match e {
            Effect::MotorInterference => Deciding::ThrottleStep,
            Effect::TemperatureBias => Deciding::LongerWarmUp,
            Effect::MagAccelMisalignment => Deciding::TurnThrough90Deg,
            Effect::HeadingOffset => Deciding::FullHeadingTurn,
            Effect::CrossAxis | Effect::ScaleNonlinearity => Deciding::Tumble,
            Effect::GyroBiasDrift => Deciding::LongerStillPeriods,
        }
    }
}

impl std::fmt::Display for Deciding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Deciding::ThrottleStep => {
                "throttle steps held for a few seconds each at a still attitude (or the battery current logged)"
            }
            Deciding::LongerWarmUp => {
                "a longer warm-up (the temperature rising by several degrees while the vehicle rests)"
            }
            Deciding::TurnThrough90Deg => "turns through 90 deg about each axis",
            Deciding::FullHeadingTurn => "a full turn in heading with the attitude logged",
            Deciding::Tumble => "a tumble that points the vehicle in every direction",
            Deciding::LongerStillPeriods => "still periods spread over a longer log",
        })
    }
}

/// How well a fitted effect's size is determined.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Determination {
    pub groups: Vec<GroupSize>,
    /// Parameters outside their physical range (empty when all inside).
    #[serde(default)]
    pub out_of_range: Vec<OutOfRange>,
    /// Parameters that alone are under 3 sigma from zero (exported as 0).
    #[serde(default)]
    pub loose: Vec<String>,
}

impl Determination {
    /// Named only when some group is determined and every parameter is inside its range.
    pub fn determined(&self) -> bool {
        self.out_of_range.is_empty() && self.groups.iter().any(|g| g.determined())
    }

    /// The best-determined group's size in sigmas (NaN when there is none).
    pub fn best_sigmas(&self) -> f64 {
        self.groups
            .iter()
            .map(|g| g.sigmas())
            .filter(|s| !s.is_nan())
            .fold(f64::NAN, f64::max)
    }
}

impl std::fmt::Display for Determination {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let groups: Vec<String> = self
            .groups
            .iter()
            .map(|g| {
                let deg = g.unit == "rad";
                let k = if deg { 1f64.to_degrees() } else { 1.0 };
                let unit = match g.unit.as_str() {
                    "rad" => " deg",
                    "1" => "",
                    u => u,
                };
                let sep = if unit.is_empty() || deg { "" } else { " " };
                format!(
                    "{} size {}{sep}{unit} +- {} ({:.1} sigma)",
                    group_label(&g.params),
                    sig3(g.size * k),
                    sig3(g.sigma_max * k),
                    g.sigmas()
                )
            })
            .collect();
        f.write_str(&groups.join(", "))?;
        if !self.out_of_range.is_empty() {
            write!(
                f,
                "; out of range: {}",
                super::plausible::render(&self.out_of_range)
            )?;
        }
        Ok(())
    }
}

/// A number with three significant digits (plain between 0.01 and 1e5, else in e-notation).
fn sig3(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 || !a.is_finite() || (0.01..1e5).contains(&a) {
        let decimals = if a >= 100.0 || a == 0.0 || !a.is_finite() {
            1
        } else if a >= 1.0 {
            2
        } else {
            3
        };
        format!("{x:.decimals$}")
    } else {
        format!("{x:.2e}")
    }
}

/// A group's name: its one parameter's, or the names' common stem (`k` of `k_x`, `k_y`, `k_z`),
/// else the names themselves.
fn group_label(params: &[String]) -> String {
    let Some(first) = params.first() else {
        return String::new();
    };
    if params.len() == 1 {
        return first.clone();
    }
    let mut stem = first.as_str();
    while !params.iter().all(|p| p.starts_with(stem)) && !stem.is_empty() {
        stem = &stem[..stem.len() - 1];
    }
    let stem = stem.trim_end_matches('_');
    if stem.is_empty() {
        params.join(",")
    } else {
        stem.to_string()
    }
}

/// The groups of effect `e`'s parameters in `lay`: consecutive parameters with the same unit and
/// the same sensor prefix (`mag_`, `accel_`).
fn groups(lay: &Layout, e: Effect) -> Vec<Vec<usize>> {
    let Some(b) = lay.block(e) else {
        return vec![];
    };
    let key = |i: usize| {
        let (name, unit) = &lay.names[i];
        // Magnetometer and accelerometer parts of one effect are separate groups.
        let prefix = name.split('_').next().unwrap_or("");
        let sensor = if prefix == "mag" || prefix == "accel" {
            prefix
        } else {
            ""
        };
        (sensor.to_string(), unit.clone())
    };
    let mut out: Vec<Vec<usize>> = vec![];
    for i in b.start..b.start + b.len {
        match out.last_mut() {
            Some(g) if key(g[0]) == key(i) => g.push(i),
            _ => out.push(vec![i]),
        }
    }
    out
}

/// The determination of effect `e` in a fit with parameters `p` and covariance `cov` (None when
/// the normal matrix could not be inverted: nothing is determined), with the effect's
/// out-of-range records.
pub(super) fn determine(
    lay: &Layout,
    p: &DVector<f64>,
    cov: Option<&DMatrix<f64>>,
    e: Effect,
    out_of_range: Vec<OutOfRange>,
) -> Determination {
    let sigma = |i: usize| {
        cov.map(|c| c[(i, i)].max(0.0).sqrt())
            .unwrap_or(f64::INFINITY)
    };
    let mut loose = vec![];
    let groups = groups(lay, e)
        .into_iter()
        .map(|g| {
            for &i in &g {
                if !(p[i].abs() >= MIN_SIZE_SIGMAS * sigma(i)) {
                    loose.push(lay.names[i].0.clone());
                }
            }
            GroupSize {
                params: g.iter().map(|&i| lay.names[i].0.clone()).collect(),
                unit: lay.names[g[0]].1.clone(),
                size: g.iter().map(|&i| p[i] * p[i]).sum::<f64>().sqrt(),
                sigma_max: g.iter().map(|&i| sigma(i)).fold(0.0, f64::max),
            }
        })
        .collect();
    Determination {
        groups,
        out_of_range,
        loose,
    }
}

/// Covariance of a weighted least-squares fit: (J^T J)^-1 s^2, s^2 = ssr / (m - n), inflated by
/// (1 + rho) / (1 - rho) for residuals with lag-1 autocorrelation rho (as the F-test is deflated).
pub(super) fn covariance(jtj: &DMatrix<f64>, ssr: f64, m: usize, rho: f64) -> Option<DMatrix<f64>> {
    let dof = (m as f64 - jtj.nrows() as f64).max(1.0);
    let rho = rho.clamp(0.0, 0.95);
    let inflate = (1.0 + rho) / (1.0 - rho);
    jtj.clone().try_inverse().map(|c| c * (ssr / dof * inflate))
}
