//! Data for dex2hoi: raw sequences, the feature pipeline of the paper (Sec. 3.1), the on-disk
//! dataset format, the object catalogue and the default character that generation starts from.
//! The procedural dataset built from them is `dex2hoi-synth`.

pub mod augment;
pub mod catalogue;
pub mod character;
pub mod dataset;
pub mod error;
pub mod features;
pub mod files;
pub mod layout;
pub mod normalise;
pub mod npz;
pub mod processed;
pub mod sequence;
pub mod settled;
pub mod start;
pub mod timeline;
pub mod window;

pub use error::{DataError, Result};
pub use layout::FeatureLayout;
pub use sequence::{MAX_OBJECTS, Sequence, SequenceObject};
