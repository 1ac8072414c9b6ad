//! The MQTT consumer against a real broker: Debian's `mosquitto` on a free loopback port (started
//! here, not as a system service) and `mosquitto_sub` as the subscriber, both from the packages
//! `scripts/test` installs.
//!
//! Without them the test says SKIPPED and passes, unless `IMUCALD_REQUIRE_BROKER=1`
//! (`scripts/test`) makes their absence a failure.

mod common;

use common::{wait_for_line, Lines};
use serde_json::Value;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// Every type of JSON line the live service emits (`imucald.live/1`).
const LINE_TYPES: [&str; 7] = [
    "ready",
    "attitude",
    "heading",
    "calibrated",
    "progress",
    "calibration",
    "status",
];
/// The longest any one awaited event may take (they come within seconds on an idle machine).
const EVENT_TIMEOUT: Duration = Duration::from_secs(60);

/// The broker and the subscriber, or `None` with SKIPPED said (a failure under
/// `IMUCALD_REQUIRE_BROKER=1`).
fn mosquitto() -> Option<(PathBuf, PathBuf)> {
    let find = |names: &[&str]| names.iter().map(PathBuf::from).find(|p| p.exists());
    let broker = find(&["/usr/sbin/mosquitto", "/usr/bin/mosquitto"]);
    let sub = find(&["/usr/bin/mosquitto_sub"]);
    if let (Some(b), Some(s)) = (broker.clone(), sub.clone()) {
        return Some((b, s));
    }
    common::testdata::absent(
        &format!("an MQTT broker (mosquitto {broker:?}, mosquitto_sub {sub:?})"),
        "IMUCALD_REQUIRE_BROKER",
        "apt-get install mosquitto mosquitto-clients; scripts/test does",
    )
}

/// A child process with its output lines; killed when dropped.
struct Proc {
    child: Child,
    out: Lines,
    err: Lines,
}

impl Proc {
    fn spawn(name: &str, mut cmd: Command) -> Proc {
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let out = Lines::read(child.stdout.take().unwrap());
        let err = Lines::read(child.stderr.take().unwrap());
        Proc { child, out, err }
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Lines until one for which `f` says true (every line is shown to `f`); a failure naming `what`
/// when none comes within [`EVENT_TIMEOUT`].
#[track_caller]
fn wait_until(lines: &mut Lines, what: &str, f: impl FnMut(&str) -> bool) {
    wait_for_line(lines, what, f, EVENT_TIMEOUT);
}

/// `mosquitto -p PORT` (Mosquitto 2 alone listens on loopback only), once it says it runs.
fn start_broker(exe: &Path, port: u16) -> Proc {
    let mut c = Command::new(exe);
    c.args(["-p", &port.to_string()]);
    let mut b = Proc::spawn("mosquitto", c);
    wait_until(&mut b.err, "the broker to run", |l| {
        assert!(!l.contains("Error"), "mosquitto: {l}");
        l.contains(" running")
    });
    b
}

/// `mosquitto_sub` on `PREFIX/#` with the topics (`-v`), once the broker confirmed the
/// subscription (`-d` says so: its other debug lines start with "Client"). Its standard output
/// is line-buffered by coreutils' `stdbuf` (its debug lines are not flushed otherwise).
///
/// A subscriber that ends before it subscribed is started again, up to three times in all, each
/// end shown with what it wrote: once, on a loaded machine, one ended 0.12 s after its start
/// with its reason not kept. (The subscriber is the test's, not the service under test.)
fn start_subscriber(exe: &Path, port: u16, prefix: &str) -> Proc {
    let mut ends = Vec::new();
    for _ in 0..3 {
        let mut c = Command::new("stdbuf");
        c.arg("-oL")
            .arg(exe)
            .args(["-h", "127.0.0.1", "-p", &port.to_string()])
            .args(["-t", &format!("{prefix}/#"), "-v", "-d"]);
        let mut s = Proc::spawn("mosquitto_sub", c);
        if s.out
            .next_where(|l| l.starts_with("Subscribed"), EVENT_TIMEOUT)
            .is_some()
        {
            return s;
        }
        let status = s.child.try_wait();
        s.kill();
        // What it wrote to stderr before it ended (its reader has it all once it ended).
        while s.err.next_where(|_| true, Duration::from_secs(1)).is_some() {}
        let end = format!(
            "mosquitto_sub ended before it subscribed ({status:?}); stdout:\n{}\nstderr:\n{}",
            s.out.seen.join("\n"),
            s.err.seen.join("\n")
        );
        eprintln!("{end}");
        ends.push(end);
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!("no subscription in three starts:\n{}", ends.join("\n"));
}

/// A message line of `mosquitto_sub -v` (`TOPIC PAYLOAD`): its topic and JSON, checked to be a
/// live line on `PREFIX/1/<type>` (the first vehicle's system id, `daemon.target_system` = 1).
fn message(line: &str, prefix: &str) -> Option<(String, Value)> {
    if !line.starts_with(&format!("{prefix}/")) {
        return None;
    }
    let (topic, payload) = line.split_once(' ').expect(line);
    let v: Value = serde_json::from_str(payload).unwrap_or_else(|e| panic!("{e}: {line}"));
    assert_eq!(v["schema"], "imucald.live/1", "{line}");
    let kind = v["type"].as_str().expect(line).to_string();
    assert_eq!(topic, format!("{prefix}/1/{kind}"), "{line}");
    Some((kind, v))
}

/// The types of the JSON lines the service has written to stdout so far.
fn types_so_far(out: &mut Lines, seen: &mut BTreeSet<String>) {
    while let Some(line) = out.next_where(|_| true, Duration::ZERO) {
        let v: Value = serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"));
        seen.insert(v["type"].as_str().expect(&line).to_string());
    }
}

/// A simulated tumble published to a real broker: every type of line reaches the subscriber on
/// `fleet/<vehicle>/<type>`; with the broker killed mid-run the service keeps calibrating and
/// counts the lines it cannot deliver; with the broker back on the same port it reconnects and
/// calibration lines reach a new subscriber.
#[test]
fn mqtt_lines_reach_a_real_broker_and_survive_its_restart() {
    let Some((broker_exe, sub_exe)) = mosquitto() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let port = common::free_tcp_port();
    let url = format!("mqtt://127.0.0.1:{port}/fleet");
    let cfg = common::sim_service_toml(dir.path(), "tumble?speed=2", "");
    let report = dir.path().join("report.json");
    let mut broker = start_broker(&broker_exe, port);
    let mut sub = start_subscriber(&sub_exe, port, "fleet");
    let mut svc = common::Service::start(&[
        "--config".as_ref(),
        cfg.as_os_str(),
        "--publish".as_ref(),
        url.as_ref(),
        "--publish".as_ref(),
        "stdout".as_ref(),
        "--report".as_ref(),
        report.as_os_str(),
    ]);

    // Every type, each on its topic (`message` checks each line).
    let mut over_mqtt = BTreeSet::new();
    wait_until(&mut sub.out, "every type of line over MQTT", |l| {
        if let Some((kind, _)) = message(l, "fleet") {
            over_mqtt.insert(kind);
        }
        LINE_TYPES.iter().all(|t| over_mqtt.contains(*t))
    });
    // Said before the service was ready, or after.
    let connected = format!("{url}: connected to the MQTT broker");
    assert!(
        svc.stderr
            .seen_or_next(|l| l.contains(&connected), EVENT_TIMEOUT)
            .is_some(),
        "the service never said it connected"
    );
    let mut on_stdout = BTreeSet::new();
    types_so_far(&mut svc.stdout, &mut on_stdout);
    assert!(
        on_stdout.is_subset(&over_mqtt),
        "stdout {on_stdout:?}, MQTT {over_mqtt:?}"
    );

    // The broker goes away mid-run.
    broker.kill();
    sub.kill();
    wait_until(
        &mut svc.stderr,
        "the service's word that the broker went",
        |l| l.contains(&format!("{url}: lost the MQTT broker")),
    );
    // It keeps calibrating, and says (in a status line) that the MQTT consumer lost lines.
    let (mut calibrated, mut undelivered) = (0, None::<u64>);
    wait_until(&mut svc.stdout, "calibrations and a drop report", |l| {
        let v: Value = serde_json::from_str(l).unwrap();
        on_stdout.insert(v["type"].as_str().unwrap().to_string());
        calibrated += usize::from(v["type"] == "calibration");
        let text = v["text"].as_str().unwrap_or("");
        if let Some(rest) = text.strip_prefix(&format!("JSON consumer {url}: ")) {
            // "... (Q with its queue full, D not delivered), S sent"
            let d = rest.split(" with its queue full, ").nth(1).expect(text);
            undelivered = Some(d.split(' ').next().unwrap().parse().expect(text));
        }
        calibrated >= 2 && undelivered.is_some()
    });
    let undelivered = undelivered.unwrap();
    eprintln!("broker down: {calibrated} calibration lines on stdout, {undelivered} lines not delivered reported");
    assert!(undelivered > 0);

    // Back on the same port: the service reconnects and calibration lines come again.
    let _broker = start_broker(&broker_exe, port);
    let mut sub = start_subscriber(&sub_exe, port, "fleet");
    wait_until(
        &mut svc.stderr,
        "the service's word that it reconnected",
        |l| {
            let said = l.contains(&format!("{url}: reconnected to the MQTT broker after"));
            if said {
                eprintln!("{l}");
            }
            said
        },
    );
    let mut after = 0;
    wait_until(&mut sub.out, "calibration lines after the restart", |l| {
        if let Some((kind, _)) = message(l, "fleet") {
            after += usize::from(kind == "calibration");
        }
        after >= 2
    });

    // Stop it; the report counts what went to the broker and what did not.
    let (status, said) = svc.stop(EVENT_TIMEOUT);
    assert!(
        status.is_some_and(|s| s.success()),
        "imucald: {status:?}\n{said}"
    );
    types_so_far(&mut svc.stdout, &mut on_stdout);
    assert!(
        on_stdout.is_subset(&LINE_TYPES.iter().map(|t| t.to_string()).collect()),
        "a type this test does not know: {on_stdout:?}"
    );
    let r: Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let sinks = r["outputs"]["json_sinks"].as_array().unwrap();
    let count = |label: &str, key: &str| {
        let s = sinks.iter().find(|s| s["sink"] == label).expect(label);
        s[key].as_u64().unwrap()
    };
    let (sent, lost) = (count(&url, "sent"), count(&url, "not_delivered"));
    let full = count(&url, "queue_full");
    let stdout_sent = count("stdout", "sent");
    eprintln!("MQTT: {sent} sent, {lost} not delivered, {full} dropped with its queue full; stdout: {stdout_sent} sent");
    assert!(
        sent > 0 && lost >= undelivered,
        "{sent} {lost} {undelivered}"
    );
    // Each line went to both consumers, and every line the MQTT one took is counted once: sent,
    // not delivered or dropped. The report is written just before the last lines settle: measured
    // 0 and 1 lines apart over four runs.
    let settled = sent + lost + full;
    assert!(
        settled.abs_diff(stdout_sent) <= 5,
        "{settled} {stdout_sent}"
    );
}
