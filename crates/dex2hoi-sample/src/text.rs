//! Building a run's text encoder from its configuration: the built-in encoder with its own
//! parameters (trained with the denoiser), or a frozen MiniLM/CLIP encoder behind a cache.

use candle_core::{DType, Device};

use dex2hoi_model::SeededVarMap;
use dex2hoi_model::text::{BuiltinTextEncoder, FrozenCache, TextEncoder, Vocabulary};
use dex2hoi_model::text_bert::BertSentenceEncoder;
use dex2hoi_model::text_clip::ClipTextEncoder;

use crate::config::TextConfig;
use crate::error::{Result, SampleError};

/// A run's text encoder.
pub enum TextModule {
    /// The built-in encoder, trained with the denoiser.
    Builtin {
        /// The encoder (boxed: in the CUDA build it is much larger than the other variant).
        encoder: Box<BuiltinTextEncoder>,
        /// Its parameters.
        vars: SeededVarMap,
    },
    /// A frozen encoder behind a cache.
    Frozen(Box<dyn TextEncoder>),
}

impl std::fmt::Debug for TextModule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Builtin { vars, .. } => f.debug_struct("Builtin").field("vars", vars).finish(),
            Self::Frozen(e) => write!(f, "Frozen({} wide)", e.embedding_size()),
        }
    }
}

impl TextModule {
    /// Builds the encoder of `config` with output width `embedding_width` (the model's
    /// `text_embedding`, checked against the encoder). The built-in encoder takes
    /// `vocabulary` and draws its initial parameters from `parameter_seed`.
    pub fn new(
        config: &TextConfig,
        embedding_width: usize,
        vocabulary: Vocabulary,
        parameter_seed: u64,
        device: &Device,
    ) -> Result<Self> {
        let module = match config {
            TextConfig::Builtin { .. } => {
                let sizes = config.builtin(embedding_width).expect("the built-in encoder");
                let vars = SeededVarMap::new(parameter_seed);
                let encoder =
                    BuiltinTextEncoder::new(vocabulary, sizes, vars.builder(DType::F32, device))?;
                Self::Builtin { encoder: Box::new(encoder), vars }
            }
            TextConfig::Bert { path } => {
                Self::Frozen(Box::new(FrozenCache::new(BertSentenceEncoder::load(path, device)?)))
            }
            TextConfig::Clip { path } => {
                Self::Frozen(Box::new(FrozenCache::new(ClipTextEncoder::load(path, device)?)))
            }
        };
        let width = module.encoder().embedding_size();
        if width != embedding_width {
            return Err(SampleError::invalid(
                "config",
                "model.text_embedding",
                format!("the text encoder's width {width}"),
                embedding_width,
            ));
        }
        Ok(module)
    }

    /// The encoder, whichever kind it is.
    pub fn encoder(&self) -> &dyn TextEncoder {
        match self {
            Self::Builtin { encoder, .. } => encoder.as_ref(),
            Self::Frozen(encoder) => encoder.as_ref(),
        }
    }

    /// The encoder, owned.
    pub fn into_encoder(self) -> Box<dyn TextEncoder> {
        match self {
            Self::Builtin { encoder, .. } => encoder,
            Self::Frozen(encoder) => encoder,
        }
    }
}

/// The warning for the words of a prompt that the model's text encoder never saw (each reads
/// as the unknown-word token), naming them; `None` when there are none.
pub fn unknown_words_warning(unknown: &[String]) -> Option<String> {
    (!unknown.is_empty()).then(|| {
        let named: Vec<String> = unknown.iter().map(|w| format!("`{w}`")).collect();
        format!(
            "the model's text encoder never saw {}: each reads as the unknown-word token",
            named.join(", ")
        )
    })
}
