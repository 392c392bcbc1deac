//! HUMOTO's per-sequence YAML text files: the top-level text values.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let _ = dex2hoi_import::yaml::top_level_text(text, "fuzz.yaml");
});
