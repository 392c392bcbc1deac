//! The error type of `dex2hoi-sample`.

use std::path::PathBuf;

/// Everything that can go wrong while loading a run or generating a motion.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// A request value that cannot be used (an object, a frame count, a timeline line).
    #[error("{source_name}: {what}: expected {expected}, got {got}")]
    Invalid {
        /// Where the value came from (a file, or what the value is).
        source_name: String,
        /// The value.
        what: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// A run directory, configuration or checkpoint that does not match the schema.
    #[error("{path}: {what}: expected {expected}, got {got}")]
    Run {
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
    /// The generation's progress hook asked it to stop (Ctrl-C); no motion was produced.
    #[error("interrupted after {frames_done} of {frames} frames: nothing generated")]
    Interrupted {
        /// Frames generated when it stopped (discarded).
        frames_done: usize,
        /// Frames requested.
        frames: usize,
    },
    /// An error from the data crate.
    #[error(transparent)]
    Data(#[from] dex2hoi_data::DataError),
    /// An error from the model crate.
    #[error(transparent)]
    Model(#[from] dex2hoi_model::ModelError),
    /// An error from the diffusion crate.
    #[error(transparent)]
    Diffusion(#[from] dex2hoi_diffusion::DiffusionError),
    /// An error from the geometry crate.
    #[error(transparent)]
    Repr(#[from] dex2hoi_repr::ReprError),
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, SampleError>`.
pub type Result<T, E = SampleError> = std::result::Result<T, E>;

impl SampleError {
    /// A [`SampleError::Invalid`] from anything printable.
    pub fn invalid(
        source_name: impl Into<String>,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid {
            source_name: source_name.into(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// A [`SampleError::Run`] from anything printable.
    pub fn run(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Run {
            path: path.into(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// A closure turning an I/O error on `path` into a [`SampleError::Io`].
    pub fn io(
        path: impl Into<PathBuf>,
        action: &'static str,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, action, source }
    }
}
