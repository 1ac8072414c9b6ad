//! The nested selection rounds: the held-out split, start values and noise levels, the base fit, and
//! per round the linearised screen of every candidate effect, the joint refits in rank order and the
//! decision (named, none, unexplained, not_identifiable), recorded as [`super::decision`] types.

use super::channel::{Ch, ALL_CH, NCH};
use super::decision::{CandidateReport, Decision, RoundReport};
use super::evidence::{quat_rot, v3, Evidence, MagObs, Unit};
use super::judge::{judge, no_effect_decision};
use super::layout::{decode, Ctx, Layout};
use super::run::{Run, Selection};
use super::screen::{linearise, screen, Cand};
use super::stats::mean_sd;
use super::{DiagnoseOptions, Effect};
use crate::calib::model::{params_from_a, ModelKind};
use crate::calib::pipeline::Pipeline;
use crate::config::Config;
use crate::types::Sample;
use nalgebra::{DVector, Matrix3, Vector3};

/// Fewest groups (poses, window blocks) for a held-out split; below it the checks are skipped.
const MIN_GROUPS_FOR_HOLDOUT: usize = 8;
/// Largest fraction of the groups held out, whatever the options say.
const MAX_HOLDOUT_FRACTION: f64 = 0.5;
/// Fewest groups held out.
const MIN_HELD_OUT_GROUPS: usize = 2;
/// Range of a unit's relative weight within a channel, sqrt(n / median n).
const REL_WEIGHT_RANGE: (f64, f64) = (0.3, 3.0);
/// Fewest samples of a channel inside a unit for its within-unit scatter.
const MIN_SCATTER_SAMPLES: usize = 3;

/// The samples sorted by time, run through the pipeline (static poses and the start fits) and turned
/// into evidence units. Err: why there is nothing to compare.
pub(super) struct Prepared {
    pub ev: Evidence,
    pub results: crate::calib::pipeline::FitResults,
    /// Sensor -> body rotation.
    pub rot: Matrix3<f64>,
}

pub(super) fn prepare(
    samples: &[Sample],
    cfg: &Config,
    base: ModelKind,
    log_where: crate::types::LogWhere,
    notes: &mut Vec<String>,
) -> Result<Prepared, String> {
    let mut cfg2 = cfg.clone();
    cfg2.fit.mag_model = base.into();
    let mut pipe = Pipeline::new(&cfg2.calib()).map_err(|e| format!("configuration: {e}"))?;
    let mut sorted: Vec<Sample> = samples
        .iter()
        .filter(|s| s.t_s.is_finite())
        .copied()
        .collect();
    if sorted.windows(2).any(|w| w[1].t_s < w[0].t_s) {
        sorted.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
        notes.push("samples sorted by time".into());
    }
    for s in &sorted {
        pipe.push(s);
    }
    let mut results = pipe.finish().clone();
    vector_start(&mut results, &sorted, &pipe, cfg, log_where, notes);
    let poses = pipe.poses().to_vec();
    let body: Vec<Sample> = sorted.iter().map(|s| pipe.to_body(s)).collect();
    let rot = crate::attitude::sensor_rotation(&cfg.orientation.sensor)
        .unwrap_or_else(|_| Matrix3::identity());
    let ev = super::evidence::build_evidence(body, &poses, &rot);
    if ev.units.is_empty() {
        return Err("no static poses and no magnetometer windows: nothing to compare".into());
    }
    Ok(Prepared { ev, results, rot })
}

/// With an attitude and the earth field (an ordinary flight, no tumble), the vector calibration is
/// the magnetometer's start instead of the sphere fit, which such data leave without coverage.
fn vector_start(
    results: &mut crate::calib::pipeline::FitResults,
    sorted: &[Sample],
    pipe: &Pipeline,
    cfg: &Config,
    log_where: crate::types::LogWhere,
    notes: &mut Vec<String>,
) {
    let mut mag = results.mag.clone();
    crate::calib::magmethod::choose(
        &mut mag,
        sorted,
        &|s| pipe.to_body(s),
        log_where,
        cfg.place.as_ref(),
    );
    let Some(choice) = &mag.report.method else {
        return;
    };
    if choice.method == crate::calib::magmethod::MagMethod::Vector {
        notes.push(format!(
            "magnetometer start: the vector calibration ({})",
            choice.method_reason
        ));
        results.mag = mag;
    }
}

/// Units in time order, and the fit and held-out units (whole groups held out, drawn with the seed).
pub(super) struct Split {
    pub order: Vec<usize>,
    pub fit_units: Vec<usize>,
    pub hold_units: Vec<usize>,
}

pub(super) fn split_units(ev: &Evidence, opts: &DiagnoseOptions, notes: &mut Vec<String>) -> Split {
    let mut groups: Vec<usize> = ev.units.iter().map(|u| u.group).collect();
    groups.sort_unstable();
    groups.dedup();
    let mut hold_groups = std::collections::BTreeSet::new();
    if groups.len() >= MIN_GROUPS_FOR_HOLDOUT && opts.holdout_fraction > 0.0 {
        use rand::{seq::SliceRandom, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
        let mut g2 = groups.clone();
        g2.shuffle(&mut rng);
        let k = ((opts.holdout_fraction.min(MAX_HOLDOUT_FRACTION) * g2.len() as f64).ceil()
            as usize)
            .max(MIN_HELD_OUT_GROUPS);
        hold_groups.extend(g2.into_iter().take(k));
    } else {
        notes.push(format!(
            "{} groups: too few to hold any out; held-out checks skipped and RMS is in-sample",
            groups.len()
        ));
    }
    let mut order: Vec<usize> = (0..ev.units.len()).collect();
    order.sort_by(|&a, &b| ev.units[a].t.total_cmp(&ev.units[b].t));
    let fit_units: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&i| !hold_groups.contains(&ev.units[i].group))
        .collect();
    let hold_units: Vec<usize> = order
        .iter()
        .copied()
        .filter(|&i| hold_groups.contains(&ev.units[i].group))
        .collect();
    Split {
        order,
        fit_units,
        hold_units,
    }
}

/// Median over the units of a channel's sample count (units without the channel left out), 1 when none.
pub(super) fn median_count(ev: &Evidence, i: usize) -> Option<usize> {
    let mut v: Vec<usize> = ev.units.iter().map(|u| u.n[i]).filter(|n| *n > 0).collect();
    v.sort_unstable();
    v.get(v.len() / 2).copied()
}

/// Largest sample count of a channel over the units, 1 when none.
fn max_count(ev: &Evidence, i: usize) -> f64 {
    ev.units
        .iter()
        .map(|u| u.n[i])
        .filter(|n| *n > 0)
        .max()
        .unwrap_or(1) as f64
}

impl<'a> Run<'a> {
    pub(super) fn new(ctx: Ctx, ev: &'a Evidence, split: &Split) -> Run<'a> {
        let mut med = [1.0; NCH];
        for (i, m) in med.iter_mut().enumerate() {
            if let Some(x) = median_count(ev, i) {
                *m = x as f64;
            }
        }
        let rel = ev
            .units
            .iter()
            .map(|u| {
                std::array::from_fn(|i| {
                    (u.n[i] as f64 / med[i])
                        .sqrt()
                        .clamp(REL_WEIGHT_RANGE.0, REL_WEIGHT_RANGE.1)
                })
            })
            .collect();
        Run {
            ctx,
            ev,
            fit_units: split.fit_units.clone(),
            hold_units: split.hold_units.clone(),
            noise_sd: [f64::NAN; NCH],
            rel,
        }
    }
}

/// Start values of the base layout: the pipeline's matrices, the mean dip, the mean field direction
/// against the reference attitude, the mean static gyro.
pub(super) fn start_params(
    run: &Run,
    lay0: &Layout,
    base: ModelKind,
    m0: &Matrix3<f64>,
    a0: &Matrix3<f64>,
) -> DVector<f64> {
    let mut p0 = DVector::zeros(lay0.n);
    if let Some(s) = lay0.mag {
        for (k, v) in params_from_a(base, m0).iter().enumerate() {
            p0[s + 3 + k] = *v;
        }
    }
    if let Some(s) = lay0.acc {
        for (k, v) in params_from_a(base, a0).iter().enumerate() {
            p0[s + 3 + k] = *v;
        }
    }
    let md = decode(&run.ctx, lay0, p0.as_slice());
    let (mut sd, mut nd) = (0.0, 0usize);
    let mut hsum = Vector3::zeros();
    let mut gsum = Vector3::zeros();
    let mut ng = 0usize;
    for u in &run.ev.units {
        if u.moving {
            for o in &u.mags {
                if let Some(w) = o.ref_w {
                    hsum += w * run.ctx.cal_mag(&md, o).normalize();
                }
            }
            continue;
        }
        let cm = u.mags.first().map(|o| run.ctx.cal_mag(&md, o).normalize());
        let ca = u.acc.map(|a| run.ctx.cal_acc(&md, &a, &u.tlag).normalize());
        if let (Some(c), Some(a)) = (cm, ca) {
            sd += -a.dot(&c);
            nd += 1;
        }
        if let (Some(c), Some(w)) = (cm, u.ref_w) {
            hsum += w * c;
        }
        if let Some(gv) = u.gyro {
            gsum += gv;
            ng += 1;
        }
    }
    if let Some(s) = lay0.dip {
        p0[s] = if nd > 0 { sd / nd as f64 } else { 0.0 };
    }
    if let Some(s) = lay0.vec {
        let h = if hsum.norm() > 0.0 {
            hsum.normalize()
        } else {
            Vector3::new(0.0, 0.5, -0.8).normalize()
        };
        p0[s] = h.x.atan2(h.y);
        p0[s + 1] = (-h.z).clamp(-1.0, 1.0).asin();
    }
    if let Some(s) = lay0.gyro {
        let m = if ng > 0 {
            gsum / ng as f64
        } else {
            Vector3::zeros()
        };
        p0[s] = m.x;
        p0[s + 1] = m.y;
        p0[s + 2] = m.z;
    }
    p0
}

/// Within-unit scatter of each channel in one unit under the model `md` (per channel, the sd of the
/// samples about the unit mean; two components of a vector channel pooled; gyro axes pooled).
fn unit_scatter(
    ctx: &Ctx,
    md: &super::layout::Model,
    ev: &Evidence,
    u: &Unit,
    rot: &Matrix3<f64>,
) -> [Option<f64>; NCH] {
    let mut vals: [Vec<f64>; NCH] = Default::default();
    let mut vals2: [Vec<f64>; NCH] = Default::default();
    let mut gyro_axes: [Vec<f64>; 3] = Default::default();
    if u.moving {
        for o in &u.mags {
            let c = ctx.cal_mag(md, o);
            vals[Ch::MagNorm.i()].push((c.norm() - 1.0) * ctx.s0m);
            if let Some(w) = o.ref_w {
                let v = w * c.normalize();
                vals[Ch::VecMag.i()].push(v.dot(&md.e1));
                vals2[Ch::VecMag.i()].push(v.dot(&md.e2));
            }
        }
    } else {
        let mut last_acc: Option<Vector3<f64>> = None;
        for &i in &u.idx {
            let s = &ev.body[i];
            let ca = s.accel_mps2.map(|a| ctx.cal_acc(md, &v3(&a), &u.tlag));
            if ca.is_some() {
                last_acc = ca;
            }
            let w = s
                .ref_q
                .and_then(|q| quat_rot(&q))
                .map(|r| r * rot.transpose());
            if let Some(a) = ca {
                vals[Ch::AccNorm.i()].push((a.norm() - 1.0) * ctx.g);
                if let Some(w) = w {
                    let f = w * a.normalize();
                    vals[Ch::VecAcc.i()].push(f.x);
                    vals2[Ch::VecAcc.i()].push(f.y);
                }
            }
            if let Some(m) = s.mag_ut {
                let o = MagObs {
                    m: v3(&m),
                    tlag: u.tlag,
                    dlag: u.dlag,
                    ref_w: None,
                };
                let c = ctx.cal_mag(md, &o);
                vals[Ch::MagNorm.i()].push((c.norm() - 1.0) * ctx.s0m);
                let ch = c.normalize();
                if let Some(a) = last_acc {
                    vals[Ch::Dip.i()].push(-a.normalize().dot(&ch));
                }
                if let Some(w) = w {
                    let v = w * ch;
                    vals[Ch::VecMag.i()].push(v.dot(&md.e1));
                    vals2[Ch::VecMag.i()].push(v.dot(&md.e2));
                }
            }
            if let Some(gv) = s.gyro_rad_s {
                for k in 0..3 {
                    gyro_axes[k].push(gv[k]);
                }
            }
        }
    }
    let mut out = [None; NCH];
    if gyro_axes[0].len() >= MIN_SCATTER_SAMPLES {
        let v: f64 = gyro_axes.iter().map(|a| mean_sd(a).1.powi(2)).sum::<f64>() / 3.0;
        if v.is_finite() {
            out[Ch::Gyro.i()] = Some(v.sqrt());
        }
    }
    for c in 0..NCH {
        if c != Ch::Gyro.i() && vals[c].len() >= MIN_SCATTER_SAMPLES {
            let (_, s1) = mean_sd(&vals[c]);
            let s = if vals2[c].len() >= MIN_SCATTER_SAMPLES {
                let (_, s2) = mean_sd(&vals2[c]);
                ((s1 * s1 + s2 * s2) / 2.0).sqrt()
            } else {
                s1
            };
            if s.is_finite() {
                out[c] = Some(s);
            }
        }
    }
    out
}

/// Within-unit scatter of each channel under the start model: the noise a unit mean should show
/// (median over units; NaN for a channel without any).
pub(super) fn estimate_noise(run: &mut Run, lay0: &Layout, p0: &DVector<f64>, rot: &Matrix3<f64>) {
    let md = decode(&run.ctx, lay0, p0.as_slice());
    let mut per_ch: [Vec<f64>; NCH] = Default::default();
    for u in &run.ev.units {
        for (c, s) in unit_scatter(&run.ctx, &md, run.ev, u, rot)
            .iter()
            .enumerate()
        {
            if let Some(s) = s {
                per_ch[c].push(*s);
            }
        }
    }
    for c in 0..NCH {
        let v = &mut per_ch[c];
        if !v.is_empty() {
            v.sort_by(|a, b| a.total_cmp(b));
            run.noise_sd[c] = v[v.len() / 2].max(1e-12);
        } else {
            run.noise_sd[c] = f64::NAN;
        }
    }
}

/// The base model fitted on the fit units, in two passes (noise weights, then residual weights);
/// channels without a noise estimate get one from the base residuals (and no excess test).
/// Returns the parameters and which channels' noise came from the within-unit scatter.
pub(super) fn base_fit(
    run: &mut Run,
    lay0: &Layout,
    p0: DVector<f64>,
) -> (DVector<f64>, [bool; NCH]) {
    let ev = run.ev;
    let noise_known: [bool; NCH] = std::array::from_fn(|i| run.noise_sd[i].is_finite());
    let mut w0 = [0.0; NCH];
    for c in ALL_CH {
        let i = c.i();
        if run.ctx.ch[i] {
            let typ_n = max_count(ev, i);
            let s = if run.noise_sd[i].is_finite() {
                run.noise_sd[i] / typ_n.sqrt()
            } else {
                1.0
            };
            w0[i] = 1.0 / s.max(1e-12);
        }
    }
    let fit = run.fit(lay0, &w0, &run.fit_units.clone(), p0);
    let w1 = run.weights(lay0, &fit.p);
    for i in 0..NCH {
        if run.ctx.ch[i] && !noise_known[i] && w1[i] > 0.0 {
            run.noise_sd[i] = max_count(ev, i).sqrt() / w1[i];
        }
    }
    let fit = run.fit(lay0, &w1, &run.fit_units.clone(), fit.p);
    (fit.p, noise_known)
}

/// Run the rounds from the base model until one names nothing (or `max_rounds`).
pub(super) fn select(
    run: &Run,
    (lay0, p0): (&Layout, &DVector<f64>),
    base_p: &DVector<f64>,
    noise_known: &[bool; NCH],
    alpha: f64,
    max_rounds: usize,
) -> Selection {
    let mut sel = Selection {
        found: vec![],
        rounds: vec![],
        lay: lay0.clone(),
        p: base_p.clone(),
        start: (lay0.clone(), p0.clone()),
    };
    for round in 1..=max_rounds.max(1) {
        let (report, named, cur_p) = one_round(run, &sel, round, noise_known, alpha);
        sel.rounds.push(report);
        match named {
            Some((e, lay1, p1)) => {
                sel.found.push(e);
                sel.lay = lay1;
                sel.p = p1;
            }
            None => {
                sel.p = cur_p;
                break;
            }
        }
    }
    sel
}

/// One round: refit the current model, screen and rank the candidates, refit them in order.
/// Returns the round's report, the effect named (with its layout and parameters) and the current
/// model's refitted parameters.
#[allow(clippy::type_complexity)]
fn one_round(
    run: &Run,
    sel: &Selection,
    round: usize,
    noise_known: &[bool; NCH],
    alpha: f64,
) -> (
    RoundReport,
    Option<(Effect, Layout, DVector<f64>)>,
    DVector<f64>,
) {
    let w = run.weights(&sel.lay, &sel.p);
    let cur = run.fit(&sel.lay, &w, &run.fit_units.clone(), sel.p.clone());
    let cur_p = cur.p.clone();
    let lin = linearise(run, sel, &cur_p, w, &cur);
    let list: Vec<Cand> = Effect::ALL
        .iter()
        .copied()
        .filter(|e| !sel.found.contains(e))
        .map(|e| screen(run, &lin, sel, &cur_p, e))
        .collect();
    let s0 = lin.s0;
    let n_ident = list.iter().filter(|c| c.ident).count().max(1);
    let thresh = alpha / n_ident as f64;
    let mut reports: Vec<CandidateReport> = list
        .iter()
        .map(|c| CandidateReport {
            name: c.e.name().into(),
            statistic: c.f_lin,
            p_value: c.p_lin,
            improvement: if s0 > 0.0 { c.ds_lin / s0 } else { 0.0 },
            plausible: c.plaus,
            identifiable: c.ident,
            params: c.q,
            refit: false,
            held_out: None,
            note: c.note.clone(),
            out_of_range: c.oor.clone(),
            size: None,
        })
        .collect();
    let mut rank: Vec<usize> = (0..list.len()).filter(|&i| list[i].ident).collect();
    rank.sort_by(|&a, &b| {
        list[a]
            .p_lin
            .total_cmp(&list[b].p_lin)
            .then(list[b].f_lin.total_cmp(&list[a].f_lin))
    });
    let verdict = judge(run, &lin, sel, &cur_p, &list, &rank, &mut reports, thresh);
    if let Some((e, lay1, p1)) = verdict.named {
        let rep = reports.iter().find(|r| r.name == e.name());
        let detail = format!(
            "{} removes {:.1}% of the weighted residual (F {:.1}, p {:.1e} < {:.1e}); {}",
            e.name(),
            100.0 * rep.map(|r| r.improvement).unwrap_or(0.0),
            rep.map(|r| r.statistic).unwrap_or(0.0),
            rep.map(|r| r.p_value).unwrap_or(1.0),
            thresh,
            rep.and_then(|r| r.size.as_ref())
                .map_or(String::new(), |d| d.to_string())
        );
        let report = RoundReport {
            round,
            decision: Decision::Named,
            effect: Some(e),
            detail,
            candidates: reports,
            possible: None,
        };
        return (report, Some((e, lay1, p1)), cur_p);
    }
    let (dec, eff, detail) = match verdict.decision {
        Some(d) => d,
        None => no_effect_decision(
            run,
            sel,
            &cur_p,
            noise_known,
            &verdict,
            (alpha, n_ident, thresh),
        ),
    };
    let report = RoundReport {
        round,
        decision: dec,
        effect: eff,
        detail,
        candidates: reports,
        possible: verdict.possible,
    };
    (report, None, cur_p)
}
