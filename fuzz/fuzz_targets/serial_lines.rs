//! The serial text path: `link::LineBuffer` over a chunked byte stream, then each line through
//! `link::parse_motioncal_line` and `link::CsvLineParser::parse` (several column layouts).
#![no_main]

mod common;

use imucald::link::{parse_motioncal_line, CsvLineParser, LineBuffer, MAX_LINE};
use imucald::types::Sample;
use libfuzzer_sys::fuzz_target;
use std::collections::BTreeMap;
use std::sync::OnceLock;

fn parsers() -> Vec<CsvLineParser> {
    let f = |names: &[&str]| names.iter().map(|s| s.to_string()).collect::<Vec<String>>();
    let mut scales = BTreeMap::new();
    for k in ["ax", "ay", "az"] {
        scales.insert(k.to_string(), 9.80665);
    }
    scales.insert("gx".to_string(), f64::NAN);
    scales.insert("t".to_string(), 1e-3);
    vec![
        CsvLineParser::new(
            &f(&["ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz"]),
            &scales,
        ),
        CsvLineParser::new(&f(&["t", "ax", "ay", "az", "_", "mx", "my", "mz"]), &scales),
        CsvLineParser::new(
            &f(&[
                "t", "ax", "ay", "az", "gx", "gy", "gz", "mx", "my", "mz", "temp", "throttle",
                "current", "ref_qw", "ref_qx", "ref_qy", "ref_qz", "moving",
            ]),
            &BTreeMap::new(),
        ),
        CsvLineParser::new(&f(&["mx", "", "my", "bogus", "mz"]), &BTreeMap::new()),
    ]
}

fn check(s: &Sample) {
    assert!(s.t_s.is_finite() && !s.is_empty(), "{s:?}");
    for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut].into_iter().flatten() {
        assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
    }
}

fuzz_target!(|data: &[u8]| {
    static PARSERS: OnceLock<Vec<CsvLineParser>> = OnceLock::new();
    let parsers = PARSERS.get_or_init(parsers);
    let (chunks, _) = common::chunks(data);
    let mut buf = LineBuffer::new();
    let mut lines = Vec::new();
    for c in &chunks {
        let (got, _dropped) = buf.push(c);
        lines.extend(got);
    }
    lines.extend(buf.take_partial());
    for (i, line) in lines.iter().enumerate() {
        // Over-long lines are dropped, never handed on.
        assert!(line.chars().count() <= MAX_LINE, "line of {} chars", line.len());
        let t = i as f64 * 0.01;
        if let Some(s) = parse_motioncal_line(line, t) {
            check(&s);
            assert_eq!(s.t_s, t);
            // int16 counts: |accel| <= 4 g per axis, |mag| <= 3276.8 uT.
            let a = s.accel_mps2.expect("accel");
            assert!(a.iter().all(|x| x.abs() <= 4.0 * 9.80665 + 1e-9), "{a:?}");
        }
        for p in parsers {
            if let Some(s) = p.parse(line, t) {
                check(&s);
            }
        }
    }
});
