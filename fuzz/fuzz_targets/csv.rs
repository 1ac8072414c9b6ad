//! The CSV log reader `decode::decode_csv` on arbitrary text, with the default column names and
//! with a user mapping (renamed columns and unit scales).
#![no_main]

use imucald::decode::{decode_csv, CsvMapping, DecodeStats};
use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;

fn user_mapping() -> CsvMapping {
    let mut m = CsvMapping::default();
    for (f, c) in [
        ("t", "time_ms"),
        ("ax", "AccX"),
        ("ay", "AccY"),
        ("az", "AccZ"),
        ("mx", "MagX"),
        ("my", "MagY"),
        ("mz", "MagZ"),
    ] {
        m.columns.insert(f.into(), c.into());
    }
    m.scales.insert("t".into(), 0.001);
    for f in ["ax", "ay", "az"] {
        m.scales.insert(f.into(), 9.80665);
    }
    m.scales.insert("gx".into(), 1e300);
    m
}

fuzz_target!(|data: &[u8]| {
    static MAPS: OnceLock<[CsvMapping; 2]> = OnceLock::new();
    let maps = MAPS.get_or_init(|| [CsvMapping::default(), user_mapping()]);
    let text = String::from_utf8_lossy(data);
    for m in maps {
        let mut stats = DecodeStats::default();
        match decode_csv(&text, m, &mut stats) {
            Ok(samples) => {
                assert_eq!(samples.len() as u64, stats.records);
                for s in &samples {
                    assert!(s.t_s.is_finite() && !s.is_empty(), "{s:?}");
                    for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut].into_iter().flatten() {
                        assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
                    }
                    for x in [s.temp_c, s.throttle, s.current_a].into_iter().flatten() {
                        assert!(x.is_finite(), "{s:?}");
                    }
                }
            }
            Err(e) => assert!(!e.is_empty()),
        }
    }
});
