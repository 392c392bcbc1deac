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
    /// The model produced something unusable.
    #[error("the denoiser returned {got}, expected {expected}")]
    Denoiser {
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
}
