//! `diagnose` on every real log in `../shared/data` it reads (`real/` and `flightlogs/`: DataFlash,
//! ULog, telemetry): nothing is named whose size the data do not determine, every reason is a
//! record, and each named effect ends in its flight-controller parameters.
//!
//! The table of docs/diagnose.md comes from this test:
//! `cargo test --release --test diagnose_real -- --nocapture`.
//! Without the shared data the test says SKIPPED and passes, unless `IMUCALD_REQUIRE_DATA=1`.

mod common;

use imucald::config::Config;
use imucald::diagnose::fix::fixes;
use imucald::diagnose::{diagnose, DiagnoseOptions, DiagnosisReport, MIN_SIZE_SIGMAS};
use std::path::PathBuf;

/// The logs `diagnose` reads: every `.bin`, `.ulg` and `.tlog` of the two folders.
fn logs() -> Option<Vec<PathBuf>> {
    let data = common::testdata::shared_data()?;
    let mut out = vec![];
    for dir in ["real", "flightlogs"] {
        let Ok(rd) = std::fs::read_dir(data.join(dir)) else {
            continue;
        };
        for e in rd.flatten() {
            let p = e.path();
            let ext = p.extension().and_then(|x| x.to_str()).unwrap_or("");
            if ["bin", "ulg", "tlog"].contains(&ext) {
                out.push(p);
            }
        }
    }
    out.sort();
    Some(out)
}

/// Every effect found has, in the final fit on all units, a parameter group whose size is at
/// least [`MIN_SIZE_SIGMAS`] times its largest sigma, and the round that named it a determined
/// size record.
fn assert_determined(name: &str, r: &DiagnosisReport) {
    for e in &r.found {
        let round = r
            .rounds
            .iter()
            .find(|x| x.effect == Some(*e) && x.decision == imucald::diagnose::Decision::Named)
            .expect("the round that named it");
        let cand = round
            .candidates
            .iter()
            .find(|c| c.name == e.name())
            .expect("its candidate");
        let size = cand.size.as_ref().expect("a size record");
        assert!(size.determined(), "{name}: {} named with {size}", e.name());
        // The reported estimates (all units): the vector of each unit's parameters against the
        // largest sigma among them.
        let p = &r.effects[e.name()];
        let mut by_unit: std::collections::BTreeMap<&str, (f64, f64)> = Default::default();
        for (k, v) in p {
            if k == "lag_s" {
                continue;
            }
            let g = by_unit.entry(v.unit.as_str()).or_default();
            g.0 += v.value * v.value;
            g.1 = g.1.max(v.sigma);
        }
        assert!(
            by_unit
                .values()
                .any(|(ss, smax)| ss.sqrt() >= MIN_SIZE_SIGMAS * smax),
            "{name}: {} reported {p:?}",
            e.name()
        );
    }
}

fn assert_no_empty_reason(name: &str, r: &DiagnosisReport) {
    for rd in &r.rounds {
        assert!(!rd.detail.trim().is_empty(), "{name}: round {}", rd.round);
        for c in &rd.candidates {
            if c.identifiable && !c.plausible {
                assert!(!c.out_of_range.is_empty(), "{name}: {} no record", c.name);
            }
            if !c.identifiable {
                assert!(!c.note.trim().is_empty(), "{name}: {} no reason", c.name);
            }
            assert!(!c.note.contains(": ;"), "{name}: {}", c.note);
        }
    }
}

/// One table row: log, seed, what is named (with sigma), what is exported, the held-out shrink.
fn row(name: &str, seed: u64, r: &DiagnosisReport) -> String {
    let named: Vec<String> = r
        .rounds
        .iter()
        .filter(|x| x.decision == imucald::diagnose::Decision::Named)
        .filter_map(|x| {
            let e = x.effect?;
            let c = x.candidates.iter().find(|c| c.name == e.name())?;
            let s = c.size.as_ref()?;
            Some(format!("{} ({:.1} sigma)", e.name(), s.best_sigmas()))
        })
        .collect();
    let possible: Vec<String> = r
        .rounds
        .iter()
        .filter_map(|x| x.possible.as_ref())
        .map(|p| format!("{} ({:.1} sigma)", p.effect.name(), p.size.best_sigmas()))
        .collect();
    let exported: Vec<String> = fixes(r)
        .iter()
        .flat_map(|f| {
            f.ardupilot
                .iter()
                .map(|(n, v)| format!("{n} {v:.0}"))
                .collect::<Vec<_>>()
        })
        .collect();
    let mn = r.rms_channels.get("mag_norm");
    let shrink = mn.map_or("-".to_string(), |c| {
        format!("{:.2} -> {:.2} uT", c.before, c.after)
    });
    let last = r
        .rounds
        .last()
        .map_or("-".to_string(), |x| x.decision.to_string());
    format!(
        "| `{name}` | {seed} | {} | {} | {} | {shrink} | {last} |",
        if named.is_empty() {
            "nothing".to_string()
        } else {
            named.join(", ")
        },
        if possible.is_empty() {
            "-".to_string()
        } else {
            possible.join(", ")
        },
        if exported.is_empty() {
            "-".to_string()
        } else {
            exported.join(", ")
        },
    )
}

#[test]
fn nothing_undetermined_is_named_on_any_real_log() {
    let Some(logs) = logs() else { return };
    let cfg = Config::default();
    eprintln!("| log | seed | named (size in sigma) | might be there (size in sigma) | ArduPilot parameters exported | held-out mag_norm RMS | last round |");
    eprintln!("| --- | --- | --- | --- | --- | --- | --- |");
    for path in logs {
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let Ok(log) = imucald::io::sources::read_log(&path, None, &cfg.input) else {
            eprintln!("| `{name}` | - | not read | - | - | - | - |");
            continue;
        };
        // The telemetry flights whose split moves what is named: every seed of 0..4.
        let seeds: &[u64] = if name.starts_with("apm_copter_2013") {
            &[0, 1, 2, 3]
        } else {
            &[0]
        };
        for &seed in seeds {
            let opts = DiagnoseOptions {
                seed,
                log_where: log.place(),
                ..Default::default()
            };
            let r = diagnose(&log.samples, &cfg, &opts);
            eprintln!("{}", row(&name, seed, &r));
            if name == "px4_tropic_ekf_failure.ulg" {
                // The flight whose misalignment fits, holds and is significant but is not
                // determined in size (measured: 1.9 sigma): said as possible, not named.
                let e = imucald::diagnose::Effect::MagAccelMisalignment;
                assert!(!r.found.contains(&e), "{:?}", r.found);
                let p = r.rounds.iter().find_map(|x| x.possible.as_ref());
                assert!(
                    p.is_some_and(|p| p.effect == e && p.size.best_sigmas() < MIN_SIZE_SIGMAS),
                    "{}",
                    r.outcome()
                );
            }
            assert_determined(&name, &r);
            assert_no_empty_reason(&name, &r);
            for f in fixes(&r) {
                assert!(
                    !f.ardupilot.is_empty() || !f.notes.is_empty(),
                    "{name}: {} has no fix",
                    f.effect.name()
                );
            }
        }
    }
}
