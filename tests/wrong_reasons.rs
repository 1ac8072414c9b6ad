//! Reasons that must name what is wrong, on readings of `../shared/data`: a hand tumble's
//! compass (`real/hand_tumble_acc_mag_no_time.csv`, gauss, no time column) turned into the
//! faults a user meets. Each is written to a temporary folder as a user's CSV would be and
//! replayed by the binary, and the report's compass record is checked for its failure, its words
//! and the coverage it shows:
//!
//! - scaled 5000x (about 3100 uT): too strong for any compass, not a coverage problem;
//! - held within 1.3 uT of a fixed 35 uT while the accelerometer turns: a field that does not
//!   turn, with no coverage claimed;
//! - left in gauss: the fit's radius check names the unit, and the readings still cover their
//!   directions.
//!
//! The data folder is shared, not in the repository: without it these tests say so and pass,
//! unless `IMUCALD_REQUIRE_DATA=1`, when they fail.

mod common;

use serde_json::Value;
use std::path::Path;
use std::process::Command;

/// The hand tumble with its magnetometer columns mapped by `mag` (gauss in, the CSV's value out),
/// written to `out`; `None` without the shared data.
fn tumble_with(out: &Path, mag: impl Fn(f64) -> f64) -> Option<()> {
    let data = common::testdata::shared_data()?;
    let text = std::fs::read_to_string(data.join("real/hand_tumble_acc_mag_no_time.csv"))
        .expect("the hand tumble in ../shared/data/real");
    let mut lines = text.lines();
    let mut csv = format!("{}\n", lines.next().expect("a header"));
    for l in lines {
        let v: Vec<&str> = l.split(',').collect();
        if v.len() != 6 {
            continue;
        }
        let m: Vec<String> = v[3..]
            .iter()
            .map(|x| format!("{:.6}", mag(x.parse::<f64>().unwrap_or(f64::NAN))))
            .collect();
        csv.push_str(&format!("{},{}\n", v[..3].join(","), m.join(",")));
    }
    std::fs::write(out, csv).expect("write the CSV");
    Some(())
}

/// `imucald replay CSV --rate-hz 50 --report`: the report.
fn replay(csv: &Path) -> Value {
    let report = csv.with_extension("json");
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["replay", "--rate-hz", "50", "--report"])
        .arg(&report)
        .arg(csv)
        .output()
        .expect("run imucald");
    assert!(
        report.exists(),
        "no report: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap()
}

#[test]
fn a_compass_reading_thousands_of_microtesla_is_implausible_not_short_of_coverage() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("strong.csv");
    if tumble_with(&csv, |g| g * 100.0 * 50.0).is_none() {
        return;
    }
    let r = replay(&csv);
    let mag = &r["calibration"]["mag"];
    assert_eq!(mag["failure"], "implausible", "{mag}");
    let detail = mag["detail"].as_str().unwrap_or_default();
    assert!(detail.contains("uT (median)"), "{detail}");
    assert!(!detail.contains("rotate"), "{detail}");
    assert_eq!(r["coverage"]["mag"]["filled"], 0, "{}", r["coverage"]);
}

#[test]
fn a_compass_whose_field_does_not_turn_says_so_and_claims_no_coverage() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("still.csv");
    // 20 uT on each axis, and the tumble's own field shrunk to a radius of 1.3 uT.
    if tumble_with(&csv, |g| 20.0 + g * 100.0 * 0.0434).is_none() {
        return;
    }
    let r = replay(&csv);
    let mag = &r["calibration"]["mag"];
    assert_eq!(mag["failure"], "implausible", "{mag}");
    let detail = mag["detail"].as_str().unwrap_or_default();
    assert!(
        detail.contains("does not turn with the vehicle"),
        "{detail}"
    );
    // Measured 99 of 100 before: the directions of noise about a centre of its own.
    assert_eq!(r["coverage"]["mag"]["filled"], 0, "{}", r["coverage"]);
}

#[test]
fn a_compass_in_gauss_is_named_as_a_unit_and_keeps_its_coverage() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("gauss.csv");
    if tumble_with(&csv, |g| g).is_none() {
        return;
    }
    let r = replay(&csv);
    let mag = &r["calibration"]["mag"];
    assert_eq!(mag["failure"], "radius", "{mag}");
    let detail = mag["detail"].as_str().unwrap_or_default();
    assert!(detail.contains("looks like gauss"), "{detail}");
    // Measured 99 of 100: the tumble covers its directions whatever the unit.
    assert!(
        r["coverage"]["mag"]["filled"].as_u64().unwrap_or(0) >= 50,
        "{}",
        r["coverage"]
    );
}

/// A calibration no better than none is not offered: BROAD's fast combined trial
/// (`broad/21_undisturbed_fast_combined.csv.gz`, a magnetometer calibrated upstream, an attitude
/// but no place) gets a sphere fit whose x offset (-1.2 uT) turns the heading at rest by about
/// 4 deg. Held out, it spreads the field's norm 2.29 % against 2.40 % as logged and its dip 3.69
/// against 3.37 deg: the verdict keeps the readings as logged, and nothing is to load. The
/// phone-vibration trial's calibration (norm 1.82 % against 4.98 %) is still offered.
#[test]
fn a_calibration_no_better_than_the_readings_as_logged_is_not_offered() {
    let Some(data) = common::testdata::shared_data() else {
        return;
    };
    for (trial, load) in [
        ("21_undisturbed_fast_combined", false),
        ("26_disturbed_phone_vibration_A", true),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let report = dir.path().join("r.json");
        Command::new(env!("CARGO_BIN_EXE_imucald"))
            .args(["replay", "--report"])
            .arg(&report)
            .arg(data.join(format!("broad/{trial}.csv.gz")))
            .output()
            .expect("run imucald");
        let r: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        let q = &r["quality"][0];
        let verdict = q["verdict"].as_str().unwrap();
        assert_eq!(r["load"][0]["load"], load, "{trial}: {verdict}");
        if load {
            assert_eq!(q["verdict_kind"], "no_onboard", "{trial}: {verdict}");
            assert!(
                verdict.contains("better than the readings as logged"),
                "{verdict}"
            );
        } else {
            assert_eq!(q["verdict_kind"], "keep_vehicle", "{trial}: {verdict}");
            assert!(verdict.contains("keep the readings as logged"), "{verdict}");
            assert_eq!(q["method"], "sphere (fitted on every reading)", "{verdict}");
        }
    }
}

/// PX4's primary compass is the one `vehicle_magnetometer` was selected from: on
/// `flightlogs/px4_cubeorange_two_mags.ulg` that is CAL_MAG1's device (592905, `sensor_mag[1]`),
/// so the primary's record is compass 1, not compass 0 (another device): its calibration would
/// otherwise be judged against, and exported to, the wrong compass.
#[test]
fn the_primary_px4_compass_is_the_slot_its_magnetometer_belongs_to() {
    let Some(data) = common::testdata::shared_data() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("r.json");
    Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["replay", "--report"])
        .arg(&report)
        .arg(data.join("flightlogs/px4_cubeorange_two_mags.ulg"))
        .output()
        .expect("run imucald");
    let r: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let slot = r["onboard"]["mag"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| {
            m["sources"]
                .as_array()
                .unwrap()
                .iter()
                .any(|s| s == "vehicle_magnetometer[0]")
        })
        .expect("a slot for vehicle_magnetometer[0]");
    assert_eq!(slot["device_id"], 592905);
    let primary = r["instances"]
        .as_array()
        .unwrap()
        .iter()
        .find(|i| i["primary"] == true)
        .expect("a primary");
    assert_eq!(primary["compass_id"], slot["instance"], "{primary}");
    assert_eq!(primary["compass_id"], 1);
    assert_eq!(r["load"][0]["compass_id"], 1);
}
