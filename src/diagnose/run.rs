//! The state the diagnosis rounds share ([`Run`]: the evidence, the fit and held-out units, the
//! noise per channel) with its fits and held-out test, and the model found so far ([`Selection`]).
use super::channel::{Ch, ALL_CH, NCH};
use super::decision::RoundReport;
use super::evidence::Evidence;
use super::layout::{decode, eval_units, residuals, tags, Ctx, Layout};
use super::stats::{mean_sd, t_sf};
use super::Effect;
use crate::calib::lm::LmFit;
use nalgebra::{DMatrix, DVector};
use std::collections::BTreeMap;

/// "Unexplained": residual variance above this multiple of the within-unit noise.
pub const EXCESS_RATIO: f64 = 4.0;
/// Most Jacobians of one Levenberg-Marquardt fit of the forward model.
const LM_MAX_ITER: usize = 60;
/// Floor of a channel's residual sd (weights), as a fraction of its within-unit noise sd.
const SD_FLOOR_PER_NOISE: f64 = 1e-4;
/// Largest lag-1 autocorrelation used to deflate the F-test (the estimate is clamped to it).
const MAX_AUTOCORR: f64 = 0.95;
/// Held-out check: the drop in squared residual must exceed this many sd of a spurious fit's...
const HELD_OUT_Z: f64 = 3.0;
/// ...or a paired one-sided t-test over the held-out groups must reach this p-value...
const HELD_OUT_P: f64 = 0.05;
/// ...over at least this many groups.
const MIN_T_TEST_GROUPS: usize = 3;

/// State shared by the rounds.
pub(super) struct Run<'a> {
    pub ctx: Ctx,
    pub ev: &'a Evidence,
    pub fit_units: Vec<usize>,
    pub hold_units: Vec<usize>,
    /// Expected noise (within-unit scatter) per channel and unit: sd_c / sqrt(n).
    pub noise_sd: [f64; NCH],
    /// Relative weight of each unit within a channel: sqrt(n / median n), clamped to [0.3, 3].
    pub rel: Vec<[f64; NCH]>,
}

impl Run<'_> {
    pub(super) fn noise(&self, ui: usize, c: Ch) -> f64 {
        let n = self.ev.units[ui].n[c.i()].max(1) as f64;
        self.noise_sd[c.i()] / n.sqrt()
    }

    pub(super) fn fit(
        &self,
        lay: &Layout,
        w: &[f64; NCH],
        units: &[usize],
        p0: DVector<f64>,
    ) -> LmFit {
        let f = |p: &[f64], out: &mut Vec<f64>| {
            out.clear();
            let md = decode(&self.ctx, lay, p);
            eval_units(&self.ctx, &md, self.ev, units, &mut |ui, c, r| {
                out.push(r * w[c.i()] * self.rel[ui][c.i()])
            });
        };
        crate::calib::lm::minimise(&f, p0, &lay.typ, LM_MAX_ITER)
    }

    /// Forward-difference Jacobian columns `cols` of the weighted fit-unit residuals at `p`
    /// (`r0` the residuals there).
    pub(super) fn jac_cols(
        &self,
        lay: &Layout,
        w: &[f64; NCH],
        p: &DVector<f64>,
        r0: &[f64],
        cols: &[usize],
    ) -> DMatrix<f64> {
        let f = |q: &[f64], out: &mut Vec<f64>| {
            let mut full = p.clone();
            for (c, v) in cols.iter().zip(q) {
                full[*c] = *v;
            }
            out.clear();
            let md = decode(&self.ctx, lay, full.as_slice());
            eval_units(&self.ctx, &md, self.ev, &self.fit_units, &mut |ui, c, r| {
                out.push(r * w[c.i()] * self.rel[ui][c.i()])
            });
        };
        let q0 = DVector::from_iterator(cols.len(), cols.iter().map(|&c| p[c]));
        let typ: Vec<f64> = cols.iter().map(|&c| lay.typ[c]).collect();
        crate::calib::lm::jacobian(&f, &q0, r0, &typ)
    }

    pub(super) fn jac(
        &self,
        lay: &Layout,
        w: &[f64; NCH],
        units: &[usize],
        p: &DVector<f64>,
    ) -> (DMatrix<f64>, Vec<f64>) {
        let f = |p: &[f64], out: &mut Vec<f64>| {
            out.clear();
            let md = decode(&self.ctx, lay, p);
            eval_units(&self.ctx, &md, self.ev, units, &mut |ui, c, r| {
                out.push(r * w[c.i()] * self.rel[ui][c.i()])
            });
        };
        let mut r0 = Vec::new();
        f(p.as_slice(), &mut r0);
        (crate::calib::lm::jacobian(&f, p, &r0, &lay.typ), r0)
    }

    /// Channel weights: 1 / residual RMS of each channel on the fit units (dof-corrected).
    pub(super) fn weights(&self, lay: &Layout, p: &DVector<f64>) -> [f64; NCH] {
        let md = decode(&self.ctx, lay, p.as_slice());
        let mut ss = [0.0; NCH];
        let mut nn = [0usize; NCH];
        eval_units(&self.ctx, &md, self.ev, &self.fit_units, &mut |ui, c, r| {
            ss[c.i()] += (r * self.rel[ui][c.i()]).powi(2);
            nn[c.i()] += 1;
        });
        let m = nn.iter().sum::<usize>() as f64;
        let corr = m / (m - lay.n as f64).max(1.0);
        let mut w = [0.0; NCH];
        for c in ALL_CH {
            let i = c.i();
            if nn[i] > 0 {
                let floor = SD_FLOOR_PER_NOISE * self.noise_sd[i] + 1e-15;
                let sd = (ss[i] / nn[i] as f64 * corr).sqrt().max(floor);
                w[i] = 1.0 / sd;
            }
        }
        w
    }

    /// Noise-normalised RMS over `units` (all channels), and per-channel physical RMS.
    pub(super) fn rms(&self, lay: &Layout, p: &DVector<f64>, units: &[usize]) -> (f64, [f64; NCH]) {
        let md = decode(&self.ctx, lay, p.as_slice());
        let mut tot = 0.0;
        let mut cnt = 0usize;
        let mut ss = [0.0; NCH];
        let mut nn = [0usize; NCH];
        eval_units(&self.ctx, &md, self.ev, units, &mut |ui, c, r| {
            let s = self.noise(ui, c).max(1e-300);
            tot += (r / s).powi(2);
            cnt += 1;
            ss[c.i()] += r * r;
            nn[c.i()] += 1;
        });
        let mut per = [f64::NAN; NCH];
        for i in 0..NCH {
            if nn[i] > 0 {
                per[i] = (ss[i] / nn[i] as f64).sqrt();
            }
        }
        ((tot / cnt.max(1) as f64).sqrt(), per)
    }

    /// Lag-1 autocorrelation of the alternative model's weighted residuals (each (channel, component)
    /// sequence in time order), averaged over channels with weights equal to each channel's share of
    /// the drop in squared residual from `cur` to `alt`: the channels the effect's evidence comes from.
    /// Smooth structure left in those channels means the units are not independent evidence.
    pub(super) fn autocorr(
        &self,
        w: &[f64; NCH],
        cur: (&Layout, &DVector<f64>),
        alt: (&Layout, &DVector<f64>),
    ) -> f64 {
        let weighted = |lay: &Layout, p: &DVector<f64>| {
            let tg = tags(&self.ctx, lay, p, self.ev, &self.fit_units);
            let res = residuals(&self.ctx, lay, self.ev, &self.fit_units, p.as_slice());
            tg.iter()
                .zip(&res)
                .map(|((ui, c, k), (_, r))| (*c, *k, r * w[c.i()] * self.rel[*ui][c.i()]))
                .collect::<Vec<_>>()
        };
        let a = weighted(cur.0, cur.1);
        let b = weighted(alt.0, alt.1);
        let mut drop = [0.0; NCH];
        for (x, y) in a.iter().zip(&b) {
            drop[x.0.i()] += x.2 * x.2 - y.2 * y.2;
        }
        let mut last: BTreeMap<(usize, usize), f64> = BTreeMap::new();
        let (mut num, mut den) = ([0.0; NCH], [0.0; NCH]);
        for (c, k, r) in &b {
            den[c.i()] += r * r;
            if let Some(prev) = last.insert((c.i(), *k), *r) {
                num[c.i()] += prev * r;
            }
        }
        let (mut acc, mut tot) = (0.0, 0.0);
        for i in 0..NCH {
            let d = drop[i].max(0.0);
            if d > 0.0 && den[i] > 0.0 {
                acc += d * (num[i] / den[i]).clamp(0.0, MAX_AUTOCORR);
                tot += d;
            }
        }
        if tot > 0.0 {
            (acc / tot).clamp(0.0, MAX_AUTOCORR)
        } else {
            0.0
        }
    }

    /// Does `alt` (q more parameters, fitted on m_fit components) beat `cur` on the held-out groups?
    /// Two tests, either suffices: the held-out drop D = S_cur - S_alt (weighted so that a component
    /// has unit variance under the current model) against its null distribution (a spurious q-parameter
    /// fit makes D about -q m_h / m_fit with sd 2 sqrt(q m_h / m_fit); we ask D > [`HELD_OUT_Z`] sd), or a
    /// paired one-sided t-test over the groups (p < [`HELD_OUT_P`], D > 0). Returns (holds, z of D, relative drop).
    pub(super) fn held_out(
        &self,
        w: &[f64; NCH],
        cur: (&Layout, &DVector<f64>),
        alt: (&Layout, &DVector<f64>),
        q: usize,
        m_fit: usize,
    ) -> (bool, f64, f64) {
        if self.hold_units.is_empty() {
            return (true, f64::NAN, f64::NAN);
        }
        let mut m_h = 0usize;
        {
            let md = decode(&self.ctx, cur.0, cur.1.as_slice());
            eval_units(&self.ctx, &md, self.ev, &self.hold_units, &mut |_, _, _| {
                m_h += 1
            });
        }
        let ratio = m_h as f64 / m_fit.max(1) as f64;
        let sd_null = 2.0 * (q as f64 * ratio).sqrt();
        let per_group = |lay: &Layout, p: &DVector<f64>| {
            let md = decode(&self.ctx, lay, p.as_slice());
            let mut g: BTreeMap<usize, f64> = BTreeMap::new();
            eval_units(
                &self.ctx,
                &md,
                self.ev,
                &self.hold_units,
                &mut |ui, c, r| {
                    *g.entry(self.ev.units[ui].group).or_insert(0.0) +=
                        (r * w[c.i()] * self.rel[ui][c.i()]).powi(2);
                },
            );
            g
        };
        let a = per_group(cur.0, cur.1);
        let b = per_group(alt.0, alt.1);
        let d: Vec<f64> = a
            .iter()
            .map(|(k, v)| v - b.get(k).copied().unwrap_or(0.0))
            .collect();
        let s0: f64 = a.values().sum();
        let s1: f64 = b.values().sum();
        let drop = if s0 > 0.0 { (s0 - s1) / s0 } else { 0.0 };
        let z = (s0 - s1) / sd_null.max(1e-12);
        if z > HELD_OUT_Z {
            return (true, z, drop);
        }
        if d.len() < MIN_T_TEST_GROUPS {
            return (false, z, drop);
        }
        let (m, sd) = mean_sd(&d);
        let t = if sd > 0.0 {
            m / (sd / (d.len() as f64).sqrt())
        } else if m > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
        let p = t_sf(t, d.len() as f64 - 1.0);
        (m > 0.0 && p < HELD_OUT_P, z, drop)
    }
}

/// The model found so far: effects named in order, the rounds' reports, the current layout and
/// parameters (fitted on the fit units).
pub(super) struct Selection {
    pub found: Vec<Effect>,
    pub rounds: Vec<RoundReport>,
    pub lay: Layout,
    pub p: DVector<f64>,
    /// The base model's start values (the pipeline's or the vector calibration): a second start
    /// of a candidate's refit when the first, from the current fit, ends implausible (a base fit
    /// that bent to absorb a large missing effect can hold the refit in its own minimum).
    pub start: (Layout, DVector<f64>),
}
