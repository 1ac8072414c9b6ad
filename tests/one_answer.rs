//! One answer everywhere: every real log of `../shared/data` (`real/` and `flightlogs/`) replayed
//! once with a report, an HTML page and the exports, and each output's account of every compass
//! compared with the report's record of it: the terminal's summary, the page's data, the
//! parameter files (values only for the compasses the report's `load` says to load, each equal to
//! the record's offset), and the held-out verdict's words against the onboard block.
//!
//! The data folder is shared, not in the repository: without it these tests say so and pass,
//! unless `IMUCALD_REQUIRE_DATA=1`, when they fail.

mod common;

use imucald::app::replay::{replay, summary, ReplayOptions};
use imucald::config::Config;
use imucald::report::{CalStatus, Report, SensorCalibration, Verdict};
use serde_json::Value;
use std::path::{Path, PathBuf};

fn logs() -> Option<Vec<PathBuf>> {
    let data = common::testdata::shared_data()?;
    let mut out = Vec::new();
    for dir in ["real", "flightlogs"] {
        for e in std::fs::read_dir(data.join(dir)).ok()? {
            let p = e.ok()?.path();
            if p.extension()
                .is_some_and(|x| x == "tlog" || x == "bin" || x == "ulg")
            {
                out.push(p);
            }
        }
    }
    out.sort();
    Some(out)
}

/// The JSON the HTML page carries (`<script type="application/json" id="data">`).
fn page_data(html: &str) -> Value {
    let start = html
        .find("<script type=\"application/json\" id=\"data\">")
        .expect("the page's data")
        + "<script type=\"application/json\" id=\"data\">".len();
    let end = start + html[start..].find("</script>").expect("its end");
    serde_json::from_str(&html[start..end]).expect("the page's data is JSON")
}

/// Every compass record of the report: (instance, compass id, the record).
fn compasses(r: &Report) -> Vec<(String, u8, &SensorCalibration)> {
    let primary = r.instances.iter().find(|i| i.primary);
    let mut out = vec![(
        primary
            .map(|i| i.instance.clone())
            .or_else(|| r.input.instance.clone())
            .unwrap_or_else(|| "primary".into()),
        primary.map_or(0, |i| i.compass_id),
        &r.calibration.mag,
    )];
    for i in r.instances.iter().filter(|i| !i.primary) {
        out.push((i.instance.clone(), i.compass_id, &i.calibration.mag));
    }
    out
}

/// The fields a person compares: status, failure, method, rung, model, offset and matrix.
fn essentials(v: &Value) -> Value {
    serde_json::json!({
        "status": v["status"], "failure": v["failure"], "method": v["method"], "rung": v["rung"],
        "model": v["model"], "offset": v["offset"], "matrix": v["matrix"],
    })
}

/// The same JSON, numbers to 1e-12 of their size (a reader may round the last digit).
fn same(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            (x - y).abs() <= 1e-12 * x.abs().max(y.abs()).max(1.0)
        }
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(x, y)| same(x, y))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| same(v, w)))
        }
        _ => a == b,
    }
}

fn check_log(log: &Path, dir: &Path) {
    let name = log.file_name().unwrap().to_string_lossy().to_string();
    let (report_path, html_path, export) = (
        dir.join(format!("{name}.json")),
        dir.join(format!("{name}.html")),
        dir.join(format!("{name}.export")),
    );
    let opts = ReplayOptions {
        report: Some(report_path.clone()),
        html: Some(html_path.clone()),
        export_dir: Some(export.clone()),
        ..Default::default()
    };
    let out = replay(log, &Config::default(), &opts, &mut |_, _| {})
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let r = &out.report;
    // The report file holds each compass's record as the report has it.
    let written: Report =
        serde_json::from_str(&std::fs::read_to_string(&report_path).unwrap()).unwrap();
    for ((i, _, a), (_, _, b)) in compasses(r).iter().zip(compasses(&written)) {
        let (a, b) = (
            essentials(&serde_json::to_value(a).unwrap()),
            essentials(&serde_json::to_value(b).unwrap()),
        );
        assert!(same(&a, &b), "{name} {i}: the report file: {a} against {b}");
    }

    // The page: each compass's record as the report has it.
    let page = page_data(&std::fs::read_to_string(&html_path).unwrap());
    let views = page["views"]["instances"].as_array().expect("views");
    for (instance, _, mag) in compasses(r) {
        let view = views
            .iter()
            .find(|v| {
                v["instance"].as_str() == Some(instance.as_str())
                    || (v["primary"] == true && std::ptr::eq(mag, &r.calibration.mag))
            })
            .unwrap_or_else(|| panic!("{name}: no view of {instance}"));
        let shown = view["sensors"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["sensor"] == "mag")
            .expect("the magnetometer's view");
        let (a, b) = (
            essentials(&shown["calibration"]),
            essentials(&serde_json::to_value(mag).unwrap()),
        );
        assert!(
            same(&a, &b),
            "{name} {instance}: the page {a} against the report {b}"
        );
    }

    // The terminal: the primary's line says the record's status and failure.
    let text = summary(r);
    let line = text
        .lines()
        .find(|l| l.starts_with("mag  :"))
        .unwrap_or_else(|| panic!("{name}: no mag line in\n{text}"));
    match (r.calibration.mag.status, r.calibration.mag.failure) {
        (CalStatus::Ok, _) => assert!(line.starts_with("mag  : ok"), "{name}: {line}"),
        (_, Some(f)) => assert!(
            line.contains(&format!("FAILED ({})", f.name())),
            "{name}: {line}"
        ),
        (_, None) => assert!(line.contains("FAILED"), "{name}: {line}"),
    }

    // The exports: values only for the compasses to load, each the record's offset; the others
    // as comments; no folder when nothing passed.
    let parm = export.join("ardupilot.parm");
    if !parm.exists() {
        assert!(
            !export.exists() || std::fs::read_dir(&export).unwrap().next().is_none(),
            "{name}: an export folder without the parameter file"
        );
        assert!(
            r.load.iter().all(|d| !d.load) || r.onboard.as_ref().is_some_and(|o| o.stack == "px4"),
            "{name}: compasses to load but no ardupilot.parm: {:?}",
            r.load
        );
    } else {
        let text = std::fs::read_to_string(&parm).unwrap();
        let values = common::parm_values(&text);
        for (instance, k, mag) in compasses(r) {
            let suffix = ["", "2", "3"][k.min(2) as usize];
            let ofs = values.get(&format!("COMPASS_OFS{suffix}_X"));
            let d = r.load.iter().find(|d| d.compass_id == k);
            match d {
                Some(d) if d.load => {
                    let v =
                        ofs.unwrap_or_else(|| panic!("{name} {instance}: to load, not written"));
                    assert!(
                        (v + 10.0 * mag.offset[0]).abs() < 1e-3,
                        "{name} {instance}: COMPASS_OFS{suffix}_X {v} against the record's {:?}",
                        mag.offset
                    );
                }
                Some(d) if mag.status == CalStatus::Ok => {
                    assert!(
                        ofs.is_none(),
                        "{name} {instance}: not to load ({:?}) but written",
                        d.reason
                    );
                    assert!(
                        text.contains("not to load"),
                        "{name} {instance}: no comment"
                    );
                }
                _ => {}
            }
        }
    }

    // The verdict's words: "no onboard" only where the log carries no calibration of that compass.
    for q in &r.quality {
        if q.verdict_kind == Some(Verdict::NoOnboard) {
            let k = compasses(r).iter().find(|c| c.0 == q.instance).map(|c| c.1);
            let has = r.onboard.as_ref().is_some_and(|o| {
                o.mag
                    .iter()
                    .any(|m| Some(m.instance) == k && !m.sources.is_empty())
            });
            assert!(
                !has,
                "{name} {}: 'no onboard' beside an onboard calibration",
                q.instance
            );
        }
        assert!(
            !q.verdict.contains("()"),
            "{name}: an empty reason: {}",
            q.verdict
        );
    }
    println!(
        "{name}: {} compasses, to load: {:?}",
        compasses(r).len(),
        r.load
            .iter()
            .filter(|d| d.load)
            .map(|d| &d.instance)
            .collect::<Vec<_>>()
    );
}

#[test]
fn every_output_of_a_replay_of_every_real_log_gives_one_answer() {
    let Some(logs) = logs() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    assert!(logs.len() >= 15, "{} logs", logs.len());
    for log in &logs {
        check_log(log, dir.path());
    }
}
