pub mod agent;
pub mod barrier;
pub mod bench;
pub mod leader;
pub mod monitor;
pub mod node;
pub mod outbox;
pub mod session;
