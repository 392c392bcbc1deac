//! `.npy` parsing, and `.npz` archives (zip, stored or deflated) with every entry read: the first
//! byte picks which.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, bytes)) = data.split_first() else { return };
    if kind % 2 == 0 {
        let _ = dex2hoi_import::npy::parse_npy(bytes, "fuzz.npy");
        return;
    }
    // The archive reader takes a file: one per process, rewritten for each input.
    let path = std::env::temp_dir().join(format!("dex2hoi-fuzz-{}.npz", std::process::id()));
    if std::fs::write(&path, bytes).is_err() {
        return;
    }
    if let Ok(mut archive) = dex2hoi_import::npy::Npz::open(&path) {
        for name in archive.names() {
            let _ = archive.read(&name, "an array");
        }
    }
});
