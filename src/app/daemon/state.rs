//! The run loop's state between events: samples and frames in (vehicles, instances, clocks),
//! heading and attitude out, MAVLink and JSON sending.

use super::*;

impl Cal {
    pub(super) fn calibrator_from_store(
        store: &StoredCalibration,
        declination: Option<f64>,
    ) -> Calibrator {
        let mut c = Calibrator::empty(declination);
        c.mag = store.mag_cal();
        c.accel = store.accel_cal();
        c.gyro_bias = store
            .gyro
            .as_ref()
            .filter(|g| g.status == crate::report::CalStatus::Ok)
            .map(|g| g.bias);
        c
    }

    /// What the orientation filter has learnt, to save: once it has run or was given a state
    /// (before, there is nothing to save). A filter just restarted by a new magnetometer
    /// calibration has kept its bias but not yet learnt the new field's reference: it is saved
    /// without one.
    pub(super) fn filter_state(&self) -> Option<crate::attitude::fusion::FilterState> {
        if self.fusion.initialized() || self.filter_seeded {
            Some(self.fusion.state())
        } else {
            self.store.filter
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
}

impl State {
    pub(super) fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// Queue MAVLink messages for the live links `to` names; [`State::flush_mav`] sends them.
    pub(super) async fn send_mav(&mut self, to: To, msgs: &[MavMessage]) {
        for m in msgs {
            let bytes = match to {
                To::Cal(c) => self.cals[c].enc.encode(m),
                To::All | To::Link(_) => self.cals[0].enc.encode(m),
            };
            for l in 0..self.links.len() {
                let link = &self.links[l];
                let reaches = link.mavlink
                    && !link.replay
                    && match to {
                        To::All => true,
                        To::Link(k) => k == l,
                        To::Cal(c) => link.cals.is_empty() || link.cals.contains(&c),
                    };
                if !reaches {
                    continue;
                }
                if !link.out.is_empty() && link.out.len() + bytes.len() > MAV_DATAGRAM_MAX {
                    self.flush_link(l);
                }
                self.links[l].out.extend_from_slice(&bytes);
            }
        }
    }

    /// Send the queued MAVLink frames to each live link as one datagram (or write). A link whose
    /// queue is full loses it, counted in `outbound_dropped`.
    pub(super) fn flush_mav(&mut self) {
        for l in 0..self.links.len() {
            self.flush_link(l);
        }
    }

    fn flush_link(&mut self, l: usize) {
        let link = &mut self.links[l];
        if link.out.is_empty() {
            return;
        }
        let datagram = std::mem::replace(&mut link.out, Vec::with_capacity(MAV_DATAGRAM_MAX));
        if link.handle.outbound.try_send(datagram).is_err() {
            link.outbound_queue_full += 1;
            link.handle
                .counters
                .outbound_dropped
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }

    /// Our HEARTBEAT on every live MAVLink link, and one for each further vehicle with the ids it
    /// is spoken for with.
    pub(super) async fn send_heartbeat(&mut self) {
        if self.links.iter().any(|l| l.mavlink && !l.replay) {
            self.send_mav(To::All, &[mavout::heartbeat()]).await;
            for c in 1..self.cals.len() {
                self.send_mav(To::Cal(c), &[mavout::heartbeat()]).await;
            }
        }
    }

    /// Queue a JSON line for every consumer (never waits: a full queue drops it, counted).
    pub(super) async fn send_json(&mut self, ev: &LiveEvent) {
        self.send_json_for(0, ev).await
    }

    /// Queue a JSON line about calibrated vehicle `c` (lines about a further vehicle say which).
    pub(super) async fn send_json_for(&mut self, c: usize, ev: &LiveEvent) {
        if self.sinks.is_empty() {
            return;
        }
        let tag = self.vehicle_tag(c);
        let line: std::sync::Arc<str> = mavout::json_line_for(ev, tag.as_ref()).into();
        for s in &self.sinks {
            s.send(&line);
        }
    }

    /// A JSON `status` line (and a log line) for each consumer that lost lines since the last
    /// time, and for each link whose outbound queue was full (not for datagrams a link could not
    /// send: a udpin link has no peer until one sends, and the HEARTBEAT goes out regardless).
    pub(super) async fn report_drops(&mut self) {
        let mut said = vec![];
        for s in self.sinks.iter_mut() {
            let lost = s.lost();
            if lost > s.lost_reported {
                let r = s.report();
                said.push(format!(
                    "JSON consumer {}: {} lines dropped since the last report, {} in all ({} with its queue full, {} not delivered), {} sent",
                    s.label,
                    lost - s.lost_reported,
                    lost,
                    r.queue_full,
                    r.not_delivered,
                    r.sent
                ));
                s.lost_reported = lost;
            }
        }
        for l in self.links.iter_mut() {
            let n = l.outbound_queue_full;
            if n > l.queue_full_reported {
                said.push(format!(
                    "{}: {} MAVLink datagrams dropped with its outbound queue full since the last report ({} in all)",
                    l.label,
                    n - l.queue_full_reported,
                    n
                ));
                l.queue_full_reported = n;
            }
        }
        for text in said {
            tracing::warn!("{text}");
            self.send_json(&LiveEvent::Status {
                level: severity_name(MavSeverity::MAV_SEVERITY_WARNING).into(),
                text,
            })
            .await;
        }
    }

    /// What the outputs could not deliver, for the report.
    pub(super) fn outputs_report(&self) -> crate::report::OutputsReport {
        crate::report::OutputsReport {
            json_sinks: self.sinks.iter().map(Sink::report).collect(),
            links: self
                .links
                .iter()
                .map(|l| crate::report::LinkOutputReport {
                    link: l.label.clone(),
                    outbound_dropped: l
                        .handle
                        .counters
                        .outbound_dropped
                        .load(std::sync::atomic::Ordering::Relaxed),
                    outbound_queue_full: l.outbound_queue_full,
                })
                .collect(),
        }
    }

    pub(super) async fn status(&mut self, severity: MavSeverity, text: String) {
        status_trace(severity, &text);
        let msgs = mavout::statustext(severity, &text);
        self.send_mav(To::All, &msgs).await;
        self.send_json(&LiveEvent::Status {
            level: severity_name(severity).into(),
            text,
        })
        .await;
    }

    /// A STATUSTEXT and JSON `status` line about calibrated vehicle `c`, sent for it.
    pub(super) async fn status_for(&mut self, c: usize, severity: MavSeverity, text: String) {
        if c == 0 {
            return self.status(severity, text).await;
        }
        status_trace(
            severity,
            &format!("vehicle {}: {text}", self.vehicle_name(c)),
        );
        let msgs = mavout::statustext(severity, &text);
        self.send_mav(To::Cal(c), &msgs).await;
        let ev = LiveEvent::Status {
            level: severity_name(severity).into(),
            text,
        };
        self.send_json_for(c, &ev).await;
    }

    /// What JSON lines about calibrated vehicle `c` carry to say which vehicle: nothing for the
    /// first (its lines are as with one vehicle), its link and system id for a further one.
    pub(super) fn vehicle_tag(&self, c: usize) -> Option<mavout::VehicleTag> {
        if c == 0 {
            return None;
        }
        let v = &self.vehicles[self.cals[c].vehicle?];
        Some(mavout::VehicleTag {
            link: self
                .links
                .get(v.key.0)
                .map(|l| l.label.clone())
                .unwrap_or_default(),
            system_id: v.key.1,
        })
    }

    /// `link 1 (udpin:...) system 2`, for the log.
    pub(super) fn vehicle_name(&self, c: usize) -> String {
        match self.vehicle_tag(c) {
            Some(t) => format!("{} system {}", t.link, t.system_id),
            None => "first".into(),
        }
    }

    /// A sample of calibrated vehicle `c`'s primary instance: calibrated for the heading and
    /// attitude, and pushed (a refit due is marked on the track).
    pub(super) fn on_sample(&mut self, c: usize, s: Sample) {
        let every = self.cfg.daemon.attitude_every_samples;
        let cal = &mut self.cals[c];
        let Some(s) = cal.tracks[0].take(&s) else {
            return;
        };
        cal.tracks[0].push(&s);
        let body = cal.tracks[0].pipe.to_body(&s);
        if body.mag_ut.is_some() {
            cal.last_body_mag = body.mag_ut;
        }
        // The angles are taken of the means at the heading rate (`publish_heading`), not per sample.
        let v = cal.calibrator.apply_vectors(&body);
        cal.window.add(&v);
        cal.fuse(&v);
        cal.latest = Some(v);
        if every > 0 {
            cal.samples_since_attitude += 1;
            if cal.samples_since_attitude >= every {
                cal.samples_since_attitude = 0;
                cal.attitude_due = true;
            }
        }
    }

    /// A sample from a link that times its own samples (text lines: the time they were read, or
    /// their own `t` column), through that link's clock, taken as a receive clock (lines read
    /// together share a time, and a still sensor's lines can repeat: none is dropped).
    pub(super) fn stamp(&mut self, link: usize, mut s: Sample) -> Sample {
        if self.links.get(link).is_some_and(|l| l.replay) {
            // Already timed: a file's samples by its reader's clock; the simulator's are ours.
            return s;
        }
        if self.sample_clocks.len() <= link {
            let fresh = SourceClock::new(ClockSettings::default());
            self.sample_clocks.resize(link + 1, fresh);
        }
        let c =
            self.sample_clocks[link].stamp(None, Some(crate::io::clock::us_from_s(s.t_s)), None);
        (s.t_s, s.segment) = (c.t_s, c.segment);
        s
    }

    /// The fused attitude as ATTITUDE_QUATERNION and/or ATTITUDE (per `daemon.attitude_message`) and a
    /// JSON `attitude` line, once the filter has its tilt and its heading.
    pub(super) async fn publish_attitudes(&mut self) {
        for c in 0..self.cals.len() {
            self.publish_attitude(c).await;
        }
    }

    /// Calibrated vehicle `c`'s attitude (see [`State::publish_attitudes`]).
    pub(super) async fn publish_attitude(&mut self, c: usize) {
        let cal = &mut self.cals[c];
        let mean_rates = cal.attitude_rates.take();
        if !(cal.fusion.initialized() && cal.fusion.mag_reference().is_some()) {
            return;
        }
        let o = cal.fusion.orientation();
        let q = [o.q.w, o.q.i, o.q.j, o.q.k];
        if !q.iter().all(|c| c.is_finite()) {
            return;
        }
        // Body rates: the calibrated gyro less the filter's residual bias estimate.
        let residual_bias = cal.fusion.bias();
        let rates_rad_s = mean_rates.map_or([0.0; 3], |r| {
            [
                r[0] - residual_bias[0],
                r[1] - residual_bias[1],
                r[2] - residual_bias[2],
            ]
        });
        let t_ms = (self.start.elapsed().as_secs_f64() * 1000.0) as u32;
        let mut msgs = vec![];
        let which: AttitudeMessage = self.cfg.daemon.attitude_message;
        if which.quaternion() {
            msgs.extend(mavout::attitude_quaternion(t_ms, q, rates_rad_s));
        }
        if which.euler() {
            msgs.extend(mavout::attitude_from_quaternion(t_ms, q, rates_rad_s));
        }
        self.send_mav(To::Cal(c), &msgs).await;
        let cal = &self.cals[c];
        let stored_bias = cal.calibrator.gyro_bias.unwrap_or([0.0; 3]);
        let ev = LiveEvent::Attitude {
            t: cal.latest.map_or(cal.tracks[0].pipe.last_t, |l| l.t_s),
            q,
            roll_deg: o.roll_deg,
            pitch_deg: o.pitch_deg,
            heading_deg: o.heading_deg,
            true_heading: self.declination.is_some(),
            gyro_bias_rad_s: [
                stored_bias[0] + residual_bias[0],
                stored_bias[1] + residual_bias[1],
                stored_bias[2] + residual_bias[2],
            ],
            mag_disturbed: cal.fusion.mag_disturbed(),
        };
        self.send_json_for(c, &ev).await;
    }

    /// The vehicle a frame comes from: its link and system id (every link is one vehicle with
    /// `daemon.links = "merged"`), taken on when first heard.
    pub(super) fn vehicle(&mut self, link: usize, system_id: u8) -> usize {
        let key = if self.cfg.daemon.links == Links::Merged {
            (0, 0)
        } else {
            (link, system_id)
        };
        if let Some(v) = self.vehicles.iter().position(|v| v.key == key) {
            return v;
        }
        self.vehicles.push(Vehicle {
            key,
            conv: self.new_converter.clone(),
            cal: None,
            announced: false,
            identity: None,
            hardware: Default::default(),
        });
        self.vehicles.len() - 1
    }

    /// The calibration of vehicle `v`, whose IMU data arrived on `link`: the first vehicle takes
    /// calibrated vehicle 0, each further one a calibration of its own (resumed from its
    /// directory). `None` (counted) past [`MAX_CALIBRATED_VEHICLES`] or when its stored
    /// calibration cannot be read (it is left as it is).
    pub(super) async fn cal_of(&mut self, v: usize, link: usize) -> Option<usize> {
        let c = match self.vehicles[v].cal {
            Some(c) => c,
            None => {
                let c = self.new_cal(v).await?;
                self.vehicles[v].cal = Some(c);
                c
            }
        };
        if let Some(l) = self.links.get_mut(link) {
            if !l.cals.contains(&c) {
                l.cals.push(c);
            }
        }
        Some(c)
    }

    async fn new_cal(&mut self, v: usize) -> Option<usize> {
        let (link, system_id) = self.vehicles[v].key;
        let label = self
            .links
            .get(link)
            .map(|l| l.label.clone())
            .unwrap_or_default();
        let me = StoredVehicle {
            link: label.clone(),
            system_id,
            source: VehicleSource::Vehicle,
            hardware: self.vehicles[v].hardware.clone(),
        };
        if self.takes_first(&me) {
            return Some(self.take_first(v, me).await);
        }
        let refuse = |why: String| {
            format!("{label}: IMU data of a further vehicle (system {system_id}): not calibrated, {why}")
        };
        if self.cals.len() >= MAX_CALIBRATED_VEHICLES {
            self.other_vehicle_samples += 1;
            if !std::mem::replace(&mut self.vehicles[v].announced, true) {
                let text = refuse(format!("{MAX_CALIBRATED_VEHICLES} vehicles are already"));
                self.status(MavSeverity::MAV_SEVERITY_WARNING, text).await;
            }
            return None;
        }
        // Kept by its hardware when the link names it, else by its link and system id.
        let name = me
            .hardware
            .tag()
            .unwrap_or_else(|| format!("vehicle-{link}-{system_id}"));
        let dir = PathBuf::from(&self.cfg.daemon.calibration_dir).join(name);
        let d = &self.cfg.daemon;
        let own = mavout::OwnIds {
            system_id,
            component_id: d.component_id,
        };
        let target = (system_id, d.target_component);
        let made = load_store(&dir).and_then(|store| {
            let store = store
                .filter(|s| s.vehicle.as_ref().is_none_or(|s| same_kind(s, &me)))
                .unwrap_or_else(StoredCalibration::empty);
            Cal::new(&self.cfg, store, dir.clone(), own, target, self.declination)
        });
        let mut cal = match made {
            Ok(cal) => cal,
            Err(e) => {
                self.other_vehicle_samples += 1;
                if !std::mem::replace(&mut self.vehicles[v].announced, true) {
                    self.status(MavSeverity::MAV_SEVERITY_ERROR, refuse(e.to_string()))
                        .await;
                }
                return None;
            }
        };
        cal.vehicle = Some(v);
        let resumed = resumed_from(&cal.store, &dir);
        cal.store.vehicle = Some(me);
        self.cals.push(cal);
        let c = self.cals.len() - 1;
        let text = format!(
            "{label}: a further vehicle (system {system_id}), calibrated on its own in {}{}",
            dir.display(),
            resumed.map(|r| format!(" ({r})")).unwrap_or_default()
        );
        self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
            .await;
        Some(c)
    }

    /// Whether vehicle `me` takes calibrated vehicle 0 (the configured directory): always with
    /// merged links; never while a simulator feeds it; else when it is free and its stored
    /// calibration names no vehicle, a simulator (not resumed: [`State::take_first`]), or `me`
    /// ([`resumable`]).
    fn takes_first(&self, me: &StoredVehicle) -> bool {
        if self.cfg.daemon.links == Links::Merged {
            return true;
        }
        let cal0 = &self.cals[0];
        if cal0.vehicle.is_some() || self.links.iter().any(|l| l.simulator) {
            return false;
        }
        let configured = |l: &str| self.links.iter().any(|k| k.label == l);
        cal0.store.vehicle.as_ref().is_none_or(|s| {
            s.source == VehicleSource::Simulator || resumable(s, me, !configured(&s.link))
        })
    }

    /// Vehicle `v` takes calibrated vehicle 0: a simulator's calibration there is dropped (said),
    /// a vehicle's is resumed (said, with when it was written).
    async fn take_first(&mut self, v: usize, me: StoredVehicle) -> usize {
        let merged = self.cfg.daemon.links == Links::Merged;
        let was = self.cals[0].store.vehicle.clone();
        let described = me.describe();
        if was
            .as_ref()
            .is_some_and(|s| s.source == VehicleSource::Simulator)
        {
            let fresh = Cal::new(
                &self.cfg,
                StoredCalibration::empty(),
                self.cals[0].cal_dir.clone(),
                self.cals[0].own,
                self.cals[0].target,
                self.declination,
            );
            if let Ok(fresh) = fresh {
                self.cals[0] = fresh;
            }
            let text = format!(
                "{described}: the simulator's calibration in {} is not resumed onto a vehicle; calibrating from scratch",
                self.cals[0].cal_dir.display()
            );
            self.status(MavSeverity::MAV_SEVERITY_WARNING, text).await;
            // The directory now holds the vehicle's record (and its calibration once made).
            self.cals[0].store.vehicle = Some(me.clone());
            self.save(0).await;
        } else if let Some(r) = resumed_from(&self.cals[0].store, &self.cals[0].cal_dir) {
            let text = format!("{described}: {r}");
            self.status(MavSeverity::MAV_SEVERITY_INFO, text).await;
        }
        let cal0 = &mut self.cals[0];
        cal0.vehicle = Some(v);
        if !merged {
            cal0.store.vehicle = Some(me);
        }
        0
    }

    /// Whether a frame from these ids is our own, echoed back: the ids we speak for any
    /// calibrated vehicle with.
    fn is_own(&self, system_id: u8, component_id: u8) -> bool {
        self.cals
            .iter()
            .any(|c| c.own.is_own(system_id, component_id))
    }

    /// A frame from a MAVLink link: heartbeats and parameters steer, IMU messages become samples.
    /// Our own frames echoed back (a router, a looped link) are dropped and counted.
    pub(super) async fn on_frame(
        &mut self,
        link: usize,
        frame: &crate::io::decode::Frame,
        time_us: u64,
    ) {
        if self.is_own(frame.system_id, frame.component_id) {
            self.own_echo += 1;
            return;
        }
        match &frame.message {
            MavMessage::HEARTBEAT(_) => {
                self.note_autopilot(frame.system_id, &frame.message);
                let v = self.vehicle(link, frame.system_id);
                let from = (frame.system_id, frame.component_id);
                self.identity_heartbeat(v, link, from, &frame.message).await;
                let conv = &mut self.vehicles[v].conv;
                let was = conv.is_ardupilot();
                // An onboard computer's HEARTBEAT speaks for no flight stack.
                if frame.component_id != 191 {
                    conv.convert_any(&frame.message, time_us);
                }
                if !was && conv.is_ardupilot() {
                    if self.cfg.daemon.ardupilot_corrected_mag == ArdupilotCorrectedMag::Undo {
                        self.status(MavSeverity::MAV_SEVERITY_INFO, "ArduPilot link: reading COMPASS_* to undo its calibration before fitting".into()).await;
                        let reqs = mavout::param_request_reads(frame.system_id, frame.component_id);
                        self.send_mav(To::Link(link), &reqs).await;
                    } else {
                        self.status(MavSeverity::MAV_SEVERITY_WARNING, "ArduPilot link: its magnetometer data is already calibrated; set daemon.ardupilot_corrected_mag = \"undo\" to fit it".into()).await;
                    }
                }
            }
            MavMessage::COMMAND_LONG(c) => {
                self.on_command(link, frame, c).await;
            }
            MavMessage::PARAM_REQUEST_LIST(_)
            | MavMessage::PARAM_REQUEST_READ(_)
            | MavMessage::PARAM_SET(_) => {
                self.on_param_request(&frame.message).await;
            }
            MavMessage::FILE_TRANSFER_PROTOCOL(d) => {
                self.on_ftp(frame.system_id, frame.component_id, d).await;
            }
            MavMessage::AUTOPILOT_VERSION(_) => {
                let v = self.vehicle(link, frame.system_id);
                self.identity_message(v, &frame.message).await;
            }
            MavMessage::PARAM_VALUE(_) => {
                let v = self.vehicle(link, frame.system_id);
                self.identity_message(v, &frame.message).await;
                self.vehicles[v].conv.convert_any(&frame.message, time_us);
                for c in self.cals.iter_mut() {
                    if c.target.0 == frame.system_id {
                        if let Some(w) = c.writer.as_mut() {
                            w.absorb(&frame.message);
                        }
                    }
                }
            }
            _ => {
                let v = self.vehicle(link, frame.system_id);
                let Some((k, s)) = self.vehicles[v].conv.convert_any(&frame.message, time_us)
                else {
                    return;
                };
                let Some(c) = self.cal_of(v, link).await else {
                    return;
                };
                let Some(track) = self.track_of(c, k).await else {
                    return;
                };
                self.on_vehicle_sample(c, track, s);
            }
        }
    }

    /// A sample of calibrated vehicle `c`'s track `track` (an ArduPilot vehicle's magnetometer
    /// reading already has its onboard calibration undone by the converter, or is held back
    /// until its parameters are known). A refit due is marked on the track (`refit_wanted`).
    fn on_vehicle_sample(&mut self, c: usize, track: usize, s: Sample) {
        if track == 0 {
            self.on_sample(c, s);
        } else {
            let t = &mut self.cals[c].tracks[track];
            if let Some(m) = t.take(&s) {
                t.push(&m);
            }
        }
    }

    /// The track of instance `k` of calibrated vehicle `c`: track 0 for its primary (named on
    /// its first sample), a new track for a further instance. `None` (counted) past
    /// [`crate::io::decode::MAX_INSTANCES`] tracks or when a pipeline cannot be made.
    pub(super) async fn track_of(&mut self, c: usize, k: usize) -> Option<usize> {
        let cal = &mut self.cals[c];
        if let Some(t) = cal.tracks.iter().position(|t| t.instance == Some(k)) {
            return Some(t);
        }
        let conv = &self.vehicles[cal.vehicle?].conv;
        let info = conv.instances().get(k).cloned()?;
        if conv.primary_index() == Some(k) {
            let t0 = &mut cal.tracks[0];
            (t0.instance, t0.name, t0.compass_id) = (Some(k), info.name, info.compass_id);
            cal.store.compass_id = info.compass_id;
            return Some(0);
        }
        if cal.tracks.len() >= crate::io::decode::MAX_INSTANCES {
            self.other_instance_samples += 1;
            return None;
        }
        let mut t = match Track::new(&self.cfg, Some(k), info.name.clone(), info.compass_id) {
            Ok(t) => t,
            Err(e) => {
                tracing::error!("instance {} not calibrated: {e}", info.name);
                self.other_instance_samples += 1;
                return None;
            }
        };
        t.pipe.mag_units = info.units.mag;
        t.pipe.gyro_units = info.units.gyro;
        cal.tracks.push(t);
        let n = cal.tracks.len();
        let text = format!(
            "{}: a further IMU instance (compass {}), calibrated on its own",
            info.name, info.compass_id
        );
        self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
            .await;
        Some(n - 1)
    }

    /// The heading cadence: each vehicle's heading, and the next messages of a parameter write
    /// in progress.
    pub(super) async fn on_heading_tick(&mut self) {
        for c in 0..self.cals.len() {
            self.publish_heading(c).await;
            self.param_write_step(c).await;
        }
    }

    async fn param_write_step(&mut self, c: usize) {
        let now = self.now_s();
        let Some(w) = self.cals[c].writer.as_mut() else {
            return;
        };
        let msgs = w.next_messages(now);
        let done = w.done();
        let failed = w.failed();
        self.send_mav(To::Cal(c), &msgs).await;
        if done {
            self.cals[c].writer = None;
            if failed.is_empty() {
                let text = "parameters written and confirmed by the flight controller".into();
                self.status_for(c, MavSeverity::MAV_SEVERITY_INFO, text)
                    .await;
            } else {
                let text = format!("parameters not confirmed: {}", failed.join(", "));
                self.status_for(c, MavSeverity::MAV_SEVERITY_ERROR, text)
                    .await;
            }
        }
    }

    pub(super) async fn publish_heading(&mut self, c: usize) {
        let declination = self.declination;
        let cal = &mut self.cals[c];
        // The mean of the calibrated vectors since the last publication (decimation with averaging).
        let Some(mut v) = cal.latest else { return };
        match cal.window.take(declination) {
            Some(m) => v = Calibrated { t_s: v.t_s, ..m },
            // Nothing new since the last time: the latest sample again, with its angles.
            None => cal.calibrator.add_attitude(&mut v),
        }
        let t_ms = (self.now_s() * 1000.0) as u32;
        let mut msgs = vec![];
        if let (Some(r), Some(p)) = (v.roll_deg, v.pitch_deg) {
            match (self.cfg.daemon.heading_message, v.heading_deg) {
                (HeadingMessage::NamedValueFloat, Some(h)) => {
                    msgs.push(mavout::named_float("HEADING", t_ms, h as f32))
                }
                (HeadingMessage::Attitude, Some(h)) => msgs.push(mavout::attitude(t_ms, r, p, h)),
                _ => {}
            }
        }
        if self.cfg.daemon.debug_vect {
            let f = |v: Vec3| [v[0] as f32, v[1] as f32, v[2] as f32];
            let t_us = (self.now_s() * 1e6) as u64;
            if let Some(m) = v.mag_ut {
                msgs.push(mavout::debug_vect("MAG_UT", t_us, f(m)));
            }
            if let Some(a) = v.accel_mps2 {
                msgs.push(mavout::debug_vect("ACC_MPS2", t_us, f(a)));
            }
        }
        self.send_mav(To::Cal(c), &msgs).await;
        if let (Some(r), Some(p), Some(h)) = (v.roll_deg, v.pitch_deg, v.heading_deg) {
            let ev = LiveEvent::Heading {
                t: v.t_s,
                roll_deg: r,
                pitch_deg: p,
                heading_deg: h,
                true_heading: declination.is_some(),
            };
            self.send_json_for(c, &ev).await;
        }
        let ev = LiveEvent::Calibrated {
            t: v.t_s,
            accel_mps2: v.accel_mps2,
            gyro_rad_s: v.gyro_rad_s,
            mag_ut: v.mag_ut,
        };
        self.send_json_for(c, &ev).await;
    }
}

impl Cal {
    /// Feed a calibrated sample (body axes, stored gyro bias removed) to the orientation filter.
    /// A gyro still in counts (no scale known) is left out: the filter then runs on accel and mag.
    pub(super) fn fuse(&mut self, c: &Calibrated) {
        let gyro = c
            .gyro_rad_s
            .filter(|_| self.tracks[0].pipe.gyro_units == Unit::Si);
        if c.accel_mps2.is_none() && gyro.is_none() && c.mag_ut.is_none() {
            return;
        }
        let s = Sample {
            gyro_rad_s: gyro,
            ..c.as_sample()
        };
        self.fusion.update_sample(&s, FUSION_DEFAULT_DT_S);
        if let Some(g) = gyro.filter(crate::types::is_finite3) {
            self.attitude_rates.add(&g);
        }
    }
}

/// A status line for the operator, whatever the outputs: under the tracing target
/// [`crate::types::STATUS_TARGET`] (the binary shows it on stderr), at the level of its MAVLink severity.
fn status_trace(severity: MavSeverity, text: &str) {
    match severity {
        MavSeverity::MAV_SEVERITY_EMERGENCY
        | MavSeverity::MAV_SEVERITY_ALERT
        | MavSeverity::MAV_SEVERITY_CRITICAL
        | MavSeverity::MAV_SEVERITY_ERROR => {
            tracing::error!(target: crate::types::STATUS_TARGET, "{text}")
        }
        MavSeverity::MAV_SEVERITY_WARNING => {
            tracing::warn!(target: crate::types::STATUS_TARGET, "{text}")
        }
        _ => tracing::info!(target: crate::types::STATUS_TARGET, "{text}"),
    }
}
