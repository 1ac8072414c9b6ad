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

/// The IMU number of an instance and its accelerometer's and gyro's device ids: the streams
/// among the instance name's parts (`IMU2+MAG2` -> `IMU2`), else the instance's position in the
/// log.
fn imu_of(name: &str, sensors: &[SensorStream], position: usize) -> (usize, [Option<u32>; 2]) {
    let find = |sensor: Sensor| {
        sensors
            .iter()
            .filter(|s| s.sensor == sensor)
            .find(|s| name.split('+').any(|p| p == s.source))
    };
    let gyro_id = find(Sensor::Gyro).and_then(|s| s.device_id);
    find(Sensor::Accel).map_or((position, [None, gyro_id]), |s| {
        (usize::from(s.instance), [s.device_id, gyro_id])
    })
}

/// The samples with a temperature calibration the flight controller applied undone, and which.
/// `params`: the log's temperature calibration parameters, `None` when the input has none.
fn undone<'a>(
    samples: &'a [Sample],
    params: Option<&BTreeMap<String, f64>>,
    imu: usize,
    [accel_id, gyro_id]: [Option<u32>; 2],
) -> (std::borrow::Cow<'a, [Sample]>, OnboardTcal) {
    let Some(params) = params else {
        return (samples.into(), OnboardTcal::NoParameters);
    };
    let applied =
        Applied::ardupilot(params, imu).or_else(|| Applied::px4(params, accel_id, gyro_id));
    match applied {
        Some(a) => (
            samples.iter().map(|s| a.undo(s)).collect::<Vec<_>>().into(),
            OnboardTcal::Undone,
        ),
        None if Applied::px4_enabled(params) => (samples.into(), OnboardTcal::NotMatched),
        None => (samples.into(), OnboardTcal::NotEnabled),
    }
}

/// The temperature calibration of every instance of the run with temperature readings: the
/// primary's first, then the further instances in the log's order. Empty when none has.
pub(super) fn temperature(run: &Run, settings: &TempCalSettings) -> Vec<TempCalReport> {
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
    let params = log.flight.as_ref().map(|f| &f.temperature_params);
    let mut out = vec![];
    for (name, position, samples) in streams {
        if !has_temperature(samples) {
            continue;
        }
        let (imu, ids) = imu_of(&name, sensors, position);
        let (samples, onboard) = undone(samples, params, imu, ids);
        let result = calibrate(&samples, settings);
        if result.samples == 0 {
            continue;
        }
        out.push(TempCalReport {
            instance: name,
            imu,
            device_id: ids[0],
            onboard,
            result,
        });
    }
    out
}

/// The names of the temperature calibration's parameter files ([`write_exports`]).
pub(super) const ARDUPILOT_FILE: &str = "tempcal_ardupilot.parm";
pub(super) const PX4_FILE: &str = "tempcal_px4.params";

/// Whether an instance was calibrated.
pub(super) fn calibrated_any(t: &[TempCalReport]) -> bool {
    t.iter().any(TempCalReport::calibrated)
}

/// What `next:` says of the temperature calibration, when an instance was calibrated: load the
/// files written, or ask for them.
pub(super) fn next_words(t: &[TempCalReport], written: &[PathBuf]) -> Option<String> {
    if !calibrated_any(t) {
        return None;
    }
    let file = |name: &str| {
        written
            .iter()
            .find(|p| p.file_name().is_some_and(|f| f == name))
            .map(|p| p.display().to_string())
    };
    Some(match (file(ARDUPILOT_FILE), file(PX4_FILE)) {
        (Some(ap), Some(px)) => format!(
            "load the temperature calibration {ap} (ArduPilot) or {px} (PX4) on the vehicle, then redo its accelerometer calibration"
        ),
        _ => "add --export DIR for the temperature calibration's ArduPilot and PX4 parameter files".into(),
    })
}

/// `tempcal_ardupilot.parm` and `tempcal_px4.params` in `dir` when an instance was calibrated
/// (else no file: nothing to load).
pub(super) fn write_exports(dir: &Path, t: &[TempCalReport]) -> Result<Vec<PathBuf>, Error> {
    if !calibrated_any(t) {
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
        (ARDUPILOT_FILE, export::ardupilot_file(&list)),
        (PX4_FILE, export::px4_file(&list)),
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
                c.bin_c,
                shrink(&c.accel.axes),
                shrink(&c.gyro.axes)
            ),
            TempOutcome::Refused(why) => format!("{head}: no temperature calibration: {why}"),
        };
        let note = match r.onboard {
            OnboardTcal::Undone => "; the onboard temperature calibration undone first",
            OnboardTcal::NotMatched => "; the onboard temperature calibration the parameters enable is not undone (no TC_A/TC_G slot of this sensor's device id): the fit is of what it left",
            OnboardTcal::NotEnabled | OnboardTcal::NoParameters => "",
        };
        s += &format!("{line}{note}\n");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_px4_correction_is_undone_by_the_device_ids_of_the_instance_or_said_not_matched() {
        let params: BTreeMap<String, f64> = [
            ("TC_A_ENABLE", 1.0),
            ("TC_A1_ID", 11.0),
            ("TC_A1_X1_0", 1e-3),
            ("TC_G_ENABLE", 1.0),
            ("TC_G0_ID", 22.0),
            ("TC_G0_X0_2", 0.01),
        ]
        .map(|(n, v)| (n.to_string(), v))
        .into();
        let s = [Sample {
            temp_c: Some(35.0),
            accel_mps2: Some([0.0; 3]),
            gyro_rad_s: Some([0.0; 3]),
            ..Default::default()
        }];
        // TREF 25 by default: the accelerometer's x gets 1e-3 * 10 back, the gyro's z 0.01.
        let (u, state) = undone(&s, Some(&params), 0, [Some(11), Some(22)]);
        assert_eq!(state, OnboardTcal::Undone);
        assert!((u[0].accel_mps2.unwrap()[0] - 0.01).abs() < 1e-15);
        assert!((u[0].gyro_rad_s.unwrap()[2] - 0.01).abs() < 1e-15);
        // The gyro's device id is not the accelerometer's: no slot, nothing undone.
        let (u, state) = undone(&s, Some(&params), 0, [Some(11), Some(11)]);
        assert_eq!(state, OnboardTcal::NotMatched);
        assert_eq!(u[0], s[0]);
        assert_eq!(undone(&s, None, 0, [None; 2]).1, OnboardTcal::NoParameters);
        assert_eq!(
            undone(&s, Some(&BTreeMap::new()), 0, [None; 2]).1,
            OnboardTcal::NotEnabled
        );
    }
}
