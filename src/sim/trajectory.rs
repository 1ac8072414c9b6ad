//! Trajectories of the scenarios: attitude (body -> NED) and motion as functions of time.

use super::{CruiseSettings, PoseTruth, RoverSettings};
use nalgebra::{UnitQuaternion, Vector3};

pub(super) type Quat = UnitQuaternion<f64>;

/// Body -> NED rotation from ZYX Euler angles in degrees.
pub fn quat_from_euler_deg(roll: f64, pitch: f64, yaw: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), yaw.to_radians())
}

use crate::attitude::wrap360;

/// Minimum-jerk profile 0 -> 1 on u in [0, 1] (zero velocity and acceleration at both ends).
fn min_jerk(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
}

/// Piece of an attitude timeline: a hold or a rotation about a fixed body axis.
#[derive(Debug, Clone)]
pub(super) enum Segment {
    Hold {
        t1: f64,
        q: Quat,
    },
    /// From `q0` by the rotation vector `v` (body axes of `q0`), min-jerk in time.
    Slew {
        t0: f64,
        t1: f64,
        q0: Quat,
        v: Vector3<f64>,
    },
}

impl Segment {
    pub(super) fn t1(&self) -> f64 {
        match self {
            Segment::Hold { t1, .. } | Segment::Slew { t1, .. } => *t1,
        }
    }
}

/// Small smooth attitude jitter: a sum of sinusoids per body axis (rotation vector, rad).
#[derive(Debug, Clone)]
pub(super) struct Tremor {
    /// (axis, amplitude rad, frequency Hz, phase rad)
    comps: Vec<(usize, f64, f64, f64)>,
}

impl Tremor {
    pub(super) fn new<R: rand::Rng>(amp_deg: f64, rng: &mut R) -> Tremor {
        let mut comps = Vec::new();
        for axis in 0..3 {
            // Relative amplitudes 1, 0.7, 0.5: the RMS of the sum is c * sqrt(1.74 / 2), made `amp_deg`.
            let c = amp_deg.to_radians() / (1.74f64 / 2.0).sqrt();
            for rel in [1.0, 0.7, 0.5] {
                let f = rng.random_range(1.0..9.0);
                let ph = rng.random_range(0.0..std::f64::consts::TAU);
                comps.push((axis, c * rel, f, ph));
            }
        }
        Tremor { comps }
    }

    pub(super) fn rotvec(&self, t: f64) -> Vector3<f64> {
        let mut v = Vector3::zeros();
        for &(axis, a, f, ph) in &self.comps {
            v[axis] += a * (std::f64::consts::TAU * f * t + ph).sin();
        }
        v
    }
}

/// The flight trajectory: closed-form functions of time.
#[derive(Debug, Clone)]
pub(super) struct FlightPlan {
    pub(super) t_total: f64,
    /// Lift-off and touch-down times.
    pub(super) t_up: f64,
    pub(super) t_down: f64,
    /// Length of the climb and the descent.
    pub(super) t_climb: f64,
    alt_m: f64,
    ground_rp_deg: [f64; 2],
    yaw0_deg: f64,
    /// (t0, t1, delta deg) yaw turns.
    turns: Vec<(f64, f64, f64)>,
    /// (amplitude deg, frequency Hz, phase) for roll and pitch.
    roll: Vec<(f64, f64, f64)>,
    pitch: Vec<(f64, f64, f64)>,
    /// (amplitude m, frequency Hz, phase) for north and east.
    north: (f64, f64, f64),
    east: (f64, f64, f64),
    hover_throttle: f64,
}

fn sines(c: &[(f64, f64, f64)], t: f64) -> f64 {
    c.iter()
        .map(|&(a, f, ph)| a * (std::f64::consts::TAU * f * t + ph).sin())
        .sum()
}

impl FlightPlan {
    pub(super) fn new<R: rand::Rng>(total: f64, rng: &mut R) -> FlightPlan {
        let t_total = total.max(30.0);
        let t_up = 5.0;
        let t_climb = 5.0;
        let t_down = t_total - 5.0 - t_climb;
        let h0 = t_up + t_climb;
        let hl = t_down - h0;
        let yaw0_deg = rng.random_range(0.0..360.0);
        FlightPlan {
            t_total,
            t_up,
            t_down,
            t_climb,
            alt_m: 5.0,
            ground_rp_deg: [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)],
            yaw0_deg,
            turns: vec![
                (h0 + 0.10 * hl, h0 + 0.45 * hl, 360.0),
                (h0 + 0.55 * hl, h0 + 0.90 * hl, -360.0),
            ],
            roll: vec![
                (6.0, 0.13, phase(rng)),
                (3.0, 0.31, phase(rng)),
                (1.5, 0.7, phase(rng)),
            ],
            pitch: vec![
                (6.0, 0.11, phase(rng)),
                (3.0, 0.27, phase(rng)),
                (1.5, 0.6, phase(rng)),
            ],
            north: (2.0, 0.05, phase(rng)),
            east: (1.5, 0.08, phase(rng)),
            hover_throttle: 0.5,
        }
    }

    /// 0 on the ground, 1 in the air, min-jerk during climb and descent.
    pub(super) fn airborne(&self, t: f64) -> f64 {
        if t < self.t_down {
            min_jerk((t - self.t_up) / self.t_climb)
        } else {
            1.0 - min_jerk((t - self.t_down) / self.t_climb)
        }
    }

    pub(super) fn attitude(&self, t: f64) -> Quat {
        let e = self.airborne(t);
        let roll = (1.0 - e) * self.ground_rp_deg[0] + e * sines(&self.roll, t);
        let pitch = (1.0 - e) * self.ground_rp_deg[1] + e * sines(&self.pitch, t);
        let yaw = self.yaw0_deg
            + self
                .turns
                .iter()
                .map(|&(t0, t1, d)| d * min_jerk((t - t0) / (t1 - t0)))
                .sum::<f64>();
        quat_from_euler_deg(roll, pitch, yaw)
    }

    pub(super) fn position_ned(&self, t: f64) -> Vector3<f64> {
        let e = self.airborne(t);
        Vector3::new(
            e * sines(&[self.north], t),
            e * sines(&[self.east], t),
            -self.alt_m * e,
        )
    }

    /// Throttle before noise: proportional to the thrust needed, spooled up 1 s before lift-off.
    pub(super) fn throttle(&self, t: f64, a_ned: &Vector3<f64>, gravity: f64) -> f64 {
        let spool = if t < self.t_down {
            min_jerk((t - (self.t_up - 1.0)) / 1.0)
        } else {
            1.0 - min_jerk((t - (self.t_down + self.t_climb)) / 1.0)
        };
        let thrust = (a_ned - Vector3::new(0.0, 0.0, gravity)).norm() / gravity;
        let wobble = 1.0 + 0.02 * (std::f64::consts::TAU * 1.3 * t).sin();
        (self.hover_throttle * thrust * wobble * spool).clamp(0.0, 1.0)
    }
}

/// The cruise trajectory: heading, bank and current as closed-form functions of time.
#[derive(Debug, Clone)]
pub(super) struct CruisePlan {
    pub(super) t_total: f64,
    gravity_mps2: f64,
    /// Its turns rise and fall smoothly, and so does the bank (coordinated: tan(bank) = v rate / g).
    track: Track,
    /// (t_start, current A) of each leg and turn; the current ramps over 2 s to the next.
    currents: Vec<(f64, f64)>,
    pub(super) max_current_a: f64,
    /// (amplitude deg, frequency Hz, phase): roll wobble and pitch about its trim.
    roll: Vec<(f64, f64, f64)>,
    pitch: Vec<(f64, f64, f64)>,
    pitch_trim_deg: f64,
}

impl CruisePlan {
    pub(super) fn new<R: rand::Rng>(
        total: f64,
        c: &CruiseSettings,
        gravity: f64,
        rng: &mut R,
    ) -> CruisePlan {
        let (mut turns, mut currents) = (Vec::new(), Vec::new());
        let mut t = 0.0;
        while t < total {
            currents.push((t, pick_in(c.current_a, rng)));
            t += pick_in(c.leg_s, rng);
            let bank = pick_in(c.bank_deg, rng).to_radians();
            let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let delta = sign * pick_in(c.turn_deg, rng).to_radians();
            // Peak rate 2 |delta| / T = g tan(bank) / v.
            let d = 2.0 * c.speed_mps * delta.abs() / (gravity * bank.tan());
            currents.push((t, pick_in(c.current_a, rng)));
            turns.push((t, t + d, delta));
            t += d;
        }
        CruisePlan {
            t_total: total,
            gravity_mps2: gravity,
            track: Track {
                speed_mps: c.speed_mps,
                yaw0_rad: rng.random_range(0.0..std::f64::consts::TAU),
                turns,
            },
            currents,
            max_current_a: c.current_a[1],
            roll: vec![(1.0, 0.23, phase(rng)), (0.5, 0.61, phase(rng))],
            pitch: vec![(2.0, 0.05, phase(rng)), (1.0, 0.17, phase(rng))],
            pitch_trim_deg: 1.5,
        }
    }

    pub(super) fn attitude(&self, t: f64) -> Quat {
        let (psi, rate) = self.track.heading(t);
        let bank = (self.track.speed_mps * rate / self.gravity_mps2)
            .atan()
            .to_degrees();
        let roll = bank + sines(&self.roll, t);
        let pitch = self.pitch_trim_deg + sines(&self.pitch, t);
        quat_from_euler_deg(roll, pitch, psi.to_degrees())
    }

    pub(super) fn current_a(&self, t: f64) -> f64 {
        let k = self.currents.partition_point(|c| c.0 <= t).max(1) - 1;
        let Some(&(t0, now)) = self.currents.get(k) else {
            return 0.0;
        };
        let before = if k > 0 { self.currents[k - 1].1 } else { now };
        before + (now - before) * min_jerk((t - t0) / 2.0)
    }
}

/// The rover trajectory: a ground vehicle at constant speed driving straight stretches, loops
/// and figure-eights on gently rolling ground; heading and tilt as closed-form functions of time.
#[derive(Debug, Clone)]
pub(super) struct RoverPlan {
    pub(super) t_total: f64,
    track: Track,
    /// (amplitude deg, wavelength m, phase): roll and pitch from the terrain along the track.
    roll: Vec<(f64, f64, f64)>,
    pitch: Vec<(f64, f64, f64)>,
}

impl RoverPlan {
    pub(super) fn new<R: rand::Rng>(total: f64, c: &RoverSettings, rng: &mut R) -> RoverPlan {
        // Peak rate 2 |delta| / T = speed / radius.
        let peak_rate = c.speed_mps / c.turn_radius_m;
        let mut turns = Vec::new();
        let mut t = 0.0;
        while t < total {
            t += pick_in(c.leg_s, rng);
            let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let mut turn = |delta: f64, t: &mut f64| {
                let d = 2.0 * delta.abs() / peak_rate;
                turns.push((*t, *t + d, delta));
                *t += d;
            };
            if rng.random_bool(c.figure_eight_share) {
                // Two full circles, one each way, then on at a new heading.
                turn(sign * std::f64::consts::TAU, &mut t);
                turn(-sign * std::f64::consts::TAU, &mut t);
                turn(sign * pick_in(c.turn_deg, rng).to_radians() / 4.0, &mut t);
            } else {
                turn(sign * pick_in(c.turn_deg, rng).to_radians(), &mut t);
            }
        }
        let a = c.terrain_deg;
        RoverPlan {
            t_total: total,
            track: Track {
                speed_mps: c.speed_mps,
                yaw0_rad: rng.random_range(0.0..std::f64::consts::TAU),
                turns,
            },
            roll: vec![(0.6 * a, 9.0, phase(rng)), (0.4 * a, 23.0, phase(rng))],
            pitch: vec![(0.6 * a, 13.0, phase(rng)), (0.4 * a, 31.0, phase(rng))],
        }
    }

    pub(super) fn attitude(&self, t: f64) -> Quat {
        let (psi, _) = self.track.heading(t);
        let s = self.track.speed_mps * t;
        let terrain = |c: &[(f64, f64, f64)]| {
            c.iter()
                .map(|&(a, l, ph)| a * (std::f64::consts::TAU * s / l + ph).sin())
                .sum::<f64>()
        };
        quat_from_euler_deg(terrain(&self.roll), terrain(&self.pitch), psi.to_degrees())
    }
}

/// A value drawn uniformly from the range `r` (its low end when the range is empty).
fn pick_in<R: rand::Rng>(r: [f64; 2], rng: &mut R) -> f64 {
    if r[1] > r[0] {
        rng.random_range(r[0]..r[1])
    } else {
        r[0]
    }
}

/// A phase drawn uniformly from [0, 2 pi).
fn phase<R: rand::Rng>(rng: &mut R) -> f64 {
    rng.random_range(0.0..std::f64::consts::TAU)
}

/// A vehicle at constant speed on level ground or in level flight, its heading turning smoothly:
/// the horizontal motion of the cruise and the rover.
#[derive(Debug, Clone)]
pub(super) struct Track {
    speed_mps: f64,
    yaw0_rad: f64,
    /// (t0, t1, heading change rad): the turn rate is `delta / T (1 - cos(2 pi u))`, u = (t - t0) / T,
    /// zero at both ends.
    turns: Vec<(f64, f64, f64)>,
}

impl Track {
    /// Heading (rad) and its rate (rad/s).
    fn heading(&self, t: f64) -> (f64, f64) {
        smooth_turns(self.yaw0_rad, &self.turns, t)
    }

    fn velocity_ned(&self, t: f64) -> Vector3<f64> {
        let (psi, _) = self.heading(t);
        self.speed_mps * Vector3::new(psi.cos(), psi.sin(), 0.0)
    }

    /// The centripetal acceleration of the turns (constant speed), m/s^2.
    fn accel_ned(&self, t: f64) -> Vector3<f64> {
        let (psi, rate) = self.heading(t);
        self.speed_mps * rate * Vector3::new(-psi.sin(), psi.cos(), 0.0)
    }
}

/// Heading (rad) and rate (rad/s) from `yaw0` through turns (t0, t1, delta rad) whose rate is
/// `delta / T (1 - cos(2 pi u))`, u = (t - t0) / T.
fn smooth_turns(yaw0: f64, turns: &[(f64, f64, f64)], t: f64) -> (f64, f64) {
    let (mut psi, mut rate) = (yaw0, 0.0);
    for &(t0, t1, delta) in turns {
        let d = t1 - t0;
        let u = ((t - t0) / d).clamp(0.0, 1.0);
        let w = std::f64::consts::TAU * u;
        psi += delta * (u - w.sin() / std::f64::consts::TAU);
        if (t0..t1).contains(&t) {
            rate += delta / d * (1.0 - w.cos());
        }
    }
    (psi, rate)
}

#[derive(Debug, Clone)]
pub(super) enum Motion {
    Segments {
        segs: Vec<Segment>,
        tremor: Option<Tremor>,
    },
    Flight(FlightPlan),
    Cruise(CruisePlan),
    Rover(RoverPlan),
    Stress(StressPlan),
}

impl Motion {
    pub(super) fn end(&self) -> f64 {
        match self {
            Motion::Segments { segs, .. } => segs.last().map(|s| s.t1()).unwrap_or(0.0),
            Motion::Flight(p) => p.t_total,
            Motion::Cruise(p) => p.t_total,
            Motion::Rover(p) => p.t_total,
            Motion::Stress(p) => p.t_total,
        }
    }

    pub(super) fn attitude(&self, t: f64) -> Quat {
        match self {
            Motion::Segments { segs, tremor } => {
                let i = segs
                    .partition_point(|s| s.t1() <= t)
                    .min(segs.len().saturating_sub(1));
                let base = match segs.get(i) {
                    None => Quat::identity(),
                    Some(Segment::Hold { q, .. }) => *q,
                    Some(Segment::Slew { t0, t1, q0, v }) => {
                        let s = min_jerk((t - t0) / (t1 - t0));
                        q0 * Quat::from_scaled_axis(v * s)
                    }
                };
                match tremor {
                    Some(tr) => base * Quat::from_scaled_axis(tr.rotvec(t)),
                    None => base,
                }
            }
            Motion::Flight(p) => p.attitude(t),
            Motion::Cruise(p) => p.attitude(t),
            Motion::Rover(p) => p.attitude(t),
            Motion::Stress(p) => p.attitude(t),
        }
    }

    /// Body angular rate, rad/s: central difference of the attitude.
    pub(super) fn body_rate(&self, t: f64) -> Vector3<f64> {
        let h = 1e-4;
        let qa = self.attitude(t - h);
        let qb = self.attitude(t + h);
        (qa.inverse() * qb).scaled_axis() / (2.0 * h)
    }

    /// Velocity in NED, m/s (zero for the ground scenarios).
    pub(super) fn velocity_ned(&self, t: f64) -> Vector3<f64> {
        match self {
            Motion::Segments { .. } => Vector3::zeros(),
            Motion::Flight(p) => {
                let h = 1e-3;
                (p.position_ned(t + h) - p.position_ned(t - h)) / (2.0 * h)
            }
            Motion::Cruise(p) => p.track.velocity_ned(t),
            Motion::Rover(p) => p.track.velocity_ned(t),
            // No place is simulated for a stress run: no position is written.
            Motion::Stress(_) => Vector3::zeros(),
        }
    }

    /// Acceleration in NED, m/s^2 (zero for the ground scenarios: rotation about the sensor).
    pub(super) fn accel_ned(&self, t: f64) -> Vector3<f64> {
        match self {
            Motion::Segments { .. } => Vector3::zeros(),
            Motion::Flight(p) => {
                let h = 1e-3;
                (p.position_ned(t + h) - 2.0 * p.position_ned(t) + p.position_ned(t - h)) / (h * h)
            }
            Motion::Cruise(p) => p.track.accel_ned(t),
            Motion::Rover(p) => p.track.accel_ned(t),
            Motion::Stress(p) => p.accel_ned(t),
        }
    }
}

/// A duration in whole sample ticks (at least one).
fn ticks(d: f64, rate: f64) -> u64 {
    (d * rate).round().max(1.0) as u64
}

/// Build hold/slew segments through `poses` (roll, pitch, yaw deg), recording the holds as [`PoseTruth`].
pub(super) fn build_segments<R: rand::Rng>(
    poses: &[[f64; 3]],
    hold_s: &mut dyn FnMut(&mut R) -> f64,
    slew_s: [f64; 2],
    rate: f64,
    rng: &mut R,
) -> (Vec<Segment>, Vec<PoseTruth>) {
    let mut segs = Vec::new();
    let mut truths = Vec::new();
    // Boundaries on the sample grid (tick / rate, computed like the sample times) so a hold of N
    // ticks holds exactly N samples.
    let mut tick: u64 = 0;
    let at = |k: u64| k as f64 / rate;
    for (k, p) in poses.iter().enumerate() {
        let q = quat_from_euler_deg(p[0], p[1], p[2]);
        let d = ticks(hold_s(rng), rate);
        segs.push(Segment::Hold {
            t1: at(tick + d),
            q,
        });
        truths.push(PoseTruth {
            t_start: at(tick),
            t_end: at(tick + d),
            roll_deg: p[0],
            pitch_deg: p[1],
            yaw_deg: wrap360(p[2]),
        });
        tick += d;
        if let Some(n) = poses.get(k + 1) {
            let q1 = quat_from_euler_deg(n[0], n[1], n[2]);
            let d = ticks(
                if slew_s[1] > slew_s[0] {
                    rng.random_range(slew_s[0]..slew_s[1])
                } else {
                    slew_s[0]
                },
                rate,
            );
            let v = (q.inverse() * q1).scaled_axis();
            segs.push(Segment::Slew {
                t0: at(tick),
                t1: at(tick + d),
                q0: q,
                v,
            });
            tick += d;
        }
    }
    (segs, truths)
}

/// A turntable plan that turns about every axis but mostly about one: six positions (gravity
/// along each body axis, `[roll, pitch, yaw]` deg), then three turns about body x in 40 deg steps.
/// The gyro scale it gives fails its held-out check.
pub fn six_positions_then_turns_about_x() -> Vec<[f64; 3]> {
    let mut att = vec![
        [0.0, 0.0, 0.0],
        [0.0, 90.0, 0.0],
        [90.0, 0.0, 0.0],
        [0.0, -90.0, 0.0],
        [180.0, 0.0, 0.0],
        [-90.0, 0.0, 0.0],
    ];
    att.extend((0..27).map(|i| [((i * 40) % 360) as f64 - 180.0, 0.0, 0.0]));
    att
}

/// The 32 turntable attitudes of Ren and Liu, "Calibration of MEMS Accelerometers and Magnetometers for Rotor UAV Attitude Estimation" (roll, pitch, yaw deg), ordered to keep slews short.
pub fn turntable_attitudes() -> Vec<[f64; 3]> {
    let mut v: Vec<[f64; 3]> = Vec::new();
    let golden = 137.5;
    let mut k = 0.0;
    let mut yaw = || {
        k += 1.0;
        wrap360(k * golden)
    };
    for p in [-60.0, -30.0, 0.0, 30.0, 60.0] {
        for r in [0.0, 90.0, 180.0, -90.0] {
            v.push([r, p, yaw()]);
        }
    }
    v.push([0.0, 90.0, yaw()]);
    v.push([0.0, -90.0, yaw()]);
    for r in [45.0, 135.0, -135.0, -45.0] {
        v.push([r, 0.0, yaw()]);
    }
    v.push([45.0, 45.0, yaw()]);
    v.push([-135.0, 45.0, yaw()]);
    v.push([-45.0, -45.0, yaw()]);
    v.push([135.0, -45.0, yaw()]);
    // Ren and Liu's check settings: pitch 15, roll +-20.
    v.push([20.0, 15.0, 0.0]);
    v.push([-20.0, 15.0, 45.0]);
    // Greedy nearest-neighbour order from the level pose.
    let start = v
        .iter()
        .position(|p| p[0] == 0.0 && p[1] == 0.0)
        .unwrap_or(0);
    let mut order = vec![v.swap_remove(start)];
    while !v.is_empty() {
        let last = order.last().copied().unwrap_or([0.0; 3]);
        let ql = quat_from_euler_deg(last[0], last[1], last[2]);
        let (i, _) = v
            .iter()
            .enumerate()
            .map(|(i, p)| (i, ql.angle_to(&quat_from_euler_deg(p[0], p[1], p[2]))))
            .fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b });
        order.push(v.swap_remove(i));
    }
    order
}

/// Random attitudes for a hand tumble: the first level, the others with a uniform random down
/// direction and a uniform random yaw.
pub(super) fn tumble_attitudes<R: rand::Rng>(n: usize, rng: &mut R) -> Vec<[f64; 3]> {
    let mut v = Vec::with_capacity(n);
    for k in 0..n {
        let yaw = rng.random_range(0.0..360.0);
        if k == 0 {
            v.push([0.0, 0.0, yaw]);
            continue;
        }
        // Down in body axes: d = (-sin(pitch), sin(roll) cos(pitch), cos(roll) cos(pitch)).
        let z: f64 = rng.random_range(-1.0..1.0);
        let phi: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let s = (1.0 - z * z).max(0.0).sqrt();
        let d = [s * phi.cos(), s * phi.sin(), z];
        let pitch = (-d[0]).clamp(-1.0, 1.0).asin().to_degrees();
        let roll = d[1].atan2(d[2]).to_degrees();
        v.push([roll, pitch, yaw]);
    }
    v
}

// ---------------------------------------------------------------------------------------------
// Stress: motion harder than any calibration needs, with truth, for the attitude filter

/// What the stress phase of a [`StressPlan`] does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum StressMotion {
    /// Shaking: a linear acceleration `stress.shake_mps2 sin(2 pi stress.shake_hz t)` along a
    /// direction that wanders slowly, on top of the calm rotation.
    Shake,
    /// A spin about a fixed body axis ramped up to `stress.spin_deg_s` and down again.
    Spin,
    /// A centrifuge (or a car on a circle): carried round a horizontal circle with the
    /// centripetal acceleration `stress.centripetal_mps2`, facing along the circle, for the whole
    /// stress phase.
    Centrifuge,
}

/// Length of the rests at the start and the end of a stress run, s.
pub(crate) const STRESS_REST_S: f64 = 10.0;
/// Calm rotation before the stress (the filters settle), s.
pub(crate) const STRESS_SETTLE_S: f64 = 20.0;
/// Calm rotation after the stress (the filters recover), s.
pub(crate) const STRESS_RECOVER_S: f64 = 60.0;
/// Ramps of the stress (shake envelope, spin rate, centrifuge speed), s.
const STRESS_RAMP_S: f64 = 2.0;

/// A stress run: rest, calm rotation (rates up to about 25 deg/s), the stress phase on top of the
/// calm rotation, calm rotation again, rest. The stress is `[stress_start_s, stress_end_s)`.
#[derive(Debug, Clone)]
pub(super) struct StressPlan {
    pub(super) motion: StressMotion,
    pub(super) stress_start_s: f64,
    pub(super) stress_end_s: f64,
    pub(super) t_total: f64,
    shake_mps2: f64,
    shake_hz: f64,
    spin_rad_s: f64,
    centripetal_mps2: f64,
    turn_rad_s: f64,
}

/// Smooth step from 0 at `u <= 0` to 1 at `u >= 1` (raised cosine).
fn smooth_step(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    0.5 * (1.0 - (std::f64::consts::PI * u).cos())
}

/// The integral over [0, u T] of `smooth_step(s / T)` ds, for u in [0, 1], times 1 / T.
fn smooth_step_integral(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    0.5 * (u - (std::f64::consts::PI * u).sin() / std::f64::consts::PI)
}

impl StressPlan {
    pub(super) fn new(motion: StressMotion, s: &super::StressSettings) -> StressPlan {
        let stress_start_s = STRESS_REST_S + STRESS_SETTLE_S;
        let stress_end_s = stress_start_s + s.stress_s.max(2.0 * STRESS_RAMP_S);
        StressPlan {
            motion,
            stress_start_s,
            stress_end_s,
            t_total: stress_end_s + STRESS_RECOVER_S + STRESS_REST_S,
            shake_mps2: s.shake_mps2,
            shake_hz: s.shake_hz,
            spin_rad_s: s.spin_deg_s.to_radians(),
            centripetal_mps2: s.centripetal_mps2,
            turn_rad_s: 2.0 * std::f64::consts::PI / s.turn_s.max(0.1),
        }
    }

    /// The envelope of the stress at `t`: 0 outside, ramped in and out over [`STRESS_RAMP_S`].
    fn envelope(&self, t: f64) -> f64 {
        smooth_step((t - self.stress_start_s) / STRESS_RAMP_S)
            * smooth_step((self.stress_end_s - t) / STRESS_RAMP_S)
    }

    /// The integral of the envelope from the stress's start to `t`, s.
    fn envelope_integral(&self, t: f64) -> f64 {
        let (t0, t1, r) = (self.stress_start_s, self.stress_end_s, STRESS_RAMP_S);
        let t = t.clamp(t0, t1);
        let up = r * smooth_step_integral((t - t0) / r);
        let hold = (t.min(t1 - r) - (t0 + r)).max(0.0);
        let down = if t > t1 - r {
            r * (0.5 - smooth_step_integral((t1 - t) / r))
        } else {
            0.0
        };
        up + hold + down
    }

    /// The calm rotation: slow sines about three axes (rotation vector, rad), faded in after the
    /// first rest and out before the last.
    fn calm(&self, t: f64) -> Vector3<f64> {
        let w = smooth_step((t - STRESS_REST_S) / STRESS_RAMP_S)
            * smooth_step((self.t_total - STRESS_REST_S - t) / STRESS_RAMP_S);
        let tau = 2.0 * std::f64::consts::PI;
        // Amplitude 0.5 rad at 0.05-0.11 Hz: rates up to about 0.35 rad/s (20 deg/s).
        Vector3::new(
            0.5 * (tau * 0.11 * t).sin(),
            0.35 * (tau * 0.07 * t + 1.0).sin(),
            0.5 * (tau * 0.05 * t + 2.0).sin(),
        ) * w
    }

    /// The heading turned by the centrifuge by `t`, rad.
    fn centrifuge_angle(&self, t: f64) -> f64 {
        self.turn_rad_s * self.envelope_integral(t)
    }

    pub(super) fn attitude(&self, t: f64) -> Quat {
        let start = super::quat_from_euler_deg(10.0, -5.0, 30.0);
        let calm = Quat::from_scaled_axis(self.calm(t));
        match self.motion {
            StressMotion::Shake => start * calm,
            StressMotion::Spin => {
                let axis = Vector3::new(1.0, 0.3, 0.2).normalize();
                let phi = self.spin_rad_s * self.envelope_integral(t);
                start * calm * Quat::from_scaled_axis(axis * phi)
            }
            StressMotion::Centrifuge => {
                let yaw = Quat::from_axis_angle(&Vector3::z_axis(), self.centrifuge_angle(t));
                yaw * start * calm
            }
        }
    }

    pub(super) fn accel_ned(&self, t: f64) -> Vector3<f64> {
        let env = self.envelope(t);
        if env == 0.0 {
            return Vector3::zeros();
        }
        match self.motion {
            StressMotion::Shake => {
                // A direction that wanders slowly over the sphere; the acceleration's mean is zero
                // over each cycle, so the velocity stays bounded.
                let u = Vector3::new((0.3 * t).cos(), (0.3 * t).sin(), 0.6 * (0.2 * t).sin())
                    .normalize();
                let phase = 2.0 * std::f64::consts::PI * self.shake_hz * t;
                u * (self.shake_mps2 * env * phase.sin())
            }
            StressMotion::Spin => Vector3::zeros(),
            StressMotion::Centrifuge => {
                // On a circle of radius r = a / w^2 at the full rate w: centripetal w^2 r towards
                // the centre, tangential r dw/dt while the rate ramps.
                let w_full = self.turn_rad_s;
                let r = self.centripetal_mps2 / (w_full * w_full);
                let w = w_full * env;
                let h = 1e-3;
                let dw = w_full * (self.envelope(t + h) - self.envelope(t - h)) / (2.0 * h);
                let psi = self.centrifuge_angle(t);
                let radial = Vector3::new(psi.cos(), psi.sin(), 0.0);
                let tangential = Vector3::new(-psi.sin(), psi.cos(), 0.0);
                -radial * (w * w * r) + tangential * (r * dw)
            }
        }
    }
}
