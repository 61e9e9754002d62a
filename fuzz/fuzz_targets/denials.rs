#![no_main]
//! Access-control denial reports (JSON, `control/denied/<node>`), as the
//! monitor files them: `denials::Table::file`, on the router's key.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    formation_fuzz::check(data, |d| formation_protocol::denied::Table::default().file("router", d));
});
