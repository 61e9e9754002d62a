//! The root crate's integration tests, one binary (`cargo test --test it`;
//! one file's: `cargo test --test it network_launch::`). Each module is a
//! former `tests/<name>.rs`, its doc comment kept: one binary links zenoh
//! and the crate once instead of once per file. The tests whose verdict
//! compare real-time runs with the model are in `tests/realtime`;
//! `tests/alloc_free.rs` keeps its own counting allocator (and binary).
//!
//! Measured on the 2-core machine, dependencies built, other builds beside
//! it: the root crate and its tests built from nothing took 319 s (229 s of
//! CPU) with 28 test binaries, 127 s (87 s) with 5 (it, realtime,
//! alloc_free, containers, layers); the workspace's test binaries and
//! their incremental caches took 900 + 400 MB, then 253 + 155 MB. After a
//! touch of src/lib.rs: 23–30 s, then 16–17 s.

#[path = "../common/mod.rs"]
mod common;

// Four tests at a time unless `RUST_TEST_THREADS` or `--test-threads`
// says otherwise (libtest's default is one per core): most of these tests
// wait on the processes they started (130 s with 2, 80 s with 4;
// docs/performance.md). It ends with a line counting its tests skipped.
common::test_binary!("4");

mod certs_safety;
mod cli_generate;
mod cli_sim;
mod docs;
mod foxglove_live;
mod fuzz_decoders;
mod hostile_inputs;
mod incomplete_runs;
mod killed;
mod layers;
mod link_faults;
mod mcap_recording;
mod network_faults;
mod network_launch;
mod network_lockstep;
mod paper_claims;
mod paper_report;
mod replay;
mod ros2;
mod safety;
mod security;
mod sim_parallel;
mod steering;
mod web_live;
mod zenoh_transport;

/// Every file of tests/it and tests/realtime is a module of its binary's
/// main.rs: a file named in neither would never be compiled, let alone run.
#[test]
fn every_test_file_is_a_module_of_its_binary() {
    let tests = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests");
    for binary in ["it", "realtime"] {
        let dir = tests.join(binary);
        let main = std::fs::read_to_string(dir.join("main.rs")).expect("main.rs");
        for e in std::fs::read_dir(&dir).expect("test folder").flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Some(module) = name.strip_suffix(".rs").filter(|m| *m != "main") else { continue };
            assert!(
                main.contains(&format!("\nmod {module};\n")),
                "tests/{binary}/{name} is not a `mod` of tests/{binary}/main.rs"
            );
        }
    }
}
