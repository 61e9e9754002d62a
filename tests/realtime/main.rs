//! The tests whose runs are judged on their timing (real time against the
//! model, the host's quiet measured) or load the machine on purpose
//! (floods, 100 agents, the lab): one binary, `cargo test --test realtime`
//! (one file's: `cargo test --test realtime attacks::`). Every test here
//! holds `common::ALONE` while it runs, so none shares the two cores with
//! another test of this binary, as when each file was a binary of its own
//! serialised by its own lock (cargo runs test binaries one after another).

#[path = "../common/mod.rs"]
mod common;

mod attacks;
mod lab;
mod network_realtime;
mod network_scale;
mod python;
mod ros2;
mod wire_attacks;
