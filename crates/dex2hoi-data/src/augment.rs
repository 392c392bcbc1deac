//! Augmentation on extracted features: swapping the two streams and mirroring left/right
//! (InterGen's augmentations, docs/CONVENTIONS.md, "Augmentation"). Both are exact and their own
//! inverse.
//!
//! Mirroring reflects the scene in the sagittal plane (`x -> -x`): joints trade places with their
//! mirror joints (the skeleton's symmetry map), rotations `R -> M R M` with `M = diag(-1, 1, 1)`,
//! positions `p -> M p`, the left and right wrist offsets trade places (`delta_L' = M delta_R`),
//! so do the left and right mixture logits, hand contacts and feet, and the words "left" and
//! "right" in the texts. Object meshes are not changed: the catalogue's objects are symmetric
//! under the reflection; for an asymmetric mesh the mirrored sequence shows its mirror image.

use glam::{Mat3, Vec3};

use dex2hoi_repr::object_repr::{
    GLOBAL_POSITION_RANGE, LEFT_OFFSET_RANGE, MIXTURE_RANGE, OBJECT_FEATURE_SIZE,
    RIGHT_OFFSET_RANGE, ROTATION_RANGE,
};
use dex2hoi_repr::{Mesh, Skeleton};

use crate::features::ProcessedSequence;
use crate::layout::{slot_frames, slot_range};
use crate::sequence::{MAX_OBJECTS, Sequence};

/// Swaps the object slots: stream A becomes stream B and back.
pub fn swap_streams(sequence: &ProcessedSequence) -> ProcessedSequence {
    let mut out = sequence.clone();
    let frames = sequence.frames;
    let swap = |values: &mut Vec<f32>, per_slot: usize| {
        for t in 0..frames {
            let row = &mut values[slot_frames(t..t + 1, per_slot)];
            let (a, b) = row.split_at_mut(per_slot);
            a.swap_with_slice(b);
        }
    };
    let hand = sequence.hand_distances.len() / (frames * MAX_OBJECTS).max(1);
    swap(&mut out.objects, OBJECT_FEATURE_SIZE);
    swap(&mut out.hand_distances, hand);
    swap(&mut out.hand_contact, 2);
    swap(&mut out.object_rotations, 9);
    swap(&mut out.object_positions, 3);
    out.object_present.swap(0, 1);
    out.object_names.swap(0, 1);
    out
}

/// The 6D form of `M R M` from the 6D form of `R` (first two rows).
fn mirror_sixd(sixd: &[f32]) -> [f32; 6] {
    [sixd[0], -sixd[1], -sixd[2], -sixd[3], sixd[4], sixd[5]]
}

/// Words that name a side, each with its mirror image; a capitalised or upper-case form is
/// swapped for the same form of its image. Other words that begin with a side ("leftover",
/// "rights") are left as they are.
const MIRRORED_WORDS: [(&str, &str); 3] =
    [("left", "right"), ("leftwards", "rightwards"), ("leftward", "rightward")];

/// The mirror image of one word ([`MIRRORED_WORDS`]), or the word itself.
fn mirror_word(word: &str) -> String {
    let lower = word.to_lowercase();
    let Some(image) = MIRRORED_WORDS.iter().find_map(|&(a, b)| {
        if lower == a {
            Some(b)
        } else if lower == b {
            Some(a)
        } else {
            None
        }
    }) else {
        return word.to_string();
    };
    if word.chars().all(char::is_uppercase) {
        image.to_uppercase()
    } else if word.starts_with(char::is_uppercase) {
        let mut chars = image.chars();
        chars.next().map(|c| c.to_uppercase().chain(chars).collect()).unwrap_or_default()
    } else {
        image.to_string()
    }
}

/// Swaps the words that name a side ([`MIRRORED_WORDS`]: "left" and "right", "leftwards" and
/// "rightwards", ...), keeping their capitalisation.
pub fn mirror_text(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        out.push_str(&mirror_word(word));
        word.clear();
    };
    for c in text.chars() {
        if c.is_alphabetic() {
            word.push(c);
        } else {
            flush(&mut word, &mut out);
            out.push(c);
        }
    }
    flush(&mut word, &mut out);
    out
}

/// Mirrors a sequence left/right (see the module documentation).
pub fn mirror(sequence: &ProcessedSequence, skeleton: &Skeleton) -> ProcessedSequence {
    let mut out = sequence.clone();
    let frames = sequence.frames;
    let joints = sequence.joints;
    let symmetry = skeleton.symmetry();
    let layout = sequence.layout();
    let m3 = |v: &[f32]| [-v[0], v[1], v[2]];
    for t in 0..frames {
        let row = &sequence.body[layout.body_row(t)];
        let new = &mut out.body[layout.body_row(t)];
        for j in 0..joints {
            let m = symmetry[j];
            new[layout.joint_rotation_range(j)]
                .copy_from_slice(&mirror_sixd(&row[layout.joint_rotation_range(m)]));
            let p = &sequence.joint_positions[(t * joints + m) * 3..(t * joints + m) * 3 + 3];
            out.joint_positions[(t * joints + j) * 3..(t * joints + j) * 3 + 3]
                .copy_from_slice(&m3(p));
        }
        new[layout.root_range()].copy_from_slice(&m3(&row[layout.root_range()]));
        for slot in 0..MAX_OBJECTS {
            let o = &sequence.objects[layout.object_row(t, slot)];
            let n = &mut out.objects[layout.object_row(t, slot)];
            n[ROTATION_RANGE].copy_from_slice(&mirror_sixd(&o[ROTATION_RANGE]));
            n[LEFT_OFFSET_RANGE].copy_from_slice(&m3(&o[RIGHT_OFFSET_RANGE]));
            n[RIGHT_OFFSET_RANGE].copy_from_slice(&m3(&o[LEFT_OFFSET_RANGE]));
            n[GLOBAL_POSITION_RANGE].copy_from_slice(&m3(&o[GLOBAL_POSITION_RANGE]));
            let alpha = &o[MIXTURE_RANGE];
            n[MIXTURE_RANGE].copy_from_slice(&[alpha[1], alpha[0], alpha[2]]);
            let c = slot_range(t, slot, 2).start;
            out.hand_contact[c] = sequence.hand_contact[c + 1];
            out.hand_contact[c + 1] = sequence.hand_contact[c];
            let r = slot_range(t, slot, 9).start;
            let rot = &sequence.object_rotations[slot_range(t, slot, 9)];
            // (M R M)_ik = m_i R_ik m_k with m = (-1, 1, 1).
            for i in 0..3 {
                for k in 0..3 {
                    let sign = if (i == 0) ^ (k == 0) { -1.0 } else { 1.0 };
                    out.object_rotations[r + 3 * i + k] = sign * rot[3 * i + k];
                }
            }
            out.object_positions[slot_range(t, slot, 3)]
                .copy_from_slice(&m3(&sequence.object_positions[slot_range(t, slot, 3)]));
        }
        let f = &sequence.foot_contact[t * 4..t * 4 + 4];
        out.foot_contact[t * 4..t * 4 + 4].copy_from_slice(&[f[2], f[3], f[0], f[1]]);
    }
    // Hand-joint distances: each joint takes its mirror joint's distance.
    let groups = skeleton.groups();
    let hand_joints: Vec<usize> =
        groups.left_hand.iter().chain(&groups.right_hand).copied().collect();
    let h = hand_joints.len();
    let source: Vec<usize> = hand_joints
        .iter()
        .map(|&j| hand_joints.iter().position(|&k| k == symmetry[j]).unwrap_or(0))
        .collect();
    for row in 0..frames * MAX_OBJECTS {
        for k in 0..h {
            out.hand_distances[row * h + k] = sequence.hand_distances[row * h + source[k]];
        }
    }
    out.root_start.x = -sequence.root_start.x;
    out.rest_offsets = skeleton.mirror_offsets(&sequence.rest_offsets);
    out.texts = sequence.texts.iter().map(|t| mirror_text(t)).collect();
    out.held_out_texts = sequence.held_out_texts.iter().map(|t| mirror_text(t)).collect();
    out
}

/// `M R M` with `M = diag(-1, 1, 1)`.
fn mirror_matrix(r: Mat3) -> Mat3 {
    let m = Mat3::from_diagonal(Vec3::new(-1.0, 1.0, 1.0));
    m * r * m
}

/// Mirrors a raw sequence left/right: the same reflection as [`mirror`], before features. The
/// body is mirrored too ([`Skeleton::mirrored`]), so an asymmetric subject stays exact; object
/// meshes are reflected (with their triangles reversed so that they still face outward).
pub fn mirror_sequence(sequence: &Sequence) -> Sequence {
    let mut out = sequence.clone();
    out.skeleton = sequence.skeleton.mirrored();
    let joints = sequence.skeleton.joint_count();
    let symmetry = sequence.skeleton.symmetry();
    let reflect = |p: Vec3| Vec3::new(-p.x, p.y, p.z);
    for t in 0..sequence.frames() {
        for j in 0..joints {
            out.local_rotations[t * joints + j] =
                mirror_matrix(sequence.local_rotations[t * joints + symmetry[j]]);
        }
        out.root_positions[t] = reflect(sequence.root_positions[t]);
    }
    for object in &mut out.objects {
        object.rotations.iter_mut().for_each(|r| *r = mirror_matrix(*r));
        object.translations.iter_mut().for_each(|p| *p = reflect(*p));
        object.mesh = Mesh {
            vertices: object.mesh.vertices.iter().map(|v| reflect(*v)).collect(),
            faces: object.mesh.faces.iter().map(|f| [f[0], f[2], f[1]]).collect(),
        };
    }
    out.texts = sequence.texts.iter().map(|t| mirror_text(t)).collect();
    out
}
