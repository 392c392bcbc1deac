//! The error type of `dex2hoi-synth`.

use dex2hoi_data::DataError;
use dex2hoi_repr::ReprError;

/// Everything that can go wrong while generating the procedural dataset.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// An argument that cannot be used (a sequence count of zero).
    #[error("{argument}: expected {expected}, got {got}")]
    Argument {
        /// The argument.
        argument: &'static str,
        /// What is required.
        expected: &'static str,
        /// What was given.
        got: String,
    },
    /// A sequence the generator could not make physically valid, or that names an object the
    /// catalogue does not hold.
    #[error("{sequence}: expected {expected}, got {got}")]
    Sequence {
        /// The sequence's id and task.
        sequence: String,
        /// What was required.
        expected: String,
        /// What the last draw gave.
        got: String,
    },
    /// Features, statistics or the dataset could not be built.
    #[error(transparent)]
    Data(#[from] DataError),
    /// Kinematics or a mesh query failed.
    #[error(transparent)]
    Repr(#[from] ReprError),
}

/// Shorthand for `Result<T, SynthError>`.
pub type Result<T, E = SynthError> = std::result::Result<T, E>;
