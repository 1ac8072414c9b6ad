//! Stillness and temperature bins of a warm-up: the samples cut into short blocks, each judged
//! still or moving by the spread of its accelerometer and gyro readings (a variance test, as
//! `calib::gate`'s detector, on fixed blocks); the readings of the still blocks averaged into
//! temperature bins.

use super::poly::Point;
use super::TempCalSettings;
use crate::types::{Sample, Vec3};

/// The six channels of a reading: accelerometer x, y, z (m/s^2), gyro x, y, z (rad/s).
pub(crate) type Six = [f64; 6];

/// A reading with all that a temperature calibration needs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Reading {
    pub t_s: f64,
    pub segment: u32,
    pub v: Six,
    pub temp_c: f64,
}

/// The readings of the samples that carry an accelerometer, a gyro and a temperature reading,
/// all finite; and how many samples did not.
pub(crate) fn readings(samples: &[Sample]) -> (Vec<Reading>, usize) {
    let mut out = Vec::with_capacity(samples.len());
    for s in samples {
        let (Some(a), Some(g), Some(t)) = (s.accel_mps2, s.gyro_rad_s, s.temp_c) else {
            continue;
        };
        let v = [a[0], a[1], a[2], g[0], g[1], g[2]];
        if v.iter().all(|x| x.is_finite()) && t.is_finite() {
            out.push(Reading {
                t_s: s.t_s,
                segment: s.segment,
                v,
                temp_c: t,
            });
        }
    }
    let skipped = samples.len() - out.len();
    (out, skipped)
}

/// One block's statistics.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Block {
    /// Index of its first reading and one past its last.
    pub start: usize,
    pub end: usize,
    pub duration_s: f64,
    pub mean: Six,
    pub std: Six,
    pub temp_c: f64,
}

/// Consecutive readings cut into blocks of `block_s` (a new one at a time segment's start).
pub(crate) fn blocks(r: &[Reading], block_s: f64) -> Vec<Block> {
    let mut out = Vec::new();
    let mut start = 0;
    while start < r.len() {
        let mut end = start + 1;
        while end < r.len()
            && r[end].segment == r[start].segment
            && r[end].t_s - r[start].t_s < block_s
        {
            end += 1;
        }
        out.push(block_of(r, start, end));
        start = end;
    }
    out
}

fn block_of(r: &[Reading], start: usize, end: usize) -> Block {
    let n = (end - start) as f64;
    let first = r[start].v;
    let (mut sum, mut sq) = ([0.0; 6], [0.0; 6]);
    let mut temp = 0.0;
    for x in &r[start..end] {
        for k in 0..6 {
            let d = x.v[k] - first[k];
            sum[k] += d;
            sq[k] += d * d;
        }
        temp += x.temp_c;
    }
    let mut mean = [0.0; 6];
    let mut std = [0.0; 6];
    for k in 0..6 {
        let m = sum[k] / n;
        mean[k] = first[k] + m;
        std[k] = (sq[k] / n - m * m).max(0.0).sqrt();
    }
    let duration_s = if end > start + 1 {
        (r[end - 1].t_s - r[start].t_s) * n / (n - 1.0)
    } else {
        0.0
    };
    Block {
        start,
        end,
        duration_s,
        mean,
        std,
        temp_c: temp / n,
    }
}

/// How much the vehicle moved during the warm-up.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct Motion {
    /// The blocks judged still (by index).
    pub still: Vec<bool>,
    /// Time in moving blocks, s, and its share of the whole.
    pub moving_s: f64,
    pub moving_fraction: f64,
    /// The rotation the moving blocks add up to at most (the rate above the still median,
    /// integrated), deg.
    pub rotated_deg: f64,
    /// The largest block-mean rate above the still median, deg/s.
    pub peak_rate_dps: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Each block judged still or moving: moving when an accelerometer axis spreads more than
/// `accel_std_max_mps2`, a gyro axis more than `gyro_std_max_rad_s`, or the block's mean rate
/// departs from the median of all blocks by more than `gyro_std_max_rad_s` (a slow, even turn).
pub(crate) fn motion(b: &[Block], s: &TempCalSettings) -> Motion {
    let med: Vec3 = [3, 4, 5].map(|k| median(b.iter().map(|x| x.mean[k]).collect()));
    let mut m = Motion {
        still: Vec::with_capacity(b.len()),
        ..Default::default()
    };
    let total: f64 = b.iter().map(|x| x.duration_s).sum();
    for x in b {
        let rate = ((0..3)
            .map(|k| (x.mean[3 + k] - med[k]).powi(2))
            .sum::<f64>())
        .sqrt();
        let spread_a = x.std[..3].iter().cloned().fold(0.0, f64::max);
        let spread_g = x.std[3..].iter().cloned().fold(0.0, f64::max);
        let moving = spread_a > s.accel_std_max_mps2
            || spread_g > s.gyro_std_max_rad_s
            || rate > s.gyro_std_max_rad_s;
        m.still.push(!moving);
        if moving {
            m.moving_s += x.duration_s;
            m.rotated_deg += (rate + spread_g).to_degrees() * x.duration_s;
            m.peak_rate_dps = m.peak_rate_dps.max((rate + spread_g).to_degrees());
        }
    }
    m.moving_fraction = if total > 0.0 { m.moving_s / total } else { 0.0 };
    m
}

/// One temperature bin of still readings.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Bin {
    pub n: usize,
    sum_t: f64,
    shift: Six,
    sum: Six,
    sq: Six,
}

impl Bin {
    fn push(&mut self, x: &Reading) {
        if self.n == 0 {
            self.shift = x.v;
        }
        self.n += 1;
        self.sum_t += x.temp_c;
        for k in 0..6 {
            let d = x.v[k] - self.shift[k];
            self.sum[k] += d;
            self.sq[k] += d * d;
        }
    }

    /// The bin's point of channel `k`.
    pub fn point(&self, k: usize) -> Point {
        let n = self.n as f64;
        let m = self.sum[k] / n;
        let var = (self.sq[k] / n - m * m).max(0.0) * n / (n - 1.0).max(1.0);
        Point {
            temp_c: self.sum_t / n,
            value: self.shift[k] + m,
            se: (var / n).sqrt(),
            n: self.n,
        }
    }
}

/// The still readings binned by temperature in bands of `bin_c` (aligned on multiples of it),
/// from the coldest band to the hottest: every band between, empty ones too.
pub(crate) fn temperature_bins(r: &[Reading], b: &[Block], still: &[bool], bin_c: f64) -> Vec<Bin> {
    let used = b
        .iter()
        .zip(still)
        .filter(|(_, s)| **s)
        .flat_map(|(x, _)| &r[x.start..x.end]);
    let band = |t: f64| (t / bin_c).floor() as i64;
    let (lo, hi) = used.clone().fold((i64::MAX, i64::MIN), |(l, h), x| {
        (l.min(band(x.temp_c)), h.max(band(x.temp_c)))
    });
    if lo > hi {
        return vec![];
    }
    let mut bins = vec![Bin::default(); (hi - lo + 1) as usize];
    for x in used {
        bins[(band(x.temp_c) - lo) as usize].push(x);
    }
    bins
}
