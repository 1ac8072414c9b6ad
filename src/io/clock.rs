//! One clock per source: turns the times a source gives (a message's own time field, the time it
//! was received or recorded) into a sample time that never goes backwards, cut into *time segments*
//! wherever the source's time cannot be trusted to be continuous. Pure; no I/O.
//!
//! Streams made by other tools do not keep time the way a simulator does: a bridge starts its
//! message clock at zero, an autopilot reboots mid-log (its time restarts near zero while the
//! ground station's record time goes on), two logs are joined with `cat` (time jumps back by the
//! length of the first), a `time_boot_ms` wraps after 2^32 ms, a router duplicates frames, a link
//! drops out. Each such event is detected and counted by kind ([`TimeFault`]); each one that makes
//! the time before and after it incomparable starts a new segment. The stages that integrate over
//! time (static-pose gate, gyro rotations between poses, orientation filter, diagnosis windows)
//! never work across a segment boundary.
//!
//! Conventions: times in microseconds in, seconds out (`t_s`, from 0 at the first sample). Within a
//! segment `t_s` follows the chosen clock exactly (clamped so it never decreases); at a boundary it
//! moves on by the receive clock's step when that is plausible, else by the last normal step.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Settings of [`SourceClock`], with defaults.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ClockSettings {
    /// A forward step longer than this is a gap and starts a new segment, s. Default 2.0.
    pub max_step_s: f64,
    /// A backward step shorter than this is jitter, not a fault: the time holds until the clock
    /// catches up, s. Default 0.005.
    pub jitter_s: f64,
    /// A message clock that jumps back to below this is a restart (reboot), otherwise a backward
    /// jump (e.g. two logs joined), s. Default 60.
    pub reset_below_s: f64,
    /// Consecutive repeats of one message time (with new readings: a repeated frame is a
    /// duplicate, [`SourceClock::duplicate`]) after which the message clock counts as stopped
    /// (left at zero, or constant); fewer are held at that time. Default 3.
    pub stuck_after: u32,
    /// Samples over which the clock is chosen: a message clock that is stuck within these is
    /// given up for the receive clock for good. Default 16.
    pub probe_samples: u32,
    /// Times start at the first sample's own time (a CSV `t` column kept as the file has it)
    /// rather than at 0. Default false.
    pub keep_origin: bool,
}

impl Default for ClockSettings {
    fn default() -> Self {
        ClockSettings {
            max_step_s: 2.0,
            jitter_s: 0.005,
            reset_below_s: 60.0,
            stuck_after: 3,
            probe_samples: 16,
            keep_origin: false,
        }
    }
}

/// Which clock a source's sample times come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClockSource {
    /// The message's own time field (`time_usec`, `time_boot_ms`, a CSV `t` column).
    Message,
    /// When the message was received (live) or recorded (the `.tlog` record time).
    Receive,
}

/// A kind of time fault, as counted in the report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TimeFault {
    /// The message clock stayed at zero: the receive clock is used instead.
    Zero,
    /// The message clock stopped at a non-zero value.
    Constant,
    /// The message clock restarted near zero (a reboot) while samples went on.
    Reset,
    /// The clock jumped backwards, not to near zero (logs joined end to end).
    Backward,
    /// A 32-bit millisecond clock wrapped; unwrapped, so the segment goes on.
    Wrap,
    /// The same frame (time and readings) twice in a row: the repeat is dropped.
    Duplicate,
    /// A forward step longer than `max_step_s`.
    Gap,
}

impl TimeFault {
    /// True when the fault breaks the timeline (a new segment starts).
    pub fn breaks(self) -> bool {
        !matches!(self, TimeFault::Wrap | TimeFault::Duplicate)
    }
}

/// What a source's clock did over a stream: the report's `input.time`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TimeStats {
    /// The clock the sample times came from (none before the first sample).
    pub clock: Option<ClockSource>,
    /// Time segments: 1 for a clean stream, one more per fault that breaks the timeline.
    pub segments: u32,
    /// Faults by kind.
    pub faults: BTreeMap<TimeFault, u64>,
}

impl TimeStats {
    fn count(&mut self, f: TimeFault) {
        *self.faults.entry(f).or_insert(0) += 1;
    }

    /// Fold in another source's statistics (several links or logs in one report).
    pub fn add(&mut self, o: &TimeStats) {
        self.clock = self.clock.or(o.clock);
        self.segments += o.segments;
        for (k, n) in &o.faults {
            *self.faults.entry(*k).or_insert(0) += n;
        }
    }
}

/// The time of one sample: seconds since the stream's first sample, and its time segment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Stamp {
    pub t_s: f64,
    pub segment: u32,
}

/// One source's clock (see the module doc). Feed every sample's times to [`SourceClock::stamp`] in
/// arrival order.
#[derive(Debug, Clone)]
pub(crate) struct SourceClock {
    cfg: ClockSettings,
    pub stats: TimeStats,
    /// Samples stamped so far.
    n: u64,
    /// The last raw time of the chosen clock, us, unwrapped.
    last_us: Option<i64>,
    /// The last receive time, us.
    last_recv_us: Option<i64>,
    /// Added to a wrapping clock's raw value, us.
    unwrap_us: i64,
    /// Segment start: raw time (us) and output time (s).
    anchor: (i64, f64),
    last_t_s: f64,
    /// The last normal step, s (used to step over a boundary when nothing better is known).
    step_s: f64,
    /// Equal message times in a row.
    same_run: u32,
    /// Inside a stuck stretch of the message clock (times synthesised).
    stuck: bool,
    /// Bumped whenever `stats` changes (so a copy of them is refreshed only then).
    revision: u64,
}

impl SourceClock {
    pub fn new(cfg: ClockSettings) -> SourceClock {
        SourceClock {
            cfg,
            stats: TimeStats::default(),
            n: 0,
            last_us: None,
            last_recv_us: None,
            unwrap_us: 0,
            anchor: (0, 0.0),
            last_t_s: 0.0,
            step_s: 0.0,
            same_run: 0,
            stuck: false,
            revision: 0,
        }
    }

    /// Changes whenever [`SourceClock::stats`] do.
    pub(crate) fn revision(&self) -> u64 {
        self.revision
    }

    /// The time of one sample from its message time, us (`None` when the message has no time
    /// field), its receive/record time, us (`None` when there is none), and the message clock's
    /// wrap period, us (`Some(2^32 * 1000)` for a u32 millisecond field). A repeated frame is the
    /// caller's to drop (it sees the readings): [`SourceClock::duplicate`].
    pub fn stamp(
        &mut self,
        msg_us: Option<i64>,
        recv_us: Option<i64>,
        wrap_us: Option<i64>,
    ) -> Stamp {
        let source = *self.stats.clock.get_or_insert(match (msg_us, recv_us) {
            (None, Some(_)) => ClockSource::Receive,
            _ => ClockSource::Message,
        });
        let recv_step = self.receive_step(recv_us);
        let (raw, wrap) = match (source, msg_us) {
            (ClockSource::Message, Some(m)) => (m, wrap_us),
            // A message without a time on a message-timed source reads as a stopped clock.
            (ClockSource::Message, None) => (self.last_us.unwrap_or(0) - self.unwrap_us, None),
            (ClockSource::Receive, _) => (recv_us.unwrap_or(0), None),
        };
        self.n += 1;
        let Some(last) = self.last_us else {
            self.begin_first(raw);
            return self.out();
        };
        let now = raw.saturating_add(self.unwrap_us);
        if now == last && source == ClockSource::Message {
            return self.same_time(raw, recv_us, recv_step);
        }
        self.same_run = 0;
        if self.stuck {
            // The clock moves again: a new segment from here.
            self.stuck = false;
            self.boundary(now, recv_step);
            return self.out();
        }
        let step_s = to_s(now.saturating_sub(last));
        if step_s >= 0.0 {
            if step_s > self.cfg.max_step_s {
                self.fault(TimeFault::Gap);
                // The receive clock tells a real outage from a jump of the message clock; with
                // none, the gap is taken as it is (at most an hour, to keep `t_s` precise).
                let over = recv_step
                    .filter(|r| *r < step_s)
                    .unwrap_or(step_s.min(3600.0));
                self.boundary(now, Some(over));
            } else {
                self.advance(now, step_s);
            }
            return self.out();
        }
        if let Some(w) = wrap.filter(|w| *w > 0) {
            let ahead = now.saturating_add(w).saturating_sub(last);
            if ahead > 0 && to_s(ahead) <= self.cfg.max_step_s {
                self.fault(TimeFault::Wrap);
                self.unwrap_us = self.unwrap_us.saturating_add(w);
                let now = raw.saturating_add(self.unwrap_us);
                self.advance(now, to_s(ahead));
                return self.out();
            }
        }
        if -step_s <= self.cfg.jitter_s {
            // Jitter: the time holds until the clock catches up; the segment goes on.
            self.last_us = Some(now);
            return self.out();
        }
        let restarted = source == ClockSource::Message && to_s(raw) < self.cfg.reset_below_s;
        self.fault(if restarted {
            TimeFault::Reset
        } else {
            TimeFault::Backward
        });
        self.boundary(now, recv_step);
        self.out()
    }

    /// The receive clock's step since the last sample, s, when it moved forward plausibly.
    fn receive_step(&mut self, recv_us: Option<i64>) -> Option<f64> {
        let r = recv_us?;
        let step = self
            .last_recv_us
            .map(|l| to_s(r.saturating_sub(l)))
            .filter(|s| (0.0..=self.cfg.max_step_s).contains(s));
        self.last_recv_us = Some(r);
        step
    }

    /// A repeated frame (same time, same readings), which the caller drops: counted.
    pub(crate) fn duplicate(&mut self) {
        self.fault(TimeFault::Duplicate);
    }

    /// Count a fault; every change of `stats` goes through here or [`SourceClock::new_segment`].
    fn fault(&mut self, f: TimeFault) {
        self.stats.count(f);
        self.revision += 1;
    }

    fn new_segment(&mut self) {
        self.stats.segments += 1;
        self.revision += 1;
    }

    fn begin_first(&mut self, raw: i64) {
        self.new_segment();
        self.last_us = Some(raw);
        let origin = if self.cfg.keep_origin { to_s(raw) } else { 0.0 };
        self.anchor = (raw, origin);
        self.last_t_s = origin;
    }

    /// A message time equal to the last one, with new readings: held at that time, or a stopped
    /// clock once it repeats `stuck_after` times.
    fn same_time(&mut self, raw: i64, recv_us: Option<i64>, recv_step: Option<f64>) -> Stamp {
        self.same_run += 1;
        if !self.stuck && self.same_run < self.cfg.stuck_after.max(1) {
            return self.out();
        }
        if !self.stuck {
            self.fault(if raw == 0 {
                TimeFault::Zero
            } else {
                TimeFault::Constant
            });
            if let (true, Some(r)) = (self.n <= u64::from(self.cfg.probe_samples), recv_us) {
                // Within the probe: the message clock is given up for the receive clock for good.
                self.stats.clock = Some(ClockSource::Receive);
                self.same_run = 0;
                self.unwrap_us = 0;
                self.boundary(r, recv_step);
                return self.out();
            }
            self.stuck = true;
            self.new_segment();
        }
        // Synthesised: the receive clock's step, else the last normal step.
        self.last_t_s += recv_step.unwrap_or(self.step_s);
        self.anchor = (raw.saturating_add(self.unwrap_us), self.last_t_s);
        self.out()
    }

    fn advance(&mut self, now: i64, step_s: f64) {
        if step_s > 0.0 {
            self.step_s = step_s;
        }
        self.last_us = Some(now);
        let t = self.anchor.1 + to_s(now.saturating_sub(self.anchor.0));
        self.last_t_s = self.last_t_s.max(t);
    }

    /// A new segment starting at raw time `now`, `step_s` after the last sample (the last normal
    /// step when not known).
    fn boundary(&mut self, now: i64, step_s: Option<f64>) {
        self.new_segment();
        self.last_t_s += step_s.unwrap_or(self.step_s).max(0.0);
        self.anchor = (now, self.last_t_s);
        self.last_us = Some(now);
    }

    fn out(&self) -> Stamp {
        Stamp {
            t_s: self.last_t_s,
            segment: self.stats.segments.saturating_sub(1),
        }
    }
}

fn to_s(us: i64) -> f64 {
    us as f64 * 1e-6
}

/// A time in seconds as whole microseconds for [`SourceClock::stamp`] (saturating; NaN as 0).
pub(crate) fn us_from_s(t_s: f64) -> i64 {
    (t_s * 1e6).round() as i64
}

/// A u64 microsecond time field as i64 (saturating).
pub(crate) fn us_from_u64(t_us: u64) -> i64 {
    i64::try_from(t_us).unwrap_or(i64::MAX)
}

/// Microseconds since the Unix epoch by this computer's clock.
pub(crate) fn now_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

/// Today by this computer's clock (UTC): the date of the earth field when neither the
/// configuration nor the log gives one. The one place the date is read from the clock.
pub fn today() -> crate::types::LogDate {
    crate::types::LogDate::from_unix_us(now_us(), crate::types::DateSource::Today).unwrap_or(
        crate::types::LogDate {
            year: 2000,
            month: 1,
            day: 1,
            source: crate::types::DateSource::Today,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1000;

    /// Stamps of a 100 Hz stream whose message and receive times are given per sample.
    fn run(
        times: &[(Option<i64>, Option<i64>)],
        wrap: Option<i64>,
    ) -> (Vec<Option<Stamp>>, TimeStats) {
        let mut c = SourceClock::new(ClockSettings::default());
        let out = times
            .iter()
            .map(|(m, r)| Some(c.stamp(*m, *r, wrap)))
            .collect();
        (out, c.stats)
    }

    fn clean(n: usize, msg0: i64, recv0: i64) -> Vec<(Option<i64>, Option<i64>)> {
        (0..n as i64)
            .map(|i| (Some(msg0 + 10 * MS * i), Some(recv0 + 10 * MS * i)))
            .collect()
    }

    fn ts(out: &[Option<Stamp>]) -> Vec<f64> {
        out.iter().flatten().map(|s| s.t_s).collect()
    }

    fn assert_monotonic(out: &[Option<Stamp>]) {
        let s: Vec<Stamp> = out.iter().flatten().copied().collect();
        for w in s.windows(2) {
            assert!(w[1].t_s >= w[0].t_s, "{w:?}");
            assert!(w[1].segment >= w[0].segment, "{w:?}");
        }
    }

    #[test]
    fn a_clean_stream_is_one_segment_on_message_time() {
        let (out, st) = run(&clean(500, 12_345 * MS, 1_700_000_000_000_000), None);
        let t = ts(&out);
        assert_eq!(t.len(), 500);
        assert!((t[499] - 4.99).abs() < 1e-9);
        assert_eq!(st.segments, 1);
        assert!(st.faults.is_empty());
        assert_eq!(st.clock, Some(ClockSource::Message));
    }

    #[test]
    fn a_message_clock_starting_at_zero_is_just_a_clock() {
        // A bridge that counts from its first sample: 0, 10 ms, 20 ms, ... beside a Unix receive time.
        let (out, st) = run(&clean(300, 0, 1_700_000_000_000_000), None);
        let t = ts(&out);
        assert!((t[1] - 0.01).abs() < 1e-12 && (t[299] - 2.99).abs() < 1e-9);
        assert_eq!(st.segments, 1);
        assert!(st.faults.is_empty());
    }

    #[test]
    fn a_message_clock_left_at_zero_gives_way_to_the_receive_clock() {
        let times: Vec<_> = (0..200)
            .map(|i| (Some(0), Some(1_700_000_000_000_000 + 10 * MS * i)))
            .collect();
        let (out, st) = run(&times, None);
        assert_monotonic(&out);
        assert_eq!(st.clock, Some(ClockSource::Receive));
        assert_eq!(st.faults.get(&TimeFault::Zero), Some(&1));
        assert_eq!(st.faults.len(), 1);
        let t = ts(&out);
        // The first three are held at 0 until the stop is recognised; then the receive clock.
        assert_eq!(&t[..3], &[0.0; 3]);
        assert!((t[199] - t[3] - 1.96).abs() < 1e-9, "{}", t[199] - t[3]);
    }

    #[test]
    fn a_reboot_mid_log_starts_a_segment_and_time_goes_on_by_the_record_clock() {
        let mut times = clean(300, 500_000 * MS, 1_700_000_000_000_000);
        // After sample 299 the autopilot reboots: message time from 2.5 s, record time goes on.
        times.extend((0..300).map(|i| {
            (
                Some(2_500 * MS + 10 * MS * i),
                Some(1_700_000_000_000_000 + 10 * MS * (300 + i)),
            )
        }));
        let (out, st) = run(&times, None);
        assert_monotonic(&out);
        assert_eq!(st.segments, 2);
        assert_eq!(st.faults.get(&TimeFault::Reset), Some(&1));
        let s: Vec<Stamp> = out.iter().flatten().copied().collect();
        assert_eq!(s[300].segment, 1);
        assert!((s[300].t_s - 3.0).abs() < 1e-9 && (s[599].t_s - 5.99).abs() < 1e-9);
    }

    #[test]
    fn two_logs_joined_are_two_segments() {
        let mut times = clean(300, 900_000 * MS, 1_700_000_500_000_000);
        times.extend(clean(300, 400_000 * MS, 1_700_000_000_000_000));
        let (out, st) = run(&times, None);
        assert_monotonic(&out);
        assert_eq!(st.segments, 2);
        assert_eq!(st.faults.get(&TimeFault::Backward), Some(&1));
        // Over the join by one normal step.
        let t = ts(&out);
        assert!((t[300] - t[299] - 0.01).abs() < 1e-9);
    }

    #[test]
    fn a_u32_millisecond_wrap_is_unwrapped_without_a_new_segment() {
        let w = (1i64 << 32) * MS;
        let times: Vec<_> = (0..200)
            .map(|i| (Some(((w - 1000 * MS) + 10 * MS * i) % w), None))
            .collect();
        let (out, st) = run(&times, Some(w));
        let t = ts(&out);
        assert_eq!(st.faults.get(&TimeFault::Wrap), Some(&1));
        assert_eq!(st.segments, 1);
        assert!((t[199] - 1.99).abs() < 1e-6);
    }

    #[test]
    fn a_repeated_time_is_held_and_gaps_and_jitter_handled() {
        let mut times = clean(100, 1_000 * MS, 0);
        times.insert(50, times[49]);
        // A 5 s outage on both clocks.
        times.extend((0..100).map(|i| {
            (
                Some(7_000 * MS + 10 * MS * i),
                Some(6_000 * MS + 10 * MS * i),
            )
        }));
        // Receive-time jitter does not matter on message time; message-time jitter of 2 ms holds.
        times.push((Some(7_990 * MS - 2 * MS), Some(0)));
        times.push((Some(8_000 * MS), Some(0)));
        let (out, st) = run(&times, None);
        assert_monotonic(&out);
        assert_eq!(st.faults.get(&TimeFault::Gap), Some(&1));
        assert_eq!(st.faults.len(), 1);
        assert_eq!(st.segments, 2);
        let t = ts(&out);
        assert_eq!(t[50], t[49]);
        assert!((t[101] - t[100] - 5.01).abs() < 1e-9, "{}", t[101] - t[100]);
        assert_eq!(t[201], t[200]);
    }

    #[test]
    fn a_clock_that_stops_late_is_a_segment_of_synthesised_time() {
        let mut times = clean(100, 1_000 * MS, 0);
        times.extend((0..50).map(|i| (Some(1_990 * MS), Some(1_000 * MS + 10 * MS * i))));
        times.extend((0..50).map(|i| {
            (
                Some(2_500 * MS + 10 * MS * i),
                Some(1_500 * MS + 10 * MS * i),
            )
        }));
        let (out, st) = run(&times, None);
        assert_monotonic(&out);
        assert_eq!(st.clock, Some(ClockSource::Message));
        assert_eq!(st.faults.get(&TimeFault::Constant), Some(&1));
        assert_eq!(st.segments, 3);
    }

    #[test]
    fn no_sequence_of_times_breaks_it() {
        // Extremes: every value, both clocks, wrap or not.
        let vals = [i64::MIN, -1, 0, 1, 999, 1 << 40, i64::MAX - 1, i64::MAX];
        for wrap in [None, Some((1i64 << 32) * MS), Some(i64::MAX)] {
            let mut times = vec![];
            for a in vals {
                for b in vals {
                    times.push((Some(a), Some(b)));
                    times.push((None, Some(b)));
                    times.push((Some(a), None));
                }
            }
            let (out, _) = run(&times, wrap);
            assert_monotonic(&out);
            assert!(out.iter().flatten().all(|s| s.t_s.is_finite()));
        }
    }
}
