//! The `formation` command line: its commands (clap), the one shell every
//! node runs in, and the exit statuses. The work is in the crates below it,
//! each named by its own name: the reports (`formation-report`), running
//! nodes as processes (`formation-launch`), the benchmarks
//! (`formation-bench`), the network (`formation-net`), the simulator
//! (`formation-sim`); docs/architecture.md draws the layers.
//!
//! # Examples
//!
//! The command line as the binary parses it (`formation --help` lists it):
//!
//! ```
//! use clap::Parser;
//! use formation::cli::Cli;
//!
//! assert!(Cli::try_parse_from(["formation", "sim", "paper", "--set", "duration=2"]).is_ok());
//! assert!(Cli::try_parse_from(["formation", "sim"]).is_err(), "the scenario is required");
//! ```

pub mod args;
pub mod cli;
pub mod node;
pub mod replay;
