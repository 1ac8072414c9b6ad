//! `imucald replay` over many logs: the logs found under the given paths, replayed one per worker
//! thread through [`crate::app::replay::replay`], gathered into one table (a row per log and
//! compass) and one JSON-lines file of the full reports.
//!
//! A log that cannot be replayed (unreadable, unknown format) or that calibrates nothing is a row
//! with its failure, and a panic in one log's replay is caught on its worker and reported the same
//! way: the batch always goes on. The work queue and the result queue are bounded (twice the
//! workers); a full queue makes its sender wait, nothing is dropped.

use crate::app::replay::{calibrated_nothing, replay, ReplayOptions};
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
pub(crate) const COLUMNS: [&str; 23] = [
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
];

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

/// What a batch did.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchSummary {
    pub logs: usize,
    /// Logs that calibrated at least one sensor.
    pub calibrated: usize,
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

impl BatchSummary {
    /// Logs that calibrated nothing or could not be replayed.
    pub fn failed(&self) -> usize {
        self.nothing_calibrated + self.errors
    }

    /// The one line said at the end.
    pub fn line(&self) -> String {
        let mut s = format!(
            "{} logs, {} calibrated, {} failed ({} calibrated nothing, {} not replayed",
            self.logs,
            self.calibrated,
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

/// One compass of one log (or the one row of a log not replayed): the [`COLUMNS`].
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
    /// The held-out quality verdict against the vehicle's onboard calibration.
    pub verdict: Option<String>,
}

impl Row {
    /// The row of a log not replayed.
    fn error(log: &str, message: String) -> Row {
        Row {
            log: log.to_string(),
            instance: None,
            primary: None,
            status: RowStatus::Error,
            failure: Some(message),
            detail: None,
            method: None,
            model: None,
            units: None,
            offset: None,
            matrix: None,
            mounting_verdict: None,
            verdict: None,
        }
    }

    /// The CSV record, in [`COLUMNS`] order; a missing value is an empty cell, a number is
    /// written as the report writes it (the shortest text that reads back to the same f64).
    fn record(&self) -> Vec<String> {
        let text = |v: &Option<String>| v.clone().unwrap_or_default();
        let mut r = vec![
            self.log.clone(),
            text(&self.instance),
            self.primary.map(|p| p.to_string()).unwrap_or_default(),
            self.status.name().to_string(),
            text(&self.failure),
            text(&self.detail),
            text(&self.method),
            text(&self.model),
            text(&self.units),
        ];
        let numbers = |v: Option<&[f64]>, n: usize| match v {
            Some(v) => v.iter().map(|x| x.to_string()).collect(),
            None => vec![String::new(); n],
        };
        r.extend(numbers(self.offset.as_ref().map(|o| &o[..]), 3));
        r.extend(numbers(self.matrix.as_ref().map(|m| &m[..]), 9));
        r.push(text(&self.mounting_verdict));
        r.push(text(&self.verdict));
        r
    }
}

/// The rows of one replay report, read off its JSON (`imucald.report/1`, whose field names are the
/// contract) as `examples_py/dask_fleet.py` reads them: each instance of a multi-instance log, the
/// primary first as the report lists them, else the log's one compass; the quality verdict is the
/// held-out entry of the same instance.
pub(crate) fn compass_rows(log: &str, report: &Value) -> Vec<Row> {
    let quality: BTreeMap<&str, &Value> = report["quality"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|q| Some((q["instance"].as_str()?, q)))
        .collect();
    let one = |instance: Option<&str>, primary: bool, mag: &Value| {
        let verdict = instance
            .and_then(|i| quality.get(i))
            .and_then(|q| text(&q["verdict"]));
        Row {
            log: log.to_string(),
            instance: instance.map(str::to_string),
            primary: Some(primary),
            status: match mag["status"].as_str() {
                Some("ok") => RowStatus::Ok,
                _ => RowStatus::Failed,
            },
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
            verdict,
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
    Calibrated,
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
        calibrated: 0,
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
                done: summary.calibrated + summary.failed(),
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
            LogOutcome::Calibrated => self.calibrated += 1,
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
    } else {
        LogOutcome::Calibrated
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
        assert_eq!((s.logs, s.errors, s.panics, s.calibrated), (6, 6, 1, 0));
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

    #[test]
    fn rows_of_a_multi_instance_report_pair_each_compass_with_its_verdict() {
        let mag = |status: &str, x: f64| {
            serde_json::json!({
                "status": status, "failure": if status == "ok" { Value::Null } else { "coverage".into() },
                "detail": null, "model": "sym9", "units": "uT", "method": "vector",
                "offset": [x, 2.0, 3.0],
                "matrix": [[1.0, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 1.0]],
                "mounting": {"verdict": "matches"}
            })
        };
        let report = serde_json::json!({
            "input": {"instance": "mag:0"},
            "calibration": {"mag": mag("ok", 1.0)},
            "instances": [
                {"instance": "mag:0", "primary": true, "calibration": {"mag": mag("ok", 1.0)}},
                {"instance": "mag:1", "primary": false, "calibration": {"mag": mag("failed", 0.25)}}
            ],
            "quality": [{"instance": "mag:1", "verdict": "worse than onboard"}]
        });
        let rows = compass_rows("f.bin", &report);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].verdict, None);
        assert_eq!(rows[1].verdict.as_deref(), Some("worse than onboard"));
        assert_eq!(rows[1].status, RowStatus::Failed);
        assert_eq!(rows[1].failure.as_deref(), Some("coverage"));
        assert_eq!(rows[1].primary, Some(false));
        let rec = rows[1].record();
        assert_eq!(rec.len(), COLUMNS.len());
        assert_eq!(&rec[9..13], ["0.25", "2", "3", "1"]);
        assert_eq!(rec[16], "1.5");
        assert_eq!(rec[21], "matches");
    }
}
