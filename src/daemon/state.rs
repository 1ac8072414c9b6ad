//! The run loop's state between events: samples and frames in (vehicles, instances, clocks),
//! heading and attitude out, MAVLink and JSON sending.

use super::*;

impl State {
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
    pub(super) fn filter_state(&self) -> Option<crate::fusion::FilterState> {
        if self.fusion.initialized() || self.filter_seeded {
            Some(self.fusion.state())
        } else {
            self.store.filter
        }
    }

    pub(super) fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// Queue MAVLink messages for the live links; [`State::flush_mav`] sends them.
    pub(super) async fn send_mav(&mut self, msgs: &[MavMessage]) {
        for m in msgs {
            let bytes = self.enc.encode(m);
            if !self.mav_out.is_empty() && self.mav_out.len() + bytes.len() > MAV_DATAGRAM_MAX {
                self.flush_mav();
            }
            self.mav_out.extend_from_slice(&bytes);
        }
    }

    /// Send the queued MAVLink frames to each live link as one datagram (or write). A link whose
    /// queue is full loses it, counted in `outbound_dropped`.
    pub(super) fn flush_mav(&mut self) {
        if self.mav_out.is_empty() {
            return;
        }
        for l in self.links.iter_mut().filter(|l| l.mavlink && !l.replay) {
            if l.handle.outbound.try_send(self.mav_out.clone()).is_err() {
                l.outbound_queue_full += 1;
                l.handle
                    .counters
                    .outbound_dropped
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
        self.mav_out.clear();
    }

    /// Our HEARTBEAT on every live MAVLink link.
    pub(super) async fn send_heartbeat(&mut self) {
        if self.links.iter().any(|l| l.mavlink && !l.replay) {
            self.send_mav(&[mavout::heartbeat()]).await;
        }
    }

    /// Queue a JSON line for every consumer (never waits: a full queue drops it, counted).
    pub(super) async fn send_json(&mut self, ev: &LiveEvent) {
        if self.sinks.is_empty() {
            return;
        }
        let line: std::sync::Arc<str> = mavout::json_line(ev).into();
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
                level: severity_name(4).into(),
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

    pub(super) async fn status(&mut self, severity: u8, text: String) {
        tracing::info!("{text}");
        let msgs = mavout::statustext(severity, &text);
        self.send_mav(&msgs).await;
        self.send_json(&LiveEvent::Status {
            level: severity_name(severity).into(),
            text,
        })
        .await;
    }

    /// A sample of the primary instance: calibrated for the heading and attitude, and pushed.
    pub(super) fn on_sample(&mut self, s: Sample) -> bool {
        let due = self.tracks[0].push(&s);
        let body = self.tracks[0].pipe.to_body(&s);
        if body.mag_ut.is_some() {
            self.last_body_mag = body.mag_ut;
        }
        // The angles are taken of the means at the heading rate (`publish_heading`), not per sample.
        let c = self.calibrator.apply_vectors(&body);
        self.window.add(&c);
        self.fuse(&c);
        self.latest = Some(c);
        let every = self.cfg.daemon.attitude_every_samples;
        if every > 0 {
            self.samples_since_attitude += 1;
            if self.samples_since_attitude >= every {
                self.samples_since_attitude = 0;
                self.attitude_due = true;
            }
        }
        due
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
        let c = self.sample_clocks[link].stamp(None, Some(crate::clock::us_from_s(s.t_s)), None);
        (s.t_s, s.segment) = (c.t_s, c.segment);
        s
    }

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

    /// The fused attitude as ATTITUDE_QUATERNION and/or ATTITUDE (per `daemon.attitude_message`) and a
    /// JSON `attitude` line, once the filter has its tilt and its heading.
    pub(super) async fn publish_attitude(&mut self) {
        let mean_rates = self.attitude_rates.take();
        if !(self.fusion.initialized() && self.fusion.mag_reference().is_some()) {
            return;
        }
        let o = self.fusion.orientation();
        let q = [o.q.w, o.q.i, o.q.j, o.q.k];
        if !q.iter().all(|c| c.is_finite()) {
            return;
        }
        // Body rates: the calibrated gyro less the filter's residual bias estimate.
        let residual_bias = self.fusion.bias();
        let rates_rad_s = mean_rates.map_or([0.0; 3], |r| {
            [
                r[0] - residual_bias[0],
                r[1] - residual_bias[1],
                r[2] - residual_bias[2],
            ]
        });
        let t_ms = (self.now_s() * 1000.0) as u32;
        let mut msgs = vec![];
        let which: AttitudeMessage = self.cfg.daemon.attitude_message;
        if which.quaternion() {
            msgs.extend(mavout::attitude_quaternion(t_ms, q, rates_rad_s));
        }
        if which.euler() {
            msgs.extend(mavout::attitude_from_quaternion(t_ms, q, rates_rad_s));
        }
        self.send_mav(&msgs).await;
        let stored_bias = self.calibrator.gyro_bias.unwrap_or([0.0; 3]);
        let ev = LiveEvent::Attitude {
            t: self.latest.map_or(self.tracks[0].pipe.last_t, |c| c.t_s),
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
            mag_disturbed: self.fusion.mag_disturbed(),
        };
        self.send_json(&ev).await;
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
            ardupilot: false,
            ap_params: ApCompassParams::default(),
            announced: false,
        });
        self.vehicles.len() - 1
    }

    /// A frame from a MAVLink link: heartbeats and parameters steer, IMU messages become samples.
    /// Our own frames echoed back (a router, a looped link) are dropped and counted.
    pub(super) async fn on_frame(
        &mut self,
        link: usize,
        frame: &crate::decode::Frame,
        time_us: u64,
    ) -> bool {
        if self.own.is_own(frame.system_id, frame.component_id) {
            self.own_echo += 1;
            return false;
        }
        match &frame.message {
            MavMessage::HEARTBEAT(h) => {
                let v = self.vehicle(link, frame.system_id);
                if h.autopilot == MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA
                    && !self.vehicles[v].ardupilot
                    && frame.component_id != 191
                {
                    self.vehicles[v].ardupilot = true;
                    if self.cfg.daemon.ardupilot_corrected_mag == ArdupilotCorrectedMag::Undo {
                        self.status(6, "ArduPilot link: reading COMPASS_* to undo its calibration before fitting".into()).await;
                        let reqs = mavout::param_request_reads(frame.system_id, frame.component_id);
                        self.send_mav(&reqs).await;
                    } else {
                        self.status(4, "ArduPilot link: its magnetometer data is already calibrated; set daemon.ardupilot_corrected_mag = \"undo\" to fit it".into()).await;
                    }
                }
                false
            }
            MavMessage::COMMAND_LONG(c) => {
                self.on_command(frame, c).await;
                false
            }
            MavMessage::PARAM_VALUE(_) => {
                let v = self.vehicle(link, frame.system_id);
                self.vehicles[v].ap_params.absorb(&frame.message);
                if let Some(w) = self.writer.as_mut() {
                    w.absorb(&frame.message);
                }
                false
            }
            _ => {
                let v = self.vehicle(link, frame.system_id);
                let Some((k, mut s)) = self.vehicles[v].conv.convert_any(&frame.message, time_us)
                else {
                    return false;
                };
                if *self.primary_vehicle.get_or_insert(v) != v {
                    self.other_vehicle_samples += 1;
                    if !std::mem::replace(&mut self.vehicles[v].announced, true) {
                        let (l, sys) = self.vehicles[v].key;
                        let label = self
                            .links
                            .get(l)
                            .map(|x| x.label.clone())
                            .unwrap_or_default();
                        self.status(4, format!("{label}: IMU data of a second vehicle (system {sys}): not calibrated; one vehicle is, the first heard (daemon.links = \"merged\" takes every link as one vehicle)")).await;
                    }
                    return false;
                }
                let Some(track) = self.track_of(k).await else {
                    return false;
                };
                let vh = &self.vehicles[v];
                if vh.ardupilot {
                    if let Some(m) = s.mag_ut {
                        s.mag_ut = if self.cfg.daemon.ardupilot_corrected_mag
                            == ArdupilotCorrectedMag::Undo
                        {
                            vh.ap_params.undo(self.tracks[track].compass_id, m)
                        } else {
                            None
                        };
                        if s.mag_ut.is_none() {
                            self.mag_awaiting_params += 1;
                        }
                    }
                }
                if track == 0 {
                    self.on_sample(s)
                } else {
                    self.tracks[track].push(&s)
                }
            }
        }
    }

    /// The track of instance `k` of the calibrated vehicle: track 0 for its primary (named on its
    /// first sample), a new track for a further instance. `None` (counted) past
    /// [`crate::decode::MAX_INSTANCES`] tracks or when a pipeline cannot be made.
    pub(super) async fn track_of(&mut self, k: usize) -> Option<usize> {
        if let Some(t) = self.tracks.iter().position(|t| t.instance == Some(k)) {
            return Some(t);
        }
        let v = self.primary_vehicle?;
        let conv = &self.vehicles[v].conv;
        let info = conv.instances().get(k).cloned()?;
        if conv.primary_index() == Some(k) {
            let t0 = &mut self.tracks[0];
            (t0.instance, t0.name, t0.compass_id) = (Some(k), info.name, info.compass_id);
            self.store.compass_id = info.compass_id;
            return Some(0);
        }
        if self.tracks.len() >= crate::decode::MAX_INSTANCES {
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
        self.tracks.push(t);
        let text = format!(
            "{}: a further IMU instance (compass {}), calibrated on its own",
            info.name, info.compass_id
        );
        self.status(6, text).await;
        Some(self.tracks.len() - 1)
    }

    /// The heading cadence: the heading, and the next messages of a parameter write in progress.
    pub(super) async fn on_heading_tick(&mut self) {
        self.publish_heading().await;
        if let Some(w) = self.writer.as_mut() {
            let now = self.start.elapsed().as_secs_f64();
            let msgs = w.next_messages(now);
            let done = w.done();
            let failed = w.failed();
            self.send_mav(&msgs).await;
            if done {
                self.writer = None;
                if failed.is_empty() {
                    self.status(
                        6,
                        "parameters written and confirmed by the flight controller".into(),
                    )
                    .await;
                } else {
                    self.status(
                        3,
                        format!("parameters not confirmed: {}", failed.join(", ")),
                    )
                    .await;
                }
            }
        }
    }

    pub(super) async fn publish_heading(&mut self) {
        // The mean of the calibrated vectors since the last publication (decimation with averaging).
        let Some(mut c) = self.latest else { return };
        match self.window.take(self.declination) {
            Some(m) => c = Calibrated { t_s: c.t_s, ..m },
            // Nothing new since the last time: the latest sample again, with its angles.
            None => self.calibrator.add_attitude(&mut c),
        }
        let t_ms = (self.now_s() * 1000.0) as u32;
        let mut msgs = vec![];
        if let (Some(r), Some(p)) = (c.roll_deg, c.pitch_deg) {
            match (self.cfg.daemon.heading_message, c.heading_deg) {
                (HeadingMessage::NamedValueFloat, Some(h)) => {
                    msgs.push(mavout::named_float("HEADING", t_ms, h as f32))
                }
                (HeadingMessage::Attitude, Some(h)) => msgs.push(mavout::attitude(t_ms, r, p, h)),
                _ => {}
            }
        }
        if self.cfg.daemon.debug_vect {
            let f = |v: Vec3| [v[0] as f32, v[1] as f32, v[2] as f32];
            if let Some(m) = c.mag_ut {
                msgs.push(mavout::debug_vect(
                    "MAG_UT",
                    (self.now_s() * 1e6) as u64,
                    f(m),
                ));
            }
            if let Some(a) = c.accel_mps2 {
                msgs.push(mavout::debug_vect(
                    "ACC_MPS2",
                    (self.now_s() * 1e6) as u64,
                    f(a),
                ));
            }
        }
        self.send_mav(&msgs).await;
        if let (Some(r), Some(p), Some(h)) = (c.roll_deg, c.pitch_deg, c.heading_deg) {
            let ev = LiveEvent::Heading {
                t: c.t_s,
                roll_deg: r,
                pitch_deg: p,
                heading_deg: h,
                true_heading: self.declination.is_some(),
            };
            self.send_json(&ev).await;
        }
        let ev = LiveEvent::Calibrated {
            t: c.t_s,
            accel_mps2: c.accel_mps2,
            gyro_rad_s: c.gyro_rad_s,
            mag_ut: c.mag_ut,
        };
        self.send_json(&ev).await;
    }
}
