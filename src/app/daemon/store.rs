//! The calibration kept on disk (`calibration.json` and its exports), the acceptance of a new
//! calibration against the one in use (held-out points), and the files the service writes off the
//! run loop.

use super::*;
use crate::calib::fit::FitFailure;
pub use crate::io::identity::Hardware;
use crate::report::CalStatus;

/// What is kept on disk between runs (`calibration.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredCalibration {
    pub schema: String,
    /// The primary instance's compass id (the index its flight-stack parameters are named for:
    /// COMPASS_OFS / CAL_MAG0 for 0, COMPASS_OFS2 / CAL_MAG1 for 1 ...).
    #[serde(default)]
    pub compass_id: u8,
    pub mag: Option<SensorCalibration>,
    pub accel: Option<SensorCalibration>,
    pub gyro: Option<GyroCalibration>,
    /// The stream's other IMU instances, each calibrated on its own (a vehicle with several
    /// compasses).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub instances: Vec<StoredInstance>,
    /// What the orientation filter had learnt (residual gyro bias, field reference), restored on
    /// start.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub filter: Option<crate::attitude::fusion::FilterState>,
    /// The vehicle this calibration belongs to (the live service, MAVLink links): after a restart
    /// it goes to that vehicle again, whichever vehicle is heard first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicle: Option<StoredVehicle>,
}

/// A vehicle as the live service knows it: the link it is heard on, its system id, what fed the
/// calibration and, where the link carries them, the ids of its hardware.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq)]
pub struct StoredVehicle {
    /// The link's address as configured (`udpin:0.0.0.0:14550`, `serial:/dev/ttyACM0:115200`,
    /// `sim:tumble`).
    pub link: String,
    /// Its MAVLink system id (0 for a simulator).
    pub system_id: u8,
    /// What the calibration was made from: a vehicle on a link, or a simulator (never resumed
    /// onto a vehicle). Files without it are a vehicle's.
    #[serde(default)]
    pub source: VehicleSource,
    /// The flight controller's id and the compasses' device ids, as far as the link told them:
    /// a calibration is resumed only onto the same hardware where both sides know an id.
    #[serde(default, skip_serializing_if = "Hardware::is_unknown")]
    pub hardware: Hardware,
}

/// What a stored calibration was made from.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum VehicleSource {
    /// A vehicle on a MAVLink link.
    #[default]
    Vehicle,
    /// The built-in simulator (`sim:` links).
    Simulator,
}

impl StoredVehicle {
    /// A simulator's record.
    pub(super) fn simulator(link: &str) -> StoredVehicle {
        StoredVehicle {
            link: link.to_string(),
            system_id: 0,
            source: VehicleSource::Simulator,
            hardware: Hardware::default(),
        }
    }

    /// How a message names it: its hardware's tag when known, else its link and system id.
    pub(super) fn describe(&self) -> String {
        match (self.source, self.hardware.tag()) {
            (VehicleSource::Simulator, _) => format!("the simulator {}", self.link),
            (_, Some(tag)) => format!("{tag} (system {} on {})", self.system_id, self.link),
            (_, None) => format!("system {} on {}", self.system_id, self.link),
        }
    }
}

/// The calibration in use of an IMU instance other than the primary.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredInstance {
    /// `highres_imu:1`, `scaled_imu2`, ...
    pub instance: String,
    /// MAG_CAL_* `compass_id`, and the index of its flight-stack parameters.
    pub compass_id: u8,
    pub mag: Option<SensorCalibration>,
    pub accel: Option<SensorCalibration>,
}

pub const STORE_SCHEMA: &str = "imucald.calibration/1";
pub const STORE_FILE: &str = "calibration.json";

impl StoredCalibration {
    pub(super) fn empty() -> Self {
        StoredCalibration {
            schema: STORE_SCHEMA.into(),
            compass_id: 0,
            mag: None,
            accel: None,
            gyro: None,
            instances: Vec::new(),
            filter: None,
            vehicle: None,
        }
    }
    pub fn mag_cal(&self) -> Option<Calibration> {
        self.mag.as_ref()?.calibration()
    }
    pub(crate) fn accel_cal(&self) -> Option<Calibration> {
        self.accel.as_ref()?.calibration()
    }
    /// Every compass's magnetometer calibration in uT with its compass id (what parameters hold).
    pub(crate) fn mags_ut(&self) -> Vec<crate::calib::export::CompassExport> {
        let export = |k: u8, m: &crate::report::SensorCalibration| {
            let mut e =
                crate::calib::export::CompassExport::determined(k as usize, m.calibration_ut()?);
            e.unknown = m.unknowns();
            Some(e)
        };
        let primary = self.mag.as_ref().and_then(|m| export(self.compass_id, m));
        let others = self
            .instances
            .iter()
            .filter_map(|i| export(i.compass_id, i.mag.as_ref()?));
        primary.into_iter().chain(others).collect()
    }
    /// The stored entry of the instance with compass id `compass_id` (made when missing).
    pub(super) fn instance_mut(&mut self, name: &str, compass_id: u8) -> &mut StoredInstance {
        let k = match self
            .instances
            .iter()
            .position(|i| i.compass_id == compass_id)
        {
            Some(k) => k,
            None => {
                self.instances.push(StoredInstance {
                    instance: name.to_string(),
                    compass_id,
                    mag: None,
                    accel: None,
                });
                self.instances.len() - 1
            }
        };
        &mut self.instances[k]
    }
}

/// Load the last good calibration; a missing file is no calibration, a damaged one is an error that
/// says which file.
pub fn load_store(dir: &Path) -> Result<Option<StoredCalibration>, Error> {
    let p = dir.join(STORE_FILE);
    match std::fs::read_to_string(&p) {
        Ok(text) => serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| Error::Format {
                path: p,
                message: format!("not a calibration file ({e}); move it away to start fresh"),
            }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(Error::Read { path: p, source }),
    }
}

/// Write the calibration and its exports atomically into `dir`.
pub fn save_store(dir: &Path, store: &StoredCalibration) -> Result<(), Error> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let a = store.accel_cal();
    let mags = store.mags_ut();
    let m = mags.iter().find(|c| c.index == store.compass_id as usize);
    // The primary compass's motor term, when its vector calibration determined one.
    let motors: Vec<(usize, crate::types::Vec3)> = store
        .mag
        .as_ref()
        .and_then(|m| m.motor_ut_per_a())
        .map(|k| (store.compass_id as usize, k))
        .into_iter()
        .collect();
    crate::io::publish::write_atomic(
        &dir.join("ardupilot.parm"),
        crate::calib::export::ardupilot_file(&mags, &[], &motors, a.as_ref()).as_bytes(),
    )?;
    crate::io::publish::write_atomic(
        &dir.join("px4.params"),
        crate::calib::export::px4_file(&mags, &[], &motors, a.as_ref()).as_bytes(),
    )?;
    crate::io::publish::write_atomic(
        &dir.join("fusion.h"),
        crate::calib::export::fusion_file(m, a.as_ref()).as_bytes(),
    )?;
    // The JSON last: it is what a restart loads.
    crate::io::publish::write_json(&dir.join(STORE_FILE), store)
}

/// RMS of |calibrated| - radius over points (calibrated units).
fn rms_on(cal: &Calibration, radius: f64, pts: &[Vec3]) -> f64 {
    if pts.is_empty() {
        return f64::INFINITY;
    }
    (pts.iter()
        .map(|p| (norm(&cal.apply(p)) - radius).powi(2))
        .sum::<f64>()
        / pts.len() as f64)
        .sqrt()
}

/// The live service holds every this-many-th kept magnetometer point and pose out of its fits
/// ([`crate::calib::pipeline::hold_out`]): a new calibration is judged on those against the current one.
pub const HOLD_OUT_EVERY: usize = 5;

/// How much worse (relative RMS) on the held-out points than the current calibration a new one may
/// be and still replace it (two fits of the same field differ by noise).
pub const ACCEPT_MARGIN: f64 = 0.02;

/// Whether a failed magnetometer fit is reported (MAG_CAL_REPORT with a failure status), as
/// ArduPilot's calibrator does: only once the run's completion reached 100 % (the data covered the
/// sphere, about a known centre) and the fit still failed for a reason other than still collecting.
pub fn failure_report_due(mag: &SensorCalibration, completion_pct: u8) -> bool {
    let collecting = matches!(
        mag.failure,
        Some(FitFailure::Coverage | FitFailure::NotEnoughSamples)
    );
    mag.status != CalStatus::Ok && !collecting && completion_pct >= 100
}

/// Why a new calibration did not replace the current one.
#[derive(Debug, Clone, PartialEq)]
pub enum NotReplaced {
    /// The fit failed a check (`failure`: the report's reason).
    Failed {
        failure: Option<FitFailure>,
        detail: String,
    },
    /// A calibration is in use and the new fit had no points held out to compare them on.
    NothingHeldOut,
    /// Worse than the current calibration on the held-out points (RMS of |calibrated| - radius).
    WorseOnHeldOut {
        points: usize,
        rms_new: f64,
        rms_current: f64,
    },
}

impl std::fmt::Display for NotReplaced {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NotReplaced::Failed { failure, detail } => {
                write!(f, "failed {}: {detail}", failure.map_or("?", FitFailure::name))
            }
            NotReplaced::NothingHeldOut => {
                write!(f, "too few points to hold out a comparison with the current calibration")
            }
            NotReplaced::WorseOnHeldOut {
                points,
                rms_new,
                rms_current,
            } => write!(
                f,
                "worse than the current calibration on {points} points held out of the fit (rms {rms_new:.4} vs {rms_current:.4})"
            ),
        }
    }
}

/// Whether a new fit replaces the current calibration: it passed its checks, and (when there is a
/// current one) it is better on the points held out of its fit, or worse by at most
/// [`ACCEPT_MARGIN`].
pub fn accept(new: &SensorResult, current: Option<&SensorCalibration>) -> Result<(), NotReplaced> {
    let Some(nc) = new.calibration else {
        return Err(NotReplaced::Failed {
            failure: new.report.failure,
            detail: new.report.detail.clone().unwrap_or_default(),
        });
    };
    let Some((cur, cc)) = current.and_then(|c| c.calibration().map(|cc| (c, cc))) else {
        return Ok(());
    };
    let held = &new.held_out;
    if held.is_empty() {
        return Err(NotReplaced::NothingHeldOut);
    }
    let rms_new = rms_on(&nc, new.report.radius, held);
    let rms_current = rms_on(&cc, cur.radius, held);
    if rms_new > rms_current * (1.0 + ACCEPT_MARGIN) + 1e-12 {
        return Err(NotReplaced::WorseOnHeldOut {
            points: held.len(),
            rms_new,
            rms_current,
        });
    }
    Ok(())
}
/// A file the service writes: the calibration store, or the report.
pub(super) enum WriteJob {
    Store(PathBuf, Box<StoredCalibration>),
    Report(PathBuf, Box<crate::report::Report>),
}

/// Which file a finished write was.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Written {
    /// The calibration in this directory.
    Calibration(PathBuf),
    Report,
}

impl WriteJob {
    /// Write it (blocking: temp file, fsync, rename). Returns which file it was, and how it went.
    pub(super) fn run(self) -> (Written, Result<(), Error>) {
        match self {
            WriteJob::Store(dir, store) => {
                let r = save_store(&dir, &store);
                (Written::Calibration(dir), r)
            }
            WriteJob::Report(path, report) => {
                // Its folder (e.g. `calibration/`) may not exist before the first calibration.
                let made = match path.parent().filter(|d| !d.as_os_str().is_empty()) {
                    Some(d) => std::fs::create_dir_all(d).map_err(|source| Error::Write {
                        path: d.to_path_buf(),
                        source,
                    }),
                    None => Ok(()),
                };
                (
                    Written::Report,
                    made.and_then(|()| crate::io::publish::write_json(&path, &report)),
                )
            }
        }
    }
}

/// Files kept up to date off the run loop: at most one write in flight on the blocking pool;
/// content asked for meanwhile waits, and newer content for the same file replaces it (only the
/// latest is written; one waiting write per file, so the queue is as long as the vehicles' files).
/// An fsync on a slow card can take a good part of a second; the live outputs must not wait for it.
#[derive(Default)]
pub(super) struct Writes {
    pub(super) job: Option<tokio::task::JoinHandle<(Written, Result<(), Error>)>>,
    pub(super) next: Vec<WriteJob>,
}

impl WriteJob {
    fn path(&self) -> &Path {
        match self {
            WriteJob::Store(dir, _) => dir,
            WriteJob::Report(path, _) => path,
        }
    }
}

impl Writes {
    pub(super) fn want(&mut self, job: WriteJob) {
        match self.next.iter().position(|j| j.path() == job.path()) {
            Some(k) => self.next[k] = job,
            None => self.next.push(job),
        }
    }

    /// Start the oldest waiting write if none is in flight.
    pub(super) fn start(&mut self) {
        if self.job.is_none() && !self.next.is_empty() {
            let job = self.next.remove(0);
            self.job = Some(tokio::task::spawn_blocking(move || job.run()));
        }
    }

    /// The write in flight (polled only when there is one).
    pub(super) async fn done(
        &mut self,
    ) -> Result<(Written, Result<(), Error>), tokio::task::JoinError> {
        match self.job.as_mut() {
            Some(j) => {
                let r = j.await;
                self.job = None;
                r
            }
            None => std::future::pending().await,
        }
    }
}
impl State {
    /// Write calibrated vehicle `c`'s store now (at shutdown; while running, `store_writes`
    /// does it).
    pub(super) async fn save(&mut self, c: usize) {
        let cal = &mut self.cals[c];
        cal.store.filter = cal.filter_state();
        let job = WriteJob::Store(cal.cal_dir.clone(), Box::new(cal.store.clone()));
        let r = tokio::task::spawn_blocking(move || job.run()).await;
        self.written(r).await;
    }

    /// Say what came of a background write: a calibration that could not be written is reported
    /// (the previous file is kept: writes are atomic), a report only logged.
    pub(super) async fn written(
        &mut self,
        r: Result<(Written, Result<(), Error>), tokio::task::JoinError>,
    ) {
        match r {
            Ok((Written::Calibration(dir), Ok(()))) => {
                tracing::info!("calibration written to {}", dir.display())
            }
            Ok((Written::Calibration(_), Err(e))) => {
                self.status(
                    MavSeverity::MAV_SEVERITY_ERROR,
                    format!("calibration not written (the previous file is kept): {e}"),
                )
                .await
            }
            Ok((Written::Report, Ok(()))) => {}
            Ok((Written::Report, Err(e))) => tracing::warn!("report not written: {e}"),
            Err(e) => tracing::error!("file write task failed: {e}"),
        }
    }

    /// Write the report now (at shutdown).
    pub(super) async fn write_report(&mut self) {
        if let Some(job) = self.report_job() {
            let r = tokio::task::spawn_blocking(move || job.run()).await;
            self.written(r).await;
        }
    }

    /// The report as it stands, ready to be written (none without `--report` or before a fit):
    /// the first vehicle's, with a block per further vehicle.
    pub(super) fn report_job(&self) -> Option<WriteJob> {
        let path = self.report.clone()?;
        let mut report = self.vehicle_report(0).1?;
        report.outputs = Some(self.outputs_report());
        report.vehicles = (1..self.cals.len())
            .filter_map(|c| {
                let tag = self.vehicle_tag(c)?;
                let (input, r) = self.vehicle_report(c);
                Some(crate::report::VehicleReport {
                    link: tag.link,
                    system_id: tag.system_id,
                    calibration_dir: self.cals[c].cal_dir.display().to_string(),
                    input,
                    calibration: r.as_ref().map(|r| r.calibration.clone()),
                    instances: r.map(|r| r.instances).unwrap_or_default(),
                })
            })
            .collect();
        Some(WriteJob::Report(path, Box::new(report)))
    }

    /// Calibrated vehicle `c`'s input, and its report (none before its first fit). The first
    /// vehicle's input also counts what the service as a whole read and skipped (text lines,
    /// other links, queues, echoes).
    fn vehicle_report(
        &self,
        c: usize,
    ) -> (crate::report::InputReport, Option<crate::report::Report>) {
        let cal = &self.cals[c];
        let vehicle = cal.vehicle.map(|v| &self.vehicles[v]);
        let mut stats = vehicle.map(|v| v.conv.stats.clone()).unwrap_or_default();
        let label = if c == 0 {
            self.service_input(&mut stats);
            let labels: Vec<_> = self.links.iter().map(|l| l.label.clone()).collect();
            labels.join(",")
        } else {
            let l = vehicle.map_or(0, |v| v.key.0);
            self.links
                .get(l)
                .map(|l| l.label.clone())
                .unwrap_or_default()
        };
        let pipe = &cal.tracks[0].pipe;
        let input = crate::report::InputReport::new(
            "live",
            Some(label),
            vehicle.and_then(|v| v.conv.instance()).map(String::from),
            &stats,
            cal.tracks[0].samples_in,
            pipe.last_t,
        );
        let Some(results) = cal.tracks[0].last_results.as_ref() else {
            return (input, None);
        };
        let mut report =
            crate::app::replay::make_report(input.clone(), pipe, results, self.declination);
        report.instances = self.instance_reports(c, &report.calibration);
        (input, Some(report))
    }

    /// What the service as a whole read and skipped, added to `stats`.
    fn service_input(&self, stats: &mut crate::io::decode::DecodeStats) {
        stats.records += self.line_stats.records;
        stats.counts.add(&self.line_stats.counts);
        stats.skip_n("other_vehicle", self.other_vehicle_samples);
        stats.skip_n("too_many_instances", self.other_instance_samples);
        for l in &self.links {
            if let Ok(d) = l.handle.decode_stats.lock() {
                for (k, v) in &d.skipped {
                    *stats.skipped.entry(k.clone()).or_insert(0) += v;
                }
                stats.time.add(&d.time);
            }
            let dropped = l
                .handle
                .counters
                .inbound_dropped
                .load(std::sync::atomic::Ordering::Relaxed);
            stats.skip_n("queue_full", dropped);
        }
        for c in &self.sample_clocks {
            stats.time.add(&c.stats);
        }
        stats.skip_n("own_echo", self.own_echo);
    }
}

/// A calibration read from a file (`calibration.json` of the service, or a replay's report), to
/// apply to a log's samples (e.g. before `eval`): each part only where it passed.
#[derive(Debug, Clone, Default)]
pub struct LoadedCalibration {
    pub mag: Option<crate::calib::model::Calibration>,
    pub accel: Option<crate::calib::model::Calibration>,
    /// Gyro bias, rad/s.
    pub gyro_bias: Option<crate::types::Vec3>,
}

impl LoadedCalibration {
    /// Read `path`: the service's `calibration.json` (`imucald.calibration/1`) or a replay report
    /// (`imucald.report/1`). Err: unreadable, or neither.
    pub fn load(path: &Path) -> Result<LoadedCalibration, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let bad = |m: String| Error::Format {
            path: path.to_path_buf(),
            message: m,
        };
        let v: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
        let gyro = |g: &crate::report::GyroCalibration| {
            (g.status == crate::report::CalStatus::Ok && g.units == crate::types::CalUnits::RadS)
                .then_some(g.bias)
        };
        match v["schema"].as_str() {
            Some(s) if s == STORE_SCHEMA => {
                let st: StoredCalibration = serde_json::from_value(v)
                    .map_err(|e| bad(format!("a calibration file, but: {e}")))?;
                Ok(LoadedCalibration {
                    mag: st.mag.as_ref().and_then(|m| m.calibration()),
                    accel: st.accel.as_ref().and_then(|a| a.calibration()),
                    gyro_bias: st.gyro.as_ref().and_then(gyro),
                })
            }
            Some(s) if s == crate::report::SCHEMA => {
                let r: crate::report::Report = serde_json::from_value(v)
                    .map_err(|e| bad(format!("a replay report, but: {e}")))?;
                Ok(LoadedCalibration {
                    mag: r.calibration.mag.calibration(),
                    accel: r.calibration.accel.calibration(),
                    gyro_bias: gyro(&r.calibration.gyro),
                })
            }
            other => Err(bad(format!(
                "schema {other:?}: give a calibration.json (the service's) or a replay's --report file"
            ))),
        }
    }

    /// `samples` with the calibration applied (raw sensor axes in, calibrated out).
    pub fn apply(&self, samples: &[crate::types::Sample]) -> Vec<crate::types::Sample> {
        samples
            .iter()
            .map(|s| {
                let mut c = *s;
                if let Some(m) = &self.mag {
                    c.mag_ut = s.mag_ut.map(|v| m.apply(&v));
                }
                if let Some(a) = &self.accel {
                    c.accel_mps2 = s.accel_mps2.map(|v| a.apply(&v));
                }
                if let Some(b) = &self.gyro_bias {
                    c.gyro_rad_s = s
                        .gyro_rad_s
                        .map(|g| [g[0] - b[0], g[1] - b[1], g[2] - b[2]]);
                }
                c
            })
            .collect()
    }
}
