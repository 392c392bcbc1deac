//! The error type of `dex2hoi-model`.

use std::path::PathBuf;

/// Everything that can go wrong while building, running, saving or loading a model.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// A configuration that cannot work.
    #[error("invalid model config: {field}: expected {expected}, got {got}")]
    Config {
        /// The field.
        field: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// An input of the wrong shape.
    #[error("model input `{input}`: expected shape {expected}, got {got:?}")]
    Shape {
        /// The input.
        input: String,
        /// The expected shape in words.
        expected: String,
        /// The shape given.
        got: Vec<usize>,
    },
    /// A checkpoint that does not match.
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
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, ModelError>`.
pub type Result<T, E = ModelError> = std::result::Result<T, E>;

impl ModelError {
    /// A [`ModelError::Config`] from anything printable.
    pub fn config(field: &str, expected: impl Into<String>, got: impl std::fmt::Display) -> Self {
        Self::Config { field: field.into(), expected: expected.into(), got: got.to_string() }
    }

    /// A [`ModelError::Shape`].
    pub fn shape(input: &str, expected: impl Into<String>, got: &[usize]) -> Self {
        Self::Shape { input: input.into(), expected: expected.into(), got: got.to_vec() }
    }
}
