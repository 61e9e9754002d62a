#![no_main]
//! Estimate messages (`formation/<run>/estimate/<id>`): `formation_protocol::wire::decode`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::wire::decode(d));
});
