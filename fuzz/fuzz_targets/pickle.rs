//! The bounded, data-only pickle reader on arbitrary bytes: it must return a value or an error,
//! never panic, hang or allocate without bound.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = dex2hoi_import::pickle::read_pickle(data, "fuzz.pkl");
});
