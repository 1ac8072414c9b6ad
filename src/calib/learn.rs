//! Continuous vector calibration for the live service: every magnetometer reading that arrives
//! with the vehicle's attitude is added to the sums of the vector fit ([`crate::calib::vector`]),
//! so an ordinary flight calibrates the compass as it goes, with no tumble and no stored points.
//!
//! Per reading (the first with each new attitude, at most one every
//! [`LearnSettings::min_interval_s`]): the earth field at the
//! vehicle's position (its GPS fix, else `[place]`; the World Magnetic Model, evaluated again only
//! when the vehicle has moved more than [`FIELD_REFRESH_KM`]) is turned into body axes by the
//! attitude and added, with the reading, to a [`VectorAccumulator`]. Older readings are discounted
//! with the time constant [`LearnSettings::memory_s`] (recursive least squares with exponential
//! forgetting), so a compass whose hard iron changes (a payload fitted) is followed. A second
//! accumulator carries the current term; it is used once the current has varied by
//! [`crate::calib::vector::MIN_CURRENT_SD_A`].
//!
//! [`VectorLearner::offer`] solves the sums (a 4x4 or 5x5 eigen-decomposition, microseconds) and
//! offers the result only when the attitudes seen determine the offset (`offset_identifiable`):
//! what they cannot determine is never installed.
//!
//! Pure: no I/O, no clock; times are handed in.

use crate::attitude::Place;
use crate::calib::vector::{VectorAccumulator, VectorFailure, VectorFit, VectorPoint};
use crate::types::{GeoPoint, Vec3};

/// The learner's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LearnSettings {
    /// Shortest time between two readings added, s. Readings closer together add little but
    /// correlation. Default: 0.1 (10 Hz, the rate flight controllers stream their attitude at).
    pub min_interval_s: f64,
    /// Time constant of the discount of older readings, s: a reading's weight falls by e every
    /// `memory_s`. Default: 1800 (half an hour of flight).
    pub memory_s: f64,
    /// Scale of the current regressor, A (the largest current expected; only conditions the sums).
    /// Default: 100.
    pub current_scale_a: f64,
}

impl LearnSettings {
    pub(crate) const DEFAULT: LearnSettings = LearnSettings {
        min_interval_s: 0.1,
        memory_s: 1800.0,
        current_scale_a: 100.0,
    };
}

impl Default for LearnSettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// The earth field is evaluated again when the vehicle is this far from where it last was, km
/// (the field changes by well under 0.1 % over it).
pub(crate) const FIELD_REFRESH_KM: f64 = 20.0;

/// The earth field where it was last evaluated.
#[derive(Debug, Clone, PartialEq)]
struct FieldAt {
    lat_deg: f64,
    lon_deg: f64,
    b_ned_ut: Vec3,
    total_ut: f64,
    /// "GPS" or "[place]".
    source: &'static str,
}

/// Running mean and variance of the current, discounted like the sums.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct CurrentSpread {
    w: f64,
    sum: f64,
    sum_sq: f64,
}

impl CurrentSpread {
    fn sd(&self) -> f64 {
        if self.w <= 1.0 {
            return 0.0;
        }
        let m = self.sum / self.w;
        (self.sum_sq / self.w - m * m).max(0.0).sqrt()
    }
}

/// Continuous vector calibration of one compass (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct VectorLearner {
    settings: LearnSettings,
    field: Option<FieldAt>,
    plain: Option<VectorAccumulator>,
    with_current: Option<VectorAccumulator>,
    current: CurrentSpread,
    last_t_s: Option<f64>,
    /// The attitude of the last reading added: a reading is added only with a new attitude, the
    /// first after it arrives (the pairing with the least lag; a later reading with the same,
    /// older attitude would see the turns late).
    last_q: Option<nalgebra::UnitQuaternion<f64>>,
    /// Readings refused because the earth field could not be evaluated.
    pub no_field: u64,
    /// The date (`YYYY-MM-DD`) of the field when `[place]` gives none: the day the service
    /// started, handed in ([`VectorLearner::on_date`]); the learner reads no clock.
    date: Option<String>,
}

/// A result the learner offers, with where its field came from.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Offer {
    pub fit: VectorFit,
    /// "GPS (lat, lon), 48.3 uT" or "[place] (...)".
    pub field_from: String,
}

impl VectorLearner {
    pub fn new(settings: LearnSettings) -> Self {
        VectorLearner {
            settings,
            field: None,
            plain: None,
            with_current: None,
            current: CurrentSpread::default(),
            last_t_s: None,
            last_q: None,
            no_field: 0,
            date: None,
        }
    }

    /// The learner evaluating the field on `date` (`YYYY-MM-DD`) where `[place]` gives no date.
    pub(crate) fn on_date(mut self, date: &str) -> Self {
        self.date = Some(date.to_string());
        self
    }

    /// Add a reading: `body_mag_ut` (body axes, before calibration, uT) at `t_s` with the
    /// attitude `body_ned` (body -> NED). `position` is the vehicle's fix when it has one, else
    /// `place` is used; with neither nothing is added. Returns whether the reading was added.
    pub fn push(
        &mut self,
        t_s: f64,
        body_mag_ut: &Vec3,
        body_ned: &nalgebra::UnitQuaternion<f64>,
        current_a: Option<f64>,
        position: Option<GeoPoint>,
        place: Option<&Place>,
    ) -> bool {
        if self.last_q == Some(*body_ned) {
            return false;
        }
        if let Some(last) = self.last_t_s {
            // A tenth of slack: readings at exactly the interval (10 Hz attitude) all count.
            if t_s >= last && t_s - last < 0.9 * self.settings.min_interval_s {
                return false;
            }
        }
        let Some((b_ned_ut, total)) = self
            .field_at(position, place)
            .map(|f| (f.b_ned_ut, f.total_ut))
        else {
            return false;
        };
        let dt = self.last_t_s.map_or(0.0, |l| (t_s - l).max(0.0));
        self.last_t_s = Some(t_s);
        self.last_q = Some(*body_ned);
        let keep = (-dt / self.settings.memory_s.max(1e-9)).exp();
        let p = VectorPoint {
            raw_ut: *body_mag_ut,
            expected_ut: crate::calib::vector::expected_field(body_ned, &b_ned_ut),
            current_a: current_a.filter(|c| c.is_finite()),
        };
        let plain = self
            .plain
            .get_or_insert_with(|| VectorAccumulator::new(total, None).expect("field > 0"));
        plain.forget(keep);
        let added = plain.push(&p);
        if let Some(c) = p.current_a {
            let scale = self.settings.current_scale_a;
            let acc = self.with_current.get_or_insert_with(|| {
                VectorAccumulator::new(total, Some(scale)).expect("field > 0")
            });
            acc.forget(keep);
            acc.push(&p);
            let cs = &mut self.current;
            (cs.w, cs.sum, cs.sum_sq) = (
                cs.w * keep + 1.0,
                cs.sum * keep + c,
                cs.sum_sq * keep + c * c,
            );
        }
        added
    }

    /// The field at the vehicle's position (or `place`), evaluated again when it moved far.
    fn field_at(&mut self, position: Option<GeoPoint>, place: Option<&Place>) -> Option<&FieldAt> {
        let (lat, lon, source, date) = match (position, place) {
            (Some(p), _) if p.lat_deg.is_finite() && p.lon_deg.is_finite() => (
                p.lat_deg,
                p.lon_deg,
                "GPS",
                place.and_then(|pl| pl.date.clone()),
            ),
            (_, Some(pl)) => (
                pl.latitude_deg,
                pl.longitude_deg,
                "[place]",
                pl.date.clone(),
            ),
            _ => return None,
        };
        let fresh = self.field.as_ref().is_some_and(|f| {
            f.source == source && distance_km(f.lat_deg, f.lon_deg, lat, lon) < FIELD_REFRESH_KM
        });
        if !fresh {
            let mut at = Place::at(lat, lon);
            at.date = date.or_else(|| self.date.clone());
            match crate::attitude::earth_field(&at) {
                Ok(f) if f.total_ut > 0.0 => {
                    self.field = Some(FieldAt {
                        lat_deg: lat,
                        lon_deg: lon,
                        b_ned_ut: f.field_ned_ut(),
                        total_ut: f.total_ut,
                        source,
                    });
                }
                _ => {
                    self.no_field += 1;
                    return None;
                }
            }
        }
        self.field.as_ref()
    }

    /// Readings added so far.
    pub fn points(&self) -> usize {
        self.plain.as_ref().map_or(0, |a| a.points())
    }

    /// Solve the sums: the fit, whatever it determines (for reports), or why there is none.
    pub(crate) fn solve(&self) -> Result<VectorFit, VectorFailure> {
        let acc = match (&self.with_current, &self.plain) {
            (Some(c), _) if self.current.sd() >= crate::calib::vector::MIN_CURRENT_SD_A => c,
            (_, Some(p)) => p,
            _ => {
                return Err(VectorFailure::NotEnoughPoints {
                    have: 0,
                    need: crate::calib::vector::MIN_POINTS,
                })
            }
        };
        acc.solve()
    }

    /// The fit when it may be installed: the attitudes seen determine the offset.
    pub(crate) fn offer(&self) -> Option<Offer> {
        let fit = self.solve().ok().filter(|f| f.offset_identifiable)?;
        let f = self.field.as_ref()?;
        Some(Offer {
            fit,
            field_from: format!(
                "{} ({:.4}, {:.4}), {:.1} uT",
                f.source, f.lat_deg, f.lon_deg, f.total_ut
            ),
        })
    }
}

/// The largest RMS residual of a fit the live service installs, as a fraction of the field: 5 %
/// (2.5 uT in a 50 uT field) is several times what attitude noise of a degree leaves, and far less
/// than an earth field that does not match the place (a wrong `[place]`, a simulator's own field).
pub(crate) const MAX_RMS_FRACTION: f64 = 0.05;
/// The soft iron's singular values must lie within this factor of 1: a compass that reads the
/// field 25 % too strong or weak is not a calibration the attitudes justify, but a field model
/// that does not fit the place.
pub(crate) const MAX_SCALE_FACTOR: f64 = 1.25;

/// The checks a learnt fit passes before the live service installs it, beside identifiability:
/// residuals and scale consistent with the earth field it was fitted against.
pub(crate) fn acceptable(fit: &VectorFit) -> Result<(), String> {
    if !(fit.rms_residual_ut <= MAX_RMS_FRACTION * fit.field_ut) {
        return Err(format!(
            "rms residual {:.2} uT is over {:.0} % of the {:.1} uT field",
            fit.rms_residual_ut,
            MAX_RMS_FRACTION * 100.0,
            fit.field_ut
        ));
    }
    let sv = crate::calib::model::rows_to_mat(&fit.soft_iron).singular_values();
    if sv
        .iter()
        .any(|s| !(*s <= MAX_SCALE_FACTOR && *s >= 1.0 / MAX_SCALE_FACTOR))
    {
        return Err(format!(
            "the soft iron scales the field by {:.2} to {:.2}",
            sv.min(),
            sv.max()
        ));
    }
    Ok(())
}

/// Great-circle distance, km (a sphere of radius 6371 km).
fn distance_km(lat1: f64, lon1: f64, lat2: f64, lon2: f64) -> f64 {
    let (p1, p2) = (lat1.to_radians(), lat2.to_radians());
    let dp = p2 - p1;
    let dl = (lon2 - lon1).to_radians();
    let a = (dp / 2.0).sin().powi(2) + p1.cos() * p2.cos() * (dl / 2.0).sin().powi(2);
    2.0 * 6371.0 * a.sqrt().clamp(0.0, 1.0).asin()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    /// Readings over banked turns at every heading, with a hidden offset; the learner must find
    /// it from the sums alone, agree with the batch fit of the same readings, and refuse to
    /// offer anything while the vehicle only turns level.
    #[test]
    fn learns_the_offset_of_banked_turns_and_refuses_level_turns() {
        let place = Place::at(47.37, 8.54).dated("2025-06-01");
        let b = crate::attitude::earth_field(&place).unwrap().field_ned_ut();
        let offset = [12.0, -25.0, 40.0];
        let mut level = VectorLearner::new(LearnSettings::DEFAULT);
        let mut banked = VectorLearner::new(LearnSettings::DEFAULT);
        let mut batch = Vec::new();
        for i in 0..3000 {
            let t = i as f64 * 0.1;
            let yaw = (i as f64 * 0.7).to_radians();
            let roll = 25f64.to_radians() * (t / 20.0).sin();
            let pitch = 4f64.to_radians() * (t / 13.0).cos();
            for (learner, r, p) in [(&mut level, 0.0, 0.0), (&mut banked, roll, pitch)] {
                let q = UnitQuaternion::from_euler_angles(r, p, yaw);
                let h = crate::calib::vector::expected_field(&q, &b);
                let raw = [h[0] + offset[0], h[1] + offset[1], h[2] + offset[2]];
                assert!(learner.push(t, &raw, &q, None, None, Some(&place)));
                if r != 0.0 {
                    batch.push(VectorPoint {
                        raw_ut: raw,
                        expected_ut: h,
                        current_a: None,
                    });
                }
            }
        }
        assert!(
            level.offer().is_none(),
            "level turns must not determine the z offset"
        );
        let o = banked.offer().expect("banked turns determine the offset");
        acceptable(&o.fit).unwrap();
        let err = (0..3)
            .map(|k| (o.fit.offset_ut[k] - offset[k]).abs())
            .fold(0.0, f64::max);
        // Noise-free: measured 1e-9 uT (rounding).
        assert!(err < 1e-6, "offset error {err} uT");
        let full = crate::calib::vector::fit(&batch, false).unwrap();
        for k in 0..3 {
            assert!((full.offset_ut[k] - o.fit.offset_ut[k]).abs() < 1e-6);
        }
        // Readings closer than min_interval_s are not added.
        let n = banked.points();
        let q = UnitQuaternion::identity();
        assert!(!banked.push(299.95, &[0.0; 3], &q, None, None, Some(&place)));
        assert_eq!(banked.points(), n);
        // Nor a reading with the attitude of the last one added.
        assert!(banked.push(300.5, &[0.0; 3], &q, None, None, Some(&place)));
        assert!(!banked.push(301.0, &[0.0; 3], &q, None, None, Some(&place)));
        assert_eq!(banked.points(), n + 1);
        // No position and no place: nothing added.
        let mut none = VectorLearner::new(LearnSettings::DEFAULT);
        assert!(!none.push(0.0, &[1.0; 3], &q, None, None, None));
    }
}
