//! The tests whose runs are judged on their timing (real time against the
//! model, the host's quiet measured) or load the machine on purpose
//! (floods, 100 agents, the lab): one binary, `cargo test --test realtime`
//! (one file's: `cargo test --test realtime attacks::`). Every test here
//! holds its share of the two cores while it runs (`common::cores`, its
//! measured load): two real-time labs side by side, or a lab beside light
//! runs, within `common::BUDGET`; floods and 100 agents alone. A lock-step
//! lab, whose verdict does not depend on time, runs beside them on what
//! they leave (`SCHED_IDLE`, one at a time). A run's comparison with the
//! model counts the tests beside it as the binary's own load; that the
//! tolerances hold beside it was measured over repeated runs
//! (docs/performance.md).

#[path = "../common/mod.rs"]
mod common;

// Eight tests at a time unless `RUST_TEST_THREADS` or `--test-threads`
// says otherwise: two labs run, a lock-step run takes what they leave
// (`Load::Idle`), and the tests waiting their turn each hold a thread.
common::test_threads_by_default!("8");

mod attacks;
mod lab;
mod network_realtime;
mod network_scale;
mod python;
mod ros2;
mod wire_attacks;
