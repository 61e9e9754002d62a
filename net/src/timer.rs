//! A precise sleep for a loop that runs as a task: a `timerfd` on the
//! reactor of the runtime that polls it, armed to the nanosecond as
//! `std::thread::sleep` is (tokio's own timer counts whole milliseconds,
//! a whole period at 1 kHz).
//!
//! Why a task and not a thread: an agent's real-time loop runs on zenoh's
//! own thread ([`crate::agent`]), so that the estimate it publishes is
//! written to the sockets in the same wake-up as the step, not handed to
//! another thread that must be woken for it.

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::Instant;

use crate::clock::Clock;

use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

/// One timer; [`Timer::sleep_until`] re-arms it.
pub struct Timer {
    fd: AsyncFd<OwnedFd>,
}

impl Timer {
    /// A timer on the reactor of the runtime this is called in.
    pub fn new() -> io::Result<Self> {
        // SAFETY: timerfd_create takes no pointers.
        let raw = unsafe { libc::timerfd_create(libc::CLOCK_MONOTONIC, libc::TFD_NONBLOCK | libc::TFD_CLOEXEC) };
        if raw < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: `raw` is a new descriptor that nothing else owns.
        let fd = unsafe { OwnedFd::from_raw_fd(raw) };
        // SAFETY: the descriptor is owned by the AsyncFd and is neither
        // closed nor replaced while registered (it closes when it drops).
        Ok(Self { fd: unsafe { AsyncFd::register_with_interest(fd, Interest::READABLE)? } })
    }

    /// Until `at` on `clock` (at once if it has passed). `Instant` is
    /// CLOCK_MONOTONIC, the timer's clock; a mock clock moves to `at` at once.
    pub async fn sleep_until(&self, at: Instant, clock: &Clock) -> io::Result<()> {
        let d = at.saturating_duration_since(clock.instant());
        if d.is_zero() {
            return Ok(());
        }
        if clock.is_mock() {
            clock.sleep_until(at);
            return Ok(());
        }
        let spec = setting(d);
        // SAFETY: a valid descriptor and a pointer to a local; no old value asked.
        if unsafe { libc::timerfd_settime(self.fd.as_raw_fd(), 0, &spec, std::ptr::null_mut()) } < 0 {
            return Err(io::Error::last_os_error());
        }
        loop {
            let mut ready = self.fd.readable().await?;
            let read = ready.try_io(|fd| {
                let mut expirations = [0u8; 8];
                // SAFETY: reads at most 8 bytes into a local buffer of 8.
                let n = unsafe { libc::read(fd.as_raw_fd(), expirations.as_mut_ptr().cast(), 8) };
                if n < 0 {
                    Err(io::Error::last_os_error())
                } else {
                    Ok(())
                }
            });
            match read {
                Ok(result) => return result,
                // Not yet (readiness was stale): wait again.
                Err(_would_block) => continue,
            }
        }
    }
}

/// The timer's setting for a sleep of `d`: once, to the nanosecond.
fn setting(d: std::time::Duration) -> libc::itimerspec {
    libc::itimerspec {
        it_interval: libc::timespec { tv_sec: 0, tv_nsec: 0 },
        it_value: libc::timespec { tv_sec: d.as_secs() as libc::time_t, tv_nsec: d.subsec_nanos() as _ },
    }
}

/// Runs `task` on zenoh's application thread, where an agent's real-time
/// loop runs (and `formation node floor`'s, measured against it), and
/// waits for it; Err if it panicked.
pub async fn on_zenoh_thread<F>(task: F) -> Result<F::Output, String>
where
    F: std::future::Future + Send + 'static,
    F::Output: Send + 'static,
{
    zenoh_runtime::ZRuntime::Application.spawn(task).await.map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Armed to the nanosecond, once (tokio's timer counts whole
    /// milliseconds, a whole period at 1 kHz); how late it wakes on this
    /// machine is a figure, not a verdict (docs/performance.md, the loop's
    /// lateness that `network.json` reports).
    #[test]
    fn it_is_armed_to_the_nanosecond_once() {
        let s = setting(Duration::from_nanos(300_007));
        assert_eq!((s.it_value.tv_sec, s.it_value.tv_nsec), (0, 300_007));
        let s = setting(Duration::from_millis(2_500));
        assert_eq!((s.it_value.tv_sec, s.it_value.tv_nsec), (2, 500_000_000));
        assert_eq!((s.it_interval.tv_sec, s.it_interval.tv_nsec), (0, 0), "no repeat");
    }

    /// It never wakes before the instant, however loaded the machine; an
    /// instant passed returns without arming the timer.
    #[tokio::test(flavor = "current_thread")]
    async fn it_never_wakes_early_and_a_passed_instant_arms_nothing() {
        let t = Timer::new().expect("timerfd");
        for _ in 0..20 {
            let at = Instant::now() + Duration::from_micros(300);
            t.sleep_until(at, &Clock::real()).await.expect("sleep");
            let now = Instant::now();
            assert!(now >= at, "woke {:?} early", at - now);
        }
        t.sleep_until(Instant::now() - Duration::from_millis(5), &Clock::real()).await.expect("past");
        let mut armed = setting(Duration::from_secs(1));
        // SAFETY: a valid descriptor and a pointer to a local.
        assert_eq!(unsafe { libc::timerfd_gettime(t.fd.as_raw_fd(), &mut armed) }, 0);
        assert_eq!((armed.it_value.tv_sec, armed.it_value.tv_nsec), (0, 0), "a passed instant armed the timer");
    }
}
