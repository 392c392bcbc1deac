//! Parameter names and shapes are the checkpoint format, and the seeded initialisation draws
//! each parameter from a stream seeded by its name: a refactor that renames one silently breaks
//! old checkpoints and changes a fresh model. The committed list was written by the model as it
//! was before the shared transformer block.

use candle_core::{DType, Device};

use dex2hoi_model::text::{BuiltinTextConfig, BuiltinTextEncoder, Vocabulary};
use dex2hoi_model::{BodyFusion, Model, ModelConfig, SeededVarMap, StreamLayout};

/// `name [shape]` of every parameter, sorted by name.
fn listing(vars: &SeededVarMap) -> Vec<String> {
    let data = vars.var_map().data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    names.into_iter().map(|name| format!("{name} {:?}", data[name].dims())).collect()
}

#[test]
fn parameter_names_and_shapes_do_not_change() {
    let mut sections = Vec::new();
    let variants = [
        ("model dual network", StreamLayout::Dual, BodyFusion::Network),
        ("model dual average", StreamLayout::Dual, BodyFusion::Average),
        ("model single", StreamLayout::Single, BodyFusion::Network),
    ];
    for (title, stream_layout, body_fusion) in variants {
        // The fixture's shapes were written with 16 BPS points (the tiny preset's size then).
        let cfg = ModelConfig { stream_layout, body_fusion, bps_points: 16, ..ModelConfig::tiny() };
        let vars = SeededVarMap::new(0);
        Model::new(&cfg, vars.builder(DType::F32, &Device::Cpu)).unwrap();
        sections.push(format!("# {title}"));
        sections.extend(listing(&vars));
    }
    let texts = ["pick up the cup", "a person lifts the red box with both hands", "wave"];
    let config = BuiltinTextConfig { width: 32, layers: 2, heads: 4, max_tokens: 6, output: 24 };
    let vars = SeededVarMap::new(0);
    BuiltinTextEncoder::new(
        Vocabulary::from_texts(texts),
        config,
        vars.builder(DType::F32, &Device::Cpu),
    )
    .unwrap();
    sections.push("# text encoder".into());
    sections.extend(listing(&vars));

    let expected = include_str!("fixtures/parameter_names.txt");
    let got = sections.join("\n") + "\n";
    for (line, (want, have)) in expected.lines().zip(got.lines()).enumerate() {
        assert_eq!(want, have, "line {} of tests/fixtures/parameter_names.txt", line + 1);
    }
    assert_eq!(expected.lines().count(), got.lines().count(), "number of parameters");
}
