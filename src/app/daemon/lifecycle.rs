//! The calibration lifecycle of each track: progress, fits and their acceptance, the
//! magnetometer calibration run driven by [`MagCalRun::on`] (ground-station commands), installing
//! and writing parameters, the report's instance blocks.

use super::*;

impl State {
    /// MAG_CAL_PROGRESS and a JSON `progress` line for each compass whose calibration run
    /// reports progress (track 0 always; a further instance once it has magnetometer data).
    pub(super) async fn publish_progress(&mut self) {
        for c in 0..self.cals.len() {
            for i in 0..self.cals[c].tracks.len() {
                self.publish_track_progress(c, i).await;
            }
        }
    }

    async fn publish_track_progress(&mut self, c: usize, i: usize) {
        let continuous = self.cfg.daemon.mag_cal == MagCalMode::Continuous;
        let cal = &mut self.cals[c];
        let centre = cal
            .in_use(i, Sensor::Mag)
            .and_then(|m| m.calibration())
            .map(|m| m.offset);
        let t = &mut cal.tracks[i];
        let Some((status, attempt)) = t.mag_run.progress(continuous) else {
            return;
        };
        if i > 0 && t.mag_samples == 0 {
            return;
        }
        {
            let p = t.pipe.progress(&mut t.progress, centre);
            let run_mask = cal.run_mask(i);
            let t = &cal.tracks[i];
            let msg = mavout::mag_cal_progress(
                t.compass_id,
                run_mask,
                p.completion_pct,
                p.mask,
                attempt,
                status,
            );
            let ev = LiveEvent::Progress {
                sensor: "mag".into(),
                instance: t.compass_id,
                completion_pct: p.completion_pct as f64,
                filled_regions: p.filled_regions,
                regions: crate::calib::coverage::regions_hex(&p.regions),
                direction: p.direction,
            };
            self.send_mav(To::Cal(c), &[msg]).await;
            self.send_json_for(c, &ev).await;
        }
    }
}

impl Cal {
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

    /// The MAG_CAL_* `cal_mask` for track `i`: every compass of this vehicle with a calibration
    /// run (ArduPilot's: every compass whose calibrator is not idle), or track `i`'s own bit when
    /// none runs (continuous calibration).
    pub(super) fn run_mask(&self, i: usize) -> u8 {
        let running = self
            .tracks
            .iter()
            .filter(|t| !matches!(t.mag_run, MagCalRun::Idle))
            .fold(0u8, |m, t| m | mavout::compass_bit(t.compass_id));
        if running == 0 {
            mavout::compass_bit(self.tracks[i].compass_id)
        } else {
            running
        }
    }

    /// A magnetometer calibration of track `i` in use from now on (the store is written by the
    /// caller). The primary's also goes to the heading and attitude.
    pub(super) fn install_mag(&mut self, i: usize, cal: SensorCalibration) {
        // Its caller says when it is a rung learnt from the track's readings (`on_fit`).
        self.tracks[i].rung_until_s = None;
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
                    "magnetometer calibration moved the field: orientation filter restarted (gyro bias kept, field reference and gyro scale learnt again)"
                );
                self.fusion.restart_for_new_field();
                self.filter_seeded = true;
            }
        }
    }
}

impl State {
    /// A refit of calibrated vehicle `c`'s track `i` came back (with the ladder climbed on its
    /// learnt readings, `live`, when the sphere fit failed): decide, store, publish.
    pub(super) async fn on_fit(
        &mut self,
        c: usize,
        i: usize,
        t: f64,
        mut results: FitResults,
        live: Option<Box<LiveLadder>>,
    ) {
        let mut changed = false;
        let cal = &mut self.cals[c];
        // A commanded run is judged on its own, as ArduPilot's calibrator judges a run: its
        // result is reported whatever the calibration in use (accepting it is the ground
        // station's call). The magnetometer's result goes to the calibration run (`mag_event`),
        // which installs it or holds it for the ground station.
        let commanded = cal.tracks[i].mag_run.running();
        // The learnt rung needs no coverage: once the ladder takes one, the run is complete.
        let by_vector = cal.tracks[i].take_rung(&mut results, live.as_deref(), !commanded);
        let id = cal.tracks[i].compass_id;
        if commanded {
            self.judge_fitness(c, id, &mut results);
        }
        let cal = &mut self.cals[c];
        let current_mag = cal.in_use(i, Sensor::Mag).filter(|_| !commanded).cloned();
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
        let mut accel_installed = false;
        match accept(&results.accel, cal.in_use(i, Sensor::Accel)) {
            Ok(()) => {
                accel_installed = true;
                let r = &results.accel.report;
                tracing::info!(sensor = "accel", compass = id, model = %r.model, rms = r.rms_residual, "calibration accepted");
                if i == 0 {
                    cal.store.accel = Some(r.clone());
                    cal.calibrator.accel = results.accel.calibration;
                } else {
                    let name = cal.tracks[i].name.clone();
                    cal.store.instance_mut(&name, id).accel = Some(r.clone());
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
            let before = cal.calibrator.gyro_bias.unwrap_or([0.0; 3]);
            let now = results.gyro.bias;
            cal.fusion
                .gyro_bias_removed(&[0, 1, 2].map(|k| now[k] - before[k]));
            cal.store.gyro = Some(results.gyro.clone());
            cal.calibrator.gyro_bias = Some(now);
        }
        // The magnetometer like ArduPilot's calibrator: success when accepted, failure once the
        // data covered the sphere and the fit still failed (not while still collecting).
        let mag = &results.mag.report;
        let completion = cal.tracks[i].progress.completion_pct();
        let mut mag_installed = false;
        if mag_passed {
            let ev = MagCalEvent::FitPassed {
                cal: Box::new(mag.clone()),
                complete: completion >= 100 || by_vector,
            };
            mag_installed = self.mag_event(c, i, ev).await.0;
            changed |= mag_installed;
            if mag_installed && by_vector {
                self.cals[c].tracks[i].rung_until_s = live.as_ref().and_then(|l| l.last_t_s);
            }
        } else if failure_report_due(mag, completion) {
            cal.tracks[i].mag_failed = Some(mag.clone());
            self.mag_event(c, i, MagCalEvent::FitFailed).await;
        }
        for (name, r, installed) in [
            ("mag", &results.mag.report, mag_installed),
            ("accel", &results.accel.report, accel_installed),
        ] {
            self.send_json_for(c, &LiveEvent::calibration(name, id, r, installed))
                .await;
        }
        let track = &mut self.cals[c].tracks[i];
        track.pipe.install(t, results.clone());
        track.last_results = Some(results);
        if changed {
            self.store_changed(c);
        }
        if let Some(job) = self.report_job() {
            self.report_writes.want(job);
        }
    }

    /// A commanded run's magnetometer fit against ArduPilot's calibrator tolerance for compass
    /// `id` of vehicle `c` ([`magcal::fail_on_fitness`]): over it, the fit fails.
    fn judge_fitness(&self, c: usize, id: u8, results: &mut FitResults) {
        let tolerance = magcal::fitness_tolerance_mgauss(
            self.cfg.daemon.mag_cal_fit_mgauss,
            id,
            self.compass_external(c, id),
        );
        if magcal::fail_on_fitness(&mut results.mag.report, tolerance) {
            results.mag.calibration = None;
        }
    }

    /// A new calibration in the store: counted, and written off the run loop (with what the
    /// orientation filter has learnt).
    pub(super) fn store_changed(&mut self, c: usize) {
        self.accepted += 1;
        let cal = &mut self.cals[c];
        cal.store.filter = cal.filter_state();
        let store = Box::new(cal.store.clone());
        self.store_writes
            .want(WriteJob::Store(cal.cal_dir.clone(), store));
    }

    /// Feed track `i`'s magnetometer calibration run an event and carry out what its transition
    /// says. Returns whether a calibration was installed (the caller has the store written) and
    /// the COMMAND_ACK results the transition gave (the caller answers the command once).
    pub(super) async fn mag_event(
        &mut self,
        c: usize,
        i: usize,
        ev: MagCalEvent,
    ) -> (bool, Vec<MavResult>) {
        let accepting = matches!(ev, MagCalEvent::Accept { .. });
        let continuous = self.cfg.daemon.mag_cal == MagCalMode::Continuous;
        let track = &mut self.cals[c].tracks[i];
        let id = track.compass_id;
        let run = std::mem::replace(&mut track.mag_run, MagCalRun::Idle);
        let (next, effects) = run.on(ev, continuous, id);
        track.mag_run = next;
        let (mut installed, mut reported, mut acks) = (false, false, vec![]);
        for fx in effects {
            match fx {
                MagCalEffect::Ack(result) => acks.push(result),
                MagCalEffect::Restart => self.restart_mag_run(c, i).await,
                MagCalEffect::Install(cal) => {
                    self.cals[c].install_mag(i, *cal);
                    installed = true;
                }
                MagCalEffect::ReportSuccess {
                    cal,
                    autosaved,
                    commanded,
                } => {
                    let moved = self.cals[c].tracks[i]
                        .reported_mag
                        .as_ref()
                        .is_none_or(|prev| {
                            prev.model != cal.model
                                || (0..3).any(|k| (prev.offset[k] - cal.offset[k]).abs() > 0.05)
                        });
                    if commanded || moved {
                        reported = autosaved;
                        let mask = self.cals[c].run_mask(i);
                        let msg = mavout::mag_cal_report_autosaved(id, mask, &cal, autosaved);
                        self.send_mav(To::Cal(c), &[msg]).await;
                        let what = if autosaved {
                            "mag calibrated"
                        } else {
                            "mag calibration ready (accept to install it, cancel to discard it)"
                        };
                        let text = format!(
                            "{what}{}: {} offset [{:.2}, {:.2}, {:.2}] uT, rms {:.3}",
                            self.cals[c].compass_label(i),
                            cal.model,
                            cal.offset[0],
                            cal.offset[1],
                            cal.offset[2],
                            cal.rms_residual
                        );
                        self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
                            .await;
                        self.cals[c].tracks[i].reported_mag = Some(*cal);
                    }
                }
                MagCalEffect::SayFailure { retry_attempt } => {
                    self.say_mag_failure(c, i, retry_attempt).await
                }
                MagCalEffect::ReportFailure | MagCalEffect::RepeatFailure => {
                    let mask = self.cals[c].run_mask(i);
                    if let Some(mag) = self.cals[c].tracks[i].mag_failed.as_ref() {
                        let msg = mavout::mag_cal_report(id, mask, mag);
                        self.send_mav(To::Cal(c), &[msg]).await;
                    }
                }
                MagCalEffect::RepeatSuccess { cal, autosaved } => {
                    let mask = self.cals[c].run_mask(i);
                    let msg = mavout::mag_cal_report_autosaved(id, mask, &cal, autosaved);
                    self.send_mav(To::Cal(c), &[msg]).await;
                }
            }
        }
        if installed && (reported || accepting) && self.cfg.daemon.write_params {
            self.cals[c].start_param_write(self.cfg.daemon.param_target);
        }
        (installed, acks)
    }

    /// A new calibration run of track `i` from zero coverage: what was collected goes, a fit in
    /// flight is disregarded (it saw the old data); the calibration in use stays.
    pub(super) async fn restart_mag_run(&mut self, c: usize, i: usize) {
        let t = &mut self.cals[c].tracks[i];
        match Pipeline::new(&self.cfg.calib()) {
            Ok(p) => {
                let (mag_units, gyro_units) = (t.pipe.mag_units, t.pipe.gyro_units);
                t.pipe = p.with_hold_out(HOLD_OUT_EVERY);
                t.samples_in = 0;
                (t.pipe.mag_units, t.pipe.gyro_units) = (mag_units, gyro_units);
            }
            Err(e) => tracing::error!("calibration run not restarted: {e}"),
        }
        t.generation += 1;
        t.refit_wanted = false;
        t.progress.restart();
        let text = format!(
            "mag calibration run started{}",
            self.cals[c].compass_label(i)
        );
        self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
            .await;
    }

    /// A STATUSTEXT for track `i`'s failed run: why its fit failed, and the attempt that starts
    /// now when it retries.
    async fn say_mag_failure(&mut self, c: usize, i: usize, retry_attempt: Option<u8>) {
        let cal = &self.cals[c];
        let why = cal.tracks[i]
            .mag_failed
            .as_ref()
            .map(|m| {
                let reason = m.failure.map_or("failed".to_string(), |f| f.to_string());
                match &m.detail {
                    Some(d) => format!("{reason}: {d}"),
                    None => reason,
                }
            })
            .unwrap_or_else(|| "failed".into());
        let next = retry_attempt.map_or(String::new(), |a| format!("; retrying, attempt {a}"));
        let text = format!(
            "mag calibration failed{}: {why}{next}",
            cal.compass_label(i)
        );
        self.status_for(c, MavSeverity::MAV_SEVERITY_WARNING, text)
            .await;
    }

    /// Whether compass `compass_id` of calibrated vehicle `c` is external, as its COMPASS_EXTERNAL
    /// parameters say (`None`: not known, no ArduPilot parameters read).
    fn compass_external(&self, c: usize, compass_id: u8) -> Option<bool> {
        let v = self.cals[c].vehicle?;
        self.vehicles[v].conv.compass_external(compass_id)
    }

    /// COMMAND_LONG: the ground station's calibration commands for the calibrated vehicles it
    /// is addressed to: to the ids one is spoken for with, or broadcast (0); a broadcast reaches
    /// the first vehicle and those heard on the command's link. Like ArduPilot, each compass has
    /// its own run and the command's compass mask says which take it (0: all); one COMMAND_ACK
    /// per vehicle answers: accepted when a compass took it.
    pub(super) async fn on_command(
        &mut self,
        link: usize,
        frame: &crate::io::decode::Frame,
        cmd: &COMMAND_LONG_DATA,
    ) {
        let to = |target: u8, own: u8| target == 0 || target == own;
        let takers: Vec<usize> = (0..self.cals.len())
            .filter(|&c| {
                let own = self.cals[c].own;
                let here = c == 0 || self.links.get(link).is_some_and(|l| l.cals.contains(&c));
                to(cmd.target_component, own.component_id)
                    && (cmd.target_system == own.system_id || (cmd.target_system == 0 && here))
            })
            .collect();
        let Some(&first) = takers.first() else {
            return;
        };
        if cmd.command == MavCmd::MAV_CMD_FIXED_MAG_CAL_YAW {
            for c in takers {
                self.fixed_yaw(c, frame, cmd).await;
            }
            return;
        }
        let ev = match cmd.command {
            MavCmd::MAV_CMD_DO_START_MAG_CAL => MagCalEvent::Start {
                opts: mavout::MagCalStart::from_command(cmd),
                now_s: self.now_s(),
            },
            MavCmd::MAV_CMD_DO_ACCEPT_MAG_CAL => MagCalEvent::Accept {
                mask: mavout::mask_param(cmd.param1),
            },
            MavCmd::MAV_CMD_DO_CANCEL_MAG_CAL => MagCalEvent::Cancel {
                mask: mavout::mask_param(cmd.param1),
            },
            other => {
                // Another command meant for us alone gets an answer; broadcast ones are for others.
                if cmd.target_system != 0 && cmd.target_component != 0 {
                    let ack = mavout::command_ack(
                        other,
                        MavResult::MAV_RESULT_UNSUPPORTED,
                        frame.system_id,
                        frame.component_id,
                    );
                    self.send_mav(To::Cal(first), &[ack]).await;
                }
                return;
            }
        };
        tracing::info!(
            "{:?} from {}/{}",
            cmd.command,
            frame.system_id,
            frame.component_id
        );
        for c in takers {
            let (mut installed, mut acks) = (false, vec![]);
            for i in 0..self.cals[c].tracks.len() {
                if i == 0 || self.cals[c].tracks[i].mag_samples > 0 {
                    let (inst, a) = self.mag_event(c, i, ev.clone()).await;
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
            let ack = mavout::command_ack(cmd.command, result, frame.system_id, frame.component_id);
            self.send_mav(To::Cal(c), &[ack]).await;
            if installed {
                self.store_changed(c);
            }
        }
    }
}

impl State {
    /// MAV_CMD_FIXED_MAG_CAL_YAW for calibrated vehicle `c`, as ArduPilot answers it: param1 the
    /// vehicle's true yaw (deg), param2 the compass mask (0: all), param3/param4 latitude and
    /// longitude (deg; both 0: the vehicle's own position, [`State::own_place`]; none: refused
    /// with ArduPilot's "Mag: no position available"). Each compass of the mask with magnetometer
    /// data in uT gets the offsets [`crate::calib::fixedyaw`] finds from its latest samples,
    /// installed, reported (MAG_CAL_REPORT) and written; one COMMAND_ACK: accepted when a compass
    /// was calibrated.
    async fn fixed_yaw(
        &mut self,
        c: usize,
        frame: &crate::io::decode::Frame,
        cmd: &COMMAND_LONG_DATA,
    ) {
        let (lat, lon) = (cmd.param3 as f64, cmd.param4 as f64);
        // The field of today where `[place]` gives no date: a fixed-yaw calibration is of now.
        let today = crate::io::clock::today().iso();
        let place = if lat == 0.0 && lon == 0.0 {
            self.own_place(c)
        } else {
            Some(crate::attitude::Place::at(lat, lon))
        };
        let Some(place) = place.map(|p| p.dated(&today)) else {
            self.status_for(
                c,
                MavSeverity::MAV_SEVERITY_ERROR,
                NO_POSITION_TEXT.to_string(),
            )
            .await;
            let ack = mavout::command_ack(
                cmd.command,
                MavResult::MAV_RESULT_FAILED,
                frame.system_id,
                frame.component_id,
            );
            self.send_mav(To::Cal(c), &[ack]).await;
            return;
        };
        let field = crate::attitude::earth_field(&place);
        let mask = mavout::mask_param(cmd.param2);
        let mut calibrated = 0;
        for i in 0..self.cals[c].tracks.len() {
            let t = &self.cals[c].tracks[i];
            if !mavout::mask_selects(mask, t.compass_id) || t.mag_samples == 0 {
                continue;
            }
            let outcome = match &field {
                Ok(f) => self.cals[c].fixed_yaw_of(i, cmd.param1 as f64, f),
                Err(e) => Err(e.clone()),
            };
            let label = self.cals[c].compass_label(i);
            match outcome {
                Ok(cal) => {
                    let id = self.cals[c].tracks[i].compass_id;
                    let text = format!(
                        "mag calibrated at a fixed yaw of {:.1} deg{label}: offset [{:.2}, {:.2}, {:.2}] uT",
                        cmd.param1, cal.offset[0], cal.offset[1], cal.offset[2]
                    );
                    let msg =
                        mavout::mag_cal_report_autosaved(id, mavout::compass_bit(id), &cal, true);
                    self.cals[c].install_mag(i, cal.clone());
                    self.cals[c].tracks[i].reported_mag = Some(cal);
                    self.send_mav(To::Cal(c), &[msg]).await;
                    self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
                        .await;
                    calibrated += 1;
                }
                Err(why) => {
                    let text = format!("fixed-yaw calibration refused{label}: {why}");
                    self.status_for(c, MavSeverity::MAV_SEVERITY_WARNING, text)
                        .await;
                }
            }
        }
        let result = if calibrated > 0 {
            MavResult::MAV_RESULT_ACCEPTED
        } else {
            MavResult::MAV_RESULT_FAILED
        };
        let ack = mavout::command_ack(cmd.command, result, frame.system_id, frame.component_id);
        self.send_mav(To::Cal(c), &[ack]).await;
        if calibrated > 0 {
            self.store_changed(c);
            if self.cfg.daemon.write_params {
                self.cals[c].start_param_write(self.cfg.daemon.param_target);
            }
        }
    }
}

/// What ArduPilot says when a fixed-yaw calibration at latitude and longitude 0 finds no position
/// (its `mag_cal_fixed_yaw`), word for word: ground stations show it as the reason.
const NO_POSITION_TEXT: &str = "Mag: no position available";

impl State {
    /// Where vehicle `c` is, for a fixed-yaw calibration given latitude and longitude 0: as
    /// ArduPilot takes its own position, the vehicle's newest fix (GLOBAL_POSITION_INT, or
    /// GPS_RAW_INT with a 3-D fix, as the primary's samples carry it); without one, `[place]`,
    /// the position the operator configured; `None` when neither is known.
    fn own_place(&self, c: usize) -> Option<crate::attitude::Place> {
        let fix = self.cals[c].tracks.iter().find_map(|t| t.position);
        match fix {
            Some(p) => Some(crate::attitude::Place {
                altitude_m: p.alt_m,
                ..crate::attitude::Place::at(p.lat_deg, p.lon_deg)
            }),
            None => self.cfg.place.clone(),
        }
    }
}

impl Cal {
    /// Track `i`'s magnetometer calibration from its latest samples at true yaw `yaw_deg` in
    /// `field` ([`crate::app::fixedyaw::calibrate`]): the offset found, the soft iron and model of
    /// the calibration in use kept. Err: why not, in words for the user.
    fn fixed_yaw_of(
        &self,
        i: usize,
        yaw_deg: f64,
        field: &crate::attitude::EarthField,
    ) -> Result<SensorCalibration, String> {
        let t = &self.tracks[i];
        if t.mag_run.collecting() {
            return Err(
                "a calibration run is in progress: cancel it first (MAVProxy `magcal cancel`)"
                    .into(),
            );
        }
        match t.recent_at.map(|at| at.elapsed().as_secs_f64()) {
            None => return Err("no magnetometer and accelerometer samples yet".into()),
            Some(age) if age > super::FIXED_YAW_MAX_AGE_S => {
                return Err(format!(
                    "the latest samples are {age:.1} s old (at most {} s): the data has stopped, so the vehicle's yaw now is not known",
                    super::FIXED_YAW_MAX_AGE_S
                ))
            }
            Some(_) => {}
        }
        let in_use = crate::app::fixedyaw::InUse {
            mag: self.in_use(i, Sensor::Mag),
            accel: self.in_use(i, Sensor::Accel),
        };
        let recent: Vec<(Vec3, Vec3)> = t.recent.iter().copied().collect();
        crate::app::fixedyaw::calibrate(&recent, &t.pipe, &in_use, yaw_deg, field, &FIXED_YAW)
            .map(|f| f.calibration)
            .map_err(|e| e.to_string())
    }

    /// Write every compass's calibration in use to the flight controller (`daemon.write_params`).
    pub(super) fn start_param_write(&mut self, convention: ParamTarget) {
        let params: Vec<_> = self
            .store
            .mags_ut()
            .iter()
            .flat_map(|c| {
                crate::calib::export::determined_mag_params(c, convention == ParamTarget::Px4)
            })
            .collect();
        if params.is_empty() {
            return;
        }
        self.writer = Some(ParamWriter::new(params, self.target.0, self.target.1));
    }
}

/// A track's fits; for the primary compass (`compass`: its number) also its mounting from the
/// static poses (against gravity, [`crate::calib::mounting`]): a calibration from a compass
/// mounted other than `orientation.sensor` is refused (failure `orientation`, the parameter to
/// set named) before it can be installed. Other compasses' mountings are not configured here.
fn fit_track(
    input: &crate::calib::pipeline::FitInput,
    cfg: &Config,
    compass: Option<usize>,
) -> FitResults {
    let mut r = fit_all(input, &cfg.calib());
    if let Some(index) = compass {
        let accel = r.accel.calibration;
        r.mag.check_mounting(
            accel.as_ref(),
            &input.poses,
            &[],
            None,
            &cfg.orientation.sensor,
            index,
        );
    }
    r
}

impl State {
    /// Start a fit of every track whose refit is due (`all`: of every track, with its last poses
    /// closed: the end of a replay), off the executor. With each track's snapshot goes a copy of
    /// its learnt readings ([`Track::ladder_job`]): when the sphere fit fails the job climbs the
    /// ladder on them too.
    pub(super) fn start_fits(&mut self, all: bool) -> tokio::task::JoinHandle<TrackFits> {
        let mut inputs = vec![];
        for c in 0..self.cals.len() {
            let onboard = self.cals[c]
                .vehicle
                .and_then(|v| self.vehicles[v].conv.ardupilot_onboard());
            for i in 0..self.cals[c].tracks.len() {
                let cal = &self.cals[c];
                let t = &cal.tracks[i];
                if !all && !t.refit_wanted {
                    continue;
                }
                let ladder = t.ladder_job(
                    t.vehicle_start(onboard.as_ref()),
                    cal.in_use(i, Sensor::Mag),
                );
                let t = &mut self.cals[c].tracks[i];
                if all {
                    t.pipe.finish_poses();
                }
                t.refit_wanted = false;
                let compass = (i == 0).then_some(t.compass_id as usize);
                inputs.push((
                    c,
                    i,
                    t.generation,
                    t.pipe.last_t,
                    t.pipe.snapshot(),
                    compass,
                    ladder,
                ));
            }
        }
        let cfg = self.cfg.clone();
        tokio::task::spawn_blocking(move || {
            inputs
                .into_iter()
                .map(|(c, i, generation, t, input, compass, ladder)| {
                    let r = fit_track(&input, &cfg, compass);
                    let live = ladder.filter(|_| ladder_stands_in(&r)).map(
                        |(points, start, incumbent)| {
                            Box::new(crate::calib::learn::climb_live(
                                &points,
                                start.as_ref(),
                                incumbent.as_ref(),
                            ))
                        },
                    );
                    (c, i, generation, t, r, live)
                })
                .collect()
        })
    }

    /// Fits came back: each goes to its track unless that track's run restarted meanwhile.
    pub(super) async fn fits_done(&mut self, r: Result<TrackFits, tokio::task::JoinError>) {
        match r {
            Ok(fits) => {
                for (c, i, generation, t, res, live) in fits {
                    if generation == self.cals[c].tracks[i].generation {
                        self.on_fit(c, i, t, res, live).await;
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

impl State {
    /// A block per instance of calibrated vehicle `c` for the report (empty with one): the
    /// primary's calibration is `primary`, the others' their latest fits.
    pub(super) fn instance_reports(
        &self,
        c: usize,
        primary: &crate::report::CalibrationReport,
    ) -> Vec<crate::report::InstanceReport> {
        let cal = &self.cals[c];
        if cal.tracks.len() < 2 {
            return Vec::new();
        }
        let infos = cal
            .vehicle
            .map(|v| self.vehicles[v].conv.instances())
            .unwrap_or_default();
        cal.tracks
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
                    samples: info.map_or(t.samples_in, |x| x.samples),
                    time: info.map(|x| x.time.clone()).unwrap_or_default(),
                    calibration,
                })
            })
            .collect()
    }
}
