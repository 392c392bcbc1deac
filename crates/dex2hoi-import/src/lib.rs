//! Native readers for the published GRAB, HUMOTO and HIMO datasets and their conversion into
//! dex2hoi datasets (`dex2hoi data prepare`). docs/CONVENTIONS.md, "Datasets", describes them.
//!
//! Everything is read as published, with no Python step: numpy `.npy`/`.npz` files including
//! pickled object arrays ([`npy`], through the bounded, data-only [`pickle`] reader), Python
//! pickles, PLY and OBJ meshes (through `dex2hoi_repr::Mesh`) and HUMOTO's YAML text ([`yaml`]).
//! [`prepare::prepare`] reads a whole dataset in parallel and assembles a
//! `dex2hoi_data::dataset::Dataset`, reporting every sequence it skipped and why.

pub mod array;
pub mod character;
pub mod error;
pub mod glb;
pub mod grab;
pub mod himo;
pub mod humoto;
pub mod npy;
pub mod pickle;
pub mod prepare;
pub mod rig;
pub mod smplx;
mod source;
pub mod value;
pub mod yaml;

pub use error::{ImportError, Result};
pub use prepare::{PrepareReport, Prepared, prepare};
pub use source::{HandPoseSource, PrepareOptions, SourceFormat};
pub use value::{Field, Value};
