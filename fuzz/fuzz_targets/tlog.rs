//! The log-file readers on arbitrary bytes: `sources::decode_log` (gunzip, format detection, tlog
//! or CSV, as `imucald replay` reads a file), then `decode::decode_tlog` forced on the (gunzipped)
//! bytes, checked against the live replay reader `link::TlogRecords`.
#![no_main]

use imucald::config::Config;
use imucald::decode::{
    decode_tlog, detect_format, maybe_gunzip, InstanceChoice, MessageConverter, RawImuScale,
};
use imucald::link::TlogRecords;
use imucald::types::Sample;
use libfuzzer_sys::fuzz_target;
use std::path::Path;
use std::sync::OnceLock;

fn converter(data_len: usize) -> MessageConverter {
    // Vary the instance choice with the input so every IMU message kind is taken somewhere.
    let scale = RawImuScale {
        accel: 9.80665 / 4096.0,
        gyro: 0.0,
        mag: 0.1,
    };
    match data_len % 5 {
        0 => MessageConverter::new(InstanceChoice::Auto, RawImuScale::default()),
        1 => MessageConverter::new(InstanceChoice::Named("highres_imu:0".into()), scale),
        2 => MessageConverter::new(InstanceChoice::Named("raw_imu:0".into()), scale),
        3 => MessageConverter::new(InstanceChoice::Named("scaled_imu2".into()), scale),
        _ => MessageConverter::new(InstanceChoice::Auto, scale),
    }
}

fn check_sample(s: &Sample) {
    assert!(s.t_s.is_finite(), "{s:?}");
    for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut].into_iter().flatten() {
        assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
    }
    for x in [s.temp_c, s.throttle].into_iter().flatten() {
        assert!(x.is_finite(), "{s:?}");
    }
}

fuzz_target!(|data: &[u8]| {
    static CFG: OnceLock<Config> = OnceLock::new();
    let cfg = CFG.get_or_init(Config::default);
    if let Ok(log) = imucald::sources::decode_log(data, Path::new("fuzz.tlog"), None, cfg) {
        assert_eq!(log.samples.len() as u64, log.stats.records);
        log.samples.iter().for_each(check_sample);
    }

    let Ok(bytes) = maybe_gunzip(data) else {
        return;
    };
    let _ = detect_format(&bytes);
    let mut conv = converter(data.len());
    let samples = decode_tlog(&bytes, &mut conv);
    assert_eq!(samples.len() as u64, conv.stats.records);
    samples.iter().for_each(check_sample);

    // The replay link reads the same records as the offline reader.
    let mut conv2 = converter(data.len());
    let replayed: Vec<Sample> = TlogRecords::new(&bytes)
        .filter_map(|(ts, f)| conv2.convert(&f.message, ts))
        .collect();
    assert_eq!(samples, replayed);
});
