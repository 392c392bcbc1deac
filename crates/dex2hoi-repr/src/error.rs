//! The error type of `dex2hoi-repr`.

use std::path::PathBuf;

/// Everything that can go wrong in this crate. Each variant names where the problem is
/// (a file, or a described in-memory source) and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum ReprError {
    /// A file could not be opened or read.
    #[error("{path}: cannot read the file: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file was read but its content is not what the format requires.
    #[error("{source_name}: {what}: expected {expected}, got {got}")]
    Format {
        /// The file or in-memory source.
        source_name: String,
        /// The part of the content that is wrong.
        what: String,
        /// What the format requires.
        expected: String,
        /// What was found.
        got: String,
    },
    /// An archive lacks a required entry.
    #[error("{path}: missing key `{key}` (expected {expected})")]
    MissingKey {
        /// The archive.
        path: PathBuf,
        /// The missing entry.
        key: String,
        /// What the entry should have held.
        expected: String,
    },
    /// An array has the wrong shape.
    #[error("{source_name}: `{key}` has shape {got:?}, expected {expected}")]
    Shape {
        /// The file or in-memory source.
        source_name: String,
        /// The array.
        key: String,
        /// The shape that was expected, in words.
        expected: String,
        /// The shape that was found.
        got: Vec<usize>,
    },
    /// A mesh has no (non-degenerate) faces.
    #[error(
        "{source_name}: the mesh has no faces (expected at least one triangle of non-zero area)"
    )]
    EmptyMesh {
        /// The file or in-memory source.
        source_name: String,
    },
    /// A NaN or an infinity where finite numbers are required.
    #[error("{source_name}: {what} at index {index} is not finite")]
    NonFinite {
        /// The file or in-memory source.
        source_name: String,
        /// Which values.
        what: String,
        /// The first offending index.
        index: usize,
    },
    /// A function argument that cannot be used.
    #[error("invalid {what}: expected {expected}, got {got}")]
    InvalidArgument {
        /// The argument.
        what: String,
        /// What the function requires.
        expected: String,
        /// What it was given.
        got: String,
    },
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, ReprError>`.
pub type Result<T, E = ReprError> = std::result::Result<T, E>;

impl ReprError {
    /// An [`ReprError::InvalidArgument`] from anything printable.
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::InvalidArgument { what: what.into(), expected: expected.into(), got: got.to_string() }
    }

    /// A [`ReprError::Format`] from anything printable.
    pub fn format(
        source_name: impl std::fmt::Display,
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Format {
            source_name: source_name.to_string(),
            what: what.into(),
            expected: expected.into(),
            got: got.to_string(),
        }
    }
}
