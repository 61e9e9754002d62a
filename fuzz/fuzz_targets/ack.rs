#![no_main]
//! The monitor's acknowledgements (`control/ack`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::codec::decode::<formation_protocol::telemetry::Ack>(d));
});
