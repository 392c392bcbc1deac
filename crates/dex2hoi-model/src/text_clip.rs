//! The CLIP text encoder (the paper's frozen text condition) from a local Hugging Face
//! directory as `openai/clip-vit-base-patch32` ships it: `model.safetensors` (`text_model.*`,
//! `text_projection.weight`), `tokenizer.json` and `config.json` (its `text_config` and
//! `projection_dim`; ViT-B/32's sizes when there is none). The output is the projected
//! end-of-text token state, as CLIP's `encode_text` gives it (512-d, not normalised).

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{Module, VarBuilder};
use candle_transformers::models::clip::text_model::{
    Activation, ClipTextConfig, ClipTextTransformer,
};
use tokenizers::Tokenizer;

use crate::error::{ModelError, Result};
use crate::text::{TextEncoder, reject_empty, unreadable};

/// The encoder.
pub struct ClipTextEncoder {
    transformer: ClipTextTransformer,
    projection: candle_nn::Linear,
    tokenizer: Tokenizer,
    config: ClipTextConfig,
    end_of_text: u32,
    device: Device,
}

/// The text configuration from a Hugging Face `config.json` (or ViT-B/32's).
fn text_config(dir: &Path) -> Result<ClipTextConfig> {
    let path = dir.join("config.json");
    if !path.is_file() {
        return Ok(ClipTextConfig::vit_base_patch32());
    }
    let text = std::fs::read_to_string(&path).map_err(|e| unreadable(&path, "config.json", e))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| unreadable(&path, "config.json", e))?;
    let base = ClipTextConfig::vit_base_patch32();
    let text_config = &json["text_config"];
    let field =
        |key: &str, default: usize| text_config[key].as_u64().map_or(default, |v| v as usize);
    Ok(ClipTextConfig {
        vocab_size: field("vocab_size", base.vocab_size),
        embed_dim: field("hidden_size", base.embed_dim),
        activation: Activation::QuickGelu,
        intermediate_size: field("intermediate_size", base.intermediate_size),
        max_position_embeddings: field("max_position_embeddings", base.max_position_embeddings),
        pad_with: None,
        num_hidden_layers: field("num_hidden_layers", base.num_hidden_layers),
        num_attention_heads: field("num_attention_heads", base.num_attention_heads),
        projection_dim: json["projection_dim"].as_u64().map_or(base.projection_dim, |v| v as usize),
    })
}

impl ClipTextEncoder {
    /// Loads the text half of a CLIP model from `dir`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self> {
        let config = text_config(dir)?;
        let weights_path = dir.join("model.safetensors");
        let bytes = std::fs::read(&weights_path)
            .map_err(|e| unreadable(&weights_path, "model.safetensors", e))?;
        let vb = VarBuilder::from_buffered_safetensors(bytes, DType::F32, device)
            .map_err(|e| unreadable(&weights_path, "safetensors content", e))?;
        let transformer = ClipTextTransformer::new(vb.pp("text_model"), &config)
            .map_err(|e| unreadable(&weights_path, "CLIP text weights", e))?;
        let projection = candle_nn::linear_no_bias(
            config.embed_dim,
            config.projection_dim,
            vb.pp("text_projection"),
        )
        .map_err(|e| unreadable(&weights_path, "text_projection", e))?;
        let tokenizer_path = dir.join("tokenizer.json");
        let tokenizer = Tokenizer::from_file(&tokenizer_path)
            .map_err(|e| unreadable(&tokenizer_path, "tokenizer.json", e))?;
        // CLIP pools at the end-of-text token, the largest id of its vocabulary.
        let end_of_text = tokenizer.get_vocab(true).values().copied().max().unwrap_or(0);
        Ok(Self { transformer, projection, tokenizer, config, end_of_text, device: device.clone() })
    }
}

impl TextEncoder for ClipTextEncoder {
    fn embedding_size(&self) -> usize {
        self.config.projection_dim
    }

    /// # Shapes
    /// - returns `[texts, projection_dim]`
    fn encode(&self, texts: &[&str]) -> Result<Tensor> {
        reject_empty(texts)?;
        let limit = self.config.max_position_embeddings;
        let mut rows = Vec::with_capacity(texts.len());
        for text in texts {
            let encoding = self
                .tokenizer
                .encode(*text, true)
                .map_err(|e| ModelError::config("text", "a text the tokenizer accepts", e))?;
            let mut ids = encoding.get_ids().to_vec();
            if ids.len() > limit {
                ids.truncate(limit);
                ids[limit - 1] = self.end_of_text;
            }
            rows.push(ids);
        }
        let length = rows.iter().map(Vec::len).max().unwrap_or(1);
        // Padding with end-of-text tokens: the causal mask keeps them out of the pooled token.
        let flat: Vec<u32> = rows
            .iter()
            .flat_map(|r| {
                r.iter().copied().chain(std::iter::repeat_n(self.end_of_text, length - r.len()))
            })
            .collect();
        let ids = Tensor::from_vec(flat, (texts.len(), length), &self.device)?;
        let pooled = self.transformer.forward(&ids)?;
        Ok(self.projection.forward(&pooled)?)
    }
}
