//! Evaluator files whose metadata asks for more than the file holds: refused, with the file
//! named, before the networks are allocated.

use std::collections::BTreeMap;

use candle_core::{Device, Tensor};

use dex2hoi_eval::evaluator::files::{
    CONFIG_KEY, EVALUATOR_FORMAT, FPS_KEY, JOINTS_KEY, LABELS_KEY, SKELETON_KEY, STATS_FILE,
    TRAINING_KEY, VOCABULARY_KEY,
};
use dex2hoi_eval::evaluator::{ClipStats, Evaluator, EvaluatorConfig, clip_feature_size};
use dex2hoi_model::checkpoint::{FORMAT_KEY, write_tensors};

/// Writes an evaluator directory of one small tensor and metadata asking for `config` and
/// `joints`; returns the error of loading it.
fn load_hostile(name: &str, config: &EvaluatorConfig, joints: usize) -> String {
    let dir = std::env::temp_dir().join(format!("dex2hoi-eval-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tensors = BTreeMap::from([(
        "motion.x".to_string(),
        Tensor::zeros(64, candle_core::DType::F32, &Device::Cpu).unwrap(),
    )]);
    let metadata = BTreeMap::from([
        (FORMAT_KEY.to_string(), EVALUATOR_FORMAT.to_string()),
        (CONFIG_KEY.to_string(), serde_json::to_string(config).unwrap()),
        (VOCABULARY_KEY.to_string(), "[\"mug\"]".to_string()),
        (LABELS_KEY.to_string(), "[]".to_string()),
        (SKELETON_KEY.to_string(), "smplx52".to_string()),
        (JOINTS_KEY.to_string(), joints.to_string()),
        (FPS_KEY.to_string(), "30".to_string()),
        (TRAINING_KEY.to_string(), "null".to_string()),
    ]);
    let path = dir.join(format!("{name}.safetensors"));
    write_tensors(&path, &tensors, &metadata).unwrap();
    let width = clip_feature_size(52);
    let stats = ClipStats { feature_size: width, mean: vec![0.0; width], std: vec![1.0; width] };
    std::fs::write(dir.join(STATS_FILE), serde_json::to_string(&stats).unwrap()).unwrap();
    let started = std::time::Instant::now();
    let Err(error) = Evaluator::load(&path, &Device::Cpu) else { panic!("refused") };
    let error = error.to_string();
    assert!(started.elapsed().as_secs_f32() < 5.0, "{error}");
    std::fs::remove_dir_all(&dir).ok();
    assert!(error.contains(&format!("{name}.safetensors")), "{error}");
    error
}

#[test]
fn sizes_past_the_files_tensors_are_refused() {
    // A latent width of 2^30: its first layer alone would be gigabytes.
    let huge = EvaluatorConfig { latent: 1 << 30, ..EvaluatorConfig::default() };
    let error = load_hostile("latent", &huge, 52);
    assert!(error.contains(CONFIG_KEY) && error.contains("past the"), "{error}");
    // A joint count whose feature width would overflow.
    let error = load_hostile("joints", &EvaluatorConfig::default(), usize::MAX / 2);
    assert!(error.contains(JOINTS_KEY) && error.contains("at most"), "{error}");
}
