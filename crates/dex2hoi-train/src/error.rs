//! The error type of `dex2hoi-train`.

use std::path::PathBuf;

/// Everything that can go wrong while configuring, running, saving or resuming training.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A configuration (file or value) that cannot be used.
    #[error("{source_name}: {field}: expected {expected}, got {got}")]
    Config {
        /// The file or argument the configuration came from.
        source_name: String,
        /// The field.
        field: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// A dataset that does not fit the configuration.
    #[error("dataset {path}: {what}: expected {expected}, got {got}")]
    Dataset {
        /// The dataset directory.
        path: PathBuf,
        /// What does not fit.
        what: String,
        /// What the configuration needs.
        expected: String,
        /// What the dataset has.
        got: String,
    },
    /// A checkpoint or run directory that does not match.
    #[error("{path}: {what}: expected {expected}, got {got}")]
    Checkpoint {
        /// The file.
        path: PathBuf,
        /// What does not match.
        what: String,
        /// What was expected.
        expected: String,
        /// What was found.
        got: String,
    },
    /// A loss became NaN or infinite; the last good checkpoint is kept.
    #[error(
        "step {step}: the loss term `{term}` is {value}; training stopped, the last checkpoint \
         (step {last_checkpoint}) is kept"
    )]
    NonFinite {
        /// The step whose loss was not finite.
        step: usize,
        /// The first non-finite term.
        term: String,
        /// Its value.
        value: f64,
        /// The step of the last checkpoint written.
        last_checkpoint: usize,
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
    /// An error from the inference crate: run files, text encoders (boxed: it is large, and
    /// clippy's `result_large_err` would flag every function returning this crate's `Result`;
    /// `?` still converts through the `From` impl below).
    #[error(transparent)]
    Sample(Box<dex2hoi_sample::SampleError>),
    /// An error from the optimiser.
    #[error(transparent)]
    Optim(#[from] dex2hoi_optim::OptimError),
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

impl From<dex2hoi_sample::SampleError> for TrainError {
    fn from(error: dex2hoi_sample::SampleError) -> Self {
        Self::Sample(Box::new(error))
    }
}

/// Shorthand for `Result<T, TrainError>`.
pub type Result<T, E = TrainError> = std::result::Result<T, E>;

impl TrainError {
    /// A [`TrainError::Config`] from anything printable.
    pub fn config(
        source_name: impl Into<String>,
        field: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Config {
            source_name: source_name.into(),
            field: field.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// A [`TrainError::Checkpoint`] from anything printable.
    pub fn checkpoint(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Checkpoint {
            path: path.into(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    pub(crate) fn io(
        path: impl Into<PathBuf>,
        action: &'static str,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, action, source }
    }
}
