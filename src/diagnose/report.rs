//! The `imucald.diagnosis/1` report: its types (the record of each round comes from
//! [`super::decision`]), its assembly from the finished selection rounds, the residual series of each
//! effect found (the data of `--plot`), the fitted effect parameters with uncertainties, and the
//! terminal table.

use super::channel::{Ch, ALL_CH, NCH};
use super::decision::{shown_unit, Decision, RoundReport};
use super::evidence::Driver;
use super::follows::ResidualTrace;
use super::layout::{decode, residuals, tags, Layout};
use super::rounds::{median_count, Split};
use super::run::{Run, Selection};
use super::{Effect, SCHEMA};
use crate::calib::model::ModelKind;
use nalgebra::{DVector, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// A fitted parameter with its 1-sigma uncertainty.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamEstimate {
    pub value: f64,
    pub sigma: f64,
    pub unit: String,
}

/// RMS of one residual channel on the held-out units, in its physical unit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelRms {
    pub unit: String,
    pub before: f64,
    pub after: f64,
    /// Noise expected from the within-unit scatter (median over units).
    pub noise: f64,
}

/// What evidence the diagnosis used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct EvidenceSummary {
    /// "static_segments" or "static_segments+moving_windows".
    pub unit: String,
    pub units: usize,
    pub static_units: usize,
    pub moving_windows: usize,
    /// Length of each moving window, s (0.25, or five reading intervals of a slower magnetometer).
    #[serde(default)]
    pub window_s: f64,
    pub poses: usize,
    pub held_out_units: usize,
    pub channels: Vec<String>,
    /// "throttle", "current" or none.
    pub driver: Option<String>,
    /// Whether the accelerometer calibration was refitted with the model (else held fixed).
    pub accel_fitted: bool,
}

/// The diagnosis (JSON contract `imucald.diagnosis/1`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiagnosisReport {
    pub schema: String,
    pub base_model: String,
    pub evidence: EvidenceSummary,
    /// Effects named, in the order they were added (empty when none).
    pub found: Vec<Effect>,
    pub rounds: Vec<RoundReport>,
    /// RMS of the held-out residuals of the base model, in units of the expected noise (all channels).
    pub rms_before: f64,
    /// The same with the effects found.
    pub rms_after: f64,
    pub rms_channels: BTreeMap<String, ChannelRms>,
    /// Per effect found: fitted parameters (all units) with uncertainties.
    pub effects: BTreeMap<String, BTreeMap<String, ParamEstimate>>,
    /// Per effect found: the residual of the channel it explains most, against its regressor, for the
    /// base model (before) and the final model (after), every unit (the data of `--plot`).
    #[serde(default)]
    pub residual_plots: Vec<ResidualSeries>,
    /// The earth field's magnitude the residuals are relative to, uT (0 without a magnetometer).
    #[serde(default)]
    pub field_ut: f64,
    /// The final model's magnetometer matrix (all units), raw to calibrated: what ArduPilot's
    /// motor compensation goes through.
    #[serde(default)]
    pub mag_matrix: Option<[[f64; 3]; 3]>,
    /// Per effect found: the held-out residual of the final model with the effect switched off and
    /// on (the shrink it brings).
    #[serde(default)]
    pub effect_shrink: BTreeMap<String, EffectShrink>,
    /// What the final model's residual follows (time, driver, heading, position).
    #[serde(default)]
    pub residual_trace: ResidualTrace,
    pub notes: Vec<String>,
}

/// The held-out residual of the final model without and with one effect.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EffectShrink {
    /// RMS of all residual components, in units of their expected noise.
    pub rms_without: f64,
    pub rms_with: f64,
    /// RMS of the field-magnitude residual, uT (NaN without that channel).
    pub mag_norm_without_ut: f64,
    pub mag_norm_with_ut: f64,
    /// RMS of the field-direction residual, deg (NaN without that channel).
    pub vector_mag_without_deg: f64,
    pub vector_mag_with_deg: f64,
}

/// Residuals of one channel against the regressor of one effect, before and after adding it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResidualSeries {
    pub effect: String,
    /// Residual channel (`mag_norm`, `dip`, ...) and its unit.
    pub channel: String,
    pub unit: String,
    /// What `x` is, with its unit.
    pub regressor: String,
    /// One entry per residual component (a unit can give several, e.g. the three gyro axes).
    pub x: Vec<f64>,
    /// Residual of the base model (fitted on the fit units).
    pub before: Vec<f64>,
    /// Residual of the final model.
    pub after: Vec<f64>,
    /// The part of the residual the effect's fitted term explains (final model with the effect
    /// switched off minus the final model): "before" lies along it, "after" does not.
    #[serde(default)]
    pub predicted: Vec<f64>,
    /// Whether each point is held out.
    pub held_out: Vec<bool>,
}

impl DiagnosisReport {
    /// One line: the effects found, the held-out RMS before and after, and the last round's
    /// decision with its detail.
    pub fn outcome(&self) -> String {
        format!(
            "found {:?}, rms {:.2} -> {:.2}; {}",
            self.found,
            self.rms_before,
            self.rms_after,
            self.rounds
                .last()
                .map(|x| format!("{}: {}", x.decision, x.detail))
                .unwrap_or_default()
        )
    }

    pub(super) fn failed(base: ModelKind, why: String) -> Self {
        DiagnosisReport {
            schema: SCHEMA.into(),
            base_model: base.name().into(),
            evidence: EvidenceSummary::default(),
            found: vec![],
            rounds: vec![RoundReport {
                round: 1,
                decision: Decision::NotIdentifiable,
                effect: None,
                detail: why.clone(),
                candidates: vec![],
                possible: None,
            }],
            rms_before: f64::NAN,
            rms_after: f64::NAN,
            rms_channels: BTreeMap::new(),
            effects: BTreeMap::new(),
            residual_plots: vec![],
            field_ut: 0.0,
            mag_matrix: None,
            effect_shrink: BTreeMap::new(),
            residual_trace: ResidualTrace::default(),
            notes: vec![why],
        }
    }
}

/// Held-out RMS per channel (physical units) for the base and the final model, with the expected
/// noise of a unit of median size.
fn rms_channels(run: &Run, pb: &[f64; NCH], pa: &[f64; NCH]) -> BTreeMap<String, ChannelRms> {
    let mut out = BTreeMap::new();
    for c in ALL_CH {
        let i = c.i();
        if run.ctx.ch[i] && pb[i].is_finite() {
            let typ_n = median_count(run.ev, i).unwrap_or(1) as f64;
            out.insert(
                c.name().to_string(),
                ChannelRms {
                    unit: c.unit().into(),
                    before: pb[i],
                    after: pa[i],
                    noise: run.noise_sd[i] / typ_n.sqrt(),
                },
            );
        }
    }
    out
}

/// The parameters of the effects found, from a fit of the final model on all units, with 1-sigma
/// uncertainties (cross-axis terms relative to the mean diagonal, angles in degrees).
fn effect_params(
    run: &Run,
    sel: &Selection,
    all: &[usize],
) -> (EffectParams, Option<[[f64; 3]; 3]>) {
    let mut effects = BTreeMap::new();
    if sel.found.is_empty() {
        let md = decode(&run.ctx, &sel.lay, sel.p.as_slice());
        return (effects, sel.lay.mag.map(|_| mat_rows(&md.am)));
    }
    let (lay, p) = (&sel.lay, &sel.p);
    let w = run.weights(lay, p);
    let fa = run.fit(lay, &w, all, p.clone());
    let dof = (fa.r.len() as f64 - lay.n as f64).max(1.0);
    let s2 = fa.ssr / dof;
    let cov = fa.jtj.clone().try_inverse().map(|c| c * s2);
    let md = decode(&run.ctx, lay, fa.p.as_slice());
    let diag_scale = (md.am[(0, 0)] + md.am[(1, 1)] + md.am[(2, 2)]) / 3.0;
    let acc_scale = (md.aa[(0, 0)] + md.aa[(1, 1)] + md.aa[(2, 2)]) / 3.0;
    for b in &lay.effects {
        let mut params = BTreeMap::new();
        for k in 0..b.len {
            let idx = b.start + k;
            let (name, unit) = lay.names[idx].clone();
            let sig = cov
                .as_ref()
                .map(|c| c[(idx, idx)].max(0.0).sqrt())
                .unwrap_or(f64::NAN);
            let (mut v, mut s, mut u) = (fa.p[idx], sig, unit);
            match b.effect {
                Effect::CrossAxis => {
                    let sc = if name.starts_with("mag") {
                        diag_scale
                    } else {
                        acc_scale
                    };
                    v /= sc;
                    s /= sc;
                }
                Effect::MagAccelMisalignment | Effect::HeadingOffset => {
                    v = v.to_degrees();
                    s = s.to_degrees();
                    u = "deg".into();
                }
                _ => {}
            }
            let name = if b.effect == Effect::MagAccelMisalignment {
                format!("{name}_deg")
            } else if b.effect == Effect::HeadingOffset {
                "heading_offset_deg".to_string()
            } else {
                name
            };
            params.insert(
                name,
                ParamEstimate {
                    value: v,
                    sigma: s,
                    unit: u,
                },
            );
        }
        if let Some((_, tau)) = lay.lag_of(b.effect) {
            // Profiled on the lag grid (steps of sqrt 2 above its first non-zero value), not
            // solved for: its uncertainty is the grid's half step.
            let first = match b.effect {
                Effect::TemperatureBias => super::evidence::TEMP_LAGS_S[1],
                _ => super::evidence::DRIVER_LAGS_S[1],
            };
            params.insert(
                "lag_s".to_string(),
                ParamEstimate {
                    value: tau,
                    sigma: if tau > 0.0 {
                        tau * (std::f64::consts::SQRT_2 - 1.0) / 2.0
                    } else {
                        first / 2.0
                    },
                    unit: "s".to_string(),
                },
            );
        }
        effects.insert(b.effect.name().to_string(), params);
    }
    (effects, lay.mag.map(|_| mat_rows(&md.am)))
}

/// The fitted parameters of each effect, by effect and parameter name.
type EffectParams = BTreeMap<String, BTreeMap<String, ParamEstimate>>;

fn mat_rows(m: &nalgebra::Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// The held-out residual of the final model with each effect found switched off and on.
fn effect_shrink(run: &Run, sel: &Selection, units: &[usize]) -> BTreeMap<String, EffectShrink> {
    let (ra, pa) = run.rms(&sel.lay, &sel.p, units);
    let mut out = BTreeMap::new();
    for e in &sel.found {
        let Some(b) = sel.lay.block(*e) else {
            continue;
        };
        let mut off = sel.p.clone();
        for k in 0..b.len {
            off[b.start + k] = 0.0;
        }
        let (rb, pb) = run.rms(&sel.lay, &off, units);
        out.insert(
            e.name().to_string(),
            EffectShrink {
                rms_without: rb,
                rms_with: ra,
                mag_norm_without_ut: pb[Ch::MagNorm.i()],
                mag_norm_with_ut: pa[Ch::MagNorm.i()],
                vector_mag_without_deg: pb[Ch::VecMag.i()].to_degrees(),
                vector_mag_with_deg: pa[Ch::VecMag.i()].to_degrees(),
            },
        );
    }
    out
}

/// The report of a finished selection: held-out RMS of the base (`lay0`, `base_p`) and the final
/// model, per-channel RMS, effect parameters, residual series.
pub(super) fn assemble(
    run: &Run,
    split: &Split,
    base: ModelKind,
    (lay0, base_p): (&Layout, &DVector<f64>),
    sel: Selection,
    notes: Vec<String>,
) -> DiagnosisReport {
    let ev = run.ev;
    let rms_units = if run.hold_units.is_empty() {
        run.fit_units.clone()
    } else {
        run.hold_units.clone()
    };
    let (rb, pb) = run.rms(lay0, base_p, &rms_units);
    let (ra, pa) = run.rms(&sel.lay, &sel.p, &rms_units);
    let rms_channels = rms_channels(run, &pb, &pa);
    let (effects, mag_matrix) = effect_params(run, &sel, &split.order);
    let effect_shrink = effect_shrink(run, &sel, &rms_units);
    let residual_trace = super::follows::trace(&run.ctx, ev, (&sel.lay, &sel.p), &split.order);
    let residual_plots: Vec<ResidualSeries> = sel
        .found
        .iter()
        .filter_map(|e| residual_series(run, *e, lay0, base_p, &sel.lay, &sel.p, &split.order))
        .collect();
    let channels = ALL_CH
        .iter()
        .filter(|c| run.ctx.ch[c.i()])
        .map(|c| c.name().to_string())
        .collect();
    let static_units = ev.units.iter().filter(|u| !u.moving).count();
    DiagnosisReport {
        schema: SCHEMA.into(),
        base_model: base.name().into(),
        evidence: EvidenceSummary {
            unit: if ev.moving_windows > 0 {
                "static_segments+moving_windows".into()
            } else {
                "static_segments".into()
            },
            units: ev.units.len(),
            static_units,
            moving_windows: ev.moving_windows,
            window_s: if ev.moving_windows > 0 {
                ev.window_s
            } else {
                0.0
            },
            poses: ev.poses,
            held_out_units: run.hold_units.len(),
            channels,
            driver: ev.driver.map(|d| match d {
                Driver::Throttle => "throttle".to_string(),
                Driver::Current => "current".to_string(),
            }),
            accel_fitted: run.ctx.acc_free,
        },
        found: sel.found.clone(),
        rounds: sel.rounds,
        rms_before: rb,
        rms_after: ra,
        rms_channels,
        effects,
        residual_plots,
        field_ut: if run.ctx.ch[Ch::MagNorm.i()] || run.ctx.ch[Ch::VecMag.i()] {
            run.ctx.s0m
        } else {
            0.0
        },
        mag_matrix,
        effect_shrink,
        residual_trace,
        notes,
    }
}

/// The residual series of effect `e` (see [`ResidualSeries`]): the channel where the effect's term
/// is largest against the expected noise, x its natural regressor (driver, temperature, time,
/// reference heading) or else the residual the effect's term predicts.
#[allow(clippy::too_many_arguments)]
fn residual_series(
    run: &Run,
    e: Effect,
    lay0: &Layout,
    p0: &DVector<f64>,
    lay: &Layout,
    p: &DVector<f64>,
    units: &[usize],
) -> Option<ResidualSeries> {
    let ev = run.ev;
    let ctx = &run.ctx;
    let block = lay.block(e)?;
    let mut p_off = p.clone();
    for k in 0..block.len {
        p_off[block.start + k] = 0.0;
    }
    let tg = tags(ctx, lay, p, ev, units);
    let after = residuals(ctx, lay, ev, units, p.as_slice());
    let off = residuals(ctx, lay, ev, units, p_off.as_slice());
    let tg0 = tags(ctx, lay0, p0, ev, units);
    let before = residuals(ctx, lay0, ev, units, p0.as_slice());
    if tg.len() != after.len() || off.len() != after.len() || tg0 != tg || before.len() != tg.len()
    {
        return None;
    }
    // The channel the effect moves most, in units of the expected noise.
    let mut score = [0.0; NCH];
    for (((ui, c, _), (_, ra)), (_, ro)) in tg.iter().zip(&after).zip(&off) {
        score[c.i()] += ((ro - ra) / run.noise(*ui, *c).max(1e-300)).powi(2);
    }
    let ch = ALL_CH
        .into_iter()
        .filter(|c| score[c.i()] > 0.0)
        .max_by(|a, b| score[a.i()].total_cmp(&score[b.i()]))?;
    let heading_deg = |ui: usize| {
        ev.units[ui].ref_w.map(|w| {
            // Heading of the body x axis in ENU: clockwise from north.
            let x = w * Vector3::x();
            x.x.atan2(x.y).to_degrees().rem_euclid(360.0)
        })
    };
    let regressor = match e {
        Effect::MotorInterference => {
            let lagged = if lay.drv_lag > 0 {
                format!(" lagged {:.2} s", lay.drv_lag_s())
            } else {
                String::new()
            };
            match ev.driver {
                Some(Driver::Current) => format!("current{lagged} (A)"),
                _ => format!("throttle{lagged} (0..1)"),
            }
        }
        Effect::TemperatureBias if lay.temp_lag > 0 => {
            format!("temperature lagged {:.0} s (deg C)", lay.temp_lag_s())
        }
        Effect::TemperatureBias => "temperature (deg C)".to_string(),
        Effect::GyroBiasDrift => "time (s)".to_string(),
        Effect::HeadingOffset if units.iter().all(|&u| heading_deg(u).is_some()) => {
            "reference heading (deg)".to_string()
        }
        _ => format!("{} predicted by {} ({})", ch.name(), e.name(), ch.unit()),
    };
    let hold: std::collections::HashSet<usize> = run.hold_units.iter().copied().collect();
    let mut out = ResidualSeries {
        effect: e.name().into(),
        channel: ch.name().into(),
        unit: ch.unit().into(),
        regressor: regressor.clone(),
        x: vec![],
        before: vec![],
        after: vec![],
        predicted: vec![],
        held_out: vec![],
    };
    for (i, (ui, c, _)) in tg.iter().enumerate() {
        if *c != ch {
            continue;
        }
        let u = &ev.units[*ui];
        let x = match e {
            Effect::MotorInterference => u.dlag[lay.drv_lag] + ev.drv_mean,
            Effect::TemperatureBias if u.has_temp => u.tlag[lay.temp_lag] + ev.temp_mean,
            Effect::GyroBiasDrift => u.t + ev.t_mean,
            Effect::HeadingOffset if regressor.starts_with("reference") => {
                heading_deg(*ui).unwrap_or(f64::NAN)
            }
            Effect::TemperatureBias => f64::NAN,
            _ => off[i].1 - after[i].1,
        };
        out.x.push(x);
        out.before.push(before[i].1);
        out.after.push(after[i].1);
        out.predicted.push(off[i].1 - after[i].1);
        out.held_out.push(hold.contains(ui));
    }
    Some(out)
}

/// A terminal table of a diagnosis.
pub fn summary_table(r: &DiagnosisReport) -> String {
    let mut s = String::new();
    let e = &r.evidence;
    let _ = writeln!(
        s,
        "diagnosis ({}): base {}, {} evidence units ({} static from {} poses, {} moving windows{}), {} held out",
        r.schema,
        r.base_model,
        e.units,
        e.static_units,
        e.poses,
        e.moving_windows,
        if e.moving_windows > 0 {
            format!(" of {:.2} s", e.window_s)
        } else {
            String::new()
        },
        e.held_out_units
    );
    let _ = writeln!(
        s,
        "channels: {}; driver: {}; accel {}",
        e.channels.join(", "),
        e.driver.as_deref().unwrap_or("none"),
        if e.accel_fitted {
            "refitted"
        } else {
            "held fixed"
        }
    );
    for rd in &r.rounds {
        let _ = writeln!(
            s,
            "round {}: {}{} - {}",
            rd.round,
            rd.decision,
            rd.effect
                .map(|x| format!(" {}", x.name()))
                .unwrap_or_default(),
            rd.detail
        );
        let _ = writeln!(
            s,
            "  {:<24} {:>10} {:>10} {:>8} {:>6} {:>6} {:>5} {:>8}",
            "candidate", "F", "p", "improv", "plaus", "ident", "q", "held-out"
        );
        for c in &rd.candidates {
            let _ = writeln!(
                s,
                "  {:<24} {:>10.2} {:>10.2e} {:>7.1}% {:>6} {:>6} {:>5} {:>8}{}",
                c.name,
                c.statistic,
                c.p_value,
                100.0 * c.improvement,
                if c.plausible { "yes" } else { "no" },
                if c.identifiable { "yes" } else { "no" },
                c.params,
                match c.held_out {
                    Some(true) => "holds",
                    Some(false) => "fails",
                    None => "-",
                },
                if c.note.is_empty() {
                    String::new()
                } else {
                    format!("  ({})", c.note)
                }
            );
        }
    }
    let _ = writeln!(
        s,
        "found: {}",
        if r.found.is_empty() {
            "nothing".to_string()
        } else {
            r.found
                .iter()
                .map(|e| e.name())
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    let ratio = r.rms_before / r.rms_after;
    if ratio.is_finite() {
        let _ = writeln!(
            s,
            "{} RMS (units of expected noise): {:.3} -> {:.3} ({:.2}x)",
            if e.held_out_units > 0 {
                "held-out"
            } else {
                "in-sample (nothing held out)"
            },
            r.rms_before,
            r.rms_after,
            ratio
        );
    } else {
        let _ = writeln!(s, "no residual to compare");
    }
    for (name, c) in &r.rms_channels {
        let _ = writeln!(
            s,
            "  {:<13} {:>12.4e} -> {:>12.4e} {} (noise {:.2e})",
            name,
            c.before,
            c.after,
            shown_unit(&c.unit),
            c.noise
        );
    }
    for (name, params) in &r.effects {
        let _ = writeln!(s, "{name}:");
        for (p, v) in params {
            let _ = writeln!(
                s,
                "  {:<22} {:>12.5} +- {:<10.2e} {:<12} ({:.1} sigma)",
                p,
                v.value,
                v.sigma,
                shown_unit(&v.unit),
                v.value.abs() / v.sigma
            );
        }
    }
    for n in &r.notes {
        let _ = writeln!(s, "note: {n}");
    }
    s
}
