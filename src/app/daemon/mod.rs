//! The live service (`imucald run`): links in, one pipeline per IMU instance (a [`Track`]), fits
//! off the async executor, heading/progress/reports published back. Thin glue: every decision
//! lives in a pure module.
//!
//! ```text
//! link tasks ──(bounded mpsc, drops counted)──> run loop ──> the instance's Track: Pipeline::push
//!                                                  │  track 0: Calibrator ─> OrientationFilter (attitude)
//!                                                  │  refit due: snapshots ─> spawn_blocking(fit_all each)
//!                                                  │  result: accept if checks pass and not worse on held-out points
//!                                                  ├─> MAVLink back to the links (progress, report per compass,
//!                                                  │   heading, ATTITUDE_QUATERNION / ATTITUDE)
//!                                                  ├─> JSON lines: a bounded queue per consumer
//!                                                  │   (try_send, drops counted) -> its writer
//!                                                  └─> calibration files (atomic), report
//! ```
//!
//! `service`: start-up, the run loop, shut-down. `state`: samples and frames in, heading and
//! attitude out. `lifecycle`: each track's fits, acceptance and calibration run. `magcal`: the
//! calibration run's states and its transition function, which decides what is installed.
//! `store`: the calibration on disk. `sinks`: JSON consumers. `outputs`: output cadences and means.

mod ftp;
mod identity;
mod lifecycle;
mod lock;
mod magcal;
mod mqtt;
mod outputs;
mod params;
mod service;
mod sinks;
mod state;
mod store;

pub use crate::types::STATUS_TARGET;
use identity::{resumable, resumed_from, same_kind};
use magcal::{MagCalEffect, MagCalEvent, MagCalRun};
use mavout::severity_name;
use outputs::*;
pub use outputs::{Ready, ReadyLink};
use service::{open_store, start_links};
use sinks::*;
pub use store::{
    accept, failure_report_due, load_store, save_store, LoadedCalibration, NotReplaced,
    StoredCalibration, StoredInstance, StoredVehicle, VehicleSource, ACCEPT_MARGIN, HOLD_OUT_EVERY,
    STORE_FILE, STORE_SCHEMA,
};
use store::{WriteJob, Writes};

use crate::attitude::fusion::OrientationFilter;
use crate::calib::blockmean::BlockMean;
use crate::calib::coverage::Progress;
use crate::calib::ladder::{Affine, RungCal};
use crate::calib::learn::{Incumbent, LadderInput, LearnSettings, LiveLadder, VectorLearner};
use crate::calib::model::Calibration;
use crate::calib::outcome::SensorResult;
use crate::calib::pipeline::{fit_all, Calibrated, Calibrator, FitResults, Pipeline};
use crate::config::{
    ArdupilotCorrectedMag, AttitudeMessage, Config, HeadingMessage, Links, MagCalMode, ParamTarget,
    PayloadKind, SourceConfig,
};
use crate::error::Error;
use crate::io::clock::{ClockSettings, SourceClock};
use crate::io::decode::{InstanceChoice, MessageConverter};
use crate::io::link::{
    inbound_queue, spawn_link, Address, Inbound, InboundRx, InboundTx, LinkHandle, LinkOpening,
    LinkOptions, LinkStatus, Payload, Queued,
};
use crate::io::mavout::{self, LiveEvent, MavEncoder, ParamWriter};
use crate::report::{GyroCalibration, SensorCalibration};
use crate::types::{norm, Sample, Sensor, Unit, Vec3};
use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavResult, MavSeverity, COMMAND_LONG_DATA,
};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

fn payload_of(s: &SourceConfig) -> Payload {
    match s.payload {
        PayloadKind::Motioncal => Payload::MotionCal,
        PayloadKind::Csv => Payload::Csv {
            fields: s.fields.clone(),
            scales: s.scales.clone(),
        },
        PayloadKind::Mavlink => Payload::Mavlink,
    }
}

/// Largest datagram of MAVLink frames sent to a link, bytes: under a 1500-byte Ethernet MTU less
/// IP and UDP headers, so a datagram is never fragmented.
const MAV_DATAGRAM_MAX: usize = 1400;

/// What `run` did, for the caller's last words.
#[derive(Debug, Clone, Default)]
pub struct RunSummary {
    pub samples: u64,
    pub accepted: usize,
    pub inbound_dropped: u64,
    /// Replays (`file:`, `sim:`) that could not be read at all, each with its reason: they can
    /// never work, so the caller ends with a failure.
    pub sources_failed: Vec<String>,
}

/// A vehicle heard on the links: its converter (instances, clocks, and its ArduPilot state: whether
/// its magnetometer data comes calibrated, and the calibration to undo).
struct Vehicle {
    /// Link index and system id; (0, 0) for every link with `daemon.links = "merged"`.
    key: (usize, u8),
    conv: MessageConverter,
    /// Its calibration (index in `State::cals`), once its IMU data arrived.
    cal: Option<usize>,
    /// Told the user it is not calibrated.
    announced: bool,
    /// Its flight stack, once a HEARTBEAT named ArduPilot or PX4 (it was then asked for its
    /// identity); `None` for a link that names none.
    identity: Option<crate::io::identity::Stack>,
    /// What its link said of its hardware.
    hardware: crate::io::identity::Hardware,
}

struct LinkEntry {
    handle: LinkHandle,
    mavlink: bool,
    /// A UDP link, read by polling on the time grid.
    polled: bool,
    ended: bool,
    replay: bool,
    label: String,
    /// Datagrams of MAVLink frames dropped because its outbound queue was full (also in the link's
    /// `outbound_dropped`, with those it could not send: no peer yet, link down).
    outbound_queue_full: u64,
    /// `outbound_queue_full` when it was last reported.
    queue_full_reported: u64,
    /// MAVLink frames queued in this turn of the run loop, sent as one datagram (or write) at its
    /// end: one `sendto` for all the messages of a tick, not one per message.
    out: Vec<u8>,
    /// The calibrated vehicles heard on it (their messages go only to such links, or to links
    /// where none was heard).
    cals: Vec<usize>,
    /// A `sim:` link: its samples feed calibrated vehicle 0, recorded as a simulator's.
    simulator: bool,
}

/// One IMU instance calibrated live: its pipeline, its magnetometer calibration run and progress,
/// its latest fit. Track 0 is the primary instance, whose calibration also gives the heading and
/// the attitude; every further compass of the calibrated vehicle gets a track of its own
/// (at most [`crate::io::decode::MAX_INSTANCES`]), calibrated, reported (MAG_CAL_* with its compass id,
/// JSON with its `instance`), stored and written under its own parameter names.
struct Track {
    /// The instance's index in the calibrated vehicle's converter; `None` for track 0 until the
    /// converter picked its primary (and for samples of text-line links, which have no instances).
    instance: Option<usize>,
    /// `highres_imu:1`, `scaled_imu2`, ...
    name: String,
    /// MAG_CAL_* `compass_id`.
    compass_id: u8,
    pipe: Pipeline,
    /// The raw samples are averaged in blocks to `daemon.pipeline_rate_hz` before `pipe` and the
    /// attitude filter see them ([`crate::calib::blockmean`]).
    blocks: BlockMean,
    /// Raw samples taken since `pipe` started (what reports count as the samples).
    samples_in: u64,
    /// Magnetometer samples pushed (a track without any reports no magnetometer progress).
    mag_samples: u64,
    /// Counts calibration-run restarts: a fit started before the latest one is disregarded.
    generation: u64,
    /// Completion of the calibration run, for the progress reports.
    progress: Progress,
    /// The magnetometer calibration run (ground-station commands, continuous calibration).
    mag_run: MagCalRun,
    /// The failed magnetometer fit to report, while its event is handled.
    mag_failed: Option<SensorCalibration>,
    /// The last magnetometer calibration sent in MAG_CAL_REPORT (reports only when it moved).
    reported_mag: Option<SensorCalibration>,
    last_results: Option<FitResults>,
    /// A refit is due (its pipeline said so since the last fit started).
    refit_wanted: bool,
    /// The latest (magnetometer uT, specific force m/s^2) pairs in sensor axes, before
    /// calibration: what a fixed-yaw calibration averages ([`crate::calib::fixedyaw`]; turned to body
    /// axes only then, not per sample).
    recent: std::collections::VecDeque<(Vec3, Vec3)>,
    /// When the newest of `recent` arrived: a fixed-yaw calibration wants the vehicle as it is
    /// now, not as it was before the data stopped.
    recent_at: Option<tokio::time::Instant>,
    /// The readings learnt from every reading that comes with the vehicle's attitude
    /// ([`crate::calib::learn`]): the ladder climbed on them stands in for a failed sphere fit.
    learner: VectorLearner,
    /// `[place]`: where the earth field is evaluated when the vehicle sends no position.
    place: Option<crate::attitude::Place>,
    /// The vehicle's newest position (its GLOBAL_POSITION_INT, or GPS_RAW_INT with a 3-D fix, as
    /// the samples carry it): where a fixed-yaw calibration at "latitude and longitude 0" is.
    position: Option<crate::types::GeoPoint>,
    /// The magnetometer calibration in use is a rung learnt from `learner`'s readings up to this
    /// time, s: a later rung is judged against it only on readings after it.
    rung_until_s: Option<f64>,
}

/// The length of the blocks a track averages, s: none (0) when the rate is 0 or every sample's
/// attitude is sent back (`daemon.attitude_every_samples`).
fn block_period_s(d: &crate::config::DaemonConfig) -> f64 {
    if d.attitude_every_samples > 0 || d.pipeline_rate_hz <= 0.0 {
        0.0
    } else {
        1.0 / d.pipeline_rate_hz
    }
}

impl Track {
    fn new(
        cfg: &Config,
        instance: Option<usize>,
        name: String,
        compass_id: u8,
    ) -> Result<Track, Error> {
        Ok(Track {
            instance,
            name,
            compass_id,
            pipe: Pipeline::new(&cfg.calib())?.with_hold_out(HOLD_OUT_EVERY),
            blocks: BlockMean::new(block_period_s(&cfg.daemon)),
            samples_in: 0,
            mag_samples: 0,
            generation: 0,
            progress: Progress::new(cfg.daemon.progress_full_regions),
            mag_run: MagCalRun::Idle,
            mag_failed: None,
            reported_mag: None,
            last_results: None,
            refit_wanted: false,
            recent: std::collections::VecDeque::with_capacity(FIXED_YAW.window_samples),
            recent_at: None,
            position: None,
            learner: VectorLearner::new(LearnSettings::DEFAULT)
                .on_date(&crate::io::clock::today().iso()),
            place: cfg.place.clone(),
            rung_until_s: None,
        })
    }

    /// Take a raw sample: counted, and added to the block being averaged; the block's mean when
    /// this sample completes it (what [`Track::push`] and the attitude filter take).
    fn take(&mut self, raw: &Sample) -> Option<Sample> {
        self.samples_in += 1;
        self.position = raw.position.or(self.position);
        self.blocks.push(raw)
    }

    /// Push a sample (a block mean, sensor axes); a refit due is marked (`refit_wanted`).
    fn push(&mut self, s: &Sample) {
        if s.mag_ut.is_some() {
            self.mag_samples += 1;
        }
        if let (Some(m), Some(a)) = (s.mag_ut, s.accel_mps2) {
            if self.recent.len() == FIXED_YAW.window_samples {
                self.recent.pop_front();
            }
            self.recent.push_back((m, a));
            self.recent_at = Some(tokio::time::Instant::now());
        }
        if let (Some(_), Some(q)) = (s.mag_ut, s.ref_q) {
            if let (Some(m), Some(q)) = (
                self.pipe.to_body(s).mag_ut,
                crate::attitude::body_ned_of_ref_q(q),
            ) {
                self.learner
                    .push(s.t_s, &m, &q, s.current_a, s.position, self.place.as_ref());
            }
        }
        self.refit_wanted |= self.pipe.push(s);
    }
}

/// Whether the ladder may stand in for the magnetometer's sphere fit: it failed, the readings
/// are in uT, and the compass was not refused for its mounting (a rung's matrix would turn the
/// readings and hide a wrong mounting).
fn ladder_stands_in(results: &FitResults) -> bool {
    results.mag.calibration.is_none()
        && results.mag.report.units == crate::types::CalUnits::Ut
        && results.mag.report.failure != Some(crate::calib::fit::FitFailure::Orientation)
}

/// What a fit job needs of a track's learner: its readings, the vehicle's own calibration to
/// start from, and the calibration a rung must beat.
type LadderJob = (LadderInput, Option<Affine>, Option<Incumbent>);

impl Track {
    /// The vehicle's own calibration of this track's compass in body axes, when its telemetry
    /// gives one: ArduPilot's COMPASS_OFS/DIA/ODI/SCALE as read to undo them from its readings
    /// (`onboard`: the vehicle's converter's record). A PX4 vehicle's CAL_MAGn_* are not read.
    fn vehicle_start(&self, onboard: Option<&crate::io::onboard::OnboardReport>) -> Option<Affine> {
        let m = onboard?
            .mag
            .iter()
            .find(|m| m.instance == self.compass_id || m.sources.contains(&self.name))
            .filter(|m| m.units == crate::types::CalUnits::Ut)?;
        // rot M (raw - o) with raw = rot^T u is (rot M rot^T) (u - rot o), as `replay` turns it.
        let rot = self.pipe.sensor_rotation();
        Some(Affine {
            matrix: rot * crate::calib::model::rows_to_mat(&m.matrix) * rot.transpose(),
            offset: rot * nalgebra::Vector3::from(m.offset),
        })
    }

    /// What the fit job climbs the ladder on, when the learner holds readings enough: the ring,
    /// `start` (the vehicle's own), and the incumbent: `in_use` (the service's calibration of
    /// this compass, with its current term), else the vehicle's own.
    fn ladder_job(
        &self,
        start: Option<Affine>,
        in_use: Option<&SensorCalibration>,
    ) -> Option<LadderJob> {
        let input = self.learner.ladder_input()?;
        let ours = in_use.and_then(|m| {
            let c = m.calibration_ut()?;
            let matrix = crate::calib::model::rows_to_mat(&c.matrix);
            Some(Incumbent {
                calibration: RungCal {
                    affine: Affine {
                        matrix,
                        offset: nalgebra::Vector3::from(c.offset),
                    },
                    // The raw reading's term (raw = A h + o + k i) in calibrated axes: -M k.
                    current_ut_per_a: m
                        .motor_ut_per_a()
                        .map(|k| -(matrix * nalgebra::Vector3::from(k))),
                },
                what: "the calibration in use",
                fitted_until_s: self.rung_until_s,
            })
        });
        let incumbent = ours.or_else(|| {
            start.map(|affine| Incumbent {
                calibration: RungCal {
                    affine,
                    current_ut_per_a: None,
                },
                what: "the vehicle's own calibration",
                fitted_until_s: None,
            })
        });
        Some((input, start, incumbent))
    }

    /// When the sphere fit failed ([`ladder_stands_in`]) and the ladder climbed in the fit job on
    /// the learner's readings took a rung that passes its checks and is better held out than
    /// the incumbent ([`LiveLadder::decide`]; `compare`: judged against it, not in a commanded
    /// run), the rung's calibration takes the magnetometer's place in `results`, as `replay`
    /// installs it, with the rung and why in the method's reason. Returns whether it did.
    fn take_rung(
        &self,
        results: &mut FitResults,
        live: Option<&LiveLadder>,
        compare: bool,
    ) -> bool {
        let Some(live) = live.filter(|_| ladder_stands_in(results)) else {
            return false;
        };
        let (chosen, judged) = match live.decide(ACCEPT_MARGIN, compare) {
            Ok(x) => x,
            Err(why) => {
                tracing::info!(
                    compass = self.compass_id,
                    "learnt calibration not offered: {why}"
                );
                return false;
            }
        };
        let sphere = crate::calib::magmethod::sphere_words(&results.mag);
        let mag = &mut results.mag;
        crate::calib::magmethod::install_rung(
            mag,
            chosen,
            live.ladder.start,
            &live.ladder.why,
            &sphere,
        );
        if let Some(m) = mag.report.method.as_mut() {
            let dropped = if live.dropped > 0 {
                format!(", {} older dropped", live.dropped)
            } else {
                String::new()
            };
            let judged = if judged.is_empty() {
                String::new()
            } else {
                format!("; {judged}")
            };
            m.vector = live.vector.clone();
            m.method_reason = format!(
                "learnt live from {} readings with the vehicle's attitude (at most one a second, the last {} kept{dropped}), field from {}: {}{judged}",
                live.readings,
                crate::calib::learn::RING_CAPACITY,
                live.field_from,
                m.method_reason
            );
        }
        true
    }
}

/// Which tracks a fit job fitted: (calibrated vehicle, track, its generation when the job
/// started, time, results, the ladder climbed on the track's learnt readings when the sphere
/// fit failed).
type TrackFits = Vec<(usize, usize, u64, f64, FitResults, Option<Box<LiveLadder>>)>;

/// Calibrated vehicles kept at most (further vehicles' samples are counted, not calibrated).
const MAX_CALIBRATED_VEHICLES: usize = 8;

/// Where a MAVLink message goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum To {
    /// Every live MAVLink link, as the service (its configured ids): status of the links,
    /// heartbeats.
    All,
    /// One link, as the service.
    Link(usize),
    /// About calibrated vehicle `c`, with the ids it is spoken for with: every live MAVLink link
    /// except those where another calibrated vehicle was heard.
    Cal(usize),
}

/// A vehicle calibrated: its IMU instances (tracks), its calibration in use and on disk, its
/// heading and attitude. Calibrated vehicle 0 is the first heard (and takes the samples of text
/// and simulator links); it is spoken for with the configured ids and kept in
/// `daemon.calibration_dir`. Each further vehicle (`daemon.links = "separate"`) is spoken for as
/// component `daemon.component_id` of its own system, and kept in
/// `calibration_dir/vehicle-<link>-<system>/`.
struct Cal {
    /// Index in `State::vehicles`; `None` until the first MAVLink vehicle's IMU data arrives
    /// (calibrated vehicle 0 only).
    vehicle: Option<usize>,
    /// The ids its messages carry, and an inbound frame carrying both is our own echo.
    own: mavout::OwnIds,
    enc: MavEncoder,
    /// Parameter writes go to this system and component.
    target: (u8, u8),
    /// The instances calibrated; track 0 is the primary.
    tracks: Vec<Track>,
    store: StoredCalibration,
    calibrator: Calibrator,
    latest: Option<Calibrated>,
    writer: Option<ParamWriter>,
    cal_dir: PathBuf,
    /// Calibrated vectors since the last heading publication.
    window: Averager,
    /// Fused attitude (body FRD -> NED, true north when the place is known) from every calibrated sample.
    fusion: OrientationFilter,
    /// Calibrated gyro since the last attitude publication (the body rates sent with it).
    attitude_rates: RateMean,
    /// `daemon.attitude_every_samples`: samples since the last attitude, and whether one is due now.
    samples_since_attitude: u32,
    attitude_due: bool,
    /// The latest magnetometer reading in body axes before calibration (to tell how far a new
    /// calibration moves the field the filter sees).
    last_body_mag: Option<Vec3>,
    /// The orientation filter was given a state (restored at start, or kept across a restart):
    /// it has something to save even before its first sample.
    filter_seeded: bool,
    /// The parameter file each ground station has open over MAVFTP (keyed by the protocol's
    /// `session` byte).
    ftp: crate::io::mavftp::FtpServer,
}

struct State {
    cfg: Config,
    /// The vehicles calibrated; 0 is the first heard.
    cals: Vec<Cal>,
    /// Clocks of the links that deliver samples rather than MAVLink frames, by link index.
    sample_clocks: Vec<SourceClock>,
    /// Inbound frames dropped as our own echo.
    own_echo: u64,
    /// Systems whose flight controller was heard (a HEARTBEAT naming an autopilot): MAVFTP
    /// requests to every component of such a system are its own.
    autopilot_systems: std::collections::BTreeSet<u8>,
    /// The calibration stores and the report, written off the run loop.
    store_writes: Writes,
    report_writes: Writes,
    links: Vec<LinkEntry>,
    sinks: Vec<Sink>,
    /// The vehicles heard (a link and a system id each, or one for all with
    /// `daemon.links = "merged"`): their converters and ArduPilot state.
    vehicles: Vec<Vehicle>,
    /// IMU samples of vehicles past [`MAX_CALIBRATED_VEHICLES`], not calibrated.
    other_vehicle_samples: u64,
    /// IMU samples of instances past the tracks the service keeps, not calibrated.
    other_instance_samples: u64,
    /// A converter as new, for the next vehicle heard.
    new_converter: MessageConverter,
    /// Counts of the samples from text-line and simulator links.
    line_stats: crate::io::decode::DecodeStats,
    accepted: usize,
    /// Replays that could not be read, with the reason ([`RunSummary::sources_failed`]).
    sources_failed: Vec<String>,
    report: Option<PathBuf>,
    start: tokio::time::Instant,
    declination: Option<f64>,
    /// The start-up's `ready` line.
    ready: Readiness,
}

/// Oldest the newest sample of a fixed-yaw calibration may be, s: the vehicle must be standing at
/// the commanded yaw now, not when the data stopped.
const FIXED_YAW_MAX_AGE_S: f64 = 2.0;

/// How still and level a fixed-yaw calibration wants the vehicle, over how many samples.
const FIXED_YAW: crate::calib::fixedyaw::FixedYawSettings =
    crate::calib::fixedyaw::FixedYawSettings::DEFAULT;

/// Time step of the orientation filter's first sample and of samples whose clock jumps, s.
const FUSION_DEFAULT_DT_S: f64 = 0.01;

/// Whether a new magnetometer calibration moves the calibrated field of `raw` (body axes, before
/// calibration) by more than 2 % in norm or 2 degrees in direction: the orientation filter would take
/// such a step for a magnetic disturbance (and distrust the field for a while), so it restarts instead.
fn mag_cal_moved(old: Option<&Calibration>, new: Option<&Calibration>, raw: &Vec3) -> bool {
    let f = |c: Option<&Calibration>| c.map_or(*raw, |c| c.apply(raw));
    let (a, b) = (f(old), f(new));
    let (na, nb) = (norm(&a), norm(&b));
    if !(na > 0.0 && nb > 0.0 && na.is_finite() && nb.is_finite()) {
        return false;
    }
    let cos = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (na * nb);
    (nb / na - 1.0).abs() > 0.02 || cos.clamp(-1.0, 1.0).acos().to_degrees() > 2.0
}
/// Run the service until `shutdown` turns true, or until every replay/sim source has ended.
pub async fn run(cfg: Config, shutdown: watch::Receiver<bool>) -> Result<RunSummary, Error> {
    run_reporting_ready(cfg, shutdown, None).await
}

/// [`run`], handing `ready` what the `ready` line says once every link has opened or failed to:
/// for a caller in the same process (a test) that must not send before the service listens, or
/// that asked for port 0. Dropped unsent when the service stops before that.
pub async fn run_reporting_ready(
    cfg: Config,
    shutdown: watch::Receiver<bool>,
    ready: Option<tokio::sync::oneshot::Sender<Ready>>,
) -> Result<RunSummary, Error> {
    // Checked here too (callers may build the config in code): bad rates would stop the timers.
    cfg.validate()?;
    // Held until the service returns: one service per store.
    let _lock = lock::StoreLock::take(Path::new(&cfg.daemon.calibration_dir))?;
    let store = open_store(&cfg.daemon)?;
    let declination = cfg.declination_deg()?;
    let mut sinks = cfg
        .daemon
        .publish
        .iter()
        .map(|p| Sink::open(p, cfg.daemon.target_system))
        .collect::<Result<Vec<_>, _>>()?;
    // The live page: a JSON consumer of its own feeds it.
    let ui = match &cfg.ui.listen {
        Some(addr) => Some(crate::app::ui::server::LiveUi::start(addr).await?),
        None => None,
    };
    sinks.extend(ui.as_ref().map(|u| Sink::ui(u.feed())));
    let (tx, rx) = inbound_queue(cfg.daemon.queue_capacity);
    // The time grid the UDP polls and the periodic outputs share.
    let epoch = tokio::time::Instant::now();
    let (link_stop_tx, link_stop_rx) = watch::channel(false);
    let links = start_links(&cfg.daemon, epoch, tx, link_stop_rx)?;
    let readiness = Readiness {
        told: false,
        ui: ui.as_ref().map(|u| u.addr),
        notify: ready,
    };
    let mut st = State::new(cfg, store, declination, links, sinks, readiness)?;
    let mut timers = Timers::new(&st.cfg.daemon, st.links.iter().any(|l| l.polled), epoch);
    let fit_job = st.serve(rx, shutdown, &mut timers).await;
    let _ = link_stop_tx.send(true);
    let summary = st.shut_down(fit_job).await;
    if let Some(u) = ui {
        u.stop().await;
    }
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::MavAutopilot;

    fn cal(offset: Vec3, scale: f64) -> Calibration {
        Calibration {
            model: crate::calib::model::ModelKind::Sphere,
            offset,
            matrix: [[scale, 0.0, 0.0], [0.0, scale, 0.0], [0.0, 0.0, scale]],
        }
    }

    #[test]
    fn daemon_restarts_fusion_only_when_the_mag_calibration_moves_the_field() {
        let raw = [30.0, -10.0, 45.0];
        let c = cal([10.0, -20.0, 30.0], 1.0);
        // First calibration after raw data: the field the filter sees jumps.
        assert!(mag_cal_moved(None, Some(&c), &raw));
        // A refit that moves the offset by a fraction of a uT: the filter keeps going.
        let near = cal([10.1, -20.05, 30.0], 1.005);
        assert!(!mag_cal_moved(Some(&c), Some(&near), &raw));
        assert!(!mag_cal_moved(Some(&c), Some(&c), &raw));
        // Norm by 5 %, or direction by several degrees: restart.
        assert!(mag_cal_moved(
            Some(&c),
            Some(&cal([10.0, -20.0, 30.0], 1.05)),
            &raw
        ));
        assert!(mag_cal_moved(
            Some(&c),
            Some(&cal([10.0, -17.0, 30.0], 1.0)),
            &raw
        ));
        // Degenerate or broken readings never restart it.
        assert!(!mag_cal_moved(Some(&c), Some(&near), &[10.0, -20.0, 30.0]));
        assert!(!mag_cal_moved(None, Some(&c), &[f64::NAN, 0.0, 0.0]));
    }

    #[test]
    fn daemon_replaces_a_calibration_only_when_better_on_points_held_out_of_the_fit() {
        let sim = crate::sim::simulate(&crate::sim::Scenario::named("tumble").unwrap(), 5);
        let cfg = Config::default();
        let mut pipe = Pipeline::new(&cfg.calib())
            .unwrap()
            .with_hold_out(HOLD_OUT_EVERY);
        for s in &sim.samples {
            pipe.push(s);
        }
        pipe.finish_poses();
        let input = pipe.snapshot();
        let r = fit_all(&input, &cfg.calib());
        let n = input.mag_points.len();
        // Every 5th kept point held out, the fit made on the rest.
        assert_eq!(r.mag.held_out.len(), n.div_ceil(HOLD_OUT_EVERY));
        assert!(r.mag.report.samples_used <= n - r.mag.held_out.len());
        let every_fifth: Vec<Vec3> = input
            .mag_points
            .iter()
            .step_by(HOLD_OUT_EVERY)
            .copied()
            .collect();
        assert_eq!(r.mag.held_out, every_fifth);
        assert_eq!(
            r.mag.report.status,
            crate::report::CalStatus::Ok,
            "{:?}",
            r.mag.report.detail
        );
        let truth = &sim.truth.mag;
        let current = |offset: Vec3| SensorCalibration {
            offset,
            matrix: truth.matrix,
            ..r.mag.report.clone()
        };
        // Nothing to compare with: its checks decide.
        assert_eq!(accept(&r.mag, None), Ok(()));
        // A current calibration 3 uT off: replaced.
        let off = [truth.offset[0] + 3.0, truth.offset[1], truth.offset[2]];
        assert_eq!(accept(&r.mag, Some(&current(off))), Ok(()));
        // A new one 1 uT off against the true one: worse on the held-out points, kept out.
        let mut worse = r.mag.clone();
        let c = worse.calibration.as_mut().unwrap();
        c.offset[1] += 1.0;
        match accept(&worse, Some(&current(truth.offset))) {
            Err(NotReplaced::WorseOnHeldOut {
                points,
                rms_new,
                rms_current,
            }) => {
                assert_eq!(points, r.mag.held_out.len());
                assert!(
                    rms_new > rms_current * (1.0 + ACCEPT_MARGIN),
                    "{rms_new} {rms_current}"
                );
            }
            other => panic!("{other:?}"),
        }
        // No points held out: no comparison, the current one stays.
        let mut none = r.mag.clone();
        none.held_out.clear();
        assert_eq!(
            accept(&none, Some(&current(off))),
            Err(NotReplaced::NothingHeldOut)
        );
        // A failed fit never replaces anything.
        let mut failed = r.mag.clone();
        failed.calibration = None;
        failed.report.failure = Some(crate::calib::fit::FitFailure::Coverage);
        assert!(matches!(
            accept(&failed, None),
            Err(NotReplaced::Failed { .. })
        ));
    }

    #[test]
    fn daemon_attitude_rates_are_means_between_publications() {
        let mut r = RateMean::default();
        assert_eq!(r.take(), None);
        r.add(&[0.1, 0.2, 0.3]);
        r.add(&[0.3, 0.0, -0.3]);
        assert_eq!(r.take(), Some([0.2, 0.1, 0.0]));
        // Nothing new: the last mean again.
        assert_eq!(r.take(), Some([0.2, 0.1, 0.0]));
        r.add(&[1.0, 1.0, 1.0]);
        assert_eq!(r.take(), Some([1.0, 1.0, 1.0]));
    }

    /// A TCP consumer that accepts and never reads: queueing lines for it never waits (no time
    /// passes on the paused clock), what its queue cannot hold is counted, and closing it ends at
    /// the deadline.
    #[tokio::test(start_paused = true)]
    async fn daemon_json_sink_for_a_stuck_consumer_drops_counts_and_closes_in_time() {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let held = std::thread::spawn(move || l.accept().map(|(c, _)| c));
        let mut sinks = vec![Sink::open(&format!("tcp:{addr}"), 1).unwrap()];
        // 20 000 lines of 1 kB: far more than the socket buffers and the queue hold.
        let line: std::sync::Arc<str> = format!("{}\n", "x".repeat(1023)).into();
        let t0 = tokio::time::Instant::now();
        for i in 0..20_000 {
            sinks[0].send(&line);
            if i % 256 == 0 {
                // Let the writer run (connect, fill the socket, block).
                tokio::task::yield_now().await;
            }
        }
        let queued = t0.elapsed();
        let r = sinks[0].report();
        // Measured: 3841 sent, 15071 dropped with the queue full.
        assert!(r.queue_full > 5_000, "{r:?}");
        // Every line is accounted for: sent, dropped, or still queued / in the writer's hands.
        let in_flight = (SINK_QUEUE_LINES + SINK_BATCH) as u64;
        assert!(
            r.sent + r.queue_full + r.not_delivered + in_flight >= 20_000,
            "{r:?}"
        );
        assert_eq!(sinks[0].lost(), r.queue_full + r.not_delivered);
        let t1 = tokio::time::Instant::now();
        close_sinks(&mut sinks, t1 + Duration::from_millis(100)).await;
        let closed = t1.elapsed();
        eprintln!("{r:?}: queued in {queued:?}, closed in {closed:?} (the paused clock)");
        assert_eq!(queued, Duration::ZERO);
        // The stuck writer is given the deadline and no more (the timer's 1 ms grain).
        assert!(
            (Duration::from_millis(100)..=Duration::from_millis(101)).contains(&closed),
            "{closed:?}"
        );
        drop(held);
    }

    /// How long a test waits for the service's answer: a deadline, not a pause.
    const ANSWER_WITHIN: Duration = Duration::from_secs(20);

    /// The service on `cfg` in this process, once its links are open: its task, its stop switch
    /// and the local port of each link (the sources ask for port 0).
    async fn started(
        cfg: Config,
    ) -> (
        tokio::task::JoinHandle<Result<RunSummary, Error>>,
        watch::Sender<bool>,
        Vec<u16>,
    ) {
        let (stop_tx, stop_rx) = watch::channel(false);
        let (ready_tx, ready_rx) = tokio::sync::oneshot::channel();
        let daemon = tokio::spawn(run_reporting_ready(cfg, stop_rx, Some(ready_tx)));
        let ready = ready_rx
            .await
            .expect("the service stopped before it was ready");
        let ports = ready
            .links
            .iter()
            .map(|l| match &l.opening {
                LinkOpening::Open { local: Some(a), .. } => a.port(),
                other => panic!("{}: {other:?}", l.source),
            })
            .collect();
        (daemon, stop_tx, ports)
    }

    /// A `udpin` source on the loopback, its port chosen by the system.
    fn udpin_any_port() -> SourceConfig {
        SourceConfig {
            address: "udpin:127.0.0.1:0".into(),
            payload: crate::config::PayloadKind::Mavlink,
            fields: vec![],
            scales: Default::default(),
        }
    }

    /// Two links, two vehicles: an ArduPilot HEARTBEAT on one does not make the service undo the
    /// other's (PX4) magnetometer data, and the second vehicle's IMU data is calibrated on its
    /// own, not mixed into the first's calibration. With `daemon.links = "merged"` both are one
    /// vehicle.
    #[tokio::test]
    async fn daemon_keeps_links_apart_as_vehicles() {
        use crate::testdata::{taken, SERVICE_IDS};
        use mavlink::dialects::ardupilotmega::{MavType, HEARTBEAT_DATA, HIGHRES_IMU_DATA};
        for merged in [false, true] {
            let dir = tempfile::tempdir().unwrap();
            let mut cfg = Config::default();
            cfg.daemon.sources = vec![udpin_any_port(), udpin_any_port()];
            let report = dir.path().join("report.json");
            cfg.daemon.calibration_dir = dir.path().join("cal").display().to_string();
            cfg.daemon.report = Some(report.display().to_string());
            cfg.daemon.publish = vec![];
            cfg.daemon.links = if merged {
                Links::Merged
            } else {
                Links::Separate
            };
            cfg.daemon.heartbeat_rate_hz = 0.0;
            cfg.fit.refit_every_s = 0.1;
            let (daemon, stop_tx, ports) = started(cfg).await;
            let imu = |i: u64| {
                MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                    time_usec: 1_000_000 + i * 10_000,
                    zacc: -9.81,
                    xmag: 0.2 + 0.001 * i as f32,
                    zmag: 0.4,
                    ..Default::default()
                })
            };
            let (px4, ap) = (
                tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap(),
                tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap(),
            );
            px4.connect(("127.0.0.1", ports[0])).await.unwrap();
            ap.connect(("127.0.0.1", ports[1])).await.unwrap();
            let (mut px4_enc, mut ap_enc) = (MavEncoder::new(1, 1), MavEncoder::new(7, 1));
            // The PX4 vehicle's IMU data first, taken before the other link says anything (it is
            // the one calibrated), then an ArduPilot vehicle on the other link: its HEARTBEAT and
            // IMU data, then more PX4 data.
            for i in 0..30 {
                px4.send(&px4_enc.encode(&imu(i))).await.unwrap();
            }
            taken(&px4, ports[0], SERVICE_IDS, ANSWER_WITHIN, |_| {}).await;
            let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                ..Default::default()
            });
            ap.send(&ap_enc.encode(&hb)).await.unwrap();
            for i in 0..20 {
                ap.send(&ap_enc.encode(&imu(i))).await.unwrap();
            }
            for i in 30..60 {
                px4.send(&px4_enc.encode(&imu(i))).await.unwrap();
            }
            // Everything taken on both links. The service answers the ArduPilot link as the
            // vehicle heard there: its own (system 7) when apart, the one merged vehicle (1).
            taken(&px4, ports[0], SERVICE_IDS, ANSWER_WITHIN, |_| {}).await;
            let ap_system = if merged { 1 } else { 7 };
            taken(&ap, ports[1], (ap_system, 191), ANSWER_WITHIN, |_| {}).await;
            stop_tx.send(true).unwrap();
            let summary = daemon.await.unwrap().unwrap();
            let r: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
            let skipped = &r["input"]["skipped"];
            if merged {
                // One vehicle: the ArduPilot HEARTBEAT holds back the magnetometer data from then
                // on (its COMPASS_* never come), as it does for a single ArduPilot link.
                assert_eq!(summary.samples, 80, "{r}");
                assert!(
                    skipped["mag_awaiting_params"].as_u64().unwrap_or(0) > 0,
                    "{skipped}"
                );
            } else {
                // Two vehicles, each calibrated on its own: the ArduPilot one holds back its own
                // magnetometer data (its COMPASS_* never come), the other's is taken.
                assert_eq!(summary.samples, 60, "{r}");
                assert!(skipped.get("other_vehicle").is_none(), "{skipped}");
                assert!(skipped.get("mag_awaiting_params").is_none(), "{skipped}");
                let v = &r["vehicles"][0];
                assert_eq!(v["system_id"], 7, "{r}");
                assert_eq!(v["input"]["samples"], 20, "{v}");
                assert_eq!(v["input"]["skipped"]["mag_awaiting_params"], 20, "{v}");
            }
        }
    }

    /// Our own frames echoed back (same system and component id) are dropped and counted, never
    /// samples and never a vehicle's HEARTBEAT; our HEARTBEAT goes out on the link, once a second
    /// of the (paused) clock.
    #[tokio::test(start_paused = true)]
    async fn daemon_drops_its_own_echo_and_sends_heartbeats() {
        use mavlink::dialects::ardupilotmega::{MavType, HEARTBEAT_DATA, HIGHRES_IMU_DATA};
        let dir = tempfile::tempdir().unwrap();
        let json = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let mut cfg = Config::default();
        cfg.daemon.sources = vec![udpin_any_port()];
        cfg.daemon.calibration_dir = dir.path().join("cal").display().to_string();
        cfg.daemon.report = Some(dir.path().join("report.json").display().to_string());
        cfg.daemon.publish = vec![format!("udp:{}", json.local_addr().unwrap())];
        // Not 191: the ArduPilot detection already passes over component 191, whoever sends it.
        cfg.daemon.system_id = 1;
        cfg.daemon.component_id = 190;
        cfg.fit.refit_every_s = 0.1;
        let t0 = tokio::time::Instant::now();
        let (daemon, stop_tx, ports) = started(cfg).await;
        let port = ports[0];
        let peer = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        peer.connect(("127.0.0.1", port)).await.unwrap();
        let imu = |i: u64| {
            MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                time_usec: 1_000_000 + i * 10_000,
                zacc: -9.81,
                xmag: 0.2,
                zmag: 0.4,
                ..Default::default()
            })
        };
        let (mut echo, mut fc) = (MavEncoder::new(1, 190), MavEncoder::new(1, 1));
        // Our own id on an ArduPilot HEARTBEAT and on IMU frames: none of it is taken.
        let ap = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            ..Default::default()
        });
        peer.send(&echo.encode(&ap)).await.unwrap();
        for i in 0..40 {
            peer.send(&echo.encode(&imu(i))).await.unwrap();
        }
        for i in 0..30 {
            peer.send(&fc.encode(&imu(100 + i))).await.unwrap();
        }
        let mut heartbeats = vec![];
        let mut heard = |f: &crate::io::decode::Frame| {
            if let MavMessage::HEARTBEAT(h) = &f.message {
                heartbeats.push((f.system_id, f.component_id, h.mavtype, h.autopilot));
            }
        };
        crate::testdata::taken(&peer, port, (1, 190), ANSWER_WITHIN, &mut heard).await;
        // What comes back until 2.3 s of the clock after the start.
        let mut dec = crate::io::decode::FrameDecoder::new();
        let mut buf = vec![0u8; 65_536];
        let until = t0 + Duration::from_millis(2300);
        while let Ok(Ok(n)) = tokio::time::timeout_at(until, peer.recv(&mut buf)).await {
            dec.push(&buf[..n]).iter().for_each(&mut heard);
        }
        stop_tx.send(true).unwrap();
        let summary = daemon.await.unwrap().unwrap();
        assert_eq!(summary.samples, 30);
        // At 1 s and 2 s (the one at the start went nowhere: no peer had sent anything yet).
        assert_eq!(heartbeats.len(), 2, "{heartbeats:?}");
        for h in &heartbeats {
            assert_eq!(
                *h,
                (
                    1,
                    190,
                    MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                    MavAutopilot::MAV_AUTOPILOT_INVALID
                )
            );
        }
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap())
                .unwrap();
        assert_eq!(
            report["input"]["skipped"]["own_echo"], 41,
            "{}",
            report["input"]
        );
        assert!(report["input"]["skipped"]
            .get("mag_awaiting_params")
            .is_none());
        let mut lines = vec![];
        while let Ok(Ok(n)) =
            tokio::time::timeout(Duration::from_millis(50), json.recv(&mut buf)).await
        {
            lines.push(String::from_utf8_lossy(&buf[..n]).to_string());
        }
        // One line says the link is open, on the port the system chose.
        let ready: Vec<serde_json::Value> = lines
            .iter()
            .map(|l| serde_json::from_str::<serde_json::Value>(l.trim()).unwrap())
            .filter(|v| v["type"] == "ready")
            .collect();
        assert_eq!(ready.len(), 1, "{lines:?}");
        let ready = &ready[0];
        assert_eq!(ready["schema"], "imucald.live/1");
        assert_eq!(ready["links"][0]["source"], "udpin:127.0.0.1:0");
        assert_eq!(ready["links"][0]["state"], "open");
        assert_eq!(
            ready["links"][0]["local"],
            format!("127.0.0.1:{port}").as_str()
        );
        assert!(
            lines.iter().all(|l| !l.contains("ArduPilot")),
            "our own HEARTBEAT was taken for a vehicle's: {lines:?}"
        );
    }

    #[test]
    fn daemon_json_sink_addresses_are_checked() {
        for bad in ["udp:nowhere", "tcp:1.2.3.4", "file:/tmp/x", ""] {
            let e = Sink::open(bad, 1).err().expect(bad).to_string();
            assert!(e.contains("publish"), "{e}");
        }
    }

    #[test]
    fn daemon_cadences_fire_on_their_grid_points_and_skip_what_was_missed() {
        let epoch = tokio::time::Instant::now();
        let ms = |n: u64| epoch + Duration::from_millis(n);
        // 10 Hz asked by a 20 ms clock: every fifth tick, the first at the epoch.
        let mut c = Cadence::new(epoch, 10.0);
        let fired: Vec<u64> = (0..=25u64)
            .map(|k| 20 * k)
            .filter(|&t| c.due(ms(t)))
            .collect();
        assert_eq!(fired, [0, 100, 200, 300, 400, 500]);
        // 30 Hz (33.3 ms) off the 20 ms grid: at the first tick at or after each due time, and the
        // mean rate is kept (6 in 200 ms).
        let mut c = Cadence::new(epoch, 30.0);
        let fired: Vec<u64> = (0..10u64)
            .map(|k| 20 * k)
            .filter(|&t| c.due(ms(t)))
            .collect();
        assert_eq!(fired, [0, 40, 80, 100, 140, 180]);
        // A stall of a second: one output, then back on the grid (no burst making up for it).
        let mut c = Cadence::new(epoch, 10.0);
        assert!(c.due(ms(0)));
        assert!(c.due(ms(1030)));
        assert!(!c.due(ms(1060)) && !c.due(ms(1080)));
        assert!(c.due(ms(1100)));
    }
}
