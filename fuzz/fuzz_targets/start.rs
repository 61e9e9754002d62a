#![no_main]
//! The leader's `Start` (`control/start`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::codec::decode::<formation_protocol::barrier::Start>(d));
});
