//! The feature layout: how many numbers a frame's features take, where each part sits, and how
//! the data's frame-major arrays turn into the model's stream-major rows and back. Every piece
//! of code that indexes into features goes through here, so that the layout is written down
//! once.
//!
//! # The two layouts
//!
//! **Frame-major** (a [`ProcessedSequence`], the dataset files, [`decode_features`]):
//! - body `[T, 6J + 3]`: per frame the 6D local rotation of every joint (`h`, `6J` numbers,
//!   joint `j` at `6j..6j + 6`), then the root's displacement from the first frame (`r`, 3);
//! - objects `[T, 2, 18]`: per frame and object slot the hand-relative object representation
//!   `o^s` (Eq. 2-4, zeros for an empty slot; its parts are the `*_RANGE` constants of
//!   [`dex2hoi_repr::object_repr`]).
//!
//! **Stream-major** (the model's input and output, `[2, T, D]` per window, `D = 6J + 3 + 18`):
//! row `(s, t)` is stream `s` at frame `t`: the body row `t` followed by object slot `s`'s row
//! `t`, i.e. stream A is `[h, r, o^A]` and stream B `[h, r, o^B]`. Both streams carry the same
//! body; going back to frame-major the body is read from stream A (the model fuses the two
//! bodies, so its output has the same body in both).
//!
//! # Object assets
//!
//! A dataset keeps one [`ObjectAsset`] per object in manifest order and every sequence names
//! the object of each slot; [`asset_index`], [`slot_assets`] and [`slot_bps`] turn those names
//! into asset indices and the per-slot BPS features the model is conditioned on.
//!
//! [`ProcessedSequence`]: crate::features::ProcessedSequence
//! [`decode_features`]: crate::features::decode_features

use std::ops::Range;

use candle_core::{D, Tensor};

use crate::error::{DataError, Result};
use crate::processed::ProcessedSequence;

pub use crate::processed::ObjectAsset;
pub use crate::sequence::MAX_OBJECTS;
pub use dex2hoi_repr::object_repr::OBJECT_FEATURE_SIZE;

/// Numbers of one joint rotation in the 6D form.
pub const ROTATION_FEATURE_SIZE: usize = 6;
/// Numbers of the root displacement.
pub const ROOT_FEATURE_SIZE: usize = 3;
/// Streams of the model: one per object slot.
pub const STREAMS: usize = MAX_OBJECTS;

/// The positions of the `per_slot` numbers of object slot `slot` at frame `frame` in any
/// frame-major per-slot array (`objects`, `hand_contact`, `object_positions`, ...).
///
/// # Shapes
/// - the array: `[T, 2, per_slot]` flattened
pub const fn slot_range(frame: usize, slot: usize, per_slot: usize) -> Range<usize> {
    let start = (frame * MAX_OBJECTS + slot) * per_slot;
    start..start + per_slot
}

/// The positions of frames `frames` in any frame-major per-slot array.
///
/// # Shapes
/// - the array: `[T, 2, per_slot]` flattened; the range covers `[frames.len(), 2, per_slot]`
pub const fn slot_frames(frames: Range<usize>, per_slot: usize) -> Range<usize> {
    frames.start * MAX_OBJECTS * per_slot..frames.end * MAX_OBJECTS * per_slot
}

/// The feature layout of a skeleton with a given number of joints (see the module
/// documentation). Cheap to copy; build it where it is needed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct FeatureLayout {
    joints: usize,
}

impl FeatureLayout {
    /// The layout for `joints` joints.
    pub const fn new(joints: usize) -> Self {
        Self { joints }
    }

    /// The layout of a skeleton's features.
    pub fn of_skeleton(skeleton: &dex2hoi_repr::Skeleton) -> Self {
        Self::new(skeleton.joint_count())
    }

    /// Joints `J`.
    pub const fn joints(self) -> usize {
        self.joints
    }

    /// Numbers per frame of the body part `[h, r]`: `6J + 3`.
    pub const fn body_width(self) -> usize {
        ROTATION_FEATURE_SIZE * self.joints + ROOT_FEATURE_SIZE
    }

    /// Numbers per frame and slot of an object: 18.
    pub const fn object_width(self) -> usize {
        OBJECT_FEATURE_SIZE
    }

    /// Numbers per frame of all object slots in the frame-major layout: `2 * 18`.
    pub const fn objects_width(self) -> usize {
        MAX_OBJECTS * OBJECT_FEATURE_SIZE
    }

    /// Numbers per frame of one stream `[h, r, o]`: `6J + 3 + 18`, the model's `D`.
    pub const fn stream_width(self) -> usize {
        self.body_width() + OBJECT_FEATURE_SIZE
    }

    /// The body part in a body row or a stream row: `0..6J + 3`.
    pub const fn body_range(self) -> Range<usize> {
        0..self.body_width()
    }

    /// The joint rotations `h` in a body or stream row: `0..6J`.
    pub const fn rotations_range(self) -> Range<usize> {
        0..ROTATION_FEATURE_SIZE * self.joints
    }

    /// Joint `joint`'s 6D rotation in a body or stream row: `6j..6j + 6`.
    pub const fn joint_rotation_range(self, joint: usize) -> Range<usize> {
        ROTATION_FEATURE_SIZE * joint..ROTATION_FEATURE_SIZE * (joint + 1)
    }

    /// The root displacement `r` in a body or stream row: `6J..6J + 3`.
    pub const fn root_range(self) -> Range<usize> {
        ROTATION_FEATURE_SIZE * self.joints..self.body_width()
    }

    /// The object part `o` in a stream row: `6J + 3..D`.
    pub const fn object_range(self) -> Range<usize> {
        self.body_width()..self.stream_width()
    }

    /// A part of the object representation (such as
    /// [`MIXTURE_RANGE`](dex2hoi_repr::object_repr::MIXTURE_RANGE)) moved to its place in a
    /// stream row.
    pub const fn object_part_range(self, part: Range<usize>) -> Range<usize> {
        self.body_width() + part.start..self.body_width() + part.end
    }

    /// Frame `frame`'s body row in a frame-major body array.
    ///
    /// # Shapes
    /// - the array: `[T, 6J + 3]` flattened
    pub const fn body_row(self, frame: usize) -> Range<usize> {
        frame * self.body_width()..(frame + 1) * self.body_width()
    }

    /// Frames `frames` of a frame-major body array.
    ///
    /// # Shapes
    /// - the array: `[T, 6J + 3]` flattened; the range covers `[frames.len(), 6J + 3]`
    pub const fn body_frames(self, frames: Range<usize>) -> Range<usize> {
        frames.start * self.body_width()..frames.end * self.body_width()
    }

    /// Object slot `slot`'s row at frame `frame` in a frame-major object array.
    ///
    /// # Shapes
    /// - the array: `[T, 2, 18]` flattened
    pub const fn object_row(self, frame: usize, slot: usize) -> Range<usize> {
        slot_range(frame, slot, OBJECT_FEATURE_SIZE)
    }

    /// Frames `frames` of a frame-major object array.
    ///
    /// # Shapes
    /// - the array: `[T, 2, 18]` flattened; the range covers `[frames.len(), 2, 18]`
    pub const fn object_frames(self, frames: Range<usize>) -> Range<usize> {
        slot_frames(frames, OBJECT_FEATURE_SIZE)
    }

    /// Stream `stream`'s row at frame `frame` in a stream-major array of `frames` frames.
    ///
    /// # Shapes
    /// - the array: `[2, frames, D]` flattened
    pub const fn stream_row(self, frames: usize, stream: usize, frame: usize) -> Range<usize> {
        let start = (stream * frames + frame) * self.stream_width();
        start..start + self.stream_width()
    }

    /// The number of frames of frame-major features, checking that body and objects agree.
    ///
    /// # Shapes
    /// - `body`: `[T, 6J + 3]`; `objects`: `[T, 2, 18]`
    pub fn frames_of(self, body: &[f32], objects: &[f32]) -> Result<usize> {
        let frames = body.len() / self.body_width();
        if body.len() != frames * self.body_width()
            || objects.len() != frames * self.objects_width()
        {
            return Err(DataError::invalid(
                "frame-major features",
                format!("[frames, {}] body and [frames, 2, 18] object features", self.body_width()),
                format!("{} and {} numbers", body.len(), objects.len()),
            ));
        }
        Ok(frames)
    }

    /// The number of frames of stream-major features.
    ///
    /// # Shapes
    /// - `streams`: `[2, T, D]`
    pub fn frames_of_streams(self, streams: &[f32]) -> Result<usize> {
        let frames = streams.len() / (STREAMS * self.stream_width());
        if streams.len() != STREAMS * frames * self.stream_width() {
            return Err(DataError::invalid(
                "stream-major features",
                format!("[2, frames, {}] features", self.stream_width()),
                format!("{} numbers", streams.len()),
            ));
        }
        Ok(frames)
    }

    /// Writes stream `stream`'s row at frame `frame` (the body row, then the slot's object row)
    /// into `row`, for callers that fill a larger buffer (a batch) or transform each row.
    ///
    /// # Shapes
    /// - `body`: `[T, 6J + 3]`; `objects`: `[T, 2, 18]`; `row`: `[D]`
    ///
    /// # Panics
    /// When `frame` is out of range or `row` is not `D` long.
    pub fn write_stream_row(
        self,
        body: &[f32],
        objects: &[f32],
        frame: usize,
        stream: usize,
        row: &mut [f32],
    ) {
        row[self.body_range()].copy_from_slice(&body[self.body_row(frame)]);
        row[self.object_range()].copy_from_slice(&objects[self.object_row(frame, stream)]);
    }

    /// Frame-major features to the model's stream-major rows.
    ///
    /// # Shapes
    /// - `body`: `[T, 6J + 3]`; `objects`: `[T, 2, 18]`
    /// - returns `[2, T, D]`: row `(s, t)` = body row `t` then object slot `s` at frame `t`
    pub fn frames_to_streams(self, body: &[f32], objects: &[f32]) -> Result<Vec<f32>> {
        let frames = self.frames_of(body, objects)?;
        let mut streams = vec![0.0f32; STREAMS * frames * self.stream_width()];
        for stream in 0..STREAMS {
            for frame in 0..frames {
                let row = self.stream_row(frames, stream, frame);
                self.write_stream_row(body, objects, frame, stream, &mut streams[row]);
            }
        }
        Ok(streams)
    }

    /// The model's stream-major rows back to frame-major features: the body from stream A,
    /// each slot's object features from its own stream.
    ///
    /// # Shapes
    /// - `streams`: `[2, T, D]`
    /// - returns body `[T, 6J + 3]` and objects `[T, 2, 18]`
    pub fn streams_to_frames(self, streams: &[f32]) -> Result<(Vec<f32>, Vec<f32>)> {
        let frames = self.frames_of_streams(streams)?;
        let body = (0..frames)
            .flat_map(|frame| &streams[self.stream_row(frames, 0, frame)][self.body_range()])
            .copied()
            .collect();
        Ok((body, self.stream_objects_to_frames(streams)?))
    }

    /// Only the object features of stream-major rows, frame-major.
    ///
    /// # Shapes
    /// - `streams`: `[2, T, D]`
    /// - returns `[T, 2, 18]`
    pub fn stream_objects_to_frames(self, streams: &[f32]) -> Result<Vec<f32>> {
        let frames = self.frames_of_streams(streams)?;
        let mut objects = vec![0.0f32; frames * self.objects_width()];
        for frame in 0..frames {
            for stream in 0..STREAMS {
                let row = &streams[self.stream_row(frames, stream, frame)];
                objects[self.object_row(frame, stream)].copy_from_slice(&row[self.object_range()]);
            }
        }
        Ok(objects)
    }

    /// The body part of features whose last dimension is a stream row (or a body row).
    ///
    /// # Shapes
    /// - `features`: `[..., D]` (or `[..., 6J + 3]`); returns `[..., 6J + 3]`
    pub fn body_of(self, features: &Tensor) -> candle_core::Result<Tensor> {
        features.narrow(D::Minus1, 0, self.body_width())
    }

    /// The joint rotations of features whose last dimension is a stream or body row, one 6D
    /// rotation per joint.
    ///
    /// # Shapes
    /// - `features`: `[..., D]` (or `[..., 6J + 3]`); returns `[..., J, 6]`
    pub fn joint_rotations_of(self, features: &Tensor) -> candle_core::Result<Tensor> {
        let rotations = features.narrow(D::Minus1, 0, self.rotations_range().end)?;
        let mut shape = rotations.dims().to_vec();
        shape.pop();
        shape.extend([self.joints, ROTATION_FEATURE_SIZE]);
        rotations.reshape(shape)
    }

    /// The root displacement of features whose last dimension is a stream or body row.
    ///
    /// # Shapes
    /// - `features`: `[..., D]` (or `[..., 6J + 3]`); returns `[..., 3]`
    pub fn root_of(self, features: &Tensor) -> candle_core::Result<Tensor> {
        features.narrow(D::Minus1, self.root_range().start, ROOT_FEATURE_SIZE)
    }

    /// The object part of features whose last dimension is a stream row.
    ///
    /// # Shapes
    /// - `features`: `[..., D]`; returns `[..., 18]`
    pub fn object_of(self, features: &Tensor) -> candle_core::Result<Tensor> {
        features.narrow(D::Minus1, self.body_width(), OBJECT_FEATURE_SIZE)
    }

    /// The body of a batch of stream-major features, read from stream A (both streams carry
    /// the same body).
    ///
    /// # Shapes
    /// - `streams`: `[B, 2, T, D]`; returns `[B, T, 6J + 3]`
    pub fn stream_body_of(self, streams: &Tensor) -> candle_core::Result<Tensor> {
        self.body_of(&streams.narrow(1, 0, 1)?.squeeze(1)?)
    }
}

impl ProcessedSequence {
    /// The layout of the sequence's features.
    pub fn layout(&self) -> FeatureLayout {
        FeatureLayout::new(self.joints)
    }

    /// Frames `frames` of the sequence as the model's stream-major rows (unnormalised), such as
    /// the clean prefix a generation starts from.
    ///
    /// # Shapes
    /// - returns `[2, frames.len(), D]`
    pub fn stream_features(&self, frames: Range<usize>) -> Result<Vec<f32>> {
        if frames.start > frames.end || frames.end > self.frames {
            return Err(DataError::invalid(
                &self.source_id,
                format!("frames within 0..{}", self.frames),
                format!("{frames:?}"),
            ));
        }
        let layout = self.layout();
        layout.frames_to_streams(
            &self.body[layout.body_frames(frames.clone())],
            &self.objects[layout.object_frames(frames)],
        )
    }
}

/// The index of the asset named `name` among `assets` (a dataset's assets, in manifest order).
pub fn asset_index(assets: &[ObjectAsset], name: &str) -> Option<usize> {
    assets.iter().position(|asset| asset.name == name)
}

/// The asset index of each object slot of a sequence (`None` for an empty slot); an error when a
/// slot names an object that is not among `assets`.
pub fn slot_assets(
    assets: &[ObjectAsset],
    sequence: &ProcessedSequence,
) -> Result<[Option<usize>; MAX_OBJECTS]> {
    let mut slots = [None; MAX_OBJECTS];
    for (slot, name) in sequence.object_names.iter().enumerate() {
        let Some(name) = name else { continue };
        slots[slot] = Some(asset_index(assets, name).ok_or_else(|| {
            DataError::invalid(
                format!("object of {}", sequence.source_id),
                "an object listed in the manifest",
                name,
            )
        })?);
    }
    Ok(slots)
}

impl ObjectAsset {
    /// The BPS offsets as the model reads them.
    ///
    /// # Shapes
    /// - returns `[points * 3]` (`[points, 3]` flattened)
    pub fn bps_features(&self) -> Vec<f32> {
        self.bps.iter().flat_map(|offset| offset.to_array()).collect()
    }
}

/// The BPS features of each slot's asset (zeros for an empty slot), checking that every asset
/// has `points` basis points (a run's `bps_points`).
///
/// # Shapes
/// - returns `[2, points * 3]` flattened
pub fn slot_bps(
    assets: &[ObjectAsset],
    slots: [Option<usize>; MAX_OBJECTS],
    points: usize,
) -> Result<Vec<f32>> {
    let width = points * 3;
    let mut bps = vec![0.0f32; MAX_OBJECTS * width];
    for (slot, asset) in slots.iter().enumerate() {
        let Some(asset) = asset.map(|index| &assets[index]) else { continue };
        if asset.bps.len() != points {
            return Err(DataError::invalid(
                format!("BPS of the {}", asset.name),
                format!("{points} basis points"),
                asset.bps.len(),
            ));
        }
        bps[slot * width..(slot + 1) * width].copy_from_slice(&asset.bps_features());
    }
    Ok(bps)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use dex2hoi_repr::object_repr::{MIXTURE_RANGE, ROTATION_RANGE};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    #[test]
    fn widths_and_ranges_fit_together() {
        for joints in [1, 22, 52, 65] {
            let layout = FeatureLayout::new(joints);
            assert_eq!(layout.body_width(), 6 * joints + 3);
            assert_eq!(layout.stream_width(), 6 * joints + 3 + 18);
            assert_eq!(layout.objects_width(), 36);
            assert_eq!(layout.body_range(), 0..layout.body_width());
            // The rotations, then the root, then the object tile the stream row.
            assert_eq!(layout.rotations_range().end, layout.root_range().start);
            assert_eq!(layout.root_range().end, layout.object_range().start);
            assert_eq!(layout.object_range().end, layout.stream_width());
            assert_eq!(layout.root_range().len(), ROOT_FEATURE_SIZE);
            assert_eq!(layout.object_range().len(), layout.object_width());
            assert_eq!(layout.joint_rotation_range(0).start, 0);
            assert_eq!(layout.joint_rotation_range(joints - 1).end, layout.rotations_range().end);
            assert_eq!(layout.object_part_range(ROTATION_RANGE).start, layout.body_width());
            assert_eq!(layout.object_part_range(MIXTURE_RANGE).end, layout.stream_width());
            // Consecutive rows follow each other.
            assert_eq!(layout.body_row(3).start, layout.body_row(2).end);
            assert_eq!(layout.object_row(2, 1).start, layout.object_row(2, 0).end);
            assert_eq!(layout.object_row(3, 0).start, layout.object_row(2, 1).end);
            assert_eq!(layout.stream_row(5, 1, 0).start, layout.stream_row(5, 0, 4).end);
            assert_eq!(layout.body_frames(2..4), layout.body_row(2).start..layout.body_row(3).end);
            assert_eq!(
                layout.object_frames(2..4),
                layout.object_row(2, 0).start..layout.object_row(3, 1).end
            );
        }
    }

    #[test]
    fn frame_and_stream_layouts_round_trip() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (joints, frames) in [(1, 1), (3, 7), (52, 5), (65, 0)] {
            let layout = FeatureLayout::new(joints);
            let body = random(&mut rng, frames * layout.body_width());
            let objects = random(&mut rng, frames * layout.objects_width());
            let streams = layout.frames_to_streams(&body, &objects).unwrap();
            assert_eq!(streams.len(), 2 * frames * layout.stream_width());
            for t in 0..frames {
                for s in 0..STREAMS {
                    let row = &streams[layout.stream_row(frames, s, t)];
                    assert_eq!(&row[layout.body_range()], &body[layout.body_row(t)]);
                    assert_eq!(&row[layout.object_range()], &objects[layout.object_row(t, s)]);
                }
            }
            let (body_back, objects_back) = layout.streams_to_frames(&streams).unwrap();
            assert_eq!((body_back, objects_back), (body.clone(), objects.clone()));
            // And stream-major rows with the same body in both streams survive the other way.
            assert_eq!(layout.frames_to_streams(&body, &objects).unwrap(), streams);
        }
    }

    #[test]
    fn going_back_reads_the_body_of_stream_a() {
        let layout = FeatureLayout::new(2);
        let mut streams = vec![0.0f32; 2 * 3 * layout.stream_width()];
        for (k, v) in streams.iter_mut().enumerate() {
            *v = k as f32;
        }
        let (body, objects) = layout.streams_to_frames(&streams).unwrap();
        assert_eq!(&body[layout.body_row(1)], &streams[layout.stream_row(3, 0, 1)][..15]);
        assert_eq!(
            &objects[layout.object_row(2, 1)],
            &streams[layout.stream_row(3, 1, 2)][layout.object_range()]
        );
        assert_eq!(layout.stream_objects_to_frames(&streams).unwrap(), objects);
    }

    #[test]
    fn mismatched_lengths_are_errors() {
        let layout = FeatureLayout::new(2);
        assert!(layout.frames_to_streams(&[0.0; 15], &[0.0; 35]).is_err());
        assert!(layout.frames_to_streams(&[0.0; 16], &[0.0; 36]).is_err());
        assert!(layout.frames_to_streams(&[0.0; 30], &[0.0; 36]).is_err());
        assert!(layout.streams_to_frames(&[0.0; 33 * 2 + 1]).is_err());
        assert_eq!(layout.frames_of(&[0.0; 30], &[0.0; 72]).unwrap(), 2);
    }

    #[test]
    fn tensor_slices_match_the_ranges() {
        let layout = FeatureLayout::new(3);
        let (b, t, d) = (2, 4, layout.stream_width());
        let values: Vec<f32> = (0..b * 2 * t * d).map(|k| k as f32).collect();
        let streams = Tensor::from_vec(values.clone(), (b, 2, t, d), &Device::Cpu).unwrap();
        let row = |i: usize, s: usize, k: usize| &values[((i * 2 + s) * t + k) * d..][..d];
        let body = layout.stream_body_of(&streams).unwrap();
        assert_eq!(body.dims(), [b, t, layout.body_width()]);
        let body = body.to_vec3::<f32>().unwrap();
        let rotations = layout.joint_rotations_of(&streams).unwrap();
        assert_eq!(rotations.dims(), [b, 2, t, 3, 6]);
        let rotations = rotations.flatten_from(3).unwrap();
        let root = layout.root_of(&streams).unwrap().flatten_all().unwrap();
        let object = layout.object_of(&streams).unwrap().flatten_all().unwrap();
        let (root, object) = (root.to_vec1::<f32>().unwrap(), object.to_vec1::<f32>().unwrap());
        for i in 0..b {
            for k in 0..t {
                assert_eq!(body[i][k], &row(i, 0, k)[layout.body_range()]);
                for s in 0..2 {
                    let n = (i * 2 + s) * t + k;
                    let r = rotations.get(i).unwrap().get(s).unwrap().get(k).unwrap();
                    assert_eq!(
                        r.to_vec1::<f32>().unwrap(),
                        &row(i, s, k)[layout.rotations_range()]
                    );
                    assert_eq!(&root[n * 3..n * 3 + 3], &row(i, s, k)[layout.root_range()]);
                    assert_eq!(&object[n * 18..n * 18 + 18], &row(i, s, k)[layout.object_range()]);
                }
            }
        }
    }
}
