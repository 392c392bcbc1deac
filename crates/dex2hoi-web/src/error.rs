//! The errors of `dex2hoi-web`: what the page shows when a request cannot be generated.

/// An error of the web API.
#[derive(Debug, thiserror::Error)]
pub enum WebError {
    /// A request's value that cannot be used.
    #[error("{what}: expected {expected}, got {got}")]
    Invalid {
        /// What is wrong.
        what: String,
        /// What was expected.
        expected: String,
        /// What was given.
        got: String,
    },
    /// Loading the model, reading an object or generating failed (boxed: the error is large).
    #[error(transparent)]
    Sample(Box<dex2hoi_sample::SampleError>),
    /// Writing the exports failed (boxed: the error is large).
    #[error(transparent)]
    Export(Box<dex2hoi_export::ExportError>),
}

/// Shorthand for `Result<T, WebError>`.
pub type Result<T, E = WebError> = std::result::Result<T, E>;

impl WebError {
    /// A [`WebError::Invalid`] from anything printable.
    pub fn invalid(
        what: impl Into<String>,
        expected: impl Into<String>,
        got: impl std::fmt::Display,
    ) -> Self {
        Self::Invalid { what: what.into(), expected: expected.into(), got: got.to_string() }
    }
}

impl From<dex2hoi_sample::SampleError> for WebError {
    fn from(error: dex2hoi_sample::SampleError) -> Self {
        Self::Sample(Box::new(error))
    }
}

impl From<dex2hoi_export::ExportError> for WebError {
    fn from(error: dex2hoi_export::ExportError) -> Self {
        Self::Export(Box::new(error))
    }
}
