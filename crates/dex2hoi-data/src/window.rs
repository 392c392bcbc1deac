//! Resampling to the target frame rate and cutting sequences into training windows of
//! `T_p + T_f` frames (a clean prefix and the predicted frames;
//! docs/CONVENTIONS.md, "Frame rate and windows").

use glam::{Mat3, Quat, Vec3};

use crate::error::{DataError, Result};
use crate::features::ProcessedSequence;
use crate::sequence::Sequence;

/// Window sizes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowConfig {
    /// Clean prefix frames `T_p` (default 20: 1 s at 20 fps).
    pub prefix_frames: usize,
    /// Predicted frames `T_f` (default 40: 2 s).
    pub predicted_frames: usize,
    /// Frames between window starts (default 10).
    pub stride: usize,
}

impl Default for WindowConfig {
    fn default() -> Self {
        Self { prefix_frames: 20, predicted_frames: 40, stride: 10 }
    }
}

impl WindowConfig {
    /// `T_p + T_f`.
    pub fn length(&self) -> usize {
        self.prefix_frames + self.predicted_frames
    }
}

/// One window of one sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// Index of the sequence.
    pub sequence: usize,
    /// First frame.
    pub start: usize,
    /// Frames of real data in the window; the rest (up to the window length) is padding that
    /// repeats the last frame and is masked out.
    pub valid_frames: usize,
}

impl Window {
    /// The mask of the window: 1 for real frames, 0 for padding.
    pub fn mask(&self, config: &WindowConfig) -> Vec<f32> {
        (0..config.length()).map(|k| if k < self.valid_frames { 1.0 } else { 0.0 }).collect()
    }

    /// The frame of the sequence to read at window position `k` (padding repeats the last).
    pub fn frame(&self, k: usize) -> usize {
        self.start + k.min(self.valid_frames.saturating_sub(1))
    }

    /// The window's `length` frames of a processed sequence (padding repeats the last real
    /// frame), every per-frame array cut alike.
    ///
    /// # Shapes
    /// - every frame-major array `[T, ...]` of `sequence` becomes `[length, ...]`
    pub fn cut(&self, sequence: &ProcessedSequence, length: usize) -> ProcessedSequence {
        // Every per-frame array is frame-major, so a frame is a contiguous run of
        // `len / frames` numbers whatever its inner shape.
        let per_frame = |values: &[f32]| -> Vec<f32> {
            let width = values.len() / sequence.frames.max(1);
            (0..length).flat_map(|k| &values[self.frame(k) * width..][..width]).copied().collect()
        };
        ProcessedSequence {
            frames: length,
            joints: sequence.joints,
            body: per_frame(&sequence.body),
            objects: per_frame(&sequence.objects),
            object_present: sequence.object_present,
            object_names: sequence.object_names.clone(),
            joint_positions: per_frame(&sequence.joint_positions),
            hand_distances: per_frame(&sequence.hand_distances),
            hand_contact: per_frame(&sequence.hand_contact),
            foot_contact: per_frame(&sequence.foot_contact),
            object_rotations: per_frame(&sequence.object_rotations),
            object_positions: per_frame(&sequence.object_positions),
            root_start: sequence.root_start,
            rest_offsets: sequence.rest_offsets.clone(),
            texts: sequence.texts.clone(),
            held_out_texts: sequence.held_out_texts.clone(),
            action: sequence.action.clone(),
            source_id: sequence.source_id.clone(),
        }
    }
}

/// All windows of sequences with the given frame counts: starts `0, stride, ...` while a full
/// window fits, plus one window ending at the last frame; a sequence shorter than a window
/// gives one padded window.
pub fn windows(frame_counts: &[usize], config: &WindowConfig) -> Result<Vec<Window>> {
    if config.stride == 0 || config.predicted_frames == 0 {
        return Err(DataError::invalid(
            "window config",
            "a positive stride and predicted frames",
            format!("{config:?}"),
        ));
    }
    let length = config.length();
    let mut out = Vec::new();
    for (sequence, &frames) in frame_counts.iter().enumerate() {
        if frames == 0 {
            continue;
        }
        if frames <= length {
            out.push(Window { sequence, start: 0, valid_frames: frames });
            continue;
        }
        let mut start = 0;
        while start + length <= frames {
            out.push(Window { sequence, start, valid_frames: length });
            start += config.stride;
        }
        if start - config.stride + length < frames {
            out.push(Window { sequence, start: frames - length, valid_frames: length });
        }
    }
    Ok(out)
}

fn slerp(a: Mat3, b: Mat3, s: f32) -> Mat3 {
    Mat3::from_quat(Quat::from_mat3(&a).slerp(Quat::from_mat3(&b), s))
}

/// Resamples a sequence to `fps`: rotations by slerp, positions linearly, over the same
/// duration (the last frame time is `floor((T - 1) * fps / source_fps)` frames at the new rate).
pub fn resample(sequence: &Sequence, fps: f32) -> Result<Sequence> {
    sequence.validate()?;
    if !(fps > 0.0 && fps.is_finite()) {
        return Err(DataError::invalid(&sequence.source_id, "a positive target frame rate", fps));
    }
    let source_frames = sequence.frames();
    let duration = (source_frames - 1) as f32 / sequence.fps;
    let frames = (duration * fps + 1e-4).floor() as usize + 1;
    let joints = sequence.skeleton.joint_count();
    let sample = |k: usize| {
        let position = k as f32 / fps * sequence.fps;
        let i = (position.floor() as usize).min(source_frames - 1);
        let next = (i + 1).min(source_frames - 1);
        (i, next, position - i as f32)
    };
    let mut out = sequence.clone();
    out.fps = fps;
    out.local_rotations = Vec::with_capacity(frames * joints);
    out.root_positions = Vec::with_capacity(frames);
    for k in 0..frames {
        let (i, next, s) = sample(k);
        for j in 0..joints {
            out.local_rotations.push(slerp(
                sequence.local_rotations[i * joints + j],
                sequence.local_rotations[next * joints + j],
                s,
            ));
        }
        out.root_positions.push(sequence.root_positions[i].lerp(sequence.root_positions[next], s));
    }
    for (object, source) in out.objects.iter_mut().zip(&sequence.objects) {
        object.rotations = (0..frames)
            .map(|k| {
                let (i, next, s) = sample(k);
                slerp(source.rotations[i], source.rotations[next], s)
            })
            .collect();
        object.translations = (0..frames)
            .map(|k| {
                let (i, next, s) = sample(k);
                let (a, b): (Vec3, Vec3) = (source.translations[i], source.translations[next]);
                a.lerp(b, s)
            })
            .collect();
    }
    Ok(out)
}
