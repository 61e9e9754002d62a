//! The formation's nodes as processes on this machine: `formation launch`
//! ([`launch`]), `formation lab` with each node in a network namespace of
//! its own ([`lab`]), the certificate folder for `--tls` ([`certs`]), the
//! disk a run will need ([`runsize`]), and the one shutdown signal every
//! supervisor waits on ([`shutdown`]). docs/architecture.md draws where
//! this crate sits: above the network and the record, below the command line.
//!
//! # Examples
//!
//! Before a launch starts a process, the size its run folder will take is
//! set against the free space ([`runsize`]): a folder of every step's rows
//! of the paper's 30 s.
//!
//! ```
//! use std::path::Path;
//! use formation_launch::runsize::projected_bytes;
//! use formation_scenario::Scenario;
//!
//! let paper = Scenario::load(Path::new("paper"), &[]).expect("scenario");
//! let every_step = projected_bytes(&paper, 1, true, false);
//! let every_tenth = projected_bytes(&paper, 10, true, false);
//! assert!(every_step > 1_000_000 && every_tenth < every_step, "{every_step} B, {every_tenth} B");
//! ```

pub mod certs;
pub mod lab;
pub mod launch;
pub mod options;
pub mod plan;
pub mod ports;
pub mod runsize;
pub mod supervisor;
pub mod zenoh_log;
