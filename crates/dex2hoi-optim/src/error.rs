//! The error type of `dex2hoi-optim`.

/// What can go wrong while updating parameters: reading or writing their tensors.
#[derive(Debug, thiserror::Error)]
pub enum OptimError {
    /// An error from a tensor operation.
    #[error(transparent)]
    Tensor(#[from] candle_core::Error),
}

/// Shorthand for `Result<T, OptimError>`.
pub type Result<T, E = OptimError> = std::result::Result<T, E>;
