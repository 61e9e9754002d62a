//! The formation's nodes as processes on this machine: `formation launch`
//! ([`launch`]), `formation lab` with each node in a network namespace of
//! its own ([`lab`]), the certificate folder for `--tls` ([`certs`]), the
//! disk a run will need ([`runsize`]), and the one shutdown signal every
//! supervisor waits on ([`shutdown`]). docs/architecture.md draws where
//! this crate sits: above the network and the record, below the command line.

pub mod certs;
pub mod error;
pub mod lab;
pub mod launch;
pub mod options;
pub mod plan;
pub mod runsize;
pub mod shutdown;
pub mod supervisor;
pub mod zenoh_log;
