//! The in-process simulator: the leader, every follower's brain and robot,
//! stepped in lock-step in docs/model.md §9's order, deterministic to the
//! bit; and the same run written to a run folder.
//!
//! [`simulation`] holds the formation and its step; [`folder`] runs it into
//! a run folder through [`formation_record`].
//!
//! # Examples
//!
//! One simulated second of the paper's formation, stepped in process
//! without recording rows:
//!
//! ```
//! use std::path::Path;
//! use formation_scenario::Scenario;
//! use formation_sim::{NoRecord, Simulation};
//!
//! let scenario = Scenario::load(Path::new("paper"), &["duration=1".to_string()]).expect("scenario");
//! let mut sim = Simulation::new(&scenario);
//! sim.step(&mut NoRecord).expect("step 0");
//! assert_eq!(sim.step_index(), 1);
//! let metrics = sim.run(&mut NoRecord, |_| {}).expect("the rest");
//! assert_eq!((metrics.len(), sim.step_index()), (4, scenario.steps() + 1));
//! ```

pub mod folder;
pub mod simulation;

pub use folder::{run_to_folder, run_to_folder_until, FolderObserver};
pub use simulation::{step_on_odometry, Diverged, NoRecord, Observer, SimError, SimFollower, SimRobot, Simulation};
