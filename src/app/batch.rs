//! `imucald replay` over many logs: the logs found under the given paths, replayed one per worker
//! thread through [`crate::app::replay::replay`], gathered into one table (a row per log and
//! compass) and one JSON-lines file of the full reports.
//!
//! Each log ends one of four ways: calibrated with something to load on the vehicle
//! ([`loadable`]), calibrated with nothing to load (a gyro bias only, or compasses whose verdict is
//! to keep the vehicle's), nothing calibrated, or not replayed. A log that cannot be replayed
//! (unreadable, unknown format) or that calibrates nothing is a row with its failure, and a panic
//! in one log's replay is caught on its worker and reported the same way: the batch always goes on. The work queue and the result queue are bounded (twice the
//! workers); a full queue makes its sender wait, nothing is dropped.

use crate::app::replay::{calibrated_nothing, loadable, replay, ReplayOptions};
use crate::config::Config;
use crate::error::Error;
use crate::io::publish::{write_atomic_with, AtomicFile};
use crate::report::Report;
use serde_json::Value;
use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::sync::Mutex;

/// The file name endings of the logs a directory is searched for (any case): what `replay` reads.
pub const LOG_SUFFIXES: [&str; 5] = [".tlog", ".csv", ".csv.gz", ".bin", ".ulg"];

/// Queued logs (and queued results) per worker: enough that no worker waits for the next log.
const QUEUE_PER_WORKER: usize = 2;

/// The table's columns, in order: the same as the Parquet rows of `examples_py/dask_fleet.py`,
/// with its 9-value `matrix` spread over `matrix_RC` (row R, column C; calibrated = matrix *
/// (raw - offset)).
pub(crate) const COLUMNS: [&str; 33] = [
    "log",
    "instance",
    "primary",
    "status",
    "failure",
    "detail",
    "method",
    "model",
    "units",
    "offset_x",
    "offset_y",
    "offset_z",
    "matrix_00",
    "matrix_01",
    "matrix_02",
    "matrix_10",
    "matrix_11",
    "matrix_12",
    "matrix_20",
    "matrix_21",
    "matrix_22",
    "mounting_verdict",
    "verdict",
    "load",
    "load_reason",
    "rung",
    "radius_ut",
    "rms_ut",
    "coverage_regions",
    "heldout_norm_pct",
    "heldout_dip_deg",
    "vehicle_norm_pct",
    "vehicle_dip_deg",
];

/// The name a log of one unnamed stream (a CSV) is judged and decided under in the report's
/// `quality` and `load`.
const UNNAMED_INSTANCE: &str = "primary";

/// A batch's settings.
#[derive(Debug, Clone, Default)]
pub struct BatchOptions {
    /// Worker threads; `None` (the default): [`std::thread::available_parallelism`]. Never more
    /// than the logs.
    pub jobs: Option<usize>,
    /// Each log's replay (its `format` and `refits`; the per-log files stay unset in a batch).
    pub replay: ReplayOptions,
    /// The table (CSV, [`COLUMNS`]); default: none written.
    pub table: Option<PathBuf>,
    /// The full reports, one JSON line per log in the order of the logs; default: none written.
    pub reports: Option<PathBuf>,
}

/// Why a file met in a directory is not replayed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkipReason {
    /// Its name has none of the [`LOG_SUFFIXES`].
    NotALogName,
    /// A symbolic link to a directory (not followed, so that a link cannot make a loop).
    DirectoryLink,
    /// Neither a file nor a directory (a socket, a device, a dangling link).
    NotAFile,
}

impl SkipReason {
    /// How the summary says it.
    pub fn name(self) -> &'static str {
        match self {
            SkipReason::NotALogName => "not a log name",
            SkipReason::DirectoryLink => "link to a directory",
            SkipReason::NotAFile => "not a file",
        }
    }
}

/// The logs to replay.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Found {
    /// In the order given; each directory's logs sorted by path.
    pub logs: Vec<PathBuf>,
    /// What the directories held besides logs.
    pub skipped: Vec<(PathBuf, SkipReason)>,
}

/// The logs of `paths`: a file is taken as given (whatever its name: a file that is no log becomes
/// a failure row); a directory gives every file under it, recursively, whose name ends with one of
/// the [`LOG_SUFFIXES`], sorted.
pub fn find_logs(paths: &[PathBuf]) -> Result<Found, Error> {
    let mut found = Found::default();
    for p in paths {
        if p.is_dir() {
            let mut logs = vec![];
            walk(p, &mut logs, &mut found.skipped)?;
            logs.sort();
            found.logs.extend(logs);
        } else {
            found.logs.push(p.clone());
        }
    }
    Ok(found)
}

/// Whether `path`'s name ends with one of the [`LOG_SUFFIXES`] (any case).
fn is_log_name(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    LOG_SUFFIXES.iter().any(|s| name.ends_with(s))
}

/// The logs under `dir` into `logs`, the other entries into `skipped`.
fn walk(
    dir: &Path,
    logs: &mut Vec<PathBuf>,
    skipped: &mut Vec<(PathBuf, SkipReason)>,
) -> Result<(), Error> {
    let read_err = |source| Error::Read {
        path: dir.to_path_buf(),
        source,
    };
    for entry in std::fs::read_dir(dir).map_err(read_err)? {
        let entry = entry.map_err(read_err)?;
        let path = entry.path();
        let kind = entry.file_type().map_err(read_err)?;
        if kind.is_dir() {
            walk(&path, logs, skipped)?;
            continue;
        }
        // A link counts as what it points to, except a directory.
        let target = if kind.is_symlink() {
            std::fs::metadata(&path).ok().map(|m| m.file_type())
        } else {
            Some(kind)
        };
        match target {
            Some(t) if t.is_dir() => skipped.push((path, SkipReason::DirectoryLink)),
            Some(t) if t.is_file() && is_log_name(&path) => logs.push(path),
            Some(t) if t.is_file() => skipped.push((path, SkipReason::NotALogName)),
            _ => skipped.push((path, SkipReason::NotAFile)),
        }
    }
    Ok(())
}

/// Where a batch stands, for a progress bar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Progress {
    /// Logs replayed so far (calibrated or failed).
    pub done: usize,
    pub total: usize,
    /// Logs so far that calibrated nothing or could not be replayed.
    pub failed: usize,
}

/// What a batch did. Every log is counted once, in `to_load`, `nothing_to_load`,
/// `nothing_calibrated` or `errors`.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchSummary {
    pub logs: usize,
    /// Logs that calibrated something to load on the vehicle ([`loadable`]).
    pub to_load: usize,
    /// Logs that calibrated something, but nothing to load: a gyro bias only, or compasses that
    /// are not to load (the vehicle's is as good, the fit held out failed, ...).
    pub nothing_to_load: usize,
    /// Logs replayed that calibrated nothing.
    pub nothing_calibrated: usize,
    /// Logs that could not be replayed (an error or a panic).
    pub errors: usize,
    /// Of `errors`, the panics caught.
    pub panics: usize,
    /// Worker threads used.
    pub jobs: usize,
    /// The rows, in the order of the logs (also in the table, when one was asked for).
    pub(crate) rows: Vec<Row>,
    /// The files written.
    pub written: Vec<PathBuf>,
}

/// How a batch ended as a whole, for its exit status.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchEnd {
    /// Every log calibrated something, and some log has something to load.
    SomethingToLoad,
    /// Every log calibrated something, but no log has anything to load.
    NothingToLoad,
    /// Some log calibrated nothing or was not replayed (or there were none).
    Failed,
}

impl BatchSummary {
    /// Logs that calibrated at least one sensor (with or without something to load).
    pub fn calibrated(&self) -> usize {
        self.to_load + self.nothing_to_load
    }

    /// Logs that calibrated nothing or could not be replayed.
    pub fn failed(&self) -> usize {
        self.nothing_calibrated + self.errors
    }

    /// How the batch ended: failed when any log failed (or there were none); else nothing to
    /// load when no log had anything to load; else something to load.
    pub fn end(&self) -> BatchEnd {
        if self.failed() > 0 || self.calibrated() == 0 {
            BatchEnd::Failed
        } else if self.to_load == 0 {
            BatchEnd::NothingToLoad
        } else {
            BatchEnd::SomethingToLoad
        }
    }

    /// The one line said at the end.
    pub fn line(&self) -> String {
        let mut s = format!(
            "{} logs, {} calibrated ({} with something to load, {} nothing to load), {} failed ({} calibrated nothing, {} not replayed",
            self.logs,
            self.calibrated(),
            self.to_load,
            self.nothing_to_load,
            self.failed(),
            self.nothing_calibrated,
            self.errors
        );
        if self.panics > 0 {
            s.push_str(&format!(", of which {} panicked", self.panics));
        }
        s.push_str(&format!(") on {} workers", self.jobs));
        for p in &self.written {
            s.push_str(&format!("; wrote {}", p.display()));
        }
        s
    }
}

/// A row's status: the compass's fit (`ok`, `failed`) or the log's (`error`: not replayed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RowStatus {
    Ok,
    Failed,
    Error,
}

impl RowStatus {
    pub fn name(self) -> &'static str {
        match self {
            RowStatus::Ok => "ok",
            RowStatus::Failed => "failed",
            RowStatus::Error => "error",
        }
    }
}

/// One compass of one log (or the one row of a log not replayed): the [`COLUMNS`]. A row whose
/// status is not `ok` carries words only: every number is empty.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Row {
    pub log: String,
    pub instance: Option<String>,
    pub primary: Option<bool>,
    pub status: RowStatus,
    /// The fit's failure name, or the error of a log not replayed.
    pub failure: Option<String>,
    pub detail: Option<String>,
    /// sphere, vector or planar.
    pub method: Option<String>,
    pub model: Option<String>,
    /// Of the offset: `uT`, or `counts` when the log's units are unknown.
    pub units: Option<String>,
    pub offset: Option<[f64; 3]>,
    /// Row-major.
    pub matrix: Option<[f64; 9]>,
    /// The mounting check's verdict on the configured mounting.
    pub mounting_verdict: Option<String>,
    /// The held-out verdict against the vehicle's own calibration as a fixed word: `better`,
    /// `keep_vehicle`, `no_onboard`, `failed`.
    pub verdict: Option<String>,
    /// Whether the compass's calibration is one to load on the vehicle (the report's `load`).
    pub load: Option<bool>,
    /// Why, as a fixed word (`better`, `keep_vehicle`, `fit_failed`, ...).
    pub load_reason: Option<String>,
    /// The rung of the model ladder taken: `offsets`, `scale`, `diagonal`, `full`.
    pub rung: Option<String>,
    /// The field's magnitude through the calibration, uT (none when the units are counts).
    pub radius_ut: Option<f64>,
    /// The fit's RMS residual, uT (none when the units are counts).
    pub rms_ut: Option<f64>,
    /// Of the 100 direction regions, those the compass's readings filled: the primary's (the
    /// report holds no other compass's).
    pub coverage_regions: Option<u64>,
    /// The field's norm spread, %, and dip spread, deg, on the held-out blocks through imucald's
    /// calibration fitted on the others.
    pub heldout_norm_pct: Option<f64>,
    pub heldout_dip_deg: Option<f64>,
    /// The same through the vehicle's own calibration.
    pub vehicle_norm_pct: Option<f64>,
    pub vehicle_dip_deg: Option<f64>,
}

impl Row {
    /// A row of `log` with `status` and nothing else.
    fn blank(log: &str, status: RowStatus) -> Row {
        Row {
            log: log.to_string(),
            instance: None,
            primary: None,
            status,
            failure: None,
            detail: None,
            method: None,
            model: None,
            units: None,
            offset: None,
            matrix: None,
            mounting_verdict: None,
            verdict: None,
            load: None,
            load_reason: None,
            rung: None,
            radius_ut: None,
            rms_ut: None,
            coverage_regions: None,
            heldout_norm_pct: None,
            heldout_dip_deg: None,
            vehicle_norm_pct: None,
            vehicle_dip_deg: None,
        }
    }

    /// The row of a log not replayed.
    fn error(log: &str, message: String) -> Row {
        Row {
            failure: Some(message),
            ..Row::blank(log, RowStatus::Error)
        }
    }

    /// Every number emptied, the words kept: what a row whose fit did not pass shows (a failed
    /// fit's offset and matrix are placeholders, and its held-out figures vouch for nothing).
    fn without_numbers(self) -> Row {
        Row {
            offset: None,
            matrix: None,
            radius_ut: None,
            rms_ut: None,
            coverage_regions: None,
            heldout_norm_pct: None,
            heldout_dip_deg: None,
            vehicle_norm_pct: None,
            vehicle_dip_deg: None,
            ..self
        }
    }

    /// The CSV record, in [`COLUMNS`] order; a missing value is an empty cell, a number is
    /// written as the report writes it (the shortest text that reads back to the same f64).
    fn record(&self) -> Vec<String> {
        let mut r = vec![
            self.log.clone(),
            cell(&self.instance),
            cell(&self.primary),
            self.status.name().to_string(),
            cell(&self.failure),
            cell(&self.detail),
            cell(&self.method),
            cell(&self.model),
            cell(&self.units),
        ];
        let numbers = |v: Option<&[f64]>, n: usize| match v {
            Some(v) => v.iter().map(|x| x.to_string()).collect(),
            None => vec![String::new(); n],
        };
        r.extend(numbers(self.offset.as_ref().map(|o| &o[..]), 3));
        r.extend(numbers(self.matrix.as_ref().map(|m| &m[..]), 9));
        r.extend([
            cell(&self.mounting_verdict),
            cell(&self.verdict),
            cell(&self.load),
            cell(&self.load_reason),
            cell(&self.rung),
            cell(&self.radius_ut),
            cell(&self.rms_ut),
            cell(&self.coverage_regions),
            cell(&self.heldout_norm_pct),
            cell(&self.heldout_dip_deg),
            cell(&self.vehicle_norm_pct),
            cell(&self.vehicle_dip_deg),
        ]);
        r
    }
}

/// A table cell: the value's text, or empty.
fn cell<T: ToString>(v: &Option<T>) -> String {
    v.as_ref().map(T::to_string).unwrap_or_default()
}

/// The rows of one replay report, read off its JSON (`imucald.report/1`, whose field names are the
/// contract) as `examples_py/dask_fleet.py` reads them: each instance of a multi-instance log, the
/// primary first as the report lists them, else the log's one compass. Each compass's `quality`
/// and `load` entries are those of the same instance (a log of one unnamed stream's: those named
/// [`UNNAMED_INSTANCE`]); the coverage is the report's, the primary's.
pub(crate) fn compass_rows(log: &str, report: &Value) -> Vec<Row> {
    let by_instance = |key: &str| -> BTreeMap<&str, &Value> {
        report[key]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|q| Some((q["instance"].as_str()?, q)))
            .collect()
    };
    let (quality, load) = (by_instance("quality"), by_instance("load"));
    let one = |instance: Option<&str>, primary: bool, mag: &Value| {
        let name = instance.unwrap_or(UNNAMED_INSTANCE);
        let q = quality.get(name).copied().unwrap_or(&Value::Null);
        let decision = load.get(name).copied().unwrap_or(&Value::Null);
        let in_ut = |v: &Value| v.as_f64().filter(|_| mag["units"] == "uT");
        let status = match mag["status"].as_str() {
            Some("ok") => RowStatus::Ok,
            _ => RowStatus::Failed,
        };
        let row = Row {
            instance: instance.map(str::to_string),
            primary: Some(primary),
            failure: text(&mag["failure"]),
            detail: text(&mag["detail"]),
            method: text(&mag["method"]),
            model: text(&mag["model"]),
            units: text(&mag["units"]),
            offset: numbers::<3>(mag["offset"].as_array().into_iter().flatten()),
            matrix: numbers::<9>(
                mag["matrix"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .flat_map(|r| r.as_array().into_iter().flatten()),
            ),
            mounting_verdict: text(&mag["mounting"]["verdict"]),
            verdict: text(&q["verdict_kind"]),
            load: decision["load"].as_bool(),
            load_reason: text(&decision["reason"]),
            rung: text(&q["rung"]).or_else(|| text(&mag["rung"])),
            radius_ut: in_ut(&mag["radius"]),
            rms_ut: in_ut(&mag["rms_residual"]),
            coverage_regions: if primary {
                report["coverage"]["mag"]["filled"].as_u64()
            } else {
                None
            },
            heldout_norm_pct: q["imucald"]["norm_spread_pct"].as_f64(),
            heldout_dip_deg: q["imucald"]["dip_spread_deg"].as_f64(),
            vehicle_norm_pct: q["onboard"]["norm_spread_pct"].as_f64(),
            vehicle_dip_deg: q["onboard"]["dip_spread_deg"].as_f64(),
            ..Row::blank(log, status)
        };
        match status {
            RowStatus::Ok => row,
            _ => row.without_numbers(),
        }
    };
    match report["instances"].as_array().filter(|a| !a.is_empty()) {
        Some(instances) => instances
            .iter()
            .map(|i| {
                one(
                    i["instance"].as_str(),
                    i["primary"].as_bool().unwrap_or(false),
                    &i["calibration"]["mag"],
                )
            })
            .collect(),
        None => vec![one(
            report["input"]["instance"].as_str(),
            true,
            &report["calibration"]["mag"],
        )],
    }
}

/// A JSON string's text (null and other kinds: none).
fn text(v: &Value) -> Option<String> {
    v.as_str().map(str::to_string)
}

/// Exactly `N` numbers, or none.
fn numbers<'a, const N: usize>(values: impl Iterator<Item = &'a Value>) -> Option<[f64; N]> {
    let v: Vec<f64> = values.map(Value::as_f64).collect::<Option<_>>()?;
    v.try_into().ok()
}

/// One log's replay, as a worker runs it.
pub(crate) type ReplayOne<'a> = dyn Fn(&Path) -> Result<Report, Error> + Sync + 'a;

/// What a worker hands back for one log.
struct Done {
    index: usize,
    rows: Vec<Row>,
    /// The log's JSON line (without its newline).
    line: String,
    outcome: LogOutcome,
}

/// How one log ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LogOutcome {
    /// Calibrated, something to load ([`loadable`]).
    ToLoad,
    /// Calibrated, nothing to load.
    NothingToLoad,
    NothingCalibrated,
    Error,
    Panicked,
}

/// Replay every log of `logs` (one per worker, [`BatchOptions::jobs`] workers) with `cfg`; write
/// the table and the reports; `progress` is called on this thread after each log.
pub fn run(
    logs: &[PathBuf],
    cfg: &Config,
    opts: &BatchOptions,
    progress: &mut dyn FnMut(Progress),
) -> Result<BatchSummary, Error> {
    let one = |p: &Path| replay(p, cfg, &opts.replay, &mut |_, _| {}).map(|o| o.report);
    run_with(logs, opts, &one, progress)
}

/// [`run`] with each log's replay done by `replay_one`.
pub(crate) fn run_with(
    logs: &[PathBuf],
    opts: &BatchOptions,
    replay_one: &ReplayOne<'_>,
    progress: &mut dyn FnMut(Progress),
) -> Result<BatchSummary, Error> {
    let jobs = worker_count(opts.jobs, logs.len());
    let mut reports = match &opts.reports {
        Some(p) => Some(ReportsFile::create(p)?),
        None => None,
    };
    let mut summary = BatchSummary {
        logs: logs.len(),
        to_load: 0,
        nothing_to_load: 0,
        nothing_calibrated: 0,
        errors: 0,
        panics: 0,
        jobs,
        rows: vec![],
        written: vec![],
    };
    let mut rows: Vec<Vec<Row>> = vec![vec![]; logs.len()];
    let mut pending = BTreeMap::new();
    let mut next_line = 0;
    let (work_tx, work_rx) = sync_channel::<usize>(QUEUE_PER_WORKER * jobs);
    let (done_tx, done_rx) = sync_channel::<Done>(QUEUE_PER_WORKER * jobs);
    let work_rx = Mutex::new(work_rx);
    // A failed write of the reports is said after the batch: the loop below always drains the
    // results, so that no worker or feeder is left waiting on a full queue.
    let mut write_failure = None;
    std::thread::scope(|scope| {
        scope.spawn(move || feed(logs.len(), work_tx));
        for _ in 0..jobs {
            let (work_rx, done_tx) = (&work_rx, done_tx.clone());
            scope.spawn(move || work(logs, replay_one, work_rx, done_tx));
        }
        drop(done_tx);
        for done in done_rx {
            summary.count(done.outcome);
            if let Some(f) = reports.as_mut() {
                pending.insert(done.index, done.line);
                if let Err(e) = f.write_ready(&mut pending, &mut next_line) {
                    write_failure = Some(e);
                    reports = None;
                }
            }
            rows[done.index] = done.rows;
            progress(Progress {
                done: summary.calibrated() + summary.failed(),
                total: logs.len(),
                failed: summary.failed(),
            });
        }
    });
    if let Some(e) = write_failure {
        return Err(e);
    }
    summary.rows = rows.into_iter().flatten().collect();
    if let Some(f) = reports {
        summary.written.push(f.commit()?);
    }
    if let Some(p) = &opts.table {
        write_table(p, &summary.rows)?;
        summary.written.push(p.clone());
    }
    Ok(summary)
}

impl BatchSummary {
    fn count(&mut self, o: LogOutcome) {
        match o {
            LogOutcome::ToLoad => self.to_load += 1,
            LogOutcome::NothingToLoad => self.nothing_to_load += 1,
            LogOutcome::NothingCalibrated => self.nothing_calibrated += 1,
            LogOutcome::Error => self.errors += 1,
            LogOutcome::Panicked => {
                self.errors += 1;
                self.panics += 1;
            }
        }
    }
}

/// `jobs` (at least 1), else the cores; never more than the logs (nor fewer than 1).
fn worker_count(jobs: Option<usize>, logs: usize) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    jobs.unwrap_or(cores).min(logs).max(1)
}

/// Queue the indices of the logs, in order; stops early when the workers are gone.
fn feed(n: usize, work: SyncSender<usize>) {
    for i in 0..n {
        if work.send(i).is_err() {
            return;
        }
    }
}

/// A worker: replay the queued logs until the queue is empty.
fn work(
    logs: &[PathBuf],
    replay_one: &ReplayOne<'_>,
    queue: &Mutex<Receiver<usize>>,
    done: SyncSender<Done>,
) {
    loop {
        // A worker that panicked holding the lock cannot happen (the replay runs unlocked), but a
        // poisoned lock still hands out its queue.
        let next = queue.lock().unwrap_or_else(|p| p.into_inner()).recv();
        let Ok(index) = next else { return };
        if done
            .send(replay_log(index, &logs[index], replay_one))
            .is_err()
        {
            return;
        }
    }
}

/// One log replayed into its rows and JSON line; a panic is caught and becomes its error row.
fn replay_log(index: usize, log: &Path, replay_one: &ReplayOne<'_>) -> Done {
    let name = log.display().to_string();
    let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| replay_one(log)));
    let (outcome, failure) = match caught {
        Ok(Ok(report)) => return done_ok(index, &name, &report),
        Ok(Err(e)) => (LogOutcome::Error, e.to_string()),
        Err(panic) => (
            LogOutcome::Panicked,
            format!("panicked: {}", panic_message(panic.as_ref())),
        ),
    };
    let line = serde_json::json!({ "log": name, "error": failure }).to_string();
    Done {
        index,
        rows: vec![Row::error(&name, failure)],
        line,
        outcome,
    }
}

/// The rows and line of a replayed log.
fn done_ok(index: usize, name: &str, report: &Report) -> Done {
    let outcome = if calibrated_nothing(report) {
        LogOutcome::NothingCalibrated
    } else if loadable(report) {
        LogOutcome::ToLoad
    } else {
        LogOutcome::NothingToLoad
    };
    match serde_json::to_value(report) {
        Ok(value) => Done {
            index,
            rows: compass_rows(name, &value),
            line: serde_json::json!({ "log": name, "report": value }).to_string(),
            outcome,
        },
        Err(e) => {
            let failure = format!("report not serialisable: {e}");
            Done {
                index,
                line: serde_json::json!({ "log": name, "error": failure }).to_string(),
                rows: vec![Row::error(name, failure)],
                outcome: LogOutcome::Error,
            }
        }
    }
}

/// The text a panic was raised with.
fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

/// The JSON-lines file being written: lines in the order of the logs as soon as each one's turn
/// comes, into a temporary file renamed into place at the end ([`AtomicFile`]).
struct ReportsFile {
    atomic: AtomicFile,
    out: std::io::BufWriter<std::fs::File>,
    path: PathBuf,
}

impl ReportsFile {
    fn create(path: &Path) -> Result<ReportsFile, Error> {
        let atomic = AtomicFile::new(path)?;
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(atomic.temp_path())
            .map_err(|source| Error::Write {
                path: path.to_path_buf(),
                source,
            })?;
        Ok(ReportsFile {
            atomic,
            out: std::io::BufWriter::new(file),
            path: path.to_path_buf(),
        })
    }

    /// Write the lines of `pending` whose turn has come (from `next` on).
    fn write_ready(
        &mut self,
        pending: &mut BTreeMap<usize, String>,
        next: &mut usize,
    ) -> Result<(), Error> {
        while let Some(line) = pending.remove(next) {
            writeln!(self.out, "{line}").map_err(|source| Error::Write {
                path: self.path.clone(),
                source,
            })?;
            *next += 1;
        }
        Ok(())
    }

    /// Flush and rename into place; the path written.
    fn commit(self) -> Result<PathBuf, Error> {
        let ReportsFile { atomic, out, path } = self;
        out.into_inner()
            .map_err(|e| Error::Write {
                path: path.clone(),
                source: e.into_error(),
            })?
            .sync_all()
            .map_err(|source| Error::Write {
                path: path.clone(),
                source,
            })?;
        atomic.commit()?;
        Ok(path)
    }
}

/// The rows as CSV (header [`COLUMNS`]) at `path`, atomically.
fn write_table(path: &Path, rows: &[Row]) -> Result<(), Error> {
    write_atomic_with(path, |f| {
        let mut w = csv::Writer::from_writer(f);
        w.write_record(COLUMNS)?;
        for r in rows {
            w.write_record(r.record())?;
        }
        w.flush()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn logs(n: usize) -> Vec<PathBuf> {
        (0..n)
            .map(|i| PathBuf::from(format!("log{i}.tlog")))
            .collect()
    }

    #[test]
    fn a_panic_is_one_failure_row_and_the_batch_goes_on() {
        let replay_one = |p: &Path| -> Result<Report, Error> {
            if p == Path::new("log3.tlog") {
                panic!("a bug in one log");
            }
            Err(Error::Other(format!("{}: unreadable", p.display())))
        };
        let opts = BatchOptions {
            jobs: Some(2),
            ..Default::default()
        };
        let mut seen = vec![];
        let s = run_with(&logs(6), &opts, &replay_one, &mut |p| seen.push(p)).unwrap();
        assert_eq!((s.logs, s.errors, s.panics, s.calibrated()), (6, 6, 1, 0));
        assert_eq!(s.rows.len(), 6);
        assert!(s.rows.iter().all(|r| r.status == RowStatus::Error));
        assert_eq!(
            s.rows[3].failure.as_deref(),
            Some("panicked: a bug in one log")
        );
        assert_eq!(s.rows[5].failure.as_deref(), Some("log5.tlog: unreadable"));
        assert_eq!(seen.len(), 6);
        assert_eq!(seen.last().map(|p| (p.done, p.failed)), Some((6, 6)));
    }

    #[test]
    fn reports_lines_follow_the_logs_order() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("r.jsonl");
        let replay_one =
            |p: &Path| -> Result<Report, Error> { Err(Error::Other(p.display().to_string())) };
        let opts = BatchOptions {
            jobs: Some(3),
            reports: Some(out.clone()),
            table: Some(d.path().join("t.csv")),
            ..Default::default()
        };
        let s = run_with(&logs(40), &opts, &replay_one, &mut |_| {}).unwrap();
        assert_eq!(s.written, vec![out.clone(), d.path().join("t.csv")]);
        let text = std::fs::read_to_string(&out).unwrap();
        let lines: Vec<Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), 40);
        for (i, l) in lines.iter().enumerate() {
            assert_eq!(l["log"], format!("log{i}.tlog"));
            assert_eq!(l["error"], format!("log{i}.tlog"));
        }
        let table = std::fs::read_to_string(d.path().join("t.csv")).unwrap();
        assert_eq!(table.lines().next().unwrap(), COLUMNS.join(","));
        assert_eq!(table.lines().count(), 41);
        // Nothing but the two files: no temporary file left.
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2);
    }

    #[test]
    fn directories_give_their_logs_sorted_and_name_the_rest() {
        let d = tempfile::tempdir().unwrap();
        let sub = d.path().join("b");
        std::fs::create_dir(&sub).unwrap();
        for f in [
            "z.tlog",
            "a.CSV.GZ",
            "notes.txt",
            "b/c.ulg",
            "b/a.bin",
            "b/x.csv",
        ] {
            std::fs::write(d.path().join(f), b"x").unwrap();
        }
        let given = d.path().join("notes.txt");
        let f = find_logs(&[d.path().to_path_buf(), given.clone()]).unwrap();
        let rel: Vec<_> = f
            .logs
            .iter()
            .map(|p| p.strip_prefix(d.path()).unwrap_or(p))
            .collect();
        let want: Vec<&Path> = [
            "a.CSV.GZ",
            "b/a.bin",
            "b/c.ulg",
            "b/x.csv",
            "z.tlog",
            "notes.txt",
        ]
        .iter()
        .map(Path::new)
        .collect();
        assert_eq!(rel, want);
        assert_eq!(f.skipped, vec![(given, SkipReason::NotALogName)]);
    }

    /// A magnetometer's record in the report's JSON: `ok` with the given offset x, or failed
    /// (`coverage`) with the placeholders a failed fit keeps (zero offset, identity matrix).
    fn mag_json(status: &str, x: f64) -> Value {
        let ok = status == "ok";
        serde_json::json!({
            "status": status, "failure": if ok { Value::Null } else { "coverage".into() },
            "detail": if ok { Value::Null } else { "4 of 100 sphere regions filled".into() },
            "model": "sym9", "units": "uT", "method": "vector", "rung": "diagonal",
            "offset": if ok { [x, 2.0, 3.0] } else { [0.0; 3] },
            "matrix": if ok {
                [[1.0, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 1.0]]
            } else {
                [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
            },
            "radius": 49.5, "rms_residual": 0.25,
            "mounting": {"verdict": "matches"}
        })
    }

    /// A held-out entry with both scores.
    fn quality_json(instance: &str, kind: &str) -> Value {
        serde_json::json!({
            "instance": instance, "verdict": "imucald's is better: load the export; held out ...",
            "verdict_kind": kind, "rung": "full",
            "imucald": {"norm_spread_pct": 0.24, "dip_spread_deg": 0.52},
            "onboard": {"norm_spread_pct": 0.35, "dip_spread_deg": 0.54}
        })
    }

    /// The record as column name -> cell.
    fn cells(row: &Row) -> BTreeMap<&'static str, String> {
        let rec = row.record();
        assert_eq!(rec.len(), COLUMNS.len());
        COLUMNS.iter().copied().zip(rec).collect()
    }

    /// The columns that hold numbers.
    const NUMBER_COLUMNS: [&str; 19] = [
        "offset_x",
        "offset_y",
        "offset_z",
        "matrix_00",
        "matrix_01",
        "matrix_02",
        "matrix_10",
        "matrix_11",
        "matrix_12",
        "matrix_20",
        "matrix_21",
        "matrix_22",
        "radius_ut",
        "rms_ut",
        "coverage_regions",
        "heldout_norm_pct",
        "heldout_dip_deg",
        "vehicle_norm_pct",
        "vehicle_dip_deg",
    ];

    fn two_compass_report() -> Value {
        serde_json::json!({
            "input": {"instance": "IMU+MAG"},
            "coverage": {"mag": {"regions": 100, "filled": 37, "gaps_pct": 63.0}},
            "calibration": {"mag": mag_json("ok", 1.0)},
            "instances": [
                {"instance": "IMU+MAG", "primary": true, "calibration": {"mag": mag_json("ok", 1.0)}},
                {"instance": "IMU2+MAG2", "primary": false, "calibration": {"mag": mag_json("failed", 0.0)}}
            ],
            "quality": [quality_json("IMU+MAG", "better"), quality_json("IMU2+MAG2", "keep_vehicle")],
            "load": [
                {"instance": "IMU+MAG", "compass_id": 0, "load": true, "reason": "better"},
                {"instance": "IMU2+MAG2", "compass_id": 1, "load": false, "reason": "fit_failed"}
            ]
        })
    }

    #[test]
    fn rows_of_a_multi_instance_report_pair_each_compass_with_its_entries() {
        let rows = compass_rows("f.bin", &two_compass_report());
        assert_eq!(rows.len(), 2);
        let ok = cells(&rows[0]);
        assert_eq!(ok["status"], "ok");
        assert_eq!(ok["primary"], "true");
        assert_eq!(
            [&ok["offset_x"], &ok["offset_y"], &ok["offset_z"]],
            ["1", "2", "3"]
        );
        assert_eq!(ok["matrix_11"], "1.5");
        assert_eq!(ok["mounting_verdict"], "matches");
        assert_eq!(ok["verdict"], "better");
        assert_eq!(
            (ok["load"].as_str(), ok["load_reason"].as_str()),
            ("true", "better")
        );
        // The held-out entry's rung before the calibration's.
        assert_eq!(ok["rung"], "full");
        assert_eq!(
            (ok["radius_ut"].as_str(), ok["rms_ut"].as_str()),
            ("49.5", "0.25")
        );
        assert_eq!(ok["coverage_regions"], "37");
        assert_eq!(
            [
                &ok["heldout_norm_pct"],
                &ok["heldout_dip_deg"],
                &ok["vehicle_norm_pct"],
                &ok["vehicle_dip_deg"]
            ],
            ["0.24", "0.52", "0.35", "0.54"]
        );
        assert_eq!(rows[1].primary, Some(false));
        assert_eq!(rows[1].instance.as_deref(), Some("IMU2+MAG2"));
    }

    #[test]
    fn a_failed_row_carries_its_words_and_no_numbers() {
        let rows = compass_rows("f.bin", &two_compass_report());
        let failed = cells(&rows[1]);
        assert_eq!(failed["status"], "failed");
        for c in NUMBER_COLUMNS {
            assert_eq!(failed[c], "", "{c}: {failed:?}");
        }
        assert_eq!(failed["failure"], "coverage");
        assert_eq!(failed["detail"], "4 of 100 sphere regions filled");
        assert_eq!(failed["verdict"], "keep_vehicle");
        assert_eq!(failed["load"], "false");
        assert_eq!(failed["load_reason"], "fit_failed");
        assert_eq!(
            (failed["method"].as_str(), failed["model"].as_str()),
            ("vector", "sym9")
        );
        // A log not replayed: its error, nothing else.
        let error = cells(&Row::error("x.tlog", "cannot read".into()));
        assert_eq!(error["status"], "error");
        assert_eq!(error["failure"], "cannot read");
        for c in NUMBER_COLUMNS
            .iter()
            .chain(&["primary", "load", "load_reason"])
        {
            assert_eq!(error[c], "", "{c}");
        }
    }

    #[test]
    fn the_verdict_column_is_the_word_not_the_prose() {
        let rows = compass_rows("f.bin", &two_compass_report());
        assert_eq!(rows[0].verdict.as_deref(), Some("better"));
        let words = ["better", "keep_vehicle", "no_onboard", "failed"];
        assert!(rows
            .iter()
            .all(|r| words.contains(&r.verdict.as_deref().unwrap())));
    }

    #[test]
    fn a_log_of_one_unnamed_stream_takes_the_entries_named_primary() {
        let report = serde_json::json!({
            "input": {"instance": null},
            "coverage": {"mag": {"regions": 100, "filled": 94, "gaps_pct": 6.0}},
            "calibration": {"mag": {"status": "ok", "units": "counts", "radius": 812.0,
                "rms_residual": 3.0, "offset": [1.0, 2.0, 3.0],
                "matrix": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}},
            "quality": [quality_json("primary", "no_onboard")],
            "load": [{"instance": "primary", "compass_id": 0, "load": true, "reason": "no_onboard"}]
        });
        let rows = compass_rows("f.csv", &report);
        assert_eq!(rows.len(), 1);
        let c = cells(&rows[0]);
        assert_eq!(c["instance"], "");
        assert_eq!(c["verdict"], "no_onboard");
        assert_eq!(
            (c["load"].as_str(), c["load_reason"].as_str()),
            ("true", "no_onboard")
        );
        assert_eq!(c["coverage_regions"], "94");
        assert_eq!(c["offset_x"], "1");
        // In counts: no figure in uT.
        assert_eq!((c["radius_ut"].as_str(), c["rms_ut"].as_str()), ("", ""));
    }

    /// A report of a log whose fits all failed: what `kind` then makes of it.
    fn report_of(kind: &str) -> Report {
        use crate::report::{CalStatus, LoadDecision, LoadReason};
        let mut pipe =
            crate::calib::pipeline::Pipeline::new(&Config::default().calib()).expect("a pipeline");
        let results = pipe.finish().clone();
        let input = crate::report::InputReport::new(
            "bin",
            None,
            Some("IMU+MAG".into()),
            &Default::default(),
            1,
            1.0,
        );
        let mut r = crate::app::replay::make_report(input, &pipe, &results, None);
        let decision = |load, reason| LoadDecision {
            instance: "IMU+MAG".into(),
            compass_id: 0,
            load,
            reason,
        };
        match kind {
            "gyro_only" => {
                r.calibration.gyro.status = CalStatus::Ok;
                r.load = vec![decision(false, LoadReason::FitFailed)];
            }
            "keep_vehicle" | "better" => {
                r.calibration.mag = crate::testdata::passing_mag_calibration(
                    crate::calib::model::CalModel::Sym9,
                    [1.0, 2.0, 3.0],
                );
                r.load = vec![if kind == "better" {
                    decision(true, LoadReason::Better)
                } else {
                    decision(false, LoadReason::KeepVehicle)
                }];
            }
            _ => r.load = vec![decision(false, LoadReason::FitFailed)],
        }
        r
    }

    /// A batch of logs named for what their replay gives: `gyro_only`, `keep_vehicle`, `better`,
    /// `nothing`, `unreadable`.
    fn batch_of(kinds: &[&str]) -> BatchSummary {
        let logs: Vec<PathBuf> = kinds
            .iter()
            .map(|k| PathBuf::from(format!("{k}.bin")))
            .collect();
        let replay_one = |p: &Path| -> Result<Report, Error> {
            match p.file_stem().and_then(|s| s.to_str()) {
                Some("unreadable") => Err(Error::Other("unreadable".into())),
                Some(kind) => Ok(report_of(kind)),
                None => unreachable!(),
            }
        };
        let opts = BatchOptions {
            jobs: Some(2),
            ..Default::default()
        };
        run_with(&logs, &opts, &replay_one, &mut |_| {}).unwrap()
    }

    #[test]
    fn a_gyro_bias_only_or_keep_vehicle_is_calibrated_with_nothing_to_load() {
        let s = batch_of(&["gyro_only", "keep_vehicle"]);
        assert_eq!(
            (s.to_load, s.nothing_to_load, s.nothing_calibrated, s.errors),
            (0, 2, 0, 0)
        );
        assert_eq!((s.calibrated(), s.failed()), (2, 0));
        assert_eq!(s.end(), BatchEnd::NothingToLoad);
        assert!(
            s.line().starts_with(
                "2 logs, 2 calibrated (0 with something to load, 2 nothing to load), 0 failed"
            ),
            "{}",
            s.line()
        );
        assert_eq!(s.rows[1].load_reason.as_deref(), Some("keep_vehicle"));
        // Nothing to load anywhere, and a log failed too: the failure is what the batch says.
        let s = batch_of(&["gyro_only", "unreadable"]);
        assert_eq!((s.nothing_to_load, s.errors), (1, 1));
        assert_eq!(s.end(), BatchEnd::Failed);
    }

    #[test]
    fn the_batch_ends_by_what_its_logs_had_to_load() {
        let s = batch_of(&["better", "keep_vehicle", "gyro_only"]);
        assert_eq!((s.to_load, s.nothing_to_load), (1, 2));
        assert_eq!(s.end(), BatchEnd::SomethingToLoad);
        // A log that failed beside one to load: failed, as before.
        let s = batch_of(&["better", "nothing", "unreadable"]);
        assert_eq!(
            (s.to_load, s.nothing_calibrated, s.errors, s.failed()),
            (1, 1, 1, 2)
        );
        assert_eq!(s.end(), BatchEnd::Failed);
        let s = batch_of(&["nothing", "unreadable"]);
        assert_eq!((s.calibrated(), s.failed()), (0, 2));
        assert_eq!(s.end(), BatchEnd::Failed);
    }
}
