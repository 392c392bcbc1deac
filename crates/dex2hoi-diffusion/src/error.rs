//! The error type of `dex2hoi-diffusion`.

/// Everything that can go wrong while noising or sampling.
#[derive(Debug, thiserror::Error)]
pub enum DiffusionError {
    /// An argument that cannot be used.
    #[error("invalid {what}: expected {expected}, got {got}")]
    Invalid {
        /// The argument.
        what: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// The [`Denoiser`](crate::Denoiser) failed: the model's own error, kept whole as the source
    /// (`std::error::Error::source` gives it; downcast it to the implementor's error type).
    #[error("the denoiser failed: {0}")]
    Denoiser(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// The denoiser returned something unusable (a prediction of another shape than its input).
    #[error("the denoiser returned {got}, expected {expected}")]
    DenoiserOutput {
        /// What was expected.
        expected: String,
        /// What came back.
        got: String,
    },
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, DiffusionError>`.
pub type Result<T, E = DiffusionError> = std::result::Result<T, E>;

impl DiffusionError {
    /// A [`DiffusionError::Invalid`] from anything printable.
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid { what: what.into(), expected: expected.into(), got: got.to_string() }
    }

    /// A [`DiffusionError::Denoiser`] holding the model's error, for implementors of
    /// [`Denoiser`](crate::Denoiser): `model.forward(..).map_err(DiffusionError::denoiser)`.
    pub fn denoiser(error: impl std::error::Error + Send + Sync + 'static) -> Self {
        Self::Denoiser(Box::new(error))
    }
}
