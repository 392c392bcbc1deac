//! Sampling through the library, for programs that embed dex2hoi rather than call the
//! `dex2hoi` binary: load a trained run, describe the scene and the prompt, generate, and read
//! the motion (here: printed once per second; `dex2hoi-export` writes npz/glTF/BVH/GIF).
//!
//! ```sh
//! cargo xtask demo   # trains target/demo/run, among other things
//! cargo run --release -p dex2hoi-sample --example sample_motion -- target/demo/run \
//!     "The person picks up the mug with the right hand and puts it down." mug
//! ```

use std::num::NonZeroUsize;

use candle_core::Device;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_sample::{
    DEFAULT_TABLE_HEIGHT, Prompt, SampleRequest, SceneObject, TrainedRun, Weights, sample,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let usage = "usage: sample_motion RUN_DIR PROMPT OBJECT [OBJECT]";
    let run_dir = args.next().ok_or(usage)?;
    let prompt = args.next().ok_or(usage)?;
    let mut objects = Vec::new();
    for spec in args {
        objects.push(SceneObject::parse(&spec, None)?);
    }

    // The EMA weights are the ones meant for sampling; any candle device works.
    let run = TrainedRun::load(run_dir.as_ref(), Weights::Ema, &Device::Cpu)?;
    let request = SampleRequest {
        prompts: vec![Prompt { start_frame: 0, text: prompt }],
        objects,
        frames: NonZeroUsize::new(4 * run.manifest.fps as usize).expect("a positive frame rate"),
        seed: 0,
        sampler: SamplerConfig::default(),
        table_height: DEFAULT_TABLE_HEIGHT,
        // As `dex2hoi sample` does: released objects at rest for a model of the procedural data,
        // and windows that carry on from the motion before them.
        free_objects: dex2hoi_sample::rest::FreeObjects::sample_default(&run.manifest.source),
        seams: dex2hoi_sample::seams::Seams::sample_default(),
        progress: None,
    };
    let sampled = sample(&run, &request)?;

    let fps = run.manifest.fps as usize;
    println!("{} frames in {:.1} s; once per second:", sampled.frames, sampled.seconds);
    for frame in (0..sampled.frames).step_by(fps.max(1)) {
        let pelvis = sampled.motion.root_positions[frame];
        let mut line = format!("  t={:4.1}s pelvis {pelvis:.2}", frame as f32 / fps as f32);
        for (slot, object) in &sampled.objects {
            if let Some((_, positions)) = &sampled.motion.objects[*slot] {
                line += &format!("  {} {:.2}", object.name, positions[frame]);
            }
        }
        println!("{line}");
    }
    Ok(())
}
