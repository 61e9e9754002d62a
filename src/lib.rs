//! The `formation` command line: its commands (clap), the one shell every
//! node runs in, and the exit statuses. The work is in the crates below it,
//! each named by its own name: the reports (`formation-report`), running
//! nodes as processes (`formation-launch`), the benchmarks
//! (`formation-bench`), the network (`formation-net`), the simulator
//! (`formation-sim`); docs/architecture.md draws the layers.

pub mod args;
pub mod cli;
pub mod error;
pub mod node;
pub mod replay;
