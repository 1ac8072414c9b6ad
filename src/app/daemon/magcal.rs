//! The magnetometer calibration run of one compass, in the manner of ArduPilot's compass
//! calibrator: the state a ground station's DO_START/ACCEPT/CANCEL_MAG_CAL commands and the fits
//! move ([`MagCalRun`]), and its one transition function [`MagCalRun::on`], which decides what is
//! installed, reported and acknowledged. Pure: the run loop (`lifecycle`) carries out the
//! [`MagCalEffect`]s; `io::mavout` reads the commands and builds the messages.

use crate::calib::fit::FitFailure;
use crate::io::mavout::{mask_selects, MagCalStart, ProgressStatus};
use crate::report::{CalStatus, SensorCalibration};
use mavlink::dialects::ardupilotmega::MavResult;

/// Where the magnetometer calibration stands, in the manner of ArduPilot's compass calibrator:
/// one status, changed only by [`MagCalRun::on`].
#[derive(Debug, Clone, PartialEq)]
pub(super) enum MagCalRun {
    /// No commanded run: passing fits are installed as they come when the service calibrates
    /// continuously (`daemon.mag_cal = "continuous"`), and not at all otherwise.
    Idle,
    /// Started with a delay (ArduPilot's WAITING_TO_START): collecting from zero coverage begins
    /// at `start_at_s` (s since the service started). Progress is reported meanwhile, at 0 %.
    Waiting {
        start_at_s: f64,
        opts: MagCalStart,
        attempt: u8,
    },
    /// Collecting from zero coverage; the next passing fit ends the run. `attempt`: 1 for the
    /// run the command started, one more for each retry after a failure (DO_START_MAG_CAL
    /// param2), as MAG_CAL_PROGRESS carries it.
    Running { opts: MagCalStart, attempt: u8 },
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
    /// A STATUSTEXT saying why the fit failed; `retry_attempt`: the attempt that starts now (a
    /// retry sends no MAG_CAL_REPORT, as ArduPilot's calibrator goes straight back to collecting).
    SayFailure { retry_attempt: Option<u8> },
    /// The MAG_CAL_REPORT of a result waiting to be accepted, again (nothing else: no text, no
    /// install).
    RepeatSuccess {
        cal: Box<SensorCalibration>,
        autosaved: bool,
    },
    /// The failed run's MAG_CAL_REPORT, again.
    RepeatFailure,
}

/// What a transition gives: the next status and what to do.
type Step = (MagCalRun, Vec<MagCalEffect>);

impl MagCalRun {
    /// The transition function of compass `compass_id`'s run: the next status and what to do,
    /// given whether the service calibrates without a command (`continuous`). Commands whose
    /// compass mask leaves this compass out are refused (MAV_RESULT_FAILED) and change nothing.
    pub(super) fn on(self, ev: MagCalEvent, continuous: bool, compass_id: u8) -> Step {
        let ours = |mask: u8| mask_selects(mask, compass_id);
        match ev {
            MagCalEvent::Start { opts, .. } if !ours(opts.mask) => {
                (self, vec![MagCalEffect::Ack(MavResult::MAV_RESULT_FAILED)])
            }
            MagCalEvent::Start { opts, now_s } => start(opts, now_s),
            MagCalEvent::Accept { mask } | MagCalEvent::Cancel { mask } if !ours(mask) => {
                (self, vec![MagCalEffect::Ack(MavResult::MAV_RESULT_FAILED)])
            }
            MagCalEvent::Accept { .. } => self.on_accept(),
            MagCalEvent::Cancel { .. } => (
                MagCalRun::Idle,
                vec![MagCalEffect::Ack(MavResult::MAV_RESULT_ACCEPTED)],
            ),
            MagCalEvent::Tick { now_s } => self.on_tick(now_s),
            MagCalEvent::FitPassed { cal, complete } => {
                self.on_fit_passed(cal, complete, continuous)
            }
            MagCalEvent::FitFailed => self.on_fit_failed(continuous),
        }
    }

    /// Time passes: a delayed start begins, a held report is repeated when due.
    fn on_tick(self, now_s: f64) -> Step {
        use MagCalRun as R;
        match self {
            R::Waiting {
                start_at_s,
                opts,
                attempt,
            } if now_s >= start_at_s => (R::Running { opts, attempt }, vec![MagCalEffect::Restart]),
            R::Succeeded {
                cal,
                saved,
                next_report_s,
            } => {
                let (next_report_s, due) = repeat_due(next_report_s, now_s);
                let fx = if due {
                    vec![MagCalEffect::RepeatSuccess {
                        cal: cal.clone(),
                        autosaved: saved,
                    }]
                } else {
                    vec![]
                };
                let next = R::Succeeded {
                    cal,
                    saved,
                    next_report_s,
                };
                (next, fx)
            }
            R::Failed { next_report_s } => {
                let (next_report_s, due) = repeat_due(next_report_s, now_s);
                let fx = if due {
                    vec![MagCalEffect::RepeatFailure]
                } else {
                    vec![]
                };
                (R::Failed { next_report_s }, fx)
            }
            s => (s, vec![]),
        }
    }

    /// A passing fit: it ends a commanded run once the data covered the sphere (installed at once
    /// with autosave, else held for the accept); while idle, continuous calibration installs it.
    fn on_fit_passed(self, cal: Box<SensorCalibration>, complete: bool, continuous: bool) -> Step {
        match self {
            MagCalRun::Running { opts, attempt } if !complete => {
                (MagCalRun::Running { opts, attempt }, vec![])
            }
            MagCalRun::Running { opts, .. } => {
                let next = MagCalRun::Succeeded {
                    cal: cal.clone(),
                    saved: opts.autosave,
                    next_report_s: None,
                };
                if opts.autosave {
                    (next, autosave(cal, true))
                } else {
                    let report = MagCalEffect::ReportSuccess {
                        cal,
                        autosaved: false,
                        commanded: true,
                    };
                    (next, vec![report])
                }
            }
            MagCalRun::Idle if continuous => (MagCalRun::Idle, autosave(cal, false)),
            s => (s, vec![]),
        }
    }

    /// A failed fit once the data covered the sphere: with retry, collecting again from zero as
    /// the next attempt (no report, as ArduPilot's calibrator); without, failed and reported.
    fn on_fit_failed(self, continuous: bool) -> Step {
        use MagCalEffect as E;
        match self {
            MagCalRun::Running { opts, attempt } if opts.retry => {
                let attempt = attempt.saturating_add(1);
                let say = E::SayFailure {
                    retry_attempt: Some(attempt),
                };
                (MagCalRun::Running { opts, attempt }, vec![say, E::Restart])
            }
            MagCalRun::Running { .. } => (
                MagCalRun::Failed {
                    next_report_s: None,
                },
                vec![
                    E::SayFailure {
                        retry_attempt: None,
                    },
                    E::ReportFailure,
                ],
            ),
            MagCalRun::Idle if continuous => (MagCalRun::Idle, vec![E::ReportFailure]),
            s => (s, vec![]),
        }
    }

    /// DO_ACCEPT_MAG_CAL for this compass: ends the run whatever it held, as ArduPilot's (its
    /// calibrator stops on any accept). A held result is installed; with nothing waiting (saved
    /// already, or no run) it is ACCEPTED, as ArduPilot answers, so a ground station that accepts
    /// every report (MAVProxy) sees it succeed; still collecting or failed: FAILED.
    fn on_accept(self) -> Step {
        let ack = |r| MagCalEffect::Ack(r);
        match self {
            MagCalRun::Succeeded {
                cal, saved: false, ..
            } => (
                MagCalRun::Idle,
                vec![
                    MagCalEffect::Install(cal),
                    ack(MavResult::MAV_RESULT_ACCEPTED),
                ],
            ),
            MagCalRun::Succeeded { saved: true, .. } | MagCalRun::Idle => {
                (MagCalRun::Idle, vec![ack(MavResult::MAV_RESULT_ACCEPTED)])
            }
            _ => (MagCalRun::Idle, vec![ack(MavResult::MAV_RESULT_FAILED)]),
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

    /// Whether the commanded run is collecting (its fits are judged as ArduPilot's calibrator
    /// judges them, fitness included).
    pub(super) fn running(&self) -> bool {
        matches!(self, MagCalRun::Running { .. })
    }

    /// What MAG_CAL_PROGRESS says of the run, when it reports progress: during a commanded run
    /// (waiting to start or collecting, with its attempt), or while idle when the service
    /// calibrates continuously (attempt 1). `None`: no progress to report.
    pub(super) fn progress(&self, continuous: bool) -> Option<(ProgressStatus, u8)> {
        match self {
            MagCalRun::Waiting { attempt, .. } => Some((ProgressStatus::WaitingToStart, *attempt)),
            MagCalRun::Running { attempt, .. } => Some((ProgressStatus::Running, *attempt)),
            MagCalRun::Idle if continuous => Some((ProgressStatus::Running, 1)),
            _ => None,
        }
    }

    /// Whether magnetometer progress is reported (see [`MagCalRun::progress`]).
    #[cfg(test)]
    pub(super) fn reports_progress(&self, continuous: bool) -> bool {
        self.progress(continuous).is_some()
    }
}

/// DO_START_MAG_CAL for this compass: attempt 1, waiting out the delay (param4) first when there
/// is one, as ArduPilot's calibrator (WAITING_TO_START), else collecting from zero at once.
fn start(opts: MagCalStart, now_s: f64) -> Step {
    let accepted = MagCalEffect::Ack(MavResult::MAV_RESULT_ACCEPTED);
    if opts.delay_s > 0.0 {
        let waiting = MagCalRun::Waiting {
            start_at_s: now_s + opts.delay_s,
            opts,
            attempt: 1,
        };
        (waiting, vec![accepted])
    } else {
        let running = MagCalRun::Running { opts, attempt: 1 };
        (running, vec![accepted, MagCalEffect::Restart])
    }
}

/// A passing fit installed and written at once, and reported.
fn autosave(cal: Box<SensorCalibration>, commanded: bool) -> Vec<MagCalEffect> {
    vec![
        MagCalEffect::Install(cal.clone()),
        MagCalEffect::ReportSuccess {
            cal,
            autosaved: true,
            commanded,
        },
    ]
}

/// ArduPilot's calibrator tolerance (COMPASS_CAL_FIT, `fit_mgauss`) for compass `compass_id`:
/// as given for the first compass when it is external, twice that for every other (internal
/// compasses, and further ones, are noisier, as ArduPilot's `_start_calibration` says).
/// `external`: COMPASS_EXTERNAL as the vehicle's parameters give it; unknown counts as internal.
pub(super) fn fitness_tolerance_mgauss(
    fit_mgauss: f64,
    compass_id: u8,
    external: Option<bool>,
) -> f64 {
    if compass_id == 0 && external == Some(true) {
        fit_mgauss
    } else {
        2.0 * fit_mgauss
    }
}

/// A commanded run's passing fit judged against the calibrator's tolerance, as ArduPilot's
/// `fit_acceptable` does last: a fitness (RMS residual, mGauss) above `tolerance_mgauss` fails
/// the fit (failure `residuals`, MAG_CAL_REPORT status FAILED_RESIDUALS_HIGH), saying both figures.
/// Returns whether it failed it.
pub(super) fn fail_on_fitness(mag: &mut SensorCalibration, tolerance_mgauss: f64) -> bool {
    let fitness_mgauss = mag.rms_residual * crate::calib::ardupilot::MGAUSS_PER_UT;
    if mag.status != CalStatus::Ok || fitness_mgauss <= tolerance_mgauss {
        return false;
    }
    mag.status = CalStatus::Failed;
    mag.failure = Some(FitFailure::Residuals);
    mag.detail = Some(format!(
        "fitness {fitness_mgauss:.1} mGauss over the tolerance {tolerance_mgauss:.1} mGauss (daemon.mag_cal_fit_mgauss, ArduPilot's COMPASS_CAL_FIT)"
    ));
    true
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
            attempt: 1,
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
        // Waiting out the delay: progress says WAITING_TO_START, attempt 1.
        assert_eq!(s.progress(false), Some((ProgressStatus::WaitingToStart, 1)));
        let (s, fx) = s.on(V::Tick { now_s: 11.9 }, false, 0);
        assert!(fx.is_empty() && matches!(s, MagCalRun::Waiting { .. }));
        let (s, fx) = s.on(V::Tick { now_s: 12.0 }, false, 0);
        assert_eq!(fx, vec![E::Restart]);
        assert_eq!(s.progress(false), Some((ProgressStatus::Running, 1)));
        // Failure: with retry, again from zero as attempt 2, then 3 (said, not reported, as
        // ArduPilot's calibrator retries); without, failed until restarted or cancelled.
        let retrying = MagCalRun::Running {
            opts: opts(true, true, 0.0),
            attempt: 1,
        };
        let (s, fx) = retrying.on(V::FitFailed, false, 0);
        let said = |retry_attempt| E::SayFailure { retry_attempt };
        assert_eq!(fx, vec![said(Some(2)), E::Restart]);
        assert_eq!(s.progress(false), Some((ProgressStatus::Running, 2)));
        let (s, fx) = s.on(V::FitFailed, false, 0);
        assert_eq!(fx, vec![said(Some(3)), E::Restart]);
        assert_eq!(s.progress(false), Some((ProgressStatus::Running, 3)));
        let (s, fx) = MagCalRun::Running {
            opts: opts(true, false, 0.0),
            attempt: 1,
        }
        .on(V::FitFailed, false, 0);
        let failed_run = |next_report_s| MagCalRun::Failed { next_report_s };
        assert_eq!(
            (s.clone(), fx),
            (failed_run(None), vec![said(None), E::ReportFailure])
        );
        assert_eq!(s.progress(true), None);
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

    #[test]
    fn fitness_over_the_tolerance_fails_the_fit_as_ardupilot_does() {
        // COMPASS_CAL_FIT as given only for an external compass 0; doubled otherwise, unknown
        // counting as internal.
        assert_eq!(fitness_tolerance_mgauss(16.0, 0, Some(true)), 16.0);
        assert_eq!(fitness_tolerance_mgauss(16.0, 0, Some(false)), 32.0);
        assert_eq!(fitness_tolerance_mgauss(16.0, 0, None), 32.0);
        assert_eq!(fitness_tolerance_mgauss(16.0, 1, Some(true)), 32.0);
        // 4.16 uT RMS is 41.6 mGauss: over 32, failed as residuals (FAILED_RESIDUALS_HIGH).
        let mut noisy = *run_cal(1.0);
        noisy.rms_residual = 4.16;
        assert!(fail_on_fitness(&mut noisy, 32.0));
        assert_eq!(noisy.status, CalStatus::Failed);
        assert_eq!(noisy.failure, Some(FitFailure::Residuals));
        assert!(
            noisy.detail.as_deref().unwrap().contains("41.6"),
            "{noisy:?}"
        );
        assert_eq!(crate::io::mavout::mag_cal_status_code(&noisy), 10);
        // At the tolerance it passes, and a failed fit stays as it was.
        let mut fine = *run_cal(1.0);
        fine.rms_residual = 3.2;
        assert!(!fail_on_fitness(&mut fine, 32.0));
        assert_eq!(fine.status, CalStatus::Ok);
        assert!(!fail_on_fitness(&mut noisy.clone(), 1.0));
    }
}
