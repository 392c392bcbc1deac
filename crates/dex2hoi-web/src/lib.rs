//! dex2hoi in a web page: a packed model's sampling path and the exporters behind one small
//! API, compiled to WebAssembly by `cargo xtask web` for a static page that generates motions
//! on the visitor's own CPU, with no server.
//!
//! [`WebGenerator::generate`] does what `dex2hoi sample` does with its defaults (the same
//! sampler, table, object places and seed stream, so the same prompt, objects and seed give
//! the same joints) and hands back, in memory, `motion.glb`, `motion.npz` and `motion.bvh`,
//! the joints' world positions and the hands' contact states for the page's view. The
//! WebAssembly bindings (`wasm` module, built for `wasm32` only) wrap exactly this API, so
//! native tests cover everything but the bindings.
//!
//! ```no_run
//! use dex2hoi_web::{WebGenerator, WebObject, WebRequest};
//!
//! let model = std::fs::read("crates/dex2hoi-cli/model/dex2hoi-demo.safetensors")?;
//! let generator = WebGenerator::from_model_bytes(&model)?;
//! let request = WebRequest {
//!     prompt: "The person picks up the mug with the right hand.",
//!     objects: vec![WebObject::Named("mug")],
//!     seed: 0,
//!     frames: 160,
//! };
//! let motion = generator.generate(&request, None)?;
//! std::fs::write("motion.glb", &motion.glb)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod error;
#[cfg(target_arch = "wasm32")]
mod wasm;

use std::num::NonZeroUsize;
use std::path::Path;

use candle_core::Device;

use dex2hoi_data::catalogue::CATALOGUE;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_export::{ExportMotion, ExportObject, JointState, encode_bvh, encode_glb, encode_npz};
use dex2hoi_sample::rest::FreeObjects;
use dex2hoi_sample::seams::Seams;
use dex2hoi_sample::{
    DEFAULT_TABLE_HEIGHT, ProgressHook, Prompt, SampleRequest, SceneObject, SceneTable, TrainedRun,
    Weights, sample, unknown_words_warning,
};

pub use error::{Result, WebError};

/// The longest motion a page generates (seconds): a minute of motion takes a few tens of
/// megabytes of exports in the page's memory; longer ones are for `dex2hoi sample`.
pub const MAX_SECONDS: f32 = 60.0;

/// The names of the built-in object catalogue, as [`WebObject::Named`] takes them.
pub fn catalogue_names() -> Vec<String> {
    CATALOGUE.iter().map(|o| o.name.to_string()).collect()
}

/// A model loaded for generating in a page.
#[derive(Debug)]
pub struct WebGenerator {
    run: TrainedRun,
}

/// An object of a request.
#[derive(Debug, Clone, Copy)]
pub enum WebObject<'a> {
    /// A catalogue name, optionally placed (`mug@x,y,z`), as `dex2hoi sample --object` takes
    /// it.
    Named(&'a str),
    /// An `.obj` or `.ply` file's bytes (by the extension of its name), from the visitor's
    /// disk.
    File {
        /// The file's name.
        file_name: &'a str,
        /// Its bytes.
        bytes: &'a [u8],
    },
}

/// What to generate.
#[derive(Debug, Clone)]
pub struct WebRequest<'a> {
    /// The prompt.
    pub prompt: &'a str,
    /// One or two objects (slot A, then slot B).
    pub objects: Vec<WebObject<'a>>,
    /// Seed of the noise: the same seed gives the same motion.
    pub seed: u64,
    /// Frames to generate, at the model's frame rate.
    pub frames: usize,
}

/// A generated motion, its exports and what the page's view draws.
#[derive(Debug, Clone)]
pub struct WebMotion {
    /// `motion.glb` (glTF binary: skinned body, objects, one animation).
    pub glb: Vec<u8>,
    /// `motion.npz` (numpy arrays, `docs/FORMATS.md`).
    pub npz: Vec<u8>,
    /// `motion.bvh`.
    pub bvh: String,
    /// Frames generated.
    pub frames: usize,
    /// Joints of the skeleton.
    pub joint_count: usize,
    /// Frames per second.
    pub fps: f32,
    /// Seconds the generation took (without the exports).
    pub seconds: f64,
    /// World positions of the joints (metres, Y up), `[frames * joints * 3]`: `joints` of
    /// `motion.npz`.
    pub joints: Vec<f32>,
    /// How each joint meets the objects on each frame, `[frames * joints]`: 0 free, 1 in
    /// contact, 2 inside (only hand joints are ever not free), as the preview colours them.
    pub hand_contacts: Vec<u8>,
    /// The table the objects stand on, when one does.
    pub table: Option<SceneTable>,
}

impl WebGenerator {
    /// Loads a packed model file (`dex2hoi model pack`) from its bytes.
    pub fn from_model_bytes(bytes: &[u8]) -> Result<Self> {
        let run = TrainedRun::from_model_bytes(
            bytes,
            Path::new("<the page's model>"),
            Weights::Ema,
            &Device::Cpu,
        )?;
        Ok(Self { run })
    }

    /// The model's frame rate.
    pub fn fps(&self) -> f32 {
        self.run.manifest.fps
    }

    /// The most frames a request may ask for ([`MAX_SECONDS`] at the model's frame rate).
    pub fn max_frames(&self) -> usize {
        (MAX_SECONDS * self.fps()).floor() as usize
    }

    /// The words the model's text encoder knows, sorted; empty for a frozen encoder (which
    /// reads any word).
    pub fn words(&self) -> Vec<String> {
        self.run.text.vocabulary().map(|v| v.words().to_vec()).unwrap_or_default()
    }

    /// The warning for the words of `prompt` the model never saw, as `dex2hoi sample` prints
    /// it; `None` when it knows them all.
    pub fn unknown_words_warning(&self, prompt: &str) -> Option<String> {
        let vocabulary = self.run.text.vocabulary()?;
        unknown_words_warning(&vocabulary.unknown_words(prompt))
    }

    /// Generates a motion and its exports; `progress` runs after each window and can stop the
    /// generation.
    pub fn generate(
        &self,
        request: &WebRequest<'_>,
        progress: Option<ProgressHook>,
    ) -> Result<WebMotion> {
        if request.prompt.trim().is_empty() {
            return Err(WebError::invalid("prompt", "what the person does", "an empty prompt"));
        }
        let frames = NonZeroUsize::new(request.frames)
            .filter(|f| f.get() <= self.max_frames())
            .ok_or_else(|| {
                WebError::invalid(
                    "length",
                    format!("1 to {} frames ({MAX_SECONDS} s)", self.max_frames()),
                    request.frames,
                )
            })?;
        let objects = request
            .objects
            .iter()
            .map(|object| match *object {
                WebObject::Named(spec) => Ok(SceneObject::parse(spec, None)?),
                WebObject::File { file_name, bytes } => {
                    Ok(SceneObject::from_mesh_bytes(bytes, file_name, None)?)
                }
            })
            .collect::<Result<Vec<_>>>()?;
        let prompts = vec![Prompt { start_frame: 0, text: request.prompt.to_string() }];
        let sampled = sample(
            &self.run,
            &SampleRequest {
                prompts: prompts.clone(),
                objects,
                frames,
                seed: request.seed,
                sampler: SamplerConfig::default(),
                table_height: DEFAULT_TABLE_HEIGHT,
                free_objects: FreeObjects::sample_default(&self.run.manifest.source),
                seams: Seams::sample_default(),
                progress,
            },
        )?;
        let export = ExportMotion {
            skeleton: &self.run.skeleton,
            fps: self.fps(),
            prompts: prompts.into_iter().map(|p| (p.start_frame, p.text)).collect(),
            motion: &sampled.motion,
            objects: sampled
                .objects
                .iter()
                .map(|(slot, o)| ExportObject { name: o.name.clone(), mesh: &o.mesh, slot: *slot })
                .collect(),
            body: None,
        };
        let joints = export.joint_positions()?.iter().flat_map(|p| p.to_array()).collect();
        let hand_contacts = export
            .hand_contacts()?
            .into_iter()
            .map(|state| match state {
                JointState::Free => 0,
                JointState::Contact => 1,
                JointState::Inside => 2,
            })
            .collect();
        Ok(WebMotion {
            glb: encode_glb(&export)?,
            npz: encode_npz(&export)?,
            bvh: encode_bvh(&export)?,
            frames: sampled.frames,
            joint_count: self.run.skeleton.joint_count(),
            fps: self.fps(),
            seconds: sampled.seconds,
            joints,
            hand_contacts,
            table: SceneTable::under(&sampled.objects, DEFAULT_TABLE_HEIGHT),
        })
    }
}
