//! Gating: the scalar Kalman prefilter of Ren and Liu, "Calibration of MEMS Accelerometers and Magnetometers for Rotor UAV Attitude Estimation" (eq. 3) and static-pose detection by sliding-window
//! variance (Camps, Harasse and Monin, "Numerical calibration for 3-axis accelerometers and magnetometers" (2009)), with a threshold that needs no hand tuning. Pure, streaming, bounded memory.

use crate::types::{Sample, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// Ren and Liu, "Calibration of MEMS Accelerometers and Magnetometers for Rotor UAV Attitude Estimation", eq. 3: a random-constant Kalman filter per channel.
/// x_k|k-1 = x, P_k|k-1 = P + Q, K = P/(P + R), x += K (z - x), P = (1 - K) P.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ScalarKalman {
    pub x: f64,
    pub p: f64,
    pub q: f64,
    pub r: f64,
    started: bool,
}

impl ScalarKalman {
    /// Ren and Liu's values: Q = 1e-4, R = 1, P0 = 1; the state starts at the first measurement.
    pub fn new(q: f64, r: f64) -> Self {
        ScalarKalman {
            x: 0.0,
            p: 1.0,
            q,
            r,
            started: false,
        }
    }
    pub fn update(&mut self, z: f64) -> f64 {
        if !self.started {
            self.x = z;
            self.started = true;
            return z;
        }
        let p = self.p + self.q;
        let k = p / (p + self.r);
        self.x += k * (z - self.x);
        self.p = (1.0 - k) * p;
        self.x
    }
}

/// Three channels of [`ScalarKalman`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Prefilter3([ScalarKalman; 3]);

impl Prefilter3 {
    pub fn new(q: f64, r: f64) -> Self {
        Prefilter3([ScalarKalman::new(q, r); 3])
    }
    pub fn update(&mut self, v: &Vec3) -> Vec3 {
        [
            self.0[0].update(v[0]),
            self.0[1].update(v[1]),
            self.0[2].update(v[2]),
        ]
    }
}

/// Settings of the static detector.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct GateConfig {
    /// Sliding window length, s. Default: 1.
    pub window_s: f64,
    /// Fixed threshold on the summed per-axis accel variance ((m/s^2)^2 or counts^2); `None` = automatic.
    /// Default: none (automatic).
    pub threshold: Option<f64>,
    /// Automatic threshold = factor x the noise floor (the 10th percentile of window variances).
    /// Default: 8.
    pub threshold_factor: f64,
    /// Shortest static run that counts as a pose, s. Default: 1.
    pub min_pose_s: f64,
}

impl Default for GateConfig {
    fn default() -> Self {
        GateConfig {
            window_s: 1.0,
            threshold: None,
            threshold_factor: 8.0,
            min_pose_s: 1.0,
        }
    }
}

/// A static pose: the mean of the samples of one still interval.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Pose {
    pub t_start: f64,
    pub t_end: f64,
    /// Time segment of its samples (a pose never spans a break in the source's time).
    #[serde(default)]
    pub segment: u32,
    pub samples: usize,
    pub accel: Vec3,
    pub mag: Option<Vec3>,
    pub gyro: Option<Vec3>,
    pub temp_c: Option<f64>,
    pub throttle: Option<f64>,
    /// Summed per-axis accel variance inside the pose.
    pub accel_var: f64,
    /// How fast the sensor turned during the pose, deg/s: the slope of a straight line fitted to
    /// the logged attitude (quaternion components against time) where there is one, else to the
    /// magnetometer's direction (which misses a turn about the field). `None` with neither. A
    /// steady turn, a climb or a slow hand rotation hold the accelerometer and gyro as steady as
    /// rest does; only this tells them apart.
    #[serde(default)]
    pub turn_rate_deg_s: Option<f64>,
}

#[cfg(test)]
impl Pose {
    /// A pose from `t_start` to `t_end` (s) of `samples` samples with the mean acceleration
    /// `accel`, nothing else known: for tests.
    pub(crate) fn still(t_start: f64, t_end: f64, samples: usize, accel: Vec3) -> Pose {
        Pose {
            t_start,
            t_end,
            segment: 0,
            samples,
            accel,
            mag: None,
            gyro: None,
            temp_c: None,
            throttle: None,
            accel_var: 0.0,
            turn_rate_deg_s: None,
        }
    }
}

impl Pose {
    /// Whether the pose was at rest: it turned no faster than [`REST_MAX_RATE_DEG_S`] where that
    /// can be seen. (Without an attitude or a magnetometer, nothing tells.)
    pub fn at_rest(&self) -> bool {
        self.turn_rate_deg_s
            .is_none_or(|r| r <= REST_MAX_RATE_DEG_S)
    }
}

/// Fastest turn of a pose at rest, deg/s (0.0044 rad/s): a slower turn, over a pose's seconds,
/// moves the attitude by less than its noise, and would bias the gyro bias by at most this.
/// The straight-line fit over a pose of 100 readings of an attitude with 0.5 deg of noise finds
/// the rate to about 0.1 deg/s.
pub(crate) const REST_MAX_RATE_DEG_S: f64 = 0.25;

/// Running sums for the straight-line fit of `N` components against time.
#[derive(Debug, Clone, Copy)]
struct Trend<const N: usize> {
    n: f64,
    st: f64,
    stt: f64,
    sx: [f64; N],
    stx: [f64; N],
}

impl<const N: usize> Default for Trend<N> {
    fn default() -> Self {
        Trend {
            n: 0.0,
            st: 0.0,
            stt: 0.0,
            sx: [0.0; N],
            stx: [0.0; N],
        }
    }
}

impl<const N: usize> Trend<N> {
    fn add(&mut self, t: f64, x: &[f64; N]) {
        self.n += 1.0;
        self.st += t;
        self.stt += t * t;
        for k in 0..N {
            self.sx[k] += x[k];
            self.stx[k] += t * x[k];
        }
    }
    /// The fitted slope of each component, per second (`None` with fewer than 3 points or no
    /// spread of time).
    fn slope(&self) -> Option<[f64; N]> {
        let stt = self.stt - self.st * self.st / self.n;
        (self.n >= 3.0 && stt > 0.0).then(|| {
            let mut s = [0.0; N];
            for k in 0..N {
                s[k] = (self.stx[k] - self.st * self.sx[k] / self.n) / stt;
            }
            s
        })
    }
    /// The mean of each component.
    fn mean(&self) -> [f64; N] {
        self.sx.map(|x| x / self.n.max(1.0))
    }
    /// How fast the components' direction moves, per second: the part of the fitted slope
    /// across the mean, over the mean's length (rad/s for a unit vector or quaternion).
    fn rate_across(&self) -> Option<f64> {
        let s = self.slope()?;
        let m = self.mean();
        let n = m.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-300);
        let along = s.iter().zip(&m).map(|(a, b)| a * b).sum::<f64>() / n;
        let across = s
            .iter()
            .zip(&m)
            .map(|(a, b)| (a - along * b / n).powi(2))
            .sum::<f64>()
            .sqrt();
        Some(across / n)
    }
}

#[derive(Debug, Clone, Default)]
struct Acc {
    t_start: f64,
    t_end: f64,
    segment: u32,
    n: usize,
    a: [f64; 3],
    a2: [f64; 3],
    m: [f64; 3],
    nm: usize,
    g: [f64; 3],
    ng: usize,
    temp: f64,
    nt: usize,
    thr: f64,
    nthr: usize,
    /// The attitude (quaternion, sign kept on the first's side) and the magnetometer's unit
    /// direction against time since the pose began: how fast the pose turned.
    q_ref: Option<[f64; 4]>,
    q_trend: Trend<4>,
    m_trend: Trend<3>,
}

impl Acc {
    fn add(&mut self, s: &Held, a: &Vec3) {
        if self.n == 0 {
            self.t_start = s.t_s;
            self.segment = s.segment;
        }
        self.t_end = s.t_s;
        self.n += 1;
        for k in 0..3 {
            self.a[k] += a[k];
            self.a2[k] += a[k] * a[k];
        }
        let t = s.t_s - self.t_start;
        if let Some(q) = s.ref_q.filter(|q| q.iter().all(|x| x.is_finite())) {
            let r = *self.q_ref.get_or_insert(q);
            let same_side = q.iter().zip(&r).map(|(a, b)| a * b).sum::<f64>() >= 0.0;
            self.q_trend
                .add(t, &if same_side { q } else { q.map(|x| -x) });
        }
        if let Some(m) = s.mag_ut {
            let n = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
            if n > 0.0 && n.is_finite() {
                self.m_trend.add(t, &m.map(|x| x / n));
            }
            self.nm += 1;
            for k in 0..3 {
                self.m[k] += m[k];
            }
        }
        if let Some(g) = s.gyro_rad_s {
            self.ng += 1;
            for k in 0..3 {
                self.g[k] += g[k];
            }
        }
        if let Some(t) = s.temp_c {
            self.nt += 1;
            self.temp += t;
        }
        if let Some(t) = s.throttle {
            self.nthr += 1;
            self.thr += t;
        }
    }
    /// How fast the pose turned, deg/s: by the attitude, |omega| = 2 |dq/dt| (the slope's part
    /// across q), else by the magnetometer, the rate its unit direction moves.
    fn turn_rate_deg_s(&self) -> Option<f64> {
        match self.q_trend.rate_across() {
            Some(r) => Some((2.0 * r).to_degrees()),
            None => self.m_trend.rate_across().map(f64::to_degrees),
        }
    }

    fn pose(&self) -> Pose {
        let n = self.n as f64;
        let mean = |v: &[f64; 3], c: usize| {
            let c = c as f64;
            [v[0] / c, v[1] / c, v[2] / c]
        };
        let a = mean(&self.a, self.n);
        let var: f64 = (0..3)
            .map(|k| (self.a2[k] / n - a[k] * a[k]).max(0.0))
            .sum();
        Pose {
            t_start: self.t_start,
            t_end: self.t_end,
            segment: self.segment,
            samples: self.n,
            accel: a,
            mag: (self.nm > 0).then(|| mean(&self.m, self.nm)),
            gyro: (self.ng > 0).then(|| mean(&self.g, self.ng)),
            temp_c: (self.nt > 0).then(|| self.temp / self.nt as f64),
            throttle: (self.nthr > 0).then(|| self.thr / self.nthr as f64),
            accel_var: var,
            turn_rate_deg_s: self.turn_rate_deg_s(),
        }
    }
}

/// Log-spaced histogram for a streaming quantile of window variances (bounded memory). The
/// quantile `q` is tracked as values arrive (a cursor on the bins that moves a step or two per
/// value), so reading it is O(1) instead of a scan of the bins per sample.
#[derive(Debug, Clone)]
struct LogHistogram {
    bins: Vec<u64>,
    total: u64,
    q: f64,
    /// Smallest bin whose cumulative count reaches `ceil(q * total)`, and the count below it.
    cursor: usize,
    below: u64,
    /// Centre value of the cursor's bin (kept so a read needs no `powf`).
    value: f64,
}

const HIST_MIN_LOG10: f64 = -14.0;
const HIST_BINS_PER_DECADE: f64 = 20.0;
const HIST_BINS: usize = 500;

impl LogHistogram {
    fn new(q: f64) -> Self {
        LogHistogram {
            bins: vec![0; HIST_BINS],
            total: 0,
            q,
            cursor: 0,
            below: 0,
            value: Self::centre(0),
        }
    }

    /// The bin of `v`: `floor((log10 v - HIST_MIN_LOG10) * HIST_BINS_PER_DECADE)`, clamped to the
    /// bins (0 for v <= 0 or NaN). Found from the binary exponent and a table of the bin edges, not
    /// a `log10` per window (this runs once per sample).
    fn bin_of(v: f64) -> usize {
        static EDGES: std::sync::OnceLock<Vec<f64>> = std::sync::OnceLock::new();
        let edges = EDGES.get_or_init(|| {
            (0..=HIST_BINS)
                .map(|i| 10f64.powf(HIST_MIN_LOG10 + i as f64 / HIST_BINS_PER_DECADE))
                .collect()
        });
        if !(v >= edges[1]) {
            return 0;
        }
        if v >= edges[HIST_BINS - 1] {
            return HIST_BINS - 1;
        }
        // log2 v to within 0.09 from the exponent and a linear mantissa, so the estimate is off by
        // at most one bin; the edges settle it.
        let bits = v.to_bits();
        let exp = ((bits >> 52) & 0x7ff) as f64 - 1023.0;
        let mant = f64::from_bits((bits & ((1u64 << 52) - 1)) | (1023u64 << 52));
        let log10 = (exp + mant - 1.0) * std::f64::consts::LOG10_2;
        // Clamped to whole bounds first, then truncated: the floor of the clamped value, which
        // is the clamped floor (a truncation, not a call to `floor`, per sample).
        let mut i = ((log10 - HIST_MIN_LOG10) * HIST_BINS_PER_DECADE)
            .clamp(1.0, (HIST_BINS - 2) as f64) as usize;
        while v < edges[i] {
            i -= 1;
        }
        while v >= edges[i + 1] {
            i += 1;
        }
        i
    }

    fn centre(bin: usize) -> f64 {
        10f64.powf(HIST_MIN_LOG10 + (bin as f64 + 0.5) / HIST_BINS_PER_DECADE)
    }

    /// `ceil(q * total)`, at least 1.
    fn target(&self) -> u64 {
        let x = self.q * self.total as f64;
        // The ceiling of a non-negative product below 2^53 by truncation: the same value as
        // `x.ceil()`, without a call per sample.
        let t = x as u64;
        let c = if (t as f64) < x { t + 1 } else { t };
        c.max(1)
    }

    fn add(&mut self, v: f64) {
        let i = Self::bin_of(v);
        self.bins[i] += 1;
        self.total += 1;
        if i < self.cursor {
            self.below += 1;
        }
        let (target, before) = (self.target(), self.cursor);
        while self.cursor + 1 < HIST_BINS && self.below + self.bins[self.cursor] < target {
            self.below += self.bins[self.cursor];
            self.cursor += 1;
        }
        while self.cursor > 0 && self.below >= target {
            self.cursor -= 1;
            self.below -= self.bins[self.cursor];
        }
        if self.cursor != before {
            self.value = Self::centre(self.cursor);
        }
    }

    /// Centre of the bin holding quantile `q`.
    fn quantile(&self) -> Option<f64> {
        (self.total > 0).then_some(self.value)
    }

    /// The same by a scan of the bins (the reference the tracked cursor is tested against).
    #[cfg(test)]
    fn quantile_by_scan(&self) -> Option<f64> {
        if self.total == 0 {
            return None;
        }
        let target = self.target();
        let mut c = 0;
        for (i, &b) in self.bins.iter().enumerate() {
            c += b;
            if c >= target {
                return Some(Self::centre(i));
            }
        }
        None
    }
}

/// What the detector reads of a sample in its window: the sample without the fields a pose
/// never takes (a third of its size; the window copies one in and one out per sample).
#[derive(Debug, Clone, Copy)]
struct Held {
    t_s: f64,
    segment: u32,
    ref_q: Option<[f64; 4]>,
    mag_ut: Option<Vec3>,
    gyro_rad_s: Option<Vec3>,
    temp_c: Option<f64>,
    throttle: Option<f64>,
}

impl From<&Sample> for Held {
    fn from(s: &Sample) -> Held {
        Held {
            t_s: s.t_s,
            segment: s.segment,
            ref_q: s.ref_q,
            mag_ut: s.mag_ut,
            gyro_rad_s: s.gyro_rad_s,
            temp_c: s.temp_c,
            throttle: s.throttle,
        }
    }
}

/// Streaming static detector on accelerometer samples. Each accel sample is judged by the variance of
/// the window centred on it (so output lags input by half a window); a run of still samples at least
/// `min_pose_s` long becomes a [`Pose`].
#[derive(Debug, Clone)]
pub(crate) struct StaticDetector {
    cfg: GateConfig,
    window: VecDeque<(Held, Vec3)>,
    half: usize,
    len: usize,
    hist: LogHistogram,
    cur: Acc,
    rate_est: Option<f64>,
    first_t: Option<f64>,
    n_seen: usize,
    /// Running sums of `accel - sum_ref` over the window (per axis), so the window variance costs
    /// O(1) per sample; recomputed exactly every `len` samples so rounding cannot build up.
    sum_ref: Vec3,
    sum: Vec3,
    sum2: Vec3,
    since_exact: usize,
    /// Current threshold in use.
    pub threshold: f64,
}

impl StaticDetector {
    pub fn new(cfg: GateConfig) -> Self {
        StaticDetector {
            cfg,
            window: VecDeque::new(),
            half: 0,
            len: 0,
            hist: LogHistogram::new(0.10),
            cur: Acc::default(),
            rate_est: None,
            first_t: None,
            n_seen: 0,
            sum_ref: [0.0; 3],
            sum: [0.0; 3],
            sum2: [0.0; 3],
            since_exact: 0,
            threshold: cfg.threshold.unwrap_or(f64::INFINITY),
        }
    }

    /// The noise-floor variance estimate (10th percentile of window variances so far).
    pub(crate) fn noise_floor(&self) -> Option<f64> {
        self.hist.quantile()
    }

    /// Summed per-axis variance of the window, from the running sums.
    fn window_variance(&self) -> f64 {
        let n = self.window.len() as f64;
        (0..3)
            .map(|k| (self.sum2[k] / n - (self.sum[k] / n).powi(2)).max(0.0))
            .sum()
    }

    /// Recompute the running sums exactly, about the window's first sample.
    fn resum(&mut self) {
        let r = self.window.front().map_or([0.0; 3], |w| w.1);
        self.sum_ref = r;
        self.sum = [0.0; 3];
        self.sum2 = [0.0; 3];
        for (_, a) in &self.window {
            for k in 0..3 {
                let d = a[k] - r[k];
                self.sum[k] += d;
                self.sum2[k] += d * d;
            }
        }
        self.since_exact = 0;
    }

    /// Take a sample into the running sums.
    fn add_sums(&mut self, a: &Vec3) {
        for k in 0..3 {
            let d = a[k] - self.sum_ref[k];
            self.sum[k] += d;
            self.sum2[k] += d * d;
        }
    }

    /// Take a sample out of the running sums (the exact negation of [`Self::add_sums`]'s terms).
    fn remove_sums(&mut self, a: &Vec3) {
        for k in 0..3 {
            let d = a[k] - self.sum_ref[k];
            self.sum[k] -= d;
            self.sum2[k] -= d * d;
        }
    }

    /// Feed one sample (accel = the prefiltered accel vector to judge). Returns a pose when one ends.
    pub fn push(&mut self, s: &Sample, accel: &Vec3) -> Option<Pose> {
        // A break in the source's time ends the pose and the window: nothing spans it.
        let ended = match self.window.back() {
            Some((last, _)) if last.segment != s.segment => {
                self.window.clear();
                self.close()
            }
            _ => None,
        };
        let next = self.push_in_segment(s, accel);
        ended.or(next)
    }

    fn push_in_segment(&mut self, s: &Sample, accel: &Vec3) -> Option<Pose> {
        // The window length in samples is fixed from the rate seen in the first 50 samples.
        self.n_seen += 1;
        let t0 = *self.first_t.get_or_insert(s.t_s);
        if self.rate_est.is_none() && self.n_seen == 50 {
            let dt = (s.t_s - t0) / 49.0;
            let rate = if dt > 0.0 { 1.0 / dt } else { 100.0 };
            self.rate_est = Some(rate);
            self.len = ((self.cfg.window_s * rate).round() as usize).clamp(5, 20_000) | 1;
            self.half = self.len / 2;
        }
        self.window.push_back((Held::from(s), *accel));
        if self.window.len() == 1 {
            self.resum();
        } else {
            self.add_sums(accel);
        }
        if self.len == 0 {
            // Rate not known yet: keep the first samples (bounded) until it is.
            return None;
        }
        let mut out = None;
        while self.window.len() > self.len {
            if let Some((_, a)) = self.window.pop_front() {
                self.remove_sums(&a);
            }
        }
        self.since_exact += 1;
        if self.since_exact >= self.len {
            self.resum();
        }
        if self.window.len() == self.len {
            let var = self.window_variance();
            self.hist.add(var);
            if self.cfg.threshold.is_none() {
                if let Some(f) = self.noise_floor() {
                    self.threshold = f * self.cfg.threshold_factor;
                }
            }
            if var <= self.threshold {
                let (cs, ca) = &self.window[self.half];
                self.cur.add(cs, ca);
            } else {
                out = self.close();
            }
        }
        out
    }

    fn close(&mut self) -> Option<Pose> {
        if self.cur.n == 0 {
            // Nothing since the last close: `cur` is as new already.
            return None;
        }
        let acc = std::mem::take(&mut self.cur);
        if acc.n > 0 && acc.t_end - acc.t_start >= self.cfg.min_pose_s {
            Some(acc.pose())
        } else {
            None
        }
    }

    /// End of input: close the current run.
    pub fn finish(&mut self) -> Option<Pose> {
        self.close()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_quantile_target_is_the_ceiling_of_its_product() {
        for q in [0.1, 0.05, 0.5, 0.9, 1.0 / 3.0] {
            let mut h = LogHistogram::new(q);
            for total in 0..200_000u64 {
                h.total = total;
                assert_eq!(
                    h.target(),
                    (q * total as f64).ceil().max(1.0) as u64,
                    "{q} {total}"
                );
            }
        }
    }

    #[test]
    fn histogram_bins_match_the_log10_formula() {
        let by_log = |v: f64| {
            let l = if v > 0.0 { v.log10() } else { HIST_MIN_LOG10 };
            ((l - HIST_MIN_LOG10) * HIST_BINS_PER_DECADE)
                .floor()
                .clamp(0.0, (HIST_BINS - 1) as f64) as usize
        };
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut checked = 0;
        for k in 0..200_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            // Log-uniform over 1e-16 .. 1e13, past both ends of the bins.
            let v = 10f64.powf(-16.0 + 29.0 * (x >> 11) as f64 / (1u64 << 53) as f64);
            let (got, want) = (LogHistogram::bin_of(v), by_log(v));
            if got != want {
                // Only within rounding of a bin edge.
                let edge = 10f64.powf(HIST_MIN_LOG10 + got.max(want) as f64 / HIST_BINS_PER_DECADE);
                assert!(
                    (v / edge - 1.0).abs() < 1e-13,
                    "{v:e}: {got} vs {want} ({k})"
                );
            }
            checked += 1;
        }
        assert_eq!(checked, 200_000);
        for v in [
            0.0,
            -1.0,
            f64::NAN,
            f64::MIN_POSITIVE,
            5e-324,
            f64::INFINITY,
            1e300,
        ] {
            assert_eq!(LogHistogram::bin_of(v), by_log(v), "{v:e}");
        }
    }

    #[test]
    fn tracked_quantile_equals_a_scan_of_the_bins() {
        let mut h = LogHistogram::new(0.10);
        assert_eq!(h.quantile(), None);
        let mut x = 0x9E37_79B9u32;
        for i in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            // A noise floor that shifts: quiet, then loud, then quiet again, plus zeros.
            let scale = if (5_000..12_000).contains(&i) {
                1e-2
            } else {
                1e-6
            };
            let v = if x.is_multiple_of(97) {
                0.0
            } else {
                scale * (x as f64 / u32::MAX as f64)
            };
            h.add(v);
            assert_eq!(h.quantile(), h.quantile_by_scan(), "after {} values", i + 1);
        }
    }
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    #[test]
    fn running_window_variance_matches_a_direct_sum() {
        // Raw counts far from zero, noise, and steps: the O(1) running sums agree with a direct
        // two-pass variance of the same window at every sample.
        let mut det = StaticDetector::new(GateConfig::default());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 3.0).unwrap();
        for i in 0..20_000 {
            let level = 33_000.0 + 4000.0 * ((i / 1500) % 3) as f64;
            let a = [
                level + noise.sample(&mut rng),
                -level + noise.sample(&mut rng),
                0.5 * level + noise.sample(&mut rng),
            ];
            let s = Sample {
                t_s: i as f64 * 0.01,
                ..Default::default()
            };
            det.push(&s, &a);
            if det.len == 0 || det.window.len() != det.len {
                continue;
            }
            let n = det.window.len() as f64;
            let direct: f64 = (0..3)
                .map(|k| {
                    let m = det.window.iter().map(|w| w.1[k]).sum::<f64>() / n;
                    det.window.iter().map(|w| (w.1[k] - m).powi(2)).sum::<f64>() / n
                })
                .sum();
            let fast = det.window_variance();
            assert!(
                (fast - direct).abs() <= 1e-6 * direct.max(1.0),
                "sample {i}: {fast} vs {direct}"
            );
        }
    }

    #[test]
    fn kalman_prefilter_converges_and_smooths() {
        let mut k = ScalarKalman::new(1e-4, 1.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let n = Normal::new(9.8, 0.5).unwrap();
        let mut last = 0.0;
        for _ in 0..2000 {
            last = k.update(n.sample(&mut rng));
        }
        assert!((last - 9.8).abs() < 0.1, "{last}");
    }

    #[test]
    fn finds_poses_between_motion_without_tuning() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let noise = Normal::new(0.0, 0.02).unwrap();
        let mut det = StaticDetector::new(GateConfig::default());
        let mut poses = vec![];
        let rate = 100.0;
        let mut t = 0.0;
        // The next sample at 100 Hz, reading `a`.
        let mut feed = |a: [f64; 3]| {
            let s = Sample {
                t_s: t,
                accel_mps2: Some(a),
                ..Default::default()
            };
            poses.extend(det.push(&s, &a));
            t += 1.0 / rate;
        };
        for p in 0..10 {
            let still = [0.0, (p as f64).sin() * 9.8, (p as f64).cos() * 9.8];
            for _ in 0..300 {
                feed([
                    still[0] + noise.sample(&mut rng),
                    still[1] + noise.sample(&mut rng),
                    still[2] + noise.sample(&mut rng),
                ]);
            }
            for i in 0..150 {
                let w = i as f64 * 0.1;
                feed([3.0 * w.sin(), 9.8 * w.cos(), 2.0]);
            }
        }
        poses.extend(det.finish());
        assert_eq!(
            poses.len(),
            10,
            "{:?}",
            poses.iter().map(|p| p.t_start).collect::<Vec<_>>()
        );
        assert!(poses[3].samples > 150);
        assert!((poses[3].accel[1] - 3f64.sin() * 9.8).abs() < 0.01);
    }
}
