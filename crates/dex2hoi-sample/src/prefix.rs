//! A generation's prefix rebuilt from the motion it decodes to (hand-relative objects).

use candle_core::{DType, Tensor};
use glam::Vec3;

use dex2hoi_data::FeatureLayout;
use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{DecodedMotion, ObjectDecoding, decode_features};
use dex2hoi_repr::{HandRelativeObject, ObjectPose, Skeleton, Wrists};

use crate::error::Result;

/// What rebuilding a prefix from its motion needs: the hand-relative object features of the
/// generated frames are decoded to object poses (the mixture, Eq. 4) and encoded again
/// against the same frames' wrists (Eq. 2-3), keeping the predicted mixture logits.
///
/// Why: in the data the three position branches of an object agree on every frame. In a
/// generated window the branch the mixture does not use drifts (while a hand holds the
/// object, its global position sank 3-5 cm below where the hand held it); fed back as the
/// next window's prefix, that drift was continued, and the object dropped to the drifted
/// height as soon as the hand let go. Rebuilt, the prefix is the motion itself, in the form
/// the model was trained on; the frames already generated are not changed.
#[derive(Debug, Clone, Copy)]
pub struct PrefixEncoding<'a> {
    /// The body the motion is posed on.
    pub skeleton: &'a Skeleton,
    /// The root position the features' root displacement is measured from.
    pub root_start: Vec3,
    /// Which object slots hold an object.
    pub present: [bool; MAX_OBJECTS],
}

/// One batch entry's body and object rows `[T, 6J + 3]`, `[T, 2, 18]` and their motion.
type DecodedEntry = (Vec<f32>, Vec<f32>, DecodedMotion);

impl PrefixEncoding<'_> {
    /// Rebuilds the object features of unnormalised frames (see the type's docs).
    ///
    /// # Shapes
    /// - `frames`: `[B, 2, T, D]`; returns the same shape
    pub fn rebuild(&self, frames: &Tensor, layout: FeatureLayout) -> Result<Tensor> {
        self.reencode(frames, layout, |_, pose, _| Ok(pose))
    }

    /// Decodes unnormalised frames to their motion (objects by the mixture, Eq. 4) and encodes
    /// every present object's pose back against the same frames' wrists (Eq. 2-3), keeping the
    /// predicted mixture logits. `pose_of((b, slot, t), decoded, logits)` gives the pose to
    /// encode: the decoded one, or another (`crate::rest`'s objects at rest).
    ///
    /// # Shapes
    /// - `frames`: `[B, 2, T, D]`; returns the same shape
    pub fn reencode(
        &self,
        frames: &Tensor,
        layout: FeatureLayout,
        mut pose_of: impl FnMut((usize, usize, usize), ObjectPose, [f32; 3]) -> Result<ObjectPose>,
    ) -> Result<Tensor> {
        let (device, dtype) = (frames.device().clone(), frames.dtype());
        let groups = self.skeleton.groups();
        let mut encoded = Vec::with_capacity(frames.elem_count());
        for (b, (body, mut objects, motion)) in
            self.decode_entries(frames, layout)?.into_iter().enumerate()
        {
            for (slot, decoded) in motion.objects.iter().enumerate() {
                let Some((rotations, positions)) = decoded else { continue };
                for (t, (&rotation, &position)) in rotations.iter().zip(positions).enumerate() {
                    let range = layout.object_row(t, slot);
                    let logits =
                        HandRelativeObject::from_slice(&objects[range.clone()])?.mixture_logits;
                    let pose = pose_of((b, slot, t), ObjectPose { rotation, position }, logits)?;
                    let wrists = Wrists::from_fk(&motion.joints, t, groups);
                    objects[range].copy_from_slice(
                        &HandRelativeObject::encode(pose, wrists, logits).to_array(),
                    );
                }
            }
            encoded.extend(layout.frames_to_streams(&body, &objects)?);
        }
        Ok(Tensor::from_vec(encoded, frames.dims(), &device)?.to_dtype(dtype)?)
    }

    /// The motion of each batch entry of unnormalised frames `[B, 2, T, D]`.
    pub fn decode(&self, frames: &Tensor, layout: FeatureLayout) -> Result<Vec<DecodedMotion>> {
        Ok(self.decode_entries(frames, layout)?.into_iter().map(|(.., motion)| motion).collect())
    }

    /// Per batch entry the body and object rows `[T, 6J + 3]`, `[T, 2, 18]` of unnormalised
    /// frames `[B, 2, T, D]` and the motion they decode to.
    fn decode_entries(&self, frames: &Tensor, layout: FeatureLayout) -> Result<Vec<DecodedEntry>> {
        let rows = frames.to_dtype(DType::F32)?.to_device(&candle_core::Device::Cpu)?;
        (0..rows.dims()[0])
            .map(|b| {
                let streams: Vec<f32> = rows.get(b)?.flatten_all()?.to_vec1()?;
                let (body, objects) = layout.streams_to_frames(&streams)?;
                let motion = decode_features(
                    self.skeleton,
                    &body,
                    &objects,
                    self.present,
                    self.root_start,
                    ObjectDecoding::Mixture,
                )?;
                Ok((body, objects, motion))
            })
            .collect()
    }
}
