#![no_main]
//! Telemetry batches, a follower's or the leader's (`telemetry/<id>`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::codec::decode::<formation_protocol::telemetry::Telemetry>(d));
});
