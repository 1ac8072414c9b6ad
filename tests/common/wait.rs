//! Waiting on events, not the clock: a child's output lines (the service's `ready` line among
//! them), its exit, a file written. Each wait has a deadline and returns as soon as the event
//! comes; none sleeps for a guessed time. (That the service took everything sent to it:
//! [`testdata::taken`].)

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, ExitStatus};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// How long a test waits for the service to say it is ready: a deadline, not a pause (it is
/// ready within milliseconds; a loaded machine can take seconds).
pub const READY_WITHIN: Duration = Duration::from_secs(30);

/// A child's output (stdout or stderr) as lines, read on a thread of its own so that the child
/// never blocks on a full pipe. Lines not yet taken wait in the channel: a test's child writes
/// little (the service's JSON lines on stdout are a few MB at most).
pub struct Lines {
    rx: mpsc::Receiver<String>,
    /// Every line taken so far, in order.
    pub seen: Vec<String>,
}

impl Lines {
    pub fn read(from: impl std::io::Read + Send + 'static) -> Lines {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(from).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Lines { rx, seen: vec![] }
    }

    /// The next line `want` accepts, once it comes; `None` when `within` passed or the output
    /// ended first.
    pub fn next_where(
        &mut self,
        mut want: impl FnMut(&str) -> bool,
        within: Duration,
    ) -> Option<String> {
        let deadline = Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let line = self.rx.recv_timeout(left).ok()?;
            self.seen.push(line.clone());
            if want(&line) {
                return Some(line);
            }
        }
    }

    /// A line `want` accepts among those already taken, or else the next one that comes
    /// ([`Lines::next_where`]): for an event that may have been said before the test looked.
    pub fn seen_or_next(
        &mut self,
        mut want: impl FnMut(&str) -> bool,
        within: Duration,
    ) -> Option<String> {
        if let Some(l) = self.seen.iter().find(|l| want(l)) {
            return Some(l.clone());
        }
        self.next_where(want, within)
    }

    /// The whole output, once the child closed it (it exited).
    pub fn until_end(&mut self) -> String {
        self.seen.extend(self.rx.iter());
        self.seen.join("\n")
    }

    /// From now on the lines are read and dropped, on a thread of their own.
    pub fn drain_in_background(&mut self) {
        let (_, closed) = mpsc::channel();
        let rx = std::mem::replace(&mut self.rx, closed);
        std::thread::spawn(move || rx.iter().for_each(drop));
    }
}

/// The next line of `lines` that `want` accepts; fails the test, naming what was `awaited` and
/// the lines seen, when it does not come within `within`.
#[track_caller]
pub fn wait_for_line(
    lines: &mut Lines,
    awaited: &str,
    want: impl FnMut(&str) -> bool,
    within: Duration,
) -> String {
    match lines.next_where(want, within) {
        Some(l) => l,
        None => panic!(
            "no {awaited} within {within:?}; the lines seen:\n{}",
            lines.seen.join("\n")
        ),
    }
}

/// Whether a log line of the service (stderr) is its `ready` line.
pub fn is_ready_log(line: &str) -> bool {
    line.contains(" ready: ")
}

/// Whether a JSON line (the service's stdout with `--publish stdout`) is its `ready` line.
pub fn is_ready_json(line: &str) -> bool {
    serde_json::from_str::<serde_json::Value>(line).is_ok_and(|v| v["type"] == "ready")
}

/// The child's exit status, once it exits; `None` when it still runs after `within`. Waits on
/// the exit itself (`waitid`, on a thread), not by polling.
pub fn wait_exit(child: &mut Child, within: Duration) -> Option<ExitStatus> {
    if let Some(s) = child.try_wait().unwrap() {
        return Some(s);
    }
    let pid = child.id();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        // SAFETY: waitid(2) on our own child with a zeroed siginfo_t for it to fill; WNOWAIT leaves
        // the child to be reaped by `try_wait` below.
        let r = unsafe {
            let mut info: libc::siginfo_t = std::mem::zeroed();
            libc::waitid(
                libc::P_PID,
                pid as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOWAIT,
            )
        };
        let _ = tx.send(r);
    });
    match rx.recv_timeout(within) {
        Ok(0) => child.try_wait().unwrap(),
        Ok(r) => panic!("waitid: {r}: {}", std::io::Error::last_os_error()),
        Err(_) => None,
    }
}

/// SIGTERM to a child.
pub fn sigterm(child: &Child) {
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(
        unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) },
        0
    );
}

/// The text of the file at `path` once `want` accepts it; `None` when `within` passed first.
/// Woken by the file system (inotify on the nearest existing directory on its way), not by a
/// timer: the service writes its files by renaming a complete temporary file into place.
pub fn wait_for_file(
    path: &Path,
    mut want: impl FnMut(&str) -> bool,
    within: Duration,
) -> Option<String> {
    let deadline = Instant::now() + within;
    // SAFETY: inotify_init1(2) with valid flags; the descriptor is owned here and closed below.
    let fd = unsafe { libc::inotify_init1(libc::IN_CLOEXEC | libc::IN_NONBLOCK) };
    assert!(fd >= 0, "inotify: {}", std::io::Error::last_os_error());
    let found = loop {
        // Watch the nearest directory that exists (the file's own once it is made), then look:
        // a change after the watch wakes the poll below, one before it is seen by the look.
        let dir = path.ancestors().skip(1).find(|d| d.is_dir());
        if let Some(dir) = dir {
            let c = std::ffi::CString::new(dir.as_os_str().as_encoded_bytes()).unwrap();
            let mask = libc::IN_CREATE | libc::IN_MOVED_TO | libc::IN_CLOSE_WRITE;
            // SAFETY: a valid descriptor and a NUL-terminated path.
            unsafe { libc::inotify_add_watch(fd, c.as_ptr(), mask) };
        }
        if let Some(text) = std::fs::read_to_string(path).ok().filter(|t| want(t)) {
            break Some(text);
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break None;
        }
        let mut p = libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = left.as_millis().min(i32::MAX as u128) as i32;
        // SAFETY: one valid pollfd; then the pending events are read into a local buffer and
        // dropped (only the wake-up matters).
        unsafe {
            libc::poll(&mut p, 1, ms);
            let mut buf = [0u8; 4096];
            while libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) > 0 {}
        }
    };
    // SAFETY: the descriptor opened above, closed once.
    unsafe { libc::close(fd) };
    found
}
