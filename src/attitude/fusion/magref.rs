//! The magnetic reference (norm and dip) learnt from the data, and the disturbance test against it.

use super::FusionConfig;
use serde::{Deserialize, Serialize};

/// Magnetic disturbance settings: the norm and dip tests against the learnt reference (keys at
/// the top level of [`FusionConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MagRefConfig {
    /// Relative field-norm deviation from the reference that counts as disturbed. Default: 0.1
    /// (VQF's value).
    pub mag_norm_tol: f64,
    /// Dip deviation from the reference that counts as disturbed, degrees. Default: 10 (VQF's
    /// value).
    pub mag_dip_tol_deg: f64,
    /// Time constant of the reference norm/dip tracking while undisturbed, s. Default: 30
    /// (physical: longer than a disturbance approaching, so that it is not learnt; VQF uses 20).
    pub mag_ref_tau_s: f64,
    /// A steady new field is accepted as the reference after this long disturbed, s. Default: 20
    /// (tuned, held at VQF's value).
    pub mag_new_field_s: f64,
}

impl Default for MagRefConfig {
    fn default() -> Self {
        MagRefConfig {
            mag_norm_tol: 0.1,
            mag_dip_tol_deg: 10.0,
            mag_ref_tau_s: 30.0,
            mag_new_field_s: 20.0,
        }
    }
}

/// Reference field (norm, dip) and disturbance state.
#[derive(Debug, Clone, Default)]
pub(super) struct MagRef {
    /// Reference norm and dip (rad), once known.
    pub(super) norm: f64,
    pub(super) dip: f64,
    pub(super) known: bool,
    /// Time the reference has been learning, s.
    pub(super) learn_s: f64,
    /// Low-passed current norm and dip.
    cur_norm: f64,
    cur_dip: f64,
    cur_init: bool,
    /// Candidate new field and how long it has been steady while disturbed.
    cand_norm: f64,
    cand_dip: f64,
    cand_s: f64,
    pub(super) disturbed: bool,
    disturbed_s: f64,
}

pub(super) const MAG_CUR_TAU_S: f64 = 0.05;
pub(super) const MAG_CAND_TAU_S: f64 = 1.0;

impl MagRef {
    /// A reference restored from a saved state: norm (input units) and dip (rad), taken as learnt
    /// for `learn_s` seconds (so that it changes only slowly from here).
    pub(super) fn restored(norm: f64, dip: f64, learn_s: f64) -> Self {
        MagRef {
            norm,
            dip,
            known: true,
            learn_s,
            ..MagRef::default()
        }
    }

    /// Whether a field of this norm is undisturbed by the norm test alone (and the reference known).
    pub(super) fn norm_ok(&self, norm: f64, cfg: &FusionConfig) -> bool {
        self.known && (norm / self.norm - 1.0).abs() <= cfg.mag_ref.mag_norm_tol
    }

    /// Feed one field measurement (norm, dip in rad); returns whether the field is undisturbed.
    pub(super) fn update(&mut self, norm: f64, dip: f64, dt: f64, cfg: &FusionConfig) -> bool {
        let lp = |x: &mut f64, v: f64, tau: f64| *x += (v - *x) * (dt / tau.max(dt)).min(1.0);
        if !self.cur_init {
            self.cur_norm = norm;
            self.cur_dip = dip;
            self.cand_norm = norm;
            self.cand_dip = dip;
            self.cur_init = true;
        } else {
            lp(&mut self.cur_norm, norm, MAG_CUR_TAU_S);
            lp(&mut self.cur_dip, dip, MAG_CUR_TAU_S);
        }
        if !self.known {
            self.norm = self.cur_norm;
            self.dip = self.cur_dip;
            self.known = true;
            self.learn_s = 0.0;
        }
        let tol_dip = cfg.mag_ref.mag_dip_tol_deg.to_radians();
        let dev_n = (self.cur_norm / self.norm - 1.0).abs();
        let dev_d = (self.cur_dip - self.dip).abs();
        self.disturbed = !(dev_n <= cfg.mag_ref.mag_norm_tol && dev_d <= tol_dip);
        if !self.disturbed {
            // Learn: a running mean at first, then a slow low-pass.
            self.learn_s += dt;
            let tau = self.learn_s.min(cfg.mag_ref.mag_ref_tau_s);
            lp(&mut self.norm, self.cur_norm, tau);
            lp(&mut self.dip, self.cur_dip, tau);
            self.disturbed_s = 0.0;
            self.cand_s = 0.0;
            self.cand_norm = self.cur_norm;
            self.cand_dip = self.cur_dip;
        } else {
            self.disturbed_s += dt;
            // Is the field steady around a candidate?
            let steady = (self.cur_norm / self.cand_norm - 1.0).abs()
                <= cfg.mag_ref.mag_norm_tol * 0.5
                && (self.cur_dip - self.cand_dip).abs() <= tol_dip * 0.5;
            if steady {
                self.cand_s += dt;
            } else {
                self.cand_s = 0.0;
                self.cand_norm = self.cur_norm;
                self.cand_dip = self.cur_dip;
            }
            lp(&mut self.cand_norm, self.cur_norm, MAG_CAND_TAU_S);
            lp(&mut self.cand_dip, self.cur_dip, MAG_CAND_TAU_S);
            if self.cand_s >= cfg.mag_ref.mag_new_field_s {
                self.norm = self.cand_norm;
                self.dip = self.cand_dip;
                self.learn_s = 0.0;
                self.disturbed = false;
                self.disturbed_s = 0.0;
                self.cand_s = 0.0;
            }
        }
        !self.disturbed
    }
}
