//! The calibration lifecycle of each track: progress, fits and their acceptance, the
//! magnetometer calibration run driven by [`MagCalRun::on`] (ground-station commands), installing
//! and writing parameters, the report's instance blocks.

use super::*;

impl State {
    /// MAG_CAL_PROGRESS and a JSON `progress` line for each compass whose calibration run
    /// reports progress (track 0 always; a further instance once it has magnetometer data).
    pub(super) async fn publish_progress(&mut self) {
        let continuous = self.cfg.daemon.mag_cal == MagCalMode::Continuous;
        for i in 0..self.tracks.len() {
            let centre = self
                .in_use(i, Sensor::Mag)
                .and_then(|m| m.calibration())
                .map(|c| c.offset);
            let t = &mut self.tracks[i];
            if (i > 0 && t.mag_samples == 0) || !t.mag_run.reports_progress(continuous) {
                continue;
            }
            let p = t.pipe.progress(&mut t.progress, centre);
            let dir = p.direction.map(|v| v as f32);
            let msg = mavout::mag_cal_progress(t.compass_id, p.completion_pct, p.mask, dir, 1);
            let ev = LiveEvent::Progress {
                sensor: "mag".into(),
                instance: t.compass_id,
                completion_pct: p.completion_pct as f64,
                filled_regions: p.filled_regions,
            };
            self.send_mav(&[msg]).await;
            self.send_json(&ev).await;
        }
    }

    /// The calibration in use of track `i`'s `sensor` (magnetometer or accelerometer).
    pub(super) fn in_use(&self, i: usize, sensor: Sensor) -> Option<&SensorCalibration> {
        let (mag, accel) = if i == 0 {
            (&self.store.mag, &self.store.accel)
        } else {
            let id = self.tracks[i].compass_id;
            let s = self.store.instances.iter().find(|s| s.compass_id == id)?;
            (&s.mag, &s.accel)
        };
        match sensor {
            Sensor::Mag => mag.as_ref(),
            Sensor::Accel => accel.as_ref(),
            Sensor::Gyro => None,
        }
    }

    /// A compass's name in messages to the user: empty with one compass.
    pub(super) fn compass_label(&self, i: usize) -> String {
        if self.tracks.len() > 1 {
            format!(" (compass {})", self.tracks[i].compass_id)
        } else {
            String::new()
        }
    }

    /// A refit of track `i` came back: decide, store, publish.
    pub(super) async fn on_fit(&mut self, i: usize, t: f64, results: FitResults) {
        let mut changed = false;
        let id = self.tracks[i].compass_id;
        // A commanded run is judged on its own, as ArduPilot's calibrator judges a run: its
        // result is reported whatever the calibration in use (accepting it is the ground
        // station's call). The magnetometer's result goes to the calibration run (`mag_event`),
        // which installs it or holds it for the ground station.
        let commanded = matches!(self.tracks[i].mag_run, MagCalRun::Running { .. });
        let current_mag = self.in_use(i, Sensor::Mag).filter(|_| !commanded).cloned();
        let mag_passed = match accept(&results.mag, current_mag.as_ref()) {
            Ok(()) => true,
            Err(why) => {
                tracing::info!(
                    sensor = "mag",
                    compass = id,
                    "calibration not replaced: {why}"
                );
                false
            }
        };
        match accept(&results.accel, self.in_use(i, Sensor::Accel)) {
            Ok(()) => {
                let r = &results.accel.report;
                tracing::info!(sensor = "accel", compass = id, model = %r.model, rms = r.rms_residual, "calibration accepted");
                if i == 0 {
                    self.store.accel = Some(r.clone());
                    self.calibrator.accel = results.accel.calibration;
                } else {
                    let name = self.tracks[i].name.clone();
                    self.store.instance_mut(&name, id).accel = Some(r.clone());
                }
                changed = true;
            }
            Err(why) => tracing::info!(
                sensor = "accel",
                compass = id,
                "calibration not replaced: {why}"
            ),
        }
        if i == 0 && results.gyro.status == crate::report::CalStatus::Ok {
            let before = self.calibrator.gyro_bias.unwrap_or([0.0; 3]);
            let now = results.gyro.bias;
            self.fusion
                .gyro_bias_removed(&[0, 1, 2].map(|k| now[k] - before[k]));
            self.store.gyro = Some(results.gyro.clone());
            self.calibrator.gyro_bias = Some(now);
        }
        // The magnetometer like ArduPilot's calibrator: success when accepted, failure once the
        // data covered the sphere and the fit still failed (not while still collecting).
        let mag = &results.mag.report;
        let completion = self.tracks[i].progress.completion_pct();
        if mag_passed {
            let ev = MagCalEvent::FitPassed {
                cal: Box::new(mag.clone()),
                complete: completion >= 100,
            };
            changed |= self.mag_event(i, ev).await.0;
        } else if failure_report_due(mag, completion) {
            self.tracks[i].mag_failed = Some(mag.clone());
            self.mag_event(i, MagCalEvent::FitFailed).await;
        }
        for (name, r) in [
            ("mag", &results.mag.report),
            ("accel", &results.accel.report),
        ] {
            self.send_json(&LiveEvent::calibration(name, id, r)).await;
        }
        self.tracks[i].pipe.install(t, results.clone());
        self.tracks[i].last_results = Some(results);
        if changed {
            self.store_changed();
        }
        if let Some(job) = self.report_job() {
            self.report_writes.want(job);
        }
    }

    /// A new calibration in the store: counted, and written off the run loop (with what the
    /// orientation filter has learnt).
    pub(super) fn store_changed(&mut self) {
        self.accepted += 1;
        self.store.filter = self.filter_state();
        let store = Box::new(self.store.clone());
        self.store_writes
            .want(WriteJob::Store(self.cal_dir.clone(), store));
    }

    /// Feed track `i`'s magnetometer calibration run an event and carry out what its transition
    /// says. Returns whether a calibration was installed (the caller has the store written) and
    /// the COMMAND_ACK results the transition gave (the caller answers the command once).
    pub(super) async fn mag_event(&mut self, i: usize, ev: MagCalEvent) -> (bool, Vec<MavResult>) {
        let accepting = matches!(ev, MagCalEvent::Accept { .. });
        let continuous = self.cfg.daemon.mag_cal == MagCalMode::Continuous;
        let id = self.tracks[i].compass_id;
        let run = std::mem::replace(&mut self.tracks[i].mag_run, MagCalRun::Idle);
        let (next, effects) = run.on(ev, continuous, id);
        self.tracks[i].mag_run = next;
        let (mut installed, mut reported, mut acks) = (false, false, vec![]);
        for fx in effects {
            match fx {
                MagCalEffect::Ack(result) => acks.push(result),
                MagCalEffect::Restart => self.restart_mag_run(i).await,
                MagCalEffect::Install(cal) => {
                    self.install_mag(i, *cal);
                    installed = true;
                }
                MagCalEffect::ReportSuccess {
                    cal,
                    autosaved,
                    commanded,
                } => {
                    let moved = self.tracks[i].reported_mag.as_ref().is_none_or(|prev| {
                        prev.model != cal.model
                            || (0..3).any(|k| (prev.offset[k] - cal.offset[k]).abs() > 0.05)
                    });
                    if commanded || moved {
                        reported = autosaved;
                        let msg = mavout::mag_cal_report_autosaved(id, &cal, autosaved);
                        self.send_mav(&[msg]).await;
                        let what = if autosaved {
                            "mag calibrated"
                        } else {
                            "mag calibration ready (accept to install it, cancel to discard it)"
                        };
                        let text = format!(
                            "{what}{}: {} offset [{:.2}, {:.2}, {:.2}] uT, rms {:.3}",
                            self.compass_label(i),
                            cal.model,
                            cal.offset[0],
                            cal.offset[1],
                            cal.offset[2],
                            cal.rms_residual
                        );
                        self.status(6, text).await;
                        self.tracks[i].reported_mag = Some(*cal);
                    }
                }
                MagCalEffect::ReportFailure => {
                    if let Some(mag) = self.tracks[i].mag_failed.take() {
                        self.send_mav(&[mavout::mag_cal_report(id, &mag)]).await;
                    }
                }
            }
        }
        if installed && (reported || accepting) && self.cfg.daemon.write_params {
            self.start_param_write();
        }
        (installed, acks)
    }

    /// A magnetometer calibration of track `i` in use from now on (the store is written by the
    /// caller). The primary's also goes to the heading and attitude.
    pub(super) fn install_mag(&mut self, i: usize, cal: SensorCalibration) {
        tracing::info!(sensor = "mag", compass = self.tracks[i].compass_id, model = %cal.model, rms = cal.rms_residual, "calibration accepted");
        if i > 0 {
            let (name, id) = (self.tracks[i].name.clone(), self.tracks[i].compass_id);
            self.store.instance_mut(&name, id).mag = Some(cal);
            return;
        }
        let before = self.calibrator.mag;
        self.store.mag = Some(cal);
        self.calibrator.mag = self.store.mag_cal();
        if let Some(m) = self.last_body_mag {
            if mag_cal_moved(before.as_ref(), self.calibrator.mag.as_ref(), &m) {
                tracing::info!(
                    "magnetometer calibration moved the field: orientation filter restarted (gyro bias kept, field reference learnt again)"
                );
                let kept = crate::fusion::FilterState {
                    mag_reference: None,
                    ..self.fusion.state()
                };
                self.fusion = OrientationFilter::new(*self.fusion.config());
                self.fusion.set_state(&kept);
                self.filter_seeded = true;
            }
        }
    }

    /// A new calibration run of track `i` from zero coverage: what was collected goes, a fit in
    /// flight is disregarded (it saw the old data); the calibration in use stays.
    pub(super) async fn restart_mag_run(&mut self, i: usize) {
        let t = &mut self.tracks[i];
        match Pipeline::new(&self.cfg) {
            Ok(p) => {
                let (mag_units, gyro_units) = (t.pipe.mag_units, t.pipe.gyro_units);
                t.pipe = p.with_hold_out(HOLD_OUT_EVERY);
                (t.pipe.mag_units, t.pipe.gyro_units) = (mag_units, gyro_units);
            }
            Err(e) => tracing::error!("calibration run not restarted: {e}"),
        }
        t.generation += 1;
        t.refit_wanted = false;
        t.progress.restart();
        let text = format!("mag calibration run started{}", self.compass_label(i));
        self.status(6, text).await;
    }

    /// COMMAND_LONG: the ground station's calibration commands when addressed to us (or to all).
    /// Like ArduPilot, each compass has its own run and the command's compass mask says which
    /// take it (0: all); one COMMAND_ACK answers: accepted when a compass took it.
    pub(super) async fn on_command(&mut self, frame: &crate::decode::Frame, c: &COMMAND_LONG_DATA) {
        let to_us = |target: u8, own: u8| target == 0 || target == own;
        if !(to_us(c.target_system, self.own.system_id)
            && to_us(c.target_component, self.own.component_id))
        {
            return;
        }
        let ev = match c.command {
            MavCmd::MAV_CMD_DO_START_MAG_CAL => MagCalEvent::Start {
                opts: mavout::MagCalStart::from_command(c),
                now_s: self.now_s(),
            },
            MavCmd::MAV_CMD_DO_ACCEPT_MAG_CAL => MagCalEvent::Accept {
                mask: mavout::mask_param(c.param1),
            },
            MavCmd::MAV_CMD_DO_CANCEL_MAG_CAL => MagCalEvent::Cancel {
                mask: mavout::mask_param(c.param1),
            },
            other => {
                // Another command meant for us alone gets an answer; broadcast ones are for others.
                if c.target_system != 0 && c.target_component != 0 {
                    let ack = mavout::command_ack(
                        other,
                        MavResult::MAV_RESULT_UNSUPPORTED,
                        frame.system_id,
                        frame.component_id,
                    );
                    self.send_mav(&[ack]).await;
                }
                return;
            }
        };
        tracing::info!(
            "{:?} from {}/{}",
            c.command,
            frame.system_id,
            frame.component_id
        );
        let (mut installed, mut acks) = (false, vec![]);
        for i in 0..self.tracks.len() {
            if i == 0 || self.tracks[i].mag_samples > 0 {
                let (inst, a) = self.mag_event(i, ev.clone()).await;
                installed |= inst;
                acks.extend(a);
            }
        }
        let result = if acks.contains(&MavResult::MAV_RESULT_ACCEPTED) {
            MavResult::MAV_RESULT_ACCEPTED
        } else {
            acks.first()
                .copied()
                .unwrap_or(MavResult::MAV_RESULT_FAILED)
        };
        let ack = mavout::command_ack(c.command, result, frame.system_id, frame.component_id);
        self.send_mav(&[ack]).await;
        if installed {
            self.store_changed();
        }
    }

    /// Write every compass's calibration in use to the flight controller (`daemon.write_params`).
    pub(super) fn start_param_write(&mut self) {
        let params: Vec<_> = self
            .store
            .mags_ut()
            .iter()
            .flat_map(|(k, m)| {
                if self.cfg.daemon.param_target == ParamTarget::Px4 {
                    crate::export::px4_mag(m, *k).0
                } else {
                    crate::export::ardupilot_mag(m, *k).0
                }
            })
            .collect();
        if params.is_empty() {
            return;
        }
        self.writer = Some(ParamWriter::new(
            params,
            self.cfg.daemon.target_system,
            self.cfg.daemon.target_component,
        ));
    }
}

impl State {
    /// Start a fit of every track whose refit is due (`all`: of every track, with its last poses
    /// closed: the end of a replay), off the executor.
    pub(super) fn start_fits(&mut self, all: bool) -> tokio::task::JoinHandle<TrackFits> {
        let mut inputs = vec![];
        for (i, t) in self.tracks.iter_mut().enumerate() {
            if all {
                t.pipe.finish_poses();
            } else if !t.refit_wanted {
                continue;
            }
            t.refit_wanted = false;
            inputs.push((i, t.generation, t.pipe.last_t, t.pipe.snapshot()));
        }
        let cfg = self.cfg.clone();
        tokio::task::spawn_blocking(move || {
            inputs
                .into_iter()
                .map(|(i, generation, t, input)| (i, generation, t, fit_all(&input, &cfg)))
                .collect()
        })
    }

    /// Fits came back: each goes to its track unless that track's run restarted meanwhile.
    pub(super) async fn fits_done(&mut self, r: Result<TrackFits, tokio::task::JoinError>) {
        match r {
            Ok(fits) => {
                for (i, generation, t, res) in fits {
                    if generation == self.tracks[i].generation {
                        self.on_fit(i, t, res).await;
                    } else {
                        tracing::info!(
                            "a fit from before the calibration run restarted: disregarded"
                        );
                    }
                }
            }
            Err(e) => tracing::error!("fit task failed: {e}"),
        }
    }
}

/// A block per calibrated instance for the report (empty with one): the primary's calibration is
/// the report's own (`primary`), the others' their latest fits.
impl State {
    pub(super) fn instance_reports(
        &self,
        primary: &crate::report::CalibrationReport,
    ) -> Vec<crate::report::InstanceReport> {
        if self.tracks.len() < 2 {
            return Vec::new();
        }
        let infos = self
            .primary_vehicle
            .map(|v| self.vehicles[v].conv.instances())
            .unwrap_or_default();
        self.tracks
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let calibration = if i == 0 {
                    primary.clone()
                } else {
                    let r = t.last_results.as_ref()?;
                    crate::report::CalibrationReport {
                        mag: r.mag.report.clone(),
                        accel: r.accel.report.clone(),
                        gyro: r.gyro.clone(),
                    }
                };
                let info = t.instance.and_then(|k| infos.get(k));
                Some(crate::report::InstanceReport {
                    instance: t.name.clone(),
                    compass_id: t.compass_id,
                    primary: i == 0,
                    samples: info.map_or(t.pipe.samples, |x| x.samples),
                    time: info.map(|x| x.time.clone()).unwrap_or_default(),
                    calibration,
                })
            })
            .collect()
    }
}
