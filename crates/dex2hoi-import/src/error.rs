//! The error type of `dex2hoi-import`: every variant names the file (and, inside archives and
//! pickles, the entry or key path) and says what was expected and what was found.

use std::path::PathBuf;

/// Everything that can go wrong while reading a published dataset.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// A file could not be opened or read.
    #[error("{path}: cannot read the file: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file, archive entry or value is not what the format requires.
    #[error("{source_name}: {what}: expected {expected}, got {got}")]
    Format {
        /// The file, with the entry or key path inside it (`s1/mug_pass.npz[body].params`).
        source_name: String,
        /// The part that is wrong.
        what: String,
        /// What the format requires.
        expected: String,
        /// What was found.
        got: String,
    },
    /// A required key, archive entry or file is absent.
    #[error("{source_name}: missing `{key}` (expected {expected})")]
    Missing {
        /// The file or container.
        source_name: String,
        /// The missing key, entry or file.
        key: String,
        /// What it should have held.
        expected: String,
    },
    /// An array has the wrong shape.
    #[error("{source_name}: `{key}` has shape {got:?}, expected {expected}")]
    Shape {
        /// The file.
        source_name: String,
        /// The array's key path.
        key: String,
        /// The shape that was expected, in words.
        expected: String,
        /// The shape that was found.
        got: Vec<usize>,
    },
    /// A NaN or an infinity where finite numbers are required.
    #[error("{source_name}: `{key}` holds a non-finite value at flat index {index}")]
    NonFinite {
        /// The file.
        source_name: String,
        /// The array's key path.
        key: String,
        /// The first offending flat index.
        index: usize,
    },
    /// A pickle that the bounded, data-only reader refuses or cannot decode.
    #[error("{source_name}: pickle byte {offset}: {message}")]
    Pickle {
        /// The file (and archive entry).
        source_name: String,
        /// Byte offset of the offending opcode in the pickle stream.
        offset: usize,
        /// What is wrong, in words.
        message: String,
    },
    /// An option or argument that cannot be used.
    #[error("invalid {what}: expected {expected}, got {got}")]
    Invalid {
        /// The option or argument.
        what: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// An error from the representation crate (meshes, skeletons; they name their files).
    #[error(transparent)]
    Repr(#[from] dex2hoi_repr::ReprError),
    /// An error from the data crate (sequence validation, features; they name the sequence).
    #[error(transparent)]
    Data(#[from] dex2hoi_data::DataError),
}

/// Shorthand for `Result<T, ImportError>`.
pub type Result<T, E = ImportError> = std::result::Result<T, E>;

impl ImportError {
    /// An [`ImportError::Format`] from anything printable.
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

    /// An [`ImportError::Missing`] from anything printable.
    pub fn missing(
        source_name: impl std::fmt::Display,
        key: impl Into<String>,
        expected: impl Into<String>,
    ) -> Self {
        Self::Missing {
            source_name: source_name.to_string(),
            key: key.into(),
            expected: expected.into(),
        }
    }

    /// An [`ImportError::Invalid`] from anything printable.
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid { what: what.into(), expected: expected.into(), got: got.to_string() }
    }

    /// An [`ImportError::Io`] for a path.
    pub fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| Self::Io { path, source }
    }
}
