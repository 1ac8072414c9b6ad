//! The calibration pipeline as pure, streaming library code: samples in, static poses, coverage and
//! fits out. The same `Pipeline` serves `replay` (fits run inline) and the live daemon (fits run on a
//! snapshot off the async executor, see [`Pipeline::snapshot`] and [`fit_all`]).
//!
//! Per sample: sensor-to-body rotation -> optional prefilter -> static detector (accel variance) ->
//! magnetometer direction bins. Per refit: norm fits of mag (bin means) and accel (pose means),
//! automatic model choice, acceptance checks, gyro bias from poses.

use crate::calib::coverage::{coverage, Coverage, DirectionBins, Progress, ProgressReport};
use crate::calib::fit::{
    fit_norm, significantly_better, six_position, FitFailure, NormFit, NormFitOptions,
};
use crate::calib::gate::{Pose, Prefilter3, StaticDetector};
use crate::calib::model::{CalModel, Calibration, ModelKind};
use crate::calib::outcome::{
    CalStatus, Candidate, GyroCalibration, RefitReport, SensorCalibration,
};
use crate::calib::settings::{
    AccelUnits, AcceptLimits, CalibSettings, MagModelChoice, ModelChoice,
};
use crate::types::{norm, CalUnits, Sample, Unit, Vec3};
use nalgebra::Matrix3;

use crate::calib::outcome::SensorResult;

/// Everything a refit needs, cloned out of the pipeline so the fit can run elsewhere.
#[derive(Debug, Clone)]
pub struct FitInput {
    pub mag_points: Vec<Vec3>,
    pub poses: Vec<Pose>,
    pub mag_units: Unit,
    pub gyro_units: Unit,
    /// From config.
    pub accel_units: AccelUnits,
    /// Hold every this-many-th magnetometer point and pose out of the fits (0: fit on all); see
    /// [`hold_out`].
    pub hold_out_every: usize,
    /// The magnetometer's own noise (one axis, the stream's units) from its readings
    /// ([`NoiseMeter`]); `None` before enough readings.
    pub mag_noise: Option<f64>,
}

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

#[derive(Debug, Clone)]
pub struct FitResults {
    pub mag: SensorResult,
    pub accel: SensorResult,
    pub gyro: GyroCalibration,
}

impl FitInput {
    /// The units the magnetometer's calibration is reported in ([`fit_mag`]).
    pub fn mag_cal_units(&self) -> CalUnits {
        CalUnits::of(self.mag_units, CalUnits::Ut)
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

/// The centre of the sphere the points lie on, when they spread enough to place it: a sphere fits
/// them (RMS distance from it at most [`CENTRE_MAX_RMS_RADII`] radii), their standard deviation
/// along their narrowest direction is at least `min_spread_radii` of its radius, and with `limits`
/// (units known) the radius is within them. A still sensor's points (a small cluster, on which an
/// algebraic sphere fit gives a small sphere through the noise) never pass. `sums` are the points'
/// own, kept as they came: the sphere, its radius and the spread come from them, and only when
/// those pass are the points read (for the RMS distance).
fn centre_from_spread_with(
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
struct SpreadSums {
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
    fn of(points: &[Vec3]) -> Self {
        let mut s = SpreadSums::default();
        for p in points {
            s.add(p);
        }
        s
    }

    fn add(&mut self, p: &Vec3) {
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

fn failed(
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

/// Which sensor a norm fit is for, and what its output must look like.
struct SensorSpec<'a> {
    model: ModelChoice,
    target_norm: Option<f64>,
    units: CalUnits,
    /// Check radius and offsets in physical units.
    units_known: bool,
    limits: &'a AcceptLimits,
    is_accel: bool,
    /// The stream's own noise per axis, same units ([`NoiseMeter`]).
    noise: Option<f64>,
}

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

/// Most refit records (one per sensor per refit) the pipeline keeps for its report: the newest
/// 1000 to 1250 (a stream that runs for days refits every 10 s).
pub(crate) const MAX_REFIT_HISTORY: usize = 1000;

/// Most static poses the pipeline keeps (the oldest are dropped).
pub(crate) const MAX_POSES: usize = 2000;

/// Largest share of magnetometer points that may be outliers before the fit is refused as disturbed.
pub(crate) const MAX_OUTLIER_SHARE: f64 = 0.25;

/// Fit one sensor: a saturated or stuck axis is refused first ([`axis_fault`]); then candidate
/// models, automatic choice, acceptance checks ([`fit_sensor_on`]). When the magnetometer fit shows
/// outliers or failed, points off the field's ellipsoid (a magnet brought near the sensor, a motor
/// running) are found ([`inliers`]) and left out, and the fit is made again on the rest. When more
/// than [`MAX_OUTLIER_SHARE`] of the points are outliers, the fit is refused (`disturbed`): no
/// single field explains the data.
fn fit_sensor(points: &[Vec3], spec: &SensorSpec) -> SensorResult {
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

/// A dead, stuck or saturated axis, with the reason; `None` when every axis looks alive. The points
/// are taken in their order (time, or neighbouring directions once binned); a step is two
/// successive points.
///
/// - Dead: one value in every point while the others change.
/// - Stuck part of the time: one value, inside the axis's range, in a fifth of the points, and
///   the axis stays on it across at least [`STUCK_MIN_HELD_STEPS`] and [`STUCK_MIN_HOLD_SHARE`] of
///   the steps from it over which the vehicle turns ([`held_while_turning`]). A still sensor read
///   in whole counts repeats its readings as well, but not while it turns.
/// - Saturated: at least 5 points and 3% of them at exactly the axis's lowest or highest value,
///   piled up there ([`CLIP_MIN_PILE_RATIO`]) on an axis that spans more than [`TURN_MIN_QUANTA`]
///   of its quantisation steps: the reading is clipped at the sensor's range, not the end of a
///   still sensor's noise.
pub fn axis_fault(points: &[Vec3]) -> Option<String> {
    let n = points.len();
    if n < 7 {
        return None;
    }
    const AXIS: [&str; 3] = ["x", "y", "z"];
    let mut ranges = [(f64::INFINITY, f64::NEG_INFINITY); 3];
    for p in points {
        for (r, v) in ranges.iter_mut().zip(p) {
            *r = (r.0.min(*v), r.1.max(*v));
        }
    }
    let widest = ranges.iter().map(|(lo, hi)| hi - lo).fold(0.0, f64::max);
    for (k, (lo, hi)) in ranges.iter().enumerate() {
        if widest > 0.0 && hi - lo <= 1e-6 * widest {
            return Some(format!(
                "axis {} reads {lo} in all {n} points while the others change: the axis is stuck or dead",
                AXIS[k]
            ));
        }
    }
    for k in 0..3 {
        if let Some((val, best)) = frequent_value(points.iter().map(|p| p[k]), 0.2) {
            if best < 5 || val <= ranges[k].0 || val >= ranges[k].1 {
                continue;
            }
            let (held, turning) = held_while_turning(points, k, val, widest);
            if held >= STUCK_MIN_HELD_STEPS && held as f64 >= STUCK_MIN_HOLD_SHARE * turning as f64
            {
                return Some(format!(
                    "axis {} reads exactly {val} in {best} of {n} points and stays on it across {held} of \
                     the {turning} steps from it over which the vehicle turns (another axis moves by more \
                     than {TURN_MIN_QUANTA} of its quantisation steps): the axis is stuck part of the time",
                    AXIS[k]
                ));
            }
        }
    }
    let need = (0.03 * n as f64).ceil().max(5.0) as usize;
    // Points at each axis's low and high extreme, counted in one pass.
    let mut at_rail = [[0usize; 2]; 3];
    for p in points {
        for k in 0..3 {
            at_rail[k][0] += (p[k] == ranges[k].0) as usize;
            at_rail[k][1] += (p[k] == ranges[k].1) as usize;
        }
    }
    let quanta = smallest_steps(points.windows(2), widest);
    for (k, (lo, hi)) in ranges.iter().enumerate() {
        if hi - lo <= TURN_MIN_QUANTA * quanta[k] {
            continue; // a still axis: its ends are its noise's
        }
        for (side, rail) in [*lo, *hi].into_iter().enumerate() {
            let at = at_rail[k][side];
            if at < need {
                continue;
            }
            let inside = count_next_inside(points, k, rail, side == 1);
            if at as f64 > CLIP_MIN_PILE_RATIO * inside as f64 {
                return Some(format!(
                    "axis {} reads exactly {rail} in {at} of {n} points ({inside} at the next value \
                     inside): saturated (the field or acceleration exceeds the sensor's range, or the \
                     reading is clipped)",
                    AXIS[k]
                ));
            }
        }
    }
    None
}

/// Quantisation steps (quanta: the smallest nonzero change an axis shows between two successive
/// readings) by which another axis must move over a step for the vehicle to count as turning over
/// it. Rounding alone moves a still reading by one quantum, and a compass's rest noise, about a
/// count rms, by a few; more than 4 quanta is, for a 50 uT field read in ArduPilot's 0.1 uT
/// (milligauss) steps, a turn of more than half a degree (8.7 quanta per degree).
const TURN_MIN_QUANTA: f64 = 4.0;

/// Share of the turning steps from a value that an axis must stay on it across to be stuck. A
/// stuck axis stays on its value over every turning step of a stuck stretch but the one that ends
/// it (3 of 4 for a stretch of four steps, more for longer ones). A working axis leaves the value
/// whenever its noise takes it a quantum away: about as often as it reads other values. Measured:
/// 0.40 for the x axis of an ArduSub ROV's SCALED_IMU2 at rest (one value in 156 of 625 readings,
/// its other axes' noise moving them by up to 30 quanta between readings, so that most steps count
/// as turning).
const STUCK_MIN_HOLD_SHARE: f64 = 0.75;

/// Fewest turning steps a stuck axis must stay on its value across: five successive points on one
/// value while the vehicle turns.
const STUCK_MIN_HELD_STEPS: usize = 4;

/// How many times the count at the next value inside a rail the rail's own count must exceed for
/// the axis to be clipped there. Clipping folds every reading beyond the rail onto it: with the
/// readings spread about evenly near the rail, the rail holds the count of one quantum times the
/// quanta by which the field went beyond it, so more than twice the next value's count is a field
/// more than two quanta beyond the sensor's range (a clip a fit cannot absorb as noise). The end
/// of a still sensor's noise thins out instead (an ArduSub ROV's compass at rest: 24 readings on
/// its lowest x value, 23 on the next).
const CLIP_MIN_PILE_RATIO: f64 = 2.0;

/// Over the steps (two successive points) that start with axis `k` at `val`: how many of those
/// over which the vehicle turns the axis stays on `val` across, and how many turn. A step turns
/// when another axis moves by more than [`TURN_MIN_QUANTA`] of its quantisation step, the smallest
/// nonzero change it shows over these steps ([`smallest_steps`]).
fn held_while_turning(points: &[Vec3], k: usize, val: f64, widest: f64) -> (usize, usize) {
    let from_val = || points.windows(2).filter(|w| w[0][k] == val);
    let quanta = smallest_steps(from_val(), widest);
    let min_move = quanta.map(|q| (TURN_MIN_QUANTA * q).max(1e-6 * widest));
    let (mut held, mut turning) = (0, 0);
    for w in from_val() {
        let turns = (0..3)
            .filter(|&j| j != k)
            .any(|j| (w[1][j] - w[0][j]).abs() > min_move[j]);
        if turns {
            turning += 1;
            held += (w[1][k] == val) as usize;
        }
    }
    (held, turning)
}

/// Each axis's quantisation step as the steps (pairs of successive points) show it: the smallest
/// change over a step larger than `1e-6 * widest` (smaller ones are a conversion's rounding, not a
/// count); 0 for an axis with none.
fn smallest_steps<'a>(steps: impl Iterator<Item = &'a [Vec3]>, widest: f64) -> [f64; 3] {
    let mut q = [f64::INFINITY; 3];
    for w in steps {
        for (j, q) in q.iter_mut().enumerate() {
            let d = (w[1][j] - w[0][j]).abs();
            if d > 1e-6 * widest {
                *q = q.min(d);
            }
        }
    }
    q.map(|q| if q.is_finite() { q } else { 0.0 })
}

/// How many points have axis `k` at the value next to `rail` on its inner side (above it for the
/// low rail, below it for the high one).
fn count_next_inside(points: &[Vec3], k: usize, rail: f64, high: bool) -> usize {
    let inner = points
        .iter()
        .map(|p| p[k])
        .filter(|&v| if high { v < rail } else { v > rail });
    let next = if high {
        inner.fold(f64::NEG_INFINITY, f64::max)
    } else {
        inner.fold(f64::INFINITY, f64::min)
    };
    points.iter().filter(|p| p[k] == next).count()
}

/// The value that occurs most often (the smallest of equally frequent ones) and its count, when it
/// occurs in at least `min_share` of the values (`min_share` > 1/6). O(n): the Misra-Gries summary
/// with five counters keeps every value more frequent than n/6, then one pass counts them exactly.
fn frequent_value(
    values: impl Iterator<Item = f64> + Clone,
    min_share: f64,
) -> Option<(f64, usize)> {
    let mut cand: [(f64, usize); 5] = [(f64::NAN, 0); 5];
    let mut n = 0usize;
    for v in values.clone() {
        n += 1;
        if let Some(c) = cand.iter_mut().find(|c| c.1 > 0 && c.0 == v) {
            c.1 += 1;
        } else if let Some(c) = cand.iter_mut().find(|c| c.1 == 0) {
            *c = (v, 1);
        } else {
            for c in cand.iter_mut() {
                c.1 -= 1;
            }
        }
    }
    let mut counts = [0usize; 5];
    for v in values {
        for (i, c) in cand.iter().enumerate() {
            if c.1 > 0 && c.0 == v {
                counts[i] += 1;
            }
        }
    }
    let mut best: Option<(f64, usize)> = None;
    for (i, c) in cand.iter().enumerate() {
        if c.1 == 0 {
            continue;
        }
        let better = match best {
            None => true,
            Some((bv, bc)) => counts[i] > bc || (counts[i] == bc && c.0 < bv),
        };
        if better {
            best = Some((c.0, counts[i]));
        }
    }
    best.filter(|&(_, c)| c as f64 >= min_share * n as f64)
}

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
fn has_outliers(residuals: &[f64]) -> bool {
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
fn inliers(points: &[Vec3], spec: &SensorSpec, sym9: Option<&NormFit>) -> (Vec<Vec3>, usize) {
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

/// Why no norm model could be fitted to `n` points.
fn no_fit_reason(n: usize, cov_before: &Coverage, spec: &SensorSpec) -> (FitFailure, String) {
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
fn norm_fit_report(
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
fn blame_coverage(report: &mut SensorCalibration, cov_before: &Coverage, spec: &SensorSpec) {
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

fn set_fail(rep: &mut SensorCalibration, why: FitFailure, detail: String) {
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

fn check_limits(rep: &mut SensorCalibration, cal: &Calibration, cov: &Coverage, spec: &SensorSpec) {
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

/// Gyro bias from the static poses at rest ([`Pose::at_rest`]): the mean of pose means. A pose
/// that turned (a steady turn holds the gyro steady too) says nothing about the bias.
fn fit_gyro(poses: &[Pose], units: Unit) -> GyroCalibration {
    let turning = poses
        .iter()
        .filter(|p| p.gyro.is_some() && !p.at_rest())
        .count();
    let g: Vec<Vec3> = poses
        .iter()
        .filter(|p| p.at_rest())
        .filter_map(|p| p.gyro)
        .collect();
    // A gyro at rest reading more than 35 rad/s (2000 deg/s) is in counts, whatever the input said.
    let mut norms: Vec<f64> = g.iter().map(norm).collect();
    norms.sort_by(|a, b| a.total_cmp(b));
    let counts = units == Unit::Counts || norms.get(norms.len() / 2).is_some_and(|m| *m > 35.0);
    let units = if counts {
        CalUnits::Counts
    } else {
        CalUnits::RadS
    };
    if g.len() < 2 {
        return GyroCalibration {
            status: CalStatus::Failed,
            failure: Some(FitFailure::NotEnoughSamples),
            units,
            bias: [0.0; 3],
            bias_sigma: [0.0; 3],
            poses_used: g.len(),
            poses_turning: turning,
            scale: None,
            scale_failure: None,
        };
    }
    let n = g.len() as f64;
    let mut mean = [0.0; 3];
    for v in &g {
        for k in 0..3 {
            mean[k] += v[k] / n;
        }
    }
    let mut sd = [0.0; 3];
    for v in &g {
        for k in 0..3 {
            sd[k] += (v[k] - mean[k]).powi(2) / (n - 1.0);
        }
    }
    GyroCalibration {
        status: CalStatus::Ok,
        failure: None,
        units,
        bias: mean,
        bias_sigma: sd.map(|v| (v / n).sqrt()),
        poses_used: g.len(),
        poses_turning: turning,
        scale: None,
        scale_failure: None,
    }
}

/// Most magnetometer points held for [`Pipeline::take_fresh_mag`] between two calls.
const MAX_FRESH_MAG: usize = 4096;

/// Detect accelerometer units from the static norms: near g means m/s^2, otherwise counts.
pub(crate) fn accel_units(poses: &[Pose], setting: AccelUnits) -> Unit {
    match setting {
        AccelUnits::Si => Unit::Si,
        AccelUnits::Counts => Unit::Counts,
        AccelUnits::Auto => {
            let mut norms: Vec<f64> = poses.iter().map(|p| norm(&p.accel)).collect();
            if norms.is_empty() {
                return Unit::Si;
            }
            norms.sort_by(|a, b| a.total_cmp(b));
            let med = norms[norms.len() / 2];
            if (5.0..=15.0).contains(&med) {
                Unit::Si
            } else {
                Unit::Counts
            }
        }
    }
}

/// Fewest points held out for a comparison: below `MIN_HELD_OUT * every` points none are.
pub(crate) const MIN_HELD_OUT: usize = 4;

/// Every `every`-th point (the 1st, the `every+1`-th, ...) held out, the rest to fit: `(fit, held)`.
/// Deterministic; on the direction bins' points (ordered by direction) the held-out ones spread
/// over the whole sphere, on poses (in time order) over the whole run. With `every` 0 or fewer
/// than `MIN_HELD_OUT * every` points, none are held out.
pub(crate) fn hold_out(points: &[Vec3], every: usize) -> (Vec<Vec3>, Vec<Vec3>) {
    if every < 2 || points.len() < MIN_HELD_OUT * every {
        return (points.to_vec(), vec![]);
    }
    let (mut fit, mut held) = (Vec::new(), Vec::new());
    for (i, p) in points.iter().enumerate() {
        if i % every == 0 {
            held.push(*p);
        } else {
            fit.push(*p);
        }
    }
    (fit, held)
}

/// All fits from a snapshot. Pure; may run on any thread.
pub fn fit_all(input: &FitInput, cfg: &CalibSettings) -> FitResults {
    let mag = fit_mag(input, cfg);
    let (accel, gyro) = fit_accel_gyro(input, cfg);
    join_fits(mag, accel, gyro, input, cfg)
}

/// The magnetometer's part of [`fit_all`], before [`join_fits`]: on its own so that a caller can
/// run it beside [`fit_accel_gyro`] (the two share nothing).
pub fn fit_mag(input: &FitInput, cfg: &CalibSettings) -> SensorResult {
    let mag_full12 = cfg.fit.mag_model == MagModelChoice::Full12;
    let (mag_fit, mag_held) = hold_out(&input.mag_points, input.hold_out_every);
    let mut mag = fit_sensor(
        &mag_fit,
        &SensorSpec {
            model: if mag_full12 {
                ModelChoice::Sym9
            } else {
                cfg.fit.mag_model.into()
            },
            target_norm: None,
            units: input.mag_cal_units(),
            units_known: input.mag_units == Unit::Si,
            limits: &cfg.accept.mag,
            is_accel: false,
            noise: input.mag_noise,
        },
    );
    mag.held_out = mag_held;
    mag
}

/// The accelerometer's and the gyroscope's part of [`fit_all`] (the gyro bias from the poses).
pub fn fit_accel_gyro(input: &FitInput, cfg: &CalibSettings) -> (SensorResult, GyroCalibration) {
    let au = accel_units(&input.poses, input.accel_units);
    let accel_points: Vec<Vec3> = input.poses.iter().map(|p| p.accel).collect();
    let (accel_fit, accel_held) = hold_out(&accel_points, input.hold_out_every);
    let mut accel = fit_sensor(
        &accel_fit,
        &SensorSpec {
            model: cfg.fit.accel_model,
            target_norm: Some(cfg.fit.gravity_mps2),
            units: CalUnits::Mps2,
            units_known: au == Unit::Si,
            limits: &cfg.accept.accel,
            is_accel: true,
            noise: None,
        },
    );
    accel.held_out = accel_held;
    let gyro = fit_gyro(&input.poses, input.gyro_units);
    (accel, gyro)
}

/// The results of [`fit_mag`] and [`fit_accel_gyro`] put together: with `fit.mag_model =
/// "full12"` the magnetometer's rotation follows from the dip seen against the accelerometer's.
pub fn join_fits(
    mut mag: SensorResult,
    accel: SensorResult,
    gyro: GyroCalibration,
    input: &FitInput,
    cfg: &CalibSettings,
) -> FitResults {
    if cfg.fit.mag_model == MagModelChoice::Full12 {
        mag_rotation_from_dip(&mut mag, &accel, &input.poses);
    }
    FitResults { mag, accel, gyro }
}

/// Applies finished calibrations to samples and derives attitude, holding the last accel and mag
/// so that sensors at different rates still give a heading on every row.
#[derive(Debug, Clone)]
pub(crate) struct Calibrator {
    pub accel: Option<Calibration>,
    pub mag: Option<Calibration>,
    pub gyro_bias: Option<Vec3>,
    pub declination_deg: Option<f64>,
    last_accel: Option<Vec3>,
    last_mag: Option<Vec3>,
}

/// A calibrated sample (body frame) with attitude in degrees.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Calibrated {
    pub t_s: f64,
    /// The sample's time segment.
    pub segment: u32,
    pub accel_mps2: Option<Vec3>,
    pub gyro_rad_s: Option<Vec3>,
    pub mag_ut: Option<Vec3>,
    pub roll_deg: Option<f64>,
    pub pitch_deg: Option<f64>,
    pub heading_deg: Option<f64>,
}

impl Calibrated {
    /// The calibrated vectors as a sample (for the orientation filter); nothing else carried over.
    pub(crate) fn as_sample(&self) -> Sample {
        Sample {
            t_s: self.t_s,
            segment: self.segment,
            accel_mps2: self.accel_mps2,
            gyro_rad_s: self.gyro_rad_s,
            mag_ut: self.mag_ut,
            ..Default::default()
        }
    }
}

impl Calibrator {
    /// No calibration yet: samples pass through raw.
    pub fn empty(declination_deg: Option<f64>) -> Self {
        Calibrator {
            accel: None,
            mag: None,
            gyro_bias: None,
            declination_deg,
            last_accel: None,
            last_mag: None,
        }
    }

    pub fn new(results: &FitResults, declination_deg: Option<f64>) -> Self {
        Calibrator {
            accel: results.accel.calibration,
            mag: results.mag.calibration,
            gyro_bias: (results.gyro.status == CalStatus::Ok).then_some(results.gyro.bias),
            declination_deg,
            last_accel: None,
            last_mag: None,
        }
    }

    /// Calibrate one body-frame sample. Sensors without an accepted calibration pass through raw.
    /// Roll, pitch and heading come from the latest accelerometer and magnetometer seen.
    pub fn apply(&mut self, s: &Sample) -> Calibrated {
        let mut out = self.apply_vectors(s);
        self.add_attitude(&mut out);
        out
    }

    /// [`Calibrator::apply`] without the roll, pitch and heading (left `None`): for a caller that
    /// averages the vectors and takes the angles of the means, at its output rate, rather than
    /// three arctangents per sample. [`Calibrator::add_attitude`] adds them later if wanted.
    pub(crate) fn apply_vectors(&mut self, s: &Sample) -> Calibrated {
        let a = s.accel_mps2.map(|v| self.accel.map_or(v, |c| c.apply(&v)));
        let m = s.mag_ut.map(|v| self.mag.map_or(v, |c| c.apply(&v)));
        let g = s.gyro_rad_s.map(|v| match self.gyro_bias {
            Some(b) => [v[0] - b[0], v[1] - b[1], v[2] - b[2]],
            None => v,
        });
        if a.is_some() {
            self.last_accel = a;
        }
        if m.is_some() {
            self.last_mag = m;
        }
        Calibrated {
            t_s: s.t_s,
            segment: s.segment,
            accel_mps2: a,
            gyro_rad_s: g,
            mag_ut: m,
            ..Default::default()
        }
    }

    /// Set `out`'s roll, pitch and heading from the latest calibrated accelerometer and
    /// magnetometer seen by [`Calibrator::apply_vectors`] (none before an accelerometer reading).
    pub(crate) fn add_attitude(&self, out: &mut Calibrated) {
        if let Some(f) = self.last_accel {
            let (r, p) = crate::attitude::roll_pitch_deg(&f);
            out.roll_deg = Some(r);
            out.pitch_deg = Some(p);
            if let Some(mv) = self.last_mag {
                let h =
                    crate::attitude::heading_deg(&mv, r, p) + self.declination_deg.unwrap_or(0.0);
                out.heading_deg = Some(crate::attitude::wrap360(h));
            }
        }
    }
}

/// `full12` magnetometer: the symmetric (sym9) fit, then the rotation that norms cannot see, from the
/// gravity-field angle at static poses against the calibrated accelerometer (matrix = R S).
fn mag_rotation_from_dip(mag: &mut SensorResult, accel: &SensorResult, poses: &[Pose]) {
    let Some(mcal) = mag.calibration else { return };
    let fail = |mag: &mut SensorResult, d: String| {
        set_fail(&mut mag.report, FitFailure::NotIdentifiable, d);
        mag.report.model = CalModel::Full12;
        mag.calibration = None;
    };
    let Some(acal) = accel.calibration else {
        return fail(mag, "full12 needs an accepted accelerometer calibration to fix the rotation from the dip angle".into());
    };
    let (mut gs, mut ms) = (vec![], vec![]);
    for p in poses {
        if let Some(m) = p.mag {
            let f = acal.apply(&p.accel);
            gs.push([-f[0], -f[1], -f[2]]);
            ms.push(mcal.apply(&m));
        }
    }
    match crate::calib::fit::fit_dip_rotation(&gs, &ms) {
        Some((r, _dip, _rms, cond)) if cond.is_finite() && cond < 1e8 => {
            let m = r * mcal.matrix3();
            let cal = Calibration { model: ModelKind::Full12, offset: mcal.offset, matrix: crate::calib::model::mat_to_rows(&m) };
            mag.report.model = CalModel::Full12;
            mag.report.matrix = cal.matrix;
            mag.calibration = Some(cal);
            mag.dirs_after = mag.dirs_after.iter().map(|v| crate::attitude::rotate(&r, v)).collect();
        }
        _ => fail(mag, format!("full12: {} static poses with accel and mag do not fix the rotation (need 6+ in varied attitudes)", gs.len())),
    }
}

#[cfg(test)]
mod tests {

    /// Deterministic standard normal numbers (a 64-bit LCG through Box-Muller) from `seed`.
    fn gaussian(mut seed: u64) -> impl FnMut() -> f64 {
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

    use super::*;

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

    /// A sensor resting for a third of a run (a vehicle on the ground streamed at a low rate)
    /// repeats one y reading exactly while x and z jitter by a count: not a stuck axis. The same
    /// y value held while x and z sweep is one.
    #[test]
    fn axis_fault_tells_a_resting_sensor_from_a_stuck_axis() {
        let sweep: Vec<Vec3> = (0..200)
            .map(|i| {
                let (a, b) = (i as f64 * 0.37, i as f64 * 0.11);
                [
                    40.0 * a.cos() * b.cos(),
                    40.0 * a.sin() * b.cos(),
                    40.0 * b.sin(),
                ]
            })
            .collect();
        let mut resting = sweep.clone();
        resting.extend((0..100).map(|i| {
            [
                -1.4 + 0.1 * (i % 2) as f64,
                -17.0,
                28.8 - 0.1 * (i % 3) as f64,
            ]
        }));
        assert_eq!(axis_fault(&resting), None);
        let mut stuck = sweep.clone();
        stuck.extend(sweep.iter().take(100).map(|p| [p[0], -17.0, p[2]]));
        let why = axis_fault(&stuck).expect("a stuck axis");
        assert!(
            why.contains("axis y reads exactly -17 in 100 of 300"),
            "{why}"
        );
    }

    /// Readings of a compass read in whole milligauss (ArduPilot's SCALED_IMU), in uT: the true
    /// field in counts plus Gaussian noise of `sigma_counts` per axis, rounded to a count.
    fn milligauss_readings(
        field_counts: impl Iterator<Item = Vec3>,
        sigma_counts: Vec3,
        seed: u32,
    ) -> Vec<Vec3> {
        let mut x = seed;
        let mut uniform = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as f64 / u32::MAX as f64
        };
        field_counts
            .map(|f| {
                let mut r = [0.0; 3];
                for k in 0..3 {
                    // Twelve uniforms less 6: mean 0, variance 1, close to Gaussian.
                    let g = (0..12).map(|_| uniform()).sum::<f64>() - 6.0;
                    r[k] = 0.1 * (f[k] + sigma_counts[k] * g).round();
                }
                r
            })
            .collect()
    }

    /// A field of 500 counts (50 uT) about a hard-iron offset, turned through many directions, in
    /// counts: `steps` readings.
    fn turning_counts(steps: usize) -> impl Iterator<Item = Vec3> {
        (0..steps).map(|i| {
            let (a, b) = (i as f64 * 0.37, i as f64 * 0.11);
            [
                120.0 + 500.0 * a.cos() * b.cos(),
                -40.0 + 500.0 * a.sin() * b.cos(),
                380.0 + 500.0 * b.sin(),
            ]
        })
    }

    /// A compass read in whole milligauss that sits still repeats its readings: one x, y and z
    /// count in most of them when its noise is under a count, and its lowest and highest readings
    /// in many. Its other axes' noise moving them by several counts between readings (as on an
    /// ArduSub ROV at rest) does not make a quiet axis stuck either. Neither is an axis fault.
    #[test]
    fn axis_fault_passes_a_still_compass_read_in_whole_counts() {
        let still = |_| [123.4, -45.7, 387.2];
        let quiet = milligauss_readings((0..300).map(still), [0.25; 3], 0x2545_F491);
        assert_eq!(axis_fault(&quiet), None);
        // Its lowest and highest readings (x: 12.3 and 12.4 uT) hold far more than 3% of them:
        // not saturated, the ends of its noise.
        let lowest_x = quiet.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
        let at_lowest = quiet.iter().filter(|p| p[0] == lowest_x).count();
        let highest_x = quiet.iter().map(|p| p[0]).fold(f64::NEG_INFINITY, f64::max);
        let at_highest = quiet.iter().filter(|p| p[0] == highest_x).count();
        assert!(at_lowest.min(at_highest) > 30, "{at_lowest} {at_highest}");
        // x quiet (0.7 counts rms), y and z noisy (3 counts rms): most steps move y or z by more
        // than 4 counts, and x stays on its most frequent count across about half of them.
        let still = |_| [128.0, -45.7, 387.2];
        let noisy = milligauss_readings((0..300).map(still), [0.7, 3.0, 3.0], 0x1B87_3593);
        assert_eq!(axis_fault(&noisy), None);
    }

    /// The same compass turning with its y axis stuck on one count for the last third: stuck while
    /// the vehicle turns, in whole counts as in floating point
    /// (`axis_fault_tells_a_resting_sensor_from_a_stuck_axis`).
    #[test]
    fn axis_fault_names_an_axis_stuck_while_the_compass_turns() {
        let mut stuck = milligauss_readings(turning_counts(300), [0.7; 3], 0x2545_F491);
        assert_eq!(axis_fault(&stuck), None, "the turn itself");
        assert!(stuck.iter().all(|p| p[1] != -12.5));
        for p in stuck.iter_mut().skip(200) {
            p[1] = -12.5;
        }
        let why = axis_fault(&stuck).expect("a stuck axis");
        // 99 steps from the stuck value; over one of them x and z move too little to count as a
        // turn (less than 4 times the smallest move they make over these steps).
        let expected = "axis y reads exactly -12.5 in 100 of 300 points and stays on it across 98 \
                        of the 98 steps from it over which the vehicle turns";
        assert!(why.contains(expected), "{why}");
        assert!(why.contains("stuck part of the time"), "{why}");
    }

    /// An axis clipped at the sensor's range while the compass turns is saturated, whether its
    /// readings are whole counts or floating point.
    #[test]
    fn axis_fault_names_a_clipped_axis() {
        let turning = milligauss_readings(turning_counts(300), [0.7; 3], 0x2545_F491);
        let clipped: Vec<Vec3> = turning
            .iter()
            .map(|p| [p[0].min(45.0), p[1], p[2]])
            .collect();
        let why = axis_fault(&clipped).expect("a clipped axis");
        assert!(why.contains("axis x reads exactly 45 in"), "{why}");
        assert!(why.contains("saturated"), "{why}");
        let float: Vec<Vec3> = turning_counts(300)
            .map(|f| [f[0] * 0.1, (f[1] * 0.1).max(-30.0), f[2] * 0.1])
            .collect();
        let why = axis_fault(&float).expect("a clipped axis");
        assert!(why.contains("axis y reads exactly -30 in"), "{why}");
        assert!(why.contains("saturated"), "{why}");
    }

    #[test]
    fn frequent_value_agrees_with_sorting_and_counting() {
        let mut x = 0x2545_F491u32;
        for case in 0..400 {
            let n = 5 + case % 60;
            let vals: Vec<f64> = (0..n)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    // Few distinct values in some cases, many in others.
                    (x % [3, 5, 8, 40][case % 4]) as f64 - 1.0
                })
                .collect();
            let mut sorted = vals.clone();
            sorted.sort_by(|a, b| a.total_cmp(b));
            let (mut best, mut run, mut val) = (0, 0, f64::NAN);
            for i in 0..n {
                run = if i > 0 && sorted[i] == sorted[i - 1] {
                    run + 1
                } else {
                    1
                };
                if run > best {
                    best = run;
                    val = sorted[i];
                }
            }
            let expected = (best as f64 >= 0.2 * n as f64).then_some((val, best));
            assert_eq!(
                frequent_value(vals.iter().copied(), 0.2),
                expected,
                "case {case}: {vals:?}"
            );
        }
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
