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

use candle_core::{DType, Tensor};
use glam::Vec3;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{ObjectDecoding, decode_features};
use dex2hoi_data::layout::FeatureLayout;
use dex2hoi_repr::{HandRelativeObject, MeshQuery, ObjectPose, Wrists};

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

/// One batch entry's frames: the body and object rows `[T, 6J + 3]`, `[T, 2, 18]`, and the
/// motion they decode to.
type DecodedEntry = (Vec<f32>, Vec<f32>, dex2hoi_data::features::DecodedMotion);

/// A generation's motion decoded from unnormalised features `[B, 2, T, D]`, per batch entry.
fn decode(
    encoding: &PrefixEncoding<'_>,
    frames: &Tensor,
    layout: FeatureLayout,
) -> Result<Vec<DecodedEntry>> {
    let rows = frames.to_dtype(DType::F32)?.to_device(&candle_core::Device::Cpu)?;
    (0..rows.dims()[0])
        .map(|b| {
            let streams: Vec<f32> = rows.get(b)?.flatten_all()?.to_vec1()?;
            let (body, objects) = layout.streams_to_frames(&streams)?;
            let motion = decode_features(
                encoding.skeleton,
                &body,
                &objects,
                encoding.present,
                encoding.root_start,
                ObjectDecoding::Mixture,
            )?;
            Ok((body, objects, motion))
        })
        .collect()
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
        decode(encoding, prefix, layout)?
            .into_iter()
            .map(|(.., motion)| {
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
        let (device, dtype) = (frames.device().clone(), frames.dtype());
        let decoded = decode(encoding, frames, layout)?;
        if decoded.len() != states.len() {
            return Err(SampleError::invalid(
                "objects at rest",
                "states",
                format!("one per batch entry ({})", decoded.len()),
                states.len(),
            ));
        }
        let groups = encoding.skeleton.groups();
        let mut settled = Vec::with_capacity(frames.elem_count());
        for ((body, mut objects, motion), state) in decoded.into_iter().zip(states) {
            for slot in 0..MAX_OBJECTS {
                let (Some((rotations, positions)), Some(mesh)) =
                    (&motion.objects[slot], self.meshes[slot])
                else {
                    continue;
                };
                for (t, (&rotation, &position)) in rotations.iter().zip(positions).enumerate() {
                    let range = layout.object_row(t, slot);
                    let predicted = HandRelativeObject::from_slice(&objects[range.clone()])?;
                    let logits = predicted.mixture_logits;
                    let free = logits[GLOBAL_BRANCH] >= logits[0].max(logits[1]);
                    let pose = if free {
                        *state.rest[slot].get_or_insert_with(|| {
                            // Released: straight down (or up) onto the support.
                            let lowest = mesh.lowest_height(rotation, position);
                            ObjectPose {
                                rotation,
                                position: position + Vec3::Y * (state.support[slot] - lowest),
                            }
                        })
                    } else {
                        state.rest[slot] = None;
                        ObjectPose { rotation, position }
                    };
                    let wrists = Wrists::from_fk(&motion.joints, t, groups);
                    objects[range].copy_from_slice(
                        &HandRelativeObject::encode(pose, wrists, logits).to_array(),
                    );
                }
            }
            settled.extend(layout.frames_to_streams(&body, &objects)?);
        }
        Ok(Tensor::from_vec(settled, frames.dims(), &device)?.to_dtype(dtype)?)
    }
}
