//! The centre of the magnetometer's sphere from buffered readings once they spread enough, before
//! a first fit places it: running sums, so the question costs no pass over the points.

use crate::calib::settings::AcceptLimits;
use crate::types::{norm, Vec3};
use nalgebra::Matrix3;

/// The centre of the sphere the points lie on, when they spread enough to place it: a sphere fits
/// them (RMS distance from it at most [`CENTRE_MAX_RMS_RADII`] radii), their standard deviation
/// along their narrowest direction is at least `min_spread_radii` of its radius, and with `limits`
/// (units known) the radius is within them. A still sensor's points (a small cluster, on which an
/// algebraic sphere fit gives a small sphere through the noise) never pass. `sums` are the points'
/// own, kept as they came: the sphere, its radius and the spread come from them, and only when
/// those pass are the points read (for the RMS distance).
pub(crate) fn centre_from_spread_with(
    points: &[Vec3],
    sums: &SpreadSums,
    min_spread_radii: f64,
    limits: Option<&AcceptLimits>,
) -> Option<Vec3> {
    let (c, r) = sums.sphere()?;
    if limits.is_some_and(|l| r < l.min_radius || r > l.max_radius) {
        return None;
    }
    if !(sums.min_sd() >= min_spread_radii * r) {
        return None;
    }
    let rms = (points
        .iter()
        .map(|p| (norm(&[p[0] - c[0], p[1] - c[1], p[2] - c[2]]) - r).powi(2))
        .sum::<f64>()
        / points.len() as f64)
        .sqrt();
    (rms <= CENTRE_MAX_RMS_RADII * r).then_some(c)
}

/// Running sums of field vectors (raw units): what the linear sphere fit's normal equations and
/// the points' covariance need, so asking whether buffered points place a centre costs no pass
/// over them.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SpreadSums {
    n: f64,
    /// Sum of x.
    s: [f64; 3],
    /// Sum of x x^T.
    sxx: [[f64; 3]; 3],
    /// Sum of x |x|^2.
    sx_r2: [f64; 3],
    /// Sum of |x|^2.
    s_r2: f64,
}

impl SpreadSums {
    pub(crate) fn of(points: &[Vec3]) -> Self {
        let mut s = SpreadSums::default();
        for p in points {
            s.add(p);
        }
        s
    }

    pub(crate) fn add(&mut self, p: &Vec3) {
        let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
        self.n += 1.0;
        self.s_r2 += r2;
        for i in 0..3 {
            self.s[i] += p[i];
            self.sx_r2[i] += p[i] * r2;
            for j in 0..3 {
                self.sxx[i][j] += p[i] * p[j];
            }
        }
    }

    /// The linear least-squares sphere |x|^2 = 2 c.x + k (design `[2x, 2y, 2z, 1]`, as
    /// [`crate::calib::fit::sphere_start`]): its centre and radius, when at least 4 points
    /// determine a finite, positive one.
    fn sphere(&self) -> Option<(Vec3, f64)> {
        if self.n < 4.0 {
            return None;
        }
        let mut ata = nalgebra::SMatrix::<f64, 4, 4>::zeros();
        let mut atb = nalgebra::SVector::<f64, 4>::zeros();
        for i in 0..3 {
            for j in 0..3 {
                ata[(i, j)] = 4.0 * self.sxx[i][j];
            }
            ata[(i, 3)] = 2.0 * self.s[i];
            ata[(3, i)] = 2.0 * self.s[i];
            atb[i] = 2.0 * self.sx_r2[i];
        }
        ata[(3, 3)] = self.n;
        atb[3] = self.s_r2;
        let st = crate::calib::fit::sphere_from_normal_equations(&ata, &atb)?;
        let r = 1.0 / st.shape[(0, 0)];
        (r.is_finite() && r > 0.0).then_some(([st.centre[0], st.centre[1], st.centre[2]], r))
    }

    /// The points' standard deviation along their narrowest direction (the square root of their
    /// covariance's smallest eigenvalue); 0 for no points.
    fn min_sd(&self) -> f64 {
        if self.n < 1.0 {
            return 0.0;
        }
        let mean = self.s.map(|v| v / self.n);
        let cov = Matrix3::from_fn(|i, j| self.sxx[i][j] / self.n - mean[i] * mean[j]);
        cov.symmetric_eigen().eigenvalues.min().max(0.0).sqrt()
    }
}

/// Largest RMS distance of the points from their sphere, in radii, for [`centre_from_spread_with`].
pub(crate) const CENTRE_MAX_RMS_RADII: f64 = 0.1;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::settings::CalibSettings;

    #[test]
    fn a_centre_only_from_points_spread_over_a_sphere() {
        let c = [12.0, -25.0, 40.0];
        // Directions within `max_deg` of +z, or on a circle (turned about one axis), radius 48 uT.
        let pts = |max_deg: f64, ring: bool| -> Vec<Vec3> {
            (0..600)
                .map(|i| {
                    let u = (i as f64 + 0.5) / 600.0;
                    let th = if ring {
                        90f64.to_radians()
                    } else {
                        (max_deg * u.sqrt()).to_radians()
                    };
                    let phi = if ring {
                        u * max_deg.to_radians()
                    } else {
                        i as f64 * 2.399_963
                    };
                    [
                        c[0] + 48.0 * th.sin() * phi.cos(),
                        c[1] + 48.0 * th.sin() * phi.sin(),
                        c[2] + 48.0 * th.cos(),
                    ]
                })
                .collect()
        };
        let limits = CalibSettings::default().accept.mag;
        let spread = CalibSettings::default().fit.centre_min_spread_radii;
        // A still sensor: noise about one reading (an algebraic sphere through the noise is small).
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let still: Vec<Vec3> = (0..600)
            .map(|_| {
                let mut f = || rng.random_range(-0.3..0.3);
                [c[0] + 30.0 + f(), c[1] + f(), c[2] + 40.0 + f()]
            })
            .collect();
        assert_eq!(centre_from_spread(&still, spread, Some(&limits)), None);
        // Units unknown (counts): still none, the noise lies on no sphere.
        assert_eq!(centre_from_spread(&still, spread, None), None);
        // Turned through a whole circle about one axis: the sphere is not determined.
        assert_eq!(
            centre_from_spread(&pts(360.0, true), spread, Some(&limits)),
            None
        );
        // A small cap (30 deg): not yet.
        assert_eq!(
            centre_from_spread(&pts(30.0, false), spread, Some(&limits)),
            None
        );
        // A cap reaching 75 deg from its middle: the centre.
        let got =
            centre_from_spread(&pts(75.0, false), spread, Some(&limits)).expect("spread enough");
        for k in 0..3 {
            assert!((got[k] - c[k]).abs() < 1e-6, "{got:?}");
        }
    }

    fn centre_from_spread(
        points: &[Vec3],
        min_spread_radii: f64,
        limits: Option<&AcceptLimits>,
    ) -> Option<Vec3> {
        centre_from_spread_with(points, &SpreadSums::of(points), min_spread_radii, limits)
    }

    /// The kept sums give the sphere of the point-by-point linear fit and the two-pass spread,
    /// on points far from the origin (raw counts with a large offset) as on field-sized ones.
    #[test]
    fn spread_sums_match_the_fit_on_the_points() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (offset, radius) in [
            ([12.0, -30.0, 5.0], 48.0),
            ([9000.0, -4000.0, 700.0], 600.0),
        ] {
            let pts: Vec<Vec3> = (0..3000)
                .map(|_| {
                    let (u, v): (f64, f64) = (
                        rng.random_range(-1.0..1.0),
                        rng.random_range(0.0..std::f64::consts::TAU),
                    );
                    let (s, n) = ((1.0 - u * u).sqrt(), rng.random_range(-0.01..0.01) * radius);
                    let r = radius + n;
                    [
                        offset[0] + r * s * v.cos(),
                        offset[1] + r * s * v.sin(),
                        offset[2] + 0.3 * r * u,
                    ]
                })
                .collect();
            let sums = SpreadSums::of(&pts);
            let (c, r) = sums.sphere().expect("a sphere");
            let st = crate::calib::fit::sphere_start(&pts).expect("a sphere");
            for k in 0..3 {
                // Measured: agree to about 1e-9 of the radius.
                assert!(
                    (c[k] - st.centre[k]).abs() < 1e-7 * radius,
                    "{c:?} {:?}",
                    st.centre
                );
            }
            assert!((r - 1.0 / st.shape[(0, 0)]).abs() < 1e-7 * radius);
            let n = pts.len() as f64;
            let mean = pts.iter().fold([0.0; 3], |a, p| {
                [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]
            });
            let mut cov = Matrix3::zeros();
            for p in &pts {
                let d = nalgebra::Vector3::new(p[0] - mean[0], p[1] - mean[1], p[2] - mean[2]);
                cov += d * d.transpose() / n;
            }
            let two_pass = cov.symmetric_eigen().eigenvalues.min().sqrt();
            // The flattened axis: about 0.17 radii.
            assert!(
                (sums.min_sd() - two_pass).abs() < 1e-9 * radius,
                "{} {two_pass}",
                sums.min_sd()
            );
        }
        assert_eq!(SpreadSums::default().sphere(), None);
        assert_eq!(SpreadSums::default().min_sd(), 0.0);
    }
}
