//! What a sensor's fit must look like, and the acceptance checks that name a failure when it
//! does not (coverage, radius, offsets, scaling, residuals, convergence).

use crate::calib::coverage::Coverage;
use crate::calib::fit::{FitFailure, NormFit};
use crate::calib::model::{CalModel, Calibration};
use crate::calib::outcome::{CalStatus, Candidate, SensorCalibration};
use crate::calib::settings::{AcceptLimits, ModelChoice};
use crate::types::CalUnits;

/// Which sensor a norm fit is for, and what its output must look like.
pub(crate) struct SensorSpec<'a> {
    pub(crate) model: ModelChoice,
    pub(crate) target_norm: Option<f64>,
    pub(crate) units: CalUnits,
    /// Check radius and offsets in physical units.
    pub(crate) units_known: bool,
    pub(crate) limits: &'a AcceptLimits,
    pub(crate) is_accel: bool,
    /// The stream's own noise per axis, same units ([`NoiseMeter`](super::NoiseMeter)).
    pub(crate) noise: Option<f64>,
}

pub(crate) fn failed(
    model: CalModel,
    units: CalUnits,
    failure: FitFailure,
    detail: String,
) -> SensorCalibration {
    SensorCalibration {
        failure: Some(failure),
        detail: Some(detail),
        ..SensorCalibration::new(CalStatus::Failed, model, units)
    }
}

/// Why no norm model could be fitted to `n` points.
pub(crate) fn no_fit_reason(
    n: usize,
    cov_before: &Coverage,
    spec: &SensorSpec,
) -> (FitFailure, String) {
    if n >= 7 && cov_before.filled < spec.limits.min_filled_regions {
        (
            FitFailure::Coverage,
            format!(
                "{} of 100 sphere regions filled, need {}",
                cov_before.filled, spec.limits.min_filled_regions
            ),
        )
    } else if n < 7 {
        (
            FitFailure::NotEnoughSamples,
            format!("{n} points; need at least 7 (more for richer models)"),
        )
    } else {
        (
            FitFailure::NotIdentifiable,
            format!("no model could be fitted to {n} points (all on a plane or a small cap?)"),
        )
    }
}

/// The report of the chosen norm fit `f`, failed when it did not converge or is not identifiable
/// (both come from the fit itself).
pub(crate) fn norm_fit_report(
    f: &NormFit,
    spec: &SensorSpec,
    candidates: Vec<Candidate>,
) -> SensorCalibration {
    let mut rep = SensorCalibration {
        status: CalStatus::Ok,
        failure: None,
        detail: None,
        model: f.calibration.model.into(),
        units: spec.units,
        offset: f.calibration.offset,
        matrix: f.calibration.matrix,
        radius: f.radius,
        rms_residual: f.rms_residual,
        offset_sigma: f.offset_sigma,
        samples_used: f.samples_used,
        iterations: f.iterations,
        candidates,
        outliers_rejected: 0,
        method: None,
        mounting: None,
    };
    if !f.converged {
        set_fail(
            &mut rep,
            FitFailure::DidNotConverge,
            format!(
                "no convergence in {} iterations: the readings do not outline an ellipsoid (too little turning, or a field that changed during the log); turn the vehicle through more directions, away from magnets and running motors",
                f.iterations
            ),
        );
    } else if !f.condition.is_finite()
        || f.condition > 1e12
        || f.offset_sigma.iter().any(|s| !(*s <= 0.05 * f.raw_radius))
    {
        set_fail(
            &mut rep,
            FitFailure::NotIdentifiable,
            format!("offset sigma {:?} vs radius {:.3}, condition {:.2e}: rotate through more orientations", f.offset_sigma, f.raw_radius, f.condition),
        );
    }
    rep
}

/// A fit that failed for numerical reasons on data that covers too little of the sphere failed
/// because of the coverage: say so, since that is what the user can fix.
pub(crate) fn blame_coverage(
    report: &mut SensorCalibration,
    cov_before: &Coverage,
    spec: &SensorSpec,
) {
    let numeric = matches!(
        report.failure,
        Some(FitFailure::DidNotConverge | FitFailure::NotIdentifiable)
    );
    if numeric && cov_before.filled < spec.limits.min_filled_regions {
        let d = format!(
            "{} of 100 sphere regions filled, need {}: rotate through the missing directions",
            cov_before.filled, spec.limits.min_filled_regions
        );
        set_fail(report, FitFailure::Coverage, d);
    }
}

pub(crate) fn set_fail(rep: &mut SensorCalibration, why: FitFailure, detail: String) {
    rep.status = CalStatus::Failed;
    rep.failure = Some(why);
    rep.detail = Some(detail);
}

/// What a radius outside the limits would be in another common unit: "; it looks like gauss:
/// scale mx, my, mz by 100 ..." when that unit brings it inside, else nothing.
fn unit_hint(radius: f64, is_accel: bool, lo: f64, hi: f64) -> String {
    let (fields, units): (&str, &[(&str, f64)]) = if is_accel {
        ("ax, ay, az", &[("g", 9.80665), ("mG", 0.00980665)])
    } else {
        (
            "mx, my, mz",
            &[("gauss", 100.0), ("mGauss", 0.1), ("nT", 0.001)],
        )
    };
    units
        .iter()
        .find(|(_, k)| (lo..=hi).contains(&(radius * k)))
        .map(|(u, k)| {
            format!("; it looks like {u}: scale {fields} by {k} (scales under [input.csv] for a CSV)")
        })
        .or_else(|| {
            // Raw counts: the factor that makes this radius the field (or gravity) expected.
            let expected = if is_accel { 9.80665 } else { 50.0 };
            (radius > hi).then(|| {
                format!(
                    "; if these are raw counts, scale {fields} by the sensor's sensitivity, about {expected}/{radius:.1} = {:.4} ({expected} {} expected; scales under [input.csv] for a CSV)",
                    expected / radius,
                    if is_accel { "m/s^2 of gravity" } else { "uT of earth field" }
                )
            })
        })
        .unwrap_or_default()
}

/// How far above the readings' noise (per axis) a fit's RMS residual may be and still be taken as
/// that noise: the radial component of white noise has the per-axis deviation, and a quarter more
/// leaves room for the noise estimate's own error and a model error well below the noise.
const NOISE_EXPLAINS: f64 = 1.25;

pub(crate) fn check_limits(
    rep: &mut SensorCalibration,
    cal: &Calibration,
    cov: &Coverage,
    spec: &SensorSpec,
) {
    let l = spec.limits;
    let nm = cal.normalised_matrix();
    if cov.filled < l.min_filled_regions {
        return set_fail(
            rep,
            FitFailure::Coverage,
            format!(
                "{} of 100 sphere regions filled, need {}: rotate through the missing directions",
                cov.filled, l.min_filled_regions
            ),
        );
    }
    if spec.units_known {
        // For accel the raw radius is the norm of the raw data (before scaling to g).
        let raw_radius = if spec.is_accel {
            rep.radius / cal.matrix3().determinant().abs().cbrt()
        } else {
            rep.radius
        };
        if raw_radius < l.min_radius || raw_radius > l.max_radius {
            return set_fail(
                rep,
                FitFailure::Radius,
                format!(
                    "field magnitude {raw_radius:.3} outside [{}, {}]{}",
                    l.min_radius,
                    l.max_radius,
                    unit_hint(raw_radius, spec.is_accel, l.min_radius, l.max_radius)
                ),
            );
        }
        if rep.offset.iter().any(|o| o.abs() > l.max_offset) {
            return set_fail(
                rep,
                FitFailure::Offsets,
                format!("offset {:?} beyond +-{}", rep.offset, l.max_offset),
            );
        }
    }
    for i in 0..3 {
        if nm[(i, i)] < l.min_diag || nm[(i, i)] > l.max_diag {
            return set_fail(
                rep,
                FitFailure::DiagonalScaling,
                format!(
                    "normalised diagonal {:.4} outside ({}, {})",
                    nm[(i, i)],
                    l.min_diag,
                    l.max_diag
                ),
            );
        }
        for j in 0..3 {
            if i != j && nm[(i, j)].abs() > l.max_offdiag {
                return set_fail(
                    rep,
                    FitFailure::DiagonalScaling,
                    format!(
                        "normalised off-diagonal {:.4} beyond +-{}",
                        nm[(i, j)],
                        l.max_offdiag
                    ),
                );
            }
        }
    }
    // A residual no larger than the readings' own noise is not a model error: the sensor is
    // noisy, and the fit is as good as its readings allow.
    let noise_explains = spec
        .noise
        .is_some_and(|sigma| rep.rms_residual <= NOISE_EXPLAINS * sigma);
    if rep.rms_residual > l.max_rms_ratio * rep.radius && noise_explains {
        rep.detail = Some(format!(
            "a noisy sensor: the RMS residual {:.4} is above {} x radius {:.4}, but no more than the readings' own noise ({:.4} per axis, from successive readings) explains",
            rep.rms_residual,
            l.max_rms_ratio,
            rep.radius,
            spec.noise.unwrap_or(f64::NAN)
        ));
    } else if rep.rms_residual > l.max_rms_ratio * rep.radius {
        set_fail(
            rep,
            FitFailure::Residuals,
            format!(
                "RMS residual {:.4} above {} x radius {:.4}",
                rep.rms_residual, l.max_rms_ratio, rep.radius
            ),
        )
    }
}
