//! Continuous magnetometer calibration for the live service: every magnetometer reading that
//! arrives with the vehicle's attitude is learnt from, so an ordinary flight calibrates the
//! compass as it goes, with no tumble, by the model ladder `replay` climbs
//! ([`crate::calib::ladder`]).
//!
//! Per reading (the first with each new attitude, at most one every
//! [`LearnSettings::min_interval_s`]): the earth field at the vehicle's position (its GPS fix,
//! else `[place]`; the World Magnetic Model, evaluated again only when the vehicle has moved more
//! than [`FIELD_REFRESH_KM`]) is turned into body axes by the attitude and added, with the
//! reading, to the sums of the full vector fit ([`crate::calib::vector`], a [`VectorAccumulator`]
//! with exponential forgetting over [`LearnSettings::memory_s`], and a second one with the current
//! term). The sums' fit is only reported beside the calibration installed.
//!
//! What is installed comes from the ring: at most one reading every
//! [`LearnSettings::ladder_interval_s`] (1 s) is kept as a [`LadderPoint`] (the reading in body
//! axes, its body -> NED attitude and the current), at most [`RING_CAPACITY`] of them (one hour;
//! the oldest go, counted), each marked fitting or held out by alternate
//! [`QUALITY_BLOCK_S`] blocks of the data time (steps of at most [`QUALITY_GAP_S`]), as `replay`
//! marks a log's readings, with the earth field they were taken against (the ring starts again,
//! counted, when the field where the vehicle is differs by [`FIELD_CHANGE_FRACTION`]).
//!
//! The fit job of the service (off its executor) climbs the ladder on a copy of the ring
//! ([`VectorLearner::ladder_input`], [`climb_live`]): offsets, scale, diagonal and full symmetric
//! soft iron (with a current term where it varies), started from the vehicle's own calibration
//! when the service knows it, bounded to ArduPilot's acceptance and chosen on the held-out blocks.
//! A rung is offered ([`LiveLadder::decide`]) only when its fit passes [`acceptable`] and its
//! held-out spreads are better than those of the calibration in use (else the vehicle's own) on
//! the same readings. Without a calibration of the vehicle's to hold what level turns leave
//! undetermined, the ladder refuses every rung when the offset would rest on an assumed soft iron.
//!
//! Pure: no I/O, no clock; times are handed in.

use crate::attitude::Place;
use crate::calib::ladder::{Affine, Chosen, Ladder, LadderPoint, RungCal};
use crate::calib::magmethod::{QUALITY_BLOCK_S, QUALITY_GAP_S};
use crate::calib::outcome::HeldOut;
use crate::calib::vector::{VectorAccumulator, VectorFailure, VectorFit, VectorPoint};
use crate::types::{GeoPoint, Vec3};
use nalgebra::Vector3;
use std::collections::VecDeque;

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
    /// Shortest time between two readings kept in the ladder's ring ([`RING_CAPACITY`]), s.
    /// Default: 1 (the ring then holds the last hour of flight).
    pub ladder_interval_s: f64,
}

impl LearnSettings {
    pub(crate) const DEFAULT: LearnSettings = LearnSettings {
        min_interval_s: 0.1,
        memory_s: 1800.0,
        current_scale_a: 100.0,
        ladder_interval_s: 1.0,
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

/// Readings the ladder's ring keeps at most: 3600, one hour of flight at one reading a second
/// ([`LearnSettings::ladder_interval_s`]), about 300 kB per compass. The oldest go first, counted.
pub(crate) const RING_CAPACITY: usize = 3600;

/// The ring starts again when the earth field where the vehicle is differs from the one its
/// readings were taken against by more than this share of the field's strength: 1 %, ten times
/// what a rung is judged on (a held-out norm spread of a tenth of a percent), far more than
/// [`FIELD_REFRESH_KM`] moves it. The readings dropped are counted.
pub(crate) const FIELD_CHANGE_FRACTION: f64 = 0.01;

/// The readings the ladder climbs on: each with its attitude and current, marked fitting or held
/// out by alternate [`QUALITY_BLOCK_S`] blocks of the data time, as `replay` marks a log's.
#[derive(Debug, Clone, PartialEq, Default)]
struct Ring {
    points: VecDeque<LadderPoint>,
    /// Each reading's time, s.
    times: VecDeque<f64>,
    /// The earth field (NED, uT) the readings were taken against.
    b_ned: Option<Vector3<f64>>,
    /// The time of the newest reading kept, s.
    last_t_s: Option<f64>,
    /// Data time since the first reading with an attitude, s, each step at most
    /// [`QUALITY_GAP_S`] (a gap in the link does not swallow a block; a step back counts none).
    clock_s: f64,
    clock_at: Option<f64>,
    /// Readings dropped as the oldest of a full ring.
    dropped: u64,
    /// Readings dropped because the earth field changed ([`FIELD_CHANGE_FRACTION`]).
    restarted: u64,
}

impl Ring {
    /// Advance the block clock to `t_s`.
    fn tick(&mut self, t_s: f64) {
        if let Some(l) = self.clock_at {
            let dt = t_s - l;
            if dt.is_finite() && dt > 0.0 {
                self.clock_s += dt.min(QUALITY_GAP_S);
            }
        }
        self.clock_at = Some(t_s);
    }

    /// Whether the block clock is in a fitting (even) block.
    fn fitting(&self) -> bool {
        ((self.clock_s / QUALITY_BLOCK_S).floor() as i64).rem_euclid(2) == 0
    }

    /// Keep a reading taken against `b_ned`: the ring starts again when that field differs from
    /// its own, and the oldest reading goes when it is full.
    fn push(&mut self, p: LadderPoint, t_s: f64, b_ned: &Vector3<f64>) {
        match self.b_ned {
            Some(b) if (b - b_ned).norm() <= FIELD_CHANGE_FRACTION * b.norm() => {}
            Some(_) => {
                self.restarted += self.points.len() as u64;
                self.points.clear();
                self.times.clear();
                self.b_ned = Some(*b_ned);
            }
            None => self.b_ned = Some(*b_ned),
        }
        if self.points.len() >= RING_CAPACITY {
            self.points.pop_front();
            self.times.pop_front();
            self.dropped += 1;
        }
        self.points.push_back(p);
        self.times.push_back(t_s);
        self.last_t_s = Some(t_s);
    }
}

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
    /// The readings the ladder climbs on.
    ring: Ring,
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
            ring: Ring::default(),
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
        self.ring.tick(t_s);
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
        let current_a = current_a.filter(|c| c.is_finite());
        // Half a sum interval of slack: of readings at 10 Hz, the ring takes every tenth.
        let slack = 0.5 * self.settings.min_interval_s;
        let ring_due = self
            .ring
            .last_t_s
            .is_none_or(|last| t_s < last || t_s - last >= self.settings.ladder_interval_s - slack);
        if ring_due {
            let p = LadderPoint {
                raw_ut: Vector3::from(*body_mag_ut),
                body_ned: *body_ned,
                fit: self.ring.fitting(),
                current_a,
            };
            self.ring.push(p, t_s, &Vector3::from(b_ned_ut));
        }
        let dt = self.last_t_s.map_or(0.0, |l| (t_s - l).max(0.0));
        self.last_t_s = Some(t_s);
        self.last_q = Some(*body_ned);
        let keep = (-dt / self.settings.memory_s.max(1e-9)).exp();
        let p = VectorPoint {
            raw_ut: *body_mag_ut,
            expected_ut: crate::calib::vector::expected_field(body_ned, &b_ned_ut),
            current_a,
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

    /// Readings in the ladder's ring.
    pub fn ring_len(&self) -> usize {
        self.ring.points.len()
    }

    /// Readings dropped from the ring: the oldest of a full ring, and those dropped because the
    /// earth field changed.
    pub fn ring_dropped(&self) -> (u64, u64) {
        (self.ring.dropped, self.ring.restarted)
    }

    /// What the ladder climbs on, a copy for a fit job off the executor: `None` until the ring
    /// holds [`MIN_CLIMB_READINGS`].
    pub(crate) fn ladder_input(&self) -> Option<LadderInput> {
        if self.ring.points.len() < MIN_CLIMB_READINGS {
            return None;
        }
        let (b_ned, f) = (self.ring.b_ned?, self.field.as_ref()?);
        Some(LadderInput {
            points: self.ring.points.iter().copied().collect(),
            times: self.ring.times.iter().copied().collect(),
            b_ned,
            field_from: format!(
                "{} ({:.4}, {:.4}), {:.1} uT",
                f.source,
                f.lat_deg,
                f.lon_deg,
                b_ned.norm()
            ),
            dropped: self.ring.dropped + self.ring.restarted,
            vector: self.solve().ok(),
        })
    }
}

/// Readings the ring holds before a ladder is climbed: enough for a rung's fit
/// ([`crate::calib::ladder::MIN_READINGS`]) and for its held-out score
/// ([`crate::calib::ladder::QUALITY_MIN_READINGS`]).
pub(crate) const MIN_CLIMB_READINGS: usize =
    crate::calib::ladder::MIN_READINGS + crate::calib::ladder::QUALITY_MIN_READINGS;

/// The learner's readings as the ladder takes them ([`VectorLearner::ladder_input`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LadderInput {
    pub points: Vec<LadderPoint>,
    /// Each reading's time, s.
    pub times: Vec<f64>,
    /// The earth field they were taken against, NED, uT.
    pub b_ned: Vector3<f64>,
    /// "GPS (lat, lon), 48.3 uT" or "[place] (...)".
    pub field_from: String,
    /// Readings the ring dropped so far (oldest, or the field changed).
    pub dropped: u64,
    /// The full vector fit of the sums, reported beside the rung.
    pub vector: Option<VectorFit>,
}

/// A calibration the rung is judged against, on the same held-out readings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Incumbent {
    pub calibration: RungCal,
    /// "the calibration in use" or "the vehicle's own calibration".
    pub what: &'static str,
    /// The time of the newest reading it was fitted on, when it was fitted on these readings (a
    /// rung learnt before): it is then judged only on held-out readings after it.
    pub fitted_until_s: Option<f64>,
}

/// The ladder climbed on a learner's readings, with the calibration it must beat scored on the
/// same held-out readings.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LiveLadder {
    pub ladder: Ladder,
    /// Readings climbed on, and those the ring had dropped before.
    pub readings: usize,
    pub dropped: u64,
    pub field_from: String,
    pub vector: Option<VectorFit>,
    /// The time of the newest reading climbed on, s.
    pub last_t_s: Option<f64>,
    /// With an incumbent: the held-out scores of the rung taken (fitted on the fitting blocks)
    /// and of the incumbent on the same readings, and what the incumbent is; or why they could
    /// not be scored.
    pub incumbent: Option<Result<(HeldOut, HeldOut, &'static str), String>>,
}

/// Climb the ladder ([`crate::calib::ladder::climb`]) on the learner's readings, from `start` (the
/// vehicle's own calibration in body axes, when known), and score `incumbent` on the same
/// held-out blocks. Runs in the fit job, off the executor (milliseconds for a full ring).
pub(crate) fn climb_live(
    input: &LadderInput,
    start: Option<&Affine>,
    incumbent: Option<&Incumbent>,
) -> LiveLadder {
    let ladder = crate::calib::ladder::climb(&input.points, &input.b_ned, start);
    let incumbent = incumbent.map(|inc| {
        // The held-out readings neither was fitted on: all of them, or those after the
        // incumbent's fit when it was fitted on these readings.
        let since = inc.fitted_until_s;
        let held: Vec<&LadderPoint> = input
            .points
            .iter()
            .zip(&input.times)
            .filter(|(p, t)| !p.fit && since.is_none_or(|s| **t > s))
            .map(|(p, _)| p)
            .collect();
        let theirs = score(&held, &inc.calibration);
        let ours = match since {
            None => ladder.held_out,
            Some(_) => ladder.chosen.as_ref().and_then(|c| {
                let cal = crate::calib::ladder::fit_on_fitting_blocks(
                    c.rung,
                    &input.points,
                    &input.b_ned,
                    start,
                )?;
                score(&held, &cal)
            }),
        };
        match (ours, theirs) {
            (Some(o), Some(t)) => Ok((o, t, inc.what)),
            _ => Err(format!(
                "{} held-out readings since {} was fitted, need {}",
                held.len(),
                inc.what,
                crate::calib::ladder::QUALITY_MIN_READINGS
            )),
        }
    });
    LiveLadder {
        ladder,
        readings: input.points.len(),
        dropped: input.dropped,
        field_from: input.field_from.clone(),
        vector: input.vector.clone(),
        last_t_s: input.times.last().copied(),
        incumbent,
    }
}

/// The held-out score of `cal` on `points` ([`crate::calib::ladder::held_out`]).
fn score(points: &[&LadderPoint], cal: &RungCal) -> Option<HeldOut> {
    let r: Vec<(Vec3, nalgebra::UnitQuaternion<f64>)> = points
        .iter()
        .map(|p| {
            let c = cal.apply(p);
            ([c.x, c.y, c.z], p.body_ned)
        })
        .collect();
    crate::calib::ladder::held_out(&r)
}

impl LiveLadder {
    /// The rung to install, with the words of its comparison, or why none: a rung was taken, its
    /// fit on every reading passes [`acceptable`], and (with `compare` and an incumbent) its
    /// held-out spreads are no worse than the incumbent's on held-out readings neither was fitted
    /// on: neither wider by more than `margin` (a share), the service's rule for every calibration
    /// it replaces. A rung learnt before is judged on the readings after its fit, with the new
    /// rung fitted on the fitting blocks; scored on readings it was fitted on, it would keep the
    /// first rung of a flight (a hundred readings) in use for the rest of it.
    pub(crate) fn decide(&self, margin: f64, compare: bool) -> Result<(&Chosen, String), String> {
        let Some(chosen) = self.ladder.chosen.as_ref() else {
            return Err(format!("no rung taken: {}", self.ladder.why));
        };
        acceptable(chosen)?;
        let Some(judged) = self.incumbent.as_ref().filter(|_| compare) else {
            return Ok((chosen, String::new()));
        };
        let (ours, theirs, what) = judged.clone()?;
        let figures = format!(
            "norm {:.2} against {:.2} %, dip {:.2} against {:.2} deg",
            ours.norm_spread_pct,
            theirs.norm_spread_pct,
            ours.dip_spread_deg,
            theirs.dip_spread_deg
        );
        let wider = ours.norm_spread_pct > theirs.norm_spread_pct * (1.0 + margin)
            || ours.dip_spread_deg > theirs.dip_spread_deg * (1.0 + margin);
        if wider {
            return Err(format!(
                "the {} rung is worse held out than {what} by more than {:.0} % ({figures})",
                chosen.rung,
                100.0 * margin
            ));
        }
        let narrower = ours.norm_spread_pct < theirs.norm_spread_pct
            || ours.dip_spread_deg < theirs.dip_spread_deg;
        let how = if narrower {
            "better than"
        } else {
            "as good as"
        };
        Ok((chosen, format!("held out {how} {what} ({figures})")))
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

/// The checks a learnt rung passes before the live service installs it, beside the ladder's own
/// bounds: residuals and scale consistent with the earth field it was fitted against.
pub(crate) fn acceptable(chosen: &Chosen) -> Result<(), String> {
    if !(chosen.rms_residual_ut <= MAX_RMS_FRACTION * chosen.field_ut) {
        return Err(format!(
            "rms residual {:.2} uT is over {:.0} % of the {:.1} uT field",
            chosen.rms_residual_ut,
            MAX_RMS_FRACTION * 100.0,
            chosen.field_ut
        ));
    }
    let sv = chosen.calibration.affine.matrix.singular_values();
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
            !level.solve().unwrap().offset_identifiable,
            "level turns must not determine the z offset"
        );
        let fit = banked.solve().unwrap();
        assert!(fit.offset_identifiable, "banked turns determine the offset");
        let err = (0..3)
            .map(|k| (fit.offset_ut[k] - offset[k]).abs())
            .fold(0.0, f64::max);
        // Noise-free: measured 1e-9 uT (rounding).
        assert!(err < 1e-6, "offset error {err} uT");
        let full = crate::calib::vector::fit(&batch, false).unwrap();
        for k in 0..3 {
            assert!((full.offset_ut[k] - fit.offset_ut[k]).abs() < 1e-6);
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

    /// A level attitude turned to `yaw_deg`, tilted a little so each reading's attitude is new.
    fn attitude(k: usize) -> UnitQuaternion<f64> {
        let t = k as f64;
        UnitQuaternion::from_euler_angles(
            20f64.to_radians() * (t / 17.0).sin(),
            5f64.to_radians() * (t / 11.0).cos(),
            (t * 7.0).to_radians(),
        )
    }

    #[test]
    fn the_ring_keeps_one_reading_a_second_bounded_in_alternate_blocks_and_counts_its_drops() {
        let place = Place::at(47.37, 8.54).dated("2025-06-01");
        let mut l = VectorLearner::new(LearnSettings::DEFAULT);
        // Readings at 10 Hz for 4000 s: the sums take each, the ring one a second.
        let n = 40_000;
        for k in 0..n {
            let t = k as f64 * 0.1;
            assert!(l.push(
                t,
                &[20.0, 0.0, 40.0],
                &attitude(k),
                None,
                None,
                Some(&place)
            ));
            if k == 10 * 100 {
                assert_eq!(l.ring_len(), 101);
                let input = l.ladder_input().expect("enough readings");
                // Blocks of 20 s alternate: the readings at 0..19 s fit, 20..39 s are held out.
                let fit: Vec<bool> = input.points.iter().map(|p| p.fit).collect();
                for (s, f) in fit.iter().enumerate() {
                    assert_eq!(*f, (s / 20) % 2 == 0, "second {s}");
                }
                assert_eq!(input.dropped, 0);
                assert!(input.field_from.starts_with("[place] (47.3700, 8.5400)"));
            }
        }
        // Bounded: the last hour kept, the 400 s before it dropped and counted.
        assert_eq!(l.ring_len(), RING_CAPACITY);
        assert_eq!(l.ring_dropped(), (400, 0));
        let input = l.ladder_input().unwrap();
        assert_eq!(input.points.len(), RING_CAPACITY);
        assert_eq!(input.dropped, 400);
        // The oldest kept is from 400 s: its block (the 21st, from 400 s) fits.
        assert!(input.points[0].fit && !input.points[20].fit && input.points[40].fit);

        // A gap in the data counts as one step of QUALITY_GAP_S: it does not swallow a block.
        let mut g = VectorLearner::new(LearnSettings::DEFAULT);
        for k in 0..30 {
            g.push(
                k as f64,
                &[20.0, 0.0, 40.0],
                &attitude(k),
                None,
                None,
                Some(&place),
            );
        }
        for k in 30..120 {
            let t = 1000.0 + k as f64;
            g.push(
                t,
                &[20.0, 0.0, 40.0],
                &attitude(k),
                None,
                None,
                Some(&place),
            );
        }
        let fit: Vec<bool> = g.ring.points.iter().map(|p| p.fit).collect();
        // 0..19 fit, 20..29 held out, then 1030.. continues the held-out block for 10 s more
        // (the gap counted as 1 s: seconds 30..39 of the block clock).
        assert!(fit[..20].iter().all(|f| *f));
        assert!(fit[20..40].iter().all(|f| !*f), "{fit:?}");
        assert!(fit[40..60].iter().all(|f| *f), "{fit:?}");

        // The field where the vehicle now is differs by more than 1 %: the ring starts again.
        let mut m = VectorLearner::new(LearnSettings::DEFAULT).on_date("2025-06-01");
        for k in 0..200 {
            let pos = GeoPoint {
                lat_deg: if k < 100 { 47.37 } else { 60.0 },
                lon_deg: 8.54,
                alt_m: 500.0,
            };
            m.push(
                k as f64,
                &[20.0, 0.0, 40.0],
                &attitude(k),
                None,
                Some(pos),
                None,
            );
        }
        assert_eq!(m.ring_dropped(), (0, 100));
        assert_eq!(m.ring_len(), 100);
        assert!(m
            .ladder_input()
            .unwrap()
            .field_from
            .starts_with("GPS (60.0000"));
    }

    /// Readings of banked turns through a hidden offset, with the attitude at 10 Hz; the last
    /// `n` seconds.
    fn banked(offset: [f64; 3], level: bool, n: usize) -> (VectorLearner, Vector3<f64>) {
        let place = Place::at(47.37, 8.54).dated("2025-06-01");
        let b = crate::attitude::earth_field(&place).unwrap().field_ned_ut();
        let mut l = VectorLearner::new(LearnSettings::DEFAULT);
        let mut seed = 11u64;
        let mut noise = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.3
        };
        for i in 0..10 * n {
            let t = i as f64 * 0.1;
            let yaw = (i as f64 * 0.7).to_radians();
            let (roll, pitch) = if level {
                (0.0, 0.0)
            } else {
                (
                    25f64.to_radians() * (t / 20.0).sin(),
                    4f64.to_radians() * (t / 13.0).cos(),
                )
            };
            let q = UnitQuaternion::from_euler_angles(roll, pitch, yaw);
            let h = crate::calib::vector::expected_field(&q, &b);
            let raw = [0, 1, 2].map(|k| h[k] + offset[k] + noise());
            l.push(t, &raw, &q, None, None, Some(&place));
        }
        (l, Vector3::from(b))
    }

    #[test]
    fn the_ladder_on_the_ring_finds_the_offset_beats_the_incumbent_and_refuses_level_turns() {
        let offset = [12.0, -25.0, 40.0];
        let (l, _) = banked(offset, false, 600);
        let input = l.ladder_input().unwrap();
        assert_eq!(input.points.len(), 600);
        // The vehicle's own calibration, 5 uT off, is the incumbent.
        let own = Incumbent {
            calibration: RungCal {
                affine: Affine {
                    matrix: nalgebra::Matrix3::identity(),
                    offset: Vector3::new(17.0, -25.0, 40.0),
                },
                current_ut_per_a: None,
            },
            what: "the vehicle's own calibration",
            fitted_until_s: None,
        };
        let live = climb_live(&input, None, Some(&own));
        let (chosen, words) = live.decide(0.02, true).expect("a rung beats it");
        assert_eq!(
            chosen.rung,
            crate::calib::ladder::Rung::Offsets,
            "{}",
            live.ladder.why
        );
        let err = (chosen.calibration.affine.offset - Vector3::from(offset)).amax();
        // 0.09 uT of noise per axis over 600 readings.
        assert!(err < 0.05, "{err}");
        assert!(
            words.starts_with("held out better than the vehicle's own"),
            "{words}"
        );
        // An incumbent 5 % narrower on the norm stays; one within 2 % is replaced.
        let ours = live.ladder.held_out.unwrap();
        let mut better = live.clone();
        for (shrink, replaced) in [(0.95, false), (0.99, true)] {
            let mut h = ours;
            h.norm_spread_pct *= shrink;
            better.incumbent = Some(Ok((ours, h, "the calibration in use")));
            let r = better.decide(0.02, true);
            assert_eq!(r.is_ok(), replaced, "{shrink}: {r:?}");
            if let Err(why) = r {
                assert!(
                    why.contains("worse held out than the calibration in use by more than 2 %"),
                    "{why}"
                );
                // ... unless not compared (a commanded run).
                assert!(better.decide(0.02, false).is_ok());
            }
        }
        // A rung learnt before, fitted on the first 300 s, is judged on the held-out readings
        // after them only (160 of them), against the new rung fitted on the fitting blocks.
        let before = banked(offset, false, 300).0.ladder_input().unwrap();
        let earlier = climb_live(&before, None, None).ladder.chosen.unwrap();
        let learnt = Incumbent {
            calibration: earlier.calibration,
            what: "the calibration in use",
            fitted_until_s: before.times.last().copied(),
        };
        assert_eq!(before.times.last(), Some(&299.0));
        let live = climb_live(&input, None, Some(&learnt));
        let Some(Ok((o, t, _))) = live.incumbent else {
            panic!("{:?}", live.incumbent)
        };
        assert_eq!((o.readings, t.readings), (160, 160));
        assert!(live.decide(0.02, true).is_ok());
        // Fitted until the newest reading, nothing is left to judge it on: it stays.
        let learnt = Incumbent {
            fitted_until_s: input.times.last().copied(),
            ..learnt
        };
        let why = climb_live(&input, None, Some(&learnt))
            .decide(0.02, true)
            .unwrap_err();
        assert!(
            why.starts_with("0 held-out readings since the calibration in use"),
            "{why}"
        );

        // Level turns with no calibration of the vehicle's: the offset would rest on an assumed
        // soft iron, and no rung is taken.
        let (l, _) = banked(offset, true, 600);
        let live = climb_live(&l.ladder_input().unwrap(), None, None);
        let why = live.decide(0.02, true).unwrap_err();
        assert!(why.contains("do not determine the offset"), "{why}");
    }
}
