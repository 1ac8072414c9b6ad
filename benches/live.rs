//! `cargo bench --bench live`: the live daemon (`imucald run`, a separate process) fed HIGHRES_IMU
//! frames over loopback UDP by this process. Figures, not assertions:
//!
//! 1. **CPU at 1 kHz**: frames paced at 1 kHz in real time for `IMUCALD_BENCH_CPU_S` seconds
//!    (default 60); the daemon's CPU time (utime + stime from /proc) over that time, as % of one core.
//! 2. **Memory**: `IMUCALD_BENCH_MINUTES` (default 60) minutes of a 1 kHz simulated stream, sent
//!    time-compressed at `IMUCALD_BENCH_RATE` frames/s (default 40000); the daemon's VmRSS after each
//!    simulated minute: first, max, last, and the growth from minute 5 to the end.
//! 3. **Load**: 10 kHz of frames for `IMUCALD_BENCH_LOAD_S` seconds (default 60): frames sent, samples
//!    the daemon took in, drops it counted at its bounded queue, and the kernel's UDP receive-buffer
//!    errors over the same time (/proc/net/snmp), so a loss is either counted or the kernel's.
//!
//! 4. **Latency**: sample-in to fused-attitude-out round trip at 1 kHz for `IMUCALD_BENCH_LATENCY_S`
//!    seconds (default 30), with `daemon.attitude_every_samples = 1`: p50/p90/p99/p99.9/max.
//!
//! 6. **Three IMUs** (`IMUCALD_BENCH_ONLY=imus`): CPU and memory of a vehicle with one IMU
//!    against one with three (HIGHRES_IMU ids 0-2 with their compasses, each at 1 kHz), in
//!    alternating runs of `IMUCALD_BENCH_IMUS_S` seconds (default 30), `IMUCALD_BENCH_IMUS_ROUNDS`
//!    rounds (default 2).
//! 5. **Live page cost** (`IMUCALD_BENCH_ONLY=ui`): CPU at 1 kHz as in 1., in alternating runs of
//!    `IMUCALD_BENCH_UI_S` seconds (default 30), `IMUCALD_BENCH_UI_ROUNDS` rounds (default 3): no
//!    page served, the page served with no one connected, and one page connected (an event-stream
//!    client reading every line, as the browser does); and the page's transfer size (the page,
//!    the snapshot, the stream's first message).
//!
//! Linux only (reads /proc). Samples come from the simulator (tumble with pauses, 1 kHz), one new
//! seed per simulated minute, generated while streaming so this process holds one minute at a time.

#![allow(dead_code)]

use imucald::io::mavout::MavEncoder;
use imucald::io::samplelog::highres_imu;
use imucald::sim::{simulate, Scenario};
use std::io::{BufRead, BufReader};
use std::net::UdpSocket;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn env_f64(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// One simulated minute of a 1 kHz tumble, starting at `minute * 60` s.
fn minute(minute: u64) -> Vec<imucald::types::Sample> {
    let mut sc = Scenario::named("tumble").unwrap();
    sc.truth.rate_hz = 1000.0;
    sc.duration_s = Some(60.0);
    let mut s = simulate(&sc, 1000 + minute).samples;
    let t0 = minute as f64 * 60.0;
    for x in s.iter_mut() {
        x.t_s += t0;
    }
    s
}

/// Two TOML snippets as one document: the `[daemon]` keys of `extra` join those of `base`.
fn merge_toml(base: &str, extra: &str) -> String {
    let mut doc: toml::Table = base.parse().expect("bench TOML");
    let more: toml::Table = extra.parse().expect("IMUCALD_BENCH_TOML is not valid TOML");
    for (k, v) in more {
        match (doc.get_mut(&k), v) {
            (Some(toml::Value::Table(t)), toml::Value::Table(m)) => t.extend(m),
            (_, v) => {
                doc.insert(k, v);
            }
        }
    }
    toml::to_string(&doc).expect("TOML")
}

struct Daemon {
    child: Child,
    port: u16,
    /// Lines received on the JSON consumer socket.
    lines: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl Daemon {
    fn start() -> Daemon {
        Daemon::start_with("")
    }

    /// Start with extra TOML (written to a temp file and passed with --config).
    fn start_with(toml: &str) -> Daemon {
        let port = free_udp_port();
        let consumer = UdpSocket::bind("127.0.0.1:0").unwrap();
        let cport = consumer.local_addr().unwrap().port();
        let lines = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let l2 = lines.clone();
        std::thread::spawn(move || {
            let mut buf = [0u8; 65536];
            while let Ok(n) = consumer.recv(&mut buf) {
                let k = buf[..n].iter().filter(|&&b| b == b'\n').count().max(1);
                l2.fetch_add(k as u64, std::sync::atomic::Ordering::Relaxed);
            }
        });
        let cfg = std::env::temp_dir().join(format!("imucald-bench-{port}.toml"));
        // IMUCALD_BENCH_TOML adds settings to every daemon the bench starts (e.g. to compare
        // `daemon.udp_poll_ms` values); a table given both ways is merged by TOML rules or refused.
        let extra = std::env::var("IMUCALD_BENCH_TOML").unwrap_or_default();
        // A calibration directory of its own: a daemon never resumes from another run's
        // calibration (nor writes into the working directory).
        let cal_dir = std::env::temp_dir().join(format!("imucald-bench-{port}-cal"));
        let _ = std::fs::remove_dir_all(&cal_dir);
        let own = format!(
            "[daemon]\ncalibration_dir = {:?}\n",
            cal_dir.display().to_string()
        );
        let toml = merge_toml(toml, &own);
        std::fs::write(&cfg, merge_toml(&toml, &extra)).expect("bench config");
        // IMUCALD_BENCH_BIN: another build of imucald to measure (an A/B against this one).
        let bin = std::env::var("IMUCALD_BENCH_BIN")
            .unwrap_or_else(|_| env!("CARGO_BIN_EXE_imucald").to_string());
        let child = Command::new(bin)
            .args([
                "run",
                "--config",
                cfg.to_str().unwrap(),
                "--source",
                &format!("udpin:127.0.0.1:{port}"),
                "--publish",
                &format!("udp:127.0.0.1:{cport}"),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start imucald run");
        std::thread::sleep(Duration::from_millis(500));
        Daemon { child, port, lines }
    }

    fn stat(&self) -> String {
        std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap_or_default()
    }

    /// CPU seconds (user + system) so far: the whole process (all threads, live and exited).
    fn cpu_s(&self) -> f64 {
        parse_cpu_s(&self.stat())
    }

    /// CPU seconds of the main thread alone: the live loop (the daemon runs a current-thread tokio
    /// runtime; fits and file writes go to the blocking pool's other threads).
    fn loop_cpu_s(&self) -> f64 {
        let id = self.child.id();
        parse_cpu_s(
            &std::fs::read_to_string(format!("/proc/{id}/task/{id}/stat")).unwrap_or_default(),
        )
    }
}

/// utime + stime of a /proc stat line, seconds.
fn parse_cpu_s(s: &str) -> f64 {
    // Fields after the ")" that closes the command name; utime and stime are fields 14 and 15.
    let rest = match s.rfind(')') {
        Some(i) => &s[i + 2..],
        None => return f64::NAN,
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = clk_tck();
    let u: f64 = f.get(11).and_then(|x| x.parse().ok()).unwrap_or(f64::NAN);
    let st: f64 = f.get(12).and_then(|x| x.parse().ok()).unwrap_or(f64::NAN);
    (u + st) / ticks
}

impl Daemon {
    /// Resident memory, MB.
    fn rss_mb(&self) -> f64 {
        let s = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .unwrap_or_default();
        s.lines()
            .find(|l| l.starts_with("VmRSS:"))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|k| k.parse::<f64>().ok())
            .map(|kb| kb / 1024.0)
            .unwrap_or(f64::NAN)
    }

    /// SIGTERM, wait, and the daemon's closing line ("N samples, K calibrations accepted, D samples
    /// dropped") as (samples, dropped).
    fn stop(self) -> (u64, u64) {
        let (n, _, d) = self.stop_counts();
        (n, d)
    }

    /// [`Daemon::stop`] as (samples, calibrations accepted, dropped).
    fn stop_counts(mut self) -> (u64, u64, u64) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let stderr = self.child.stderr.take().unwrap();
        let mut last = (0, 0, 0);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.strip_prefix("imucald run: ") {
                let nums: Vec<u64> = rest
                    .split(|c: char| !c.is_ascii_digit())
                    .filter_map(|x| x.parse().ok())
                    .collect();
                if nums.len() >= 3 {
                    last = (nums[0], nums[1], nums[2]);
                }
            }
        }
        let _ = self.child.wait();
        last
    }
}

/// A bench that panics must not leave its daemon running (it would load the next measurements).
impl Drop for Daemon {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn clk_tck() -> f64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8_lossy(&o.stdout).trim().parse().ok())
        .unwrap_or(100.0)
}

/// UDP receive-buffer errors of the whole host so far (/proc/net/snmp `Udp: ... RcvbufErrors`).
fn udp_rcvbuf_errors() -> u64 {
    let s = std::fs::read_to_string("/proc/net/snmp").unwrap_or_default();
    let rows: Vec<&str> = s.lines().filter(|l| l.starts_with("Udp:")).collect();
    if rows.len() < 2 {
        return 0;
    }
    let names: Vec<&str> = rows[0].split_whitespace().collect();
    let vals: Vec<&str> = rows[1].split_whitespace().collect();
    names
        .iter()
        .position(|n| *n == "RcvbufErrors")
        .and_then(|i| vals.get(i))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// Send `samples` as HIGHRES_IMU frames at `rate_hz` (paced against the wall clock).
fn send_paced(
    sock: &UdpSocket,
    enc: &mut MavEncoder,
    samples: &[imucald::types::Sample],
    rate_hz: f64,
) -> u64 {
    send_paced_imus(sock, enc, samples, rate_hz, 1)
}

/// [`send_paced`] for a vehicle with `imus` IMUs (HIGHRES_IMU ids 0 .. imus-1), each sending
/// every sample: `imus` frames per instant, each IMU at `rate_hz`.
fn send_paced_imus(
    sock: &UdpSocket,
    enc: &mut MavEncoder,
    samples: &[imucald::types::Sample],
    rate_hz: f64,
    imus: u8,
) -> u64 {
    let start = Instant::now();
    let mut sent = 0u64;
    for (i, s) in samples.iter().enumerate() {
        let due = Duration::from_secs_f64(i as f64 / rate_hz);
        loop {
            let el = start.elapsed();
            if el >= due {
                break;
            }
            let wait = due - el;
            if wait > Duration::from_micros(300) {
                std::thread::sleep(wait - Duration::from_micros(200));
            } else {
                std::hint::spin_loop();
            }
        }
        for id in 0..imus {
            let mut msg = highres_imu(s, (s.t_s * 1e6) as u64 + 1_000_000);
            if let mavlink::dialects::ardupilotmega::MavMessage::HIGHRES_IMU(h) = &mut msg {
                h.id = id;
            }
            if sock.send(&enc.encode(&msg)).is_ok() {
                sent += 1;
            }
        }
    }
    sent
}

fn cpu_at_1khz(seconds: f64) {
    let d = Daemon::start();
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.connect(("127.0.0.1", d.port)).unwrap();
    let mut enc = MavEncoder::new(1, 1); // a flight controller: (1, 191) is the service itself
    let minutes = (seconds / 60.0).ceil() as u64;
    let mut sent = 0;
    let (mut cpu0, mut loop0, mut t0) = (f64::NAN, f64::NAN, Instant::now());
    for m in 0..minutes {
        let mut s = minute(m);
        let keep = ((seconds - m as f64 * 60.0).min(60.0) * 1000.0) as usize;
        s.truncate(keep);
        if m == 0 {
            // Start the clock after the first frames, so start-up is not counted.
            sent += send_paced(&sock, &mut enc, &s[..1000.min(s.len())], 1000.0);
            cpu0 = d.cpu_s();
            loop0 = d.loop_cpu_s();
            t0 = Instant::now();
            sent += send_paced(&sock, &mut enc, &s[1000.min(s.len())..], 1000.0);
        } else {
            sent += send_paced(&sock, &mut enc, &s, 1000.0);
        }
    }
    let wall = t0.elapsed().as_secs_f64();
    let cpu = d.cpu_s() - cpu0;
    let lp = d.loop_cpu_s() - loop0;
    let rss = d.rss_mb();
    let lines = d.lines.load(std::sync::atomic::Ordering::Relaxed);
    // The last datagrams wait in the kernel until the next read (`daemon.udp_poll_ms`, 200 ms at
    // most).
    std::thread::sleep(Duration::from_millis(300));
    let (taken, dropped) = d.stop();
    println!(
        "live CPU at 1 kHz: {:.3} CPU-s over {wall:.1} s wall = {:.2}% of one core; {:.1} us per sample; {sent} frames sent, {taken} samples taken, {dropped} dropped; RSS {rss:.1} MB; {lines} JSON lines out",
        cpu,
        100.0 * cpu / wall,
        1e6 * cpu / (wall * 1000.0)
    );
    println!(
        "  of which the per-sample live loop (main thread): {:.3} CPU-s = {:.2}% of one core, {:.1} us per sample (target < 1%); refits and file writes (blocking pool): {:.3} CPU-s = {:.2}%",
        lp,
        100.0 * lp / wall,
        1e6 * lp / (wall * 1000.0),
        cpu - lp,
        100.0 * (cpu - lp) / wall
    );
}

fn memory(minutes: u64, rate: f64) {
    let d = Daemon::start();
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.connect(("127.0.0.1", d.port)).unwrap();
    let mut enc = MavEncoder::new(1, 1); // a flight controller: (1, 191) is the service itself
    let mut rss = vec![];
    let start = Instant::now();
    let mut sent = 0;
    for m in 0..minutes {
        let s = minute(m);
        sent += send_paced(&sock, &mut enc, &s, rate);
        std::thread::sleep(Duration::from_millis(50));
        rss.push(d.rss_mb());
    }
    let wall = start.elapsed().as_secs_f64();
    let (taken, dropped) = d.stop();
    let max = rss.iter().cloned().fold(f64::MIN, f64::max);
    let from = rss.get(4).copied().unwrap_or(rss[0]);
    let from_half = rss[rss.len() / 2];
    let last = *rss.last().unwrap();
    println!(
        "memory over {minutes} simulated minutes at 1 kHz ({sent} frames in {wall:.0} s, {taken} taken, {dropped} dropped): RSS first {:.1} MB, max {max:.1} MB, last {last:.1} MB, growth minute 5 -> end {:+.2} MB, second half {:+.2} MB (target < 30 MB, no growth)",
        rss[0],
        last - from,
        last - from_half
    );
    let per: Vec<String> = rss.iter().map(|r| format!("{r:.1}")).collect();
    println!("  RSS per minute (MB): {}", per.join(" "));
}

fn load(seconds: f64) {
    let d = Daemon::start();
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.connect(("127.0.0.1", d.port)).unwrap();
    let mut enc = MavEncoder::new(1, 1); // a flight controller: (1, 191) is the service itself
    let k0 = udp_rcvbuf_errors();
    let mut sent = 0;
    let minutes = (seconds / 6.0).ceil() as u64;
    // 10 kHz: each simulated minute of 1 kHz samples goes out in 6 s.
    for m in 0..minutes {
        let mut s = minute(m);
        let keep = ((seconds - m as f64 * 6.0).min(6.0) * 10_000.0) as usize;
        s.truncate(keep);
        sent += send_paced(&sock, &mut enc, &s, 10_000.0);
    }
    std::thread::sleep(Duration::from_millis(300));
    let kernel = udp_rcvbuf_errors() - k0;
    let (taken, dropped) = d.stop();
    println!(
        "load 10 kHz for {seconds:.0} s: {sent} frames sent, {taken} samples taken, {dropped} dropped and counted at the bounded queue, {} not delivered by the kernel; UDP receive-buffer errors on this machine meanwhile (all sockets) {kernel}; lost after the kernel delivered and not counted: {}",
        sent.saturating_sub(taken + dropped),
        // Frames that went missing beyond what the kernel could have dropped.
        (sent as i64 - taken as i64 - dropped as i64 - kernel as i64).max(0)
    );
}

/// Sample-in to attitude-out on loopback: the daemon publishes the fused attitude after every
/// sample (`daemon.attitude_every_samples = 1`) back to the sender (udpin answers the last peer).
/// Frames go out at 1 kHz; the time from each send to the ATTITUDE_QUATERNION that answers it is a
/// round trip (two loopback hops and this process's wake-up included), so an upper bound.
fn latency(seconds: f64) {
    // The timer's own attitude messages off (its first tick comes before any data).
    let d = Daemon::start_with("[daemon]\nattitude_every_samples = 1\nattitude_rate_hz = 0.001\n");
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.connect(("127.0.0.1", d.port)).unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let mut enc = MavEncoder::new(1, 1); // a flight controller: (1, 191) is the service itself
    let n = (seconds * 1000.0) as usize + 3000;
    let mut samples = Vec::new();
    let mut m = 0;
    while samples.len() < n {
        samples.extend(minute(m));
        m += 1;
    }
    samples.truncate(n);
    // Whether a datagram holds an ATTITUDE_QUATERNION (id 31): messages due together share one.
    let has_attitude_q = |mut b: &[u8]| -> bool {
        use imucald::io::decode::{parse_frame, FrameParse};
        use mavlink::Message;
        while !b.is_empty() {
            match parse_frame(b) {
                FrameParse::Frame(f, n) => {
                    if f.message.message_id() == 31 {
                        return true;
                    }
                    b = &b[n..];
                }
                FrameParse::Skip(n, _) => b = &b[n.max(1)..],
                FrameParse::Incomplete => return false,
            }
        }
        false
    };
    let mut buf = [0u8; 2048];
    let mut rtt_us = Vec::with_capacity(n);
    let (mut missing, mut answered) = (0u64, 0u64);
    let start = Instant::now();
    for (i, s) in samples.iter().enumerate() {
        let due = Duration::from_secs_f64(i as f64 / 1000.0);
        while let Some(wait) = due.checked_sub(start.elapsed()) {
            if wait > Duration::from_micros(300) {
                std::thread::sleep(wait - Duration::from_micros(200));
            } else {
                std::hint::spin_loop();
            }
        }
        let frame = enc.encode(&highres_imu(s, (s.t_s * 1e6) as u64 + 1_000_000));
        // Nothing stale may be taken for this sample's answer: drain first.
        sock.set_nonblocking(true).unwrap();
        while sock.recv(&mut buf).is_ok() {}
        sock.set_nonblocking(false).unwrap();
        let t0 = Instant::now();
        if sock.send(&frame).is_err() {
            continue;
        }
        // The filter needs its tilt and a field reference before it answers: skip 3 s.
        let measured = i >= 3000;
        loop {
            match sock.recv(&mut buf) {
                Ok(k) => {
                    let rtt = t0.elapsed();
                    if !has_attitude_q(&buf[..k]) {
                        continue;
                    }
                    answered += 1;
                    if measured {
                        rtt_us.push(rtt.as_secs_f64() * 1e6);
                    }
                    break;
                }
                Err(_) => {
                    if measured {
                        missing += 1;
                    }
                    break;
                }
            }
        }
    }
    let (taken, dropped) = d.stop();
    rtt_us.sort_by(|a, b| a.total_cmp(b));
    let q = |p: f64| {
        rtt_us
            .get(((rtt_us.len() as f64 * p) as usize).min(rtt_us.len().saturating_sub(1)))
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "latency sample-in -> ATTITUDE_QUATERNION-out (round trip on loopback, 1 kHz, {} measured): p50 {:.0} us, p90 {:.0} us, p99 {:.0} us (target < 1000 us), p99.9 {:.0} us, max {:.0} us; {missing} unanswered within 20 ms; {answered} answers, {taken} samples taken, {dropped} dropped",
        rtt_us.len(),
        q(0.5),
        q(0.9),
        q(0.99),
        q(0.999),
        rtt_us.last().copied().unwrap_or(f64::NAN)
    );
}

/// The service's CPU over `seconds` of 1 kHz frames: (whole process, main thread), % of one core.
fn cpu_run(d: &Daemon, seconds: f64, seed_minute: u64) -> (f64, f64) {
    cpu_run_imus(d, seconds, seed_minute, 1)
}

/// [`cpu_run`] for a vehicle with `imus` IMUs and compasses, each at 1 kHz.
fn cpu_run_imus(d: &Daemon, seconds: f64, seed_minute: u64, imus: u8) -> (f64, f64) {
    let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
    sock.connect(("127.0.0.1", d.port)).unwrap();
    let mut enc = MavEncoder::new(1, 1); // a flight controller: (1, 191) is the service itself
    let mut s = minute(seed_minute);
    s.truncate(((seconds + 1.0).min(60.0) * 1000.0) as usize);
    let warm = 1000.min(s.len());
    send_paced_imus(&sock, &mut enc, &s[..warm], 1000.0, imus);
    let (cpu0, loop0, t0) = (d.cpu_s(), d.loop_cpu_s(), Instant::now());
    send_paced_imus(&sock, &mut enc, &s[warm..], 1000.0, imus);
    let wall = t0.elapsed().as_secs_f64();
    (
        100.0 * (d.cpu_s() - cpu0) / wall,
        100.0 * (d.loop_cpu_s() - loop0) / wall,
    )
}

/// GET on loopback: (bytes of the whole response, body).
fn http_get(port: u16, path: &str) -> (usize, String) {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).expect("live page");
    write!(
        c,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut out = String::new();
    c.read_to_string(&mut out).unwrap();
    let body = out.split_once("\r\n\r\n").map_or("", |x| x.1).to_string();
    (out.len(), body)
}

/// An open page's event stream: reads every byte until the service ends it; (bytes read so far).
fn event_client(port: u16) -> std::sync::Arc<std::sync::atomic::AtomicU64> {
    use std::io::{Read, Write};
    let n = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let n2 = n.clone();
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).expect("live page");
    write!(c, "GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n").unwrap();
    std::thread::spawn(move || {
        let mut buf = vec![0u8; 65536];
        while let Ok(k) = c.read(&mut buf) {
            if k == 0 {
                break;
            }
            n2.fetch_add(k as u64, std::sync::atomic::Ordering::Relaxed);
        }
    });
    n
}

fn ui_cost(seconds: f64, rounds: u64) {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let (mut off, mut idle, mut page) = (vec![], vec![], vec![]);
    let mut transfer = None;
    for r in 0..rounds {
        for variant in 0..3 {
            let port = std::net::TcpListener::bind("127.0.0.1:0")
                .unwrap()
                .local_addr()
                .unwrap()
                .port();
            let toml = match variant {
                0 => String::new(),
                _ => format!("[ui]\nlisten = \"127.0.0.1:{port}\"\n"),
            };
            let d = Daemon::start_with(&toml);
            let stream = (variant == 2).then(|| {
                let (page_bytes, _) = http_get(port, "/");
                let (state_bytes, _) = http_get(port, "/api/state");
                (page_bytes, state_bytes, event_client(port))
            });
            let (cpu, lp) = cpu_run(&d, seconds, r);
            let streamed = stream
                .as_ref()
                .map(|s| s.2.load(std::sync::atomic::Ordering::Relaxed));
            if let Some((p, s, _)) = &stream {
                transfer = Some((*p, *s));
            }
            d.stop();
            let name = [
                "no page served",
                "page served, none connected",
                "one page connected",
            ][variant];
            println!(
                "  round {r}: {name}: {cpu:.2}% of one core (main thread {lp:.2}%){}",
                streamed.map_or(String::new(), |b| format!(
                    ", {b} bytes streamed to the page"
                ))
            );
            [&mut off, &mut idle, &mut page][variant].push(cpu);
        }
    }
    println!(
        "live page cost at 1 kHz ({rounds} rounds of {seconds:.0} s, alternated): no page {:.2}%, served with none connected {:.2}%, one page connected {:.2}% of one core: +{:.2} points for the connected page over none connected, +{:.2} over no page (target < 0.5)",
        mean(&off),
        mean(&idle),
        mean(&page),
        mean(&page) - mean(&idle),
        mean(&page) - mean(&off)
    );
    if let Some((p, s)) = transfer {
        println!(
            "live page transfer: page {p} bytes, snapshot {s} bytes (the stream's first message is the same snapshot): {} bytes before the stream (target < 200 KB)",
            p + s
        );
    }
}

/// One IMU against three (HIGHRES_IMU ids 0-2, each with its compass, each at 1 kHz), in
/// alternating runs of `seconds`, `rounds` times: the whole process's CPU (% of one core), the
/// live loop's, and the resident memory at the end of each run; then whether all three were
/// calibrated (the report's instances).
fn imus_cost(seconds: f64, rounds: u64) {
    for round in 0..rounds {
        for imus in [1u8, 3] {
            let d = Daemon::start();
            let (cpu, lp) = cpu_run_imus(&d, seconds, round, imus);
            let rss = d.rss_mb();
            let (taken, accepted, dropped) = d.stop_counts();
            println!(
                "{imus} IMU(s) at 1 kHz, round {round}: {cpu:.2}% of one core (live loop {lp:.2}%), RSS {rss:.1} MB; {taken} samples taken, {accepted} calibrations accepted, {dropped} dropped"
            );
        }
    }
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    if !std::path::Path::new("/proc/self/stat").exists() {
        println!("live bench: needs Linux /proc; skipped");
        return;
    }
    let only = std::env::var("IMUCALD_BENCH_ONLY").unwrap_or_default();
    if only.is_empty() || only == "cpu" {
        cpu_at_1khz(env_f64("IMUCALD_BENCH_CPU_S", 60.0));
    }
    if only.is_empty() || only == "latency" {
        latency(env_f64("IMUCALD_BENCH_LATENCY_S", 30.0));
    }
    if only.is_empty() || only == "memory" {
        memory(
            env_f64("IMUCALD_BENCH_MINUTES", 60.0) as u64,
            env_f64("IMUCALD_BENCH_RATE", 40_000.0),
        );
    }
    if only.is_empty() || only == "load" {
        load(env_f64("IMUCALD_BENCH_LOAD_S", 60.0));
    }
    if only.is_empty() || only == "imus" {
        imus_cost(
            env_f64("IMUCALD_BENCH_IMUS_S", 30.0),
            env_f64("IMUCALD_BENCH_IMUS_ROUNDS", 2.0) as u64,
        );
    }
    if only.is_empty() || only == "ui" {
        ui_cost(
            env_f64("IMUCALD_BENCH_UI_S", 30.0),
            env_f64("IMUCALD_BENCH_UI_ROUNDS", 3.0) as u64,
        );
    }
}
