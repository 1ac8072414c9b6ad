//! Finished calibrations applied to samples, with roll, pitch and heading.

use super::fits::FitResults;
use crate::calib::model::Calibration;
use crate::calib::outcome::CalStatus;
use crate::types::{Sample, Vec3};

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
