//! Block means: a fast stream averaged over short, equal blocks of samples before the calibration
//! and the attitude filter see it.
//!
//! An IMU read at 1 kHz tells the calibration no more than its means over a few milliseconds do:
//! a pose is held for a second or more ([`crate::calib::gate::GateConfig::min_pose_s`]), the
//! magnetometer's kept points lie a degree or more apart
//! ([`crate::calib::settings::FitSettings::min_separation_deg`]), and over a 10 ms block a vehicle
//! turning a full turn per second moves 3.6 degrees, which shortens the block's mean field by
//! about 1.6e-4 of its length (1 - sinc of half the angle). The mean of a block also has the
//! noise of one reading divided by the square root of its length, and the gyro's mean times the
//! block's length is the block's rotation (to within its coning, second order in the angle), so
//! the attitude filter integrates the same motion at the lower rate.
//!
//! The block length is counted in samples, from the stream's measured spacing: a stream at or
//! below the target rate passes through unchanged, sample for sample, with no delay.

use crate::types::{Sample, Vec3};

/// Smoothing of the measured sample spacing (weight of each new spacing).
const SPACING_WEIGHT: f64 = 0.01;

/// Averages a stream over blocks of about `period_s`.
#[derive(Debug, Clone)]
pub struct BlockMean {
    period_s: f64,
    /// Measured spacing of the input, s (an exponential mean of the steps within a segment).
    spacing_s: Option<f64>,
    /// The previous input's time and segment.
    last: Option<(f64, u32)>,
    block: Block,
}

/// Sums of the block being filled.
#[derive(Debug, Clone, Default)]
struct Block {
    n: usize,
    segment: u32,
    t_s: f64,
    accel: Sum3,
    gyro: Sum3,
    mag: Sum3,
    temp_c: Sum1,
    throttle: Sum1,
    current_a: Sum1,
    /// The newest of the block's values that are not averaged.
    ref_q: Option<[f64; 4]>,
    moving: Option<bool>,
    position: Option<crate::types::GeoPoint>,
}

#[derive(Debug, Clone, Copy, Default)]
struct Sum3 {
    n: u32,
    s: Vec3,
}

impl Sum3 {
    fn add(&mut self, v: Option<Vec3>) {
        if let Some(v) = v {
            self.n += 1;
            for k in 0..3 {
                self.s[k] += v[k];
            }
        }
    }

    fn mean(&self) -> Option<Vec3> {
        (self.n > 0).then(|| self.s.map(|x| x / self.n as f64))
    }
}

#[derive(Debug, Clone, Copy, Default)]
struct Sum1 {
    n: u32,
    s: f64,
}

impl Sum1 {
    fn add(&mut self, v: Option<f64>) {
        if let Some(v) = v {
            self.n += 1;
            self.s += v;
        }
    }

    fn mean(&self) -> Option<f64> {
        (self.n > 0).then(|| self.s / self.n as f64)
    }
}

impl Block {
    fn add(&mut self, s: &Sample) {
        if self.n == 0 {
            self.segment = s.segment;
        }
        self.n += 1;
        self.t_s += s.t_s;
        self.accel.add(s.accel_mps2);
        self.gyro.add(s.gyro_rad_s);
        self.mag.add(s.mag_ut);
        self.temp_c.add(s.temp_c);
        self.throttle.add(s.throttle);
        self.current_a.add(s.current_a);
        self.ref_q = s.ref_q.or(self.ref_q);
        self.moving = s.moving.or(self.moving);
        self.position = s.position.or(self.position);
    }

    /// The block's mean sample (at its mean time); the block is emptied.
    fn take(&mut self) -> Sample {
        let b = std::mem::take(self);
        Sample {
            t_s: b.t_s / b.n as f64,
            segment: b.segment,
            accel_mps2: b.accel.mean(),
            gyro_rad_s: b.gyro.mean(),
            mag_ut: b.mag.mean(),
            temp_c: b.temp_c.mean(),
            throttle: b.throttle.mean(),
            current_a: b.current_a.mean(),
            ref_q: b.ref_q,
            moving: b.moving,
            position: b.position,
        }
    }
}

impl BlockMean {
    /// Blocks of about `period_s` seconds; 0 (or less) passes every sample through.
    pub fn new(period_s: f64) -> Self {
        BlockMean {
            period_s: period_s.max(0.0),
            spacing_s: None,
            last: None,
            block: Block::default(),
        }
    }

    /// Samples per block at the spacing measured so far (1 until one is measured).
    pub fn block_len(&self) -> usize {
        match self.spacing_s {
            Some(dt) if dt > 0.0 && self.period_s > 0.0 => {
                // (A ratio under 1.5 rounds to 1: a stream at the target rate passes through.)
                ((self.period_s / dt).round() as usize).max(1)
            }
            _ => 1,
        }
    }

    /// Take one sample; the mean of a block when this one completes it. A break in time (a new
    /// segment) ends the block before it, which is returned then: nothing is averaged across a
    /// break.
    pub fn push(&mut self, s: &Sample) -> Option<Sample> {
        self.measure_spacing(s);
        let ended =
            (self.block.n > 0 && self.block.segment != s.segment).then(|| self.block.take());
        let k = self.block_len();
        if ended.is_none() && k == 1 && self.block.n == 0 {
            return Some(*s);
        }
        self.block.add(s);
        match ended {
            Some(m) => Some(m),
            None if self.block.n >= k => Some(self.block.take()),
            None => None,
        }
    }

    fn measure_spacing(&mut self, s: &Sample) {
        if let Some((t, seg)) = self.last {
            let dt = s.t_s - t;
            if seg == s.segment && dt > 0.0 && dt.is_finite() {
                self.spacing_s = Some(match self.spacing_s {
                    Some(m) => m + SPACING_WEIGHT * (dt - m),
                    None => dt,
                });
            }
        }
        self.last = Some((s.t_s, s.segment));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t_s: f64, segment: u32, v: f64) -> Sample {
        Sample {
            t_s,
            segment,
            accel_mps2: Some([v, 0.0, 9.8]),
            gyro_rad_s: Some([0.0, v, 0.0]),
            mag_ut: (v as i64 % 2 == 0).then_some([20.0, v, 40.0]),
            temp_c: Some(v),
            ..Default::default()
        }
    }

    /// A stream at or below the target rate comes out as it went in, with no delay.
    #[test]
    fn a_slow_stream_passes_through() {
        let mut b = BlockMean::new(0.01);
        for i in 0..300 {
            let s = sample(i as f64 * 0.01, 0, i as f64);
            assert_eq!(b.push(&s), Some(s));
        }
        let mut off = BlockMean::new(0.0);
        for i in 0..300 {
            let s = sample(i as f64 * 0.001, 0, i as f64);
            assert_eq!(off.push(&s), Some(s));
        }
    }

    /// At 1 kHz with 10 ms blocks, each output is the mean of ten inputs, at their mean time; a
    /// field present in only some of them is the mean of those.
    #[test]
    fn a_fast_stream_gives_the_means_of_its_blocks() {
        let mut b = BlockMean::new(0.01);
        let mut out = Vec::new();
        for i in 0..2000 {
            if let Some(m) = b.push(&sample(i as f64 * 0.001, 0, i as f64)) {
                out.push(m);
            }
        }
        assert_eq!(b.block_len(), 10);
        // The first sample passes (no spacing measured yet); then blocks of ten: samples 1-10,
        // 11-20, ..., 1981-1990 (1991-1999 wait for one more).
        assert_eq!(out.len(), 200);
        let last = out.last().unwrap();
        assert!((last.t_s - 1.9855).abs() < 1e-9, "{}", last.t_s);
        assert!((last.accel_mps2.unwrap()[0] - 1985.5).abs() < 1e-9);
        assert!((last.temp_c.unwrap() - 1985.5).abs() < 1e-9);
        // The magnetometer is in the even samples only: their mean.
        assert!((last.mag_ut.unwrap()[1] - 1986.0).abs() < 1e-9);
    }

    /// A break in time ends the block: nothing is averaged across it.
    #[test]
    fn a_break_ends_the_block() {
        let mut b = BlockMean::new(0.01);
        let mut out = Vec::new();
        for i in 0..105 {
            out.extend(b.push(&sample(i as f64 * 0.001, 0, 1.0)));
        }
        for i in 0..20 {
            out.extend(b.push(&sample(50.0 + i as f64 * 0.001, 1, 3.0)));
        }
        let first_of_1 = out.iter().position(|s| s.segment == 1).unwrap();
        assert!(out[..first_of_1]
            .iter()
            .all(|s| s.accel_mps2.unwrap()[0] == 1.0));
        assert!(out[first_of_1..]
            .iter()
            .all(|s| s.accel_mps2.unwrap()[0] == 3.0));
        // The partial block before the break was given out, not lost.
        assert!(out[first_of_1 - 1].t_s < 0.105 && out[first_of_1 - 1].t_s > 0.099);
    }
}
