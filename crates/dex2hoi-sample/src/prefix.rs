//! A generation's prefix rebuilt from the motion it decodes to (hand-relative objects).

use candle_core::{DType, Tensor};
use glam::Vec3;

use dex2hoi_data::FeatureLayout;
use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{ObjectDecoding, decode_features};
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

impl PrefixEncoding<'_> {
    /// Rebuilds the object features of unnormalised frames (see the type's docs).
    ///
    /// # Shapes
    /// - `frames`: `[B, 2, T, D]`; returns the same shape
    pub fn rebuild(&self, frames: &Tensor, layout: FeatureLayout) -> Result<Tensor> {
        let (device, dtype) = (frames.device().clone(), frames.dtype());
        let rows = frames.to_dtype(DType::F32)?.to_device(&candle_core::Device::Cpu)?;
        let mut rebuilt = Vec::with_capacity(rows.elem_count());
        for b in 0..rows.dims()[0] {
            let streams: Vec<f32> = rows.get(b)?.flatten_all()?.to_vec1()?;
            let (body, mut objects) = layout.streams_to_frames(&streams)?;
            let motion = decode_features(
                self.skeleton,
                &body,
                &objects,
                self.present,
                self.root_start,
                ObjectDecoding::Mixture,
            )?;
            let groups = self.skeleton.groups();
            for (slot, decoded) in motion.objects.iter().enumerate() {
                let Some((rotations, positions)) = decoded else { continue };
                for (t, (&rotation, &position)) in rotations.iter().zip(positions).enumerate() {
                    let range = layout.object_row(t, slot);
                    let predicted = HandRelativeObject::from_slice(&objects[range.clone()])?;
                    let wrists = Wrists::from_fk(&motion.joints, t, groups);
                    let pose = ObjectPose { rotation, position };
                    objects[range].copy_from_slice(
                        &HandRelativeObject::encode(pose, wrists, predicted.mixture_logits)
                            .to_array(),
                    );
                }
            }
            rebuilt.extend(layout.frames_to_streams(&body, &objects)?);
        }
        Ok(Tensor::from_vec(rebuilt, frames.dims(), &device)?.to_dtype(dtype)?)
    }
}
