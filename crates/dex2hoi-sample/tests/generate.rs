//! Autoregressive generation with a (tiny, random) model: window bookkeeping, the prompt
//! timeline, seeding, bad requests, and the prefix rebuilt from its motion.

use candle_core::{DType, Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use glam::{Mat3, Vec3};

use dex2hoi_data::FeatureLayout;
use dex2hoi_data::start::StartPose;
use dex2hoi_diffusion::{CosineSchedule, SamplerConfig, SamplerKind};
use dex2hoi_model::{InferenceModel, Model, ModelConfig, ObjectStart, SeededVarMap};
use dex2hoi_repr::{HandRelativeObject, ObjectPose, Skeleton, SkeletonKind};
use dex2hoi_sample::seams::Seams;
use dex2hoi_sample::{
    Generation, Normaliser, PrefixEncoding, ProgressHook, SampleError, TimedText, WindowProgress,
    generate,
};

fn random(shape: &[usize], rng: &mut ChaCha8Rng) -> Tensor {
    let n: usize = shape.iter().product();
    Tensor::from_vec(
        (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect::<Vec<_>>(),
        shape,
        &Device::Cpu,
    )
    .unwrap()
}

fn tiny_model() -> InferenceModel {
    tiny_model_of(&ModelConfig::tiny())
}

fn tiny_model_of(cfg: &ModelConfig) -> InferenceModel {
    let vars = SeededVarMap::new(0);
    let model = Model::new(cfg, vars.builder(DType::F32, &Device::Cpu)).unwrap();
    // Untrained heads predict zeros; give every parameter a value so the output depends on all
    // inputs.
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let data = vars.var_map().data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        var.set(&random(var.dims(), &mut rng).affine(0.3, 0.0).unwrap()).unwrap();
    }
    InferenceModel::new(&model).unwrap()
}

/// The tiny model, and the same with the prompt clock, the object start and the memory of
/// set-down objects, and with the start or the reach frame in the prefix alone (which a
/// generation must feed each window, or the model refuses it).
#[test]
fn generation_runs_window_by_window_with_a_timeline() {
    let from_prefix = ModelConfig {
        prompt_clock: true,
        object_start: ObjectStart::FromPrefix,
        settled_objects: true,
        ..ModelConfig::tiny()
    };
    let start_token = ModelConfig { start_in_prefix: true, ..ModelConfig::tiny() };
    let reach_token = ModelConfig { reach_in_prefix: true, ..ModelConfig::tiny() };
    for cfg in [ModelConfig::tiny(), from_prefix, start_token, reach_token] {
        runs_window_by_window_with_a_timeline(&tiny_model_of(&cfg));
    }
}

fn runs_window_by_window_with_a_timeline(model: &InferenceModel) {
    let cfg = model.config().clone();
    let d = cfg.stream_features();
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let normaliser = Normaliser {
        mean: random(&[d], &mut rng),
        std: random(&[d], &mut rng).abs().unwrap().affine(1.0, 0.5).unwrap(),
    };
    let first = random(&[1, cfg.text_embedding], &mut rng);
    let second = random(&[1, cfg.text_embedding], &mut rng);
    let base = Generation {
        model,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix: random(&[1, 2, cfg.prefix_frames, d], &mut rng),
        timeline: vec![TimedText { start_frame: 0, embedding: first.clone() }],
        bps: random(&[1, 2, cfg.bps_points * 3], &mut rng),
        presence: Tensor::new(&[[1.0f32, 1.0]], &Device::Cpu).unwrap(),
        frames: std::num::NonZeroUsize::new(25).unwrap(),
        sampler: SamplerConfig {
            kind: SamplerKind::Ddim { eta: 0.0 },
            steps: 5,
            guidance: Some(2.0),
        },
        prefix_encoding: None,
        free_objects: None,
        seams: Default::default(),
        progress: None,
    };
    let run = |request: &Generation<'_>, seed| {
        generate(request, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap()
    };
    let one = run(&base, 3);
    // 25 frames: windows of 8 starting at 0, 8, 16, 24 (the last one cut to a frame).
    assert_eq!(one.dims(), &[1, 2, 25, d]);
    assert_eq!(
        one.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        run(&base, 3).flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
    // A second prompt from frame 16 on changes frames 16.. and nothing before.
    let switched = Generation {
        timeline: vec![
            TimedText { start_frame: 0, embedding: first },
            TimedText { start_frame: 16, embedding: second },
        ],
        ..base.clone()
    };
    let two = run(&switched, 3);
    let slice = |t: &Tensor, from: usize, len: usize| {
        t.narrow(2, from, len).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap()
    };
    assert_eq!(slice(&one, 0, 16), slice(&two, 0, 16));
    assert_ne!(slice(&one, 16, 9), slice(&two, 16, 9));
    // Each later prefix rebuilt from its motion: the first window (made from the initial
    // prefix) is unchanged, the windows after it see another prefix.
    let skeleton = Skeleton::builtin(SkeletonKind::Smplx52);
    let encoding =
        PrefixEncoding { skeleton: &skeleton, root_start: Vec3::Y, present: [true, true] };
    let rebuilt = run(&Generation { prefix_encoding: Some(encoding), ..base.clone() }, 3);
    assert_eq!(rebuilt.dims(), one.dims());
    assert_eq!(slice(&one, 0, 8), slice(&rebuilt, 0, 8));
    assert_ne!(slice(&one, 8, 17), slice(&rebuilt, 8, 17));
    // Bad requests.
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    assert!(generate(&Generation { timeline: vec![], ..base.clone() }, &mut rng).is_err());
    let late = vec![TimedText { start_frame: 5, embedding: base.timeline[0].embedding.clone() }];
    assert!(generate(&Generation { timeline: late, ..base.clone() }, &mut rng).is_err());
    let short_prefix = base.initial_prefix.narrow(2, 0, 2).unwrap();
    assert!(generate(&Generation { initial_prefix: short_prefix, ..base }, &mut rng).is_err());
}

#[test]
fn a_progress_hook_sees_every_window_and_can_stop_the_generation() {
    use std::ops::ControlFlow;
    use std::sync::{Arc, Mutex};

    let model = tiny_model();
    let cfg = model.config().clone();
    let d = cfg.stream_features();
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let normaliser = Normaliser {
        mean: random(&[d], &mut rng),
        std: random(&[d], &mut rng).abs().unwrap().affine(1.0, 0.5).unwrap(),
    };
    let seen = Arc::new(Mutex::new(Vec::new()));
    let record = |stop_after: usize| {
        let seen = Arc::clone(&seen);
        ProgressHook::new(move |progress: WindowProgress| {
            seen.lock().unwrap().push(progress);
            if progress.windows_done >= stop_after {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
    };
    let request = Generation {
        model: &model,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix: random(&[1, 2, cfg.prefix_frames, d], &mut rng),
        timeline: vec![TimedText {
            start_frame: 0,
            embedding: random(&[1, cfg.text_embedding], &mut rng),
        }],
        bps: random(&[1, 2, cfg.bps_points * 3], &mut rng),
        presence: Tensor::new(&[[1.0f32, 0.0]], &Device::Cpu).unwrap(),
        frames: std::num::NonZeroUsize::new(25).unwrap(),
        sampler: SamplerConfig { kind: SamplerKind::Ddim { eta: 0.0 }, steps: 2, guidance: None },
        prefix_encoding: None,
        free_objects: None,
        seams: Default::default(),
        progress: Some(record(usize::MAX)),
    };
    // Windows of 8 frames: 25 frames take 4, the last cut to one frame.
    let whole = generate(&request, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
    let window = |windows_done, frames_done| WindowProgress {
        windows_done,
        windows: 4,
        frames_done,
        frames: 25,
    };
    assert_eq!(*seen.lock().unwrap(), [window(1, 8), window(2, 16), window(3, 24), window(4, 25)]);
    // The hook does not change the motion.
    let unobserved = Generation { progress: None, ..request.clone() };
    let plain = generate(&unobserved, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
    assert_eq!(
        whole.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        plain.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
    // Stopping after the first window: no motion, the error says how far it got.
    seen.lock().unwrap().clear();
    let stopped = Generation { progress: Some(record(1)), ..request };
    match generate(&stopped, &mut ChaCha8Rng::seed_from_u64(3)) {
        Err(SampleError::Interrupted { frames_done: 8, frames: 25 }) => {}
        other => panic!("expected an interruption after 8 of 25 frames, got {other:?}"),
    }
    assert_eq!(*seen.lock().unwrap(), [window(1, 8)]);
}

/// With continuous seams every window's first body frame is where the frames before it lead
/// (the last plus its step), in the unnormalised features the motion decodes from; the paper's
/// sampler jumps there. The first window's objects are the model's own either way.
#[test]
fn continuous_seams_carry_each_window_on_from_the_frames_before_it() {
    let model = tiny_model();
    let cfg = model.config().clone();
    let (d, tp, tf) = (cfg.stream_features(), cfg.prefix_frames, cfg.predicted_frames);
    let body = cfg.layout().body_width();
    let schedule = CosineSchedule::new(1000).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let normaliser = Normaliser {
        mean: random(&[d], &mut rng),
        std: random(&[d], &mut rng).abs().unwrap().affine(1.0, 0.5).unwrap(),
    };
    let request = Generation {
        model: &model,
        schedule: &schedule,
        normaliser: &normaliser,
        initial_prefix: random(&[1, 2, tp, d], &mut rng),
        timeline: vec![TimedText {
            start_frame: 0,
            embedding: random(&[1, cfg.text_embedding], &mut rng),
        }],
        bps: random(&[1, 2, cfg.bps_points * 3], &mut rng),
        presence: Tensor::new(&[[1.0f32, 1.0]], &Device::Cpu).unwrap(),
        frames: std::num::NonZeroUsize::new(3 * tf).unwrap(),
        sampler: SamplerConfig { kind: SamplerKind::Ddim { eta: 0.0 }, steps: 3, guidance: None },
        prefix_encoding: None,
        free_objects: None,
        seams: Seams::Continuous,
        progress: None,
    };
    let with_prefix = |request: &Generation<'_>| {
        let generated = generate(request, &mut ChaCha8Rng::seed_from_u64(6)).unwrap();
        let all = Tensor::cat(&[&request.initial_prefix, &generated], 2).unwrap();
        all.squeeze(0).unwrap().to_vec3::<f32>().unwrap()
    };
    // The worst distance of a window's first body frame from where the two frames before lead.
    let worst_seam = |all: &Vec<Vec<Vec<f32>>>| {
        let mut worst = 0.0f32;
        for stream in all {
            for first in (tp..tp + 3 * tf).step_by(tf) {
                for k in 0..body {
                    let leads_to = 2.0 * stream[first - 1][k] - stream[first - 2][k];
                    worst = worst.max((stream[first][k] - leads_to).abs());
                }
            }
        }
        worst
    };
    let continuous = with_prefix(&request);
    let paper = with_prefix(&Generation { seams: Seams::AsGenerated, ..request.clone() });
    assert!(worst_seam(&continuous) < 1e-4, "{}", worst_seam(&continuous));
    assert!(worst_seam(&paper) > 0.1, "{}", worst_seam(&paper));
    for (a, b) in continuous.iter().zip(&paper) {
        for t in tp..tp + tf {
            assert_eq!(a[t][body..], b[t][body..], "the first window's objects, frame {t}");
        }
    }
}

/// Frames of the standing start with a mug on the table, `[1, 2, frames, D]`, and the layout.
fn standing_frames(frames: usize) -> (Vec<f32>, Vec<f32>, FeatureLayout) {
    let mug =
        ObjectPose { rotation: Mat3::from_rotation_y(0.3), position: Vec3::new(-0.16, 0.95, 0.39) };
    let (body, objects) =
        StartPose::smplx_standing().features(&Skeleton::smplx(), [Some(mug), None]).unwrap();
    let layout = FeatureLayout::new(52);
    (body.repeat(frames), objects.repeat(frames), layout)
}

fn as_tensor(layout: FeatureLayout, body: &[f32], objects: &[f32], frames: usize) -> Tensor {
    let streams = layout.frames_to_streams(body, objects).unwrap();
    Tensor::from_vec(streams, (1, 2, frames, layout.stream_width()), &Device::Cpu).unwrap()
}

#[test]
fn a_rebuilt_prefix_agrees_with_its_motion_in_every_branch() {
    let skeleton = Skeleton::builtin(SkeletonKind::Smplx52);
    let encoding = PrefixEncoding {
        skeleton: &skeleton,
        root_start: StartPose::smplx_standing().root(),
        present: [true, false],
    };
    let frames = 5;
    let (body, objects, layout) = standing_frames(frames);
    // The data's own features already agree: rebuilding them changes nothing that shows.
    let consistent = as_tensor(layout, &body, &objects, frames);
    let again = encoding.rebuild(&consistent, layout).unwrap();
    let difference = (again - &consistent).unwrap().abs().unwrap().max_all().unwrap();
    assert!(difference.to_scalar::<f32>().unwrap() < 1e-5);

    // The right hand holds the mug (its mixture weight near one) while the global branch has
    // sunk 4 cm: the rebuilt global position is where the right hand holds it, and the
    // right-hand offset is kept.
    let mut drifted = objects.clone();
    for t in 0..frames {
        let row = layout.object_row(t, 0);
        let mut o = HandRelativeObject::from_slice(&drifted[row.clone()]).unwrap();
        o.mixture_logits = [-7.0, 7.0, -7.0];
        o.global_position.y -= 0.04;
        drifted[row].copy_from_slice(&o.to_array());
    }
    let rebuilt = encoding.rebuild(&as_tensor(layout, &body, &drifted, frames), layout).unwrap();
    let streams: Vec<f32> = rebuilt.flatten_all().unwrap().to_vec1().unwrap();
    let (rebuilt_body, rebuilt_objects) = layout.streams_to_frames(&streams).unwrap();
    assert_eq!(rebuilt_body, body);
    for t in 0..frames {
        let row = layout.object_row(t, 0);
        let before = HandRelativeObject::from_slice(&objects[row.clone()]).unwrap();
        let held = HandRelativeObject::from_slice(&drifted[row.clone()]).unwrap();
        let after = HandRelativeObject::from_slice(&rebuilt_objects[row]).unwrap();
        assert!((after.global_position - before.global_position).length() < 1e-4, "frame {t}");
        assert!((after.right_offset - held.right_offset).length() < 1e-5, "frame {t}");
        assert_eq!(after.mixture_logits, held.mixture_logits);
    }
}
