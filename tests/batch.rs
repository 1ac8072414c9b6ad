//! `imucald replay` over many logs: the table and the reports against each log's own replay, a bad
//! log among good ones, the same table from one worker and from two, and the exit status of logs
//! that calibrate something but have nothing to load.

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
    assert!(
        said.contains(
            "5 logs, 4 calibrated (4 with something to load, 0 nothing to load), 1 failed"
        ),
        "{said}"
    );
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
        // The held-out entry and the load decision of the log's one compass.
        let quality = report["quality"]
            .as_array()
            .and_then(|q| q.first())
            .cloned()
            .unwrap_or(Value::Null);
        assert!(
            cell_matches(&row["verdict"], &quality["verdict_kind"]),
            "{row:?}"
        );
        let load = &report["load"][0];
        assert_eq!(row["load"], load["load"].to_string(), "{name}");
        assert!(
            cell_matches(&row["load_reason"], &load["reason"]),
            "{row:?}"
        );
        let rung = match &quality["rung"] {
            Value::Null => &mag["rung"],
            r => r,
        };
        assert!(cell_matches(&row["rung"], rung), "{row:?}");
        assert_eq!(mag["units"], "uT");
        assert!(cell_matches(&row["radius_ut"], &mag["radius"]), "{row:?}");
        assert!(
            cell_matches(&row["rms_ut"], &mag["rms_residual"]),
            "{row:?}"
        );
        assert!(cell_matches(
            &row["coverage_regions"],
            &report["coverage"]["mag"]["filled"]
        ));
        for (col, who, key) in [
            ("heldout_norm_pct", "imucald", "norm_spread_pct"),
            ("heldout_dip_deg", "imucald", "dip_spread_deg"),
            ("vehicle_norm_pct", "onboard", "norm_spread_pct"),
            ("vehicle_dip_deg", "onboard", "dip_spread_deg"),
        ] {
            assert!(
                cell_matches(&row[col], &quality[who][key]),
                "{col}: {row:?}"
            );
        }
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
        text(&run).contains(
            "2 logs, 2 calibrated (2 with something to load, 0 nothing to load), 0 failed"
        ),
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

/// A CSV of an accelerometer and a gyro (no magnetometer) resting in three poses for 5 s each at
/// 100 Hz, turned between them: a gyro bias passes, the accelerometer (3 poses of the 7 it needs)
/// and the compass (no readings) do not. The noise is a fixed pseudo-random sequence.
fn gyro_bias_only_csv(path: &Path) {
    const G_MPS2: f64 = 9.80665;
    const BIAS_RADPS: [f64; 3] = [0.01, -0.02, 0.005];
    let mut state: u64 = 0x2545_f491_4f6c_dd1d;
    let mut noise = move |scale: f64| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) * scale
    };
    let tilt_rad: f64 = 0.5;
    let poses = [
        [0.0, 0.0, -G_MPS2],
        [0.0, G_MPS2 * tilt_rad.sin(), -G_MPS2 * tilt_rad.cos()],
        [G_MPS2 * tilt_rad.sin(), 0.0, -G_MPS2 * tilt_rad.cos()],
    ];
    let mut text = String::from("t,ax,ay,az,gx,gy,gz\n");
    let mut t_s = 0.0;
    let mut row = |accel: [f64; 3], gyro: [f64; 3], text: &mut String| {
        text.push_str(&format!("{t_s:.2}"));
        for a in accel {
            text.push_str(&format!(",{:.4}", a + noise(0.03)));
        }
        for g in gyro {
            text.push_str(&format!(",{:.5}", g + noise(0.003)));
        }
        text.push('\n');
        t_s += 0.01;
    };
    for (k, pose) in poses.iter().enumerate() {
        for _ in 0..500 {
            row(*pose, BIAS_RADPS, &mut text);
        }
        if let Some(next) = poses.get(k + 1) {
            for i in 0..100 {
                let f = f64::from(i) / 100.0;
                let accel = std::array::from_fn(|a| pose[a] * (1.0 - f) + next[a] * f);
                row(accel, [0.5, 0.3, BIAS_RADPS[2]], &mut text);
            }
        }
    }
    std::fs::write(path, text).unwrap();
}

/// A log that calibrates a gyro bias only has nothing to load: alone it exits 4 naming its
/// compass's reason; beside a log that failed the batch exits 3 (the failure first), counting it
/// as calibrated with nothing to load; a log with something to load beside it makes the batch's
/// exit 0.
#[test]
fn a_gyro_bias_only_is_nothing_to_load_alone_and_in_a_batch() {
    let d = tempfile::tempdir().unwrap();
    let gyro = d.path().join("gyro.csv");
    gyro_bias_only_csv(&gyro);
    let alone = imucald(&["replay".as_ref(), gyro.as_os_str()]);
    let said = text(&alone);
    assert_eq!(alone.status.code(), Some(4), "{said}");
    assert!(said.contains("gyro : bias"), "{said}");
    assert!(
        said.contains(
            "error: nothing to load (exit status 4): compass 0 (primary): the fit failed"
        ),
        "{said}"
    );
    assert!(said.contains("keep the vehicle's calibration"), "{said}");

    let broken = d.path().join("broken.tlog");
    std::fs::write(&broken, vec![0x81u8; 4096]).unwrap();
    let t = d.path().join("t.csv");
    let run = imucald(&[
        "replay".as_ref(),
        gyro.as_os_str(),
        broken.as_os_str(),
        "--table".as_ref(),
        t.as_os_str(),
    ]);
    let said = text(&run);
    assert_eq!(run.status.code(), Some(3), "{said}");
    assert!(
        said.contains(
            "2 logs, 1 calibrated (0 with something to load, 1 nothing to load), 1 failed"
        ),
        "{said}"
    );
    let rows = table(&t);
    assert_eq!(rows[0]["status"], "failed");
    assert_eq!(
        (rows[0]["load"].as_str(), rows[0]["load_reason"].as_str()),
        ("false", "fit_failed")
    );

    let tumble = d.path().join("tumble.tlog");
    let sim = imucald(&["simulate".as_ref(), "--out".as_ref(), tumble.as_os_str()]);
    assert!(sim.status.success(), "{}", text(&sim));
    let run = imucald(&["replay".as_ref(), gyro.as_os_str(), tumble.as_os_str()]);
    let said = text(&run);
    assert_eq!(run.status.code(), Some(0), "{said}");
    assert!(
        said.contains(
            "2 logs, 2 calibrated (1 with something to load, 1 nothing to load), 0 failed"
        ),
        "{said}"
    );
}
