//! Data for dex2hoi: raw sequences, the feature pipeline of the paper (Sec. 3.1), the on-disk
//! dataset format, and the built-in procedural HOI dataset that everything runs on by default.

pub mod augment;
pub mod dataset;
pub mod error;
pub mod features;
pub mod layout;
pub mod npz;
pub mod sequence;
pub mod synth;
pub mod window;

pub use error::{DataError, Result};
pub use layout::FeatureLayout;
pub use sequence::{MAX_OBJECTS, Sequence, SequenceObject};
