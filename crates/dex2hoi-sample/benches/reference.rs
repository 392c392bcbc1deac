//! Writes what the PyTorch reference (`bench/torch_reference.py`) needs to check that it does
//! the same work as dex2hoi: for the `small` and `paper` presets, the seeded parameters with
//! the zero-initialised ones randomised (see `SeededVarMap::randomise_zero_parameters`), one
//! batch of inputs and dex2hoi's output for it, in `target/bench/reference/{preset}.safetensors`
//! (parameters under `model.`, inputs under `input.`, the output as `output`). Run by
//! `cargo xtask bench compare` before the reference.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_diffusion::gaussian;
use dex2hoi_model::{Model, ModelConfig, ModelInput, SeededVarMap};

fn main() {
    let device = Device::Cpu;
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/bench/reference");
    std::fs::create_dir_all(&dir).expect("target/bench/reference");
    for preset in ["small", "paper"] {
        let cfg = ModelConfig::preset(preset).expect("a preset");
        let vars = SeededVarMap::new(0);
        let model = Model::new(&cfg, vars.builder(DType::F32, &device)).expect("a model");
        vars.randomise_zero_parameters(1).expect("randomised parameters");
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let batch = 2;
        let d = cfg.stream_features();
        let mut random = |shape: &[usize]| gaussian(shape, &mut rng, DType::F32, &device).unwrap();
        let noisy = random(&[batch, 2, cfg.predicted_frames, d]);
        let prefix = random(&[batch, 2, cfg.prefix_frames, d]);
        let text = random(&[batch, cfg.text_embedding]);
        let bps = random(&[batch, 2, cfg.bps_points * 3]);
        // The second sample has one object: the empty slot's path is exercised too.
        let presence = Tensor::new(&[[1f32, 1.0], [1.0, 0.0]], &device).unwrap();
        let timesteps = Tensor::new(&[37u32, 612], &device).unwrap();
        let input = ModelInput {
            noisy: &noisy,
            prefix: &prefix,
            timesteps: &timesteps,
            text: &text,
            bps: &bps,
            presence: &presence,
            frame_mask: None,
            elapsed: None,
            object_start: None,
            settled: None,
            reach: None,
        };
        let output = model.forward(&input, None).expect("a forward pass");
        let mut tensors: HashMap<String, Tensor> = HashMap::new();
        for (name, var) in vars.var_map().data().lock().unwrap().iter() {
            tensors.insert(format!("model.{name}"), var.as_tensor().clone());
        }
        for (name, t) in [
            ("noisy", &noisy),
            ("prefix", &prefix),
            ("text", &text),
            ("bps", &bps),
            ("presence", &presence),
        ] {
            tensors.insert(format!("input.{name}"), t.clone());
        }
        tensors.insert("input.timesteps".into(), timesteps.to_dtype(DType::F32).unwrap());
        tensors.insert("output".into(), output);
        let path = dir.join(format!("{preset}.safetensors"));
        let temporary = dir.join(format!("{preset}.safetensors.tmp"));
        candle_core::safetensors::save(&tensors, &temporary).expect("writing the reference");
        std::fs::rename(&temporary, &path).expect("renaming the reference");
        println!("wrote {} ({} parameters)", path.display(), tensors.len() - 7);
    }
}
