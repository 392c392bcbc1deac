//! Sampling a trained run from a request: the scene's objects placed, BPS computed on the fly
//! with the run's basis, the starting state (standing, nobody holding anything), a prompt
//! timeline, autoregressive generation and decoding to joint rotations, FK and object poses.

use std::num::NonZeroUsize;
use web_time::Instant;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::DecodedMotion;
use dex2hoi_data::start::StartPose;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_model::text::reject_empty;
use dex2hoi_repr::{BpsBasis, MeshQuery, ObjectPose};

use crate::error::{Result, SampleError};
use crate::generate::{Conditioning, ProgressHook, generate_motion};
use crate::rest::{FreeObjects, ObjectsAtRest};
use crate::run::TrainedRun;
use crate::scene::{
    DEFAULT_OBJECT_DEPTH, SceneObject, default_lone_object_side, default_pair_sides,
};
use crate::seams::Seams;
use crate::timeline::Prompt;

/// What to generate.
#[derive(Debug, Clone)]
pub struct SampleRequest {
    /// Prompts by start frame (the first at frame 0).
    pub prompts: Vec<Prompt>,
    /// One or two objects (slot A, then slot B).
    pub objects: Vec<SceneObject>,
    /// Frames to generate.
    pub frames: NonZeroUsize,
    /// Seed of the noise.
    pub seed: u64,
    /// Sampler (DDIM steps, guidance).
    pub sampler: SamplerConfig,
    /// Table height for the default places.
    pub table_height: f32,
    /// What happens to the objects no hand holds ([`crate::rest`]).
    pub free_objects: FreeObjects,
    /// How each window joins the frames before it ([`crate::seams`]).
    pub seams: Seams,
    /// Called after each generated window: progress, and a way to stop early
    /// ([`SampleError::Interrupted`]); `None` runs the generation to its end.
    pub progress: Option<ProgressHook>,
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

/// The prefix a generation from scratch starts from: `start` on the run's skeleton with the
/// objects at `placed` and nobody holding them, held over the run's prefix frames, as
/// unnormalised stream features `[2, T_p, D]` flattened; its root displacement is measured from
/// [`StartPose::root`].
pub fn standing_prefix(
    run: &TrainedRun,
    start: &StartPose,
    placed: [Option<ObjectPose>; MAX_OBJECTS],
) -> Result<Vec<f32>> {
    let config = &run.config.model;
    let (body_row, object_rows) = start.features(&run.skeleton, placed)?;
    Ok(config.layout().frames_to_streams(
        &body_row.repeat(config.prefix_frames),
        &object_rows.repeat(config.prefix_frames),
    )?)
}

/// Generates a motion with a trained run.
pub fn sample(run: &TrainedRun, request: &SampleRequest) -> Result<SampledMotion> {
    let started = Instant::now();
    if request.objects.is_empty() || request.objects.len() > MAX_OBJECTS {
        return Err(SampleError::invalid(
            "request",
            "objects",
            format!("one or two objects (the model takes at most {MAX_OBJECTS})"),
            request.objects.len(),
        ));
    }
    let texts: Vec<&str> = request.prompts.iter().map(|p| p.text.as_str()).collect();
    reject_empty(&texts)?;
    let config = &run.config.model;
    let first_prompt = request.prompts.first().map_or("", |p| p.text.as_str());
    let places: Vec<(f32, f32)> = if let [one, other] = request.objects.as_slice() {
        default_pair_sides(first_prompt, [one.name.as_str(), other.name.as_str()])
            .map(|side| (side, DEFAULT_OBJECT_DEPTH))
            .to_vec()
    } else {
        vec![(default_lone_object_side(first_prompt), DEFAULT_OBJECT_DEPTH)]
    };
    let mut poses = [None; MAX_OBJECTS];
    let mut present = [false; MAX_OBJECTS];
    let bps_basis =
        BpsBasis::new(run.manifest.bps.points, run.manifest.bps.radius, run.manifest.bps.seed)?;
    let mut bps = vec![0.0f32; MAX_OBJECTS * config.bps_points * 3];
    let mut queries: [Option<MeshQuery>; MAX_OBJECTS] = [None, None];
    for (slot, object) in request.objects.iter().enumerate() {
        poses[slot] = Some(object.start_pose(places[slot], request.table_height));
        present[slot] = true;
        let query: &MeshQuery = queries[slot].insert(MeshQuery::new(&object.mesh)?);
        let features = bps_basis.encode_flat(query);
        if features.len() != config.bps_points * 3 {
            return Err(SampleError::invalid(
                "run",
                "bps_points",
                format!("{} BPS numbers", config.bps_points * 3),
                features.len(),
            ));
        }
        bps[slot * config.bps_points * 3..(slot + 1) * config.bps_points * 3]
            .copy_from_slice(&features);
    }
    let start = run.manifest.start_pose()?;
    let prefix = standing_prefix(run, &start, poses)?;
    let prompts: Vec<(usize, &str)> =
        request.prompts.iter().map(|p| (p.start_frame, p.text.as_str())).collect();
    let generated = generate_motion(
        run,
        &Conditioning {
            prefix,
            bps,
            present,
            prompts,
            root_start: start.root(),
            skeleton: &run.skeleton,
            free_objects: (request.free_objects == FreeObjects::AtRest)
                .then(|| ObjectsAtRest { meshes: queries.each_ref().map(Option::as_ref) }),
            seams: request.seams,
            progress: request.progress.clone(),
        },
        request.frames,
        request.seed,
        request.sampler,
    )?;
    let motion = generated.motion;
    let frames = request.frames.get();
    Ok(SampledMotion {
        motion,
        objects: request.objects.iter().cloned().enumerate().collect(),
        frames,
        seconds: started.elapsed().as_secs_f64(),
    })
}
