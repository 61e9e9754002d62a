//! One follower of the formation: the distributed leader estimator
//! (eq. 11–15), the kinematic controllers (bioinspired backstepping,
//! eq. 29 and 34–36, and the conventional baseline), the dynamic controllers
//! (bioinspired sliding mode, eq. 37–43, conventional and super-twisting
//! baselines) and the velocity filters (KF and ASIF, eq. 57–65).
//!
//! The crate is pure: a [`Follower`] is a plain struct whose
//! [`Follower::step`] takes one step's inputs and returns its outputs. It
//! never reads a clock, a socket, a file or an environment variable, and the
//! step does not allocate.
//!
//! # Examples
//!
//! The bioinspired neural dynamics behind both controllers (eq. 34): the
//! shunting model's state follows its input, yet stays in [−D, B] however
//! large the input, which is what keeps the paper's commands smooth and
//! bounded.
//!
//! ```
//! use formation_control::Shunting;
//!
//! let model = Shunting { a: 5.0, b: 2.0, d: 2.0 };
//! let (mut v, dt) = (0.0, 0.01);
//! for _ in 0..1000 {
//!     v = model.advance(v, 1e6, dt); // an error a million times too large
//! }
//! assert!(v <= 2.0 && v > 1.99, "saturates at B, not at the input: {v}");
//! assert!(model.advance(0.0, -1.0, dt) < 0.0, "a negative input pulls it down");
//! ```

pub mod deadlock;
pub mod dynamic;
pub mod estimator;
pub mod filter;
pub mod follower;
pub mod guard;
pub mod kinematic;
pub mod links;
pub mod math;
pub mod slot;

pub use deadlock::DeadlockRule;
pub use dynamic::{DynamicGains, DynamicKind};
pub use estimator::EstimatorGains;
pub use filter::{FilterKind, FilterParams, VelocityFilter};
pub use follower::{ControlParams, Fault, Follower, FollowerConfig, NonFinite, StepOutput};
pub use guard::{Guard, GuardStep, GuardTally, Limits, Nearby, SafetyParams, Seen};
pub use kinematic::{BodyError, KinematicGains, KinematicKind};
pub use links::{Hearing, LinkLoss, LossWindow, Message, RejoinPolicy, RejoinRule};
pub use math::Shunting;
pub use slot::{Frame, Slots};
