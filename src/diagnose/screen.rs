//! The linearised screen of a round: the current model's Jacobian with every remaining candidate
//! appended at zero, each candidate's lag profiled, its identifiability, and its linearised nested
//! test (the rank order of the refits, [`super::judge`]).

use super::channel::NCH;
use super::layout::{applicable, build_layout, carry_params, Layout};
use super::plausible::{out_of_range, render};
use super::run::{Run, Selection};
use super::stats::{columns, explained, nested_f, select_cols};
use super::Effect;
use crate::calib::lm::LmFit;
use nalgebra::{DMatrix, DVector};

/// A regressor column with norm below this (relative to 1 + |r|) does not vary.
const MIN_REGRESSOR_NORM: f64 = 1e-12;
/// A regressor whose normalised column keeps less than this norm after projecting out the current
/// model is absorbed by it (collinear, or poor coverage).
const MIN_RESIDUAL_REGRESSOR: f64 = 0.03;
/// Largest condition number of a candidate's projected regressors.
const MAX_CANDIDATE_CONDITION: f64 = 1e3;

/// The current model linearised with every remaining candidate appended at zero: one Jacobian for
/// the ranking.
pub(super) struct Linearised {
    /// Channel weights of the round.
    pub w: [f64; NCH],
    /// Weighted sum of squares of the current fit, its component count and parameter count.
    pub s0: f64,
    pub m: usize,
    pub p_cur: usize,
    pub lay_all: Layout,
    pub j_all: DMatrix<f64>,
    pub r_vec: DVector<f64>,
    /// Columns of the current model (base and effects found).
    pub base_cols: Vec<usize>,
    /// Sum of squares the current model's columns explain, and an orthonormal basis of them.
    pub ex0: f64,
    u0: DMatrix<f64>,
    /// The candidates whose lag was chosen in this round by profiling (the time constant then
    /// counts as one more parameter in the tests).
    lag_profiled: Vec<Effect>,
}

/// A candidate after the linearised screen.
pub(super) struct Cand {
    pub e: Effect,
    pub q: usize,
    pub ident: bool,
    pub plaus: bool,
    pub note: String,
    /// Out-of-range records of the linearised step.
    pub oor: Vec<super::plausible::OutOfRange>,
    pub ds_lin: f64,
    pub f_lin: f64,
    pub p_lin: f64,
    pub cols: Vec<usize>,
}

impl Cand {
    fn rejected(e: Effect, q: usize, note: String, cols: Vec<usize>) -> Cand {
        Cand {
            e,
            q,
            ident: false,
            plaus: false,
            note,
            oor: vec![],
            ds_lin: 0.0,
            f_lin: 0.0,
            p_lin: 1.0,
            cols,
        }
    }
}
pub(super) fn linearise(
    run: &Run,
    sel: &Selection,
    cur_p: &DVector<f64>,
    w: [f64; NCH],
    cur: &LmFit,
) -> Linearised {
    let cands: Vec<Effect> = Effect::ALL
        .iter()
        .copied()
        .filter(|e| !sel.found.contains(e))
        .collect();
    let mut all_effects = sel.found.clone();
    all_effects.extend(cands.iter().copied());
    let mut lay_all = build_layout(&run.ctx, &all_effects).with_lags_of(&sel.lay);
    let p_all = carry_params(&sel.lay, cur_p, &lay_all);
    let (mut j_all, r_all) = run.jac(&lay_all, &w, &run.fit_units.clone(), &p_all);
    let r_vec = DVector::from_column_slice(&r_all);
    let base_cols: Vec<usize> = (0..sel.lay.n_base)
        .chain(sel.found.iter().flat_map(|e| columns(&lay_all, *e)))
        .collect();
    let j0 = select_cols(&j_all, &base_cols);
    let (ex0, u0) = explained(&j0, &r_vec);
    let lag_profiled: Vec<Effect> = cands
        .iter()
        .copied()
        .filter(|&e| lay_all.lag_of(e).is_some() && applicable(&run.ctx, e).is_ok())
        .collect();
    for &e in &lag_profiled {
        let (k, x) = profile_lag(run, &w, e, (&lay_all, &p_all), (&j_all, &r_all), &base_cols);
        let cols = columns(&lay_all, e);
        for (c, &col) in cols.iter().enumerate() {
            j_all.set_column(col, &x.column(c));
        }
        lay_all = lay_all.with_lag(e, k);
    }
    Linearised {
        w,
        s0: cur.ssr,
        m: cur.r.len(),
        p_cur: sel.lay.n,
        lay_all,
        j_all,
        r_vec,
        base_cols,
        ex0,
        u0,
        lag_profiled,
    }
}

/// The lag of effect `e`'s grid ([`super::evidence::TEMP_LAGS_S`], [`super::evidence::DRIVER_LAGS_S`])
/// whose regressors explain most of the current residual beyond the current model's columns (the
/// time constant is profiled on the fit units, as least squares would fit it), with the effect's
/// Jacobian columns at that lag.
fn profile_lag(
    run: &Run,
    w: &[f64; NCH],
    e: Effect,
    (lay_all, p_all): (&Layout, &DVector<f64>),
    (j_all, r0): (&DMatrix<f64>, &[f64]),
    base_cols: &[usize],
) -> (usize, DMatrix<f64>) {
    let cols = columns(lay_all, e);
    let r_vec = DVector::from_column_slice(r0);
    let j_base = select_cols(j_all, base_cols);
    let mut best: Option<(f64, usize, DMatrix<f64>)> = None;
    let n_lags = lay_all.lag_of(e).map_or(1, |l| l.0);
    for k in 0..n_lags {
        let lay_k = lay_all.clone().with_lag(e, k);
        let x = run.jac_cols(&lay_k, w, p_all, r0, &cols);
        let mut jb = j_base
            .clone()
            .resize_horizontally(base_cols.len() + cols.len(), 0.0);
        for c in 0..cols.len() {
            jb.set_column(base_cols.len() + c, &x.column(c));
        }
        let (ex, _) = explained(&jb, &r_vec);
        if best.as_ref().is_none_or(|b| ex > b.0) {
            best = Some((ex, k, x));
        }
    }
    match best {
        Some((_, k, x)) => (k, x),
        None => (0, select_cols(j_all, &cols)),
    }
}

/// Identifiability of a candidate's regressors `x`: each must vary and must not be absorbed by the
/// current model. Err: why not.
fn identifiable(lin: &Linearised, cols: &[usize], x: &DMatrix<f64>) -> Result<(), String> {
    let q = cols.len();
    let mut xn = x.clone();
    for c in 0..q {
        let s = xn.column(c).norm();
        if !(s > MIN_REGRESSOR_NORM * (1.0 + lin.r_vec.norm())) {
            return Err(format!(
                "regressor {} has no variation",
                lin.lay_all.names[cols[c]].0
            ));
        }
        xn.column_mut(c).scale_mut(1.0 / s);
    }
    let px = &xn - &lin.u0 * (lin.u0.transpose() * &xn);
    let mut worst = f64::INFINITY;
    let mut worst_c = 0;
    for c in 0..q {
        let r = px.column(c).norm();
        if r < worst {
            worst = r;
            worst_c = c;
        }
    }
    let sv = px.clone().svd(false, false).singular_values;
    let cond = sv.max() / sv.min().max(1e-300);
    if worst < MIN_RESIDUAL_REGRESSOR {
        Err(format!(
            "regressor {} is absorbed by the current model (collinear or poor coverage)",
            lin.lay_all.names[cols[worst_c]].0
        ))
    } else if cond > MAX_CANDIDATE_CONDITION {
        Err(format!(
            "collinear regressors (condition {cond:.1e}): poor coverage"
        ))
    } else {
        Ok(())
    }
}

/// The linearised nested test of candidate `e` at the current fit.
pub(super) fn screen(
    run: &Run,
    lin: &Linearised,
    sel: &Selection,
    cur_p: &DVector<f64>,
    e: Effect,
) -> Cand {
    let cols = columns(&lin.lay_all, e);
    if let Err(why) = applicable(&run.ctx, e) {
        return Cand::rejected(e, 0, why, cols);
    }
    let x = select_cols(&lin.j_all, &cols);
    // A profiled time constant is one more parameter.
    let q = cols.len() + usize::from(lin.lag_profiled.contains(&e));
    if let Err(note) = identifiable(lin, &cols, &x) {
        return Cand::rejected(e, q, note, cols);
    }
    let mut bc = lin.base_cols.clone();
    bc.extend(cols.iter().copied());
    let jb = select_cols(&lin.j_all, &bc);
    let (ex1, _) = explained(&jb, &lin.r_vec);
    let ds = (ex1 - lin.ex0).max(0.0);
    // Linearised parameter step, for a first plausibility check.
    let mut effs = sel.found.clone();
    effs.push(e);
    let lay1 = build_layout(&run.ctx, &effs).with_lags_of(&lin.lay_all);
    let mut p1 = carry_params(&sel.lay, cur_p, &lay1);
    if let Ok(step) = jb.clone().svd(true, true).solve(&(-&lin.r_vec), 1e-10) {
        if step.len() == lay1.n {
            p1 += step;
        }
    }
    let oor = out_of_range(&run.ctx, &lay1, &p1, e);
    let plaus_lin = oor.is_empty();
    let note = if plaus_lin {
        String::new()
    } else {
        format!(
            "linearised estimate outside its physical range: {}",
            render(&oor)
        )
    };
    let s1 = (lin.s0 - ds).max(1e-300);
    let (f, pl) = nested_f(ds, s1, q, lin.m as f64 - (lin.p_cur + q) as f64, 1.0);
    Cand {
        e,
        q,
        ident: true,
        plaus: plaus_lin,
        note,
        oor,
        ds_lin: ds,
        f_lin: f,
        p_lin: pl,
        cols,
    }
}
