//! The Python package `formation` (docs/python.md): its Rust half, which
//! needs no Python, and with the `python` feature the PyO3 module
//! `formation._formation` that the package's Python code wraps.
//!
//! - [`memory`]: a scenario run in process into columns held in memory,
//!   the numbers `formation sim` writes to its CSVs;
//! - [`folder`]: any run folder (simulated or networked) read back into the
//!   same columns;
//! - [`keys`]: a scenario's keys as the file gives them, with `--set`'s
//!   names and checks;
//! - [`paper`]: the paper's Tables I and II over seeds, as numbers.
//!
//! # Examples
//!
//! The names the Python package takes are the command line's: a graph as
//! `formation generate --graph` names it, and an unknown one refused with
//! the list.
//!
//! ```
//! use _formation::keys::graph_kind;
//!
//! assert!(graph_kind("ring").is_ok());
//! let refused = graph_kind("star").unwrap_err();
//! assert!(refused.contains("ring") && refused.contains("grid"), "{refused}");
//! ```

pub mod folder;
pub mod keys;
pub mod memory;
pub mod paper;

#[cfg(feature = "python")]
mod py;
