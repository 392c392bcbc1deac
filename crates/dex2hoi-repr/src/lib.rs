//! The mathematical core of dex2hoi: rotations, skeletons, forward kinematics, the hand-relative
//! object representation of the Dex2HOI paper (Sec. 3.1, Eq. 2-4), meshes, signed
//! nearest-surface distances and BPS object features.
//!
//! CPU versions work on `glam` `f32` types for data processing; tensor versions (candle, batched
//! over leading dimensions, differentiable) serve everything the training losses touch. Both
//! agree to 1e-5 in `f32`.
//!
//! Conventions (docs/CONVENTIONS.md, "Coordinate frames and units"): metres, right-handed, Y up,
//! the character facing +Z in its rest pose; rotation matrices act on column vectors; the 6D form
//! is the first two rows (PyTorch3D).

pub mod bps;
#[cfg(feature = "cuda")]
pub mod cuda_kernel;
pub mod error;
pub mod fk;
#[cfg(feature = "cuda")]
mod fk_cuda;
pub mod mesh;
pub mod object_repr;
pub mod rotation;
pub mod sdf;
pub mod skeleton;
pub mod smplx_model;

pub use bps::BpsBasis;
pub use error::{ReprError, Result};
pub use fk::{
    FkOutput, forward_kinematics, tensor_forward_kinematics, tensor_forward_kinematics_per_sample,
};
pub use mesh::{Mesh, SurfaceSamples};
pub use object_repr::{HandRelativeObject, MixtureTargetConfig, ObjectPose, WristPose, Wrists};
pub use sdf::{CONTACT_RADIUS_M, MeshQuery, PENETRATION_TOLERANCE_M, SurfacePoint};
pub use skeleton::{JointGroups, Skeleton, SkeletonKind};
