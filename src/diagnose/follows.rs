//! What a residual the catalogue leaves unexplained follows: for each magnetometer channel, how
//! much of the final model's residual over the evidence units a least-squares line in time, the
//! motor driver, the reference heading (sine and cosine) or the position (east and north) takes
//! out, as a multiple correlation R. The strongest, when it is clear, names what the residual
//! could be: a field that is not uniform (it follows position), an attitude that is wrong (it
//! follows heading), something that changes with time, or a motor field beyond a linear term.

use super::channel::Ch;
use super::evidence::Evidence;
use super::layout::{residuals, tags, Ctx, Layout};
use nalgebra::{DMatrix, DVector, Vector3};
use serde::{Deserialize, Serialize};

/// A regressor set must explain at least this multiple correlation R to name the residual, 1...
pub const MIN_NAMING_R: f64 = 0.5;
/// ...and its regression F-test (neighbouring units are not independent, so a strict one) must
/// reach this p-value.
pub const MAX_NAMING_P: f64 = 1e-3;
/// Fewest residual components of a channel to correlate, count.
const MIN_COMPONENTS: usize = 8;
/// Positions within this many metres of each other everywhere do not vary, m.
const MIN_POSITION_SPREAD_M: f64 = 2.0;
/// Mean earth radius for east/north metres from latitude and longitude, m.
const EARTH_RADIUS_M: f64 = 6_371_000.0;

/// What a residual is compared with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Regressor {
    /// Time since the log's start.
    Time,
    /// The motor driver (throttle or current).
    Driver,
    /// The reference heading (its sine and cosine).
    Heading,
    /// The position, east and north of the first fix.
    Position,
}

impl Regressor {
    pub fn name(self) -> &'static str {
        match self {
            Regressor::Time => "time",
            Regressor::Driver => "throttle or current",
            Regressor::Heading => "heading",
            Regressor::Position => "position",
        }
    }
}

/// How far one channel's residual follows one regressor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Follows {
    pub channel: String,
    pub regressor: Regressor,
    /// Multiple correlation of the residual with the regressor set (intercept included), 0..1.
    pub r: f64,
    /// Residual components compared.
    pub n: usize,
    /// p-value of the regression's F-test (R^2 / k against (1 - R^2) / (n - k - 1)).
    pub p_value: f64,
}

/// What an unexplained residual could be, by what it follows most.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reading {
    /// It follows position: the field is not uniform where the vehicle moved (steel, buildings,
    /// cables near the ground or indoors).
    FieldNotUniform,
    /// It follows heading: the attitude the log gives (its heading) or the compass's mounting is
    /// wrong (or, without a logged position, a field that is not uniform where the vehicle
    /// turned: indoors the two look alike).
    AttitudeWrong,
    /// It follows time: a field or a sensor that changes over the log.
    ChangesWithTime,
    /// It follows the driver beyond a linear term: a motor field of another form.
    DriverBeyondLinear,
}

impl Reading {
    fn of(r: Regressor) -> Reading {
        match r {
            Regressor::Position => Reading::FieldNotUniform,
            Regressor::Heading => Reading::AttitudeWrong,
            Regressor::Time => Reading::ChangesWithTime,
            Regressor::Driver => Reading::DriverBeyondLinear,
        }
    }
}

impl std::fmt::Display for Reading {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Reading::FieldNotUniform => "a field that is not uniform where the vehicle moved",
            Reading::AttitudeWrong => {
                "an attitude (heading) or a compass mounting that is wrong, or, where the position is not logged, a field whose direction is not uniform where the vehicle turned"
            }
            Reading::ChangesWithTime => "a field or a sensor that changes over the log",
            Reading::DriverBeyondLinear => "a motor field that is not linear in the driver",
        })
    }
}

/// The residual's correlations, strongest first, and what they name.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct ResidualTrace {
    pub follows: Vec<Follows>,
    /// What the strongest correlation names (None when no R reaches [`MIN_NAMING_R`]).
    pub reading: Option<Reading>,
}

/// East and north metres of each unit from the first fix (None without a fix near its time).
fn unit_positions(ev: &Evidence) -> Vec<Option<[f64; 2]>> {
    let fixes: Vec<(f64, crate::types::GeoPoint)> = ev
        .body
        .iter()
        .filter_map(|s| s.position.map(|p| (s.t_s, p)))
        .filter(|(_, p)| p.lat_deg.is_finite() && p.lon_deg.is_finite())
        .collect();
    let Some((_, origin)) = fixes.first().copied() else {
        return vec![None; ev.units.len()];
    };
    let coslat = origin.lat_deg.to_radians().cos();
    ev.units
        .iter()
        .map(|u| {
            let t = u.t + ev.t_mean;
            let i = fixes.partition_point(|(ft, _)| *ft < t);
            let near = [i.checked_sub(1), Some(i)]
                .into_iter()
                .flatten()
                .filter_map(|k| fixes.get(k))
                .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))?;
            let p = near.1;
            Some([
                (p.lon_deg - origin.lon_deg).to_radians() * coslat * EARTH_RADIUS_M,
                (p.lat_deg - origin.lat_deg).to_radians() * EARTH_RADIUS_M,
            ])
        })
        .collect()
}

/// The reference heading of a unit, rad (body x axis clockwise from north).
fn unit_heading(u: &super::evidence::Unit) -> Option<f64> {
    let w = u.ref_w.or_else(|| u.mags.iter().find_map(|o| o.ref_w))?;
    let x = w * Vector3::x();
    Some(x.x.atan2(x.y))
}

/// Multiple correlation of `y` with the columns `x` (an intercept added).
fn multiple_r(y: &[f64], x: &[Vec<f64>]) -> Option<f64> {
    let n = y.len();
    let mut a = DMatrix::from_element(n, x.len() + 1, 1.0);
    for (j, col) in x.iter().enumerate() {
        for i in 0..n {
            a[(i, j + 1)] = col[i];
        }
    }
    let yv = DVector::from_column_slice(y);
    let mean = yv.mean();
    let ss_tot: f64 = yv.iter().map(|v| (v - mean).powi(2)).sum();
    if !(ss_tot > 0.0) {
        return None;
    }
    let beta = a.clone().svd(true, true).solve(&yv, 1e-10).ok()?;
    let ss_res = (&yv - &a * beta).norm_squared();
    Some((1.0 - ss_res / ss_tot).clamp(0.0, 1.0).sqrt())
}

/// p-value of a regression with `k` regressors (and an intercept) explaining R over `n` points.
fn regression_p(r: f64, k: usize, n: usize) -> f64 {
    let dof = n as f64 - k as f64 - 1.0;
    if !(dof > 0.0) || !(r < 1.0) {
        return if r >= 1.0 && dof > 0.0 { 0.0 } else { 1.0 };
    }
    let r2 = r * r;
    let f = (r2 / k as f64) / ((1.0 - r2) / dof);
    super::stats::f_sf(f, k as f64, dof)
}

/// A regressor's columns for the given units, None when it does not vary or is missing.
fn regressor_columns(
    ev: &Evidence,
    reg: Regressor,
    units: &[usize],
    pos: &[Option<[f64; 2]>],
) -> Option<Vec<Vec<f64>>> {
    let vary = |v: &[f64], min: f64| {
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), x| {
                (l.min(*x), h.max(*x))
            });
        hi - lo > min
    };
    match reg {
        Regressor::Time => {
            let t: Vec<f64> = units.iter().map(|&u| ev.units[u].t).collect();
            vary(&t, 0.0).then_some(vec![t])
        }
        Regressor::Driver => {
            let d: Vec<f64> = units.iter().map(|&u| ev.units[u].drv).collect();
            (ev.driver.is_some() && vary(&d, 0.0)).then_some(vec![d])
        }
        Regressor::Heading => {
            let h: Option<Vec<f64>> = units.iter().map(|&u| unit_heading(&ev.units[u])).collect();
            let h = h?;
            let (s, c): (Vec<f64>, Vec<f64>) = h.iter().map(|a| a.sin_cos()).unzip();
            (vary(&s, 0.1) || vary(&c, 0.1)).then_some(vec![s, c])
        }
        Regressor::Position => {
            let p: Option<Vec<[f64; 2]>> = units.iter().map(|&u| pos[u]).collect();
            let p = p?;
            let e: Vec<f64> = p.iter().map(|x| x[0]).collect();
            let n: Vec<f64> = p.iter().map(|x| x[1]).collect();
            (vary(&e, MIN_POSITION_SPREAD_M) || vary(&n, MIN_POSITION_SPREAD_M))
                .then_some(vec![e, n])
        }
    }
}

/// What the residual of the model (`lay`, `p`) over `units` follows, in the magnetometer channels.
pub(super) fn trace(
    ctx: &Ctx,
    ev: &Evidence,
    (lay, p): (&Layout, &DVector<f64>),
    units: &[usize],
) -> ResidualTrace {
    let tg = tags(ctx, lay, p, ev, units);
    let res = residuals(ctx, lay, ev, units, p.as_slice());
    let pos = unit_positions(ev);
    let mut follows = vec![];
    for ch in [Ch::MagNorm, Ch::VecMag, Ch::Dip] {
        for comp in 0..2 {
            let (us, y): (Vec<usize>, Vec<f64>) = tg
                .iter()
                .zip(&res)
                .filter(|((_, c, k), _)| *c == ch && *k == comp)
                .map(|((ui, _, _), (_, r))| (*ui, *r))
                .unzip();
            if y.len() < MIN_COMPONENTS {
                continue;
            }
            let channel = if ch == Ch::VecMag {
                format!("{} (component {})", ch.name(), comp + 1)
            } else {
                ch.name().to_string()
            };
            for reg in [
                Regressor::Position,
                Regressor::Heading,
                Regressor::Time,
                Regressor::Driver,
            ] {
                let Some(x) = regressor_columns(ev, reg, &us, &pos) else {
                    continue;
                };
                if let Some(r) = multiple_r(&y, &x) {
                    follows.push(Follows {
                        channel: channel.clone(),
                        regressor: reg,
                        r,
                        n: y.len(),
                        p_value: regression_p(r, x.len(), y.len()),
                    });
                }
            }
        }
    }
    follows.sort_by(|a, b| b.r.total_cmp(&a.r));
    let reading = follows
        .first()
        .filter(|f| f.r >= MIN_NAMING_R && f.p_value < MAX_NAMING_P)
        .map(|f| Reading::of(f.regressor));
    ResidualTrace { follows, reading }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_residual_along_a_regressor_is_followed_and_noise_is_not() {
        let x: Vec<f64> = (0..40).map(|i| i as f64).collect();
        let y: Vec<f64> = x.iter().map(|v| 2.0 * v + 1.0).collect();
        let r = multiple_r(&y, std::slice::from_ref(&x)).unwrap();
        assert!((r - 1.0).abs() < 1e-9, "{r}");
        // A residual that alternates in sign follows no line in x.
        let y: Vec<f64> = (0..40)
            .map(|i| if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let r = multiple_r(&y, &[x]).unwrap();
        // Measured: R 0.049.
        assert!(r < 0.15, "{r}");
        assert!(regression_p(r, 1, 40) > 0.5);
        assert!(regression_p(0.8, 2, 40) < MAX_NAMING_P);
    }
}
