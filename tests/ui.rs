//! The pages in a real browser: headless Chromium (Debian's `chromium`, which `scripts/test`
//! installs) driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`: commands on
//! its fd 3, answers on fd 4, each message ended by a NUL byte).
//!
//! Without Chromium these tests say SKIPPED and pass, unless `IMUCALD_REQUIRE_BROWSER=1`
//! (`scripts/test`) makes its absence a failure ([`common::chromium`]).
//!
//! Nothing here waits for a guessed time: the page is watched for the state awaited (a
//! MutationObserver in the page), the service for its `ready` line and its event stream.
//!
//! Screenshots go to `IMUCALD_SCREENSHOT_DIR` when set (`docs/` for the README's pictures:
//! `IMUCALD_SCREENSHOT_DIR=docs cargo test --release --test ui`), else to a temporary directory.

mod common;

use common::chromium;
use serde_json::{json, Value};
use std::io::{BufRead, Read, Write};
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// A headless Chromium with one page, spoken to over the DevTools pipe.
struct Browser {
    child: Child,
    to: std::fs::File,
    from: mpsc::Receiver<Value>,
    next_id: u64,
    cdp_target: String,
    /// Events seen while waiting for answers.
    events: Vec<Value>,
    _profile: tempfile::TempDir,
}

fn pipe() -> (i32, i32) {
    let mut fds = [0i32; 2];
    // SAFETY: fds is a valid array of two ints for pipe(2) to fill.
    assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
    (fds[0], fds[1])
}

impl Browser {
    fn start(exe: &str) -> Browser {
        let profile = tempfile::tempdir().unwrap();
        let (cmd_r, cmd_w) = pipe(); // we write commands, it reads on fd 3
        let (ans_r, ans_w) = pipe(); // it writes answers on fd 4, we read
        let mut c = Command::new(exe);
        c.args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--remote-debugging-pipe",
            "--window-size=1280,1000",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .arg("about:blank")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
        // SAFETY: between fork and exec only dup2 and close, which are async-signal-safe.
        unsafe {
            c.pre_exec(move || {
                if libc::dup2(cmd_r, 3) < 0 || libc::dup2(ans_w, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                for fd in [cmd_r, cmd_w, ans_r, ans_w] {
                    if fd > 4 {
                        libc::close(fd);
                    }
                }
                Ok(())
            });
        }
        let child = c.spawn().unwrap();
        // SAFETY: the parent's ends, owned from here on; the child's ends are closed here.
        let (to, mut from_file) = unsafe {
            libc::close(cmd_r);
            libc::close(ans_w);
            use std::os::fd::FromRawFd;
            (
                std::fs::File::from_raw_fd(cmd_w),
                std::fs::File::from_raw_fd(ans_r),
            )
        };
        let (tx, from) = mpsc::channel();
        std::thread::spawn(move || {
            let mut buf = Vec::new();
            let mut chunk = vec![0u8; 1 << 16];
            while let Ok(n) = from_file.read(&mut chunk) {
                if n == 0 {
                    break;
                }
                buf.extend_from_slice(&chunk[..n]);
                while let Some(end) = buf.iter().position(|&b| b == 0) {
                    let msg: Vec<u8> = buf.drain(..=end).collect();
                    if let Ok(v) = serde_json::from_slice::<Value>(&msg[..msg.len() - 1]) {
                        if tx.send(v).is_err() {
                            return;
                        }
                    }
                }
            }
        });
        let mut b = Browser {
            child,
            to,
            from,
            next_id: 0,
            cdp_target: String::new(),
            events: vec![],
            _profile: profile,
        };
        let t = b.call(None, "Target.createTarget", json!({"url": "about:blank"}));
        let target = t["targetId"].as_str().unwrap().to_string();
        let s = b.call(
            None,
            "Target.attachToTarget",
            json!({"targetId": target, "flatten": true}),
        );
        b.cdp_target = s["sessionId"].as_str().unwrap().to_string();
        b
    }

    /// A command; its result (panics on an error answer or no answer in 30 s).
    fn call(&mut self, cdp_target: Option<&str>, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = cdp_target {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to.write_all(&bytes).unwrap();
        let v = self.next_where(|v| v["id"] == id, &format!("an answer to {method}"));
        assert!(v.get("error").is_none(), "{method}: {v}");
        v["result"].clone()
    }

    /// The next message `want` accepts (panics when none comes in 30 s, naming what was
    /// `awaited`); the others are kept in `events`.
    fn next_where(&mut self, want: impl Fn(&Value) -> bool, awaited: &str) -> Value {
        let until = Instant::now() + Duration::from_secs(30);
        loop {
            let left = until.saturating_duration_since(Instant::now());
            let v = self
                .from
                .recv_timeout(left)
                .unwrap_or_else(|_| panic!("no {awaited} within 30 s"));
            if want(&v) {
                return v;
            }
            self.events.push(v);
        }
    }

    fn page(&mut self, method: &str, params: Value) -> Value {
        let s = self.cdp_target.clone();
        self.call(Some(&s), method, params)
    }

    /// Evaluate a JavaScript expression in the page; its value.
    fn eval(&mut self, expr: &str) -> Value {
        let r = self.page(
            "Runtime.evaluate",
            json!({"expression": expr, "returnByValue": true}),
        );
        r["result"]["value"].clone()
    }

    /// Waits until `expr` is true in the page (panics after `secs`): the page watches for it
    /// itself, looking again at every change of its document (a MutationObserver: elements,
    /// attributes, text), and answers once it holds or the time is up.
    fn wait_for(&mut self, expr: &str, secs: f64) {
        let ms = (secs * 1000.0).round() as u64;
        let js = format!(
            "new Promise(done => {{ \
               const ok = () => {{ try {{ return !!({expr}); }} catch (e) {{ return false; }} }}; \
               if (ok()) {{ done(true); return; }} \
               const watch = new MutationObserver(() => {{ if (ok()) {{ watch.disconnect(); done(true); }} }}); \
               watch.observe(document, {{subtree: true, childList: true, attributes: true, characterData: true}}); \
               setTimeout(() => {{ watch.disconnect(); done(ok()); }}, {ms}); \
             }})"
        );
        let r = self.page(
            "Runtime.evaluate",
            json!({"expression": js, "awaitPromise": true, "returnByValue": true}),
        );
        assert_eq!(r["result"]["value"], json!(true), "page never got {expr}");
    }

    /// Navigates to `url` and waits for the page's load event (its document is then the one
    /// the next evaluation runs in). Needs `Page.enable`.
    fn navigate(&mut self, url: &str) {
        self.page("Page.navigate", json!({ "url": url }));
        if let Some(i) = self
            .events
            .iter()
            .position(|e| e["method"] == "Page.loadEventFired")
        {
            self.events.remove(i);
            return;
        }
        self.next_where(
            |v| v["method"] == "Page.loadEventFired",
            &format!("load of {url}"),
        );
    }

    /// A PNG of the page.
    fn screenshot(&mut self) -> Vec<u8> {
        let r = self.page("Page.captureScreenshot", json!({"format": "png"}));
        base64_decode(r["data"].as_str().unwrap())
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a') as u32 + 26,
            b'0'..=b'9' => (c - b'0') as u32 + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=' && c != b'\n').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= val(c) << (18 - 6 * i);
        }
        let k = chunk.len() - 1;
        out.extend_from_slice(&[(n >> 16) as u8, (n >> 8) as u8, n as u8][..k]);
    }
    out
}

/// Standard deviation of the grey levels of a PNG (a blank page: about 0).
fn png_grey_sd(png_bytes: &[u8]) -> (u32, u32, f64) {
    let dec = png::Decoder::new(png_bytes);
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size()];
    let info = r.next_frame(&mut buf).unwrap();
    let ch = match info.color_type {
        png::ColorType::Rgba => 4,
        png::ColorType::Rgb => 3,
        other => panic!("{other:?}"),
    };
    let (mut s, mut sq, mut n) = (0.0, 0.0, 0.0);
    for px in buf[..info.buffer_size()].chunks(ch) {
        let g = (px[0] as f64 + px[1] as f64 + px[2] as f64) / 3.0;
        s += g;
        sq += g * g;
        n += 1.0;
    }
    let mean = s / n;
    (
        info.width,
        info.height,
        (sq / n - mean * mean).max(0.0).sqrt(),
    )
}

fn screenshot_dir() -> (PathBuf, Option<tempfile::TempDir>) {
    match std::env::var("IMUCALD_SCREENSHOT_DIR") {
        Ok(d) => {
            let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(d);
            std::fs::create_dir_all(&p).unwrap();
            (p, None)
        }
        Err(_) => {
            let t = tempfile::tempdir().unwrap();
            (t.path().to_path_buf(), Some(t))
        }
    }
}

/// GET on loopback; the body.
fn http_get(port: u16, path: &str) -> Option<String> {
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    c.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        c,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut out = String::new();
    c.read_to_string(&mut out).ok()?;
    let i = out.find("\r\n\r\n")?;
    Some(out[i + 4..].to_string())
}

fn state_completion(port: u16) -> Option<f64> {
    let v: Value = serde_json::from_str(&http_get(port, "/api/state")?).ok()?;
    assert_eq!(v["schema"], "imucald.ui/1");
    v["progress"]
        .as_array()?
        .iter()
        .find(|p| p["sensor"] == "mag" && p["instance"] == 0)?["completion_pct"]
        .as_f64()
}

/// The page's event stream (`/api/events`), read until the magnetometer's completion (compass 0)
/// is above 0 in a line (or in the first, the snapshot); fails after `within`. The state
/// (`/api/state`) is updated before a line goes out on the stream.
fn wait_for_completion(port: u16, within: Duration) -> f64 {
    let until = Instant::now() + within;
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    write!(
        c,
        "GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut lines = std::io::BufReader::new(c.try_clone().unwrap());
    let mut line = String::new();
    loop {
        let left = until.saturating_duration_since(Instant::now());
        assert!(
            !left.is_zero(),
            "no progress on /api/events within {within:?}"
        );
        c.set_read_timeout(Some(left)).unwrap();
        line.clear();
        let n = lines
            .read_line(&mut line)
            .unwrap_or_else(|e| panic!("no progress on /api/events: {e}"));
        assert!(n > 0, "/api/events ended");
        let Some(at) = line.find('{') else { continue };
        let Ok(v) = serde_json::from_str::<Value>(line[at..].trim()) else {
            continue;
        };
        let mag0 = |p: &Value| p["sensor"] == "mag" && p["instance"] == 0;
        let pct = if v["type"] == "progress" && mag0(&v) {
            v["completion_pct"].as_f64()
        } else {
            v["progress"]
                .as_array()
                .and_then(|a| a.iter().find(|p| mag0(p)))
                .and_then(|p| p["completion_pct"].as_f64())
        };
        if let Some(pct) = pct.filter(|p| *p > 0.0) {
            return pct;
        }
    }
}

/// The live page while a simulated tumble runs: the completion it shows is the service's own
/// (`/api/state`) within one update, it updates at 5 Hz or more, its screenshot is not blank, and
/// SIGTERM stops the service within a second with the page open.
#[test]
fn ui_live_page_shows_the_services_completion_and_does_not_hold_its_exit() {
    let Some(exe) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    // Port 0: the service's `ready` line says which port the page got.
    let cfg = common::sim_service_toml(
        dir.path(),
        "tumble?speed=2",
        "[ui]\nlisten = \"127.0.0.1:0\"\n",
    );
    let mut svc = common::Service::start(&[
        "--config".as_ref(),
        cfg.as_os_str(),
        "--publish".as_ref(),
        "stdout".as_ref(),
    ]);
    let ui: std::net::SocketAddr = svc.ready_json()["ui"].as_str().unwrap().parse().unwrap();
    let port = ui.port();
    // The centre is known and regions counted: completion above 0 (the tumble at twice its pace
    // reaches it in about 10 s).
    let loaded_at = wait_for_completion(port, Duration::from_secs(60));
    // Completion never goes down within a run: the state has it too.
    assert!(state_completion(port).is_some_and(|c| c >= loaded_at));
    let mut b = Browser::start(exe);
    b.page("Page.enable", json!({}));
    b.navigate(&format!("http://127.0.0.1:{port}/"));
    b.wait_for("!!document.getElementById('completion-0')", 20.0);
    // The page's completion against the service's, read just before and after it: equal to one
    // of them (the progress line at 1 Hz may land between the two reads), or to the service's
    // value before that (a page that has not drawn the latest line yet: on a loaded machine it
    // can render a little after the line), never further behind than one update.
    let mut compared = 0;
    let mut rising = vec![];
    // Successive distinct values the service reported (the first: when the page loaded).
    let mut seen: Vec<f64> = vec![loaded_at];
    for _ in 0..20 {
        let before = state_completion(port).unwrap();
        if seen.last() != Some(&before) {
            seen.push(before);
        }
        let shown = b
            .eval("Number(document.getElementById('completion-0').dataset.pct)")
            .as_f64()
            .unwrap();
        let after = state_completion(port).unwrap();
        let earlier = seen.len().checked_sub(2).map(|k| seen[k]);
        assert!(
            shown == before || shown == after || Some(shown) == earlier,
            "page shows {shown} %, service {earlier:?} % earlier, {before} % then {after} %"
        );
        if seen.last() != Some(&after) {
            seen.push(after);
        }
        compared += 1;
        rising.push(shown);
        // Samples spread over 3 s of the stream (a measurement's spacing, not a wait).
        std::thread::sleep(Duration::from_millis(150));
    }
    eprintln!("page completion over 3 s: {rising:?}");
    // Update rate: events the page took and renders it made over 2 s of its own clock.
    let counts = "[Number(document.body.dataset.events||0), Number(document.body.dataset.rendered||0), performance.now()]";
    let a = b.eval(counts);
    // The window the rate is measured over.
    std::thread::sleep(Duration::from_secs(2));
    let z = b.eval(counts);
    let dt_s = (z[2].as_f64().unwrap() - a[2].as_f64().unwrap()) / 1000.0;
    let events_hz = (z[0].as_f64().unwrap() - a[0].as_f64().unwrap()) / dt_s;
    let renders_hz = (z[1].as_f64().unwrap() - a[1].as_f64().unwrap()) / dt_s;
    eprintln!("page: {events_hz:.1} events/s, {renders_hz:.1} renders/s");
    // Measured: about 21 events/s (attitude 10, heading 5, calibrated 5, progress 1) and
    // 9 to 10 renders/s (at most one per 100 ms).
    assert!(
        events_hz >= 5.0 && renders_hz >= 5.0,
        "{events_hz} {renders_hz}"
    );
    // The sphere canvas is drawn (not one colour).
    let sphere_sd = b.eval(
        "(() => { const c = document.getElementById('sphere'); const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let s = 0, q = 0, n = 0; for (let i = 0; i < d.length; i += 4) { const g = d[i] + d[i+1] + d[i+2]; s += g; q += g * g; n++; } const m = s / n; return Math.sqrt(q / n - m * m); })()",
    );
    assert!(sphere_sd.as_f64().unwrap() > 5.0, "{sphere_sd}");
    let png = b.screenshot();
    let (w, h, sd) = png_grey_sd(&png);
    let (shots, _tmp) = screenshot_dir();
    std::fs::write(shots.join("live-page.png"), &png).unwrap();
    eprintln!(
        "live page screenshot {w}x{h}, grey level sd {sd:.1}, {} bytes",
        png.len()
    );
    assert!(w >= 800 && h >= 600, "{w}x{h}");
    // Measured: sd about 60 (a blank page: 0).
    assert!(sd > 15.0, "{sd}");
    // The page's transfer: the page itself and the first snapshot.
    let page_bytes = http_get(port, "/").unwrap().len();
    let state_bytes = http_get(port, "/api/state").unwrap().len();
    eprintln!("transfer: page {page_bytes} bytes, state {state_bytes} bytes");
    assert!(page_bytes + state_bytes < 200_000);
    // SIGTERM with the page (its event stream) open.
    let t = Instant::now();
    let (status, log) = svc.stop(Duration::from_secs(5));
    let status = status.expect("imucald did not exit within 5 s of SIGTERM with a page open");
    let stop_s = t.elapsed().as_secs_f64();
    assert!(status.success(), "{status:?}: {log}");
    eprintln!("stopped {stop_s:.3} s after SIGTERM, {compared} comparisons");
    // Prompt with the event stream open, not held by it: under 1 s alone on the 2-core VM, and a
    // held stream is the 5 s the stop waits; the bound leaves room for a loaded machine.
    assert!(stop_s < 3.5, "{stop_s}");
    // The page says the connection went.
    b.wait_for(
        "document.getElementById('link').textContent.includes('lost')",
        10.0,
    );
}

/// The `--html` report of the bundled tumble, opened with the network off: it renders its views
/// (spheres drawn, screenshot not blank) and asks for nothing over the network.
#[test]
fn ui_html_report_renders_offline() {
    let Some(exe) = chromium() else { return };
    let dir = tempfile::tempdir().unwrap();
    let html = dir.path().join("report.html");
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .args(["replay", "--html"])
        .arg(&html)
        .output()
        .unwrap();
    common::assert_success(&out);
    let mut b = Browser::start(exe);
    b.page("Network.enable", json!({}));
    b.page(
        "Network.emulateNetworkConditions",
        json!({"offline": true, "latency": 0, "downloadThroughput": -1, "uploadThroughput": -1}),
    );
    b.page("Page.enable", json!({}));
    b.page(
        "Emulation.setDeviceMetricsOverride",
        json!({"width": 1280, "height": 2000, "deviceScaleFactor": 1, "mobile": false}),
    );
    let url = format!("file://{}", html.display());
    b.navigate(&url);
    b.wait_for("document.body && document.body.dataset.ready === '1'", 20.0);
    let spheres = b.eval("document.querySelectorAll('canvas[role=img]').length");
    // Mag and accel, before and after, and their residual plots.
    assert_eq!(spheres, json!(6), "{spheres}");
    let labels = b.eval("[...document.querySelectorAll('canvas')].every(c => (c.getAttribute('aria-label') || '').length > 10)");
    assert_eq!(labels, json!(true));
    let png = b.screenshot();
    let (w, h, sd) = png_grey_sd(&png);
    let (shots, _tmp) = screenshot_dir();
    std::fs::write(shots.join("html-report.png"), &png).unwrap();
    eprintln!("report screenshot {w}x{h}, grey level sd {sd:.1}");
    assert!(sd > 15.0, "{sd}");
    // Nothing but the file itself was asked for.
    let requests: Vec<String> = b
        .events
        .iter()
        .filter(|e| e["method"] == "Network.requestWillBeSent")
        .map(|e| {
            e["params"]["request"]["url"]
                .as_str()
                .unwrap_or("")
                .to_string()
        })
        .filter(|u| *u != url)
        .collect();
    assert!(requests.is_empty(), "{requests:?}");
}

/// The `--html` report of a real ArduPilot flight answers the pilot's question in words: the
/// held-out verdict for each compass and its figures, as the report's `quality` block has them.
#[test]
fn ui_html_report_answers_whether_it_is_better_than_the_vehicles() {
    let Some(exe) = chromium() else { return };
    let Some(data) = common::testdata::shared_data() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let html = dir.path().join("report.html");
    let out = Command::new(env!("CARGO_BIN_EXE_imucald"))
        .arg("replay")
        .arg(data.join("real/apm_copter_2013_c.tlog"))
        .arg("--html")
        .arg(&html)
        .output()
        .unwrap();
    common::assert_success(&out);
    let mut b = Browser::start(exe);
    b.page("Page.enable", json!({}));
    let url = format!("file://{}", html.display());
    b.navigate(&url);
    b.wait_for("document.body && document.body.dataset.ready === '1'", 20.0);
    let text = b.eval("document.body.innerText");
    let text = text.as_str().unwrap_or("");
    assert!(
        text.contains("Is it better than the vehicle's own?")
            && text.contains("raw_imu:0: imucald's is better"),
        "{text}"
    );
    assert!(text.contains("the vehicle's own") && text.contains("readings)"));
}
