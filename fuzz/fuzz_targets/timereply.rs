#![no_main]
//! The leader's clock replies (`control/time`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::codec::decode::<formation_net::clock_sync::TimeReply>(d));
});
