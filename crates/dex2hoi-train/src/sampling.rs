//! Sampling a trained run: objects from the catalogue or the user's meshes placed on a table,
//! BPS computed on the fly with the run's basis, the starting state (standing, nobody holding
//! anything), a prompt timeline, autoregressive generation with the EMA weights
//! (`dex2hoi_diffusion::generate`) and decoding to joint rotations, FK and object poses.

use std::path::Path;
use std::time::Instant;

use candle_core::{Device, Tensor};
use glam::{Mat3, Vec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{DecodedMotion, OBJECT_FEATURE_SIZE, ObjectDecoding, decode_features};
use dex2hoi_data::synth::{PELVIS_HEIGHT, catalogue::catalogue_object, standing_features};
use dex2hoi_diffusion::{CosineSchedule, Generation, SamplerConfig, TimedText, generate};
use dex2hoi_model::ObjectRepresentation;
use dex2hoi_model::text::reject_empty;
use dex2hoi_repr::{BpsBasis, Mesh, MeshQuery, ObjectPose};

use crate::error::{Result, TrainError};
use crate::run::TrainedRun;

/// Height of the default table top (the middle of the procedural dataset's 0.86-0.94 m).
pub const DEFAULT_TABLE_HEIGHT: f32 = 0.90;
/// Distance of the default object places in front of the character (metres along +Z).
pub const DEFAULT_OBJECT_DEPTH: f32 = 0.39;
/// Sideways distance of each object when there are two (metres along X; the left hand is +X).
pub const DEFAULT_OBJECT_SIDE: f32 = 0.16;
/// The default table's near edge (metres along +Z), for previews.
pub const DEFAULT_TABLE_NEAR_EDGE: f32 = 0.25;

/// An object of the scene: a name, a mesh centred on its bounding box, and where it stands.
#[derive(Debug, Clone)]
pub struct SceneObject {
    /// Name (catalogue name or file stem).
    pub name: String,
    /// Mesh, centred on its bounding box.
    pub mesh: Mesh,
    /// Where the object frame's origin is at the start; `None` puts it on the table.
    pub position: Option<Vec3>,
}

impl SceneObject {
    /// An object from a specification: a catalogue name (`mug`) or an OBJ/PLY file, optionally
    /// followed by `@x,y,z` (metres, character frame: +Z ahead, +X to the left, +Y up).
    pub fn parse(spec: &str) -> Result<Self> {
        let (what, position) = match spec.split_once('@') {
            Some((what, at)) => {
                let values: Vec<f32> = at
                    .split(',')
                    .map(|v| v.trim().parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| TrainError::config("--object", spec, "NAME@x,y,z in metres", e))?;
                if values.len() != 3 || values.iter().any(|v| !v.is_finite()) {
                    return Err(TrainError::config(
                        "--object",
                        spec,
                        "three finite numbers after @",
                        at,
                    ));
                }
                (what, Some(Vec3::new(values[0], values[1], values[2])))
            }
            None => (spec, None),
        };
        let what = what.trim();
        if let Some(object) = catalogue_object(what) {
            return Ok(Self { name: object.name.to_string(), mesh: object.mesh(), position });
        }
        let path = Path::new(what);
        let is_mesh = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("obj") || e.eq_ignore_ascii_case("ply"));
        if !is_mesh {
            let names: Vec<&str> =
                dex2hoi_data::synth::catalogue::CATALOGUE.iter().map(|o| o.name).collect();
            return Err(TrainError::config(
                "--object",
                what,
                format!("a catalogue object ({}) or an .obj/.ply file", names.join(", ")),
                "neither",
            ));
        }
        let mut mesh = Mesh::load(path)?;
        mesh.recenter();
        let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("object").to_string();
        Ok(Self { name, mesh, position })
    }

    /// The starting pose: the given position, or standing on the table at `default_place`.
    fn start_pose(&self, default_place: (f32, f32), table_height: f32) -> ObjectPose {
        let (low, high) = self.mesh.bounding_box();
        let position = self.position.unwrap_or_else(|| {
            Vec3::new(default_place.0, table_height + (high.y - low.y) / 2.0, default_place.1)
        });
        ObjectPose { rotation: Mat3::IDENTITY, position }
    }
}

/// A prompt that applies from a frame on.
#[derive(Debug, Clone, PartialEq)]
pub struct Prompt {
    /// First frame (counted from the first generated frame).
    pub start_frame: usize,
    /// The text.
    pub text: String,
}

/// Reads a timeline: one prompt per line, `SECONDS TEXT` (the first at 0, increasing; blank
/// lines and lines starting with `#` are skipped).
pub fn parse_timeline(text: &str, fps: f32, source_name: &str) -> Result<Vec<Prompt>> {
    let mut prompts: Vec<Prompt> = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |expected: &str| {
            TrainError::config(source_name, format!("line {}", n + 1), expected, line)
        };
        let (seconds, prompt) =
            line.split_once(char::is_whitespace).ok_or_else(|| bad("SECONDS TEXT"))?;
        let seconds: f32 =
            seconds.parse().map_err(|_| bad("a start time in seconds, then the text"))?;
        if !(seconds >= 0.0 && seconds.is_finite()) {
            return Err(bad("a non-negative start time"));
        }
        let start_frame = (seconds * fps).round() as usize;
        if prompts.last().is_some_and(|p| p.start_frame >= start_frame) {
            return Err(bad("start times that increase"));
        }
        if prompts.is_empty() && start_frame != 0 {
            return Err(bad("the first prompt at 0 seconds"));
        }
        prompts.push(Prompt { start_frame, text: prompt.trim().to_string() });
    }
    if prompts.is_empty() {
        return Err(TrainError::config(source_name, "timeline", "at least one prompt", "none"));
    }
    Ok(prompts)
}

/// What to generate.
#[derive(Debug, Clone)]
pub struct SampleRequest {
    /// Prompts by start frame (the first at frame 0).
    pub prompts: Vec<Prompt>,
    /// One or two objects (slot A, then slot B).
    pub objects: Vec<SceneObject>,
    /// Frames to generate.
    pub frames: usize,
    /// Seed of the noise.
    pub seed: u64,
    /// Sampler (DDIM steps, guidance).
    pub sampler: SamplerConfig,
    /// Table height for the default places.
    pub table_height: f32,
}

/// A generated motion.
#[derive(Debug, Clone)]
pub struct SampledMotion {
    /// Rotations, positions and object poses.
    pub motion: DecodedMotion,
    /// The objects with their slots.
    pub objects: Vec<(usize, SceneObject)>,
    /// Frames generated.
    pub frames: usize,
    /// Seconds the generation took (without loading).
    pub seconds: f64,
}

/// Generates a motion with a trained run.
pub fn sample(run: &TrainedRun, request: &SampleRequest) -> Result<SampledMotion> {
    let started = Instant::now();
    if request.objects.is_empty() || request.objects.len() > MAX_OBJECTS {
        return Err(TrainError::config(
            "--object",
            "objects",
            format!("one or two objects (the model takes at most {MAX_OBJECTS})"),
            request.objects.len(),
        ));
    }
    if request.frames == 0 {
        return Err(TrainError::config("--frames", "frames", "at least 1", 0));
    }
    let texts: Vec<&str> = request.prompts.iter().map(|p| p.text.as_str()).collect();
    reject_empty(&texts)?;
    let config = &run.config.model;
    let places: Vec<(f32, f32)> = if request.objects.len() == 1 {
        vec![(0.0, DEFAULT_OBJECT_DEPTH)]
    } else {
        vec![
            (DEFAULT_OBJECT_SIDE, DEFAULT_OBJECT_DEPTH),
            (-DEFAULT_OBJECT_SIDE, DEFAULT_OBJECT_DEPTH),
        ]
    };
    let mut poses = [None; MAX_OBJECTS];
    let mut present = [false; MAX_OBJECTS];
    let bps_basis =
        BpsBasis::new(run.manifest.bps.points, run.manifest.bps.radius, run.manifest.bps.seed)?;
    let mut bps = vec![0.0f32; MAX_OBJECTS * config.bps_points * 3];
    for (slot, object) in request.objects.iter().enumerate() {
        poses[slot] = Some(object.start_pose(places[slot], request.table_height));
        present[slot] = true;
        let query = MeshQuery::new(&object.mesh)?;
        let features = bps_basis.encode_flat(&query);
        if features.len() != config.bps_points * 3 {
            return Err(TrainError::config(
                "run",
                "bps_points",
                format!("{} BPS numbers", config.bps_points * 3),
                features.len(),
            ));
        }
        bps[slot * config.bps_points * 3..(slot + 1) * config.bps_points * 3]
            .copy_from_slice(&features);
    }
    let (body_row, object_rows) = standing_features(poses)?;
    let width = config.stream_features();
    let mut prefix = Vec::with_capacity(MAX_OBJECTS * config.prefix_frames * width);
    for slot in 0..MAX_OBJECTS {
        for _ in 0..config.prefix_frames {
            prefix.extend_from_slice(&body_row);
            prefix.extend_from_slice(
                &object_rows[slot * OBJECT_FEATURE_SIZE..(slot + 1) * OBJECT_FEATURE_SIZE],
            );
        }
    }
    let prompts: Vec<(usize, &str)> =
        request.prompts.iter().map(|p| (p.start_frame, p.text.as_str())).collect();
    let generated = generate_motion(
        run,
        &Conditioning {
            prefix,
            bps,
            present,
            prompts,
            root_start: Vec3::new(0.0, PELVIS_HEIGHT, 0.0),
        },
        request.frames,
        request.seed,
        request.sampler,
    )?;
    let motion = generated.motion;
    let frames = request.frames;
    Ok(SampledMotion {
        motion,
        objects: request.objects.iter().cloned().enumerate().collect(),
        frames,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// What a generation is conditioned on besides the model.
#[derive(Debug, Clone)]
pub struct Conditioning<'a> {
    /// The initial prefix, unnormalised features `[2, T_p, D]` flattened (stream A then B); its
    /// root displacement is measured from the canonical start (`r = 0` stands at the origin).
    pub prefix: Vec<f32>,
    /// BPS per slot, `[2, P * 3]` flattened (zeros for an empty slot).
    pub bps: Vec<f32>,
    /// Which slots hold an object.
    pub present: [bool; MAX_OBJECTS],
    /// Prompts by start frame (the first at 0).
    pub prompts: Vec<(usize, &'a str)>,
    /// The root position the prefix's root displacement is measured from.
    pub root_start: Vec3,
}

/// A generated motion with its features.
#[derive(Debug, Clone)]
pub struct GeneratedMotion {
    /// Decoded rotations, FK and object poses.
    pub motion: DecodedMotion,
    /// The unnormalised features of both streams, `[2, frames, D]` flattened.
    pub features: Vec<f32>,
    /// Seconds the generation took.
    pub seconds: f64,
}

/// Generates `frames` frames after a prefix with a trained run (the weights it was loaded
/// with) and decodes them, the root measured from the conditioning's `root_start`.
pub fn generate_motion(
    run: &TrainedRun,
    conditioning: &Conditioning<'_>,
    frames: usize,
    seed: u64,
    sampler: SamplerConfig,
) -> Result<GeneratedMotion> {
    let started = Instant::now();
    let device = Device::Cpu;
    let config = &run.config.model;
    let (width, body) = (config.stream_features(), config.body_features());
    let bps_width = config.bps_points * 3;
    if conditioning.prefix.len() != MAX_OBJECTS * config.prefix_frames * width
        || conditioning.bps.len() != MAX_OBJECTS * bps_width
    {
        return Err(TrainError::config(
            "generation",
            "conditioning",
            format!("a [2, {}, {width}] prefix and [2, {bps_width}] BPS", config.prefix_frames),
            format!("{} and {} numbers", conditioning.prefix.len(), conditioning.bps.len()),
        ));
    }
    if frames == 0 {
        return Err(TrainError::config("generation", "frames", "at least 1", 0));
    }
    let texts: Vec<&str> = conditioning.prompts.iter().map(|p| p.1).collect();
    reject_empty(&texts)?;
    let initial_prefix = Tensor::from_vec(
        conditioning.prefix.clone(),
        (1, MAX_OBJECTS, config.prefix_frames, width),
        &device,
    )?;
    let timeline = conditioning
        .prompts
        .iter()
        .map(|&(start_frame, text)| {
            Ok(TimedText { start_frame, embedding: run.text.encode(&[text])? })
        })
        .collect::<Result<Vec<_>>>()?;
    let presence: Vec<f32> = conditioning.present.iter().map(|&p| f32::from(u8::from(p))).collect();
    let schedule = CosineSchedule::new(run.config.training.diffusion_steps)?;
    let normaliser = run.normaliser(&device)?;
    let generation = Generation {
        model: &run.model,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix,
        timeline,
        bps: Tensor::from_vec(conditioning.bps.clone(), (1, MAX_OBJECTS, bps_width), &device)?,
        presence: Tensor::from_vec(presence, (1, MAX_OBJECTS), &device)?,
        frames,
        sampler,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let features: Vec<f32> = generate(&generation, &mut rng)?.flatten_all()?.to_vec1()?;
    let mut body_features = Vec::with_capacity(frames * body);
    let mut object_features = vec![0.0f32; frames * MAX_OBJECTS * OBJECT_FEATURE_SIZE];
    for t in 0..frames {
        body_features.extend_from_slice(&features[t * width..t * width + body]);
        for s in 0..MAX_OBJECTS {
            let row = &features[(s * frames + t) * width..(s * frames + t + 1) * width];
            object_features[(t * MAX_OBJECTS + s) * OBJECT_FEATURE_SIZE..][..OBJECT_FEATURE_SIZE]
                .copy_from_slice(&row[body..]);
        }
    }
    let decoding = match config.object_representation {
        ObjectRepresentation::HandRelative => ObjectDecoding::Mixture,
        ObjectRepresentation::GlobalOnly => ObjectDecoding::GlobalOnly,
    };
    let motion = decode_features(
        &run.skeleton,
        &body_features,
        &object_features,
        conditioning.present,
        conditioning.root_start,
        decoding,
    )?;
    Ok(GeneratedMotion { motion, features, seconds: started.elapsed().as_secs_f64() })
}
