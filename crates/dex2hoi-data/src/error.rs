//! The error type of `dex2hoi-data`.

use std::path::PathBuf;

/// Everything that can go wrong while building, writing or reading datasets.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
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
    /// A file's content is not what the format requires.
    #[error("{path}: {what}: expected {expected}, got {got}")]
    Format {
        /// The file.
        path: PathBuf,
        /// The part that is wrong.
        what: String,
        /// What the format requires.
        expected: String,
        /// What was found.
        got: String,
    },
    /// A sequence or argument that cannot be used.
    #[error("{context}: expected {expected}, got {got}")]
    Invalid {
        /// Where (a sequence id, an argument).
        context: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// An error from the representation crate.
    #[error(transparent)]
    Repr(#[from] dex2hoi_repr::ReprError),
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, DataError>`.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

impl DataError {
    /// A [`DataError::Invalid`] from anything printable.
    pub fn invalid(
        context: impl std::fmt::Display,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid {
            context: context.to_string(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }

    /// A [`DataError::Format`] from anything printable.
    pub fn format(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Format {
            path: path.into(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }
}
