//! The error type of `dex2hoi-eval`.

use std::path::PathBuf;

/// Everything that can go wrong while training evaluators, computing metrics or reporting.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// An argument or input that cannot be used.
    #[error("invalid {what}: expected {expected}, got {got}")]
    Invalid {
        /// What is wrong.
        what: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// A saved evaluator or report file that does not match.
    #[error("{path}: {what}: expected {expected}, got {got}")]
    File {
        /// The file.
        path: PathBuf,
        /// What does not match.
        what: String,
        /// What was expected.
        expected: String,
        /// What was found.
        got: String,
    },
    /// A file could not be read or written.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        action: &'static str,
        /// The underlying error.
        source: std::io::Error,
    },
    /// An error from the data crate.
    #[error(transparent)]
    Data(#[from] dex2hoi_data::DataError),
    /// An error from the model crate.
    #[error(transparent)]
    Model(#[from] dex2hoi_model::ModelError),
    /// An error from the inference crate: loading a run, generating (boxed: it is large, and
    /// clippy's `result_large_err` would flag every function returning this crate's `Result`;
    /// `?` still converts through the `From` impl below).
    #[error(transparent)]
    Sample(Box<dex2hoi_sample::SampleError>),
    /// An error from the optimiser.
    #[error(transparent)]
    Optim(#[from] dex2hoi_optim::OptimError),
    /// An error from the geometry crate.
    #[error(transparent)]
    Repr(#[from] dex2hoi_repr::ReprError),
    /// An error from the diffusion crate.
    #[error(transparent)]
    Diffusion(#[from] dex2hoi_diffusion::DiffusionError),
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

impl From<dex2hoi_sample::SampleError> for EvalError {
    fn from(error: dex2hoi_sample::SampleError) -> Self {
        Self::Sample(Box::new(error))
    }
}

/// Shorthand for `Result<T, EvalError>`.
pub type Result<T, E = EvalError> = std::result::Result<T, E>;

impl EvalError {
    /// An [`EvalError::Invalid`] from anything printable.
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid { what: what.into(), expected: expected.into(), got: got.to_string() }
    }

    /// An [`EvalError::File`] from anything printable.
    pub fn file(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::File {
            path: path.into(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// A closure turning an I/O error into [`EvalError::Io`].
    pub fn io(
        path: impl Into<PathBuf>,
        action: &'static str,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, action, source }
    }
}
