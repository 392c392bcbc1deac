//! The CLIP text encoder from a tiny randomly initialised model and tokenizer written here, in
//! the Hugging Face layout (`text_model.*`, `text_projection.weight`, `config.json`).

mod common;

use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};
use candle_transformers::models::clip::text_model::{
    Activation, ClipTextConfig, ClipTextTransformer,
};

use dex2hoi_model::text::TextEncoder;
use dex2hoi_model::text_clip::ClipTextEncoder;

#[test]
fn tiny_clip_from_files_written_here() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-clip-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // The end-of-text token has the largest id, as in CLIP's vocabulary.
    let words = [
        "<unk>",
        "the",
        "person",
        "picks",
        "up",
        "mug",
        "bowl",
        "<|startoftext|>",
        "<|endoftext|>",
    ];
    let config = serde_json::json!({
        "projection_dim": 6,
        "text_config": {"vocab_size": words.len(), "hidden_size": 8, "intermediate_size": 16, "num_hidden_layers": 2,
                        "num_attention_heads": 2, "max_position_embeddings": 10}
    });
    std::fs::write(dir.join("config.json"), config.to_string()).unwrap();
    let text_config = ClipTextConfig {
        vocab_size: words.len(),
        embed_dim: 8,
        activation: Activation::QuickGelu,
        intermediate_size: 16,
        max_position_embeddings: 10,
        pad_with: None,
        num_hidden_layers: 2,
        num_attention_heads: 2,
        projection_dim: 6,
    };
    let vars = VarMap::new();
    let vb = VarBuilder::from_varmap(&vars, DType::F32, &Device::Cpu);
    ClipTextTransformer::new(vb.pp("text_model"), &text_config).unwrap();
    candle_nn::linear_no_bias(8, 6, vb.pp("text_projection")).unwrap();
    vars.save(dir.join("model.safetensors")).unwrap();
    common::write_word_tokenizer(&dir, &words, "<unk>", "<|startoftext|>", "<|endoftext|>");

    let encoder = ClipTextEncoder::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(encoder.embedding_size(), 6);
    let out = encoder.encode(&["the person picks up the mug", "bowl"]).unwrap();
    assert_eq!(out.dims(), &[2, 6]);
    let both = out.to_vec2::<f32>().unwrap();
    assert_ne!(both[0], both[1]);
    // Padding the shorter text does not change its embedding (causal mask, pooled at its end).
    let alone = encoder.encode(&["bowl"]).unwrap().to_vec2::<f32>().unwrap();
    for (a, b) in alone[0].iter().zip(&both[1]) {
        assert!((a - b).abs() < 1e-5);
    }
    // Longer than the 10 positions: cut, still ending in end-of-text.
    let long = ["the person picks up the mug"; 3].join(" ");
    assert_eq!(encoder.encode(&[long.as_str()]).unwrap().dims(), &[1, 6]);
    assert!(encoder.encode(&[""]).is_err());
    std::fs::remove_file(dir.join("model.safetensors")).unwrap();
    let error = ClipTextEncoder::load(&dir, &Device::Cpu).err().expect("no weights").to_string();
    assert!(error.contains("model.safetensors"), "{error}");
    std::fs::remove_dir_all(&dir).ok();
}
