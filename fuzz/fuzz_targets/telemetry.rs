#![no_main]
//! Telemetry batches, a follower's or the leader's (`telemetry/<id>`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_net::codec::decode::<formation_net::telemetry::Telemetry>(d));
});
