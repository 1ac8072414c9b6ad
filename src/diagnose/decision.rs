//! What one round of the search decided, as the `imucald.diagnosis/1` report carries it: the
//! decision, the effect it concerns and every candidate's tests. The rounds ([`super::rounds`])
//! fill these in; the report ([`super::report`]) collects them.

use super::determined::{Deciding, Determination};
use super::plausible::OutOfRange;
use super::Effect;
use serde::{Deserialize, Serialize};

/// One candidate effect of a round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandidateReport {
    pub name: String,
    /// F statistic of the nested test (joint refit when `refit`, else linearised at the current fit).
    pub statistic: f64,
    /// Uncorrected p-value of that test (compare with alpha / number of identifiable candidates).
    pub p_value: f64,
    /// Fraction of the current model's weighted squared residual (fit units) the effect removes.
    pub improvement: f64,
    pub plausible: bool,
    pub identifiable: bool,
    /// Number of parameters the effect adds.
    pub params: usize,
    /// Whether it was refitted jointly with the current model.
    pub refit: bool,
    /// Whether the improvement holds on the held-out groups (refitted candidates only).
    pub held_out: Option<bool>,
    pub note: String,
    /// Why the fitted (or, before a refit, the linearised) parameters are outside their physical
    /// range; empty when inside.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub out_of_range: Vec<OutOfRange>,
    /// How well the refit determines the effect's size (refitted candidates only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size: Option<Determination>,
}

/// An effect that passed every test but whose size the data do not determine: it might be there,
/// and this is the data that would decide it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Possible {
    pub effect: Effect,
    pub size: Determination,
    pub decide_with: Deciding,
}

/// How a round of the search ended: "named", "none", "unexplained" or "not_identifiable" in the
/// report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// An effect passed every test and joins the model.
    Named,
    /// No candidate is significant (or the significant ones failed a check), and no channel's
    /// residual is well above its noise.
    #[serde(rename = "none")]
    NoEffect,
    /// Nothing named, but some channel's residual variance is well above its noise.
    Unexplained,
    /// A significant candidate cannot be told apart: a degenerate joint fit, or collinear with
    /// another candidate.
    NotIdentifiable,
}

impl Decision {
    /// The report's name of the decision.
    pub fn name(self) -> &'static str {
        match self {
            Decision::Named => "named",
            Decision::NoEffect => "none",
            Decision::Unexplained => "unexplained",
            Decision::NotIdentifiable => "not_identifiable",
        }
    }
}

impl std::fmt::Display for Decision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One round of the search.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundReport {
    pub round: usize,
    pub decision: Decision,
    /// The effect named (or the one that could not be told apart, for not_identifiable).
    pub effect: Option<Effect>,
    pub detail: String,
    pub candidates: Vec<CandidateReport>,
    /// The effect that might be there (passed every test, size not determined), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub possible: Option<Possible>,
}

/// A unit as the terminal shows it: a dimensionless one (`1` in the report) as nothing.
pub(super) fn shown_unit(u: &str) -> &str {
    if u == "1" {
        ""
    } else {
        u
    }
}
