//! The links' tests: addresses, text lines, framing, every transport against real sockets,
//! replays and their pacing.

use super::udp::*;
use super::*;
use crate::types::STANDARD_GRAVITY_MPS2;
use mavlink::dialects::ardupilotmega as apm;
use mavlink::MavlinkVersion;
use std::sync::atomic::Ordering::Relaxed;

const WAIT: Duration = Duration::from_secs(5);

fn frame_bytes(msg: &apm::MavMessage, v: MavlinkVersion) -> Vec<u8> {
    let mut out = Vec::new();
    let h = mavlink::MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: 0,
    };
    mavlink::write_versioned_msg(&mut out, v, h, msg).expect("encode");
    out
}

fn imu(x: f32) -> apm::MavMessage {
    apm::MavMessage::HIGHRES_IMU(apm::HIGHRES_IMU_DATA {
        time_usec: 1000,
        xacc: x,
        zacc: -9.8,
        xmag: 0.2,
        zmag: 0.4,
        ..Default::default()
    })
}

fn heartbeat() -> apm::MavMessage {
    apm::MavMessage::HEARTBEAT(apm::HEARTBEAT_DATA::default())
}

fn fast_opts() -> LinkOptions {
    LinkOptions {
        silent_after_s: 0.0,
        backoff_min_s: 0.05,
        backoff_max_s: 0.2,
        ..LinkOptions::default()
    }
}

struct Rig {
    rx: InboundRx,
    /// Frames of an item taken, not yet looked at.
    pending: std::collections::VecDeque<TimedFrame>,
    stop: watch::Sender<bool>,
    handle: LinkHandle,
}

fn start(addr: Address, payload: Payload, opts: LinkOptions, capacity: usize) -> Rig {
    let (tx, rx) = inbound_queue(capacity);
    let (stop, stop_rx) = watch::channel(false);
    let handle = spawn_link(7, addr, payload, tx, stop_rx, opts);
    Rig {
        rx,
        pending: Default::default(),
        stop,
        handle,
    }
}

impl Rig {
    /// The next item (its room in the queue given back at once).
    async fn next(&mut self) -> Inbound {
        match tokio::time::timeout(WAIT, self.rx.recv()).await {
            Ok(Some(q)) => q.into_parts().0,
            Ok(None) => panic!("inbound channel closed"),
            Err(_) => panic!("nothing from the link within {WAIT:?}"),
        }
    }

    /// The next status, skipping data items (and the frames not looked at yet).
    async fn status(&mut self) -> LinkStatus {
        self.pending.clear();
        loop {
            if let Inbound::Status { link, status } = self.next().await {
                assert_eq!(link, 7);
                return status;
            }
        }
    }

    /// The next frame, from the item taken last or the next one.
    async fn frame(&mut self) -> (Frame, u64) {
        if self.pending.is_empty() {
            match self.next().await {
                Inbound::Frames { link, frames } => {
                    assert_eq!(link, 7);
                    assert!(!frames.is_empty(), "an empty batch was queued");
                    self.pending.extend(frames);
                }
                other => panic!("expected frames, got {other:?}"),
            }
        }
        let f = self.pending.pop_front().expect("a frame");
        (f.frame, f.time_us)
    }

    /// Stop the link and check that its task ends promptly and without a panic.
    async fn stop(self) {
        self.stop.send(true).expect("stop");
        let t0 = std::time::Instant::now();
        let r = tokio::time::timeout(Duration::from_millis(500), self.handle.task).await;
        let joined = r.expect("link task did not stop within 500 ms");
        joined.expect("link task panicked");
        assert!(t0.elapsed() < Duration::from_millis(500));
    }
}

fn free_udp_port() -> u16 {
    let s = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    s.local_addr().expect("addr").port()
}

/// Waits until `done` holds: a counter the link task moves, looked at every 5 ms (an atomic
/// counter has no event to wait on). Fails after [`WAIT`].
async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let t0 = std::time::Instant::now();
    while !done() {
        assert!(t0.elapsed() < WAIT, "not within {WAIT:?}: {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// How the link's first opening went, once it is known.
async fn opening(rig: &mut Rig) -> LinkOpening {
    let o = tokio::time::timeout(WAIT, rig.handle.opening.wait_for(Option::is_some))
        .await
        .expect("opened or failed within WAIT")
        .expect("told before the link stopped");
    o.clone().expect("some")
}

// --- addresses -----------------------------------------------------------------------------

#[test]
fn address_parse_round_trips() {
    let forms = [
        "udpin:127.0.0.1:14550",
        "udpout:127.0.0.1:14551",
        "udpin:[::1]:14550",
        "tcpout:localhost:5760",
        "tcpout:10.0.0.2:5762",
        "tcpin:127.0.0.1:5760",
        "serial:/dev/ttyUSB0:115200",
        "serial:COM3:57600",
        "file:logs/flight.tlog",
        "file:log.tlog?speed=10",
        "file:log.csv.gz?speed=0",
        "file:log.tlog?speed=0.5",
        "sim:tumble",
        "sim:tumble?seed=3&speed=5",
        "sim:flight?speed=0",
        "sim:turntable?seed=42",
        "sim:scenarios/my.toml?seed=9",
    ];
    for f in forms {
        let a = Address::parse(f).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert_eq!(a.to_string(), f, "display of {a:?}");
        assert_eq!(Address::parse(&a.to_string()).unwrap(), a);
    }
    assert_eq!(
        Address::parse("serial:/dev/ttyUSB0:115200").unwrap(),
        Address::Serial {
            path: "/dev/ttyUSB0".into(),
            baud: 115200
        }
    );
    assert_eq!(
        Address::parse("sim:tumble?seed=3&speed=5").unwrap(),
        Address::Sim {
            scenario: "tumble".into(),
            seed: 3,
            speed: 5.0
        }
    );
    // Defaults: speed 1, seed 1; a default written out reads back the same.
    assert_eq!(
        Address::parse("file:a.tlog?speed=1").unwrap(),
        Address::File {
            path: "a.tlog".into(),
            speed: 1.0
        }
    );
    assert_eq!(
        Address::parse("sim:tumble?seed=1").unwrap().to_string(),
        "sim:tumble"
    );
    assert!(Address::parse("sim:tumble").unwrap().is_replay());
    assert!(!Address::parse("udpin:127.0.0.1:1").unwrap().is_replay());
}

#[test]
fn address_parse_rejects_bad_forms_helpfully() {
    let cases = [
        ("", "no scheme"),
        ("/dev/ttyUSB0", "no scheme"),
        ("udp:127.0.0.1:14550", "unknown scheme"),
        ("udpin:localhost:14550", "IP address and port"),
        ("udpin:127.0.0.1", "IP address and port"),
        ("udpout:127.0.0.1:99999", "IP address and port"),
        ("tcpout:host", "HOST:PORT"),
        ("tcpout::5760", "HOST:PORT"),
        ("tcpout:host:0", "HOST:PORT"),
        ("serial:/dev/ttyUSB0", "baud rate"),
        ("serial:/dev/ttyUSB0:fast", "baud rate"),
        ("serial::115200", "baud rate"),
        ("file:", "needs a path"),
        ("file:a.tlog?speed=-1", "speed"),
        ("file:a.tlog?speed=fast", "speed"),
        ("file:a.tlog?rate=2", "unknown option `rate`"),
        ("file:a.tlog?speed", "needs a value"),
        ("sim:nope", "tumble"),
        ("sim:", "scenario name"),
        ("sim:tumble?seed=-3", "seed"),
    ];
    for (s, want) in cases {
        match Address::parse(s) {
            Ok(a) => panic!("`{s}` parsed as {a:?}"),
            Err(Error::Config { key, message }) => {
                assert_eq!(key, "source");
                assert!(message.contains(want), "`{s}`: {message}");
                assert!(message.contains("udpin:IP:PORT"), "forms listed: {message}");
            }
            Err(e) => panic!("`{s}`: wrong error kind {e:?}"),
        }
    }
}

// --- text lines ----------------------------------------------------------------------------

#[test]
fn motioncal_raw_line_in_si_units() {
    let s = parse_motioncal_line("Raw:8192,-4096,0,16,-32,160,100,-25,0", 1.5).expect("raw line");
    assert_eq!(s.t_s, 1.5);
    let a = s.accel_mps2.unwrap();
    assert!((a[0] - 9.80665).abs() < 1e-12 && (a[1] + 4.903325).abs() < 1e-12 && a[2] == 0.0);
    let g = s.gyro_rad_s.unwrap();
    assert!((g[0] - 1f64.to_radians()).abs() < 1e-12);
    assert!((g[1] + 2f64.to_radians()).abs() < 1e-12);
    assert!((g[2] - 10f64.to_radians()).abs() < 1e-12);
    assert_eq!(s.mag_ut, Some([10.0, -2.5, 0.0]));
    // Whitespace and CR around the numbers are tolerated.
    assert!(parse_motioncal_line(" Raw: 1, 2,3,4,5,6,7,8,9\r", 0.0).is_some());
}

#[test]
fn motioncal_other_lines_are_rejected() {
    for bad in [
        "Uni:0.01,0.02,9.81,0,0,0,12.5,3.0,-40.1",
        "Cal1:0,0,0,0,0,0,0,0,0,0",
        "Raw:1,2,3,4,5,6,7,8",
        "Raw:1,2,3,4,5,6,7,8,9,10",
        "Raw:1,2,3,4,5,6,7,8,x",
        "Raw:1,2,3,4,5,6,7,8,40000",
        "Raw:1.5,2,3,4,5,6,7,8,9",
        "Raw:",
        "garbage \u{fffd}\u{fffd}",
        "",
    ] {
        assert!(parse_motioncal_line(bad, 0.0).is_none(), "{bad:?}");
    }
}

#[test]
fn line_buffer_joins_partial_lines_and_strips_crlf() {
    let mut b = LineBuffer::new();
    let (l, d) = b.push(b"Raw:1,2,");
    assert!(l.is_empty() && d == 0);
    let (l, _) = b.push(b"3\r\nUni:9\r");
    assert_eq!(l, vec!["Raw:1,2,3".to_string()]);
    let (l, _) = b.push(b"\nA\nB\r\n\r\nC");
    assert_eq!(l, vec!["Uni:9", "A", "B", ""]);
    assert_eq!(b.take_partial().as_deref(), Some("C"));
    assert_eq!(b.take_partial(), None);
    // An over-long line is dropped once, up to its newline; the next line is intact.
    let long = vec![b'x'; MAX_LINE + 10];
    let (l, d) = b.push(&long);
    assert!(l.is_empty());
    assert_eq!(d, 1);
    let (l, d) = b.push(b"yyy\nok\n");
    assert_eq!((l, d), (vec!["ok".to_string()], 0));
    // Also when its start fitted in an earlier read, and when one read holds all of it.
    let (l, d) = b.push(&long[..MAX_LINE - 5]);
    assert!(l.is_empty() && d == 0);
    let (l, d) = b.push(b"123456\nok\n");
    assert_eq!((l, d), (vec!["ok".to_string()], 1));
    let mut one = long.clone();
    one.extend(b"\nok\n");
    assert_eq!(b.push(&one), (vec!["ok".to_string()], 1));
    // A line of exactly MAX_LINE bytes is kept.
    let mut max = vec![b'z'; MAX_LINE];
    max.push(b'\n');
    assert_eq!(b.push(&max).0[0].len(), MAX_LINE);
}

#[test]
fn csv_lines_in_field_order_with_scales() {
    let fields: Vec<String> = ["t", "ax", "ay", "az", "_", "mx", "my", "mz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let mut scales = BTreeMap::new();
    scales.insert("t".to_string(), 0.001);
    scales.insert("az".to_string(), STANDARD_GRAVITY_MPS2);
    let p = CsvLineParser::new(&fields, &scales);
    let s = p.parse("1500,0,0,-1,99,10,20,30", 7.0).unwrap();
    assert_eq!(s.t_s, 1.5);
    assert_eq!(s.accel_mps2, Some([0.0, 0.0, -STANDARD_GRAVITY_MPS2]));
    assert_eq!(s.mag_ut, Some([10.0, 20.0, 30.0]));
    assert_eq!(s.gyro_rad_s, None);
    // Empty cells: no reading of that sensor.
    let s = p.parse("1600,,,,0,10,20,30", 7.0).unwrap();
    assert_eq!(s.accel_mps2, None);
    assert!(p.parse("t,ax,ay,az,_,mx,my,mz", 0.0).is_none(), "header");
    assert!(p.parse("1,2,3", 0.0).is_none(), "too few cells");
    assert!(
        p.parse("1,2,3,4,5,6,7,8,9", 0.0).is_none(),
        "too many cells"
    );
    assert!(p.parse("1700,,,,,,,", 0.0).is_none(), "no sensor data");
    // No t field: the arrival time.
    let p = CsvLineParser::new(&fields[1..4], &BTreeMap::new());
    assert_eq!(p.parse("0,0,9.8", 2.25).unwrap().t_s, 2.25);

    let ok = Payload::Csv {
        fields: fields.clone(),
        scales: scales.clone(),
    };
    ok.check().unwrap();
    let bad = Payload::Csv {
        fields: vec!["t".into(), "accx".into()],
        scales: BTreeMap::new(),
    };
    assert!(bad.check().unwrap_err().to_string().contains("accx"));
}

#[test]
fn datagram_decoder_counts_garbage_runs_and_truncation() {
    let mut d = frame_bytes(&imu(1.0), MavlinkVersion::V2);
    d.extend(b"junk junk");
    d.extend(frame_bytes(&heartbeat(), MavlinkVersion::V1));
    let whole = frame_bytes(&imu(2.0), MavlinkVersion::V2);
    d.extend(&whole[..whole.len() - 3]);
    let mut st = DecodeStats::default();
    let mut frames = vec![];
    let n = decode_datagram(&d, &mut st, |f| frames.push(f));
    assert_eq!((n, frames.len()), (2, 2));
    assert_eq!(st.skipped.get("resync"), Some(&1));
    assert_eq!(st.skipped.get("truncated"), Some(&1));
}

// --- udp -----------------------------------------------------------------------------------

#[test]
fn poll_thresholds_scale_with_the_buffer_the_kernel_granted() {
    // Linux's default buffer (212992 bytes) holds 256 small datagrams: 96 and 40.
    assert_eq!(poll_thresholds(212_992), (96, 40));
    // Not known, or smaller: as the default.
    assert_eq!(poll_thresholds(0), (96, 40));
    // The 1 MiB asked for reads back as 2 MiB, 2520 datagrams: 945 and 393.
    assert_eq!(poll_thresholds(2 << 20), (945, 393));
}

#[tokio::test]
async fn udpin_polled_takes_a_burst_replies_reports_silence_and_stops() {
    // `udp_poll_s`: the socket is read every 20 ms; a burst of 50 datagrams sent between two
    // reads all arrive, in order; the reply goes to the sender; silence is reported once.
    let port = free_udp_port();
    let addr = Address::parse(&format!("udpin:127.0.0.1:{port}")).unwrap();
    let opts = LinkOptions {
        udp_poll_s: 0.02,
        silent_after_s: 0.3,
        ..fast_opts()
    };
    let mut rig = start(addr, Payload::Mavlink, opts, 256);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    for i in 0..50 {
        let d = frame_bytes(&imu(i as f32), MavlinkVersion::V2);
        client.send_to(&d, ("127.0.0.1", port)).await.unwrap();
    }
    for i in 0..50 {
        match rig.frame().await.0.message {
            apm::MavMessage::HIGHRES_IMU(a) => assert_eq!(a.xacc, i as f32),
            other => panic!("{other:?}"),
        }
    }
    let reply = frame_bytes(&heartbeat(), MavlinkVersion::V2);
    rig.handle.outbound.send(reply.clone()).await.unwrap();
    let mut buf = [0u8; 512];
    let (n, _) = tokio::time::timeout(WAIT, client.recv_from(&mut buf))
        .await
        .expect("reply within 5 s")
        .unwrap();
    assert_eq!(&buf[..n], &reply[..]);
    match rig.status().await {
        LinkStatus::Silent { for_s } => assert!(for_s >= 0.29, "{for_s}"),
        s => panic!("{s:?}"),
    }
    rig.stop().await;
}

/// The first opening is told once, before the first status: the bound address of a link asked
/// for port 0, the failure of one that cannot open (and not again on its retries), no local
/// address for a replay.
#[tokio::test]
async fn link_opening_tells_the_bound_port_or_the_failure() {
    let mut udp = start(
        Address::parse("udpin:127.0.0.1:0").unwrap(),
        Payload::Mavlink,
        fast_opts(),
        64,
    );
    let local = match opening(&mut udp).await {
        LinkOpening::Open { local: Some(a), .. } => a,
        other => panic!("{other:?}"),
    };
    assert!(local.ip().is_loopback() && local.port() != 0, "{local}");
    match udp.status().await {
        LinkStatus::Connected(s) => assert!(s.contains(&local.to_string()), "{s}"),
        s => panic!("{s:?}"),
    }
    // It listens there: a datagram sent to the told port arrives.
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    client
        .send_to(&frame_bytes(&imu(5.0), MavlinkVersion::V2), local)
        .await
        .unwrap();
    assert!(matches!(
        udp.frame().await.0.message,
        apm::MavMessage::HIGHRES_IMU(_)
    ));
    udp.stop().await;

    let refused = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap()
    };
    let mut tcp = start(
        Address::TcpOut(refused.to_string()),
        Payload::Mavlink,
        fast_opts(),
        64,
    );
    match opening(&mut tcp).await {
        LinkOpening::Failed { detail } => {
            assert!(detail.contains("cannot connect"), "{detail}")
        }
        other => panic!("{other:?}"),
    }
    let c = tcp.handle.counters.clone();
    until("a retry", || c.reconnects.load(Relaxed) >= 1).await;
    assert!(!tcp.handle.opening.has_changed().unwrap(), "told once");
    tcp.stop().await;

    let mut sim = start(
        Address::parse("sim:turntable?speed=0").unwrap(),
        Payload::Mavlink,
        fast_opts(),
        64,
    );
    match opening(&mut sim).await {
        LinkOpening::Open {
            local: None,
            detail,
        } => {
            assert!(detail.contains("turntable"), "{detail}")
        }
        other => panic!("{other:?}"),
    }
    sim.stop().await;
}

#[tokio::test]
async fn udpin_frames_v1_v2_garbage_counted_and_reply_to_sender() {
    let port = free_udp_port();
    let addr = Address::parse(&format!("udpin:127.0.0.1:{port}")).unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 64);
    match rig.status().await {
        LinkStatus::Connected(s) => assert!(s.contains(&port.to_string()), "{s}"),
        s => panic!("{s:?}"),
    }
    // Before any datagram there is no peer: outbound is dropped and counted.
    rig.handle.outbound.send(b"early".to_vec()).await.unwrap();

    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut dgram = frame_bytes(&imu(1.0), MavlinkVersion::V2);
    dgram.extend(b"\x00garbage\x01\x02");
    dgram.extend(frame_bytes(&imu(2.0), MavlinkVersion::V1));
    client.send_to(&dgram, ("127.0.0.1", port)).await.unwrap();

    let (f1, t1) = rig.frame().await;
    let (f2, _) = rig.frame().await;
    assert_eq!(f1.version, MavlinkVersion::V2);
    assert_eq!(f2.version, MavlinkVersion::V1);
    match (&f1.message, &f2.message) {
        (apm::MavMessage::HIGHRES_IMU(a), apm::MavMessage::HIGHRES_IMU(b)) => {
            assert_eq!((a.xacc, b.xacc), (1.0, 2.0))
        }
        other => panic!("{other:?}"),
    }
    assert!(t1 > 1_600_000_000_000_000, "arrival time in Unix us: {t1}");
    let c = &rig.handle.counters;
    assert_eq!(c.frames_in.load(Relaxed), 2);
    assert_eq!(c.bytes_in.load(Relaxed), dgram.len() as u64);
    assert_eq!(c.outbound_dropped.load(Relaxed), 1);
    {
        let st = rig.handle.decode_stats.lock().unwrap();
        assert_eq!(st.skipped.get("resync"), Some(&1), "{st:?}");
        assert_eq!(st.records, 2);
    }

    // Outbound now goes back to the sender's socket.
    let reply = frame_bytes(&heartbeat(), MavlinkVersion::V2);
    rig.handle.outbound.send(reply.clone()).await.unwrap();
    let mut buf = [0u8; 512];
    let (n, from) = tokio::time::timeout(WAIT, client.recv_from(&mut buf))
        .await
        .expect("reply within 5 s")
        .unwrap();
    assert_eq!(&buf[..n], &reply[..]);
    assert_eq!(from.port(), port);
    rig.stop().await;
}

#[tokio::test]
async fn udp_full_inbound_drops_and_counts_without_blocking() {
    let port = free_udp_port();
    let addr = Address::UdpIn(format!("127.0.0.1:{port}").parse().unwrap());
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 2);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let mut dgram = Vec::new();
    for i in 0..5 {
        dgram.extend(frame_bytes(&imu(i as f32), MavlinkVersion::V2));
    }
    let c = rig.handle.counters.clone();
    for round in 1..=2u64 {
        client.send_to(&dgram, ("127.0.0.1", port)).await.unwrap();
        until("the reader takes both datagrams", || {
            c.frames_in.load(Relaxed) >= 5 * round
        })
        .await;
    }
    // 2 fit in the channel; the other 8 were dropped, and the reader went on.
    assert_eq!(c.inbound_dropped.load(Relaxed), 8);
    rig.stop().await;
}

#[tokio::test]
async fn frames_of_one_read_go_as_one_item_and_a_full_queue_drops_whole_items() {
    // Room for 4 frames: a datagram of 5 is queued as an item of 4 (the most an item holds in such
    // a queue) and one of 1, which finds no room while the first is not handled: dropped, counted.
    let port = free_udp_port();
    let addr = Address::UdpIn(format!("127.0.0.1:{port}").parse().unwrap());
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 4);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let dgram: Vec<u8> = (0..5)
        .flat_map(|i| frame_bytes(&imu(i as f32), MavlinkVersion::V2))
        .collect();
    client.send_to(&dgram, ("127.0.0.1", port)).await.unwrap();
    let c = rig.handle.counters.clone();
    until("the reader takes the datagram", || {
        c.frames_in.load(Relaxed) >= 5
    })
    .await;
    match rig.next().await {
        Inbound::Frames { frames, .. } => {
            let xs: Vec<f32> = frames
                .iter()
                .map(|f| match &f.frame.message {
                    apm::MavMessage::HIGHRES_IMU(d) => d.xacc,
                    other => panic!("{other:?}"),
                })
                .collect();
            assert_eq!(xs, [0.0, 1.0, 2.0, 3.0]);
            assert!(frames.iter().all(|f| f.time_us == frames[0].time_us));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(c.inbound_dropped.load(Relaxed), 1);
    // The queue is empty again: the next datagram comes whole, as one item.
    client
        .send_to(&dgram[..dgram.len() / 5 * 2], ("127.0.0.1", port))
        .await
        .unwrap();
    match rig.next().await {
        Inbound::Frames { frames, .. } => assert_eq!(frames.len(), 2),
        other => panic!("{other:?}"),
    }
    rig.stop().await;
}

#[tokio::test]
async fn udpout_sends_to_target_and_reports_silence_once_per_gap() {
    let peer = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let target = peer.local_addr().unwrap();
    let opts = LinkOptions {
        silent_after_s: 0.2,
        ..fast_opts()
    };
    let mut rig = start(Address::UdpOut(target), Payload::Mavlink, opts, 64);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    rig.handle.outbound.send(b"hello".to_vec()).await.unwrap();
    let mut buf = [0u8; 64];
    let (n, from) = tokio::time::timeout(WAIT, peer.recv_from(&mut buf))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(&buf[..n], b"hello");
    match rig.status().await {
        LinkStatus::Silent { for_s } => assert!(for_s >= 0.19, "{for_s}"),
        s => panic!("{s:?}"),
    }
    // Still silent: no second report until bytes arrive.
    assert!(
        tokio::time::timeout(Duration::from_millis(400), rig.rx.recv())
            .await
            .is_err()
    );
    peer.send_to(&frame_bytes(&heartbeat(), MavlinkVersion::V2), from)
        .await
        .unwrap();
    rig.frame().await;
    assert!(matches!(rig.status().await, LinkStatus::Silent { .. }));
    rig.stop().await;
}

// --- tcp -----------------------------------------------------------------------------------

#[tokio::test]
async fn tcpout_reconnects_after_the_peer_drops() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let addr = Address::parse(&format!("tcpout:127.0.0.1:{port}")).unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 64);

    let (first, _) = tokio::time::timeout(WAIT, listener.accept())
        .await
        .unwrap()
        .unwrap();
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    drop(first);
    match rig.status().await {
        LinkStatus::Lost(r) => assert!(r.contains("closed"), "{r}"),
        s => panic!("{s:?}"),
    }
    let (mut second, _) = tokio::time::timeout(WAIT, listener.accept())
        .await
        .unwrap()
        .unwrap();
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    assert!(rig.handle.counters.reconnects.load(Relaxed) >= 1);

    // The stream decoder reassembles a frame split across writes.
    let f = frame_bytes(&imu(3.0), MavlinkVersion::V2);
    second.write_all(&f[..7]).await.unwrap();
    second.flush().await.unwrap();
    tokio::time::sleep(Duration::from_millis(20)).await;
    second.write_all(&f[7..]).await.unwrap();
    let (frame, _) = rig.frame().await;
    assert!(matches!(frame.message, apm::MavMessage::HIGHRES_IMU(_)));
    // Outbound reaches the peer.
    rig.handle.outbound.send(b"ping".to_vec()).await.unwrap();
    let mut buf = [0u8; 4];
    tokio::time::timeout(WAIT, second.read_exact(&mut buf))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(&buf, b"ping");
    rig.stop().await;
}

#[tokio::test]
async fn tcpout_refused_is_lost_once_and_outbound_dropped_while_down() {
    // A port with nobody listening.
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let mut rig = start(
        Address::TcpOut(format!("127.0.0.1:{port}")),
        Payload::Mavlink,
        fast_opts(),
        64,
    );
    match rig.status().await {
        LinkStatus::Lost(r) => assert!(r.contains("cannot connect"), "{r}"),
        s => panic!("{s:?}"),
    }
    rig.handle.outbound.send(b"x".to_vec()).await.unwrap();
    let c = rig.handle.counters.clone();
    until("retries with backoff", || c.reconnects.load(Relaxed) >= 2).await;
    assert_eq!(c.outbound_dropped.load(Relaxed), 1);
    // Repeated failures are not reported again.
    assert!(rig.rx.try_recv().is_none());
    rig.stop().await;
}

#[tokio::test]
async fn tcpin_serves_one_client_at_a_time() {
    // Port 0: the listener's opening says which port it got.
    let addr = Address::parse("tcpin:127.0.0.1:0").unwrap();
    let mut rig = start(addr, Payload::MotionCal, fast_opts(), 64);
    let port = match opening(&mut rig).await {
        LinkOpening::Open {
            local: Some(a),
            detail,
        } => {
            assert!(detail.contains(&a.to_string()), "{detail}");
            a.port()
        }
        other => panic!("{other:?}"),
    };
    assert_ne!(port, 0);
    let mut c1 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("client")));
    // A second client is closed at once.
    let mut c2 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    let mut b = [0u8; 1];
    let r = tokio::time::timeout(WAIT, c2.read(&mut b)).await.unwrap();
    assert!(matches!(r, Ok(0) | Err(_)));

    c1.write_all(b"Raw:0,0,8192,0,0,0,0,0,0\n").await.unwrap();
    match rig.next().await {
        Inbound::Sample { sample, .. } => {
            assert!((sample.accel_mps2.unwrap()[2] - 9.80665).abs() < 1e-12)
        }
        other => panic!("{other:?}"),
    }
    drop(c1);
    assert!(matches!(rig.status().await, LinkStatus::Lost(_)));
    let _c3 = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    assert_eq!(rig.handle.counters.reconnects.load(Relaxed), 1);
    rig.stop().await;
}

// --- serial --------------------------------------------------------------------------------

#[tokio::test]
async fn serial_pty_motioncal_samples_then_lost_when_the_other_end_closes() {
    let (mut master, slave) = match tokio_serial::SerialStream::pair() {
        Ok(p) => p,
        Err(e) => {
            eprintln!("skipped: no pseudo-terminal available: {e}");
            return;
        }
    };
    let path = tokio_serial::SerialPort::name(&slave).expect("pty name");
    drop(slave);
    let opts = LinkOptions {
        backoff_min_s: 1.0,
        ..fast_opts()
    };
    let addr = Address::Serial { path, baud: 115200 };
    let mut rig = start(addr, Payload::MotionCal, opts, 64);
    match rig.status().await {
        LinkStatus::Connected(s) => assert!(s.contains("serial"), "{s}"),
        s => panic!("{s:?}"),
    }
    for chunk in [
        &b"Uni:0.00,0.01,9.80,0,0,0,1,2,3\r\nRaw:8192,0,-8192,16,-16,0,100,-100,0\r"[..],
        b"\nRaw:0,0,81",
        b"92,0,0,160,0,0,-500\r\ngarbage\xff\r\n",
    ] {
        master.write_all(chunk).await.unwrap();
        master.flush().await.unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut samples = Vec::new();
    while samples.len() < 2 {
        match rig.next().await {
            Inbound::Sample { sample, .. } => samples.push(sample),
            other => panic!("{other:?}"),
        }
    }
    let g = STANDARD_GRAVITY_MPS2;
    let a = samples[0].accel_mps2.unwrap();
    assert!((a[0] - g).abs() < 1e-12 && a[1] == 0.0 && (a[2] + g).abs() < 1e-12);
    let w = samples[0].gyro_rad_s.unwrap();
    assert!((w[0] - 1f64.to_radians()).abs() < 1e-12 && (w[1] + 1f64.to_radians()).abs() < 1e-12);
    assert_eq!(samples[0].mag_ut, Some([10.0, -10.0, 0.0]));
    assert_eq!(samples[1].mag_ut, Some([0.0, 0.0, -50.0]));
    assert!(samples[1].t_s >= samples[0].t_s && samples[0].t_s >= 0.0);
    let c = rig.handle.counters.clone();
    until("two lines skipped", || c.lines_skipped.load(Relaxed) >= 2).await;
    assert_eq!(c.samples_in.load(Relaxed), 2);

    drop(master);
    match rig.status().await {
        LinkStatus::Lost(r) => assert!(!r.is_empty()),
        s => panic!("{s:?}"),
    }
    assert!(!rig.handle.task.is_finished(), "keeps retrying");
    rig.stop().await;
}

// --- replays -------------------------------------------------------------------------------

fn tlog(records: &[(u64, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    for (ts, f) in records {
        out.extend(ts.to_be_bytes());
        out.extend(f);
    }
    out
}

const T0: u64 = 1_700_000_000_000_000;

#[tokio::test]
async fn file_tlog_at_speed_zero_is_emitted_completely_then_ended() {
    let mut recs = Vec::new();
    for i in 0..6u64 {
        let v = if i % 2 == 0 {
            MavlinkVersion::V2
        } else {
            MavlinkVersion::V1
        };
        let msg = if i == 3 { heartbeat() } else { imu(i as f32) };
        recs.push((T0 + i * 10_000, frame_bytes(&msg, v)));
    }
    let mut bytes = tlog(&recs[..3]);
    bytes.extend(b"noise!");
    bytes.extend(tlog(&recs[3..]));
    bytes.extend(&T0.to_be_bytes()[..5]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("small.tlog");
    std::fs::write(&path, &bytes).unwrap();

    let addr = Address::parse(&format!("file:{}?speed=0", path.display())).unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 2);
    assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("tlog")));
    for i in 0..6u64 {
        let (f, ts) = rig.frame().await;
        assert_eq!(ts, T0 + i * 10_000);
        assert_eq!(f.version == MavlinkVersion::V2, i % 2 == 0);
    }
    assert_eq!(rig.status().await, LinkStatus::Ended);
    let st = rig.handle.decode_stats.lock().unwrap().clone();
    assert_eq!(st.records, 6);
    assert!(st.skipped.contains_key("resync"), "{st:?}");
    assert_eq!(st.skipped.get("truncated"), Some(&1), "{st:?}");
    assert_eq!(rig.handle.counters.inbound_dropped.load(Relaxed), 0);
    tokio::time::timeout(WAIT, rig.handle.task)
        .await
        .unwrap()
        .unwrap();
}

#[tokio::test]
async fn file_tlog_is_paced_by_its_timestamps() {
    // 0.3 s of recording at speed 2: about 0.15 s.
    let recs: Vec<_> = (0..4u64)
        .map(|i| (T0 + i * 100_000, frame_bytes(&imu(0.0), MavlinkVersion::V2)))
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("paced.tlog");
    std::fs::write(&path, tlog(&recs)).unwrap();
    let mut rig = start(
        Address::File { path, speed: 2.0 },
        Payload::Mavlink,
        fast_opts(),
        64,
    );
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let t0 = std::time::Instant::now();
    rig.frame().await;
    for _ in 0..3 {
        rig.frame().await;
    }
    let dt = t0.elapsed().as_secs_f64();
    assert!((0.14..1.5).contains(&dt), "{dt}");
    assert_eq!(rig.status().await, LinkStatus::Ended);
}

#[tokio::test]
async fn file_csv_gz_headerless_with_payload_fields_and_scales() {
    use std::io::Write;
    let text = "0,0,0,-1000,10,20,30\n0.01,0,0,-1000,11,21,31\nbad,row\n0.02,0,0,-1000,12,22,32\n";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("imu.csv.gz");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(text.as_bytes()).unwrap();
    std::fs::write(&path, gz.finish().unwrap()).unwrap();
    let fields = ["t", "ax", "ay", "az", "mx", "my", "mz"]
        .map(String::from)
        .to_vec();
    let mut scales = BTreeMap::new();
    for f in ["ax", "ay", "az"] {
        scales.insert(f.to_string(), STANDARD_GRAVITY_MPS2 / 1000.0);
    }
    let payload = Payload::Csv { fields, scales };
    let mut rig = start(Address::File { path, speed: 0.0 }, payload, fast_opts(), 64);
    assert!(matches!(rig.status().await, LinkStatus::Connected(s) if s.contains("csv")));
    let mut got = Vec::new();
    loop {
        match rig.next().await {
            Inbound::Sample { sample, .. } => got.push(sample),
            Inbound::Status { status, .. } => {
                assert_eq!(status, LinkStatus::Ended);
                break;
            }
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(got.len(), 3);
    assert_eq!(got[2].t_s, 0.02);
    assert!((got[0].accel_mps2.unwrap()[2] + STANDARD_GRAVITY_MPS2).abs() < 1e-12);
    assert_eq!(got[1].mag_ut, Some([11.0, 21.0, 31.0]));
    let st = rig.handle.decode_stats.lock().unwrap().clone();
    assert_eq!(st.skipped.get("bad_row"), Some(&1));
}

#[tokio::test]
async fn file_missing_is_lost_then_ended() {
    let addr = Address::parse("file:/nonexistent/dir/x.tlog?speed=0").unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 8);
    match rig.status().await {
        LinkStatus::Lost(r) => assert!(r.contains("cannot read"), "{r}"),
        s => panic!("{s:?}"),
    }
    assert_eq!(rig.status().await, LinkStatus::Ended);
}

#[tokio::test]
async fn sim_at_speed_zero_emits_every_sample_then_ended() {
    let want = crate::sim::simulate(&crate::sim::Scenario::named("tumble").unwrap(), 3).samples;
    let addr = Address::parse("sim:tumble?seed=3&speed=0").unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 256);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let mut n = 0;
    loop {
        match rig.next().await {
            Inbound::Sample { sample, .. } => {
                assert_eq!(sample, want[n]);
                n += 1;
            }
            Inbound::Status { status, .. } => {
                assert_eq!(status, LinkStatus::Ended);
                break;
            }
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(n, want.len());
    assert_eq!(rig.handle.counters.samples_in.load(Relaxed), n as u64);
}

#[tokio::test]
async fn sim_paced_stops_promptly_on_shutdown() {
    let mut rig = start(
        Address::parse("sim:tumble").unwrap(),
        Payload::Mavlink,
        fast_opts(),
        256,
    );
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let t0 = std::time::Instant::now();
    for _ in 0..10 {
        assert!(matches!(rig.next().await, Inbound::Sample { .. }));
    }
    // 10 samples at 100 Hz, recorded pace: about 0.09 s.
    assert!(
        t0.elapsed() > Duration::from_millis(60),
        "{:?}",
        t0.elapsed()
    );
    rig.stop().await;
}

#[tokio::test]
async fn sim_scenario_file_and_bad_scenario() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("short.toml");
    std::fs::write(&path, "name = \"tumble\"\nduration_s = 2.0\n").unwrap();
    let addr = Address::parse(&format!("sim:{}?speed=0", path.display())).unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 1024);
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let mut n = 0;
    while let Inbound::Sample { .. } = rig.next().await {
        n += 1;
    }
    assert!(n > 0);
    let addr = Address::parse("sim:/nonexistent/x.toml").unwrap();
    let mut rig = start(addr, Payload::Mavlink, fast_opts(), 8);
    assert!(matches!(rig.status().await, LinkStatus::Lost(_)));
    assert_eq!(rig.status().await, LinkStatus::Ended);
}

#[tokio::test]
async fn live_links_stop_promptly() {
    let port = free_udp_port();
    let mut rig = start(
        Address::UdpIn(format!("127.0.0.1:{port}").parse().unwrap()),
        Payload::Mavlink,
        fast_opts(),
        8,
    );
    assert!(matches!(rig.status().await, LinkStatus::Connected(_)));
    let t0 = std::time::Instant::now();
    rig.stop.send(true).unwrap();
    tokio::time::timeout(Duration::from_millis(100), &mut rig.handle.task)
        .await
        .expect("stopped within 100 ms")
        .unwrap();
    assert!(t0.elapsed() < Duration::from_millis(100));
    // Already stopped before it started: returns at once.
    let (tx, _rx) = inbound_queue(1);
    let (_s, stop_rx) = watch::channel(true);
    let h = spawn_link(
        0,
        Address::parse("sim:tumble").unwrap(),
        Payload::Mavlink,
        tx,
        stop_rx,
        LinkOptions::default(),
    );
    tokio::time::timeout(Duration::from_millis(100), h.task)
        .await
        .unwrap()
        .unwrap();
}
