//! The `formation` shells around the pure core: the in-process simulator,
//! run recording and metrics, the zenoh nodes and the command line.

pub mod bench;
pub mod certs;
pub mod cli;
pub mod error;
pub mod foxglove_live;
pub mod lab;
pub mod launch;
pub mod mcap_file;
pub mod net;
pub mod outage;
pub mod paper;
pub mod record;
pub mod report;
pub mod sim;
pub mod study;
pub mod web;
