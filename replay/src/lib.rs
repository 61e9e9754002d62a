//! A finished networked run again, offline: `formation replay` runs the
//! hearing record through the follower's steps and writes the same folder
//! with the same [`formation_recorder::Recorder`] ([`replay`]) and sets it
//! against the run ([`check`]), `--explain`
//! sets each fault beside its model ([`explain`]), and `formation play`
//! shows a finished run on the live page or in Foxglove ([`playback`]).
//!
//! This crate must never import zenoh, tokio or a node of `formation-net`:
//! an offline command reads a run without a network stack.
//!
//! # Examples
//!
//! A folder written by the in-process simulator has no hearing record:
//! there is nothing to replay, and [`replay::load`] says so instead of
//! computing anything.
//!
//! ```
//! use std::path::Path;
//! use formation_record::RecordOptions;
//! use formation_scenario::Scenario;
//!
//! let dir = std::env::temp_dir().join(format!("formation-replay-doc-{}", std::process::id()));
//! let scenario = Scenario::load(Path::new("paper"), &["duration=0.5".to_string()]).expect("scenario");
//! let opts = RecordOptions { dir: dir.clone(), every: 1, csv: true, mcap: false, rosbag2: false };
//! formation_sim::run_to_folder(&scenario, &opts, 1, |_| {}).expect("simulated");
//! let refused = formation_replay::replay::load(&dir).err().expect("not a networked run");
//! assert!(refused.to_string().contains("hearing"), "{refused}");
//! std::fs::remove_dir_all(&dir).unwrap();
//! ```

pub mod check;
pub mod explain;
#[cfg(feature = "playback")]
pub mod playback;
pub mod replay;
