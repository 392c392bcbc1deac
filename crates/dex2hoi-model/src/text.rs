//! Text encoders behind one trait (paper Sec. 3.2 conditions on a frozen CLIP embedding).
//!
//! - [`BuiltinTextEncoder`]: needs no downloaded files. A word-level vocabulary built from the
//!   dataset's texts and a small transformer trained together with the denoiser; mean-pooled
//!   and projected to the model's text width. Words are lower-cased and split at anything that
//!   is not a letter or a digit. **An unknown word** maps to the `[UNK]` token, whose embedding
//!   is learned from the words that training replaces by it (word dropout), so a new word still
//!   counts as "some word" in its place rather than being skipped.
//! - [`FrozenCache`]: memoises the embeddings of a frozen encoder by text.

use std::collections::{BTreeSet, HashMap};
use std::sync::Mutex;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, init::Init};

use crate::error::{ModelError, Result};
use crate::layers::{Dense, dense};
use crate::transformer::{BlockConfig, TransformerEncoder, masked_mean};

/// What every text encoder offers the model.
pub trait TextEncoder {
    /// Width of the embeddings.
    fn embedding_size(&self) -> usize;

    /// Embeds texts.
    ///
    /// # Shapes
    /// - returns `[texts, embedding_size]`
    fn encode(&self, texts: &[&str]) -> Result<Tensor>;

    /// The word-level vocabulary of an encoder that knows only the words it saw (the built-in
    /// one); `None` for subword tokenizers, which read any word.
    fn vocabulary(&self) -> Option<&Vocabulary> {
        None
    }
}

/// Refuses an empty (or blank) prompt, naming its position.
pub fn reject_empty(texts: &[&str]) -> Result<()> {
    match texts.iter().position(|t| t.trim().is_empty()) {
        Some(i) => {
            Err(ModelError::config("text", "a non-empty prompt", format!("text {i} is empty")))
        }
        None => Ok(()),
    }
}

/// An error for a file of a Hugging Face model directory that cannot be used.
pub(crate) fn unreadable(
    path: &std::path::Path,
    what: &str,
    error: impl std::fmt::Display,
) -> ModelError {
    ModelError::Checkpoint {
        path: path.to_path_buf(),
        what: what.into(),
        expected: "a readable file of the Hugging Face layout".into(),
        got: error.to_string(),
    }
}

/// Lower-cased words of a text: runs of letters and digits.
pub fn words(text: &str) -> Vec<String> {
    text.split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect()
}

/// The padding token.
pub const PAD: u32 = 0;
/// The unknown-word token.
pub const UNKNOWN: u32 = 1;

/// A word-level vocabulary: `[PAD]`, `[UNK]`, then the words of the corpus in sorted order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Vocabulary {
    words: Vec<String>,
    index: HashMap<String, u32>,
}

impl Vocabulary {
    /// The vocabulary of a corpus.
    pub fn from_texts<'a>(texts: impl IntoIterator<Item = &'a str>) -> Self {
        let set: BTreeSet<String> = texts.into_iter().flat_map(words).collect();
        Self::from_words(set.into_iter().collect())
    }

    /// A vocabulary from its word list (without the special tokens), as saved.
    pub fn from_words(words: Vec<String>) -> Self {
        let mut all = vec!["[PAD]".to_string(), "[UNK]".to_string()];
        all.extend(words);
        let index = all.iter().enumerate().map(|(i, w)| (w.clone(), i as u32)).collect();
        Self { words: all, index }
    }

    /// The words without the special tokens (what [`Vocabulary::from_words`] takes back).
    pub fn words(&self) -> &[String] {
        &self.words[2..]
    }

    /// Tokens including the special ones.
    pub fn len(&self) -> usize {
        self.words.len()
    }

    /// Whether there are no words besides the special tokens.
    pub fn is_empty(&self) -> bool {
        self.words.len() == 2
    }

    /// The words of `text` that are not in the vocabulary (in order, each once).
    pub fn unknown_words(&self, text: &str) -> Vec<String> {
        let mut unknown: Vec<String> = Vec::new();
        for word in words(text) {
            if !self.index.contains_key(&word) && !unknown.contains(&word) {
                unknown.push(word);
            }
        }
        unknown
    }

    /// Token ids of a text; unknown words become [`UNKNOWN`].
    pub fn tokenize(&self, text: &str) -> Vec<u32> {
        words(text).iter().map(|w| self.index.get(w).copied().unwrap_or(UNKNOWN)).collect()
    }
}

/// Sizes of the built-in encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BuiltinTextConfig {
    /// Token width.
    pub width: usize,
    /// Transformer layers.
    pub layers: usize,
    /// Attention heads.
    pub heads: usize,
    /// Longest text in tokens (longer texts are cut).
    pub max_tokens: usize,
    /// Output width (the model's `text_embedding`).
    pub output: usize,
}

impl Default for BuiltinTextConfig {
    fn default() -> Self {
        Self { width: 128, layers: 2, heads: 4, max_tokens: 48, output: 256 }
    }
}

/// The built-in encoder (see the module documentation); trained with the denoiser.
pub struct BuiltinTextEncoder {
    vocabulary: Vocabulary,
    config: BuiltinTextConfig,
    tokens: Tensor,
    positions: Tensor,
    layers: TransformerEncoder,
    output: Dense,
    device: Device,
    dtype: DType,
}

impl BuiltinTextEncoder {
    /// An encoder over a vocabulary; parameters under `vb` (`text_encoder.*` in checkpoints).
    pub fn new(
        vocabulary: Vocabulary,
        config: BuiltinTextConfig,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        if config.width == 0
            || config.heads == 0
            || !config.width.is_multiple_of(config.heads)
            || config.max_tokens == 0
        {
            return Err(ModelError::config(
                "text encoder",
                "a width divisible by the heads and a positive length",
                format!("{config:?}"),
            ));
        }
        // No dropout inside the encoder (word dropout is its training noise), so encoding needs
        // no random stream.
        let block = BlockConfig::plain(config.width, config.heads, 2 * config.width, 0.0);
        let layers = TransformerEncoder::new(&block, config.layers, vb.pp("layers"))?;
        Ok(Self {
            tokens: vb.get_with_hints(
                (vocabulary.len(), config.width),
                "tokens",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            positions: vb.get_with_hints(
                (config.max_tokens, config.width),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            layers,
            output: dense(config.width, config.output, vb.pp("output"))?,
            device: vb.device().clone(),
            dtype: vb.dtype(),
            vocabulary,
            config,
        })
    }

    /// The vocabulary.
    pub fn vocabulary(&self) -> &Vocabulary {
        &self.vocabulary
    }

    /// Encodes token ids directly (training replaces some by [`UNKNOWN`]: word dropout).
    ///
    /// # Shapes
    /// - `ids`: one list per text; returns `[texts, output]`
    pub fn encode_ids(&self, ids: &[Vec<u32>]) -> Result<Tensor> {
        let batch = ids.len();
        let length = ids.iter().map(Vec::len).max().unwrap_or(0).clamp(1, self.config.max_tokens);
        let mut flat = Vec::with_capacity(batch * length);
        let mut mask = Vec::with_capacity(batch * length);
        for (i, text) in ids.iter().enumerate() {
            if text.is_empty() {
                return Err(ModelError::config(
                    "text",
                    "a text with at least one word",
                    format!("text {i} is empty"),
                ));
            }
            for k in 0..length {
                flat.push(text.get(k).copied().unwrap_or(PAD));
                mask.push(if k < text.len() { 1.0f32 } else { 0.0 });
            }
        }
        let ids = Tensor::from_vec(flat, (batch * length,), &self.device)?;
        let mask = Tensor::from_vec(mask, (batch, length), &self.device)?.to_dtype(self.dtype)?;
        let embedded =
            self.tokens.index_select(&ids, 0)?.reshape((batch, length, self.config.width))?;
        let x = embedded.broadcast_add(&self.positions.narrow(0, 0, length)?)?;
        // Mean over the words of each text.
        let pooled = masked_mean(&self.layers.forward(&x, Some(&mask), None)?, &mask)?;
        self.output.forward(&pooled)
    }
}

impl TextEncoder for BuiltinTextEncoder {
    fn embedding_size(&self) -> usize {
        self.config.output
    }

    fn encode(&self, texts: &[&str]) -> Result<Tensor> {
        let ids: Vec<Vec<u32>> = texts.iter().map(|t| self.vocabulary.tokenize(t)).collect();
        self.encode_ids(&ids)
    }

    fn vocabulary(&self) -> Option<&Vocabulary> {
        Some(&self.vocabulary)
    }
}

/// Memoises a frozen encoder's embeddings by text (each text is encoded once).
pub struct FrozenCache<E> {
    inner: E,
    cache: Mutex<HashMap<String, Vec<f32>>>,
}

impl<E: TextEncoder> FrozenCache<E> {
    /// A cache in front of an encoder.
    pub fn new(inner: E) -> Self {
        Self { inner, cache: Mutex::new(HashMap::new()) }
    }

    /// Texts encoded so far.
    pub fn cached(&self) -> usize {
        self.cache.lock().map(|c| c.len()).unwrap_or(0)
    }
}

impl<E: TextEncoder> TextEncoder for FrozenCache<E> {
    fn embedding_size(&self) -> usize {
        self.inner.embedding_size()
    }

    fn encode(&self, texts: &[&str]) -> Result<Tensor> {
        let mut cache = self.cache.lock().expect("the text cache lock is not poisoned");
        let missing: Vec<&str> = texts
            .iter()
            .copied()
            .filter(|t| !cache.contains_key(*t))
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        if !missing.is_empty() {
            let embedded =
                self.inner.encode(&missing)?.detach().to_dtype(DType::F32)?.to_vec2::<f32>()?;
            for (text, row) in missing.into_iter().zip(embedded) {
                cache.insert(text.to_string(), row);
            }
        }
        let width = self.embedding_size();
        let rows: Vec<f32> = texts.iter().flat_map(|t| cache[*t].iter().copied()).collect();
        Ok(Tensor::from_vec(rows, (texts.len(), width), &Device::Cpu)?)
    }
}
