//! The text-motion evaluator and action classifier: training on the procedural dataset lowers
//! the loss and retrieves and classifies well above chance, gradients match finite differences,
//! files round-trip, datasets and files that do not fit are refused, and the seed decides the
//! weights.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor};

use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::{ObjectDecoding, decode_features};
use dex2hoi_eval::EvalError;
use dex2hoi_eval::evaluator::{
    EVALUATOR_FILE, Evaluator, EvaluatorConfig, MotionClip, STATS_FILE, train_evaluator,
};
use dex2hoi_optim::step_rng;

fn dataset() -> &'static Dataset {
    static DATA: OnceLock<Dataset> = OnceLock::new();
    DATA.get_or_init(|| {
        dex2hoi_synth::build_dataset(48, 7, 20.0, &|_| {}).expect("a procedural dataset")
    })
}

fn data_path() -> PathBuf {
    PathBuf::from("procedural-dataset")
}

fn temporary(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dex2hoi-eval-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

fn tiny(steps: usize) -> EvaluatorConfig {
    EvaluatorConfig {
        latent: 32,
        layers: 1,
        heads: 4,
        clip_frames: 30,
        embedding: 32,
        steps,
        batch_size: 32,
        learning_rate: 3e-3,
        warmup_steps: 20,
        ..EvaluatorConfig::default()
    }
}

fn train_split() -> &'static [dex2hoi_data::features::ProcessedSequence] {
    &dataset().splits[&Split::Train]
}

fn first_texts() -> Vec<&'static str> {
    train_split().iter().map(|s| s.texts[0].as_str()).collect()
}

fn values(evaluator: &Evaluator) -> Vec<(String, Vec<f32>)> {
    evaluator
        .parameters()
        .into_iter()
        .map(|p| {
            let v = p.var.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            (p.name, v)
        })
        .collect()
}

#[test]
fn training_lowers_the_loss_retrieves_and_classifies_above_chance_and_round_trips() {
    let mut losses = Vec::new();
    let evaluator =
        train_evaluator(dataset(), &data_path(), &tiny(150), &Device::Cpu, &mut |_, loss| {
            losses.push(loss)
        })
        .unwrap();
    assert_eq!(losses.len(), 150);
    let summary = evaluator.training().unwrap().clone();
    assert!(
        summary.final_loss < 0.5 * summary.first_loss,
        "the loss fell from {} to {}",
        summary.first_loss,
        summary.final_loss
    );
    assert_eq!(evaluator.labels().len(), 8, "{:?}", evaluator.labels());

    let windows = evaluator.evaluation_windows(train_split()).unwrap();
    let retrieval = evaluator.retrieval(&windows, &first_texts(), 32).unwrap();
    assert_eq!(retrieval.batch, 32);
    assert!(retrieval.top1 > 0.25, "top-1 retrieval {} against chance 1/32", retrieval.top1);
    let labels: Vec<&str> = train_split().iter().map(|s| s.action.as_deref().unwrap()).collect();
    let accuracy = evaluator.classification_accuracy(&windows, &labels).unwrap();
    assert!(accuracy > 0.4, "action accuracy {accuracy} against chance 1/8");

    // Embeddings are unit vectors; features have the latent width.
    let motion = evaluator.embed_motions(&windows[..5]).unwrap();
    let texts = evaluator.embed_texts(&first_texts()[..5]).unwrap();
    for row in motion.iter().chain(&texts) {
        assert_eq!(row.len(), 32);
        let norm: f32 = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-4, "{norm}");
    }
    let features = evaluator.action_features(&windows[..5]).unwrap();
    assert!(features.iter().all(|f| f.len() == 32));

    // Save and load: the same embeddings, features and labels.
    let dir = temporary("round-trip");
    evaluator.save(&dir).unwrap();
    assert!(dir.join(EVALUATOR_FILE).is_file() && dir.join(STATS_FILE).is_file());
    let loaded = Evaluator::load(&dir, &Device::Cpu).unwrap();
    let by_file = Evaluator::load(&dir.join(EVALUATOR_FILE), &Device::Cpu).unwrap();
    assert_eq!(by_file.embed_motions(&windows[..2]).unwrap(), motion[..2]);
    assert_eq!(loaded.config(), evaluator.config());
    assert_eq!(loaded.labels(), evaluator.labels());
    assert_eq!(loaded.vocabulary(), evaluator.vocabulary());
    assert_eq!(loaded.stats(), evaluator.stats());
    let reloaded = loaded.training().unwrap();
    assert_eq!(reloaded.steps, summary.steps);
    assert!((reloaded.final_loss - summary.final_loss).abs() < 1e-12);
    assert_eq!(loaded.embed_motions(&windows[..5]).unwrap(), motion);
    assert_eq!(loaded.embed_texts(&first_texts()[..5]).unwrap(), texts);
    assert_eq!(loaded.action_features(&windows[..5]).unwrap(), features);
    assert_eq!(loaded.classify(&windows).unwrap(), evaluator.classify(&windows).unwrap());
    loaded.check_dataset(&dataset().manifest, &data_path()).unwrap();
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn gradients_match_finite_differences() {
    let config = EvaluatorConfig {
        latent: 16,
        layers: 1,
        heads: 2,
        clip_frames: 8,
        max_tokens: 12,
        embedding: 8,
        batch_size: 5,
        ..EvaluatorConfig::default()
    };
    let evaluator =
        Evaluator::initialise(dataset(), &data_path(), &config, DType::F64, &Device::Cpu).unwrap();
    let sequences: Vec<_> = train_split().iter().collect();
    let batch = evaluator.draw_batch(&sequences, &mut step_rng(3, 0)).unwrap();
    let loss = evaluator.loss(&batch).unwrap();
    assert!(loss.classification.is_some());
    let gradients = loss.total.backward().unwrap();
    let total = |evaluator: &Evaluator| -> f64 {
        evaluator.loss(&batch).unwrap().total.to_scalar::<f64>().unwrap()
    };
    let used_token = batch.tokens[0][0] as usize;
    let width = config.latent;
    let checks: [(&str, usize); 9] = [
        ("motion.input.weight", 121 * 16 + 7),
        ("motion.positions", 3 * width + 2),
        ("motion.blocks.0.attention.query.weight", 11),
        ("motion.blocks.0.feed_forward.down.weight", 5),
        ("motion.projection.bias", 1),
        ("motion.action.logits.weight", 9),
        ("text.tokens", used_token * width + 3),
        ("text.layers.0.attention.key_value.weight", 17),
        ("text.output.weight", 4),
    ];
    let parameters = evaluator.parameters();
    for (name, index) in checks {
        let parameter = parameters.iter().find(|p| p.name == name).unwrap_or_else(|| {
            panic!("{name} in {:?}", parameters.iter().map(|p| &p.name).collect::<Vec<_>>())
        });
        let original = parameter.var.as_tensor().flatten_all().unwrap().to_vec1::<f64>().unwrap();
        let analytic = gradients
            .get(parameter.var.as_tensor())
            .unwrap_or_else(|| panic!("a gradient for {name}"))
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap()[index];
        let step = 1e-5;
        let at = |delta: f64| {
            let mut shifted = original.clone();
            shifted[index] += delta;
            let tensor = Tensor::from_vec(shifted, parameter.var.shape(), &Device::Cpu).unwrap();
            parameter.var.set(&tensor).unwrap();
            total(&evaluator)
        };
        let numeric = (at(step) - at(-step)) / (2.0 * step);
        at(0.0);
        let scale = analytic.abs().max(numeric.abs()).max(1e-6);
        assert!(
            (analytic - numeric).abs() / scale < 1e-4,
            "{name}[{index}]: analytic {analytic}, finite differences {numeric}"
        );
        assert!(analytic != 0.0, "{name}[{index}] has a zero gradient");
    }
}

#[test]
fn the_seed_decides_the_weights() {
    let run = |seed: u64| {
        let config = EvaluatorConfig { seed, ..tiny(3) };
        values(
            &train_evaluator(dataset(), &data_path(), &config, &Device::Cpu, &mut |_, _| {})
                .unwrap(),
        )
    };
    let first = run(5);
    assert_eq!(first, run(5));
    assert_ne!(first, run(6));
}

#[test]
fn datasets_files_and_inputs_that_do_not_fit_are_refused() {
    let evaluator =
        Evaluator::initialise(dataset(), &data_path(), &tiny(1), DType::F32, &Device::Cpu).unwrap();
    let dir = temporary("refusals");
    evaluator.save(&dir).unwrap();
    let loaded = Evaluator::load(&dir, &Device::Cpu).unwrap();

    let other = Path::new("other-dataset");
    let mut manifest = dataset().manifest.clone();
    manifest.fps = 30.0;
    let error = loaded.check_dataset(&manifest, other).unwrap_err().to_string();
    assert!(error.contains("other-dataset/manifest.json") && error.contains("fps"), "{error}");
    assert!(error.contains(EVALUATOR_FILE), "{error}");
    let mut manifest = dataset().manifest.clone();
    manifest.skeleton = "mixamo65".into();
    manifest.joints = 65;
    let error = loaded.check_dataset(&manifest, other).unwrap_err().to_string();
    assert!(error.contains("skeleton") && error.contains("mixamo65"), "{error}");

    // Clips of another skeleton, non-finite clips, empty texts.
    let mut clip = MotionClip::from_processed(&train_split()[0], 0, 10).unwrap();
    assert_eq!(clip.frames(), 10);
    let short =
        MotionClip { joints: clip.joints[..clip.joints.len() - 3].to_vec(), ..clip.clone() };
    assert!(matches!(loaded.embed_motions(&[short]), Err(EvalError::Invalid { .. })));
    clip.joints[4] = f32::NAN;
    let error = loaded.embed_motions(&[clip]).unwrap_err().to_string();
    assert!(error.contains("finite"), "{error}");
    assert!(loaded.embed_texts(&["  ...  "]).is_err());
    assert!(MotionClip::from_processed(&train_split()[0], 0, 100_000).is_err());

    // Corrupt and missing files.
    let weights = dir.join(EVALUATOR_FILE);
    std::fs::write(&weights, b"not a safetensors file").unwrap();
    let error = Evaluator::load(&dir, &Device::Cpu).unwrap_err().to_string();
    assert!(error.contains(&weights.display().to_string()), "{error}");
    evaluator.save(&dir).unwrap();
    std::fs::write(dir.join(STATS_FILE), b"{\"feature_size\": 3}").unwrap();
    let error = Evaluator::load(&dir, &Device::Cpu).unwrap_err().to_string();
    assert!(error.contains(STATS_FILE), "{error}");
    std::fs::remove_file(dir.join(STATS_FILE)).unwrap();
    let error = Evaluator::load(&dir, &Device::Cpu).unwrap_err().to_string();
    assert!(error.contains(STATS_FILE), "{error}");
    std::fs::remove_dir_all(&dir).ok();

    // A dataset without texts cannot train; one without labels has no classifier.
    let mut unlabelled = dataset().clone();
    for sequence in unlabelled.splits.values_mut().flatten() {
        sequence.action = None;
    }
    let plain =
        Evaluator::initialise(&unlabelled, &data_path(), &tiny(1), DType::F32, &Device::Cpu)
            .unwrap();
    assert!(plain.labels().is_empty());
    let windows = plain.evaluation_windows(&train_split()[..2]).unwrap();
    assert!(plain.action_features(&windows).is_err());
    assert!(plain.classify(&windows).is_err());
    let mut silent = unlabelled;
    for sequence in silent.splits.values_mut().flatten() {
        sequence.texts.clear();
    }
    let error = Evaluator::initialise(&silent, &data_path(), &tiny(1), DType::F32, &Device::Cpu)
        .unwrap_err()
        .to_string();
    assert!(error.contains("procedural-dataset") && error.contains("training split"), "{error}");
    let bad = EvaluatorConfig { heads: 3, ..tiny(1) };
    assert!(
        Evaluator::initialise(dataset(), &data_path(), &bad, DType::F32, &Device::Cpu).is_err()
    );
}

#[test]
fn decoded_motions_give_the_clips_of_their_sequences() {
    let sequence = &train_split()[0];
    let skeleton = dex2hoi_repr::Skeleton::smplx();
    let decoded = decode_features(
        &skeleton,
        &sequence.body,
        &sequence.objects,
        sequence.object_present,
        sequence.root_start,
        ObjectDecoding::Mixture,
    )
    .unwrap();
    let from_decoded = MotionClip::from_decoded(&decoded).unwrap();
    let from_data = MotionClip::from_processed(sequence, 0, sequence.frames).unwrap();
    assert_eq!(from_decoded.frames(), sequence.frames);
    assert_eq!(from_decoded.present, from_data.present);
    let largest =
        |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(largest(&from_decoded.joints, &from_data.joints) < 1e-3);
    for slot in (0..2).filter(|s| from_data.present[*s]) {
        for f in 0..sequence.frames {
            let p = (f * 2 + slot) * 3;
            let r = (f * 2 + slot) * 9;
            let position = largest(
                &from_decoded.object_positions[p..p + 3],
                &from_data.object_positions[p..p + 3],
            );
            let rotation = largest(
                &from_decoded.object_rotations[r..r + 9],
                &from_data.object_rotations[r..r + 9],
            );
            assert!(position < 1e-2 && rotation < 1e-2, "frame {f}: {position} {rotation}");
        }
    }
}
