//! The live MAVLink path: `decode::FrameDecoder::push` on a byte stream cut into chunks (as serial
//! and TCP reads deliver it), then every frame through `MessageConverter::convert`, as
//! `link.rs` and `daemon.rs` do.
#![no_main]

mod common;

use imucald::decode::{FrameDecoder, InstanceChoice, MessageConverter, RawImuScale};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let (chunks, stream) = common::chunks(data);
    let mut dec = FrameDecoder::new();
    let mut frames = Vec::new();
    for c in &chunks {
        frames.extend(dec.push(c));
    }
    // The frames do not depend on how the stream was cut.
    let mut whole = FrameDecoder::new();
    let once = whole.push(stream);
    assert_eq!(frames.len(), once.len());
    for (a, b) in frames.iter().zip(&once) {
        assert_eq!((a.system_id, a.component_id), (b.system_id, b.component_id));
        assert_eq!(format!("{:?}", a.message), format!("{:?}", b.message));
    }

    let scale = RawImuScale {
        accel: 1e-3,
        gyro: 1e-3,
        mag: 0.1,
    };
    for choice in [InstanceChoice::Auto, InstanceChoice::Named("raw_imu:0".into())] {
        let mut conv = MessageConverter::new(choice, scale);
        // Receive times as the daemon gives them: a clock that moves on.
        let mut time_us = 1_700_000_000_000_000u64;
        for f in &frames {
            time_us += 1000;
            if let Some(s) = conv.convert(&f.message, time_us) {
                assert!(s.t_s.is_finite(), "{s:?}");
                for v in [s.accel_mps2, s.gyro_rad_s, s.mag_ut].into_iter().flatten() {
                    assert!(v.iter().all(|x| x.is_finite()), "{s:?}");
                }
            }
        }
        let _ = conv.units();
    }
});
