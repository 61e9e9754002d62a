//! How every command and node of the formation ends, in one place low in
//! the stack:
//!
//! - [`Error`]: the one error they fail with, of four kinds (bad input, a
//!   failed run, a degraded run, a signal), each with its exit status
//!   ([`Error::status`]);
//! - [`shutdown`]: the one shutdown they stop on, the first SIGINT or
//!   SIGTERM, as a future a node's `run(args, shutdown)` takes (feature
//!   `async`) or as a flag the in-process simulator reads between steps.
//!
//! The libraries' own errors (a scenario's, a run folder's) say what went
//! wrong in their words and convert into [`Error`] in their own crates,
//! each choosing its kind once.
//!
//! # Examples
//!
//! ```
//! use formation_exit::{at_least_one, Error};
//!
//! let refused = at_least_one("--seeds", 0).unwrap_err();
//! assert_eq!(refused.to_string(), "--seeds must be at least 1, not 0");
//! assert_eq!(refused.status(), 2, "bad input");
//! assert_eq!(Error::Interrupted("stopped".into(), libc::SIGTERM as u8).status(), 143);
//! ```

mod error;
pub mod shutdown;

pub use error::{at_least_one, zerr, Error, DEGRADED};
