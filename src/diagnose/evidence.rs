//! Evidence units: the means of still static segments (split where the motor driver steps) and, when
//! the static segments carry too little magnetometer, moving windows of magnetometer samples.

use super::channel::{Ch, NCH};
use crate::types::{Sample, Vec3};
use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

/// Below this many static units with a magnetometer, moving windows are added as evidence.
pub const MIN_STATIC_MAG_UNITS: usize = 15;
/// Moving windows per held-out block.
pub const WINDOW_BLOCK: usize = 5;
/// Length of a moving window, s, when the magnetometer is fast enough to put
/// [`MIN_WINDOW_SAMPLES`] readings in it; a slower one (telemetry at 1 Hz) gets windows of that
/// many of its median reading intervals.
pub const WINDOW_S: f64 = 0.25;
/// Largest spread of the accelerometer direction inside a static unit, degrees.
pub const MAX_STILL_SPREAD_DEG: f64 = 1.0;
/// Largest RMS scatter of the gyro inside a static unit, rad/s.
pub const MAX_STILL_GYRO_RAD_S: f64 = 0.05;
/// Largest turn of the reference attitude between the first and the last of a static unit's
/// samples, degrees. In flight, a straight leg and a steady banked turn both hold the specific
/// force and the gyro steady; only the attitude tells the turn (whose field mean is not a pose's).
pub const MAX_STILL_TURN_DEG: f64 = 5.0;
/// Fewest samples with a reference attitude for a static unit to carry one (the attitude often
/// comes at a tenth of the IMU's rate).
const MIN_UNIT_REF_SAMPLES: usize = 2;
/// Smallest range of the logged current that makes it the motor driver, A.
pub(crate) const MIN_CURRENT_RANGE_A: f64 = 0.5;
/// Smallest range of the throttle (0..1) that makes it the motor driver, when current does not vary.
pub(crate) const MIN_THROTTLE_RANGE: f64 = 0.02;
/// A static pose is split into units where the driver moves by more than this fraction of its range.
const DRIVER_STEP_FRACTION: f64 = 0.05;
/// A split piece of a pose is a unit when it has at least this fraction of the pose's samples...
const MIN_UNIT_FRACTION: f64 = 0.1;
/// ...and at least this many samples.
const MIN_UNIT_SAMPLES: f64 = 5.0;
/// Fewest magnetometer samples of a static unit that count as magnetometer evidence.
const MIN_UNIT_MAG_SAMPLES: usize = 3;
/// Fewest samples of a channel whose mean a static unit carries (accel, gyro).
const MIN_UNIT_CHANNEL_SAMPLES: usize = 3;
/// Fewest magnetometer samples of a moving window.
const MIN_WINDOW_SAMPLES: usize = 5;
/// A gap between magnetometer samples longer than this ends a moving window, s...
const WINDOW_MAX_GAP_S: f64 = 0.2;
/// ...or than this many median reading intervals, whichever is longer (a slow stream's readings
/// come about one interval apart, and one lost message should not end a window).
const WINDOW_GAP_INTERVALS: f64 = 2.5;
/// Temperature is a usable regressor when this fraction (numerator, denominator) of the units have
/// it...
const MIN_TEMP_COVERAGE: (usize, usize) = (4, 5);
/// ...and it spans at least this range over the units, degrees C.
pub(crate) const MIN_TEMP_RANGE_C: f64 = 0.5;
/// Time constants, s, of the first-order lags of the temperature the temperature effect is fitted
/// on (the first, 0, is the temperature itself). A sensor follows the temperature logged beside it
/// late when the two sit apart on the board or the package heats through: seconds for a bare
/// chip, minutes behind a heat sink. Steps of sqrt(2) from 5 s to 226 s: a lag between two grid
/// values is matched within 19 %, and a lag beyond a few minutes cannot be told from a slow drift
/// on a flight of tens of minutes.
pub const TEMP_LAGS_S: [f64; N_TEMP_LAGS] = [
    0.0, 5.0, 7.07, 10.0, 14.1, 20.0, 28.3, 40.0, 56.6, 80.0, 113.0, 160.0, 226.0,
];
/// How many lags [`TEMP_LAGS_S`] holds.
pub(crate) const N_TEMP_LAGS: usize = 13;
/// Time constants, s, of the first-order lags of the motor driver (throttle or current) the motor
/// field is fitted on (the first, 0, is the driver itself). The field follows the current as the
/// motors spin up and the ESCs settle (tens to hundreds of ms), and a logged current is often
/// filtered: steps of sqrt(2) from 0.05 s to 1.6 s.
pub(crate) const DRIVER_LAGS_S: [f64; N_DRIVER_LAGS] = [
    0.0, 0.05, 0.0707, 0.1, 0.141, 0.2, 0.283, 0.4, 0.566, 0.8, 1.13, 1.6,
];
/// How many lags [`DRIVER_LAGS_S`] holds.
pub(crate) const N_DRIVER_LAGS: usize = 12;

#[derive(Debug, Clone, Copy)]
pub(super) struct MagObs {
    pub m: Vector3<f64>,
    /// Centred temperature of this observation, lagged by each of [`TEMP_LAGS_S`] (0 when absent).
    pub tlag: [f64; N_TEMP_LAGS],
    /// Centred driver of this observation, lagged by each of [`DRIVER_LAGS_S`].
    pub dlag: [f64; N_DRIVER_LAGS],
    /// Moving windows: this reading's reference attitude (body -> ENU), when it has one.
    pub ref_w: Option<Matrix3<f64>>,
}

#[derive(Debug, Clone)]
pub(super) struct Unit {
    pub group: usize,
    /// Centred time, s.
    pub t: f64,
    pub moving: bool,
    /// Static: one entry, the mean. Moving window: every sample.
    pub mags: Vec<MagObs>,
    pub acc: Option<Vector3<f64>>,
    pub gyro: Option<Vector3<f64>>,
    /// Centred temperature (0 when absent) and driver.
    pub temp: f64,
    /// Centred temperature lagged by each of [`TEMP_LAGS_S`] (`tlag[0] == temp`).
    pub tlag: [f64; N_TEMP_LAGS],
    /// Centred driver lagged by each of [`DRIVER_LAGS_S`] (`dlag[0] == drv`).
    pub dlag: [f64; N_DRIVER_LAGS],
    pub has_temp: bool,
    pub drv: f64,
    /// Reference attitude, body -> ENU.
    pub ref_w: Option<Matrix3<f64>>,
    /// Samples behind each residual channel ([`Ch::i`]).
    pub n: [usize; NCH],
    /// Sample indices (static units).
    pub idx: Vec<usize>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Driver {
    Throttle,
    Current,
}

pub(super) struct Evidence {
    pub body: Vec<Sample>,
    pub units: Vec<Unit>,
    pub poses: usize,
    pub moving_windows: usize,
    /// Length of the moving windows, s ([`WINDOW_S`], longer for a slow magnetometer).
    pub window_s: f64,
    pub driver: Option<Driver>,
    pub drv_ok: bool,
    pub drv_range: f64,
    pub temp_ok: bool,
    pub temp_range: f64,
    pub time_span: f64,
    /// Means removed from unit time (s), temperature (deg C) and driver.
    pub t_mean: f64,
    pub temp_mean: f64,
    pub drv_mean: f64,
}

pub(super) fn v3(a: &Vec3) -> Vector3<f64> {
    Vector3::new(a[0], a[1], a[2])
}

pub(super) fn quat_rot(q: &[f64; 4]) -> Option<Matrix3<f64>> {
    let qq = Quaternion::new(q[0], q[1], q[2], q[3]);
    if !(qq.norm() > 0.5) || !q.iter().all(|x| x.is_finite()) {
        return None;
    }
    Some(
        *UnitQuaternion::from_quaternion(qq)
            .to_rotation_matrix()
            .matrix(),
    )
}

/// A pose is still when the RMS angle of its accelerometer samples about their mean direction is at
/// most [`MAX_STILL_SPREAD_DEG`], the gyro's RMS scatter at most [`MAX_STILL_GYRO_RAD_S`] and the
/// reference attitude (when there is one) turns by at most [`MAX_STILL_TURN_DEG`].
fn is_still(samples: &[Sample]) -> bool {
    let refs: Vec<Matrix3<f64>> = samples.iter().filter_map(|s| quat_rot(&s.ref_q?)).collect();
    if let (Some(a), Some(b)) = (refs.first(), refs.last()) {
        let turn = nalgebra::Rotation3::from_matrix_unchecked(a.transpose() * b).angle();
        if turn.to_degrees() > MAX_STILL_TURN_DEG {
            return false;
        }
    }
    let acc: Vec<Vector3<f64>> = samples
        .iter()
        .filter_map(|s| s.accel_mps2.map(|a| v3(&a)))
        .collect();
    if acc.len() >= 3 {
        let mean = acc.iter().fold(Vector3::zeros(), |a, b| a + b) / acc.len() as f64;
        if !(mean.norm() > 0.0) {
            return false;
        }
        let d = mean.normalize();
        let ms: f64 = acc
            .iter()
            .map(|a| {
                let n = a.norm().max(1e-300);
                (a / n).cross(&d).norm().asin().powi(2)
            })
            .sum::<f64>()
            / acc.len() as f64;
        if ms.sqrt().to_degrees() > MAX_STILL_SPREAD_DEG {
            return false;
        }
    }
    let gyr: Vec<Vector3<f64>> = samples
        .iter()
        .filter_map(|s| s.gyro_rad_s.map(|a| v3(&a)))
        .collect();
    if gyr.len() >= 3 {
        let mean = gyr.iter().fold(Vector3::zeros(), |a, b| a + b) / gyr.len() as f64;
        let ms: f64 = gyr.iter().map(|g| (g - mean).norm_squared()).sum::<f64>() / gyr.len() as f64;
        if ms.sqrt() > MAX_STILL_GYRO_RAD_S {
            return false;
        }
    }
    true
}

/// Per sample, the last finite temperature, throttle and current seen (sensors run at different
/// rates, so each sample carries the latest value forward).
struct Carried {
    temp: Vec<Option<f64>>,
    throttle: Vec<Option<f64>>,
    current: Vec<Option<f64>>,
}

fn carry_forward(body: &[Sample]) -> Carried {
    let n = body.len();
    let (mut ct, mut cth, mut ccur) = (vec![None; n], vec![None; n], vec![None; n]);
    let (mut lt, mut lth, mut lc) = (None, None, None);
    for (i, s) in body.iter().enumerate() {
        lt = s.temp_c.filter(|x| x.is_finite()).or(lt);
        lth = s.throttle.filter(|x| x.is_finite()).or(lth);
        lc = s.current_a.filter(|x| x.is_finite()).or(lc);
        ct[i] = lt;
        cth[i] = lth;
        ccur[i] = lc;
    }
    Carried {
        temp: ct,
        throttle: cth,
        current: ccur,
    }
}

/// Per sample, a carried value (temperature, driver) through a first-order lag of each time
/// constant of `taus_s` (`taus_s[0]` = 0: the value itself; NaN before the first value). The lag
/// starts at the first value and steps with the exact discrete form y += (1 - exp(-dt / tau))
/// (x - y), so uneven sample times are followed exactly; a break in the source's time (a joined
/// log) restarts it.
fn lag_series<const N: usize>(
    body: &[Sample],
    temp: &[Option<f64>],
    taus_s: &[f64; N],
) -> Vec<[f64; N]> {
    let mut out = Vec::with_capacity(body.len());
    let mut y = [f64::NAN; N];
    let mut last: Option<(f64, u32)> = None;
    for (s, t) in body.iter().zip(temp) {
        let Some(v) = *t else {
            out.push(y);
            continue;
        };
        let restart = match last {
            None => true,
            Some((_, seg)) => seg != s.segment,
        };
        if restart {
            y = [v; N];
        } else {
            let dt = (s.t_s - last.map_or(s.t_s, |l| l.0)).max(0.0);
            for k in 0..N {
                y[k] = if taus_s[k] > 0.0 {
                    y[k] + (1.0 - (-dt / taus_s[k]).exp()) * (v - y[k])
                } else {
                    v
                };
            }
        }
        last = Some((s.t_s, s.segment));
        out.push(y);
    }
    out
}

/// Range (max - min) of the values present, 0 when none.
fn range(v: &[Option<f64>]) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for x in v.iter().flatten() {
        lo = lo.min(*x);
        hi = hi.max(*x);
    }
    if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

/// A unit before its means: group (pose, or window block), sample indices, moving window or not.
type RawUnit = (usize, Vec<usize>, bool);

/// Static units: each still pose split where the driver steps. Marks the samples inside still poses.
fn static_units(
    body: &[Sample],
    times: &[f64],
    poses: &[crate::calib::gate::Pose],
    drv: &[Option<f64>],
    split: f64,
    in_pose: &mut [bool],
) -> Vec<RawUnit> {
    let mut raw_units: Vec<RawUnit> = Vec::new();
    for (pi, p) in poses.iter().enumerate() {
        let a = times.partition_point(|t| *t < p.t_start);
        let b = times.partition_point(|t| *t <= p.t_end).max(a);
        let mut segs: Vec<Vec<usize>> = vec![];
        let mut cur: Vec<usize> = vec![];
        let mut ref_x: Option<f64> = None;
        // Still enough to be a pose? (A detector threshold learned on continuous motion can pass
        // slow rotations; those samples go to the moving windows instead.)
        if !is_still(&body[a..b]) {
            continue;
        }
        for i in a..b {
            in_pose[i] = true;
            if let Some(x) = drv[i] {
                match ref_x {
                    Some(r) if (x - r).abs() > split => {
                        segs.push(std::mem::take(&mut cur));
                        ref_x = Some(x);
                    }
                    None => ref_x = Some(x),
                    _ => {}
                }
            }
            cur.push(i);
        }
        segs.push(cur);
        let total = b.saturating_sub(a);
        let min_len = (total as f64 * MIN_UNIT_FRACTION).max(MIN_UNIT_SAMPLES) as usize;
        for s in segs {
            if s.len() >= min_len {
                raw_units.push((pi, s, false));
            }
        }
    }
    raw_units
}

/// The length of a moving window and the longest gap inside one, s, for the magnetometer's median
/// interval between readings outside still poses (see [`WINDOW_S`]).
fn window_span(body: &[Sample], times: &[f64], in_pose: &[bool]) -> (f64, f64) {
    let mut dts: Vec<f64> = Vec::new();
    let mut last: Option<(f64, u32)> = None;
    for (i, s) in body.iter().enumerate() {
        if in_pose[i] || s.mag_ut.is_none() {
            continue;
        }
        if let Some((t, seg)) = last {
            let dt = times[i] - t;
            if seg == s.segment && dt > 0.0 {
                dts.push(dt);
            }
        }
        last = Some((times[i], s.segment));
    }
    if dts.is_empty() {
        return (WINDOW_S, WINDOW_MAX_GAP_S);
    }
    let mid = dts.len() / 2;
    let dt = *dts.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    (
        WINDOW_S.max(MIN_WINDOW_SAMPLES as f64 * dt),
        WINDOW_MAX_GAP_S.max(WINDOW_GAP_INTERVALS * dt),
    )
}

/// Moving windows of the magnetometer samples outside still poses, appended to `raw_units`; their
/// groups are blocks of [`WINDOW_BLOCK`] windows numbered after the poses. Returns the window count.
fn moving_windows(
    body: &[Sample],
    times: &[f64],
    in_pose: &[bool],
    n_poses: usize,
    raw_units: &mut Vec<RawUnit>,
) -> (usize, f64) {
    let (window_s, max_gap_s) = window_span(body, times, in_pose);
    let mut cur: Vec<usize> = vec![];
    let mut t0 = f64::NAN;
    let mut last_t = f64::NAN;
    let mut w = 0usize;
    let flush = |cur: &mut Vec<usize>, w: &mut usize, out: &mut Vec<RawUnit>| {
        if cur.len() >= MIN_WINDOW_SAMPLES {
            out.push((n_poses + *w / WINDOW_BLOCK, std::mem::take(cur), true));
            *w += 1;
        } else {
            cur.clear();
        }
    };
    for i in 0..body.len() {
        if in_pose[i] || body[i].mag_ut.is_none() {
            continue;
        }
        let t = times[i];
        // A window never spans a gap or a break in the source's time.
        let broke = cur
            .last()
            .is_some_and(|&j| body[j].segment != body[i].segment);
        if !cur.is_empty() && (broke || t - t0 >= window_s || t - last_t > max_gap_s) {
            flush(&mut cur, &mut w, raw_units);
        }
        if cur.is_empty() {
            t0 = t;
        }
        cur.push(i);
        last_t = t;
    }
    flush(&mut cur, &mut w, raw_units);
    (w, window_s)
}

/// The means (and sample counts) of one unit; time, temperature and driver not yet centred.
fn unit_means(
    body: &[Sample],
    tlag: &[[f64; N_TEMP_LAGS]],
    dlag: &[[f64; N_DRIVER_LAGS]],
    rot_t: &Matrix3<f64>,
    (group, idx, moving): RawUnit,
) -> Unit {
    let mut acc = Vector3::zeros();
    let mut mag = Vector3::zeros();
    let mut gyr = Vector3::zeros();
    let (mut na, mut nm, mut ng) = (0usize, 0usize, 0usize);
    let (mut ts, mut nts) = ([0.0; N_TEMP_LAGS], 0usize);
    let (mut ds, mut nds) = ([0.0; N_DRIVER_LAGS], 0usize);
    let mut qsum = nalgebra::Vector4::zeros();
    let mut q0: Option<nalgebra::Vector4<f64>> = None;
    let (mut nra, mut nrm) = (0usize, 0usize);
    let mut nref = 0usize;
    for &i in &idx {
        let s = &body[i];
        if let Some(a) = s.accel_mps2 {
            acc += v3(&a);
            na += 1;
        }
        if let Some(m) = s.mag_ut {
            mag += v3(&m);
            nm += 1;
        }
        if let Some(g) = s.gyro_rad_s {
            gyr += v3(&g);
            ng += 1;
        }
        if tlag[i][0].is_finite() {
            for (a, b) in ts.iter_mut().zip(&tlag[i]) {
                *a += b;
            }
            nts += 1;
        }
        if dlag[i][0].is_finite() {
            for (a, b) in ds.iter_mut().zip(&dlag[i]) {
                *a += b;
            }
            nds += 1;
        }
        if let Some(q) = s.ref_q {
            let v = nalgebra::Vector4::new(q[0], q[1], q[2], q[3]);
            let r = *q0.get_or_insert(v);
            qsum += if v.dot(&r) < 0.0 { -v } else { v };
            nref += 1;
            if s.accel_mps2.is_some() {
                nra += 1;
            }
            if s.mag_ut.is_some() {
                nrm += 1;
            }
        }
    }
    let t_mid = 0.5 * (body[idx[0]].t_s + body[*idx.last().unwrap()].t_s);
    let mean_tlag = ts.map(|x| if nts > 0 { x / nts as f64 } else { f64::NAN });
    let mean_temp = mean_tlag[0];
    let mean_dlag = ds.map(|x| if nds > 0 { x / nds as f64 } else { 0.0 });
    let d = mean_dlag[0];
    // The reference attitude, the mean of the unit's.
    let ref_w = if !moving && nref >= MIN_UNIT_REF_SAMPLES {
        quat_rot(&[qsum[0], qsum[1], qsum[2], qsum[3]]).map(|r| r * rot_t)
    } else {
        None
    };
    let mags = if moving {
        idx.iter()
            .filter_map(|&i| {
                body[i].mag_ut.map(|m| MagObs {
                    m: v3(&m),
                    tlag: tlag[i],
                    dlag: dlag[i].map(|x| if x.is_finite() { x } else { 0.0 }),
                    ref_w: body[i].ref_q.and_then(|q| quat_rot(&q)).map(|r| r * rot_t),
                })
            })
            .collect()
    } else if nm >= MIN_UNIT_MAG_SAMPLES {
        vec![MagObs {
            m: mag / nm as f64,
            tlag: mean_tlag,
            dlag: mean_dlag,
            ref_w: None,
        }]
    } else {
        vec![]
    };
    let mut cnt = [0usize; NCH];
    cnt[Ch::MagNorm.i()] = nm;
    cnt[Ch::AccNorm.i()] = na;
    cnt[Ch::Dip.i()] = nm.min(na);
    cnt[Ch::VecAcc.i()] = nra;
    cnt[Ch::VecMag.i()] = nrm;
    cnt[Ch::Gyro.i()] = ng;
    Unit {
        group,
        t: t_mid,
        moving,
        mags,
        acc: (!moving && na >= MIN_UNIT_CHANNEL_SAMPLES).then(|| acc / na as f64),
        gyro: (!moving && ng >= MIN_UNIT_CHANNEL_SAMPLES).then(|| gyr / ng as f64),
        temp: mean_temp,
        tlag: mean_tlag,
        dlag: mean_dlag,
        has_temp: nts > 0,
        drv: d,
        ref_w,
        n: cnt,
        idx,
    }
}

/// Means and ranges over the units of time, temperature and driver, after centring them in place.
struct Centred {
    t_mean: f64,
    temp_mean: f64,
    drv_mean: f64,
    temp_range: f64,
    drv_range: f64,
    with_temp: usize,
    time_span: f64,
}

/// Centre time, temperature and driver of the units (and of every magnetometer observation).
fn centre(units: &mut [Unit]) -> Centred {
    let mean_of = |f: &dyn Fn(&Unit) -> Option<f64>| {
        let v: Vec<f64> = units.iter().filter_map(f).collect();
        if v.is_empty() {
            0.0
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let tbar = mean_of(&|u: &Unit| Some(u.t));
    let tempbar = mean_of(&|u: &Unit| u.has_temp.then_some(u.temp));
    let dbar = mean_of(&|u: &Unit| Some(u.drv));
    let (mut tlo, mut thi) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut dlo, mut dhi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut with_temp = 0;
    for u in units.iter_mut() {
        u.t -= tbar;
        if u.has_temp {
            with_temp += 1;
            tlo = tlo.min(u.temp);
            thi = thi.max(u.temp);
            u.temp -= tempbar;
        } else {
            u.temp = 0.0;
        }
        u.tlag = u
            .tlag
            .map(|x| if x.is_finite() { x - tempbar } else { 0.0 });
        dlo = dlo.min(u.drv);
        dhi = dhi.max(u.drv);
        u.drv -= dbar;
        u.dlag = u.dlag.map(|x| x - dbar);
        for o in u.mags.iter_mut() {
            o.tlag = o
                .tlag
                .map(|x| if x.is_finite() { x - tempbar } else { 0.0 });
            o.dlag = o.dlag.map(|x| x - dbar);
        }
    }
    let (t_lo, t_hi) = units
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), u| {
            (a.min(u.t), b.max(u.t))
        });
    Centred {
        t_mean: tbar,
        temp_mean: tempbar,
        drv_mean: dbar,
        temp_range: if thi >= tlo { thi - tlo } else { 0.0 },
        drv_range: if dhi >= dlo { dhi - dlo } else { 0.0 },
        with_temp,
        time_span: if t_hi > t_lo { t_hi - t_lo } else { 0.0 },
    }
}

/// Build the evidence units from body-frame samples and the pipeline's poses.
pub(super) fn build_evidence(
    body: Vec<Sample>,
    poses: &[crate::calib::gate::Pose],
    rot_sensor_to_body: &Matrix3<f64>,
) -> Evidence {
    let n = body.len();
    let carried = carry_forward(&body);
    let tlag = lag_series(&body, &carried.temp, &TEMP_LAGS_S);
    let driver = if range(&carried.current) >= MIN_CURRENT_RANGE_A {
        Some(Driver::Current)
    } else if range(&carried.throttle) >= MIN_THROTTLE_RANGE {
        Some(Driver::Throttle)
    } else {
        None
    };
    let drv: Vec<Option<f64>> = match driver {
        Some(Driver::Current) => carried.current,
        Some(Driver::Throttle) => carried.throttle,
        None => vec![None; n],
    };
    let split = (DRIVER_STEP_FRACTION * range(&drv)).max(1e-9);
    let dlag = lag_series(&body, &drv, &DRIVER_LAGS_S);
    let rot_t = rot_sensor_to_body.transpose();
    let times: Vec<f64> = body.iter().map(|s| s.t_s).collect();

    let mut in_pose = vec![false; n];
    let mut raw_units = static_units(&body, &times, poses, &drv, split, &mut in_pose);
    let n_poses = poses.len();
    // Static units with the magnetometer: decide whether moving windows are needed.
    let static_mag = raw_units
        .iter()
        .filter(|(_, s, _)| {
            s.iter().filter(|&&i| body[i].mag_ut.is_some()).count() >= MIN_UNIT_MAG_SAMPLES
        })
        .count();
    let (moving, window_s) = if static_mag < MIN_STATIC_MAG_UNITS {
        moving_windows(&body, &times, &in_pose, n_poses, &mut raw_units)
    } else {
        (0, WINDOW_S)
    };
    let mut units: Vec<Unit> = raw_units
        .into_iter()
        .map(|r| unit_means(&body, &tlag, &dlag, &rot_t, r))
        .collect();
    let c = centre(&mut units);
    let temp_ok = !units.is_empty()
        && c.with_temp * MIN_TEMP_COVERAGE.1 >= units.len() * MIN_TEMP_COVERAGE.0
        && c.temp_range >= MIN_TEMP_RANGE_C;
    let min_drv = match driver {
        Some(Driver::Current) => MIN_CURRENT_RANGE_A,
        _ => MIN_THROTTLE_RANGE,
    };
    let drv_ok = driver.is_some() && c.drv_range >= min_drv;
    Evidence {
        body,
        units,
        poses: n_poses,
        moving_windows: moving,
        window_s,
        driver,
        drv_ok,
        drv_range: c.drv_range,
        temp_ok,
        temp_range: c.temp_range,
        time_span: c.time_span,
        t_mean: c.t_mean,
        temp_mean: c.temp_mean,
        drv_mean: c.drv_mean,
    }
}
