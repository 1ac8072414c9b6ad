//! The replay's temperature calibration ([`crate::calib::tempcal`]): every IMU instance whose
//! kept samples carry a temperature, its record in the report's `temperature`, its parameter
//! files and its terminal line.

use super::Run;
use crate::calib::tempcal::export::{self, InstanceExport};
use crate::calib::tempcal::onboard::Applied;
use crate::calib::tempcal::{
    calibrate, has_temperature, OnboardTcal, TempCalReport, TempCalSettings, TempOutcome,
};
use crate::error::Error;
use crate::io::onboard::SensorStream;
use crate::types::{Sample, Sensor};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The IMU number and device id of an instance: the accelerometer stream among the instance
/// name's parts (`IMU2+MAG2` -> `IMU2`), else the instance's position in the log.
fn imu_of(name: &str, sensors: &[SensorStream], position: usize) -> (usize, Option<u32>) {
    sensors
        .iter()
        .filter(|s| s.sensor == Sensor::Accel)
        .find(|s| name.split('+').any(|p| p == s.source))
        .map_or((position, None), |s| (usize::from(s.instance), s.device_id))
}

/// Every parameter the log hands on (the onboard calibration slots' own), by name.
fn log_params(run: &Run) -> BTreeMap<String, f64> {
    let Some(o) = run.log.onboard() else {
        return BTreeMap::new();
    };
    o.mag
        .iter()
        .chain(&o.accel)
        .flat_map(|c| c.params.iter().map(|(k, v)| (k.clone(), *v)))
        .collect()
}

/// The samples with a temperature calibration the flight controller applied undone, and which.
fn undone<'a>(
    samples: &'a [Sample],
    params: &BTreeMap<String, f64>,
    flight_log: bool,
    imu: usize,
    device_id: Option<u32>,
) -> (std::borrow::Cow<'a, [Sample]>, OnboardTcal) {
    let has = |p: &str| params.keys().any(|k| k.starts_with(p));
    if !has("INS_TCAL") && !has("TC_") {
        let state = if flight_log {
            OnboardTcal::NotExposed
        } else {
            OnboardTcal::NoParameters
        };
        return (samples.into(), state);
    }
    let applied = Applied::ardupilot(params, imu)
        .or_else(|| device_id.and_then(|id| Applied::px4(params, id)));
    match applied {
        Some(a) => (
            samples.iter().map(|s| a.undo(s)).collect::<Vec<_>>().into(),
            OnboardTcal::Undone,
        ),
        None => (samples.into(), OnboardTcal::NotEnabled),
    }
}

/// The temperature calibration of every instance of the run with temperature readings: the
/// primary's first, then the further instances in the log's order. Empty when none has.
pub(super) fn temperature(run: &Run) -> Vec<TempCalReport> {
    let log = &run.log;
    let sensors: &[SensorStream] = log.flight.as_ref().map_or(&[], |f| &f.sensors);
    let primary_at = log.flight.as_ref().and_then(|f| f.primary).unwrap_or(0);
    let primary = log
        .instance
        .clone()
        .unwrap_or_else(|| super::load::PRIMARY.to_string());
    let mut streams: Vec<(String, usize, &[Sample])> = vec![(primary, primary_at, &log.samples)];
    for (k, info) in log.instances.iter().enumerate() {
        let samples = run.other_samples.get(k).map_or(&[][..], |v| &v[..]);
        if run.others.get(k).is_some_and(Option::is_some) && !samples.is_empty() {
            streams.push((info.name.clone(), k, samples));
        }
    }
    let params = log_params(run);
    let settings = TempCalSettings::default();
    let mut out = vec![];
    for (name, position, samples) in streams {
        if !has_temperature(samples) {
            continue;
        }
        let (imu, device_id) = imu_of(&name, sensors, position);
        let (samples, onboard) = undone(samples, &params, log.flight.is_some(), imu, device_id);
        let result = calibrate(&samples, &settings);
        if result.samples == 0 {
            continue;
        }
        out.push(TempCalReport {
            instance: name,
            imu,
            device_id,
            onboard,
            result,
        });
    }
    out
}

/// `tempcal_ardupilot.parm` and `tempcal_px4.params` in `dir` when an instance was calibrated
/// (else no file: nothing to load).
pub(super) fn write_exports(dir: &Path, t: &[TempCalReport]) -> Result<Vec<PathBuf>, Error> {
    if !t
        .iter()
        .any(|r| matches!(r.result.outcome, TempOutcome::Calibrated(_)))
    {
        return Ok(vec![]);
    }
    let list: Vec<InstanceExport<'_>> = t
        .iter()
        .map(|r| InstanceExport {
            index: r.imu,
            name: &r.instance,
            device_id: r.device_id,
            outcome: &r.result.outcome,
        })
        .collect();
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut written = vec![];
    for (name, text) in [
        ("tempcal_ardupilot.parm", export::ardupilot_file(&list)),
        ("tempcal_px4.params", export::px4_file(&list)),
    ] {
        let p = dir.join(name);
        crate::io::publish::write_atomic(&p, text.as_bytes())?;
        written.push(p);
    }
    Ok(written)
}

/// The median of the axes' held-out shrink of a sensor, `-` when none was scored.
fn shrink(axes: &[crate::calib::tempcal::AxisCurve]) -> String {
    let mut v: Vec<f64> = axes
        .iter()
        .filter_map(|a| a.held_out.map(|h| h.shrink))
        .collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2)
        .map_or("-".into(), |m| format!("{m:.0}x"))
}

/// One terminal line per instance.
pub(super) fn summary_lines(t: &[TempCalReport]) -> String {
    let mut s = String::new();
    for r in t {
        let [lo, hi] = r.result.range_c;
        let head = format!(
            "temperature ({}, IMU {}): {:.1} to {:.1} C",
            r.instance, r.imu, lo, hi
        );
        let line = match &r.result.outcome {
            TempOutcome::Calibrated(c) => format!(
                "{head}, {} points of {} C: accel and gyro biases fitted (cubic), held-out shrink accel {}, gyro {} (medians of the axes)",
                c.points,
                TempCalSettings::default().bin_c,
                shrink(&c.accel.axes),
                shrink(&c.gyro.axes)
            ),
            TempOutcome::Refused(why) => format!("{head}: no temperature calibration: {why}"),
        };
        let note = match r.onboard {
            OnboardTcal::Undone => "; the onboard temperature calibration undone first",
            OnboardTcal::NotExposed => "; an onboard temperature calibration, if the log's parameters enable one, is not undone (the reader does not hand on INS_TCAL*/TC_*)",
            OnboardTcal::NotEnabled | OnboardTcal::NoParameters => "",
        };
        s += &format!("{line}{note}\n");
    }
    s
}
