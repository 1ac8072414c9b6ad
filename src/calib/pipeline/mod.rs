//! The calibration pipeline as pure, streaming library code: samples in, static poses, coverage and
//! fits out. The same `Pipeline` serves `replay` (fits run inline) and the live daemon (fits run on a
//! snapshot off the async executor, see [`Pipeline::snapshot`] and [`fit_all`]).
//!
//! Per sample: sensor-to-body rotation -> optional prefilter -> static detector (accel variance) ->
//! magnetometer direction bins. Per refit: norm fits of mag (bin means) and accel (pose means),
//! automatic model choice, acceptance checks, gyro bias from poses.
//!
//! This file is the stream (`Pipeline`, its noise meter); the rest, one concern a file: `centre`
//! (the field's centre from spread points, before a first fit), `fits` (what a refit takes and
//! gives, the entries from a snapshot, the gyro bias), `sensor` (one sensor's norm fit: candidate
//! models, automatic choice), `axisfault` (a dead, stuck or saturated axis), `outliers` (readings
//! off the field's ellipsoid: robust sigmas, least median of squares), `accept` (the acceptance
//! checks and the named failures), `calibrator` (finished calibrations applied to samples).

mod accept;
mod axisfault;
mod calibrator;
mod centre;
mod fits;
mod outliers;
mod sensor;

pub use axisfault::axis_fault;
pub(crate) use calibrator::{Calibrated, Calibrator};
pub use fits::{fit_accel_gyro, fit_all, fit_mag, join_fits, FitInput, FitResults};
// Named by path in the docs of the held-out points (`SensorResult::held_out`, the service's store).
#[allow(unused_imports)]
pub(crate) use fits::hold_out;

use crate::calib::coverage::{DirectionBins, Progress, ProgressReport};
use crate::calib::gate::{Pose, Prefilter3, StaticDetector};
use crate::calib::outcome::RefitReport;
use crate::calib::settings::CalibSettings;
use crate::types::{norm, Sample, Unit, Vec3};
use centre::{centre_from_spread_with, SpreadSums};
use nalgebra::Matrix3;

/// Readings a [`NoiseMeter`] needs before it gives a noise level.
pub(crate) const NOISE_MIN_READINGS: u64 = 500;

/// A sensor's white noise from its stream: the second difference of three successive readings,
/// x[i+1] - 2 x[i] + x[i-1], removes the reading's value and any steady rate of change (a turn),
/// and for white noise of standard deviation sigma per axis has variance 6 sigma^2. A break in
/// time starts a new triple.
#[derive(Debug, Clone, Default)]
pub(crate) struct NoiseMeter {
    last: Option<(Vec3, Option<Vec3>, u32)>,
    sum_sq: f64,
    n: u64,
}

impl NoiseMeter {
    /// Take the next reading of the stream (`segment`: its time segment).
    pub fn push(&mut self, x: Vec3, segment: u32) {
        match self.last {
            Some((b, Some(a), seg)) if seg == segment => {
                for k in 0..3 {
                    let d2 = x[k] - 2.0 * b[k] + a[k];
                    self.sum_sq += d2 * d2;
                }
                self.n += 3;
                self.last = Some((x, Some(b), segment));
            }
            Some((b, None, seg)) if seg == segment => self.last = Some((x, Some(b), segment)),
            _ => self.last = Some((x, None, segment)),
        }
    }

    /// The noise's standard deviation per axis, once [`NOISE_MIN_READINGS`] triples are in.
    pub fn sigma(&self) -> Option<f64> {
        (self.n >= 3 * NOISE_MIN_READINGS).then(|| (self.sum_sq / self.n as f64 / 6.0).sqrt())
    }
}

/// The streaming pipeline state.
#[derive(Debug, Clone)]
pub struct Pipeline {
    cfg: CalibSettings,
    rot: Matrix3<f64>,
    pre_a: Option<Prefilter3>,
    pre_m: Option<Prefilter3>,
    /// The prefilters as new, and the time segment they are running in (reset at a break).
    pre_new: (Option<Prefilter3>, u32),
    detector: StaticDetector,
    poses: Vec<Pose>,
    mag_buffer: Vec<Vec3>,
    /// The sums of `mag_buffer` that [`centre_from_spread_with`] reads.
    mag_sums: SpreadSums,
    mag_stride: usize,
    mag_seen: usize,
    mag_bins: Option<DirectionBins>,
    last_refit_t: Option<f64>,
    /// Fit inputs (kept mag points, poses) added since the last refit.
    new_inputs: usize,
    /// Bumped whenever kept magnetometer points are dropped or re-binned (not merely added).
    mag_epoch: u64,
    /// Magnetometer points kept since the last [`Pipeline::take_fresh_mag`] in this epoch.
    fresh_mag: Vec<Vec3>,
    pub last_t: f64,
    pub samples: u64,
    pub mag_units: Unit,
    pub gyro_units: Unit,
    /// [`FitInput::hold_out_every`] of the snapshots (0, fit on all, unless set: the live service
    /// holds points out to judge a new calibration against the current one; `replay` replaces
    /// nothing and fits on all).
    pub hold_out_every: usize,
    /// Latest results (whether accepted or not) and refit history.
    pub latest: Option<FitResults>,
    pub refits: Vec<RefitReport>,
    /// The magnetometer stream's noise, as the fit sees it (after the prefilter).
    mag_noise: NoiseMeter,
}

const MAG_BUFFER_MAX: usize = 4000;

impl Pipeline {
    pub fn new(cfg: &CalibSettings) -> Result<Self, crate::error::Error> {
        let rot = crate::attitude::sensor_rotation(&cfg.sensor_orientation).map_err(|m| {
            crate::error::Error::Config {
                key: "orientation.sensor".into(),
                message: m,
            }
        })?;
        let pf = cfg
            .fit
            .prefilter
            .then(|| Prefilter3::new(cfg.fit.prefilter_q, cfg.fit.prefilter_r));
        Ok(Pipeline {
            cfg: cfg.clone(),
            rot,
            pre_a: pf,
            pre_m: pf,
            pre_new: (pf, 0),
            detector: StaticDetector::new(cfg.gate),
            poses: Vec::new(),
            mag_buffer: Vec::new(),
            mag_sums: SpreadSums::default(),
            mag_stride: 1,
            mag_seen: 0,
            mag_bins: None,
            last_refit_t: None,
            new_inputs: 0,
            mag_epoch: 0,
            fresh_mag: Vec::new(),
            last_t: 0.0,
            samples: 0,
            mag_units: Unit::Si,
            gyro_units: Unit::Si,
            hold_out_every: 0,
            latest: None,
            refits: Vec::new(),
            mag_noise: NoiseMeter::default(),
        })
    }

    /// The pipeline with [`Pipeline::hold_out_every`] set.
    pub fn with_hold_out(mut self, every: usize) -> Self {
        self.hold_out_every = every;
        self
    }

    /// The settings it runs with.
    pub fn settings(&self) -> &CalibSettings {
        &self.cfg
    }

    pub fn poses(&self) -> &[Pose] {
        &self.poses
    }

    /// The sensor's axes are the body's (no mounting rotation): [`Pipeline::to_body`] changes no
    /// finite reading, but for the sign of a zero.
    pub fn sensor_is_body(&self) -> bool {
        self.rot == Matrix3::identity()
    }

    /// Rotate a sample's vectors from sensor to body axes.
    /// The rotation from the sensor's axes to the body's (`orientation.sensor`).
    pub(crate) fn sensor_rotation(&self) -> Matrix3<f64> {
        self.rot
    }

    pub fn to_body(&self, s: &Sample) -> Sample {
        Sample {
            accel_mps2: self.vector_to_body(s.accel_mps2),
            gyro_rad_s: self.vector_to_body(s.gyro_rad_s),
            mag_ut: self.vector_to_body(s.mag_ut),
            ..*s
        }
    }

    /// The part of a sample the gyro scale reads, its angular rate in body axes as
    /// [`Pipeline::to_body`] turns it (without copying the rest).
    pub(crate) fn rate_in_body(&self, s: &Sample) -> crate::calib::gyro::Rate {
        crate::calib::gyro::Rate {
            gyro_rad_s: self.vector_to_body(s.gyro_rad_s),
            ..s.into()
        }
    }

    /// A sample's magnetometer reading in body axes, as [`Pipeline::to_body`] turns it (without
    /// turning or copying the rest).
    pub(crate) fn mag_in_body(&self, s: &Sample) -> Option<Vec3> {
        self.vector_to_body(s.mag_ut)
    }

    fn vector_to_body(&self, v: Option<Vec3>) -> Option<Vec3> {
        v.map(|v| crate::attitude::rotate(&self.rot, &v))
    }

    /// Feed one sample. Returns true when a refit is due (every `fit.refit_every_s` of data).
    pub fn push(&mut self, raw: &Sample) -> bool {
        let mut s = self.to_body(raw);
        self.samples += 1;
        self.last_t = s.t_s;
        if s.segment != self.pre_new.1 {
            // A break in time: the prefilters start again (the gate ends its pose itself).
            self.pre_new.1 = s.segment;
            (self.pre_a, self.pre_m) = (self.pre_new.0, self.pre_new.0);
        }
        if let (Some(pf), Some(a)) = (self.pre_a.as_mut(), s.accel_mps2) {
            s.accel_mps2 = Some(pf.update(&a));
        }
        if let (Some(pf), Some(m)) = (self.pre_m.as_mut(), s.mag_ut) {
            s.mag_ut = Some(pf.update(&m));
        }
        if let Some(a) = s.accel_mps2 {
            if let Some(p) = self.detector.push(&s, &a) {
                self.add_pose(p);
                self.new_inputs += 1;
            }
        }
        if let Some(m) = s.mag_ut {
            self.mag_noise.push(m, s.segment);
            self.add_mag(m);
        }
        let due = match self.last_refit_t {
            None => {
                self.last_refit_t = Some(s.t_s);
                false
            }
            // Nothing new to fit: no refit (a vehicle sitting still costs nothing).
            Some(t) => s.t_s - t >= self.cfg.fit.refit_every_s && self.new_inputs > 0,
        };
        if due {
            self.last_refit_t = Some(s.t_s);
        }
        due
    }

    /// Keep a pose; past [`MAX_POSES`] the oldest goes (memory and fit time stay bounded on a
    /// stream that runs for days; the newest poses also say most about the gyro bias now).
    fn add_pose(&mut self, p: Pose) {
        self.poses.push(p);
        if self.poses.len() > MAX_POSES {
            let extra = self.poses.len() - MAX_POSES;
            self.poses.drain(..extra);
        }
    }

    fn add_mag(&mut self, m: Vec3) {
        if let Some(b) = self.mag_bins.as_mut() {
            let cell = b.cell_deg();
            if b.add(&m) {
                self.new_inputs += 1;
                if b.cell_deg() == cell {
                    self.note_fresh_mag(m);
                } else {
                    self.mag_points_changed(); // the cells widened: re-binned
                }
            }
            return;
        }
        self.mag_seen += 1;
        if self.mag_seen.is_multiple_of(self.mag_stride) {
            self.mag_buffer.push(m);
            self.mag_sums.add(&m);
            self.new_inputs += 1;
            self.note_fresh_mag(m);
        }
        if self.mag_buffer.len() >= MAG_BUFFER_MAX {
            // Bounded memory before a centre is known: keep every other point, sample half as often.
            let kept: Vec<Vec3> = self.mag_buffer.iter().step_by(2).copied().collect();
            self.mag_sums = SpreadSums::of(&kept);
            self.mag_buffer = kept;
            self.mag_stride *= 2;
            self.mag_points_changed();
        }
        if self.mag_buffer.len() >= 100 && self.mag_buffer.len().is_multiple_of(50) {
            self.try_start_bins();
        }
    }

    /// Start direction binning once the buffered field vectors spread enough to place the centre
    /// of their sphere ([`centre_from_spread_with`]).
    fn try_start_bins(&mut self) {
        let limits = (self.mag_units == Unit::Si).then_some(&self.cfg.accept.mag);
        if let Some(c) = centre_from_spread_with(
            &self.mag_buffer,
            &self.mag_sums,
            self.cfg.fit.centre_min_spread_radii,
            limits,
        ) {
            self.start_bins(c);
        }
    }

    fn start_bins(&mut self, centre: Vec3) {
        let mut b = DirectionBins::new(centre, self.cfg.fit.min_separation_deg);
        for p in self.mag_buffer.drain(..) {
            b.add(&p);
        }
        self.mag_sums = SpreadSums::default();
        self.mag_bins = Some(b);
        self.mag_points_changed();
    }

    /// Copy out what a refit needs.
    pub fn snapshot(&self) -> FitInput {
        let mut poses = self.poses.clone();
        // Include a still run that has not ended yet.
        let mut det = self.detector.clone();
        if let Some(p) = det.finish() {
            poses.push(p);
        }
        FitInput {
            mag_points: self.mag_points(),
            poses,
            mag_units: self.mag_units,
            gyro_units: self.gyro_units,
            accel_units: self.cfg.accel_units,
            hold_out_every: self.hold_out_every,
            mag_noise: self.mag_noise.sigma(),
        }
    }

    /// Take in results computed from a snapshot: record them, and re-centre the direction bins on the
    /// new hard-iron estimate.
    pub fn install(&mut self, t_s: f64, results: FitResults) {
        self.new_inputs = 0;
        for (sensor, r) in [
            (crate::types::Sensor::Mag, &results.mag),
            (crate::types::Sensor::Accel, &results.accel),
        ] {
            self.refits.push(RefitReport {
                t_s,
                sensor,
                model: r.report.model,
                status: r.report.status,
                failure: r.report.failure,
                rms_residual: r.report.rms_residual,
            });
        }
        // Bounded history: past a quarter over the limit, the oldest go (in one move, not one by one).
        if self.refits.len() > MAX_REFIT_HISTORY + MAX_REFIT_HISTORY / 4 {
            let extra = self.refits.len() - MAX_REFIT_HISTORY;
            self.refits.drain(..extra);
        }
        let mut recentred = false;
        if let (None, Some(c)) = (&self.mag_bins, results.mag.calibration.as_ref()) {
            // A first fit that passed its checks places the centre before the spread did.
            self.start_bins(c.offset);
        } else if let (Some(b), Some(c)) =
            (self.mag_bins.as_mut(), results.mag.calibration.as_ref())
        {
            let d = norm(&[
                b.centre[0] - c.offset[0],
                b.centre[1] - c.offset[1],
                b.centre[2] - c.offset[2],
            ]);
            if d > 1e-3 * results.mag.report.radius.max(1e-9) {
                b.recentre(c.offset);
                recentred = true;
            }
        }
        if recentred {
            self.mag_points_changed();
        }
        self.latest = Some(results);
    }

    /// Refit now, inline.
    pub fn refit(&mut self) -> &FitResults {
        let input = self.snapshot();
        let r = fit_all(&input, &self.cfg);
        let t = self.last_t;
        self.install(t, r);
        self.latest.as_ref().expect("just installed")
    }

    /// End of input: close the last pose and refit.
    pub fn finish(&mut self) -> &FitResults {
        let input = self.finish_input();
        let r = fit_all(&input, &self.cfg);
        self.install_final(r)
    }

    /// [`Pipeline::finish`] in steps, for a caller that runs the fits itself (on other threads):
    /// close the last pose and copy out what the fits need.
    pub fn finish_input(&mut self) -> FitInput {
        self.finish_poses();
        self.snapshot()
    }

    /// The last step of [`Pipeline::finish`]: install the results of the fits of
    /// [`Pipeline::finish_input`] at the time of the last sample.
    pub fn install_final(&mut self, results: FitResults) -> &FitResults {
        let t = self.last_t;
        self.install(t, results);
        self.latest.as_ref().expect("just installed")
    }

    /// Close a still run at the end of input.
    pub(crate) fn finish_poses(&mut self) {
        if let Some(p) = self.detector.finish() {
            self.add_pose(p);
        }
    }

    fn note_fresh_mag(&mut self, m: Vec3) {
        if self.fresh_mag.len() < MAX_FRESH_MAG {
            self.fresh_mag.push(m);
        } else {
            // Nobody is taking them: start a new epoch rather than grow.
            self.mag_points_changed();
        }
    }

    fn mag_points_changed(&mut self) {
        self.mag_epoch += 1;
        self.fresh_mag.clear();
    }

    /// The magnetometer points kept since the last call, and the epoch of the kept set. While the
    /// epoch stays the same, [`Pipeline::mag_points`] is the points of earlier calls plus these
    /// (a consumer can update what it derived from them); a new epoch means points were dropped or
    /// re-binned, so start again from [`Pipeline::mag_points`].
    pub(crate) fn take_fresh_mag(&mut self) -> (u64, Vec<Vec3>) {
        (self.mag_epoch, std::mem::take(&mut self.fresh_mag))
    }

    /// The magnetometer points kept so far (raw units, body axes).
    pub(crate) fn mag_points(&self) -> Vec<Vec3> {
        match &self.mag_bins {
            Some(b) => b.points(),
            None => self.mag_buffer.clone(),
        }
    }

    /// The magnetometer's centre (hard iron, raw units) as far as it is known: the last fit that
    /// passed its checks, or before one the centre of the kept points once they spread enough
    /// ([`centre_from_spread_with`]). `None` before either.
    pub(crate) fn mag_centre(&self) -> Option<Vec3> {
        self.mag_bins.as_ref().map(|b| b.centre)
    }

    /// A progress report for this run: the points kept since the last report about `calibrated`
    /// (the centre of the calibration in use) or else [`Pipeline::mag_centre`].
    pub fn progress(&mut self, run: &mut Progress, calibrated: Option<Vec3>) -> ProgressReport {
        let centre = calibrated.or(self.mag_centre());
        let (epoch, fresh) = self.take_fresh_mag();
        run.update(centre, epoch, &fresh, || self.mag_points())
    }
}

/// Most refit records (one per sensor per refit) the pipeline keeps for its report: the newest
/// 1000 to 1250 (a stream that runs for days refits every 10 s).
pub(crate) const MAX_REFIT_HISTORY: usize = 1000;

/// Most static poses the pipeline keeps (the oldest are dropped).
pub(crate) const MAX_POSES: usize = 2000;

/// Most magnetometer points held for [`Pipeline::take_fresh_mag`] between two calls.
const MAX_FRESH_MAG: usize = 4096;

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic standard normal numbers (a 64-bit LCG through Box-Muller) from `seed`; the
    /// other files' tests of the pipeline draw theirs here too.
    pub(super) fn gaussian(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            let mut u = || {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos()
        }
    }

    #[test]
    fn the_noise_meter_finds_white_noise_under_a_steady_turn() {
        // Deterministic pseudo-random noise of 0.5 per axis on a field turning steadily.
        let mut gauss = gaussian(12345);
        let mut m = NoiseMeter::default();
        for i in 0..5000 {
            let a = i as f64 * 0.01;
            let x = [40.0 * a.cos(), 40.0 * a.sin(), 10.0];
            m.push(
                [
                    x[0] + 0.5 * gauss(),
                    x[1] + 0.5 * gauss(),
                    x[2] + 0.5 * gauss(),
                ],
                0,
            );
        }
        let sigma = m.sigma().unwrap();
        assert!((sigma - 0.5).abs() < 0.03, "{sigma}");
        // Too few readings: no figure.
        let mut few = NoiseMeter::default();
        for i in 0..100 {
            few.push([i as f64, 0.0, 0.0], 0);
        }
        assert_eq!(few.sigma(), None);
    }

    #[test]
    fn refit_history_is_bounded_and_the_newest_kept() {
        let mut p = Pipeline::new(&CalibSettings::default()).unwrap();
        for i in 0..2000 {
            let r = p.snapshot();
            let res = fit_all(&r, &CalibSettings::default());
            p.install(i as f64, res);
            assert!(p.refits.len() <= MAX_REFIT_HISTORY + MAX_REFIT_HISTORY / 4);
        }
        assert!(p.refits.len() >= MAX_REFIT_HISTORY);
        assert_eq!(p.refits.last().unwrap().t_s, 1999.0);
    }

    #[test]
    fn poses_are_bounded_and_the_newest_kept() {
        let mut p = Pipeline::new(&CalibSettings::default()).unwrap();
        for i in 0..(MAX_POSES + 500) {
            p.add_pose(Pose::still(i as f64, i as f64 + 0.5, 50, [0.0, 0.0, -9.8]));
        }
        assert_eq!(p.poses().len(), MAX_POSES);
        assert_eq!(p.poses()[0].t_start, 500.0);
        assert_eq!(p.poses().last().unwrap().t_start, (MAX_POSES + 499) as f64);
    }
}
