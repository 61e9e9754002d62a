#![no_main]
//! Checkpoints (JSON files, `<run>-follower-<id>.json`): the input is
//! written to a file that `checkpoint::read` reads, as a restarted agent
//! does, asked for the fingerprint and epoch the input itself names (where
//! it names them), so that a checkpoint of its own run goes on to the
//! pose's checks.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let own = serde_json::from_slice::<serde_json::Value>(data).ok();
    let named = |key: &str| own.as_ref().and_then(|v| v[key].as_u64()).unwrap_or(0);
    let (fingerprint, epoch) = (named("fingerprint"), named("epoch_unix_ns"));
    let path = std::env::temp_dir().join(format!("formation-fuzz-{}-follower-1.json", std::process::id()));
    std::fs::write(&path, data).expect("writing the checkpoint");
    formation_fuzz::check(data, |_| formation_net::checkpoint::read(&path, fingerprint, epoch));
});
