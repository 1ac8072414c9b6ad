//! The timing and averaging of the periodic outputs: cadences on the run loop's time grid, the
//! mean calibrated vectors and body rates between two publications.

use super::*;

/// A periodic output: served at the ticks of the run loop's clock when its period is a whole number
/// of clock periods, else by a timer of its own. Both are on the time grid from `epoch`.
pub(super) struct Output {
    pub(super) cadence: Cadence,
    pub(super) own: Option<tokio::time::Interval>,
}

impl Output {
    pub(super) fn new(epoch: tokio::time::Instant, rate_hz: f64) -> Output {
        Output {
            cadence: Cadence::new(epoch, rate_hz),
            own: None,
        }
    }

    /// Keep to the clock of period `clock`, or take a timer of its own.
    pub(super) fn use_clock(&mut self, epoch: tokio::time::Instant, clock: Duration) {
        let (p, c) = (self.cadence.period.as_nanos(), clock.as_nanos());
        if c == 0 || p % c != 0 {
            let mut t = tokio::time::interval_at(epoch, self.cadence.period);
            t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            self.own = Some(t);
        }
    }

    /// Whether the output is due at clock tick `t` (never, when it has a timer of its own).
    pub(super) fn due_at_clock(&mut self, t: tokio::time::Instant) -> bool {
        self.own.is_none() && self.cadence.due(t)
    }

    /// The next tick of its own timer (polled only when it has one).
    pub(super) async fn own_tick(&mut self) {
        match self.own.as_mut() {
            Some(t) => {
                t.tick().await;
            }
            None => std::future::pending().await,
        }
    }
}

/// A periodic output on the shared time grid: due at `epoch + k * period`. Asked at the ticks of a
/// clock on the same grid, at least as fast; ticks missed while busy are skipped, not made up.
#[derive(Debug, Clone, Copy)]
pub(super) struct Cadence {
    pub(super) period: Duration,
    pub(super) next: tokio::time::Instant,
}

impl Cadence {
    pub(super) fn new(epoch: tokio::time::Instant, rate_hz: f64) -> Cadence {
        Cadence {
            // (Rates are validated: finite, positive and at most 1 kHz.)
            period: Duration::from_secs_f64(1.0 / rate_hz).max(Duration::from_micros(1)),
            next: epoch,
        }
    }

    /// Whether the output is due at clock tick `t`; if so, the next time is set after `t`.
    pub(super) fn due(&mut self, t: tokio::time::Instant) -> bool {
        if t < self.next {
            return false;
        }
        let behind = (t - self.next).as_nanos() / self.period.as_nanos();
        self.next = u32::try_from(behind + 1)
            .ok()
            .and_then(|k| self.period.checked_mul(k))
            .and_then(|d| self.next.checked_add(d))
            .unwrap_or(t + self.period);
        true
    }
}

/// Mean of the calibrated body rates between two attitude publications; keeps the last mean when
/// no gyro sample came in between.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct RateMean {
    pub(super) sum: Vec3,
    pub(super) n: u32,
    pub(super) last: Option<Vec3>,
}

impl RateMean {
    pub(super) fn add(&mut self, g: &Vec3) {
        for k in 0..3 {
            self.sum[k] += g[k];
        }
        self.n += 1;
    }

    pub(super) fn take(&mut self) -> Option<Vec3> {
        if self.n > 0 {
            let n = self.n as f64;
            self.last = Some(self.sum.map(|v| v / n));
            self.sum = [0.0; 3];
            self.n = 0;
        }
        self.last
    }
}

/// Running means of calibrated vectors between publications.
#[derive(Debug, Default)]
pub(super) struct Averager {
    pub(super) a: [f64; 3],
    pub(super) na: usize,
    pub(super) g: [f64; 3],
    pub(super) ng: usize,
    pub(super) m: [f64; 3],
    pub(super) nm: usize,
}

impl Averager {
    pub(super) fn add(&mut self, c: &Calibrated) {
        let acc = |s: &mut [f64; 3], n: &mut usize, v: Option<Vec3>| {
            if let Some(v) = v {
                for k in 0..3 {
                    s[k] += v[k];
                }
                *n += 1;
            }
        };
        acc(&mut self.a, &mut self.na, c.accel_mps2);
        acc(&mut self.g, &mut self.ng, c.gyro_rad_s);
        acc(&mut self.m, &mut self.nm, c.mag_ut);
    }

    /// Means and the attitude from them; resets. None when nothing arrived.
    pub(super) fn take(&mut self, declination: Option<f64>) -> Option<Calibrated> {
        let mean = |s: [f64; 3], n: usize| (n > 0).then(|| s.map(|v| v / n as f64));
        let out = Calibrated {
            accel_mps2: mean(self.a, self.na),
            gyro_rad_s: mean(self.g, self.ng),
            mag_ut: mean(self.m, self.nm),
            ..Default::default()
        };
        *self = Averager::default();
        if out.accel_mps2.is_none() && out.mag_ut.is_none() {
            return None;
        }
        let mut out = out;
        if let Some(f) = out.accel_mps2 {
            let (r, p) = crate::attitude::roll_pitch_deg(&f);
            out.roll_deg = Some(r);
            out.pitch_deg = Some(p);
            if let Some(m) = out.mag_ut {
                out.heading_deg = Some(crate::attitude::wrap360(
                    crate::attitude::heading_deg(&m, r, p) + declination.unwrap_or(0.0),
                ));
            }
        }
        Some(out)
    }
}

/// The periodic outputs' timing, on the same time grid as the links' UDP polls (`epoch`). Those
/// whose period is a whole number of clock periods are served at the ticks of one clock that ticks
/// with the polls, in the wake-up a poll makes anyway (a timer of its own per output, set 100 ms or
/// more ahead, would cost tokio's timer wheel a wake-up of its own to move it to its finest level).
/// Any other keeps a timer of its own, so every output stays evenly spaced.
pub(super) struct Timers {
    /// On the polls' grid ([`crate::io::link::GridTimer`]: one wake-up per tick on Linux).
    pub(super) clock: crate::io::link::GridTimer,
    pub(super) heading: Output,
    pub(super) progress: Output,
    pub(super) attitude: Output,
    pub(super) drops: Output,
    pub(super) heartbeat: Option<Output>,
}

impl Timers {
    /// `polled`: a link is read by polling on the time grid.
    pub(super) fn new(
        d: &crate::config::DaemonConfig,
        polled: bool,
        epoch: tokio::time::Instant,
    ) -> Timers {
        let poll = Some(d.udp_poll()).filter(|p| polled && !p.is_zero());
        let mut outputs = [
            Output::new(epoch, d.heading_rate_hz),
            Output::new(epoch, d.progress_rate_hz),
            Output::new(epoch, d.attitude_rate_hz),
        ];
        let clock_period = poll
            .or_else(|| outputs.iter().map(|o| o.cadence.period).min())
            .unwrap_or(Duration::from_millis(100));
        let on_clock = |mut o: Output| {
            o.use_clock(epoch, clock_period);
            o
        };
        for o in outputs.iter_mut() {
            o.use_clock(epoch, clock_period);
        }
        let [heading, progress, attitude] = outputs;
        let clock = crate::io::link::GridTimer::new(epoch, clock_period);
        Timers {
            clock,
            heading,
            progress,
            attitude,
            drops: on_clock(Output::new(epoch, 1.0 / DROPS_REPORT_S)),
            heartbeat: (d.heartbeat_rate_hz > 0.0)
                .then(|| on_clock(Output::new(epoch, d.heartbeat_rate_hz))),
        }
    }
}

/// What the start-up's `ready` line says: every link opened, or failed to the first time (a live
/// link then keeps trying), and where the service listens.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ready {
    /// One per configured source, in the configured order.
    pub links: Vec<ReadyLink>,
    /// The live page's address (`[ui] listen`, the port chosen when 0 was asked), when served.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ui: Option<std::net::SocketAddr>,
}

/// A link in the `ready` line: its address as configured, and how its opening went
/// (`"state": "open"` with its bound `local` address, or `"failed"`, each with a `detail`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReadyLink {
    pub source: String,
    #[serde(flatten)]
    pub opening: LinkOpening,
}

impl Ready {
    /// The JSON line (`schema`, `"type": "ready"`, then the fields), terminated by `\n`.
    pub(super) fn json_line(&self) -> String {
        #[derive(Serialize)]
        struct Line<'a> {
            schema: &'static str,
            #[serde(rename = "type")]
            kind: &'static str,
            #[serde(flatten)]
            ready: &'a Ready,
        }
        let line = Line {
            schema: mavout::JSON_SCHEMA,
            kind: "ready",
            ready: self,
        };
        // Strings, numbers and addresses only: serialising cannot fail.
        let mut s = serde_json::to_string(&line).unwrap_or_default();
        s.push('\n');
        s
    }

    /// The log line's text: each link and how it opened, the live page's address.
    pub(super) fn summary(&self) -> String {
        let mut parts: Vec<String> = self
            .links
            .iter()
            .map(|l| match &l.opening {
                LinkOpening::Open { local: Some(a), .. } => format!("{} open on {a}", l.source),
                LinkOpening::Open { detail, .. } => format!("{} open ({detail})", l.source),
                LinkOpening::Failed { detail } => format!("{} failed ({detail})", l.source),
            })
            .collect();
        parts.extend(self.ui.map(|a| format!("live page on http://{a}/")));
        parts.join("; ")
    }
}

/// The `ready` line's state: told once, at start-up, when every link has opened or failed to.
pub(super) struct Readiness {
    pub(super) told: bool,
    /// The live page's address.
    pub(super) ui: Option<std::net::SocketAddr>,
    /// A caller in this process waiting for it ([`super::run_reporting_ready`]).
    pub(super) notify: Option<tokio::sync::oneshot::Sender<Ready>>,
}

/// Resolves once every link in `opening` has opened or failed to (or stopped before either).
pub(super) async fn all_opened(opening: &mut [watch::Receiver<Option<LinkOpening>>]) {
    for o in opening.iter_mut() {
        let _ = o.wait_for(Option::is_some).await;
    }
}

impl State {
    /// The `ready` line (JSON consumers, log, a waiting caller) once every link has opened or
    /// failed to; nothing before, and only once.
    pub(super) fn tell_ready_if_open(&mut self) {
        if self.ready.told {
            return;
        }
        let mut links = Vec::with_capacity(self.links.len());
        for l in &self.links {
            let opening = match l.handle.opening.borrow().clone() {
                Some(o) => o,
                // The link's task ended before it opened (the service is stopping).
                None if l.handle.opening.has_changed().is_err() => LinkOpening::Failed {
                    detail: "stopped before it opened".into(),
                },
                None => return,
            };
            links.push(ReadyLink {
                source: l.label.clone(),
                opening,
            });
        }
        self.ready.told = true;
        let ready = Ready {
            links,
            ui: self.ready.ui,
        };
        tracing::info!(target: super::STATUS_TARGET, "ready: {}", ready.summary());
        let line: std::sync::Arc<str> = ready.json_line().into();
        for s in &self.sinks {
            s.send(&line);
        }
        if let Some(tx) = self.ready.notify.take() {
            let _ = tx.send(ready);
        }
    }
}
