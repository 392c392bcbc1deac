//! The error type of `dex2hoi-export`.

use std::path::PathBuf;

/// Everything that can go wrong while exporting a motion.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
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
    /// A motion, object, option or parsed file that cannot be used.
    #[error("{context}: expected {expected}, got {got}")]
    Invalid {
        /// What is wrong (an argument, a frame and joint, a line of a file).
        context: String,
        /// What is required.
        expected: String,
        /// What was given.
        got: String,
    },
    /// An error from the data crate (atomic writes).
    #[error(transparent)]
    Data(#[from] dex2hoi_data::DataError),
    /// An error from the representation crate (forward kinematics).
    #[error(transparent)]
    Repr(#[from] dex2hoi_repr::ReprError),
}

/// Shorthand for `Result<T, ExportError>`.
pub type Result<T, E = ExportError> = std::result::Result<T, E>;

impl ExportError {
    /// An [`ExportError::Invalid`] from anything printable.
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
}
