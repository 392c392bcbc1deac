//! Model checkpoints (safetensors): every tensor read, then, when the file parses, the model
//! its metadata configures built from the tensors under `model.`.
#![no_main]

use std::path::Path;

use candle_core::{DType, Device};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("fuzz.safetensors");
    let Ok((tensors, metadata)) =
        dex2hoi_model::checkpoint::read_tensors_from_bytes(data, path, &Device::Cpu)
    else {
        return;
    };
    let _ = dex2hoi_model::Model::from_checkpoint(
        path,
        &tensors,
        &metadata,
        "model.",
        None,
        DType::F32,
        &Device::Cpu,
    );
});
