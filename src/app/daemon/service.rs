//! Start-up, the run loop and shut-down of the service: links started, state built, events
//! dispatched until a stop, then the last fits, files and lines out.

use super::*;

/// One fit job at a time, for every track whose refit was due when it started.
pub(super) type FitJob = Option<tokio::task::JoinHandle<TrackFits>>;

/// Whatever is queued is taken in one go (at most this many), so the run loop's `select!` runs
/// once per batch of samples rather than once per sample.
const INBOX_BATCH: usize = 256;

/// The folder of the simulator's calibration in `daemon.calibration_dir`.
pub(super) const SIM_DIR: &str = "sim";

/// The directory of calibrated vehicle 0 and the stored calibration to resume from there (none
/// yet: empty); a damaged file is an error. The built-in simulator (no source configured) keeps
/// its calibration in `calibration_dir/sim/`, as does a run with `sim:` sources whose
/// `calibration_dir` holds a vehicle's: a simulator's calibration never takes a vehicle's place.
pub(super) fn open_store(
    d: &crate::config::DaemonConfig,
) -> Result<(StoredCalibration, PathBuf), Error> {
    let configured = PathBuf::from(&d.calibration_dir);
    let simulated = d.sources.is_empty()
        || d.sources
            .iter()
            .any(|s| matches!(Address::parse(&s.address), Ok(Address::Sim { .. })));
    let mut cal_dir = configured.clone();
    let mut store = load_store(&cal_dir)?;
    let a_vehicles = |s: &Option<StoredCalibration>| {
        s.as_ref()
            .and_then(|s| s.vehicle.as_ref())
            .is_some_and(|v| v.source == VehicleSource::Vehicle)
    };
    if simulated && (d.sources.is_empty() || a_vehicles(&store)) {
        cal_dir = configured.join(SIM_DIR);
        store = load_store(&cal_dir)?;
    }
    let store = store.unwrap_or_else(StoredCalibration::empty);
    let shown = std::path::absolute(&cal_dir).unwrap_or_else(|_| cal_dir.clone());
    if let Some(r) = super::resumed_from(&store, &cal_dir) {
        tracing::info!(
            target: super::STATUS_TARGET,
            "{r}, from {}",
            shown.join(STORE_FILE).display()
        );
    } else {
        tracing::info!(
            target: super::STATUS_TARGET,
            "calibrations will be written to {} (daemon.calibration_dir)",
            shown.display()
        );
    }
    Ok((store, cal_dir))
}

/// Start a task per source (the embedded simulated tumble when none is configured).
pub(super) fn start_links(
    d: &crate::config::DaemonConfig,
    epoch: tokio::time::Instant,
    tx: InboundTx,
    stop: watch::Receiver<bool>,
) -> Result<Vec<LinkEntry>, Error> {
    let sources = if d.sources.is_empty() {
        vec![SourceConfig {
            address: "sim:tumble".into(),
            payload: crate::config::PayloadKind::Mavlink,
            fields: vec![],
            scales: Default::default(),
        }]
    } else {
        d.sources.clone()
    };
    let mut links = vec![];
    for (i, s) in sources.iter().enumerate() {
        let addr = Address::parse(&s.address)?;
        let replay = matches!(addr, Address::File { .. } | Address::Sim { .. });
        let payload = payload_of(s);
        let mavlink = matches!(payload, Payload::Mavlink) && !matches!(addr, Address::Sim { .. });
        let opts = LinkOptions {
            silent_after_s: d.silent_after_s,
            // A consumer of per-sample attitude wants each sample at once.
            // (Zero, every datagram at once, for a consumer of per-sample attitude.)
            udp_poll_s: d.udp_poll().as_secs_f64(),
            poll_epoch: Some(epoch),
            ..LinkOptions::default()
        };
        let polled = matches!(addr, Address::UdpIn(_) | Address::UdpOut(_));
        let handle = spawn_link(i, addr.clone(), payload, tx.clone(), stop.clone(), opts);
        links.push(LinkEntry {
            handle,
            mavlink,
            polled,
            ended: false,
            replay,
            label: s.address.clone(),
            outbound_queue_full: 0,
            queue_full_reported: 0,
            out: Vec::with_capacity(MAV_DATAGRAM_MAX),
            cals: Vec::new(),
            simulator: matches!(addr, Address::Sim { .. }),
        });
    }
    Ok(links)
}

impl Cal {
    /// A vehicle's calibration, resumed from `store`, spoken for with `own` ids, writing its
    /// parameters to `target`.
    pub(super) fn new(
        cfg: &Config,
        store: StoredCalibration,
        cal_dir: PathBuf,
        own: mavout::OwnIds,
        target: (u8, u8),
        declination: Option<f64>,
    ) -> Result<Cal, Error> {
        let track0 = Track::new(cfg, None, String::new(), store.compass_id)?;
        let mut c = Cal {
            vehicle: None,
            own,
            enc: MavEncoder::new(own.system_id, own.component_id),
            target,
            tracks: vec![track0],
            calibrator: Cal::calibrator_from_store(&store, declination),
            store,
            latest: None,
            writer: None,
            cal_dir,
            window: Averager::default(),
            fusion: OrientationFilter::new(cfg.fusion_config(declination)),
            attitude_rates: RateMean::default(),
            samples_since_attitude: 0,
            attitude_due: false,
            last_body_mag: None,
            filter_seeded: false,
            ftp: Default::default(),
        };
        if let Some(f) = c.store.filter {
            c.fusion.set_state(&f);
            c.filter_seeded = true;
        }
        Ok(c)
    }
}

impl State {
    pub(super) fn new(
        cfg: Config,
        (store, cal_dir): (StoredCalibration, PathBuf),
        declination: Option<f64>,
        links: Vec<LinkEntry>,
        sinks: Vec<Sink>,
        ready: Readiness,
    ) -> Result<State, Error> {
        let d = cfg.daemon.clone();
        let choice = cfg.input.instance.clone();
        let ardupilot_mag = match d.ardupilot_corrected_mag {
            crate::config::ArdupilotCorrectedMag::Undo => crate::io::decode::ArduPilotMag::Undo,
            crate::config::ArdupilotCorrectedMag::Refuse => crate::io::decode::ArduPilotMag::Refuse,
        };
        let mut new_converter = MessageConverter::new(choice, cfg.input.raw_imu_scale)
            .with_ardupilot_mag(ardupilot_mag);
        if new_converter.choice == InstanceChoice::Auto {
            // Every compass of the calibrated vehicle, each on its own track.
            new_converter = new_converter.with_other_instances();
        }
        let own = mavout::OwnIds {
            system_id: d.system_id,
            component_id: d.component_id,
        };
        let target = (d.target_system, d.target_component);
        let cal0 = Cal::new(&cfg, store, cal_dir, own, target, declination)?;
        Ok(State {
            cals: vec![cal0],
            sample_clocks: Vec::new(),
            own_echo: 0,
            autopilot_systems: Default::default(),
            store_writes: Writes::default(),
            report_writes: Writes::default(),
            links,
            sinks,
            vehicles: Vec::new(),
            other_vehicle_samples: 0,
            other_instance_samples: 0,
            new_converter,
            line_stats: crate::io::decode::DecodeStats::default(),
            accepted: 0,
            sources_failed: vec![],
            report: d.report.as_ref().map(PathBuf::from),
            start: tokio::time::Instant::now(),
            declination,
            ready,
            cfg,
        })
    }

    /// Whether a refit is due on any track of any vehicle.
    fn refit_wanted(&self) -> bool {
        self.cals
            .iter()
            .any(|c| c.tracks.iter().any(|t| t.refit_wanted))
    }

    /// The run loop: events until a stop (shutdown asked, the inbound queue closed, every replay
    /// source ended). Returns the fit job still in flight.
    pub(super) async fn serve(
        &mut self,
        mut rx: InboundRx,
        mut shutdown: watch::Receiver<bool>,
        tm: &mut Timers,
    ) -> FitJob {
        let mut fit_job: FitJob = None;
        let mut inbox: Vec<Queued> = Vec::with_capacity(INBOX_BATCH);
        let mut opening: Vec<_> = self
            .links
            .iter()
            .map(|l| l.handle.opening.clone())
            .collect();
        loop {
            // `daemon.attitude_every_samples`: the attitude right after the sample that made it due.
            self.attitude_if_due().await;
            if fit_job.is_none() && self.refit_wanted() {
                fit_job = Some(self.start_fits(false));
            }
            // Whatever this turn queued for the links goes out before the loop waits again.
            self.flush_mav();
            self.store_writes.start();
            self.report_writes.start();
            tokio::select! {
                _ = shutdown.changed() => {
                    if *shutdown.borrow() { break; }
                }
                n = rx.recv_many(&mut inbox, INBOX_BATCH) => {
                    if n == 0 || self.on_inbox(&mut inbox, &mut fit_job).await {
                        break;
                    }
                }
                r = async { fit_job.as_mut().expect("guarded").await }, if fit_job.is_some() => {
                    fit_job = None;
                    self.fits_done(r).await;
                }
                _ = all_opened(&mut opening), if !self.ready.told => self.tell_ready_if_open(),
                t = tm.clock.tick() => {
                    if self.take_polled(&mut rx, &mut inbox, &mut fit_job).await {
                        break;
                    }
                    self.on_clock(t, tm).await
                }
                _ = tm.heading.own_tick(), if tm.heading.own.is_some() => self.on_heading_tick().await,
                _ = tm.progress.own_tick(), if tm.progress.own.is_some() => self.publish_progress().await,
                _ = tm.attitude.own_tick(), if tm.attitude.own.is_some() => self.publish_attitudes().await,
                _ = tm.drops.own_tick(), if tm.drops.own.is_some() => self.report_drops().await,
                _ = async { tm.heartbeat.as_mut().expect("guarded").own_tick().await },
                    if tm.heartbeat.as_ref().is_some_and(|o| o.own.is_some()) => self.send_heartbeat().await,
                r = self.store_writes.done(), if self.store_writes.job.is_some() => self.written(r).await,
                r = self.report_writes.done(), if self.report_writes.job.is_some() => self.written(r).await,
            }
        }
        self.flush_mav();
        fit_job
    }

    /// Handles the items taken from the queue; true when the service is to stop.
    async fn on_inbox(&mut self, inbox: &mut Vec<Queued>, fit_job: &mut FitJob) -> bool {
        let mut done = false;
        for q in inbox.drain(..) {
            // The item's room in the queue is given back once it is handled.
            let (ev, _room) = q.into_parts();
            done = done || self.on_inbound(ev, fit_job).await;
        }
        done
    }

    /// At a clock tick, before the outputs read the state: the UDP polls on the same grid point
    /// woke their links in the same wake-up; they run first (one yield) and what they queued is
    /// handled, so the outputs see the frames of this tick's poll rather than one poll late. True
    /// when the service is to stop.
    async fn take_polled(
        &mut self,
        rx: &mut InboundRx,
        inbox: &mut Vec<Queued>,
        fit_job: &mut FitJob,
    ) -> bool {
        if !self.links.iter().any(|l| l.polled && !l.ended) {
            return false;
        }
        tokio::task::yield_now().await;
        while inbox.len() < INBOX_BATCH {
            match rx.try_recv() {
                Some(q) => inbox.push(q),
                None => break,
            }
        }
        self.on_inbox(inbox, fit_job).await
    }

    async fn attitude_if_due(&mut self) {
        for c in 0..self.cals.len() {
            if std::mem::take(&mut self.cals[c].attitude_due) {
                self.publish_attitude(c).await;
            }
        }
    }

    /// One event from the links; true when the service is to stop (every source was a replay and
    /// all have ended: the last fits are done here).
    async fn on_inbound(&mut self, ev: Inbound, fit_job: &mut FitJob) -> bool {
        self.attitude_if_due().await;
        match ev {
            Inbound::Sample { link, sample } => {
                self.note_simulator(link);
                let sample = self.stamp(link, sample);
                self.line_stats.records += 1;
                self.line_stats.count_sample(&sample);
                self.on_sample(0, sample);
            }
            Inbound::Frames { link, frames } => {
                for (i, f) in frames.iter().enumerate() {
                    if i > 0 {
                        // Each frame's attitude as it was due, as for frames queued one by one.
                        self.attitude_if_due().await;
                    }
                    self.on_frame(link, &f.frame, f.time_us).await;
                }
            }
            Inbound::Status { link, status } => {
                // A link's opening is told before its first status: the `ready` line comes
                // before the status lines of the last link to open (and before any end).
                self.tell_ready_if_open();
                let label = self
                    .links
                    .get(link)
                    .map(|l| l.label.clone())
                    .unwrap_or_default();
                match status {
                    LinkStatus::Connected(s) => {
                        self.status(
                            MavSeverity::MAV_SEVERITY_INFO,
                            format!("{label}: connected {s}"),
                        )
                        .await
                    }
                    LinkStatus::Lost(s) => {
                        let replay = self.links.get(link).is_some_and(|l| l.replay);
                        let text = if replay {
                            // A replay never reconnects: it can never work.
                            self.sources_failed.push(format!("{label}: {s}"));
                            format!("{label}: {s}")
                        } else {
                            format!("{label}: lost ({s}); reconnecting, calibration kept")
                        };
                        self.status(MavSeverity::MAV_SEVERITY_WARNING, text).await
                    }
                    LinkStatus::Silent { for_s } => {
                        self.status(
                            MavSeverity::MAV_SEVERITY_WARNING,
                            format!("{label}: silent for {for_s:.1} s"),
                        )
                        .await
                    }
                    LinkStatus::Ended => {
                        if let Some(l) = self.links.get_mut(link) {
                            l.ended = true;
                        }
                        self.status(MavSeverity::MAV_SEVERITY_INFO, format!("{label}: ended"))
                            .await;
                        if self.links.iter().all(|l| l.replay && l.ended) {
                            if let Some(j) = fit_job.take() {
                                self.fits_done(j.await).await;
                            }
                            let last = self.start_fits(true).await;
                            self.fits_done(last).await;
                            return true;
                        }
                    }
                }
            }
        }
        false
    }

    /// The clock on the polls' time grid: the periodic outputs due at `t`, a delayed calibration
    /// run's start.
    async fn on_clock(&mut self, t: tokio::time::Instant, tm: &mut Timers) {
        if tm.heading.due_at_clock(t) {
            self.on_heading_tick().await;
        }
        if tm.progress.due_at_clock(t) {
            self.publish_progress().await;
        }
        if tm.attitude.due_at_clock(t) {
            self.publish_attitudes().await;
        }
        if tm.drops.due_at_clock(t) {
            self.report_drops().await;
        }
        if tm.heartbeat.as_mut().is_some_and(|o| o.due_at_clock(t)) {
            self.send_heartbeat().await;
        }
        for c in 0..self.cals.len() {
            for i in 0..self.cals[c].tracks.len() {
                if self.cals[c].tracks[i].mag_run.wants_ticks() {
                    let now_s = self.now_s();
                    self.mag_event(c, i, MagCalEvent::Tick { now_s }).await;
                }
            }
        }
    }

    /// Shut-down (the links told to stop): the fit in flight briefly, the writes in flight, then
    /// the last calibration and report, the JSON consumers drained briefly.
    pub(super) async fn shut_down(mut self, fit_job: FitJob) -> RunSummary {
        if let Some(j) = fit_job {
            if let Ok(r) = tokio::time::timeout(Duration::from_millis(500), j).await {
                self.fits_done(r).await;
            }
        }
        // Writes in flight finish first, so an older file cannot land after the final one.
        for w in [&mut self.store_writes, &mut self.report_writes] {
            w.next.clear();
        }
        if self.store_writes.job.is_some() {
            let r = self.store_writes.done().await;
            self.written(r).await;
        }
        if self.report_writes.job.is_some() {
            let r = self.report_writes.done().await;
            self.written(r).await;
        }
        for c in 0..self.cals.len() {
            let s = &self.cals[c].store;
            if s.mag.is_some() || s.accel.is_some() {
                self.save(c).await;
            }
        }
        self.write_report().await;
        // What is queued for the JSON consumers goes out, briefly: one that does not read cannot
        // hold the exit.
        self.report_drops().await;
        let deadline = tokio::time::Instant::now() + SINK_DRAIN_AT_EXIT;
        close_sinks(&mut self.sinks, deadline).await;
        let counters = self.links.iter().map(|l| &l.handle.counters);
        let inbound_dropped = counters
            .map(|c| c.inbound_dropped.load(std::sync::atomic::Ordering::Relaxed))
            .sum();
        for l in &self.links {
            l.handle.task.abort();
        }
        RunSummary {
            samples: self.cals[0].tracks[0].samples_in,
            accepted: self.accepted,
            inbound_dropped,
            sources_failed: self.sources_failed,
        }
    }
}
