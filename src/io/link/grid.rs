//! A timer that ticks on a time grid, `epoch + k * period`: the UDP polls and the service's
//! periodic outputs share one grid, so that they fall in one wake-up.
//!
//! tokio's timer wheel keeps a timer more than a few tens of milliseconds ahead on a coarser level
//! and wakes the process once more, at the start of that level's slot (a multiple of 64 ms from the
//! runtime's start), to move it to the finest level: with a 50 ms poll that is a second wake-up for
//! about three polls in four (50/64), all the same work for the kernel as the poll's own. On Linux
//! the grid is therefore kept by a `timerfd` (the kernel's periodic timer on the monotonic clock,
//! which `std::time::Instant` reads; the `timerfd` crate): one wake-up per tick. Elsewhere, and
//! when tokio's clock is paused (tests), tokio's timers keep it.

use std::time::Duration;
use tokio::time::Instant;

/// The first point of the grid `epoch + k * every` after `now` (`now + every` when `now` is before
/// the epoch or `every` is zero).
pub(crate) fn next_on_grid(epoch: Instant, every: Duration, now: Instant) -> Instant {
    let (since, step) = (now.saturating_duration_since(epoch), every.as_nanos());
    if now < epoch || step == 0 {
        return now + every;
    }
    let k = since.as_nanos() / step + 1;
    // (k * step is at most `since + every`, so it fits a Duration whenever `now + every` does.)
    epoch + Duration::from_nanos(u64::try_from(k * step).unwrap_or(u64::MAX))
}

/// The last point of the grid at or before `now` (the epoch when `now` is before it).
fn last_on_grid(epoch: Instant, every: Duration, now: Instant) -> Instant {
    let (since, step) = (now.saturating_duration_since(epoch), every.as_nanos());
    if step == 0 {
        return now;
    }
    let k = since.as_nanos() / step;
    epoch + Duration::from_nanos(u64::try_from(k * step).unwrap_or(u64::MAX))
}

/// Ticks at `epoch + k * period`, the first at the epoch (at once, when it is past); ticks missed
/// while busy are skipped, not made up.
pub(crate) struct GridTimer {
    epoch: Instant,
    period: Duration,
    clock: Clock,
}

enum Clock {
    /// The kernel's timer.
    #[cfg(target_os = "linux")]
    Kernel(kernel::TimerFd),
    /// tokio's timers. `guard`, never awaited, is kept one period past `next`: when `next` fires,
    /// the timer driver's next wake-up becomes the earliest timer left, and re-arming `next`
    /// earlier than that makes tokio wake its driver (an eventfd write and one more `epoll_wait`
    /// per tick); with `guard`, re-arming is never earlier, and moving `guard` later only extends a
    /// pending timer.
    Tokio {
        next: std::pin::Pin<Box<tokio::time::Sleep>>,
        guard: std::pin::Pin<Box<tokio::time::Sleep>>,
    },
}

impl GridTimer {
    /// A timer on the grid from `epoch` every `period` (at least 1 ms).
    pub fn new(epoch: Instant, period: Duration) -> GridTimer {
        let period = period.max(Duration::from_millis(1));
        let clock = Self::kernel(epoch, period).unwrap_or_else(|| Clock::Tokio {
            next: Box::pin(tokio::time::sleep_until(epoch)),
            guard: Box::pin(tokio::time::sleep_until(epoch + period)),
        });
        GridTimer {
            epoch,
            period,
            clock,
        }
    }

    #[cfg(target_os = "linux")]
    fn kernel(epoch: Instant, period: Duration) -> Option<Clock> {
        if clock_paused() {
            return None;
        }
        match kernel::TimerFd::new(epoch, period) {
            Ok(fd) => Some(Clock::Kernel(fd)),
            Err(e) => {
                tracing::debug!("timerfd not available, tokio's timers keep the grid: {e}");
                None
            }
        }
    }

    #[cfg(not(target_os = "linux"))]
    fn kernel(_epoch: Instant, _period: Duration) -> Option<Clock> {
        None
    }

    /// Tick every `period` from now on, on the grid from the same epoch (the next tick is the
    /// new grid's first point after now).
    pub fn set_period(&mut self, period: Duration) {
        let period = period.max(Duration::from_millis(1));
        if period == self.period {
            return;
        }
        self.period = period;
        let due = next_on_grid(self.epoch, period, Instant::now());
        match &mut self.clock {
            #[cfg(target_os = "linux")]
            Clock::Kernel(fd) => {
                fd.arm(due, period);
            }
            Clock::Tokio { next, guard } => {
                next.as_mut().reset(due);
                guard.as_mut().reset(due + period);
            }
        }
    }

    /// Wait for the next tick; returns its point on the grid (the latest one when ticks were
    /// missed).
    pub async fn tick(&mut self) -> Instant {
        match &mut self.clock {
            #[cfg(target_os = "linux")]
            Clock::Kernel(fd) => {
                if let Err(e) = fd.wait().await {
                    tracing::debug!("timerfd failed, tokio's timers take over: {e}");
                    let due = next_on_grid(self.epoch, self.period, Instant::now());
                    self.clock = Clock::Tokio {
                        next: Box::pin(tokio::time::sleep_until(due)),
                        guard: Box::pin(tokio::time::sleep_until(due + self.period)),
                    };
                    return Box::pin(self.tick()).await;
                }
                last_on_grid(self.epoch, self.period, Instant::now())
            }
            Clock::Tokio { next, guard } => {
                next.as_mut().await;
                let now = Instant::now();
                let due = next_on_grid(self.epoch, self.period, now);
                next.as_mut().reset(due);
                guard.as_mut().reset(due + self.period);
                last_on_grid(self.epoch, self.period, now)
            }
        }
    }
}

/// Whether tokio's clock is paused (`tokio::time::pause`, tests): it does not move between two
/// readings without a yield, while the real clock moves on.
#[cfg(target_os = "linux")]
fn clock_paused() -> bool {
    let a = Instant::now();
    let real = std::time::Instant::now();
    while std::time::Instant::now() <= real {
        std::hint::spin_loop();
    }
    Instant::now() == a
}

#[cfg(target_os = "linux")]
mod kernel {
    use std::io;
    use std::time::Duration;
    use timerfd::{ClockId, SetTimeFlags, TimerState};
    use tokio::io::unix::AsyncFd;
    use tokio::time::Instant;

    /// A `timerfd` on the monotonic clock (the `timerfd` crate), watched by the tokio reactor.
    pub(super) struct TimerFd {
        fd: AsyncFd<timerfd::TimerFd>,
        /// Armed for the grid's next point while the first one asked for was already past: the
        /// next wait returns at once.
        due_now: bool,
    }

    impl TimerFd {
        pub(super) fn new(epoch: Instant, period: Duration) -> io::Result<TimerFd> {
            let fd = timerfd::TimerFd::new_custom(ClockId::Monotonic, true, true)?;
            // The one unsafe left: tokio (1.54 on) asks its caller to vouch for the descriptor.
            // SAFETY: `timerfd::TimerFd` owns its descriptor (an `OwnedFd` it never gives away or
            // replaces), so it is open and the same for as long as the AsyncFd that owns it lives.
            let fd = unsafe { AsyncFd::register_with_interest(fd, tokio::io::Interest::READABLE) }
                .map_err(|e| e.into_parts().1)?;
            let mut t = TimerFd { fd, due_now: false };
            t.arm(epoch, period);
            Ok(t)
        }

        /// Expire at `first` and every `period` after it; when `first` is past, the next wait
        /// returns at once and the timer expires at the following points `first + k * period`.
        pub(super) fn arm(&mut self, first: Instant, period: Duration) {
            // Armed relative to now (`Instant` reads the monotonic clock the timer runs on): the
            // kernel's reading of now is a few hundred ns after ours, far within its timer slack
            // of 50 us, so timers armed on one grid expire together, and periodic expirations keep
            // the first one's phase.
            let now = Instant::now();
            self.due_now = first <= now;
            let first = if self.due_now {
                super::next_on_grid(first, period, now)
            } else {
                first
            };
            // A zero time would disarm the timer.
            let current = first
                .saturating_duration_since(now)
                .max(Duration::from_nanos(1));
            // (Setting the time fails only for a bad descriptor or times out of range, which
            // neither an owned descriptor nor a Duration can be.)
            self.fd.get_mut().set_state(
                TimerState::Periodic {
                    current,
                    interval: period,
                },
                SetTimeFlags::Default,
            );
        }

        /// Wait until the timer expired (once or more) and take its count (0 for the first wait
        /// after arming for a point already past).
        pub(super) async fn wait(&mut self) -> io::Result<u64> {
            if std::mem::take(&mut self.due_now) {
                return Ok(0);
            }
            loop {
                let mut ready = self.fd.readable().await?;
                // The crate's nonblocking read gives 0 when nothing expired (readiness was stale):
                // taken as "would block", it clears the readiness and the loop waits again.
                let read = ready.try_io(|fd| match fd.get_ref().read() {
                    0 => Err(io::ErrorKind::WouldBlock.into()),
                    count => Ok(count),
                });
                if let Ok(count) = read {
                    // A read takes every expiration so far: the next one is a new event (a later
                    // read would only find nothing, one more system call per tick).
                    ready.clear_ready();
                    return count;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Polls land on the shared grid, strictly after now, whatever the phase of `now`.
    #[test]
    fn points_land_on_the_grid() {
        let epoch = Instant::now();
        let ms = Duration::from_millis;
        assert_eq!(next_on_grid(epoch, ms(10), epoch), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, ms(10), epoch + ms(3)), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, ms(10), epoch + ms(10)), epoch + ms(20));
        assert_eq!(
            next_on_grid(epoch, ms(10), epoch + ms(1234)),
            epoch + ms(1240)
        );
        // Before the epoch, or no period: one period from now.
        let later = epoch + ms(50);
        assert_eq!(next_on_grid(later, ms(10), epoch), epoch + ms(10));
        assert_eq!(next_on_grid(epoch, Duration::ZERO, later), later);
        assert_eq!(
            last_on_grid(epoch, ms(10), epoch + ms(1239)),
            epoch + ms(1230)
        );
        assert_eq!(
            last_on_grid(epoch, ms(10), epoch + ms(1240)),
            epoch + ms(1240)
        );
        assert_eq!(last_on_grid(later, ms(10), epoch), later);
    }

    /// The real clock (the kernel's timer on Linux): ticks on the grid, never before their point,
    /// the first at once when the epoch is past, missed ones skipped, and a new period on the same
    /// grid. (Lower bounds only: a loaded machine may make any tick late.)
    #[tokio::test]
    async fn ticks_on_the_grid_and_skips_missed_ticks() {
        #[cfg(target_os = "linux")]
        assert!(!clock_paused());
        let ms = Duration::from_millis;
        let epoch = Instant::now() - ms(35);
        let on_grid = |t: Instant, every: Duration| (t - epoch).as_nanos() % every.as_nanos();
        let mut t = GridTimer::new(epoch, ms(20));
        // The epoch is past: the first tick is at once and says the latest point passed.
        let t0 = Instant::now();
        let first = t.tick().await;
        assert!(
            first >= epoch + ms(20) && first <= t0 + ms(1),
            "{:?}",
            first - epoch
        );
        let mut last = first;
        for _ in 0..3 {
            let next = t.tick().await;
            assert!(next >= last + ms(20) && Instant::now() >= next);
            assert_eq!(on_grid(next, ms(20)), 0);
            last = next;
        }
        // Busy for two periods and more: the ticks missed are skipped, not made up.
        std::thread::sleep(ms(45));
        let late = t.tick().await;
        assert!(late >= last + ms(40), "{:?}", late - last);
        let next = t.tick().await;
        assert!(next >= late + ms(20));
        t.set_period(ms(10));
        let finer = t.tick().await;
        assert_eq!(on_grid(finer, ms(10)), 0);
        assert!(finer > next);
    }

    /// Under tokio's paused clock (tests), tokio's timers keep the grid: ticks come as the clock
    /// is advanced, at the grid's points.
    #[tokio::test(start_paused = true)]
    async fn paused_clock_ticks_on_tokio_timers() {
        let ms = Duration::from_millis;
        let epoch = Instant::now();
        let mut t = GridTimer::new(epoch, ms(50));
        assert!(matches!(t.clock, Clock::Tokio { .. }));
        assert_eq!(t.tick().await, epoch);
        assert_eq!(t.tick().await, epoch + ms(50));
        assert_eq!(t.tick().await, epoch + ms(100));
        assert_eq!(Instant::now(), epoch + ms(100));
    }
}
