#![no_main]
//! The start barrier's `Ready` (`control/ready/<node>`).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::codec::decode::<formation_protocol::barrier::Ready>(d));
});
