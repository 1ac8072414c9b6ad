//! `imucald eval`: imucald's orientation filter scored against a reference orientation, the log's
//! own (`ref_q` columns, [`crate::attitude::eval`]) or optical motion capture's
//! ([`crate::attitude::align`]): each capture read and aligned with the log, the best correlated
//! one used, the flight controller's own attitude scored beside the filter where the log has one.

use crate::attitude::align::{self, MocapAlignment, Pose, ReferenceEvaluation};
use crate::attitude::eval::Alignment;
use crate::attitude::fusion::FusionConfig;
use crate::config::Config;
use crate::error::Error;
use crate::io::decode::Format;
use crate::io::mocap::MocapTake;
use crate::io::sources::Log;
use std::path::{Path, PathBuf};

/// The log at `path`, through the calibration at `calibration` when given (the service's
/// `calibration.json` or a replay's report; a raw log is scored uncalibrated without one).
pub fn read_log(
    path: &Path,
    format: Option<Format>,
    cfg: &Config,
    calibration: Option<&Path>,
) -> Result<Log, Error> {
    let mut log = crate::io::sources::read_log(path, format, &cfg.input)?;
    if let Some(c) = calibration {
        let cal = crate::app::daemon::LoadedCalibration::load(c)?;
        log.samples = cal.apply(&log.samples);
    }
    Ok(log)
}

/// Captures read and aligned with a log, each with its alignment or why it failed.
#[derive(Debug)]
pub struct Captures {
    pub takes: Vec<MocapTake>,
    /// By the same index as `takes`.
    pub alignments: Vec<Result<MocapAlignment, Error>>,
    /// The take whose rotation rate correlates best with the gyro, among those aligned.
    pub best: Option<usize>,
    poses: Vec<Vec<Pose>>,
}

/// Read each Motive export of `references` (rigid body `rigid_body`, default the first tracked)
/// and align it with `log`'s gyro and accelerometer.
pub fn align_captures(
    log: &Log,
    references: &[PathBuf],
    rigid_body: Option<&str>,
) -> Result<Captures, Error> {
    let takes = references
        .iter()
        .map(|p| crate::io::mocap::read_motive(p, rigid_body))
        .collect::<Result<Vec<_>, _>>()?;
    let poses: Vec<Vec<Pose>> = takes.iter().map(MocapTake::poses).collect();
    let opts = align::AlignOptions::default();
    let alignments: Vec<_> = poses
        .iter()
        .map(|p| align::align_to_log(&log.samples, p, &opts))
        .collect();
    let best = align::best_alignment(&alignments);
    Ok(Captures {
        takes,
        alignments,
        best,
        poses,
    })
}

impl Captures {
    /// The filter (and the flight controller's attitude, where `log` has one) scored against the
    /// best aligned capture, `alignment` removed first.
    pub fn evaluate(
        &self,
        log: &Log,
        fusion: &FusionConfig,
        alignment: Alignment,
    ) -> Result<ReferenceEvaluation, Error> {
        let i = self
            .best
            .ok_or_else(|| Error::Other("no capture could be aligned with the log".into()))?;
        let a = self.alignments[i]
            .as_ref()
            .map_err(|e| Error::Other(e.to_string()))?;
        align::evaluate_against_reference(
            &log.samples,
            &self.poses[i],
            a,
            fusion,
            alignment,
            flight_controller(log.format),
        )
    }
}

/// The flight controller's attitude a log of `format` carries, by name; `None` for a CSV, whose
/// `ref_q` is a reference, not an estimate.
pub fn flight_controller(format: Format) -> Option<&'static str> {
    match format {
        Format::Ulg => Some("PX4 EKF (vehicle_attitude)"),
        Format::Bin => Some("ArduPilot attitude (ATT)"),
        Format::Tlog => Some("vehicle attitude (ATTITUDE)"),
        Format::Csv => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_flight_controller_logs_carry_an_estimate() {
        assert_eq!(flight_controller(Format::Csv), None);
        for f in [Format::Ulg, Format::Bin, Format::Tlog] {
            assert!(flight_controller(f).is_some(), "{f:?}");
        }
    }

    #[test]
    fn a_missing_capture_is_an_error_and_no_alignment_no_evaluation() {
        let log = Log {
            format: Format::Csv,
            samples: vec![],
            stats: Default::default(),
            instance: None,
            units: Default::default(),
            instances: vec![],
            flight: None,
            telemetry_onboard: None,
            date: None,
        };
        let e = align_captures(&log, &[PathBuf::from("/nonexistent/take.csv")], None);
        assert!(matches!(e, Err(Error::Read { .. })), "{e:?}");
        let none = Captures {
            takes: vec![],
            alignments: vec![],
            best: None,
            poses: vec![],
        };
        let e = none
            .evaluate(&log, &FusionConfig::default(), Alignment::Heading)
            .unwrap_err();
        assert!(e.to_string().contains("no capture could be aligned"), "{e}");
    }
}
