//! The magnetometer calibration run of one compass, in the manner of ArduPilot's compass
//! calibrator: the state a ground station's DO_START/ACCEPT/CANCEL_MAG_CAL commands and the fits
//! move ([`MagCalRun`]), and its one transition function [`MagCalRun::on`], which decides what is
//! installed, reported and acknowledged. Pure: the run loop (`lifecycle`) carries out the
//! [`MagCalEffect`]s; `io::mavout` reads the commands and builds the messages.

use crate::io::mavout::{mask_selects, MagCalStart};
use crate::report::SensorCalibration;
use mavlink::dialects::ardupilotmega::MavResult;

/// Where the magnetometer calibration stands, in the manner of ArduPilot's compass calibrator:
/// one status, changed only by [`MagCalRun::on`].
#[derive(Debug, Clone, PartialEq)]
pub(super) enum MagCalRun {
    /// No commanded run: passing fits are installed as they come when the service calibrates
    /// continuously (`daemon.mag_cal = "continuous"`), and not at all otherwise.
    Idle,
    /// Started with a delay: collecting from zero coverage begins at `start_at_s` (s since the
    /// service started).
    Waiting { start_at_s: f64, opts: MagCalStart },
    /// Collecting from zero coverage; the next passing fit ends the run.
    Running { opts: MagCalStart },
    /// Passed with autosave off: the result waits for DO_ACCEPT_MAG_CAL (not installed, not written).
    Held { cal: Box<SensorCalibration> },
    /// Failed with retry off; stays so until a new start or a cancel.
    Failed,
}

/// What happens to a calibration run.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum MagCalEvent {
    /// DO_START_MAG_CAL, received at `now_s` (s since the service started).
    Start { opts: MagCalStart, now_s: f64 },
    /// DO_ACCEPT_MAG_CAL for the compasses of `mask` (0: all).
    Accept { mask: u8 },
    /// DO_CANCEL_MAG_CAL for the compasses of `mask` (0: all).
    Cancel { mask: u8 },
    /// Time passes: it is `now_s` (s since the service started), for the start delay.
    Tick { now_s: f64 },
    /// A fit passed its checks (and is no worse than the calibration in use); `complete`: the data
    /// covered the sphere (progress 100 %). A commanded run ends only on a complete one, as
    /// ArduPilot's fits only once its sections are filled.
    FitPassed {
        cal: Box<SensorCalibration>,
        complete: bool,
    },
    /// A fit failed after the data covered the sphere.
    FitFailed,
}

/// What the service does on a transition.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum MagCalEffect {
    /// COMMAND_ACK with this result to the command's sender.
    Ack(MavResult),
    /// Drop what was collected: a new run from zero coverage.
    Restart,
    /// Install the calibration and write it.
    Install(Box<SensorCalibration>),
    /// MAG_CAL_REPORT of a passing fit; `commanded`: it ends a commanded run (always reported).
    ReportSuccess {
        cal: Box<SensorCalibration>,
        autosaved: bool,
        commanded: bool,
    },
    /// MAG_CAL_REPORT of the failed fit.
    ReportFailure,
}

impl MagCalRun {
    /// The transition function of compass `compass_id`'s run: the next status and what to do,
    /// given whether the service calibrates without a command (`continuous`). Commands whose
    /// compass mask leaves this compass out are refused (MAV_RESULT_FAILED) and change nothing.
    pub(super) fn on(
        self,
        ev: MagCalEvent,
        continuous: bool,
        compass_id: u8,
    ) -> (MagCalRun, Vec<MagCalEffect>) {
        let ours = |mask: u8| mask_selects(mask, compass_id);
        use MagCalEffect as E;
        use MagCalEvent as V;
        use MagCalRun as R;
        let ack = E::Ack;
        // A passing fit installed and written at once, and reported.
        let autosave = |cal: Box<SensorCalibration>, commanded: bool| {
            vec![
                E::Install(cal.clone()),
                E::ReportSuccess {
                    cal,
                    autosaved: true,
                    commanded,
                },
            ]
        };
        match (self, ev) {
            (s, V::Start { opts, .. }) if !ours(opts.mask) => {
                (s, vec![ack(MavResult::MAV_RESULT_FAILED)])
            }
            (_, V::Start { opts, now_s }) if opts.delay_s > 0.0 => (
                R::Waiting {
                    start_at_s: now_s + opts.delay_s,
                    opts,
                },
                vec![ack(MavResult::MAV_RESULT_ACCEPTED)],
            ),
            (_, V::Start { opts, .. }) => (
                R::Running { opts },
                vec![ack(MavResult::MAV_RESULT_ACCEPTED), E::Restart],
            ),
            (R::Waiting { start_at_s, opts }, V::Tick { now_s }) if now_s >= start_at_s => {
                (R::Running { opts }, vec![E::Restart])
            }
            (
                R::Running { opts },
                V::FitPassed {
                    complete: false, ..
                },
            ) => (R::Running { opts }, vec![]),
            (R::Running { opts }, V::FitPassed { cal, .. }) if opts.autosave => {
                (R::Idle, autosave(cal, true))
            }
            (R::Running { .. }, V::FitPassed { cal, .. }) => (
                R::Held { cal: cal.clone() },
                vec![E::ReportSuccess {
                    cal,
                    autosaved: false,
                    commanded: true,
                }],
            ),
            (R::Idle, V::FitPassed { cal, .. }) if continuous => (R::Idle, autosave(cal, false)),
            (R::Running { opts }, V::FitFailed) if opts.retry => {
                (R::Running { opts }, vec![E::ReportFailure, E::Restart])
            }
            (R::Running { .. }, V::FitFailed) => (R::Failed, vec![E::ReportFailure]),
            (R::Idle, V::FitFailed) if continuous => (R::Idle, vec![E::ReportFailure]),
            (s, V::Accept { mask } | V::Cancel { mask }) if !ours(mask) => {
                (s, vec![ack(MavResult::MAV_RESULT_FAILED)])
            }
            (R::Held { cal }, V::Accept { .. }) => (
                R::Idle,
                vec![E::Install(cal), ack(MavResult::MAV_RESULT_ACCEPTED)],
            ),
            // Nothing waits to be accepted (the run saved its result, or none ran): accepted, as
            // ArduPilot's compass calibration answers when its result is already saved, so a
            // ground station that accepts every report (MAVProxy) sees it succeed.
            (R::Idle, V::Accept { .. }) => (R::Idle, vec![ack(MavResult::MAV_RESULT_ACCEPTED)]),
            // Still collecting, or failed: nothing to accept.
            (s, V::Accept { .. }) => (s, vec![ack(MavResult::MAV_RESULT_FAILED)]),
            (_, V::Cancel { .. }) => (R::Idle, vec![ack(MavResult::MAV_RESULT_ACCEPTED)]),
            (s, V::Tick { .. } | V::FitPassed { .. } | V::FitFailed) => (s, vec![]),
        }
    }

    /// Whether magnetometer progress is reported: during a commanded run, or while idle when the
    /// service calibrates continuously.
    pub(super) fn reports_progress(&self, continuous: bool) -> bool {
        match self {
            MagCalRun::Running { .. } => true,
            MagCalRun::Idle => continuous,
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_cal(offset_x: f64) -> Box<SensorCalibration> {
        Box::new(crate::testdata::passing_mag_calibration(
            crate::calib::model::CalModel::Sym9,
            [offset_x, 0.0, 0.0],
        ))
    }

    #[test]
    fn run_follows_the_ground_station_protocol() {
        use MagCalEffect as E;
        use MagCalEvent as V;
        let accepted = E::Ack(MavResult::MAV_RESULT_ACCEPTED);
        let failed = E::Ack(MavResult::MAV_RESULT_FAILED);
        let opts = |autosave: bool, retry: bool, delay_s: f64| MagCalStart {
            mask: 0,
            retry,
            autosave,
            delay_s,
            autoreboot: false,
        };
        // Autosave off: start -> ack + restart; a passing fit is held and reported (not saved);
        // accept installs it.
        let (s, fx) = MagCalRun::Idle.on(
            V::Start {
                opts: opts(false, false, 0.0),
                now_s: 5.0,
            },
            false,
            0,
        );
        assert_eq!(fx, vec![accepted.clone(), E::Restart]);
        assert!(s.reports_progress(false));
        // A fit that passes before the data covers the sphere does not end the run.
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(2.0),
                complete: false,
            },
            false,
            0,
        );
        assert!(fx.is_empty() && matches!(s, MagCalRun::Running { .. }));
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(3.0),
                complete: true,
            },
            false,
            0,
        );
        assert_eq!(s, MagCalRun::Held { cal: run_cal(3.0) });
        assert_eq!(
            fx,
            vec![E::ReportSuccess {
                cal: run_cal(3.0),
                autosaved: false,
                commanded: true
            }]
        );
        assert!(!s.reports_progress(true));
        // Held: later fits change nothing.
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(4.0),
                complete: true,
            },
            true,
            0,
        );
        assert!(fx.is_empty() && s == MagCalRun::Held { cal: run_cal(3.0) });
        let (s, fx) = s.on(V::Accept { mask: 0 }, false, 0);
        assert_eq!(s, MagCalRun::Idle);
        assert_eq!(fx, vec![E::Install(run_cal(3.0)), accepted.clone()]);
        // Accept with nothing held (already saved) is accepted, as ArduPilot answers; during a
        // run it fails. Cancel always succeeds and discards the held result.
        let (s, fx) = s.on(V::Accept { mask: 1 }, false, 0);
        assert_eq!((s.clone(), fx), (MagCalRun::Idle, vec![accepted.clone()]));
        let running = MagCalRun::Running {
            opts: opts(false, false, 0.0),
        };
        let (_, fx) = running.on(V::Accept { mask: 0 }, false, 0);
        assert_eq!(fx, vec![failed.clone()]);
        let (s, _) = s.on(
            V::Start {
                opts: opts(false, false, 0.0),
                now_s: 0.0,
            },
            false,
            0,
        );
        let (s, _) = s.on(
            V::FitPassed {
                cal: run_cal(3.0),
                complete: true,
            },
            false,
            0,
        );
        let (s, fx) = s.on(V::Cancel { mask: 0 }, false, 0);
        assert_eq!((s, fx), (MagCalRun::Idle, vec![accepted.clone()]));
        // Autosave on: installed and reported as saved at once, back to idle.
        let (s, _) = MagCalRun::Idle.on(
            V::Start {
                opts: opts(true, false, 0.0),
                now_s: 0.0,
            },
            false,
            0,
        );
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(1.0),
                complete: true,
            },
            false,
            0,
        );
        assert_eq!(s, MagCalRun::Idle);
        assert_eq!(
            fx,
            vec![
                E::Install(run_cal(1.0)),
                E::ReportSuccess {
                    cal: run_cal(1.0),
                    autosaved: true,
                    commanded: true
                }
            ]
        );
        // Delay: collecting starts (from zero) when it has passed.
        let (s, fx) = MagCalRun::Idle.on(
            V::Start {
                opts: opts(true, false, 2.0),
                now_s: 10.0,
            },
            false,
            0,
        );
        assert_eq!(fx, vec![accepted.clone()]);
        assert!(!s.reports_progress(true));
        let (s, fx) = s.on(V::Tick { now_s: 11.9 }, false, 0);
        assert!(fx.is_empty() && matches!(s, MagCalRun::Waiting { .. }));
        let (s, fx) = s.on(V::Tick { now_s: 12.0 }, false, 0);
        assert_eq!(fx, vec![E::Restart]);
        assert!(matches!(s, MagCalRun::Running { .. }));
        // Failure: with retry, again from zero; without, failed until restarted or cancelled.
        let (s, fx) = MagCalRun::Running {
            opts: opts(true, true, 0.0),
        }
        .on(V::FitFailed, false, 0);
        assert_eq!(fx, vec![E::ReportFailure, E::Restart]);
        assert!(matches!(s, MagCalRun::Running { .. }));
        let (s, fx) = MagCalRun::Running {
            opts: opts(true, false, 0.0),
        }
        .on(V::FitFailed, false, 0);
        assert_eq!((s.clone(), fx), (MagCalRun::Failed, vec![E::ReportFailure]));
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(1.0),
                complete: true,
            },
            true,
            0,
        );
        assert!(fx.is_empty() && s == MagCalRun::Failed);
        // A mask without compass 0 is refused and changes nothing.
        let other = MagCalStart {
            mask: 0b10,
            ..opts(true, false, 0.0)
        };
        let (s, fx) = MagCalRun::Idle.on(
            V::Start {
                opts: other,
                now_s: 0.0,
            },
            false,
            0,
        );
        assert_eq!((s, fx), (MagCalRun::Idle, vec![failed.clone()]));
        // ... and taken by compass 1's run, which it selects.
        let (s, fx) = MagCalRun::Idle.on(
            V::Start {
                opts: other,
                now_s: 0.0,
            },
            false,
            1,
        );
        assert!(matches!(s, MagCalRun::Running { .. }));
        assert_eq!(fx, vec![E::Ack(MavResult::MAV_RESULT_ACCEPTED), E::Restart]);
        // Idle: continuous installs and reports passing fits and reports failures; on command only,
        // nothing happens without a run.
        let (_, fx) = MagCalRun::Idle.on(
            V::FitPassed {
                cal: run_cal(2.0),
                complete: true,
            },
            true,
            0,
        );
        assert_eq!(
            fx,
            vec![
                E::Install(run_cal(2.0)),
                E::ReportSuccess {
                    cal: run_cal(2.0),
                    autosaved: true,
                    commanded: false
                }
            ]
        );
        assert_eq!(
            MagCalRun::Idle.on(V::FitFailed, true, 0).1,
            vec![E::ReportFailure]
        );
        assert!(MagCalRun::Idle
            .on(
                V::FitPassed {
                    cal: run_cal(2.0),
                    complete: true
                },
                false,
                0
            )
            .1
            .is_empty());
        assert!(MagCalRun::Idle.on(V::FitFailed, false, 0).1.is_empty());
        assert!(MagCalRun::Idle.reports_progress(true) && !MagCalRun::Idle.reports_progress(false));
    }
}
