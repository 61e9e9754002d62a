//! The in-process simulator: the leader, every follower's brain and robot,
//! stepped in lock-step in docs/model.md §9's order, deterministic to the
//! bit; and the same run written to a run folder.
//!
//! [`simulation`] holds the formation and its step; [`folder`] runs it into
//! a run folder through [`formation_record`].

pub mod folder;
pub mod simulation;

pub use folder::{run_to_folder, run_to_folder_until, FolderObserver};
pub use simulation::{step_on_odometry, Diverged, NoRecord, Observer, SimError, SimFollower, SimRobot, Simulation};
