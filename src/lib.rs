//! The `formation` command line and its tools, above the libraries: the
//! model (`formation-plant`, `-leader`, `-agent`, `-topology`), the run
//! record (`formation-record`), the simulator (`formation-sim`) and the
//! network (`formation-net`). This crate alone knows exit statuses and clap
//! commands; docs/architecture.md draws the layers.

pub mod args;
pub mod bench;
pub mod bench_floor;
pub mod bench_hearing;
pub mod bench_net;
pub mod bench_netns;
pub mod bench_ros2;
pub mod calibrate;
pub mod certs;
pub mod cli;
pub mod error;
pub mod explain;
pub mod lab;
pub mod launch;
pub mod node;
pub mod outdir;
pub mod paper;
pub mod progress;
pub mod replay;
pub mod report;
pub mod runsize;
pub mod shutdown;
pub mod study;
pub mod words;
