//! A warm-up at rest: the vehicle still at a fixed attitude while its IMUs warm from about 15 to
//! about 40 C (a first-order rise of the die temperature; each sensor's own temperature reading
//! lags its die by a first-order lag), each IMU instance with hidden cubic bias curves of
//! temperature on every accelerometer and gyro axis, and white noise. Optionally the vehicle is
//! picked up and turned part-way through. Readings in the sensor axes (here the body's), no
//! magnetometer, no earth rotation.

use crate::calib::tempcal::poly::Cubic;
use crate::types::{Sample, STANDARD_GRAVITY_MPS2};
use nalgebra::{Rotation3, Vector3};
use rand::SeedableRng;
use rand_distr::Distribution;
use serde::{Deserialize, Serialize};

/// A turn in the middle of the warm-up (the vehicle picked up and set down at another attitude).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WarmupTurn {
    /// Start, s from the beginning; how long, s; the angle about the body x axis, deg.
    pub at_s: f64,
    pub duration_s: f64,
    pub angle_deg: f64,
}

/// The warm-up's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarmupSettings {
    /// Length of the run, s. Default 1500 (five time constants).
    pub duration_s: f64,
    /// Sample rate, Hz. Default 50.
    pub rate_hz: f64,
    /// Die temperature at the start and where it settles, deg C. Default 15 and 40.
    pub start_c: f64,
    pub end_c: f64,
    /// Time constant of the warm-up, s. Default 300.
    pub tau_s: f64,
    /// Lag of instance 0's temperature reading behind its die, s; each further instance's is
    /// 2 s longer. Default 3.
    pub sensor_lag_s: f64,
    /// IMU instances. Default 3.
    pub instances: usize,
    /// Roll, pitch, yaw of the vehicle at rest, deg. Default (2, -3, 40).
    pub attitude_deg: [f64; 3],
    /// White noise per reading: accelerometer m/s^2, gyro rad/s, temperature deg C.
    /// Defaults 0.03, 0.003 (0.17 deg/s), 0.02.
    pub accel_noise_mps2: f64,
    pub gyro_noise_rad_s: f64,
    pub temp_noise_c: f64,
    /// The size of the hidden bias curves' linear term in the range scaled to -1..1 (see
    /// `random_cubic`): accelerometer m/s^2, gyro rad/s. Defaults 0.08 (8 mg) and 0.002
    /// (0.11 deg/s).
    pub accel_bias_mps2: f64,
    pub gyro_bias_rad_s: f64,
    /// A turn part-way through. Default none.
    pub turn: Option<WarmupTurn>,
}

impl Default for WarmupSettings {
    fn default() -> Self {
        WarmupSettings {
            duration_s: 1500.0,
            rate_hz: 50.0,
            start_c: 15.0,
            end_c: 40.0,
            tau_s: 300.0,
            sensor_lag_s: 3.0,
            instances: 3,
            attitude_deg: [2.0, -3.0, 40.0],
            accel_noise_mps2: 0.03,
            gyro_noise_rad_s: 0.003,
            temp_noise_c: 0.02,
            accel_bias_mps2: 0.08,
            gyro_bias_rad_s: 0.002,
            turn: None,
        }
    }
}

/// The hidden bias curves of one instance: per axis c0..c3 of a cubic in (T_die - 35 C),
/// accelerometer m/s^2, gyro rad/s.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InstanceTruth {
    pub accel: [[f64; 4]; 3],
    pub gyro: [[f64; 4]; 3],
}

impl InstanceTruth {
    /// The true bias of accelerometer (`gyro` false) or gyro axis `axis` at die temperature `temp_c`.
    pub fn bias(&self, gyro: bool, axis: usize, temp_c: f64) -> f64 {
        let c = if gyro {
            self.gyro[axis]
        } else {
            self.accel[axis]
        };
        Cubic { ref_c: 35.0, c }.eval(temp_c)
    }
}

/// A simulated warm-up: each instance's samples and the truth.
#[derive(Debug, Clone)]
pub struct Warmup {
    pub instances: Vec<Vec<Sample>>,
    pub truth: Vec<InstanceTruth>,
}

fn normal(rng: &mut rand_chacha::ChaCha8Rng) -> f64 {
    rand_distr::StandardNormal.sample(rng)
}

/// A cubic with random terms over `lo..hi`: in the range scaled to -1..1 its linear term is
/// `scale` (0.5 + |N(0, 1)|) with a random sign (a MEMS sensor drifts: never a flat curve), the
/// higher terms N(0, scale / 2) and N(0, 0.3 scale), the constant N(0, offset).
fn random_cubic(
    rng: &mut rand_chacha::ChaCha8Rng,
    lo: f64,
    hi: f64,
    scale: f64,
    offset: f64,
) -> [f64; 4] {
    let linear = scale * (0.5 + normal(rng).abs()) * normal(rng).signum();
    let a = [
        offset * normal(rng),
        linear,
        0.5 * scale * normal(rng),
        0.3 * scale * normal(rng),
    ];
    let (centre, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
    let c: [f64; 4] = std::array::from_fn(|k| a[k] / half.powi(k as i32));
    Cubic { ref_c: centre, c }.about(35.0).c
}

/// The vehicle's attitude (body -> NED) and rate (rad/s, body axes) at `t_s`.
fn attitude(s: &WarmupSettings, t_s: f64) -> (Rotation3<f64>, Vector3<f64>) {
    let [r, p, y] = s.attitude_deg.map(f64::to_radians);
    let rest = Rotation3::from_euler_angles(r, p, y);
    let Some(turn) = s.turn.filter(|t| t.duration_s > 0.0) else {
        return (rest, Vector3::zeros());
    };
    let tau = ((t_s - turn.at_s) / turn.duration_s).clamp(0.0, 1.0);
    let angle = turn.angle_deg.to_radians();
    let theta = angle * 0.5 * (1.0 - (std::f64::consts::PI * tau).cos());
    let moving = t_s > turn.at_s && t_s < turn.at_s + turn.duration_s;
    let rate = if moving {
        angle * 0.5 * std::f64::consts::PI / turn.duration_s * (std::f64::consts::PI * tau).sin()
    } else {
        0.0
    };
    (
        rest * Rotation3::from_axis_angle(&Vector3::x_axis(), theta),
        Vector3::new(rate, 0.0, 0.0),
    )
}

/// The warm-up of `s` with noise and hidden curves from `seed`.
pub fn simulate(s: &WarmupSettings, seed: u64) -> Warmup {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = (s.duration_s * s.rate_hz).max(0.0) as usize;
    let dt = 1.0 / s.rate_hz;
    let mut out = Warmup {
        instances: vec![],
        truth: vec![],
    };
    for k in 0..s.instances {
        // Each die its own start and end (a board warms unevenly), each reading its own lag.
        let (t0, t1) = (s.start_c + 0.4 * k as f64, s.end_c - 0.6 * k as f64);
        let lag = s.sensor_lag_s + 2.0 * k as f64;
        let truth = InstanceTruth {
            accel: std::array::from_fn(|_| random_cubic(&mut rng, t0, t1, s.accel_bias_mps2, 0.1)),
            gyro: std::array::from_fn(|_| random_cubic(&mut rng, t0, t1, s.gyro_bias_rad_s, 0.005)),
        };
        let mut read_c = t0;
        let mut samples = Vec::with_capacity(n);
        for i in 0..n {
            let t = i as f64 * dt;
            let die = t1 - (t1 - t0) * (-t / s.tau_s).exp();
            read_c += (die - read_c) * (1.0 - (-dt / lag.max(1e-9)).exp());
            let (att, rate) = attitude(s, t);
            let f = att.inverse() * Vector3::new(0.0, 0.0, -STANDARD_GRAVITY_MPS2);
            let accel = std::array::from_fn(|a| {
                f[a] + truth.bias(false, a, die) + s.accel_noise_mps2 * normal(&mut rng)
            });
            let gyro = std::array::from_fn(|a| {
                rate[a] + truth.bias(true, a, die) + s.gyro_noise_rad_s * normal(&mut rng)
            });
            samples.push(Sample {
                t_s: t,
                accel_mps2: Some(accel),
                gyro_rad_s: Some(gyro),
                temp_c: Some(read_c + s.temp_noise_c * normal(&mut rng)),
                ..Default::default()
            });
        }
        out.instances.push(samples);
        out.truth.push(truth);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_readings_lag_the_die_and_the_vehicle_rests_until_it_turns() {
        let s = WarmupSettings {
            duration_s: 400.0,
            instances: 2,
            turn: Some(WarmupTurn {
                at_s: 200.0,
                duration_s: 4.0,
                angle_deg: 30.0,
            }),
            ..Default::default()
        };
        let w = simulate(&s, 3);
        assert_eq!(w.instances.len(), 2);
        let a = &w.instances[0];
        assert_eq!(a.len(), 20_000);
        // The first reading is the start temperature; after a time constant the die is at
        // 40 - 25 / e = 30.80 C, rising 0.031 C/s; the reading 3 s behind it is 0.09 C lower
        // (30.71 C), plus noise of 0.02 C.
        assert!((a[0].temp_c.unwrap() - 15.0).abs() < 0.1);
        let t300 = a[15_000].temp_c.unwrap();
        assert!(t300 > 30.61 && t300 < 30.79, "{t300}");
        // Gravity on another axis after the turn: y grows by g sin 30 deg at the most.
        let ay = |i: usize| a[i].accel_mps2.unwrap()[1];
        assert!(
            (ay(12_000) - ay(9_000)).abs() > 3.0,
            "{} {}",
            ay(9_000),
            ay(12_000)
        );
    }
}
