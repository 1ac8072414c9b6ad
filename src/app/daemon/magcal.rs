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
    /// A commanded run passed (ArduPilot's SUCCESS): installed and written already when `saved`
    /// (autosave), else waiting for DO_ACCEPT_MAG_CAL. Its report is repeated every
    /// [`REPORT_REPEAT_S`] (`next_report_s`, s since the service started; `None` until the first
    /// tick) until an accept or a cancel ends the run, as ArduPilot repeats MAG_CAL_REPORT while
    /// its calibrator holds a result: a report lost on the way is sent again.
    Succeeded {
        cal: Box<SensorCalibration>,
        saved: bool,
        next_report_s: Option<f64>,
    },
    /// A commanded run failed with retry off; its report is repeated as [`MagCalRun::Succeeded`]'s
    /// until a new start, an accept or a cancel.
    Failed { next_report_s: Option<f64> },
}

/// How often a result waiting to be accepted is reported again, s (about the rate of ArduPilot's
/// MAG_CAL_REPORT stream, which a ground station accepts on the first it hears).
pub(super) const REPORT_REPEAT_S: f64 = 1.0;

/// The time of the next repeat of a report: the first tick sets it, one that reaches it repeats
/// the report (`true`) and sets the next.
fn repeat_due(next_report_s: Option<f64>, now_s: f64) -> (Option<f64>, bool) {
    match next_report_s {
        Some(at) if now_s < at => (Some(at), false),
        Some(_) => (Some(now_s + REPORT_REPEAT_S), true),
        None => (Some(now_s + REPORT_REPEAT_S), false),
    }
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
    /// The MAG_CAL_REPORT of a result waiting to be accepted, again (nothing else: no text, no
    /// install).
    RepeatSuccess {
        cal: Box<SensorCalibration>,
        autosaved: bool,
    },
    /// The failed run's MAG_CAL_REPORT, again.
    RepeatFailure,
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
            (R::Running { opts }, V::FitPassed { cal, .. }) if opts.autosave => (
                R::Succeeded {
                    cal: cal.clone(),
                    saved: true,
                    next_report_s: None,
                },
                autosave(cal, true),
            ),
            (R::Running { .. }, V::FitPassed { cal, .. }) => (
                R::Succeeded {
                    cal: cal.clone(),
                    saved: false,
                    next_report_s: None,
                },
                vec![E::ReportSuccess {
                    cal,
                    autosaved: false,
                    commanded: true,
                }],
            ),
            (
                R::Succeeded {
                    cal,
                    saved,
                    next_report_s,
                },
                V::Tick { now_s },
            ) => {
                let (next_report_s, due) = repeat_due(next_report_s, now_s);
                let fx = if due {
                    vec![E::RepeatSuccess {
                        cal: cal.clone(),
                        autosaved: saved,
                    }]
                } else {
                    vec![]
                };
                (
                    R::Succeeded {
                        cal,
                        saved,
                        next_report_s,
                    },
                    fx,
                )
            }
            (R::Failed { next_report_s }, V::Tick { now_s }) => {
                let (next_report_s, due) = repeat_due(next_report_s, now_s);
                let fx = if due { vec![E::RepeatFailure] } else { vec![] };
                (R::Failed { next_report_s }, fx)
            }
            (R::Idle, V::FitPassed { cal, .. }) if continuous => (R::Idle, autosave(cal, false)),
            (R::Running { opts }, V::FitFailed) if opts.retry => {
                (R::Running { opts }, vec![E::ReportFailure, E::Restart])
            }
            (R::Running { .. }, V::FitFailed) => (
                R::Failed {
                    next_report_s: None,
                },
                vec![E::ReportFailure],
            ),
            (R::Idle, V::FitFailed) if continuous => (R::Idle, vec![E::ReportFailure]),
            (s, V::Accept { mask } | V::Cancel { mask }) if !ours(mask) => {
                (s, vec![ack(MavResult::MAV_RESULT_FAILED)])
            }
            // Accept ends the run, as ArduPilot's (its calibrator stops whatever the answer).
            (
                R::Succeeded {
                    cal, saved: false, ..
                },
                V::Accept { .. },
            ) => (
                R::Idle,
                vec![E::Install(cal), ack(MavResult::MAV_RESULT_ACCEPTED)],
            ),
            // Nothing waits to be accepted (the run saved its result, or none ran): accepted, as
            // ArduPilot's compass calibration answers when its result is already saved, so a
            // ground station that accepts every report (MAVProxy) sees it succeed.
            (R::Succeeded { saved: true, .. } | R::Idle, V::Accept { .. }) => {
                (R::Idle, vec![ack(MavResult::MAV_RESULT_ACCEPTED)])
            }
            // Still collecting, or failed: nothing to accept; the run stops all the same.
            (_, V::Accept { .. }) => (R::Idle, vec![ack(MavResult::MAV_RESULT_FAILED)]),
            (_, V::Cancel { .. }) => (R::Idle, vec![ack(MavResult::MAV_RESULT_ACCEPTED)]),
            (s, V::Tick { .. } | V::FitPassed { .. } | V::FitFailed) => (s, vec![]),
        }
    }

    /// Whether the run needs the clock ([`MagCalEvent::Tick`]): a delayed start, or a report to
    /// repeat.
    pub(super) fn wants_ticks(&self) -> bool {
        matches!(
            self,
            MagCalRun::Waiting { .. } | MagCalRun::Succeeded { .. } | MagCalRun::Failed { .. }
        )
    }

    /// Whether a run is collecting or about to (a fixed-yaw calibration waits for it to end).
    pub(super) fn collecting(&self) -> bool {
        matches!(self, MagCalRun::Waiting { .. } | MagCalRun::Running { .. })
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
        let held = |next_report_s| MagCalRun::Succeeded {
            cal: run_cal(3.0),
            saved: false,
            next_report_s,
        };
        assert_eq!(s, held(None));
        assert_eq!(
            fx,
            vec![E::ReportSuccess {
                cal: run_cal(3.0),
                autosaved: false,
                commanded: true
            }]
        );
        assert!(!s.reports_progress(true));
        assert!(s.wants_ticks() && !s.collecting());
        // Held: later fits change nothing.
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(4.0),
                complete: true,
            },
            true,
            0,
        );
        assert!(fx.is_empty() && s == held(None));
        // The report again every REPORT_REPEAT_S until accepted: the first tick sets the time,
        // a tick before it does nothing, one at it repeats the report.
        let (s, fx) = s.on(V::Tick { now_s: 20.0 }, false, 0);
        assert!(fx.is_empty() && s == held(Some(21.0)));
        let (s, fx) = s.on(V::Tick { now_s: 20.5 }, false, 0);
        assert!(fx.is_empty() && s == held(Some(21.0)));
        let (s, fx) = s.on(V::Tick { now_s: 21.0 }, false, 0);
        assert_eq!(s, held(Some(22.0)));
        assert_eq!(
            fx,
            vec![E::RepeatSuccess {
                cal: run_cal(3.0),
                autosaved: false
            }]
        );
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
        // ... and stops it, as ArduPilot's calibrator stops on any accept.
        let (s2, fx) = running.on(V::Accept { mask: 0 }, false, 0);
        assert_eq!((s2, fx), (MagCalRun::Idle, vec![failed.clone()]));
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
        // Autosave on: installed and reported as saved at once; the report repeats (saved) until
        // the ground station accepts it, which answers ACCEPTED and ends the run.
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
        assert_eq!(
            s,
            MagCalRun::Succeeded {
                cal: run_cal(1.0),
                saved: true,
                next_report_s: None
            }
        );
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
        let (s, _) = s.on(V::Tick { now_s: 1.0 }, false, 0);
        let (s, fx) = s.on(V::Tick { now_s: 2.0 }, false, 0);
        assert_eq!(
            fx,
            vec![E::RepeatSuccess {
                cal: run_cal(1.0),
                autosaved: true
            }]
        );
        let (s, fx) = s.on(V::Accept { mask: 1 }, false, 0);
        assert_eq!((s, fx), (MagCalRun::Idle, vec![accepted.clone()]));
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
        let failed_run = |next_report_s| MagCalRun::Failed { next_report_s };
        assert_eq!((s.clone(), fx), (failed_run(None), vec![E::ReportFailure]));
        let (s, fx) = s.on(
            V::FitPassed {
                cal: run_cal(1.0),
                complete: true,
            },
            true,
            0,
        );
        assert!(fx.is_empty() && s == failed_run(None));
        // Its report repeats too, until an accept (answered FAILED: nothing to save) ends it.
        let (s, _) = s.on(V::Tick { now_s: 5.0 }, false, 0);
        let (s, fx) = s.on(V::Tick { now_s: 6.0 }, false, 0);
        assert_eq!(
            (s.clone(), fx),
            (failed_run(Some(7.0)), vec![E::RepeatFailure])
        );
        let (s, fx) = s.on(V::Accept { mask: 0 }, false, 0);
        assert_eq!((s, fx), (MagCalRun::Idle, vec![failed.clone()]));
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
