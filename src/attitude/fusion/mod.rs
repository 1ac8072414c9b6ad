//! Orientation filter for 9D (gyro + accel + mag) and 6D (gyro + accel) data: a unit quaternion
//! sensor -> world per sample (world ENU or NED, selectable), plus roll/pitch/heading. Pure math, no I/O.
//!
//! # Design
//! The starting point is the linear quaternion Kalman filter of Chu et al., "Magnetic Orientation
//! System Based on Magnetometer, Accelerometer and Gyroscope": the gyroscope drives the prediction
//! and a quaternion built from accelerometer (tilt) and magnetometer (heading) is the measurement. Here
//! that filter is written in error-state form: the state is the small rotation `dtheta` (world axes)
//! that takes the predicted attitude to the measured one, plus the gyro bias error (and the gyro's
//! scale error as a consider state, below). With the measurement
//! quaternion split into its tilt part and its rotation about the vertical, the measurement equations
//! stay linear (H is a selection matrix, as in Chu et al.) and no Jacobian is needed:
//!
//! * tilt: `z = (a_w.y, -a_w.x) / g = (dtheta_x, dtheta_y)` with `a_w` the specific force rotated into
//!   the world frame by the prediction. Applied every accelerometer sample, the Kalman update averages
//!   the horizontal specific force **in the world frame**, where a bounded motion's linear acceleration
//!   averages out (it is the derivative of a bounded velocity), not in the sensor frame where it does not.
//! * heading: `z = azimuth(m_w) - declination = dtheta_z`, the azimuth of the horizontal field.
//!
//! Around that core, for robustness:
//! * **rest detection** (gyro and accel within thresholds of their low-passed values for `rest_min_s`):
//!   at rest, each gyro sample is a direct measurement of the bias (`z = omega - b`), and the tilt
//!   and heading measurements are trusted more (`acc_rest_noise_mps2`, `mag_rest_heading_noise_deg`:
//!   no linear acceleration and no magnetometer timing error then);
//! * **online gyro bias estimation** in motion through the Kalman cross-covariance between attitude
//!   error and bias (tilt observes the two horizontal world axes, heading the vertical one);
//! * **linear acceleration**: the tilt noise grows by the slow RMS deviation of |f| from g and by
//!   the RMS of the world-frame linear acceleration `R f - g z` (`acc_lin_tau_s`), one for one: a
//!   linear acceleration `a` puts an error of `a` on the horizontal force the tilt measures, so it
//!   is the measurement's noise, with no gain to choose (a gain of 0.25, chosen on BROAD, let the
//!   simulated centrifuge tilt the estimate by 7 deg; BROAD itself moves 0.734 to 0.75x VQF). Samples
//!   far from g correct nothing. The second term is what sees sustained horizontal translation
//!   and vibration, which change |f| only to second order. Both are mean squares, even in the
//!   acceleration, so over a back-and-forth motion the weights do not favour one direction and the
//!   world-frame average the tilt correction relies on stays unbiased. Laidig, Caruso, Cereatti and
//!   Seel ("BROAD - A Benchmark for Robust Inertial Orientation Estimation", 2021) show that the
//!   inclination of filters with a fixed accelerometer gain suffers most in the translation and
//!   vibration trials; VQF (Laidig and Seel, "VQF: Highly Accurate IMU Orientation Estimation with
//!   Bias Estimation and Magnetic Disturbance Rejection", 2023) low-passes the accelerometer in an
//!   almost-inertial frame instead; the adaptive noise here is the Kalman counterpart;
//! * **world-frame low-pass** (`acc_lp_tau_s`): before the tilt update, the specific force in the
//!   world frame goes through a second-order Butterworth low-pass, as VQF does in its
//!   almost-inertial frame. A first-order correction alone (the Kalman gain) lets a linear
//!   acceleration through at -20 dB per decade above its corner; with the low-pass in front it
//!   falls at -60 above the low-pass's. As in VQF, the low-pass runs in an almost-inertial frame:
//!   the attitude integrated from the gyro alone (`q_gyro`, started at the first tilt), whose frame
//!   no correction turns. Its output is turned into the world with the correction accumulated so
//!   far (`q q_gyro^-1`), so the corrections never have to turn the filter's state;
//! * **magnetic disturbance**: field norm and dip (with the current tilt) are compared with reference
//!   values learned from the data (initialised from the first seconds, then tracked slowly while
//!   undisturbed); a disturbed field is not used, and a new steady field is accepted after a while
//!   (as VQF's norm and dip tests); a gate on the heading innovation (`mag_gate_deg` plus
//!   `mag_gate_sigma` standard deviations of the heading state) rejects what slips through, for
//!   `mag_gate_timeout_s` at most;
//! * **heading only about the vertical**: the heading update's gain is zero on the two tilt states, and
//!   the tilt update's gain is zero on the heading state, so a bad field cannot tilt the inclination and
//!   a linear acceleration cannot turn the heading;
//! * **rotation-rate dependent process noise**: gyro scale and misalignment errors grow with the rate;
//! * **gyro scale learnt between rests** (`gyro_scale_sigma`): the gyro integrated from one rest to
//!   the next must turn the first rest's attitude (gravity and field, TRIAD) into the second's
//!   (Tedaldi, Pretto and Menegatti, 2014); each pair of rests is one least-squares step on the
//!   per-axis scale. It matters where the heading is held by the gyro through long motions: BROAD's
//!   IMU under-reads by 0.3 to 0.5 % per axis, which cost its slow rotation with breaks 1.0 deg of
//!   total RMSE (1.80 deg without the scale, 0.80 with it);
//! * **the scale's uncertainty carried into the attitude** (a consider state): the scale error
//!   left (1-sigma `gyro_scale_sigma` until a pair of rests narrows it) turns into attitude error
//!   in proportion to the angle turned, `dtheta' = R diag(w) ds`, and in the same direction for as
//!   long as the rotation keeps its sense. The covariance carries the three scale errors with that
//!   coupling, so the attitude's uncertainty, and with it the weight of gravity and the field,
//!   grows with the angle turned since they last set the attitude; the Kalman updates never move
//!   the scale itself (the field's errors in motion are too slow and too large to learn it from:
//!   estimating it there took BROAD's scale to the wrong side of 1), which only the rests teach.
//!   Without it the heading held the gyro's drift through ten turns in one sense: BROAD's slow
//!   rotation A (no rest in its two minutes of motion), through the replay's calibration, drifted
//!   5 deg from a field that was right to 1 deg (3.49 deg total RMSE, 1.76x VQF's; 2.46 and
//!   1.24x with it);
//! * **magnetometer latency**: the field is rotated into the world with the attitude of `mag_delay_s`
//!   ago (many IMUs deliver the magnetometer late); the delay is a setting or estimated online from the
//!   IMU data alone (the world-frame field must not move with the rotation rate).
//!
//! # What bounds each correction
//! No correction can be switched off for long, and nothing learnt can run away:
//! * **Tilt.** Its noise is `acc_noise_mps2` plus the slow RMS of the linear acceleration
//!   (time constants `intensity_tau_s`, `acc_lin_tau_s`): it grows with the motion and falls back
//!   within a few of those seconds after it, so the correction slows under acceleration but never
//!   stops. A sample skips the correction only while its own force is more than
//!   `acc_reject_mps2` from g; the low-pass in front sees every sample, so the average it takes
//!   stays unbiased whatever is skipped.
//! * **Clipped gyro.** A reading at `gyro_range_rad_s` grows the attitude's uncertainty by what the
//!   clipped axis may have turned beyond it; gravity and the field then hold the attitude (on the
//!   simulated saturated spin the error stays under 6 deg, against 180 without this).
//! * **Heading.** A field that fails the norm or dip test is set aside for at most
//!   `mag_new_field_s`, after which a steady new field becomes the reference; the innovation gate
//!   opens after `mag_gate_timeout_s` of rejections.
//! * **Bias.** Learnt at rest only from readings the rest still holds half a second later, never
//!   from a tilt under acceleration, never within `CLIP_SETTLE_S` of a clipped reading, and
//!   clipped at `bias_clip` per axis.
//! * **Gyro scale.** Learnt only between two rests, each step gated by a chi-square test and
//!   the result held within 10 % of 1 (`SCALE_MAX_DEV`); its uncertainty, carried in the
//!   covariance, never grows (no update moves it, and it has no process noise).
//!
//! Internally the world frame is ENU (z up): at rest the specific force points up, `(0, 0, +g)`.
//! The sensor frame is whatever the sensor's axes are (FRD for a flight controller's body, z up for
//! BROAD's sensor): only the specific-force convention matters (an accelerometer at rest reads +g along
//! the axis that points up). NED output is `C * q_enu` with `C` the ENU -> NED rotation (180 deg about
//! (1, 1, 0)/sqrt(2)).

mod delay;
mod heading;
mod kalman;
mod lowpass;
mod magref;
mod rest;
mod scale;
mod state;
#[cfg(test)]
mod tests;
mod tilt;

use crate::types::{Sample, Vec3, STANDARD_GRAVITY_MPS2};
use delay::DelayEst;
use lowpass::Butter3;
use magref::MagRef;
use nalgebra::{SMatrix, SVector, UnitQuaternion, Vector3};
use rest::{Rest, REST_TAU_S};
use scale::ScaleEst;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

pub use delay::MagDelayConfig;
pub use heading::HeadingConfig;
pub use kalman::{BiasConfig, ProcessConfig};
pub use magref::MagRefConfig;
pub use rest::RestConfig;
pub use scale::GyroScaleConfig;
pub use state::FilterState;
pub use tilt::TiltConfig;

/// Error states: the attitude (3, world axes), the gyro bias (3, sensor axes, rad/s) and the
/// gyro's per-axis scale (3, sensor axes, relative; a consider state: carried in the covariance,
/// never moved by an update).
const NS: usize = 9;
/// Index of the first scale state.
const SCALE0: usize = 6;
type MatrixN = SMatrix<f64, NS, NS>;
type VectorN = SVector<f64, NS>;

/// The world frame of the output quaternion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum WorldFrame {
    /// North, East, Down (the project's convention; MAVLink ATTITUDE).
    #[default]
    Ned,
    /// East, North, Up (BROAD's reference).
    Enu,
}

/// Filter settings, each with its unit, its default and the reason for that default:
/// - **Physical**: a property of the sensor, the Earth or the motion, with the reason given.
/// - **VQF's value**: the same test as VQF's (Laidig and Seel, 2023), with its default.
/// - **Tuned**: chosen on the eighteen BROAD trials by `cargo bench --bench broad -- --tune`
///   (a coordinate search, see that bench) from the start point `tests/common/untuned.rs`. The
///   tuned defaults are scored beside the untuned ones on data the tuning never saw: the stress
///   simulations (`cargo test --release --test stress -- --nocapture`) and two real PX4 flights
///   against motion capture (`cargo test --release --test mocap_flights -- --nocapture`). There
///   the tuned set is better in the shake and the saturated spin and worse in the centrifuge, and
///   on the real flights the two are within 0.1 deg (figures in the README).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// World frame of [`OrientationFilter::quaternion`]. Default: NED, the project's convention.
    pub world: WorldFrame,
    /// Use the magnetometer (9D); false = 6D, heading from the gyro alone. Default: true.
    pub use_mag: bool,
    /// Magnetic declination, degrees east: the world's north is true north when set, magnetic when
    /// 0. Default: 0 (physical: the place's, from a world magnetic model; unknown until given).
    pub declination_deg: f64,
    /// Gravity magnitude, m/s^2. Default: 9.80665 (physical: standard gravity; the place's own
    /// differs by at most 0.3 %).
    pub gravity_mps2: f64,
    /// Prediction: the gyro's noise and range; its keys sit at the top level. Default: [`ProcessConfig::default`].
    #[serde(flatten)]
    pub process: ProcessConfig,
    /// The gyro bias; its keys sit at the top level. Default: [`BiasConfig::default`].
    #[serde(flatten)]
    pub bias: BiasConfig,
    /// The tilt correction; its keys sit at the top level. Default: [`TiltConfig::default`].
    #[serde(flatten)]
    pub tilt: TiltConfig,
    /// The heading correction; its keys sit at the top level. Default: [`HeadingConfig::default`].
    #[serde(flatten)]
    pub heading: HeadingConfig,
    /// The magnetic disturbance tests; its keys sit at the top level. Default: [`MagRefConfig::default`].
    #[serde(flatten)]
    pub mag_ref: MagRefConfig,
    /// The magnetometer's latency; its keys sit at the top level. Default: [`MagDelayConfig::default`].
    #[serde(flatten)]
    pub mag_delay: MagDelayConfig,
    /// The gyro scale learnt between rests; its keys sit at the top level. Default: [`GyroScaleConfig::default`].
    #[serde(flatten)]
    pub scale: GyroScaleConfig,
    /// Rest detection; its keys sit at the top level. Default: [`RestConfig::default`].
    #[serde(flatten)]
    pub rest: RestConfig,
}

impl Default for FusionConfig {
    fn default() -> Self {
        FusionConfig {
            world: WorldFrame::Ned,
            use_mag: true,
            declination_deg: 0.0,
            gravity_mps2: STANDARD_GRAVITY_MPS2,
            process: ProcessConfig::default(),
            bias: BiasConfig::default(),
            tilt: TiltConfig::default(),
            heading: HeadingConfig::default(),
            mag_ref: MagRefConfig::default(),
            mag_delay: MagDelayConfig::default(),
            scale: GyroScaleConfig::default(),
            rest: RestConfig::default(),
        }
    }
}

/// One output of the filter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orientation {
    /// Sensor -> world rotation in the configured world frame.
    pub q: UnitQuaternion<f64>,
    /// Roll, pitch, heading (deg; heading in [0, 360)): ZYX angles of the sensor -> NED rotation.
    pub roll_deg: f64,
    pub pitch_deg: f64,
    pub heading_deg: f64,
}

/// Sensor -> ENU to sensor -> NED: `q_ned = C * q_enu`, C = 180 deg about (1, 1, 0)/sqrt(2).
pub fn enu_to_ned() -> UnitQuaternion<f64> {
    let s = std::f64::consts::FRAC_1_SQRT_2;
    UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(0.0, s, s, 0.0))
}

fn v3(v: &Vec3) -> Vector3<f64> {
    Vector3::new(v[0], v[1], v[2])
}

/// Shortest rotation taking unit vector `a` onto unit vector `b`.
fn rotation_between(a: &Vector3<f64>, b: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(a, b).unwrap_or_else(|| {
        // Opposite vectors: 180 deg about any axis perpendicular to `a`.
        let axis = if a.x.abs() < 0.9 {
            a.cross(&Vector3::x())
        } else {
            a.cross(&Vector3::y())
        };
        UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), std::f64::consts::PI)
    })
}

/// The rotation by the rotation vector `v`, for the small vectors of a correction: the quaternion
/// `(1, v / 2)` normalised, which differs from the exact one by less than `|v|^3 / 12` rad (below
/// 1e-7 rad for the 2 deg corrections seen after a clipped gyro) at no trigonometric cost.
fn small_rotation(v: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        1.0,
        0.5 * v.x,
        0.5 * v.y,
        0.5 * v.z,
    ))
}

/// The orientation filter. Feed samples in time order with [`OrientationFilter::update`].
#[derive(Debug, Clone)]
pub struct OrientationFilter {
    cfg: FusionConfig,
    /// Sensor -> ENU.
    q: UnitQuaternion<f64>,
    /// Gyro bias, rad/s, sensor axes.
    bias: Vector3<f64>,
    /// Covariance of [dtheta (world), dbias (sensor), dscale (sensor, relative)]; the scale block
    /// is `ScaleEst::p`, the scale's own uncertainty.
    p: MatrixN,
    tilt_init: bool,
    heading_init: bool,
    rest: Rest,
    /// Gyro samples of the last [`REST_TAU_S`] (time, reading), waiting to become bias
    /// measurements: a sample is used only if the rest still holds `REST_TAU_S` after it, so the
    /// first moments of a motion, which the rest detector sees only after its low-pass, never count.
    rest_gyro: VecDeque<(f64, Vector3<f64>)>,
    mag_ref: MagRef,
    delay: DelayEst,
    scale: ScaleEst,
    /// Recent (time, attitude) for the magnetometer latency.
    history: VecDeque<(f64, UnitQuaternion<f64>)>,
    /// Time and time segment of the last sample.
    last_t: Option<(f64, u32)>,
    last_gyro: Vector3<f64>,
    t: f64,
    mag_used: bool,
    /// How long every heading innovation has been gated out, s.
    gated_s: f64,
    /// Slow mean squares of the rotation rate and of | |f| - g |, for the noise levels.
    rate_ms: f64,
    acc_ms: f64,
    /// Mean square of the world-frame linear acceleration, (m/s^2)^2 (`acc_lin_tau_s`).
    lin_ms: f64,
    /// Sensor -> almost-inertial frame: the attitude integrated from the (bias-corrected) gyro
    /// alone since the first tilt, never corrected.
    q_gyro: UnitQuaternion<f64>,
    /// The specific force in the almost-inertial frame, low-passed (`acc_lp_tau_s`).
    acc_lp: Butter3,
    /// Time since the last clipped gyro reading, s (infinite before the first), and whether the
    /// almost-inertial frame was turned by clipped readings since the low-pass last started.
    since_clip_s: f64,
    lp_clipped: bool,
    /// How many axes of the last gyro reading are clipped (counted once per reading).
    clipped_now: usize,
}

impl OrientationFilter {
    pub fn new(cfg: FusionConfig) -> Self {
        let mut p = MatrixN::zeros();
        let scale = ScaleEst::new(cfg.scale.gyro_scale_sigma, cfg.scale.gyro_scale_path_sd);
        for i in 0..3 {
            p[(i, i)] = 1.0;
            p[(i + 3, i + 3)] = cfg.bias.bias_sigma_init.powi(2);
        }
        p.fixed_view_mut::<3, 3>(SCALE0, SCALE0).copy_from(&scale.p);
        OrientationFilter {
            cfg,
            q: UnitQuaternion::identity(),
            bias: Vector3::zeros(),
            p,
            tilt_init: false,
            heading_init: false,
            rest: Rest::default(),
            rest_gyro: VecDeque::new(),
            mag_ref: MagRef::default(),
            delay: DelayEst::default(),
            scale,
            history: VecDeque::new(),
            last_t: None,
            last_gyro: Vector3::zeros(),
            t: 0.0,
            mag_used: false,
            gated_s: 0.0,
            rate_ms: 0.0,
            acc_ms: 0.0,
            lin_ms: 0.0,
            q_gyro: UnitQuaternion::identity(),
            acc_lp: Butter3::default(),
            since_clip_s: f64::INFINITY,
            lp_clipped: false,
            clipped_now: 0,
        }
    }

    pub fn config(&self) -> &FusionConfig {
        &self.cfg
    }

    /// Feed one sample: the time step is taken from `t_s` (the first sample, the first of a new
    /// time segment and steps outside (0, 1] s use `default_dt`).
    pub fn update_sample(&mut self, s: &Sample, default_dt: f64) {
        let dt = match self.last_t {
            Some((t0, seg)) if seg == s.segment && s.t_s - t0 > 0.0 && s.t_s - t0 <= 1.0 => {
                s.t_s - t0
            }
            _ => default_dt,
        };
        if self.last_t.is_some_and(|(_, seg)| seg != s.segment) {
            // What the gyro turned through in a gap is unknown: no rest-to-rest step spans it.
            self.scale.break_chain();
        }
        self.last_t = Some((s.t_s, s.segment));
        self.update(
            dt,
            s.gyro_rad_s.as_ref(),
            s.accel_mps2.as_ref(),
            s.mag_ut.as_ref(),
        );
    }

    /// Feed one instant: `dt` since the previous one, and whichever readings are new.
    /// Gyro in rad/s, accel specific force in m/s^2, mag in any unit (uT).
    pub fn update(&mut self, dt: f64, gyro: Option<&Vec3>, acc: Option<&Vec3>, mag: Option<&Vec3>) {
        let dt = if dt.is_finite() && dt > 0.0 { dt } else { 0.01 };
        self.t += dt;
        let gyro = gyro.filter(|g| crate::types::is_finite3(g)).map(v3);
        let acc = acc.filter(|a| crate::types::is_finite3(a)).map(v3);
        let mag = mag
            .filter(|m| crate::types::is_finite3(m) && self.cfg.use_mag)
            .map(v3);
        let bias_sd = (self.p[(3, 3)] + self.p[(4, 4)] + self.p[(5, 5)]).sqrt();
        self.rest.update(
            gyro.as_ref(),
            acc.as_ref(),
            dt,
            (&self.bias, bias_sd),
            &self.cfg,
        );
        let a_int = (dt / self.cfg.process.intensity_tau_s.max(dt)).min(1.0);
        if let Some(g) = gyro {
            self.last_gyro = g;
            self.rate_ms += (g.norm_squared() - self.rate_ms) * a_int;
            self.clipped_now = self.clipped_axes(&g);
            if self.clipped_now > 0 {
                self.since_clip_s = 0.0;
            } else {
                self.since_clip_s += dt;
            }
        }
        if let Some(a) = acc {
            self.acc_ms += ((a.norm() - self.cfg.gravity_mps2).powi(2) - self.acc_ms) * a_int;
        }
        let dq = if !self.tilt_init {
            match acc {
                Some(a) if a.norm() > 1e-6 => self.init_tilt(&a),
                _ => return,
            }
            UnitQuaternion::identity()
        } else {
            let dq = self.predict(dt);
            if let Some(a) = acc {
                let lin = self.q * a - Vector3::new(0.0, 0.0, self.cfg.gravity_mps2);
                let a_lin = (dt / self.cfg.tilt.acc_lin_tau_s.max(dt)).min(1.0);
                self.lin_ms += (lin.norm_squared() - self.lin_ms) * a_lin;
                self.tilt_update(&a, dt);
            }
            dq
        };
        if let Some(g) = gyro {
            self.rest_gyro.push_back((self.t, g));
        }
        while let Some(&(t, g)) = self.rest_gyro.front() {
            if self.t - t < REST_TAU_S {
                break;
            }
            self.rest_gyro.pop_front();
            if self.rest.rest {
                self.bias_update(&g);
            }
        }
        if self.scale.enabled() {
            let w = self.last_gyro - self.bias;
            let mag = mag.as_ref().map(|m| (m, !self.mag_ref.disturbed));
            let steps = self.scale.steps;
            self.scale
                .update(self.rest.rest, &w, &dq, acc.as_ref(), mag, dt);
            if self.scale.steps != steps {
                self.scale_learnt();
            }
        }
        // Keep the attitude history for the magnetometer latency.
        self.history.push_back((self.t, self.q));
        let keep = self
            .cfg
            .mag_delay
            .mag_delay_max_s
            .max(self.cfg.mag_delay.mag_delay_s.unwrap_or(0.0))
            + 2.0 * dt;
        while self
            .history
            .front()
            .is_some_and(|(t, _)| self.t - *t > keep)
        {
            self.history.pop_front();
        }
        self.mag_used = false;
        if let Some(m) = mag {
            self.mag_update(&m, dt);
        }
    }

    fn init_tilt(&mut self, a: &Vector3<f64>) {
        self.q = rotation_between(&a.normalize(), &Vector3::z());
        self.q_gyro = self.q;
        self.tilt_init = true;
        let s2 = 0.05f64.powi(2);
        self.p[(0, 0)] = s2;
        self.p[(1, 1)] = s2;
        // Heading is free until the first field measurement (kept small in 6D: it is unobservable).
        self.p[(2, 2)] = if self.cfg.use_mag { 1.0 } else { 1e-6 };
    }

    /// Sensor -> world quaternion in the configured world frame.
    pub fn quaternion(&self) -> UnitQuaternion<f64> {
        match self.cfg.world {
            WorldFrame::Enu => self.q,
            WorldFrame::Ned => enu_to_ned() * self.q,
        }
    }

    /// Sensor -> ENU quaternion whatever the configured frame.
    pub fn quaternion_enu(&self) -> UnitQuaternion<f64> {
        self.q
    }

    /// The current output (quaternion and roll/pitch/heading).
    pub fn orientation(&self) -> Orientation {
        let e = crate::attitude::euler_zyx_deg(&(enu_to_ned() * self.q));
        Orientation {
            q: self.quaternion(),
            roll_deg: e[0],
            pitch_deg: e[1],
            heading_deg: e[2],
        }
    }

    /// Gyro bias estimate, rad/s, sensor axes.
    pub fn bias(&self) -> Vec3 {
        [self.bias.x, self.bias.y, self.bias.z]
    }

    /// 1-sigma of the bias estimate per axis, rad/s.
    pub fn bias_sigma(&self) -> Vec3 {
        [
            self.p[(3, 3)].sqrt(),
            self.p[(4, 4)].sqrt(),
            self.p[(5, 5)].sqrt(),
        ]
    }

    /// True while the rest detector sees the sensor still.
    pub fn at_rest(&self) -> bool {
        self.rest.rest
    }

    /// True while the field is judged disturbed (norm or dip off the reference).
    pub fn mag_disturbed(&self) -> bool {
        self.mag_ref.disturbed
    }

    /// Whether the last magnetometer sample corrected the heading.
    pub fn mag_used(&self) -> bool {
        self.mag_used
    }

    /// Reference field norm (input units) and dip (deg), once learned.
    pub fn mag_reference(&self) -> Option<(f64, f64)> {
        self.mag_ref
            .known
            .then(|| (self.mag_ref.norm, self.mag_ref.dip.to_degrees()))
    }

    /// The magnetometer latency in use, s.
    pub(crate) fn mag_delay_s(&self) -> f64 {
        self.cfg
            .mag_delay
            .mag_delay_s
            .unwrap_or_else(|| self.delay.estimate(self.cfg.mag_delay.mag_delay_max_s))
    }

    /// True once the first accelerometer sample has set the tilt.
    pub(crate) fn initialized(&self) -> bool {
        self.tilt_init
    }

    /// The gyro fed to the filter has `removed_rad_s` more bias taken out from now on (a new gyro
    /// calibration upstream): the residual bias estimate moves by as much the other way, its
    /// uncertainty unchanged, so the filter neither removes the bias twice nor learns it again.
    pub(crate) fn gyro_bias_removed(&mut self, removed_rad_s: &Vec3) {
        if crate::types::is_finite3(removed_rad_s) {
            self.bias -= v3(removed_rad_s);
        }
    }
}

/// Run the filter over a log: one orientation per sample (identity until the first accel sample).
/// The nominal step for the first sample is the median sample interval.
pub fn run(samples: &[Sample], cfg: &FusionConfig) -> Vec<Orientation> {
    let dt = median_dt(samples);
    let mut f = OrientationFilter::new(*cfg);
    samples
        .iter()
        .map(|s| {
            f.update_sample(s, dt);
            f.orientation()
        })
        .collect()
}

/// Median interval between consecutive sample times (0.01 s when it cannot be told).
pub fn median_dt(samples: &[Sample]) -> f64 {
    let mut d: Vec<f64> = samples
        .windows(2)
        .take(2000)
        .map(|w| w[1].t_s - w[0].t_s)
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if d.is_empty() {
        return 0.01;
    }
    d.sort_by(|a, b| a.total_cmp(b));
    d[d.len() / 2]
}
