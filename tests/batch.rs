//! `imucald replay` over many logs: the table and the reports against each log's own replay, a bad
//! log among good ones, the same table from one worker and from two.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn imucald(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(args)
        .output()
        .unwrap()
}

fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// A fleet directory: simulated tumbles (three .tlog, one DataFlash .bin in a subdirectory), a
/// file named .tlog that holds no log, and a file whose name is no log's. The logs, sorted.
fn fleet(dir: &Path) -> Vec<PathBuf> {
    std::fs::create_dir(dir.join("sub")).unwrap();
    let mut logs = vec![];
    for (seed, name) in [
        (1, "a1.tlog"),
        (2, "a2.tlog"),
        (3, "a3.tlog"),
        (4, "sub/f4.bin"),
    ] {
        let p = dir.join(name);
        let out = imucald(&[
            "simulate".as_ref(),
            "--scenario".as_ref(),
            "tumble".as_ref(),
            "--seed".as_ref(),
            seed.to_string().as_ref(),
            "--out".as_ref(),
            p.as_os_str(),
        ]);
        assert!(out.status.success(), "{}", text(&out));
        logs.push(p);
    }
    // Bytes no format reads (no MAVLink magic at byte 8, no ULog or DataFlash header, no text).
    let junk: Vec<u8> = (0..4096u32).map(|i| (i * 7 % 251) as u8 | 0x80).collect();
    let broken = dir.join("a0-broken.tlog");
    std::fs::write(&broken, junk).unwrap();
    logs.push(broken);
    std::fs::write(dir.join("notes.txt"), "flight notes\n").unwrap();
    logs.sort();
    logs
}

fn batch(dir: &Path, out: &Path, jobs: &str) -> Output {
    imucald(&[
        "replay".as_ref(),
        dir.as_os_str(),
        "--jobs".as_ref(),
        jobs.as_ref(),
        "--table".as_ref(),
        out.join(format!("table{jobs}.csv")).as_os_str(),
        "--reports".as_ref(),
        out.join(format!("reports{jobs}.jsonl")).as_os_str(),
    ])
}

/// The table as header -> cell maps, in order.
fn table(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let mut r = csv::Reader::from_path(path).unwrap();
    let header: Vec<String> = r.headers().unwrap().iter().map(String::from).collect();
    r.records()
        .map(|rec| {
            let rec = rec.unwrap();
            header
                .iter()
                .cloned()
                .zip(rec.iter().map(String::from))
                .collect()
        })
        .collect()
}

/// A JSON value as the table writes it: text as is, null empty, a number the same f64. serde_json
/// (without its float_roundtrip feature) reads a number back up to one unit in the last place off,
/// so numbers are allowed 2 units (one is the most seen).
fn cell_matches(cell: &str, v: &Value) -> bool {
    match v {
        Value::Null => cell.is_empty(),
        Value::String(s) => cell == s,
        Value::Bool(b) => cell == b.to_string(),
        Value::Number(n) => match (cell.parse::<f64>(), n.as_f64()) {
            (Ok(a), Some(b)) => (a - b).abs() <= 2.0 * f64::EPSILON * b.abs(),
            _ => false,
        },
        _ => false,
    }
}

#[test]
fn batch_rows_equal_each_logs_own_replay_and_a_bad_log_is_a_failure_row() {
    let d = tempfile::tempdir().unwrap();
    let (logs_dir, out) = (d.path().join("logs"), d.path().join("out"));
    std::fs::create_dir_all(&out).unwrap();
    std::fs::create_dir(&logs_dir).unwrap();
    let logs = fleet(&logs_dir);
    let run = batch(&logs_dir, &out, "2");
    let said = text(&run);
    // The broken log calibrates nothing: the documented status, after the whole batch.
    assert_eq!(run.status.code(), Some(3), "{said}");
    assert!(said.contains("5 logs, 4 calibrated, 1 failed"), "{said}");
    assert!(said.contains("notes.txt (not a log name)"), "{said}");
    assert!(
        said.contains(&out.join("table2.csv").display().to_string()),
        "{said}"
    );

    let rows = table(&out.join("table2.csv"));
    let lines: Vec<Value> = std::fs::read_to_string(out.join("reports2.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(
        rows.len(),
        5,
        "one compass per simulated log, one row for the bad one"
    );
    assert_eq!(lines.len(), 5);
    for ((row, line), log) in rows.iter().zip(&lines).zip(&logs) {
        let name = log.display().to_string();
        assert_eq!(row["log"], name);
        assert_eq!(line["log"], name.as_str());
        if log.ends_with("a0-broken.tlog") {
            assert_eq!(row["status"], "error");
            assert!(row["failure"].contains("cannot tell the format"), "{row:?}");
            assert!(line["error"]
                .as_str()
                .unwrap()
                .contains("cannot tell the format"));
            continue;
        }
        // The same log replayed alone, its report written by `--report`.
        let report_path = out.join("alone.json");
        let alone = imucald(&[
            "replay".as_ref(),
            log.as_os_str(),
            "--report".as_ref(),
            report_path.as_os_str(),
        ]);
        assert!(alone.status.success(), "{}", text(&alone));
        let report: Value =
            serde_json::from_str(&std::fs::read_to_string(&report_path).unwrap()).unwrap();
        assert_eq!(
            line["report"], report,
            "{name}: the reports line is the full report"
        );
        let mag = &report["calibration"]["mag"];
        assert_eq!(row["status"], "ok", "{name}");
        assert!(cell_matches(&row["instance"], &report["input"]["instance"]));
        for key in ["failure", "detail", "method", "model", "units"] {
            assert!(cell_matches(&row[key], &mag[key]), "{name} {key}: {row:?}");
        }
        assert!(cell_matches(
            &row["mounting_verdict"],
            &mag["mounting"]["verdict"]
        ));
        let verdict = report["quality"]
            .as_array()
            .and_then(|q| q.first())
            .map_or(Value::Null, |q| q["verdict"].clone());
        assert!(cell_matches(&row["verdict"], &verdict), "{row:?}");
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            assert!(cell_matches(
                &row[&format!("offset_{axis}")],
                &mag["offset"][k]
            ));
        }
        for r in 0..3 {
            for c in 0..3 {
                let cell = &row[&format!("matrix_{r}{c}")];
                assert!(cell_matches(cell, &mag["matrix"][r][c]), "{name} {r}{c}");
            }
        }
    }
}

#[test]
fn one_worker_and_two_workers_give_the_same_table_and_reports() {
    let d = tempfile::tempdir().unwrap();
    let (logs_dir, out) = (d.path().join("logs"), d.path().join("out"));
    std::fs::create_dir_all(&out).unwrap();
    std::fs::create_dir(&logs_dir).unwrap();
    fleet(&logs_dir);
    for jobs in ["1", "2"] {
        let run = batch(&logs_dir, &out, jobs);
        assert_eq!(run.status.code(), Some(3), "{}", text(&run));
        assert!(text(&run).contains(&format!("on {jobs} workers")));
    }
    let read = |name: &str| std::fs::read(out.join(name)).unwrap();
    assert_eq!(read("table1.csv"), read("table2.csv"));
    assert_eq!(read("reports1.jsonl"), read("reports2.jsonl"));
    // Nothing else in the output directory: no temporary file left behind.
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 4);
}

#[test]
fn a_batch_of_good_logs_exits_0_and_one_log_is_replayed_as_before() {
    let d = tempfile::tempdir().unwrap();
    let logs: Vec<PathBuf> = (1..=2)
        .map(|i| d.path().join(format!("g{i}.tlog")))
        .collect();
    for (i, p) in logs.iter().enumerate() {
        let seed = (10 + i).to_string();
        let out = imucald(&[
            "simulate".as_ref(),
            "--seed".as_ref(),
            seed.as_ref(),
            "--out".as_ref(),
            p.as_os_str(),
        ]);
        assert!(out.status.success(), "{}", text(&out));
    }
    let run = imucald(&["replay".as_ref(), logs[0].as_os_str(), logs[1].as_os_str()]);
    assert_eq!(run.status.code(), Some(0), "{}", text(&run));
    assert!(
        text(&run).contains("2 logs, 2 calibrated, 0 failed"),
        "{}",
        text(&run)
    );
    // One log: the per-sensor summary, not a batch line.
    let one = imucald(&["replay".as_ref(), logs[0].as_os_str()]);
    assert_eq!(one.status.code(), Some(0));
    let said = String::from_utf8_lossy(&one.stdout);
    assert!(said.starts_with("input: "), "{said}");
    assert!(said.contains("mag  : ok"), "{said}");
    assert!(!said.contains("logs,"), "{said}");
    // A per-log output in a batch is refused, with what to use instead.
    let refused = imucald(&[
        "replay".as_ref(),
        logs[0].as_os_str(),
        logs[1].as_os_str(),
        "--report".as_ref(),
        d.path().join("r.json").as_os_str(),
    ]);
    assert_eq!(refused.status.code(), Some(1));
    assert!(
        text(&refused).contains("--reports FILE.jsonl"),
        "{}",
        text(&refused)
    );
}

/// The table's columns are those of the Python example's Parquet rows, its 9-value matrix spread
/// over nine columns.
#[test]
fn the_table_has_the_python_examples_columns() {
    let src = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/examples_py/dask_fleet.py"
    ))
    .unwrap();
    let schema = &src[src.find("def table_schema").unwrap()..src.find("def find_logs").unwrap()];
    let mut python = vec![];
    for part in schema.split("(\"").skip(1) {
        let name = &part[..part.find('"').unwrap()];
        if name == "matrix" {
            python.extend((0..9).map(|i| format!("matrix_{}{}", i / 3, i % 3)));
        } else {
            python.push(name.to_string());
        }
    }
    let d = tempfile::tempdir().unwrap();
    let missing = d.path().join("missing.tlog");
    let t = d.path().join("t.csv");
    let run = imucald(&[
        "replay".as_ref(),
        missing.as_os_str(),
        "--table".as_ref(),
        t.as_os_str(),
    ]);
    assert_eq!(run.status.code(), Some(3), "{}", text(&run));
    let mut r = csv::Reader::from_path(&t).unwrap();
    let ours: Vec<String> = r.headers().unwrap().iter().map(String::from).collect();
    assert_eq!(ours, python);
    let row = r.records().next().unwrap().unwrap();
    assert_eq!(&row[3], "error");
    assert!(row[4].contains("cannot read"), "{row:?}");
}
