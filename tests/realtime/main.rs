//! The tests that run the formation in real time or load the machine on
//! purpose (floods, 100 agents, the lab): one binary, `cargo test --test
//! realtime` (one file's: `cargo test --test realtime attacks::`). Every
//! test here holds its share of the two cores while it runs
//! (`common::cores`, its measured load): two labs side by side, or a lab
//! beside light runs, within `common::BUDGET`; floods and 100 agents
//! alone. No verdict here depends on the machine's speed: what holds
//! whatever the timing (every step recorded, the replay byte for byte, the
//! health naming what departed) is asserted always, and a run's figures
//! are compared with the model's only when its own record says it kept the
//! period (`common::judge_if_timely`). The binary's last line counts the
//! comparisons judged and not judged, and why. The same runs at nominal
//! timing, the machine to themselves, are `formation verify`'s.

#[path = "../common/mod.rs"]
mod common;

// Four tests at a time unless `RUST_TEST_THREADS` or `--test-threads`
// says otherwise: the budget holds at most four light runs, and the tests
// waiting their turn each hold a thread.
common::test_binary!("4");

mod attacks;
mod lab;
mod network_realtime;
mod network_scale;
mod python;
mod ros2;
mod wire_attacks;
