pub mod session;
pub mod agent;
pub mod barrier;
pub mod leader;
pub mod monitor;
pub mod node;
pub mod bench;
