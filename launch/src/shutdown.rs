//! The process's one shutdown: the first SIGINT or SIGTERM, as a future
//! that the command hands down to whatever must stop on it (a node's loop,
//! a launch's or a lab's supervisor, a playback). No other place installs
//! a signal handler, except the in-process simulator's flag
//! (`cli::interrupt`), which has no runtime to poll a future.

use std::future::Future;

use formation_replay::watch::Signal;
use tokio::signal::unix::{signal, SignalKind};

/// Resolves on the first SIGINT or SIGTERM, saying which. The handlers are
/// installed when it is first polled (where a node starts waiting for a
/// signal): a signal before that ends the process as the system does. If
/// they cannot be installed it says so and never resolves.
pub async fn signalled() -> Signal {
    wait(streams()).await
}

/// The same with the handlers installed now (call it inside the runtime):
/// a launch or a lab catches a signal from the moment it has children to
/// clean up.
pub fn from_now() -> impl Future<Output = Signal> {
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
            formation_net::node::say(&format!(
                "warning: cannot install the SIGINT and SIGTERM handlers ({e}): a signal ends the process unrecorded"
            ));
            std::future::pending().await
        }
    }
}

/// The signal's number (the exit status is 128 + it).
pub fn number(s: Signal) -> i32 {
    match s {
        Signal::Interrupt => libc::SIGINT,
        Signal::Terminate => libc::SIGTERM,
    }
}
