//! Which compass calibrations a replay offers to load on the vehicle ([`LoadDecision`]): one
//! decision per compass, made once from the report's records, that the report states, the
//! exports follow (a compass not to load is written as comments with the reason) and the
//! terminal's `next:` names.

use crate::report::{CalStatus, LoadDecision, LoadReason, Report};

/// The name a log of one unnamed stream (a CSV) is judged and decided under.
pub(crate) const PRIMARY: &str = "primary";

/// Every compass with a calibration record: the primary's first, then the further instances'.
/// A compass is to load when it passed, the vehicle uses it, its RMS residual is within
/// `max_rms_ratio` of the field, and its held-out verdict is `better` or `no_onboard` (or the
/// log has no attitude to judge it on).
/// Two records of the same compass (the same `compass_id`) are never both to load: the first to
/// load (the primary's first) is, the other is [`LoadReason::SameCompass`].
pub(crate) fn decide(r: &Report, max_rms_ratio: f64) -> Vec<LoadDecision> {
    let primary = r.instances.iter().find(|i| i.primary);
    let mut compasses = vec![(
        primary_instance(r),
        primary.map_or(0, |i| i.compass_id),
        &r.calibration.mag,
    )];
    for i in r.instances.iter().filter(|i| !i.primary) {
        compasses.push((i.instance.clone(), i.compass_id, &i.calibration.mag));
    }
    let mut decisions: Vec<LoadDecision> = compasses
        .into_iter()
        .map(|(instance, compass_id, mag)| {
            let reason = reason(r, &instance, compass_id, mag, max_rms_ratio);
            LoadDecision {
                instance,
                compass_id,
                load: matches!(
                    reason,
                    LoadReason::Better | LoadReason::NoOnboard | LoadReason::NotJudged
                ),
                reason,
            }
        })
        .collect();
    for k in 0..decisions.len() {
        let id = decisions[k].compass_id;
        if decisions[k].load && decisions[..k].iter().any(|d| d.load && d.compass_id == id) {
            decisions[k].load = false;
            decisions[k].reason = LoadReason::SameCompass;
        }
    }
    decisions
}

/// The name the primary compass is judged and decided under: its instance's, the input's, or
/// [`PRIMARY`].
pub(crate) fn primary_instance(r: &Report) -> String {
    r.instances
        .iter()
        .find(|i| i.primary)
        .map(|i| i.instance.clone())
        .or_else(|| r.input.instance.clone())
        .unwrap_or_else(|| PRIMARY.to_string())
}

fn reason(
    r: &Report,
    instance: &str,
    compass_id: u8,
    mag: &crate::report::SensorCalibration,
    max_rms_ratio: f64,
) -> LoadReason {
    if mag.status != CalStatus::Ok {
        return LoadReason::FitFailed;
    }
    if unused(r, compass_id) {
        return LoadReason::Unused;
    }
    if mag.radius > 0.0 && mag.rms_residual / mag.radius > max_rms_ratio {
        return LoadReason::OverRmsLimit;
    }
    use crate::calib::outcome::Verdict;
    match r
        .quality
        .iter()
        .find(|q| q.instance == instance)
        .and_then(|q| q.verdict_kind)
    {
        Some(Verdict::Better) => LoadReason::Better,
        Some(Verdict::NoOnboard) => LoadReason::NoOnboard,
        Some(Verdict::KeepVehicle) => LoadReason::KeepVehicle,
        // The held-out fit is the vector ladder's: it cannot judge a planar calibration, which
        // its own checks (the headings' sectors, the 2-D soft iron) vouch for.
        Some(Verdict::Failed)
            if mag.method.as_ref().map(|m| m.method)
                == Some(crate::calib::outcome::MagMethod::Planar) =>
        {
            LoadReason::NotJudged
        }
        Some(Verdict::Failed) => LoadReason::HeldOutFailed,
        None => LoadReason::NotJudged,
    }
}

/// The vehicle's own parameters say it does not use compass `k`: ArduPilot's COMPASS_USEn 0, or
/// PX4's CAL_MAGn_PRIO 0.
fn unused(r: &Report, k: u8) -> bool {
    let Some(onboard) = &r.onboard else {
        return false;
    };
    let suffix = ["", "2", "3"].get(k as usize).copied().unwrap_or("");
    onboard
        .mag
        .iter()
        .filter(|c| c.instance == k)
        .flat_map(|c| &c.params)
        .any(|(n, v)| {
            (*n == format!("COMPASS_USE{suffix}") || *n == format!("CAL_MAG{k}_PRIO")) && *v == 0.0
        })
}

/// Why the compass of record `instance` is written as comments rather than values to load, or
/// `None` to load it. With `export_all` every compass is written as values, and the reason it
/// would not have been is said in a comment; a second record of a compass another record loads
/// stays comments (its values would overwrite the other's).
pub(crate) fn withheld(
    r: &Report,
    instance: &str,
    export_all: bool,
) -> Option<crate::calib::export::Withheld> {
    let d = r.load.iter().find(|d| d.instance == instance)?;
    (!d.load).then(|| crate::calib::export::Withheld {
        reason: d.reason.words().to_string(),
        written_anyway: export_all && d.reason != LoadReason::SameCompass,
    })
}

/// Whether the replay found anything to load on the vehicle: a compass whose calibration is one
/// to load ([`decide`]), an accelerometer calibration that passed, or a temperature calibration
/// made. A gyro bias alone is not: no parameter file carries it, and the flight controller learns
/// its own at every start.
pub fn loadable(r: &Report) -> bool {
    r.load.iter().any(|d| d.load)
        || r.calibration.accel.status == CalStatus::Ok
        || r.temperature.iter().any(|t| t.calibrated())
}

/// The compasses to load and those not, in words, for `next:`.
pub(crate) fn named(r: &Report) -> (Vec<String>, Vec<String>) {
    let name = |d: &LoadDecision| format!("compass {} ({})", d.compass_id, d.instance);
    let load = r.load.iter().filter(|d| d.load).map(name).collect();
    let keep = r
        .load
        .iter()
        .filter(|d| !d.load && d.reason != LoadReason::FitFailed)
        .map(|d| format!("{}: {}", name(d), d.reason.words()))
        .collect();
    (load, keep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::outcome::Verdict;

    fn report_with(verdict: Option<Verdict>, use_param: f64, rms_ut: f64) -> Report {
        let mut pipe =
            crate::calib::pipeline::Pipeline::new(&crate::config::Config::default().calib())
                .expect("a pipeline");
        let results = pipe.finish().clone();
        let input = crate::report::InputReport::new(
            "bin",
            None,
            Some("IMU+MAG".into()),
            &Default::default(),
            1,
            1.0,
        );
        let mut r = crate::app::replay::make_report(input, &pipe, &results, None);
        r.calibration.mag = crate::testdata::passing_mag_calibration(
            crate::calib::model::CalModel::Full12,
            [1.0, 2.0, 3.0],
        );
        r.calibration.mag.radius = 50.0;
        r.calibration.mag.rms_residual = rms_ut;
        let mut params = std::collections::BTreeMap::new();
        params.insert("COMPASS_USE".to_string(), use_param);
        r.onboard = Some(crate::report::OnboardReport {
            mag: vec![crate::report::OnboardCal {
                instance: 0,
                device_id: None,
                sources: vec!["MAG".into()],
                offset: [0.0; 3],
                matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                units: crate::types::CalUnits::Ut,
                params,
            }],
            ..Default::default()
        });
        if let Some(v) = verdict {
            r.quality.push(crate::report::QualityReport {
                instance: "IMU+MAG".into(),
                block_s: 20.0,
                method: "vector ladder".into(),
                imucald: None,
                onboard: None,
                imucald_failure: None,
                verdict: String::new(),
                verdict_kind: Some(v),
                start: None,
                rung: None,
                rung_reason: None,
                rungs: Vec::new(),
            });
        }
        r
    }

    #[test]
    fn the_verdict_decides_what_is_loaded() {
        for (verdict, load, reason) in [
            (Some(Verdict::Better), true, LoadReason::Better),
            (Some(Verdict::NoOnboard), true, LoadReason::NoOnboard),
            (None, true, LoadReason::NotJudged),
            (Some(Verdict::KeepVehicle), false, LoadReason::KeepVehicle),
            (Some(Verdict::Failed), false, LoadReason::HeldOutFailed),
        ] {
            let r = report_with(verdict, 1.0, 0.5);
            let d = decide(&r, 0.05);
            assert_eq!((d[0].load, d[0].reason), (load, reason), "{verdict:?}");
        }
    }

    #[test]
    fn an_unused_compass_or_one_over_the_rms_limit_is_not_loaded() {
        let d = decide(&report_with(Some(Verdict::Better), 0.0, 0.5), 0.05);
        assert_eq!((d[0].load, d[0].reason), (false, LoadReason::Unused));
        // 3.5 uT of 50 is 7 %, over 5 %.
        let d = decide(&report_with(Some(Verdict::Better), 1.0, 3.5), 0.05);
        assert_eq!((d[0].load, d[0].reason), (false, LoadReason::OverRmsLimit));
    }

    /// PX4's `vehicle_magnetometer` (the primary's) and the `sensor_mag[k]` it was selected from
    /// are one compass: only the first record to load is loaded, and the export's values of the
    /// other stay comments, even with `--export-all`.
    #[test]
    fn two_records_of_one_compass_are_not_both_loaded() {
        let mut r = report_with(Some(Verdict::Better), 1.0, 0.5);
        r.input.instance = Some("primary".into());
        let mut again = r.quality[0].clone();
        again.instance = "sensor_mag[0]".into();
        r.quality[0].instance = "primary".into();
        r.quality.push(again);
        r.instances.push(crate::report::InstanceReport {
            instance: "sensor_mag[0]".into(),
            compass_id: 0,
            primary: false,
            samples: 100,
            time: Default::default(),
            calibration: r.calibration.clone(),
        });
        let d = decide(&r, 0.05);
        assert_eq!((d[0].load, d[0].reason), (true, LoadReason::Better));
        assert_eq!((d[1].load, d[1].reason), (false, LoadReason::SameCompass));
        r.load = d;
        assert!(withheld(&r, "primary", true).is_none());
        let w = withheld(&r, "sensor_mag[0]", true).expect("withheld");
        assert!(!w.written_anyway);
    }
}
