//! The refits of a round and its decision: each candidate worth it refitted jointly with the
//! current model (F-test, held-out check, physical range, conditioning, determined size,
//! confounding), in rank order until one is named; else the round's other decision.

use super::channel::{ALL_CH, NCH};
use super::decision::{shown_unit, CandidateReport, Decision, Possible};
use super::determined::{covariance, determine, Deciding, Determination};
use super::layout::{build_layout, carry_params, residuals, tags, Layout};
use super::plausible::{out_of_range, render};
use super::run::{Run, Selection, EXCESS_RATIO};
use super::screen::{Cand, Linearised};
use super::stats::{condition, explained, nested_f, select_cols};
use super::Effect;
use nalgebra::DVector;

/// Candidates are refitted jointly, in rank order, while their linearised p is below this multiple
/// of the round's threshold alpha / m.
const REFIT_P_FACTOR: f64 = 10.0;
/// Largest condition number of a joint fit's normal matrix (column-normalised); above it the fit is
/// degenerate.
const MAX_JOINT_CONDITION: f64 = 1e12;
/// Confounding: another significant candidate explains at least this share of the named one's
/// linearised drop...
const CONFOUND_SHARE: f64 = 0.8;
/// ...and both together explain at most this multiple of the larger single drop.
const CONFOUND_UNION: f64 = 1.1;
/// "Unexplained" needs at least this many residual components in the channel.
const MIN_EXCESS_COMPONENTS: usize = 5;
/// Floor of the fraction of a channel's components left as degrees of freedom in the excess test.
const MIN_DOF_FRACTION: f64 = 0.1;

/// A held-out z above this is shown as "> 100 sd" (the statistic is the held-out drop in units of
/// a spurious fit's sd; far beyond any threshold its digits say nothing).
const SHOWN_Z_CAP: f64 = 100.0;

/// How the refits of a round ended: an effect named, a decision without one, or neither (with the
/// significant candidates that failed a check, and the first that passed every test but whose
/// size the data do not determine).
pub(super) struct Verdict {
    pub decision: Option<(Decision, Option<Effect>, String)>,
    pub named: Option<(Effect, Layout, DVector<f64>)>,
    pub failed_sig: Vec<String>,
    pub possible: Option<Possible>,
}

/// The held-out drop as the terminal shows it.
fn held_text(hdrop: f64, z: f64) -> String {
    if !hdrop.is_finite() {
        return "no held-out groups".to_string();
    }
    let sd = if z > SHOWN_Z_CAP {
        format!("> {SHOWN_Z_CAP:.0}")
    } else {
        format!("{z:.1}")
    };
    format!(
        "held-out squared residual drops {:.1}% ({sd} sd of a spurious fit's drop)",
        100.0 * hdrop
    )
}

/// The effect's parameters as `name value unit`, joined.
fn params_text(lay: &Layout, p: &DVector<f64>, e: Effect) -> String {
    lay.block(e)
        .map(|b| {
            (0..b.len)
                .map(|k| {
                    let (name, unit) = &lay.names[b.start + k];
                    format!("{name} {:.4} {}", p[b.start + k], shown_unit(unit))
                        .trim_end()
                        .to_string()
                })
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}

/// A candidate's joint refit: its layout and parameters, p-value, physical range, held-out
/// verdict, condition number and determination.
pub(super) struct Refit {
    pub lay: Layout,
    pub p: DVector<f64>,
    pub p_value: f64,
    pub plausible: bool,
    pub holds: bool,
    pub condition: f64,
    pub size: Determination,
}

/// The joint refit of the current model plus candidate `c`: its report entry is updated.
fn refit(
    run: &Run,
    lin: &Linearised,
    sel: &Selection,
    cur_p: &DVector<f64>,
    c: &Cand,
    rep: &mut CandidateReport,
) -> Refit {
    let mut effs = sel.found.clone();
    effs.push(c.e);
    let lay1 = build_layout(&run.ctx, &effs).with_lags_of(&lin.lay_all);
    let p1s = carry_params(&sel.lay, cur_p, &lay1);
    let w = &lin.w;
    let mut alt = run.fit(&lay1, w, &run.fit_units.clone(), p1s);
    if !out_of_range(&run.ctx, &lay1, &alt.p, c.e).is_empty() {
        let again = carry_params(&sel.start.0, &sel.start.1, &lay1);
        let alt2 = run.fit(&lay1, w, &run.fit_units.clone(), again);
        if alt2.ssr < alt.ssr {
            alt = alt2;
        }
    }
    let (m, p_cur, q, s0) = (lin.m, lin.p_cur, c.q, lin.s0);
    let s1 = alt.ssr.max(1e-300);
    let rho = run.autocorr(w, (&sel.lay, cur_p), (&lay1, &alt.p));
    let defl = (1.0 - rho) / (1.0 + rho);
    let (f, pv) = nested_f(
        (s0 - s1).max(0.0),
        s1,
        q,
        m as f64 - (p_cur + q) as f64,
        defl,
    );
    let oor = out_of_range(&run.ctx, &lay1, &alt.p, c.e);
    let plaus = oor.is_empty();
    let (holds, hz, hdrop) = run.held_out(w, (&sel.lay, cur_p), (&lay1, &alt.p), q, m);
    let cond = condition(&alt.jtj);
    let cov = covariance(&alt.jtj, alt.ssr, alt.r.len(), rho);
    let size = determine(&lay1, &alt.p, cov.as_ref(), c.e, oor.clone());
    rep.statistic = f;
    rep.p_value = pv;
    rep.improvement = if s0 > 0.0 { (s0 - s1) / s0 } else { 0.0 };
    rep.plausible = plaus;
    rep.refit = true;
    rep.held_out = Some(holds);
    let lag = match lay1.lag_of(c.e) {
        Some((_, tau)) => format!(", lagged {tau:.2} s"),
        None => String::new(),
    };
    let mut note = format!(
        "{}; lag-1 autocorrelation {rho:.2}; linearised F {:.2}; {}{lag}; {size}",
        held_text(hdrop, hz),
        c.f_lin,
        params_text(&lay1, &alt.p, c.e)
    );
    if !(cond < MAX_JOINT_CONDITION) {
        note.push_str(&format!("; joint fit degenerate (condition {cond:.1e})"));
    }
    rep.note = note;
    rep.out_of_range = oor;
    rep.size = Some(size.clone());
    Refit {
        lay: lay1,
        p: alt.p,
        p_value: pv,
        plausible: plaus,
        holds,
        condition: cond,
        size,
    }
}

/// Refit the candidates in rank order until one is named or a decision is reached.
#[allow(clippy::too_many_arguments)]
pub(super) fn judge(
    run: &Run,
    lin: &Linearised,
    sel: &Selection,
    cur_p: &DVector<f64>,
    list: &[Cand],
    rank: &[usize],
    reports: &mut [CandidateReport],
    thresh: f64,
) -> Verdict {
    let mut v = Verdict {
        decision: None,
        named: None,
        failed_sig: vec![],
        possible: None,
    };
    for &ci in rank {
        let c = &list[ci];
        if !(c.p_lin < REFIT_P_FACTOR * thresh) {
            break;
        }
        let r = refit(run, lin, sel, cur_p, c, &mut reports[ci]);
        let pv = r.p_value;
        if !(pv < thresh) {
            continue;
        }
        if !(r.condition < MAX_JOINT_CONDITION) {
            let d = format!(
                "{} is significant but its joint fit is degenerate (condition {:.1e}): poor coverage",
                c.e.name(),
                r.condition
            );
            v.decision = Some((Decision::NotIdentifiable, Some(c.e), d));
            return v;
        }
        if !r.plausible || !r.holds {
            let why = if !r.plausible {
                format!(
                    "outside its physical range: {}",
                    render(&r.size.out_of_range)
                )
            } else {
                "does not hold on held-out poses".to_string()
            };
            v.failed_sig
                .push(format!("{} (p {pv:.1e}) {why}", c.e.name()));
            continue;
        }
        if !r.size.determined() {
            if v.possible.is_some() {
                // The first is said in full as the effect that might be there.
                v.failed_sig.push(format!(
                    "{} (p {pv:.1e}) size not determined: {}",
                    c.e.name(),
                    r.size
                ));
            } else {
                v.possible = Some(Possible {
                    effect: c.e,
                    size: r.size,
                    decide_with: Deciding::for_effect(c.e),
                });
            }
            continue;
        }
        if let Some(o) = confounder(lin, list, c, thresh) {
            let d = format!(
                "{} and {} explain the same residual structure (their regressors are collinear in this data); vary them independently",
                c.e.name(),
                o.name()
            );
            v.decision = Some((Decision::NotIdentifiable, Some(c.e), d));
            return v;
        }
        v.named = Some((c.e, r.lay, r.p));
        return v;
    }
    v
}

/// The channels whose residual variance is more than [`EXCESS_RATIO`] x their
/// expected noise, as (channel, ratio).
fn excess_channels(
    run: &Run,
    sel: &Selection,
    cur_p: &DVector<f64>,
    noise_known: &[bool; NCH],
) -> Vec<(super::channel::Ch, f64)> {
    let ev = run.ev;
    let res = residuals(&run.ctx, &sel.lay, ev, &run.fit_units, cur_p.as_slice());
    let tg = tags(&run.ctx, &sel.lay, cur_p, ev, &run.fit_units);
    let mut chi = [0.0; NCH];
    let mut nn = [0usize; NCH];
    for ((ui, _, _), (c, r)) in tg.iter().zip(&res) {
        chi[c.i()] += (r / run.noise(*ui, *c).max(1e-300)).powi(2);
        nn[c.i()] += 1;
    }
    let mtot = res.len() as f64;
    let mut excess = vec![];
    for c in ALL_CH {
        let i = c.i();
        if nn[i] >= MIN_EXCESS_COMPONENTS && noise_known[i] {
            let dof = nn[i] as f64 * (1.0 - sel.lay.n as f64 / mtot).max(MIN_DOF_FRACTION);
            let ratio = chi[i] / dof;
            if ratio > EXCESS_RATIO {
                excess.push((c, ratio));
            }
        }
    }
    excess
}

/// No effect named and no other decision: "unexplained" when some channel's residual variance is
/// more than [`EXCESS_RATIO`] x its expected noise, else "not_identifiable" when a
/// candidate passed every test but its size is not determined, else "none". A candidate whose size
/// is not determined is said in either of the first two (the effect that might be there, and the
/// data that would decide it).
pub(super) fn no_effect_decision(
    run: &Run,
    sel: &Selection,
    cur_p: &DVector<f64>,
    noise_known: &[bool; NCH],
    v: &Verdict,
    (alpha, n_ident, thresh): (f64, usize, f64),
) -> (Decision, Option<Effect>, String) {
    let excess: Vec<String> = excess_channels(run, sel, cur_p, noise_known)
        .into_iter()
        .map(|(c, ratio)| format!("{} {ratio:.1}x", c.name()))
        .collect();
    let excess = if excess.is_empty() {
        vec![]
    } else {
        vec![format!(
            "residual variance {} the noise expected from the scatter within each unit",
            excess.join(", ")
        )]
    };
    let failed = if v.failed_sig.is_empty() {
        String::new()
    } else {
        format!(
            "; candidates that fit but failed: {}",
            v.failed_sig.join(", ")
        )
    };
    let possible = v.possible.as_ref().map(|pos| {
        format!(
            "{} might be there but its size is not determined ({}); {} would decide it",
            pos.effect.name(),
            pos.size,
            pos.decide_with
        )
    });
    if !excess.is_empty() {
        let mut d = excess.join("; ");
        if let Some(t) = &possible {
            d.push_str(&format!("; {t}"));
        }
        d.push_str(&failed);
        return (Decision::Unexplained, None, d);
    }
    if let (Some(pos), Some(t)) = (&v.possible, possible) {
        return (Decision::NotIdentifiable, Some(pos.effect), t);
    }
    let d = if v.failed_sig.is_empty() {
        format!("no candidate is significant at {thresh:.1e} (alpha {alpha} / {n_ident})")
    } else {
        format!("significant but rejected: {}", v.failed_sig.join(", "))
    };
    (Decision::NoEffect, None, d)
}

/// Another significant candidate that explains the same structure as `c`, if any.
fn confounder(lin: &Linearised, list: &[Cand], c: &Cand, thresh: f64) -> Option<Effect> {
    for o in list {
        if o.e == c.e || !o.ident || !(o.p_lin < thresh) {
            continue;
        }
        let mut bc = lin.base_cols.clone();
        bc.extend(c.cols.iter().copied());
        bc.extend(o.cols.iter().copied());
        let (exu, _) = explained(&select_cols(&lin.j_all, &bc), &lin.r_vec);
        let dsu = (exu - lin.ex0).max(0.0);
        if o.ds_lin >= CONFOUND_SHARE * c.ds_lin && dsu <= CONFOUND_UNION * c.ds_lin.max(o.ds_lin) {
            return Some(o.e);
        }
    }
    None
}
