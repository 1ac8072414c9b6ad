//! One sensor's norm fit: a faulty axis refused first, candidate models, the automatic choice
//! between them (or six positions for a handful of accelerometer poses), the acceptance checks,
//! and the robust pass without the magnetometer's outliers.

use super::accept::{
    blame_coverage, check_limits, failed, no_fit_reason, norm_fit_report, set_fail, SensorSpec,
};
use super::axisfault::axis_fault;
use super::outliers::{has_outliers, inliers};
use crate::calib::coverage::{coverage, Coverage};
use crate::calib::fit::{significantly_better, six_position, FitFailure, NormFit, NormFitOptions};
use crate::calib::model::{CalModel, Calibration, ModelKind};
use crate::calib::outcome::{CalStatus, Candidate, SensorCalibration, SensorResult};
use crate::calib::settings::ModelChoice;
use crate::types::{norm, Vec3};

fn empty_result(report: SensorCalibration, points: &[Vec3]) -> SensorResult {
    let c = coverage(points, &[0.0; 3]);
    SensorResult {
        report,
        calibration: None,
        coverage_before: c.clone(),
        coverage_after: c,
        dirs_before: vec![],
        dirs_after: vec![],
        residuals: vec![],
        held_out: vec![],
    }
}

/// Largest share of magnetometer points that may be outliers before the fit is refused as disturbed.
pub(crate) const MAX_OUTLIER_SHARE: f64 = 0.25;

/// Fit one sensor: a saturated or stuck axis is refused first ([`axis_fault`]); then candidate
/// models, automatic choice, acceptance checks ([`fit_sensor_on`]). When the magnetometer fit shows
/// outliers or failed, points off the field's ellipsoid (a magnet brought near the sensor, a motor
/// running) are found ([`inliers`]) and left out, and the fit is made again on the rest. When more
/// than [`MAX_OUTLIER_SHARE`] of the points are outliers, the fit is refused (`disturbed`): no
/// single field explains the data.
pub(crate) fn fit_sensor(points: &[Vec3], spec: &SensorSpec) -> SensorResult {
    if let Some(d) = axis_fault(points) {
        return empty_result(
            failed(spec.model.into(), spec.units, FitFailure::AxisFault, d),
            points,
        );
    }
    let (plain, sym9, _) = fit_sensor_with_sym9(points, spec);
    // A plain fit that failed on its residuals or numerically may have been pulled apart by a
    // disturbed cluster: look for outliers then too (and when its residuals passed only as the
    // sensor's noise: a noisy stream has its wild readings too).
    let noisy = plain.report.rms_residual > spec.limits.max_rms_ratio * plain.report.radius;
    let suspicious = has_outliers(&plain.residuals)
        || noisy
        || matches!(
            plain.report.failure,
            Some(
                FitFailure::Residuals
                    | FitFailure::DidNotConverge
                    | FitFailure::NotIdentifiable
                    | FitFailure::Radius
            )
        );
    // Too little of the sphere even before calibration: leaving points out cannot add any, so the
    // robust pass (several more fits, slow ones on a small cap) would only confirm the failure.
    let raw_coverage_short = plain.report.failure == Some(FitFailure::Coverage)
        && plain.coverage_before.filled < spec.limits.min_filled_regions;
    if spec.is_accel || points.len() < 30 || !suspicious || raw_coverage_short {
        return plain;
    }
    let (keep, rejected) = inliers(points, spec, sym9.as_ref());
    if rejected == 0 {
        return plain;
    }
    let share = rejected as f64 / points.len() as f64;
    if share > MAX_OUTLIER_SHARE {
        let mut r = plain;
        r.report.outliers_rejected = rejected;
        let d = format!(
            "{rejected} of {} points ({:.0}%) do not lie on one field ellipsoid: was a magnet, a motor or \
             metal near the sensor? Keep them away and rotate again",
            points.len(),
            100.0 * share
        );
        set_fail(&mut r.report, FitFailure::Disturbed, d);
        r.calibration = None;
        return r;
    }
    let mut r = fit_sensor_on(&keep, spec);
    r.report.outliers_rejected = rejected;
    r
}

/// Candidate models, automatic choice, acceptance checks, on the points as given.
fn fit_sensor_on(points: &[Vec3], spec: &SensorSpec) -> SensorResult {
    fit_sensor_with_sym9(points, spec).0
}

/// [`fit_sensor_on`], with its `sym9` candidate fit when it made one (the robust pass's first
/// look, [`inliers`]) and whether the fit was refused before it ran ([`undetermined`]).
fn fit_sensor_with_sym9(
    points: &[Vec3],
    spec: &SensorSpec,
) -> (SensorResult, Option<NormFit>, bool) {
    // The candidate fits share their set-up; its sphere fit is the centre for the "before" coverage.
    let mut fitter = crate::calib::fit::NormFitter::new(points);
    let raw_centre = fitter.sphere_centre().unwrap_or([0.0; 3]);
    let dirs_before: Vec<Vec3> = points
        .iter()
        .map(|p| {
            [
                p[0] - raw_centre[0],
                p[1] - raw_centre[1],
                p[2] - raw_centre[2],
            ]
        })
        .collect();
    let cov_before = coverage(&dirs_before, &[0.0; 3]);
    if let Some(detail) = undetermined(&fitter, &cov_before, spec) {
        let report = failed(
            spec.model.into(),
            spec.units,
            FitFailure::NotIdentifiable,
            detail,
        );
        let r = SensorResult {
            coverage_after: cov_before.clone(),
            dirs_after: dirs_before.clone(),
            coverage_before: cov_before,
            dirs_before,
            ..empty_result(report, &[])
        };
        // The robust pass ([`fit_sensor`]) still looks for readings off the field's ellipsoid
        // (a disturbance can scatter the rest): its first look is the sym9 fit the candidates
        // would have made.
        let sym9 = candidate_kinds(spec)
            .contains(&ModelKind::Sym9)
            .then(|| fitter.fit(ModelKind::Sym9, &candidate_options(spec)).ok())
            .flatten();
        return (r, sym9, true);
    }
    let fits = candidate_fits(&mut fitter, spec);
    let sym9 = fits
        .iter()
        .find(|f| f.calibration.model == ModelKind::Sym9)
        .cloned();
    let n = points.len();
    let mut candidates: Vec<Candidate> = fits
        .iter()
        .map(|f| Candidate {
            model: f.calibration.model.into(),
            rms_residual: f.rms_residual,
            params: f.calibration.model.n_params(),
            chosen: false,
        })
        .collect();
    let (cal, mut report) = if let Some(cal) = six_position_fit(points, spec) {
        (cal, six_position_report(points, &cal, spec, candidates))
    } else {
        let Some(ci) = choose_model(&fits, n) else {
            let (why, detail) = no_fit_reason(n, &cov_before, spec);
            let r = empty_result(failed(spec.model.into(), spec.units, why, detail), points);
            return (r, sym9, false);
        };
        candidates[ci].chosen = true;
        (
            fits[ci].calibration,
            norm_fit_report(&fits[ci], spec, candidates),
        )
    };
    let dirs_after: Vec<Vec3> = points.iter().map(|p| cal.apply(p)).collect();
    let residuals: Vec<f64> = dirs_after.iter().map(|c| norm(c) - report.radius).collect();
    let cov_after = coverage(&dirs_after, &[0.0; 3]);
    if report.status == CalStatus::Ok {
        check_limits(&mut report, &cal, &cov_after, spec);
    }
    blame_coverage(&mut report, &cov_before, spec);
    let calibration = (report.status == CalStatus::Ok).then_some(cal);
    let r = SensorResult {
        report,
        calibration,
        coverage_before: cov_before,
        coverage_after: cov_after,
        dirs_before,
        dirs_after,
        residuals,
        held_out: vec![],
    };
    (r, sym9, false)
}

/// Most a magnetometer's readings may scatter about the closest sphere, as a share of their
/// spread ([`crate::calib::fit::Outline`]), for a norm fit to be run on them. Readings that
/// outline a sphere, even a small cap of one, spread several times their scatter (a tumble by
/// hand: 0.05; the logs whose fits pass: at most 0.2); from about a half the readings are a blob
/// whose sphere, let alone ellipsoid, no fit determines: the iterations would run off or stop on
/// a shape the noise made (a hover log: 0.7, and every fit of it failed to converge).
pub(crate) const MAX_SCATTER_OF_SPREAD: f64 = 0.5;

/// Why a magnetometer's norm fit cannot be determined by `fitter`'s points, before it is run;
/// `None` when it can be tried. Only where the coverage suffices: short of it, the fit is
/// refused on the coverage as before.
fn undetermined(
    fitter: &crate::calib::fit::NormFitter,
    cov_before: &Coverage,
    spec: &SensorSpec,
) -> Option<String> {
    if spec.is_accel || cov_before.filled < spec.limits.min_filled_regions {
        return None;
    }
    let o = fitter.outline()?;
    let unit = if spec.units_known { " uT" } else { "" };
    (o.scatter > MAX_SCATTER_OF_SPREAD * o.spread).then(|| {
        format!(
            "the readings spread {:.2}{unit} across (their second-widest direction) and scatter {:.2}{unit} \
             about the closest sphere (radius {:.2}{unit}), need a spread of at least {:.0} times the \
             scatter: they outline no sphere, so no field ellipsoid is determined (the {} of 100 regions \
             they fill are the scatter's, about a centre among them); turn the vehicle through more \
             directions, away from magnets and running motors",
            o.spread,
            o.scatter,
            o.radius,
            1.0 / MAX_SCATTER_OF_SPREAD,
            cov_before.filled
        )
    })
}

/// The norm fits of the models `spec` asks for (every one for "auto"), those that succeed.
fn candidate_fits(fitter: &mut crate::calib::fit::NormFitter, spec: &SensorSpec) -> Vec<NormFit> {
    fitter
        .fit_each(&candidate_kinds(spec), &candidate_options(spec))
        .into_iter()
        .filter_map(Result::ok)
        .collect()
}

/// The models `spec` asks for (every one for "auto"), simplest first.
fn candidate_kinds(spec: &SensorSpec) -> Vec<ModelKind> {
    match spec.model {
        ModelChoice::Auto => vec![ModelKind::Sphere, ModelKind::Diag6, ModelKind::Sym9],
        m => m.kind().into_iter().collect(),
    }
}

fn candidate_options(spec: &SensorSpec) -> NormFitOptions {
    NormFitOptions {
        target_norm: spec.target_norm,
        ..Default::default()
    }
}

/// The simplest of `fits` (ordered simplest first) that a richer one does not beat significantly.
fn choose_model(fits: &[NormFit], n: usize) -> Option<usize> {
    let mut chosen: Option<usize> = if fits.is_empty() { None } else { Some(0) };
    for i in 1..fits.len() {
        let c = chosen.expect("set");
        let (a, b) = (&fits[c], &fits[i]);
        let extra = crate::calib::model::n_norm_params(b.calibration.model)
            - crate::calib::model::n_norm_params(a.calibration.model);
        if significantly_better(
            a.ssr_normalised,
            b.ssr_normalised,
            extra,
            n,
            crate::calib::model::n_norm_params(b.calibration.model),
        ) {
            chosen = Some(i);
        }
    }
    chosen
}

/// Six-position accelerometer calibration when asked, or when the log holds only a handful of
/// poses near the axes.
fn six_position_fit(points: &[Vec3], spec: &SensorSpec) -> Option<Calibration> {
    if spec.is_accel
        && (spec.model == ModelChoice::SixPosition
            || (spec.model == ModelChoice::Auto && points.len() < 12))
    {
        six_position(
            points,
            spec.target_norm
                .unwrap_or(crate::types::STANDARD_GRAVITY_MPS2),
            15.0,
        )
    } else {
        None
    }
}

/// The report of a six-position calibration, added to the norm fit `candidates` as the chosen one.
fn six_position_report(
    points: &[Vec3],
    cal: &Calibration,
    spec: &SensorSpec,
    mut candidates: Vec<Candidate>,
) -> SensorCalibration {
    let n = points.len();
    let g = spec
        .target_norm
        .unwrap_or(crate::types::STANDARD_GRAVITY_MPS2);
    let res: Vec<f64> = points.iter().map(|p| norm(&cal.apply(p)) - g).collect();
    let rms = (res.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
    candidates.push(Candidate {
        model: CalModel::SixPosition,
        rms_residual: rms,
        params: 12,
        chosen: true,
    });
    SensorCalibration {
        status: CalStatus::Ok,
        failure: None,
        detail: None,
        model: CalModel::SixPosition,
        units: spec.units,
        offset: cal.offset,
        matrix: cal.matrix,
        radius: g,
        rms_residual: rms,
        offset_sigma: [f64::NAN; 3],
        samples_used: n,
        iterations: 1,
        candidates,
        outliers_rejected: 0,
        method: None,
        mounting: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::pipeline::tests::gaussian;
    use crate::types::CalUnits;

    /// Readings that scatter about any sphere nearly as far as they spread (a hover: the field
    /// barely turns, the noise and the motors make the rest) are refused before any iteration,
    /// with their spread and scatter named; a tumble as noisy is fitted and passes.
    #[test]
    fn a_blob_of_readings_is_refused_before_fitting_and_a_tumble_is_not() {
        let mut gauss = gaussian(99);
        let limits = crate::calib::settings::AcceptConfig::default().mag;
        let spec = SensorSpec {
            model: ModelChoice::Auto,
            target_norm: None,
            units: CalUnits::Ut,
            units_known: true,
            limits: &limits,
            is_accel: false,
            noise: None,
        };
        let blob: Vec<Vec3> = (0..600)
            .map(|_| [20.0 + gauss(), -5.0 + gauss(), 40.0 + gauss()])
            .collect();
        let r = fit_sensor(&blob, &spec);
        assert_eq!(r.report.failure, Some(FitFailure::NotIdentifiable));
        assert_eq!(r.report.iterations, 0);
        assert!(r.report.candidates.is_empty());
        let why = r.report.detail.unwrap();
        assert!(why.contains("they outline no sphere"), "{why}");
        let tumble: Vec<Vec3> = (0..600)
            .map(|i| {
                let (a, b) = (i as f64 * 0.37, (i as f64 * 0.011).sin() * 1.4);
                [
                    10.0 + 50.0 * a.cos() * b.cos() + gauss(),
                    -20.0 + 45.0 * a.sin() * b.cos() + gauss(),
                    5.0 + 48.0 * b.sin() + gauss(),
                ]
            })
            .collect();
        let r = fit_sensor(&tumble, &spec);
        assert_eq!(r.report.status, CalStatus::Ok, "{:?}", r.report.detail);
    }
}
