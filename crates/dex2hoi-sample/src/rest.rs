//! Objects at rest, a rule of the autoregressive sampler beyond the paper: an object no hand
//! holds stays where it was put down, standing on its support.
//!
//! Why: the model predicts every object on every frame, also those nobody touches. Over long
//! generations the free objects drift (the shipped model's untouched objects moved at a median
//! 3 cm/s over 160 frames) and released ones end centimetres inside the table or above it. The
//! rule reads the model's own mixture (Eq. 4): on a frame whose mixture picks the global branch,
//! no hand holds the object, and its pose is its rest pose: the pose it was placed at, or the
//! pose it was released at lowered or raised until its lowest point touches its support (the
//! height its lowest point had at the start). Frames a hand holds are left as generated. The
//! settled poses are encoded back into the window's features, so that the next window's prefix
//! is the settled motion.

use candle_core::Tensor;
use glam::Vec3;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::layout::FeatureLayout;
use dex2hoi_repr::{MeshQuery, ObjectPose};

use crate::error::{Result, SampleError};
use crate::prefix::PrefixEncoding;

/// What happens to the objects no hand holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FreeObjects {
    /// As the model generates them (the paper's sampler).
    #[default]
    AsGenerated,
    /// Kept at rest on their support ([`ObjectsAtRest`]).
    AtRest,
}

impl FreeObjects {
    /// What `dex2hoi sample` and the web page do, unless told otherwise, with a model trained
    /// on data from `source` (`Manifest::source`). At rest for the procedural data, where every
    /// object is put down on the surface it started on, as the rule assumes: over ten seconds
    /// the model alone leaves released objects a median 2-4 cm into or above their support
    /// (docs/results/long-generations.md). As generated for captured data, where objects go
    /// to other surfaces (a shelf, the floor). `Default` is the paper's sampler, which
    /// `evaluate` keeps, so that its figures are the model's own.
    pub fn sample_default(source: &str) -> Self {
        if source == dex2hoi_data::dataset::PROCEDURAL_SOURCE {
            Self::AtRest
        } else {
            Self::AsGenerated
        }
    }
}

/// Index of the global branch in the mixture logits (left, right, global).
const GLOBAL_BRANCH: usize = 2;

/// The meshes the rule needs to find each object's lowest point.
#[derive(Debug, Clone, Copy)]
pub struct ObjectsAtRest<'a> {
    /// The mesh of each object slot (`None` for an empty slot).
    pub meshes: [Option<&'a MeshQuery>; MAX_OBJECTS],
}

/// Where each object of one generation rests, carried from window to window.
#[derive(Debug, Clone, PartialEq)]
pub struct RestState {
    /// The height of each object's lowest point on its support.
    support: [f32; MAX_OBJECTS],
    /// Each free object's rest pose; `None` while a hand holds it.
    rest: [Option<ObjectPose>; MAX_OBJECTS],
}

impl ObjectsAtRest<'_> {
    /// The state at the start: every object rests where the last frame of the (unnormalised)
    /// initial prefix `[B, 2, T_p, D]` puts it.
    pub fn start(
        &self,
        encoding: &PrefixEncoding<'_>,
        prefix: &Tensor,
        layout: FeatureLayout,
    ) -> Result<Vec<RestState>> {
        encoding
            .decode(prefix, layout)?
            .into_iter()
            .map(|motion| {
                let mut state = RestState { support: [0.0; MAX_OBJECTS], rest: [None; 2] };
                for slot in 0..MAX_OBJECTS {
                    let (Some((rotations, positions)), Some(mesh)) =
                        (&motion.objects[slot], self.meshes[slot])
                    else {
                        if motion.objects[slot].is_some() {
                            return Err(SampleError::invalid(
                                "objects at rest",
                                "meshes",
                                "a mesh for every present object",
                                format!("none for slot {slot}"),
                            ));
                        }
                        continue;
                    };
                    let last = positions.len() - 1;
                    let pose = ObjectPose { rotation: rotations[last], position: positions[last] };
                    state.support[slot] = mesh.lowest_height(pose.rotation, pose.position);
                    state.rest[slot] = Some(pose);
                }
                Ok(state)
            })
            .collect()
    }

    /// Settles the free objects of unnormalised window frames `[B, 2, T, D]` (see the module
    /// docs) and returns the frames with their object features encoded from the settled poses.
    ///
    /// # Shapes
    /// - `frames`: `[B, 2, T, D]`; returns the same shape; `states`: `[B]`
    pub fn settle(
        &self,
        encoding: &PrefixEncoding<'_>,
        frames: &Tensor,
        layout: FeatureLayout,
        states: &mut [RestState],
    ) -> Result<Tensor> {
        let batch = frames.dims()[0];
        if batch != states.len() {
            return Err(SampleError::invalid(
                "objects at rest",
                "states",
                format!("one per batch entry ({batch})"),
                states.len(),
            ));
        }
        encoding.reencode(frames, layout, |(b, slot, _), pose, logits| {
            // Every present object has a mesh (`start` checked).
            let (Some(mesh), state) = (self.meshes[slot], &mut states[b]) else { return Ok(pose) };
            if logits[GLOBAL_BRANCH] < logits[0].max(logits[1]) {
                // A hand holds it: as generated.
                state.rest[slot] = None;
                return Ok(pose);
            }
            Ok(*state.rest[slot].get_or_insert_with(|| {
                // Released: straight down (or up) onto the support.
                let lowest = mesh.lowest_height(pose.rotation, pose.position);
                ObjectPose {
                    rotation: pose.rotation,
                    position: pose.position + Vec3::Y * (state.support[slot] - lowest),
                }
            }))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::FreeObjects;

    /// The rule is `sample`'s default only where its assumption holds: the procedural data,
    /// whose objects always go back down on the surface they started on.
    #[test]
    fn sample_default_follows_the_data_source() {
        let procedural = dex2hoi_data::dataset::PROCEDURAL_SOURCE;
        assert_eq!(FreeObjects::sample_default(procedural), FreeObjects::AtRest);
        for captured in ["grab", "humoto", "himo"] {
            assert_eq!(FreeObjects::sample_default(captured), FreeObjects::AsGenerated);
        }
        assert_eq!(FreeObjects::default(), FreeObjects::AsGenerated, "the paper's sampler");
    }
}
