//! The process's one shutdown: the first SIGINT or SIGTERM. A node, a
//! launch's or a lab's supervisor and a playback take it as a future
//! ([`signalled`], [`from_now`]; `run(args, shutdown)`, any future, so that
//! a test passes its own); the in-process simulator, which has no runtime
//! to poll a future, reads a [`flag`] between steps. Nothing else in the
//! project installs a signal handler (`tests/it/layers.rs` keeps it so).
//!
//! # Examples
//!
//! A node's loop stopped by whatever future its caller hands down, here a
//! test's rather than a real signal's:
//!
//! ```
//! use formation_exit::shutdown::Signal;
//!
//! let stopped = Signal::Terminate;
//! assert_eq!(stopped.number(), libc::SIGTERM);
//! assert_eq!(stopped.status(), 143);
//! assert_eq!(stopped.error("monitor: stopped").status(), 143);
//! assert_eq!(Signal::from_number(libc::SIGINT), Some(Signal::Interrupt));
//! ```

/// The signal that stops a process: what its shutdown future resolves to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Signal {
    /// SIGINT (Ctrl-C).
    Interrupt,
    /// SIGTERM.
    Terminate,
}

impl Signal {
    /// The signal's number (the exit status is 128 + it).
    pub fn number(self) -> i32 {
        match self {
            Signal::Interrupt => libc::SIGINT,
            Signal::Terminate => libc::SIGTERM,
        }
    }

    /// The exit status of a process it stopped: 128 + its number (130,
    /// 143), as a shell says it.
    pub fn status(self) -> u8 {
        self.error("").status()
    }

    /// The signal of a number, if it is one of the two.
    pub fn from_number(n: i32) -> Option<Signal> {
        match n {
            libc::SIGINT => Some(Signal::Interrupt),
            libc::SIGTERM => Some(Signal::Terminate),
            _ => None,
        }
    }

    /// The error a process stopped by it ends with, saying `line`.
    pub fn error(self, line: impl Into<String>) -> crate::Error {
        crate::Error::Interrupted(line.into(), self.number() as u8)
    }
}

#[cfg(feature = "async")]
mod future {
    use super::Signal;
    use tokio::signal::unix::{signal, SignalKind};

    /// Resolves on the first SIGINT or SIGTERM, saying which. The handlers
    /// are installed when it is first polled (where a node starts waiting
    /// for a signal): a signal before that ends the process as the system
    /// does. If they cannot be installed it says so and never resolves.
    pub async fn signalled() -> Signal {
        wait(streams()).await
    }

    /// The same with the handlers installed now (call it inside the
    /// runtime): a node, a launch or a lab catches a signal from its first
    /// moment (one before its loop began is a stop, not the default death).
    pub fn from_now() -> impl std::future::Future<Output = Signal> {
        wait(streams())
    }

    type Streams = std::io::Result<(tokio::signal::unix::Signal, tokio::signal::unix::Signal)>;

    fn streams() -> Streams {
        Ok((signal(SignalKind::interrupt())?, signal(SignalKind::terminate())?))
    }

    async fn wait(streams: Streams) -> Signal {
        // Streams created once, so that a signal arriving between two polls is not lost.
        match streams {
            Ok((mut int, mut term)) => tokio::select! {
                _ = int.recv() => Signal::Interrupt,
                _ = term.recv() => Signal::Terminate,
            },
            Err(e) => {
                eprintln!(
                    "warning: cannot install the SIGINT and SIGTERM handlers ({e}): a signal ends the process unrecorded"
                );
                std::future::pending().await
            }
        }
    }
}

#[cfg(feature = "async")]
pub use future::{from_now, signalled};

/// Ctrl-C and SIGTERM during an in-process run: a flag the run reads
/// between steps, so that it stops with its folder whole up to that step.
pub mod flag {
    use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};

    use super::Signal;

    static STOP: AtomicBool = AtomicBool::new(false);
    static SIGNAL: AtomicI32 = AtomicI32::new(libc::SIGINT);

    extern "C" fn on_signal(signal: libc::c_int) {
        // Async-signal-safe: two atomic stores.
        SIGNAL.store(signal, Ordering::Relaxed);
        STOP.store(true, Ordering::Relaxed);
    }

    /// Installs the handler for SIGINT and SIGTERM, once: a second Ctrl-C
    /// ends the process as it always did (a run stuck writing). The flag
    /// it sets.
    pub fn catch() -> &'static AtomicBool {
        for signal in [libc::SIGINT, libc::SIGTERM] {
            // SAFETY: a zeroed sigaction filled in; the handler only stores
            // to atomics.
            unsafe {
                let mut action: libc::sigaction = std::mem::zeroed();
                action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
                action.sa_flags = libc::SA_RESETHAND;
                libc::sigemptyset(&mut action.sa_mask);
                libc::sigaction(signal, &action, std::ptr::null_mut());
            }
        }
        &STOP
    }

    /// The default actions again once the run is over.
    pub fn release() {
        // SAFETY: restoring the default disposition.
        unsafe {
            libc::signal(libc::SIGINT, libc::SIG_DFL);
            libc::signal(libc::SIGTERM, libc::SIG_DFL);
        }
    }

    /// The signal that stopped the run.
    pub fn signal() -> Signal {
        Signal::from_number(SIGNAL.load(Ordering::Relaxed)).unwrap_or(Signal::Interrupt)
    }
}
