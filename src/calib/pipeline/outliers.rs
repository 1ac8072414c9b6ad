//! Magnetometer readings off the field's ellipsoid (a magnet near the sensor, a motor running):
//! robust sigmas about a `sym9` fit, and a least-median-of-squares start that a disturbed cluster
//! cannot pull over.

use super::accept::SensorSpec;
use crate::calib::fit::{fit_norm, NormFit, NormFitOptions};
use crate::calib::model::ModelKind;
use crate::types::{norm, Vec3};

/// Which residuals lie within 4 robust sigmas (1.4826 MAD, at least `floor`) of the median, the
/// median and MAD taken over the residuals that `over` marks.
fn robust_inliers(residuals: &[f64], over: &[bool], floor: f64) -> Vec<bool> {
    let median = |mut v: Vec<f64>| -> f64 {
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
    };
    let sel: Vec<f64> = residuals
        .iter()
        .zip(over)
        .filter(|(_, k)| **k)
        .map(|(x, _)| *x)
        .collect();
    if sel.is_empty() {
        return over.to_vec();
    }
    let med = median(sel.clone());
    let thr = (4.0 * 1.4826 * median(sel.iter().map(|x| (x - med).abs()).collect())).max(floor);
    residuals.iter().map(|x| (x - med).abs() <= thr).collect()
}

/// Whether any residual of the plain fit lies outside 4 robust sigmas: on clean data none does and
/// the plain fit stands.
pub(crate) fn has_outliers(residuals: &[f64]) -> bool {
    residuals.len() >= 30
        && robust_inliers(residuals, &vec![true; residuals.len()], 0.0).contains(&false)
}

/// The points that `mask` marks.
fn masked(points: &[Vec3], mask: &[bool]) -> Vec<Vec3> {
    points
        .iter()
        .zip(mask)
        .filter(|(_, k)| **k)
        .map(|(p, _)| *p)
        .collect()
}

/// A `sym9` fit to the points `mask` marks, and all points classified against it
/// ([`robust_inliers`]).
fn sym9_inliers(
    points: &[Vec3],
    mask: &[bool],
    opts: &NormFitOptions,
) -> Option<(NormFit, Vec<bool>)> {
    let f = fit_norm(&masked(points, mask), ModelKind::Sym9, opts).ok()?;
    let inliers = classify(points, &f, mask);
    Some((f, inliers))
}

/// All points classified against the fit `f` to the points `mask` marks ([`robust_inliers`]).
fn classify(points: &[Vec3], f: &NormFit, mask: &[bool]) -> Vec<bool> {
    let r: Vec<f64> = points
        .iter()
        .map(|p| norm(&f.calibration.apply(p)) - f.radius)
        .collect();
    robust_inliers(&r, mask, 1e-9 * f.radius.abs())
}

/// The points within 4 robust sigmas of a `sym9` fit, and how many were not. The first look is a
/// fit to all points; when more than 0.5% fall outside, a least-median-of-squares fit
/// ([`lmeds_inliers`]), which a cluster of disturbed points (up to about 40%) cannot pull over, is a
/// second start. From each start: fit the inliers and reclassify all points, until the set stops
/// changing (at most 4 times) or a fit does not converge. Of the two, the one whose fit has the smaller median residual over
/// all points wins (the least-median criterion again: a random subset of the least-median search
/// can leave its start far off, and the plain start is the one a cluster pulls over).
/// `sym9`: the plain fit's own `sym9` candidate to all points, when it made one (the first look).
pub(crate) fn inliers(
    points: &[Vec3],
    spec: &SensorSpec,
    sym9: Option<&NormFit>,
) -> (Vec<Vec3>, usize) {
    let opts = NormFitOptions {
        target_norm: spec.target_norm,
        ..Default::default()
    };
    let all = vec![true; points.len()];
    let first = match sym9 {
        Some(f) => Some(classify(points, f, &all)),
        None => sym9_inliers(points, &all, &opts).map(|(_, m)| m),
    };
    let Some(first) = first else {
        return (points.to_vec(), 0);
    };
    let out = first.iter().filter(|k| !**k).count();
    if out == 0 {
        return (points.to_vec(), 0);
    }
    // The set the refinement settles on, with the sym9 fit to it when the last round made it. A
    // fit that did not converge (it ran off: the points it was given outline no ellipsoid) says
    // nothing about which points lie off the field's ellipsoid: the refinement stops there.
    let refine = |mut mask: Vec<bool>| -> (Vec<bool>, Option<NormFit>) {
        for _ in 0..4 {
            let Some((fit, new)) = sym9_inliers(points, &mask, &opts) else {
                break;
            };
            if new == mask || !fit.converged || new.iter().filter(|k| **k).count() < 12 {
                return (mask, Some(fit));
            }
            mask = new;
        }
        (mask, None)
    };
    // Median |residual| over all points of a sym9 fit to the marked ones (`fit`, when made).
    let median_residual = |(mask, fit): &(Vec<bool>, Option<NormFit>)| -> f64 {
        let fitted = match fit {
            Some(f) => Ok(f.clone()),
            None => fit_norm(&masked(points, mask), ModelKind::Sym9, &opts),
        };
        let Ok(f) = fitted else {
            return f64::INFINITY;
        };
        let mut r: Vec<f64> = points
            .iter()
            .map(|p| (norm(&f.calibration.apply(p)) - f.radius).abs() / f.radius.abs())
            .collect();
        let mid = r.len() / 2;
        let m = *r.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        if m.is_finite() {
            m
        } else {
            f64::INFINITY
        }
    };
    // The second start and its refinement run on a thread of their own beside the first's (each
    // a pure function of the points: the same sets as one after the other).
    let second = out as f64 > 0.005 * points.len() as f64;
    let (mut mask, lmeds) = std::thread::scope(|scope| {
        let lmeds = second.then(|| {
            scope.spawn(|| {
                let m = refine(lmeds_inliers(points)?);
                let r = median_residual(&m);
                Some((m, r))
            })
        });
        let mask = refine(first);
        let lmeds = lmeds.and_then(|h| {
            h.join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        });
        (mask, lmeds)
    });
    if let Some((m, r)) = lmeds {
        if r < median_residual(&mask) {
            mask = m;
        }
    }
    let keep = masked(points, &mask.0);
    let rejected = points.len() - keep.len();
    (keep, rejected)
}

/// Least median of squares: algebraic ellipsoid fits to random 12-point subsets (seeded, so
/// replays repeat), the one whose median squared norm residual over all points is smallest wins;
/// its inliers are the points within 2.5 robust sigmas. `None` when no subset gave an ellipsoid.
fn lmeds_inliers(points: &[Vec3]) -> Option<Vec<bool>> {
    use rand::{Rng, SeedableRng};
    let n = points.len();
    // Centre the points for a well-conditioned algebraic fit.
    let mut c = [0.0; 3];
    for p in points {
        for k in 0..3 {
            c[k] += p[k] / n as f64;
        }
    }
    let xs: Vec<Vec3> = points
        .iter()
        .map(|p| [p[0] - c[0], p[1] - c[1], p[2] - c[2]])
        .collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(n as u64);
    let resid = |st: &crate::calib::fit::Start, p: &Vec3| -> f64 {
        (st.shape * (nalgebra::Vector3::new(p[0], p[1], p[2]) - st.centre)).norm() - 1.0
    };
    let mut best: Option<(f64, crate::calib::fit::Start)> = None;
    let mut sq = vec![0.0; n];
    let mut subset = [[0.0; 3]; 12];
    for _ in 0..300 {
        for s in subset.iter_mut() {
            *s = xs[rng.random_range(0..n)];
        }
        let Some(st) = crate::calib::fit::ellipsoid_start(&subset) else {
            continue;
        };
        for (q, p) in sq.iter_mut().zip(&xs) {
            *q = resid(&st, p).powi(2);
        }
        let mid = n / 2;
        let (_, m, _) = sq.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
        let m = *m;
        if m.is_finite() && best.as_ref().is_none_or(|b| m < b.0) {
            best = Some((m, st));
        }
    }
    let (med, st) = best?;
    // Rousseeuw's robust scale for LMedS with p = 9 parameters.
    let sigma = 1.4826 * (1.0 + 5.0 / (n as f64 - 9.0).max(1.0)) * med.sqrt();
    Some(
        xs.iter()
            .map(|p| resid(&st, p).abs() <= 2.5 * sigma)
            .collect(),
    )
}
