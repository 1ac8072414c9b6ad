//! Orientation error metrics of the BROAD benchmark (Laidig, Caruso, Cereatti, Seel, "BROAD - A
//! Benchmark for Robust Inertial Orientation Estimation", Data 6(7), 2021). Pure math, no I/O.
//!
//! # Definition (as in the paper and its published example code `broad_utils.py`)
//! With `q_est` and `q_ref` both sensor -> ENU, the error quaternion expressed in the world frame is
//! `e = q_est * q_ref^-1`. Per sample:
//! * total error: the rotation angle of `e`, `2 acos(|e_w|)`;
//! * heading error: the angle of `e`'s rotation about the vertical, `2 atan(|e_z / e_w|)`;
//! * inclination error: the angle of what remains, `2 acos(sqrt(e_w^2 + e_z^2))`.
//!
//! Each is an RMSE over the samples of the movement phase (`moving == 1`) that have a reference
//! (occluded samples, empty `ref_q`, are skipped, like the `nanmean` of the original).
//!
//! # Constant frame offsets
//! Two constant rotations separate an estimate from an optical reference: the heading of the
//! optical world frame against the IMU's (magnetic north) world frame, and the misalignment of the
//! marker cluster against the sensor axes. BROAD estimates both when it prepares the data and
//! publishes the reference already corrected (the `opt_quat` of its files is the IMU's sensor -> ENU
//! orientation); its metric code then applies no further correction. That is checked on the six trials
//! in `shared/data/broad`: at the start rest, the field rotated by the reference points to magnetic north
//! within 0.8 deg and the reference quaternion is within 1.5 deg of the identity.
//! So [`evaluate`] does exactly what BROAD does: no offset estimation.
//!
//! For references that are *not* pre-aligned (other logs, a reference in another world frame),
//! [`evaluate_with`] can estimate and remove the two constant offsets itself: it finds the heading
//! rotation `h` (about the vertical) and the sensor-side rotation `m` that minimise the error of
//! `q_est ~ h * q_ref * m` over the evaluated samples, by alternating a circular mean of the heading
//! parts of the errors (for `h`) and a quaternion mean (for `m`). This removes real errors as well
//! (a constant heading error of the filter disappears in `Alignment::Heading`), so it is off by default.

use crate::types::Sample;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// BROAD error metrics, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EvalResult {
    pub total_rmse_deg: f64,
    pub heading_rmse_deg: f64,
    pub inclination_rmse_deg: f64,
    /// Samples that entered the RMSE (moving, with a reference and an estimate).
    pub samples: usize,
    /// Heading offset removed (deg; 0 unless [`Alignment`] asked for it).
    pub heading_offset_deg: f64,
    /// Angle of the sensor-side misalignment removed (deg; 0 unless asked for).
    pub misalignment_deg: f64,
}

/// Which constant offsets [`evaluate_with`] estimates and removes before the metrics (the command
/// line's `--align`: `none`, `heading` or `heading-and-misalignment`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Alignment {
    /// None: the reference is already aligned (BROAD's published data).
    #[default]
    None,
    /// A constant heading offset between the reference and the estimate world frames.
    Heading,
    /// The heading offset and a constant sensor-to-marker misalignment.
    HeadingAndMisalignment,
}

/// What `imucald eval LOG` reports: the metrics of imucald's orientation filter on a log with a
/// reference, and what the filter learned on the way.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FilterEvaluation {
    pub metrics: EvalResult,
    pub alignment: Alignment,
    /// 9D (with magnetometer) or 6D.
    pub use_mag: bool,
    /// Samples in the log.
    pub samples_total: usize,
    /// Final gyro bias estimate, rad/s.
    pub gyro_bias_rad_s: [f64; 3],
    /// Magnetometer latency in use at the end, s.
    pub mag_delay_s: f64,
    /// Learned reference field norm (input units) and dip (deg).
    pub mag_reference: Option<(f64, f64)>,
}

impl FilterEvaluation {
    /// Plain-text summary, one item a line.
    pub fn to_text(&self) -> String {
        let m = &self.metrics;
        let mut s = format!(
            "orientation filter ({}) against the log's reference, BROAD metrics over {} moving samples:\n",
            if self.use_mag { "9D" } else { "6D" },
            m.samples
        );
        s += &format!("  total RMSE        {:.3} deg\n", m.total_rmse_deg);
        s += &format!("  heading RMSE      {:.3} deg\n", m.heading_rmse_deg);
        s += &format!("  inclination RMSE  {:.3} deg\n", m.inclination_rmse_deg);
        if self.alignment != Alignment::None {
            s += &format!(
                "  removed offsets: heading {:.2} deg, misalignment {:.2} deg\n",
                m.heading_offset_deg, m.misalignment_deg
            );
        }
        let b = self.gyro_bias_rad_s;
        s += &format!(
            "  gyro bias (end)   {:.5} {:.5} {:.5} rad/s\n",
            b[0], b[1], b[2]
        );
        if self.use_mag {
            s += &format!("  mag latency       {:.1} ms\n", self.mag_delay_s * 1e3);
            if let Some((n, d)) = self.mag_reference {
                s += &format!("  field reference   norm {n:.2}, dip {d:.2} deg\n");
            }
        }
        s
    }
}

/// Run imucald's orientation filter (world ENU, as the reference) over a log and evaluate it against
/// the log's reference orientation. `None` when the log has no reference in its evaluated samples.
pub fn evaluate_filter(
    samples: &[Sample],
    cfg: &crate::attitude::fusion::FusionConfig,
    align: Alignment,
) -> Option<FilterEvaluation> {
    let cfg = crate::attitude::fusion::FusionConfig {
        world: crate::attitude::fusion::WorldFrame::Enu,
        ..*cfg
    };
    let dt = crate::attitude::fusion::median_dt(samples);
    let mut f = crate::attitude::fusion::OrientationFilter::new(cfg);
    let est: Vec<UnitQuaternion<f64>> = samples
        .iter()
        .map(|s| {
            f.update_sample(s, dt);
            f.quaternion()
        })
        .collect();
    let metrics = evaluate_with(samples, &est, align);
    (metrics.samples > 0).then(|| FilterEvaluation {
        metrics,
        alignment: align,
        use_mag: cfg.use_mag,
        samples_total: samples.len(),
        gyro_bias_rad_s: f.bias(),
        mag_delay_s: f.mag_delay_s(),
        mag_reference: f.mag_reference(),
    })
}

/// The per-sample errors (total, heading, inclination), radians, of `q_est` against `q_ref`.
pub fn errors(q_est: &UnitQuaternion<f64>, q_ref: &UnitQuaternion<f64>) -> (f64, f64, f64) {
    let e = (q_est * q_ref.inverse()).into_inner();
    let n = e.norm();
    let (w, z) = if n > 0.0 {
        (e.w / n, e.k / n)
    } else {
        (1.0, 0.0)
    };
    let total = 2.0 * w.abs().clamp(0.0, 1.0).acos();
    let heading = if w == 0.0 {
        std::f64::consts::PI
    } else {
        2.0 * (z / w).abs().atan()
    };
    let incl = 2.0 * (w * w + z * z).sqrt().clamp(0.0, 1.0).acos();
    (total, heading, incl)
}

/// The reference quaternion of a sample (sensor -> ENU), when present and valid.
pub fn reference(s: &Sample) -> Option<UnitQuaternion<f64>> {
    let r = s.ref_q?;
    if !r.iter().all(|x| x.is_finite()) {
        return None;
    }
    let q = Quaternion::new(r[0], r[1], r[2], r[3]);
    (q.norm() > 0.5).then(|| UnitQuaternion::from_quaternion(q))
}

/// Indices that BROAD's metric uses: moving (or all samples when the log has no `moving` flag), with a
/// reference.
fn evaluated(samples: &[Sample]) -> Vec<usize> {
    let has_flag = samples.iter().any(|s| s.moving.is_some());
    samples
        .iter()
        .enumerate()
        .filter(|(_, s)| (!has_flag || s.moving == Some(true)) && reference(s).is_some())
        .map(|(i, _)| i)
        .collect()
}

/// BROAD's total, heading and inclination RMSE of `estimate` (sensor -> ENU, one per sample) over the
/// movement phase, with the reference taken as published (already aligned, see the module docs).
pub fn evaluate(samples: &[Sample], estimate: &[UnitQuaternion<f64>]) -> EvalResult {
    evaluate_with(samples, estimate, Alignment::None)
}

/// As [`evaluate`], removing the constant offsets that `align` names first.
pub fn evaluate_with(
    samples: &[Sample],
    estimate: &[UnitQuaternion<f64>],
    align: Alignment,
) -> EvalResult {
    let idx: Vec<usize> = evaluated(samples)
        .into_iter()
        .filter(|&i| i < estimate.len())
        .collect();
    let pairs: Vec<(UnitQuaternion<f64>, UnitQuaternion<f64>)> = idx
        .iter()
        .filter_map(|&i| reference(&samples[i]).map(|r| (estimate[i], r)))
        .collect();
    let (h, m) = match align {
        Alignment::None => (UnitQuaternion::identity(), UnitQuaternion::identity()),
        Alignment::Heading => (
            heading_offset(&pairs, &UnitQuaternion::identity()),
            UnitQuaternion::identity(),
        ),
        Alignment::HeadingAndMisalignment => offsets(&pairs),
    };
    let (mut st, mut sh, mut si) = (0.0, 0.0, 0.0);
    for (e, r) in &pairs {
        let (t, hd, inc) = errors(e, &(h * r * m));
        st += t * t;
        sh += hd * hd;
        si += inc * inc;
    }
    let n = pairs.len().max(1) as f64;
    let deg = |s: f64| {
        if pairs.is_empty() {
            f64::NAN
        } else {
            (s / n).sqrt().to_degrees()
        }
    };
    EvalResult {
        total_rmse_deg: deg(st),
        heading_rmse_deg: deg(sh),
        inclination_rmse_deg: deg(si),
        samples: pairs.len(),
        heading_offset_deg: 2.0 * h.k.atan2(h.w).to_degrees(),
        misalignment_deg: m.angle().to_degrees(),
    }
}

/// The constant heading rotation `h` (about z) best matching `q_est ~ h * q_ref * m`: the circular mean
/// of the signed heading angles `2 atan2(e_z, e_w)` of the world-frame errors.
fn heading_offset(
    pairs: &[(UnitQuaternion<f64>, UnitQuaternion<f64>)],
    m: &UnitQuaternion<f64>,
) -> UnitQuaternion<f64> {
    let (mut c, mut s) = (0.0, 0.0);
    for (e, r) in pairs {
        let d = e * (r * m).inverse();
        let a = 2.0 * d.k.atan2(d.w);
        c += a.cos();
        s += a.sin();
    }
    if c == 0.0 && s == 0.0 {
        return UnitQuaternion::identity();
    }
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), s.atan2(c))
}

/// Alternating estimate of the heading offset `h` and the sensor-side misalignment `m`.
fn offsets(
    pairs: &[(UnitQuaternion<f64>, UnitQuaternion<f64>)],
) -> (UnitQuaternion<f64>, UnitQuaternion<f64>) {
    let mut m = UnitQuaternion::identity();
    for _ in 0..200 {
        let h = heading_offset(pairs, &m);
        // Mean of (h q_ref)^-1 q_est with signs aligned to the current m.
        let mut acc = Quaternion::new(0.0, 0.0, 0.0, 0.0);
        for (e, r) in pairs {
            let d = ((h * r).inverse() * e).into_inner();
            acc += if d.dot(&m) < 0.0 { -d } else { d };
        }
        if acc.norm() == 0.0 {
            break;
        }
        let m_new = UnitQuaternion::from_quaternion(acc);
        let step = m_new.angle_to(&m);
        m = m_new;
        if step < 1e-10 {
            break;
        }
    }
    (heading_offset(pairs, &m), m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples_with(refs: &[UnitQuaternion<f64>]) -> Vec<Sample> {
        refs.iter()
            .enumerate()
            .map(|(i, r)| Sample {
                t_s: i as f64 * 0.01,
                ref_q: Some([r.w, r.i, r.j, r.k]),
                moving: Some(i >= 10),
                ..Default::default()
            })
            .collect()
    }

    fn refs(n: usize) -> Vec<UnitQuaternion<f64>> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 0.05;
                UnitQuaternion::from_euler_angles(0.8 * t.sin(), 0.5 * (0.7 * t).cos(), 0.3 * t)
            })
            .collect()
    }

    #[test]
    fn heading_and_inclination_errors_split() {
        let r = refs(200);
        let s = samples_with(&r);
        let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians());
        let est: Vec<_> = r.iter().map(|q| rz * q).collect();
        let e = evaluate(&s, &est);
        assert_eq!(e.samples, 190);
        assert!((e.heading_rmse_deg - 2.0).abs() < 1e-9, "{e:?}");
        assert!(e.inclination_rmse_deg < 1e-6);
        assert!((e.total_rmse_deg - 2.0).abs() < 1e-9);
        let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 3f64.to_radians());
        let est: Vec<_> = r.iter().map(|q| rx * q).collect();
        let e = evaluate(&s, &est);
        assert!(e.heading_rmse_deg < 1e-6, "{e:?}");
        assert!((e.inclination_rmse_deg - 3.0).abs() < 1e-9);
        // Sign of the quaternion does not matter.
        let neg: Vec<_> = est
            .iter()
            .map(|q| UnitQuaternion::new_unchecked(-q.into_inner()))
            .collect();
        assert!((evaluate(&s, &neg).total_rmse_deg - 3.0).abs() < 1e-9);
    }

    #[test]
    fn occluded_and_resting_samples_are_skipped() {
        let r = refs(50);
        let mut s = samples_with(&r);
        s[20].ref_q = None;
        s[21].ref_q = Some([f64::NAN; 4]);
        // Huge errors where they must not count.
        let mut est = r.clone();
        let big = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 1.0);
        for i in [0, 5, 20, 21] {
            est[i] = big * est[i];
        }
        let e = evaluate(&s, &est);
        assert_eq!(e.samples, 38);
        assert!(e.total_rmse_deg < 1e-6, "{e:?}");
    }

    #[test]
    fn constant_offsets_are_found_and_removed() {
        let r = refs(400);
        let s = samples_with(&r);
        let h = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 25f64.to_radians());
        let m = UnitQuaternion::from_euler_angles(0.05, -0.08, 0.1);
        let est: Vec<_> = r.iter().map(|q| h * q * m).collect();
        let plain = evaluate(&s, &est);
        assert!(plain.total_rmse_deg > 20.0);
        let e = evaluate_with(&s, &est, Alignment::HeadingAndMisalignment);
        assert!(e.total_rmse_deg < 1e-3, "{e:?}");
        assert!((e.heading_offset_deg - 25.0).abs() < 1e-3);
        assert!((e.misalignment_deg - m.angle().to_degrees()).abs() < 1e-3);
        let est: Vec<_> = r.iter().map(|q| h * q).collect();
        let e = evaluate_with(&s, &est, Alignment::Heading);
        assert!(e.total_rmse_deg < 1e-6, "{e:?}");
    }
}
