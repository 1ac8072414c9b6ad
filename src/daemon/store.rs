//! The calibration kept on disk (`calibration.json` and its exports), the acceptance of a new
//! calibration against the one in use (held-out points), and the files the service writes off the
//! run loop.

use super::*;
use crate::fit::FitFailure;
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
    pub filter: Option<crate::fusion::FilterState>,
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
        }
    }
    pub fn mag_cal(&self) -> Option<Calibration> {
        self.mag.as_ref()?.calibration()
    }
    pub fn accel_cal(&self) -> Option<Calibration> {
        self.accel.as_ref()?.calibration()
    }
    /// Every compass's magnetometer calibration in uT with its compass id (what parameters hold).
    pub fn mags_ut(&self) -> Vec<(usize, Calibration)> {
        let primary = self.mag.as_ref().and_then(|m| m.calibration_ut());
        let others = self.instances.iter().filter_map(|i| {
            let c = i.mag.as_ref()?.calibration_ut()?;
            Some((i.compass_id as usize, c))
        });
        primary
            .map(|c| (self.compass_id as usize, c))
            .into_iter()
            .chain(others)
            .collect()
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
    let (m, a) = (store.mag_cal(), store.accel_cal());
    let mags = store.mags_ut();
    crate::publish::write_atomic(
        &dir.join("ardupilot.parm"),
        crate::export::ardupilot_file(&mags, a.as_ref()).as_bytes(),
    )?;
    crate::publish::write_atomic(
        &dir.join("px4.params"),
        crate::export::px4_file(&mags, a.as_ref()).as_bytes(),
    )?;
    crate::publish::write_atomic(
        &dir.join("fusion.h"),
        crate::export::fusion_file(m.as_ref(), a.as_ref()).as_bytes(),
    )?;
    // The JSON last: it is what a restart loads.
    crate::publish::write_json(&dir.join(STORE_FILE), store)
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
/// ([`crate::pipeline::hold_out`]): a new calibration is judged on those against the current one.
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
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Written {
    Calibration,
    Report,
}

impl WriteJob {
    /// Write it (blocking: temp file, fsync, rename). Returns which file it was, and how it went.
    pub(super) fn run(self) -> (Written, Result<(), Error>) {
        match self {
            WriteJob::Store(dir, store) => (Written::Calibration, save_store(&dir, &store)),
            WriteJob::Report(path, report) => {
                (Written::Report, crate::publish::write_json(&path, &report))
            }
        }
    }
}

/// One file kept up to date off the run loop: at most one write in flight on the blocking pool;
/// content asked for meanwhile waits, and newer content replaces it (only the latest is written).
/// An fsync on a slow card can take a good part of a second; the live outputs must not wait for it.
#[derive(Default)]
pub(super) struct Writes {
    pub(super) job: Option<tokio::task::JoinHandle<(Written, Result<(), Error>)>>,
    pub(super) next: Option<WriteJob>,
}

impl Writes {
    pub(super) fn want(&mut self, job: WriteJob) {
        self.next = Some(job);
    }

    /// Start the waiting write if none is in flight.
    pub(super) fn start(&mut self) {
        if self.job.is_none() {
            if let Some(job) = self.next.take() {
                self.job = Some(tokio::task::spawn_blocking(move || job.run()));
            }
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
    /// Write the calibration store now (at shutdown; while running, `store_writes` does it).
    pub(super) async fn save(&mut self) {
        self.store.filter = self.filter_state();
        let job = WriteJob::Store(self.cal_dir.clone(), Box::new(self.store.clone()));
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
            Ok((Written::Calibration, Ok(()))) => {
                tracing::info!("calibration written to {}", self.cal_dir.display())
            }
            Ok((Written::Calibration, Err(e))) => {
                self.status(
                    3,
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

    /// The report as it stands, ready to be written (none without `--report` or before a fit).
    pub(super) fn report_job(&self) -> Option<WriteJob> {
        let (Some(path), Some(results)) =
            (self.report.clone(), self.tracks[0].last_results.clone())
        else {
            return None;
        };
        let mut stats = self
            .primary_vehicle
            .map(|v| self.vehicles[v].conv.stats.clone())
            .unwrap_or_default();
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
        stats.skip_n("mag_awaiting_params", self.mag_awaiting_params);
        for c in &self.sample_clocks {
            stats.time.add(&c.stats);
        }
        stats.skip_n("own_echo", self.own_echo);
        let label = self
            .links
            .iter()
            .map(|l| l.label.clone())
            .collect::<Vec<_>>()
            .join(",");
        let input = crate::report::InputReport::new(
            "live",
            Some(label),
            self.primary_vehicle
                .and_then(|v| self.vehicles[v].conv.instance())
                .map(String::from),
            &stats,
            self.tracks[0].pipe.samples,
            self.tracks[0].pipe.last_t,
        );
        let pipe = &self.tracks[0].pipe;
        let mut report = crate::replay::make_report(input, pipe, &results, self.declination);
        report.instances = self.instance_reports(&report.calibration);
        report.outputs = Some(self.outputs_report());
        Some(WriteJob::Report(path, Box::new(report)))
    }
}
