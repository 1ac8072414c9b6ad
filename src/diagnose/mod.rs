//! `diagnose`: where the forward model (the fitted calibration) and the measured data disagree, which
//! missing effect explains the gap, and how far the gap shrinks once that effect is in the model.
//!
//! Pure: samples in, a [`DiagnosisReport`] (schema `imucald.diagnosis/1`) out; no I/O.
//!
//! # Evidence
//! The unit of evidence is the mean of a static segment, not a single sample (time series residuals are
//! autocorrelated and each sample's noise is not what the model is about):
//! * **static units**: the pipeline's static poses ([`crate::calib::gate`]) that are really still (accel
//!   direction spread <= [`MAX_STILL_SPREAD_DEG`], gyro scatter <= [`MAX_STILL_GYRO_RAD_S`]; the
//!   detector's automatic threshold, learned on a continuous tumble, passes slow rotations), each split
//!   where the motor driver (current when the log has it, else throttle) steps, so a bench run that steps
//!   the throttle at each attitude gives one unit per (attitude, level). Per unit the means of accel,
//!   mag, gyro, temperature, driver and reference attitude, and the within-unit scatter of every channel.
//! * **moving windows** (only when fewer than [`MIN_STATIC_MAG_UNITS`] static units carry the
//!   magnetometer, e.g. a continuous hand tumble such as the tyrex phone recordings, or an ordinary
//!   flight): [`WINDOW_S`] windows of the magnetometer samples outside static units; the unit's
//!   residual is the window mean of the per-sample field-magnitude residual (a rotation invariant,
//!   so motion does not matter) and, for the samples with a reference attitude, of their field
//!   directions turned into ENU (`vector_mag`), each sample keeping its own driver and
//!   temperature. Windows are grouped in blocks of [`WINDOW_BLOCK`] for the held-out split
//!   (neighbouring windows are not independent).
//!
//! With a reference attitude, a pose is still only while the attitude turns by at most
//! [`MAX_STILL_TURN_DEG`] (in flight a steady banked turn keeps accel and gyro steady as well).
//!
//! # Residual channels (what the model predicts each unit should have read)
//! `mag_norm` |calibrated field| - F (uT); `accel_norm` |calibrated accel| - g; `dip` the gravity-field
//! angle, g.m - sin(dip); `vector_accel`/`vector_mag` the calibrated vectors turned into ENU by the
//! reference attitude against up and the fitted earth-field direction (only with `ref_q`); `gyro` the
//! static gyro mean minus the bias. The base model (diag6 or sym9 mag and accel, dip, field direction,
//! gyro bias) is fitted jointly to all channels, starting from the pipeline's fits; when the log
//! has an attitude and a position (or `[place]`) and the vector calibration determines the offset
//! ([`crate::calib::magmethod`]), the magnetometer starts from that instead of the sphere fit (an
//! ordinary flight leaves the sphere without coverage). A candidate's refit that ends implausible
//! from the current fit is started again from these start values (a base fit bent by a large
//! missing effect can hold the refit in its own minimum).
//!
//! # Decisions (per round)
//! The current model (base + effects found so far) is fitted on the fit units; channel weights are the
//! channels' residual RMS (units within a channel weighted by sqrt of their sample count), so every
//! channel counts as noise of variance 1 under the current model. Each catalogue effect is a switchable
//! term with its own regressors: they are ranked by a linearised nested test at the current fit
//! (projecting out the current parameters; a regressor that does not vary or that the current model
//! absorbs makes the candidate not identifiable), then refitted jointly in that order. The
//! temperature term's lag is profiled first: of the lags [`TEMP_LAGS_S`], the one whose regressors
//! explain most of the current residual on the fit units; its time constant then counts as one
//! more parameter in both tests below. An effect is
//! **named** when
//! 1. the nested F-test on unit means has p < alpha / m (Bonferroni over the m identifiable candidates
//!    of the round); F and its denominator degrees of freedom are deflated by (1 - rho) / (1 + rho), rho
//!    the lag-1 autocorrelation (time order) of the refitted residuals in the channels the effect improves;
//! 2. it holds on held-out groups: the held-out drop in squared residual exceeds 3 sd of what a spurious
//!    fit of the same size gives, or a paired one-sided t-test over groups has p < 0.05;
//! 3. its fitted parameters are physically plausible (and the base calibration stays sane);
//! 4. the joint fit is well conditioned and no other significant candidate explains the same structure.
//!
//! Otherwise the round says **not_identifiable** (two significant candidates explain the same structure,
//! or the joint fit is degenerate), **unexplained** (some channel's residual variance is more than
//! [`EXCESS_RATIO`] x the noise expected from within-unit scatter, and no candidate explains it) or
//! **none**. Rounds repeat while an effect is named. `rms_before`/`rms_after` are the held-out RMS of
//! all residual components in units of their expected noise, for the base model and the final model
//! (both fitted on the fit units); the parameters in `effects` come from a final fit on all units.

//! # What this module owns, and what it must not touch
//! It owns the residual channels ([`channel`]), the evidence units ([`evidence`]), the forward model
//! with its catalogue of effects as switchable terms ([`layout`]), the tests ([`stats`]), the nested
//! selection rounds ([`rounds`]) with the record of what each decided ([`decision`]), and the
//! `imucald.diagnosis/1` report ([`report`]). It runs the calibration pipeline
//! ([`crate::calib::pipeline`]) for the static poses and the start fits, and solves with [`crate::calib::lm`]. It does
//! no I/O (the caller reads the log and writes the report) and knows nothing of tokio; it never
//! changes a calibration in use.

mod channel;
mod decision;
mod determined;
mod evidence;
pub mod fix;
mod follows;
mod judge;
mod layout;
mod plausible;
mod report;
mod rounds;
mod run;
mod screen;
mod stats;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_fix;
#[cfg(test)]
mod tests_mismatch;

pub use decision::{CandidateReport, Decision, Possible, RoundReport};
pub use determined::{Deciding, Determination, GroupSize, MIN_SIZE_SIGMAS};
pub use evidence::{
    MAX_STILL_GYRO_RAD_S, MAX_STILL_SPREAD_DEG, MAX_STILL_TURN_DEG, MIN_STATIC_MAG_UNITS,
    TEMP_LAGS_S, WINDOW_BLOCK, WINDOW_S,
};
pub use follows::{Follows, Reading, Regressor, ResidualTrace, MAX_NAMING_P, MIN_NAMING_R};
pub use plausible::{OutOfRange, SensorKind};
pub use report::{
    summary_table, ChannelRms, DiagnosisReport, EffectShrink, EvidenceSummary, ParamEstimate,
    ResidualSeries,
};
pub use run::EXCESS_RATIO;

use crate::calib::model::ModelKind;
use crate::config::Config;
use crate::types::Sample;
use serde::{Deserialize, Serialize};

/// The report's schema name.
pub const SCHEMA: &str = "imucald.diagnosis/1";
/// Family-wise significance level used when the options give one outside (0, 1).
pub const DEFAULT_ALPHA: f64 = 0.01;

// ---------------------------------------------------------------------------------------------
// Public API

/// The catalogue of effects the diagnosis can add to the forward model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Effect {
    /// Symmetric off-diagonal terms of the mag (and accel) matrix beyond a diag6 base.
    CrossAxis,
    /// A rotation between the magnetometer and accelerometer frames (seen in the dip).
    MagAccelMisalignment,
    /// Mag and accel biases linear in a first-order lag of the logged temperature, the time
    /// constant profiled over [`TEMP_LAGS_S`] (0: the temperature itself) and reported as `lag_s`.
    TemperatureBias,
    /// A field proportional to the motor driver: `m_raw += k * throttle` (or current), k in uT per unit.
    MotorInterference,
    /// A constant mounting yaw against the reference attitude.
    HeadingOffset,
    /// Per-axis cubic scale nonlinearity: sensed = v + c v^3 / |nominal|^2 (mag, and accel).
    ScaleNonlinearity,
    /// Gyro bias linear in time (and in temperature when it varies independently of time).
    GyroBiasDrift,
}

impl Effect {
    pub const ALL: [Effect; 7] = [
        Effect::CrossAxis,
        Effect::MagAccelMisalignment,
        Effect::TemperatureBias,
        Effect::MotorInterference,
        Effect::HeadingOffset,
        Effect::ScaleNonlinearity,
        Effect::GyroBiasDrift,
    ];
    pub fn name(self) -> &'static str {
        match self {
            Effect::CrossAxis => "cross_axis",
            Effect::MagAccelMisalignment => "mag_accel_misalignment",
            Effect::TemperatureBias => "temperature_bias",
            Effect::MotorInterference => "motor_interference",
            Effect::HeadingOffset => "heading_offset",
            Effect::ScaleNonlinearity => "scale_nonlinearity",
            Effect::GyroBiasDrift => "gyro_bias_drift",
        }
    }
    pub fn parse(s: &str) -> Option<Effect> {
        Effect::ALL.iter().copied().find(|e| e.name() == s)
    }
}

/// Options of [`diagnose`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DiagnoseOptions {
    /// Base calibration model: `diag6` (default; `cross_axis` is then a candidate) or `sym9`.
    pub base_model: ModelKind,
    /// Family-wise significance level of a round (Bonferroni over its candidates).
    pub alpha: f64,
    /// Fraction of groups (poses, window blocks) held out to check that an effect generalises.
    pub holdout_fraction: f64,
    /// Seed of the held-out split.
    pub seed: u64,
    /// Most effects to add.
    pub max_rounds: usize,
    /// Where and when the log was recorded, as the log says ([`crate::io::sources::Log::place`]):
    /// the earth field of the vector start. Default: nothing (the configuration's `[place]`, else
    /// today).
    #[serde(skip)]
    pub log_where: crate::types::LogWhere,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        DiagnoseOptions {
            base_model: ModelKind::Diag6,
            alpha: DEFAULT_ALPHA,
            holdout_fraction: 0.25,
            seed: 0,
            max_rounds: 4,
            log_where: Default::default(),
        }
    }
}

/// The base model the options ask for, as one the diagnosis fits (diag6 or sym9).
fn base_model(opts: &DiagnoseOptions, notes: &mut Vec<String>) -> ModelKind {
    let base = match opts.base_model {
        ModelKind::Diag6 | ModelKind::Sphere => ModelKind::Diag6,
        ModelKind::Sym9 | ModelKind::Full12 => ModelKind::Sym9,
    };
    if base != opts.base_model {
        notes.push(format!(
            "base model {} used as {}",
            opts.base_model.name(),
            base.name()
        ));
    }
    base
}

/// Diagnose a log: which effect missing from the calibration model explains what the data show.
pub fn diagnose(samples: &[Sample], cfg: &Config, opts: &DiagnoseOptions) -> DiagnosisReport {
    let mut notes = Vec::new();
    let base = base_model(opts, &mut notes);
    let alpha = if opts.alpha > 0.0 && opts.alpha < 1.0 {
        opts.alpha
    } else {
        DEFAULT_ALPHA
    };
    let prep = match rounds::prepare(samples, cfg, base, opts.log_where, &mut notes) {
        Ok(p) => p,
        Err(why) => return DiagnosisReport::failed(base, why),
    };
    let ev = &prep.ev;
    let start = match layout::context(ev, &prep.results, base, cfg.fit.gravity_mps2, &mut notes) {
        Ok(s) => s,
        Err(why) => return DiagnosisReport::failed(base, why),
    };
    let split = rounds::split_units(ev, opts, &mut notes);
    let mut run = run::Run::new(start.ctx, ev, &split);
    let lay0 = layout::build_layout(&run.ctx, &[]);
    let p0 = rounds::start_params(&run, &lay0, base, &start.m0, &start.a0);
    rounds::estimate_noise(&mut run, &lay0, &p0, &prep.rot);
    let (base_p, noise_known) = rounds::base_fit(&mut run, &lay0, p0.clone());
    let sel = rounds::select(
        &run,
        (&lay0, &p0),
        &base_p,
        &noise_known,
        alpha,
        opts.max_rounds,
    );
    report::assemble(&run, &split, base, (&lay0, &base_p), sel, notes)
}
