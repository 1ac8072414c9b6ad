//! Cubics of temperature: a weighted least-squares fit on binned points, the same polynomial
//! written about another reference temperature, and the held-out score on alternate bands.

use nalgebra::{Matrix4, Vector4};

/// One temperature bin's mean of one channel: temperature (deg C), value (the channel's unit),
/// its standard error (same unit) and the samples in it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    pub temp_c: f64,
    pub value: f64,
    pub se: f64,
    pub n: usize,
}

/// A cubic in `(T - ref_c)`: `c[0] + c[1] x + c[2] x^2 + c[3] x^3`, `x = T - ref_c` in deg C,
/// `c[k]` in the channel's unit per deg C^k.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cubic {
    pub ref_c: f64,
    pub c: [f64; 4],
}

impl Cubic {
    /// The value at `temp_c`.
    pub fn eval(&self, temp_c: f64) -> f64 {
        let x = temp_c - self.ref_c;
        self.c[0] + x * (self.c[1] + x * (self.c[2] + x * self.c[3]))
    }

    /// The same polynomial in `(T - ref_c)` (exact re-expansion by the binomial theorem).
    pub fn about(&self, ref_c: f64) -> Cubic {
        // x_old = x_new + d with d = ref_c - self.ref_c.
        let d = ref_c - self.ref_c;
        let binom = [
            [1.0, 0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0, 0.0],
            [1.0, 2.0, 1.0, 0.0],
            [1.0, 3.0, 3.0, 1.0],
        ];
        let mut out = [0.0; 4];
        for (k, ck) in self.c.iter().enumerate() {
            for (j, o) in out.iter_mut().enumerate().take(k + 1) {
                *o += ck * binom[k][j] * d.powi((k - j) as i32);
            }
        }
        Cubic { ref_c, c: out }
    }
}

/// Weights of the points: 1 / se^2, the standard error floored at half the median one (so a
/// bin of few, accidentally alike samples cannot take the fit).
fn weights(points: &[Point]) -> Vec<f64> {
    let mut se: Vec<f64> = points
        .iter()
        .map(|p| p.se)
        .filter(|s| s.is_finite())
        .collect();
    se.sort_by(f64::total_cmp);
    let floor = se.get(se.len() / 2).copied().unwrap_or(1.0) * 0.5;
    points
        .iter()
        .map(|p| {
            let s = if p.se.is_finite() {
                p.se.max(floor)
            } else {
                floor
            };
            if s > 0.0 {
                1.0 / (s * s)
            } else {
                1.0
            }
        })
        .collect()
}

/// The weighted least-squares cubic through `points` (`degree` 0 to 3; higher terms 0), about
/// `ref_c`. Fitted in a scaled variable (the points' range mapped to -1..1) for conditioning.
/// `None` with fewer points than terms or a singular system.
pub fn fit(points: &[Point], degree: usize, ref_c: f64) -> Option<Cubic> {
    let terms = degree.min(3) + 1;
    if points.len() < terms {
        return None;
    }
    let (lo, hi) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| {
            (l.min(p.temp_c), h.max(p.temp_c))
        });
    let centre = 0.5 * (lo + hi);
    let half = (0.5 * (hi - lo)).max(1e-6);
    let w = weights(points);
    let mut a = Matrix4::<f64>::zeros();
    let mut b = Vector4::<f64>::zeros();
    for (p, wi) in points.iter().zip(&w) {
        let u = (p.temp_c - centre) / half;
        let mut v = [0.0; 4];
        let mut uk = 1.0;
        for vk in v.iter_mut().take(terms) {
            *vk = uk;
            uk *= u;
        }
        for r in 0..terms {
            b[r] += wi * v[r] * p.value;
            for c in 0..terms {
                a[(r, c)] += wi * v[r] * v[c];
            }
        }
    }
    for k in terms..4 {
        a[(k, k)] = 1.0;
    }
    let sol = crate::calib::lm::cholesky(&a)?.solve(&b);
    if !sol.iter().all(|x| x.is_finite()) {
        return None;
    }
    // In u = (T - centre) / half: c_k(T - centre) = s_k / half^k.
    let mut c = [0.0; 4];
    for (k, ck) in c.iter_mut().enumerate() {
        *ck = sol[k] / half.powi(k as i32);
    }
    Some(Cubic { ref_c: centre, c }.about(ref_c))
}

/// Residual RMS of the points about a curve (unweighted, the channel's unit).
pub fn rms_about(points: &[Point], f: impl Fn(f64) -> f64) -> f64 {
    if points.is_empty() {
        return f64::NAN;
    }
    let ss: f64 = points.iter().map(|p| (p.value - f(p.temp_c)).powi(2)).sum();
    (ss / points.len() as f64).sqrt()
}

/// The held-out score of a cubic on alternate temperature bands.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HeldOut {
    /// RMS of the held-out points about a constant fitted on the others (no temperature
    /// calibration), the channel's unit.
    pub before: f64,
    /// RMS of the held-out points about the cubic fitted on the others.
    pub after: f64,
    /// before / after.
    pub shrink: f64,
}

/// Fit on the bands of `band_c` whose index from the coldest point is even, score on the odd
/// ones, then the other way round; the two scores pooled. `None` when either half has fewer
/// than 4 points.
pub fn held_out(points: &[Point], band_c: f64) -> Option<HeldOut> {
    let lo = points
        .iter()
        .map(|p| p.temp_c)
        .fold(f64::INFINITY, f64::min);
    let band = |p: &Point| ((p.temp_c - lo) / band_c).floor() as i64 % 2;
    let (mut ss_before, mut ss_after, mut n) = (0.0, 0.0, 0usize);
    for parity in [0, 1] {
        let (train, test): (Vec<Point>, Vec<Point>) =
            points.iter().partition(|p| band(p) == parity);
        if train.len() < 4 || test.is_empty() {
            return None;
        }
        let constant = fit(&train, 0, lo)?;
        let cubic = fit(&train, 3, lo)?;
        for p in &test {
            ss_before += (p.value - constant.eval(p.temp_c)).powi(2);
            ss_after += (p.value - cubic.eval(p.temp_c)).powi(2);
        }
        n += test.len();
    }
    let before = (ss_before / n as f64).sqrt();
    let after = (ss_after / n as f64).sqrt();
    Some(HeldOut {
        before,
        after,
        shrink: if after > 0.0 {
            before / after
        } else {
            f64::INFINITY
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points_of(c: &Cubic, temps: impl Iterator<Item = f64>) -> Vec<Point> {
        temps
            .map(|t| Point {
                temp_c: t,
                value: c.eval(t),
                se: 1e-3,
                n: 100,
            })
            .collect()
    }

    #[test]
    fn a_cubic_is_the_same_about_another_reference() {
        let c = Cubic {
            ref_c: 35.0,
            c: [0.1, -2e-3, 3e-5, 4e-6],
        };
        let d = c.about(27.5);
        for t in [10.0, 20.0, 35.0, 41.0] {
            assert!((c.eval(t) - d.eval(t)).abs() < 1e-12, "{t}");
        }
        assert!((d.about(35.0).c[3] - c.c[3]).abs() < 1e-18);
    }

    #[test]
    fn an_exact_cubic_is_fitted_back_and_scores_the_noise_floor_held_out() {
        let truth = Cubic {
            ref_c: 35.0,
            c: [0.02, 1e-3, -4e-5, 2e-6],
        };
        let pts = points_of(&truth, (0..60).map(|k| 15.25 + 0.5 * k as f64));
        let f = fit(&pts, 3, 35.0).unwrap();
        for k in 0..4 {
            // Measured: 1e-17 at most (rounding).
            assert!((f.c[k] - truth.c[k]).abs() < 1e-12, "{k}: {:?}", f.c);
        }
        let h = held_out(&pts, 1.0).unwrap();
        assert!(h.after < 1e-12 && h.before > 1e-3, "{h:?}");
        assert!(fit(&pts[..3], 3, 35.0).is_none());
    }
}
