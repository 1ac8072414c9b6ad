//! Tests of the decoders, and what other readers' tests share ([`Trickle`]).

use super::*;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MavlinkVersion, Message};

#[test]
fn known_message_ids_are_the_dialects() {
    let mut known = 0;
    for id in (0..70_000u32).chain([1 << 20, (1 << 24) - 1, u32::MAX]) {
        let want = MavMessage::default_message_from_id(id).is_some();
        assert_eq!(known_message(id), want, "id {id}");
        known += want as usize;
    }
    // HEARTBEAT, HIGHRES_IMU, ArduPilot's MAG_CAL_REPORT: and a few hundred in all.
    assert!(known_message(0) && known_message(105) && known_message(192));
    assert!(known > 200, "{known}");
}

/// `msg` as a MAVLink `v` frame from system 1, component 1.
fn frame_bytes(msg: &MavMessage, v: MavlinkVersion) -> Vec<u8> {
    let mut enc = crate::io::mavout::MavEncoder::new(1, 1);
    enc.version = v;
    enc.encode(msg)
}

fn imu_msg(x: f32) -> MavMessage {
    crate::testdata::level_highres_imu(1000, x)
}

#[test]
fn frame_crc_matches_the_mavlink_crate() {
    let mut x = 0x1234_5678u32;
    for len in [0usize, 1, 2, 9, 30, 255, 280] {
        let data: Vec<u8> = (0..len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                x as u8
            })
            .collect();
        for extra in [0u8, 46, 255] {
            assert_eq!(
                frame_crc(&data, extra),
                mavlink::calculate_crc(&data, extra)
            );
        }
    }
}

#[test]
fn frames_v1_and_v2_roundtrip_and_bad_crc_is_counted() {
    for v in [MavlinkVersion::V1, MavlinkVersion::V2] {
        let b = frame_bytes(&imu_msg(0.5), v);
        match parse_frame(&b) {
            FrameParse::Frame(f, n) => {
                assert_eq!(n, b.len());
                assert!(matches!(f.message, MavMessage::HIGHRES_IMU(_)));
            }
            other => panic!("{other:?}"),
        }
        let mut bad = b.clone();
        let k = bad.len() - 4;
        bad[k] ^= 0x55;
        assert!(matches!(
            parse_frame(&bad),
            FrameParse::Skip(_, SkipReason::BadCrc)
        ));
        assert!(matches!(
            parse_frame(&b[..b.len() - 1]),
            FrameParse::Incomplete
        ));
    }
}

#[test]
fn stream_decoder_resyncs_over_garbage() {
    let mut bytes = vec![0x00, 0x13, 0xFD, 0x77];
    bytes.extend(frame_bytes(&imu_msg(1.0), MavlinkVersion::V2));
    bytes.extend([1, 2, 3]);
    bytes.extend(frame_bytes(&imu_msg(2.0), MavlinkVersion::V1));
    let mut d = FrameDecoder::new();
    let mut frames = d.push(&bytes[..10]);
    frames.extend(d.push(&bytes[10..]));
    assert_eq!(frames.len(), 2);
}

#[test]
fn tlog_with_damage_is_decoded_and_counted() {
    let mut log = Vec::new();
    for i in 0..10u64 {
        log.extend((1_700_000_000_000_000u64 + i * 10_000).to_be_bytes());
        log.extend(frame_bytes(&imu_msg(i as f32), MavlinkVersion::V2));
    }
    // Damage record 3's CRC and cut the last record in half.
    let rec = log.len() / 10;
    log[3 * rec + rec - 3] ^= 0xFF;
    log.truncate(log.len() - rec / 2);
    let mut conv = MessageConverter::new(InstanceChoice::Auto, RawImuScale::default());
    let s = decode_tlog(&log, &mut conv);
    assert_eq!(s.len(), 8);
    assert_eq!(conv.stats.skipped.get("bad_crc"), Some(&1));
    assert_eq!(conv.stats.skipped.get("truncated"), Some(&1));
    let m = s[0].mag_ut.unwrap();
    assert!((m[0] - 20.0).abs() < 1e-4 && (m[2] - 40.0).abs() < 1e-4);
    assert_eq!(conv.instance(), Some("highres_imu:0"));
}

/// A reader that hands out at most `step` bytes a read, the way a pipe or a gzip stream may.
pub(crate) struct Trickle<'a> {
    pub bytes: &'a [u8],
    pub step: usize,
}

impl std::io::Read for Trickle<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = buf.len().min(self.step).min(self.bytes.len());
        buf[..n].copy_from_slice(&self.bytes[..n]);
        self.bytes = &self.bytes[n..];
        Ok(n)
    }
}

#[test]
fn a_tlog_streamed_through_a_window_reads_as_the_whole_bytes() {
    // Over a megabyte (several windows) of records with damage of every kind spread
    // through it, so that windows end inside garbage, inside a resynchronisation and inside
    // records; the last record cut.
    let mut log = Vec::new();
    let mut x = 0x9E37_79B9u32;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        x
    };
    for i in 0..24_000u64 {
        let v = if i % 2 == 0 {
            MavlinkVersion::V2
        } else {
            MavlinkVersion::V1
        };
        let at = log.len();
        log.extend((1_700_000_000_000_000u64 + i * 10_000).to_be_bytes());
        log.extend(frame_bytes(&imu_msg(i as f32), v));
        match next() % 97 {
            0 => log.extend((0..next() % 700).map(|_| next() as u8)),
            1 => log[at + 12] ^= 0x5A,
            2 => log.extend([0xFD, 0x09, 0x00]),
            _ => {}
        }
    }
    log.truncate(log.len() - 20);
    assert!(
        log.len() > 4 * crate::io::window::STREAM_CHUNK_BYTES,
        "{} bytes",
        log.len()
    );
    let mut whole = TlogRecords::new(&log);
    let expected: Vec<(u64, f32)> = whole.by_ref().map(|(t, f)| (t, xacc(&f))).collect();
    for step in [1 << 20, 4093] {
        let mut stream = TlogStream::new(Trickle { bytes: &log, step });
        let got: Vec<(u64, f32)> = stream.by_ref().map(|(t, f)| (t, xacc(&f))).collect();
        assert_eq!(got.len(), expected.len());
        assert!(got == expected, "records differ at step {step}");
        assert_eq!(stream.stats, whole.stats, "step {step}");
        assert_eq!(stream.bytes_read(), log.len());
    }
    assert!(whole.stats.skipped["resync"] > 100, "{:?}", whole.stats);
    assert!(whole.stats.skipped["bad_crc"] > 100, "{:?}", whole.stats);
    assert_eq!(whole.stats.skipped["truncated"], 1);
}

/// The x acceleration of a HIGHRES_IMU frame, NaN for another.
fn xacc(f: &Frame) -> f32 {
    match &f.message {
        MavMessage::HIGHRES_IMU(m) => m.xacc,
        _ => f32::NAN,
    }
}

#[test]
fn csv_any_order_subset_and_empty_cells() {
    let text =
        "mz,t,mx,my,ax,ay,az\n3,0.0,1,2,,,\n6,0.1,4,5,0,0,-9.8\nbad,row\n9,0.2,7,8,0,NaN,1\n";
    let mut st = DecodeStats::default();
    let s = decode_csv(text, &CsvMapping::default(), &mut st).unwrap();
    assert_eq!(s.len(), 3);
    assert_eq!(s[0].mag_ut, Some([1.0, 2.0, 3.0]));
    assert_eq!(s[0].accel_mps2, None);
    assert_eq!(s[1].accel_mps2, Some([0.0, 0.0, -9.8]));
    assert_eq!(s[2].accel_mps2, None);
    assert_eq!(st.skipped.get("bad_row"), Some(&1));
    assert_eq!(st.skipped.get("non_finite"), Some(&1));
}

#[test]
fn csv_without_time_takes_the_rate_given_or_its_preamble_or_says_what_to_give() {
    let body = "mx,my,mz\n1,2,3\n4,5,6\nbad\n7,8,9\n";
    let mut st = DecodeStats::default();
    let e = decode_csv(body, &CsvMapping::default(), &mut st).unwrap_err();
    assert!(e.contains("--rate-hz") && e.contains("rate_hz"), "{e}");
    let with_preamble = format!("Fs,50.00\nInitialization time,60\n{body}");
    let s = decode_csv(&with_preamble, &CsvMapping::default(), &mut st).unwrap();
    let t: Vec<f64> = s.iter().map(|s| s.t_s).collect();
    // The bad row keeps its place in time.
    assert_eq!(t, vec![0.0, 0.02, 0.06]);
    let m = CsvMapping {
        rate_hz: Some(10.0),
        ..Default::default()
    };
    let s = decode_csv(&with_preamble, &m, &mut st).unwrap();
    assert!((s[1].t_s - 0.1).abs() < 1e-12);
    let m = CsvMapping {
        rate_hz: Some(0.0),
        ..Default::default()
    };
    assert!(decode_csv(body, &m, &mut st)
        .unwrap_err()
        .contains("positive"));
}

#[test]
fn csv_user_mapping_with_scales() {
    let text = "time_ms,AccX,AccY,AccZ\n10,0,0,-1\n";
    let mut m = CsvMapping::from_pairs(
        &[
            ("t", "time_ms"),
            ("ax", "AccX"),
            ("ay", "AccY"),
            ("az", "AccZ"),
        ],
        &[
            ("t", 0.001),
            ("ax", 9.80665),
            ("ay", 9.80665),
            ("az", 9.80665),
        ],
    );
    let mut st = DecodeStats::default();
    let s = decode_csv(text, &m, &mut st).unwrap();
    assert!((s[0].t_s - 0.01).abs() < 1e-12);
    assert_eq!(s[0].accel_mps2, Some([0.0, 0.0, -9.80665]));
    m.columns.insert("mx".into(), "Nope".into());
    assert!(decode_csv(text, &m, &mut st).unwrap_err().contains("Nope"));
}
