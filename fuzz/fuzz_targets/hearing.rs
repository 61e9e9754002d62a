#![no_main]
//! A run's `hearing.bin`: `HearingRecord::decode`, of the input as it is and
//! with its last 4 bytes replaced by the checksum of the others (so that
//! what decodes is also checked past the checksum).

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let decode = |d: &[u8]| formation_record::hearing::HearingRecord::decode(d, "hearing.bin");
    formation_fuzz::check(data, decode);
    if let Some(n) = data.len().checked_sub(4) {
        let mut sealed = data.to_vec();
        let crc = crc32fast::hash(&data[..n]).to_le_bytes();
        sealed[n..].copy_from_slice(&crc);
        formation_fuzz::check(&sealed, decode);
    }
});
