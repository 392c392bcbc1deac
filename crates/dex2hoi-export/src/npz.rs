//! `motion.npz`: a numpy archive of the motion (layout in `docs/FORMATS.md`, section "Exported
//! motions").
//!
//! Every skeleton gets its description (`skeleton`, `joint_names`, `parents`, `rest_offsets`),
//! the motion (`local_rotations`, `poses`, `root_positions`, `joints`), the objects, the text
//! and the frame rate. The SMPL-X skeleton also gets the parameters of the `smplx` Python
//! package's SMPL-X layer (`global_orient`, `body_pose`, the hand poses, `transl` and zero jaw,
//! eye and expression parameters), `float32`, shaped so that `model(**params)` takes them
//! as they are; a motion skinned to a user's SMPL-X model also gets its `betas`. Strings are numpy unicode arrays (`<U..`), so no array needs `allow_pickle`.
//!
//! The archive is written by `dex2hoi_data::npz` (fixed timestamp: the same motion always gives
//! the same bytes).

use std::path::Path;

use glam::Vec3;

use dex2hoi_data::npz::{NpyArray as Array, encode_npz as encode_arrays};

use dex2hoi_repr::SkeletonKind;
use dex2hoi_repr::rotation::matrix_to_axis_angle;

use crate::error::Result;
use crate::{Checked, ExportMotion, write_file};

/// Number of SMPL-X body joints after the pelvis in `body_pose` (joints 1-21).
pub const SMPLX_BODY_JOINTS: usize = 21;
/// Joints per hand in `left_hand_pose` and `right_hand_pose`.
pub const SMPLX_HAND_JOINTS: usize = 15;
/// Expression coefficients written (zeros) for the SMPL-X layer.
pub const SMPLX_EXPRESSION_COEFFICIENTS: usize = 10;

/// Body-shape coefficients of the `smplx` layer by default (`num_betas=10`): `betas` has at
/// least this many columns.
pub const SMPLX_DEFAULT_BETAS: usize = 10;

/// The first joint of the left hand in the 52-joint order (SMPL-X 25, after jaw and eyes).
const SMPLX52_LEFT_HAND: usize = 22;
/// The first joint of the right hand in the 52-joint order (SMPL-X 40).
const SMPLX52_RIGHT_HAND: usize = 37;

fn flatten(vectors: impl IntoIterator<Item = Vec3>) -> Vec<f32> {
    vectors.into_iter().flat_map(|v| v.to_array()).collect()
}

/// Row-major matrix entries (`R[row][column]`), as numpy reads a `(3, 3)` array.
fn row_major(matrices: impl IntoIterator<Item = glam::Mat3>) -> Vec<f32> {
    matrices.into_iter().flat_map(|m| m.transpose().to_cols_array()).collect()
}

/// Axis-angle of the given joints of every frame, `[frames, joints.len() * 3]`.
fn axis_angles(motion: &Checked<'_>, joints: std::ops::Range<usize>) -> Vec<f32> {
    let count = motion.skeleton.joint_count();
    (0..motion.frames)
        .flat_map(|t| joints.clone().map(move |j| t * count + j))
        .flat_map(|i| matrix_to_axis_angle(motion.local_rotations[i]).to_array())
        .collect()
}

/// The arrays of the archive, in the order they are written.
fn arrays(motion: &Checked<'_>) -> Vec<Array> {
    let skeleton = motion.skeleton;
    let (frames, joints, objects) = (motion.frames, skeleton.joint_count(), motion.objects.len());
    let parents = skeleton.parents().iter().map(|p| p.map_or(-1, |p| p as i64)).collect();
    let mut out = vec![
        Array::text("skeleton", &[], vec![skeleton.kind().name().to_string()]),
        Array::text("joint_names", &[joints], skeleton.joint_names().to_vec()),
        Array::i64("parents", &[joints], parents),
        Array::f32("rest_offsets", &[joints, 3], flatten(skeleton.rest_offsets().iter().copied())),
        Array::f32(
            "local_rotations",
            &[frames, joints, 3, 3],
            row_major(motion.local_rotations.iter().copied()),
        ),
        Array::f32("poses", &[frames, joints, 3], axis_angles(motion, 0..joints)),
        Array::f32("root_positions", &[frames, 3], flatten(motion.root_positions.iter().copied())),
        Array::f32("joints", &[frames, joints, 3], flatten(motion.fk.positions.iter().copied())),
        Array::text("text", &[], vec![motion.text.to_string()]),
        Array::f32("fps", &[], vec![motion.fps]),
        Array::text(
            "object_names",
            &[objects],
            motion.objects.iter().map(|o| o.name.to_string()).collect(),
        ),
        Array::i64(
            "object_slots",
            &[objects],
            motion.objects.iter().map(|o| o.slot as i64).collect(),
        ),
        Array::f32(
            "object_rotations",
            &[objects, frames, 3, 3],
            row_major(motion.objects.iter().flat_map(|o| o.rotations.iter().copied())),
        ),
        Array::f32(
            "object_translations",
            &[objects, frames, 3],
            flatten(motion.objects.iter().flat_map(|o| o.positions.iter().copied())),
        ),
    ];
    if skeleton.kind() == SkeletonKind::Smplx52 {
        let pelvis_rest = skeleton.rest_offsets()[0];
        let zeros = |width: usize| vec![0.0; frames * width];
        out.extend([
            Array::f32("global_orient", &[frames, 3], axis_angles(motion, 0..1)),
            Array::f32(
                "body_pose",
                &[frames, 3 * SMPLX_BODY_JOINTS],
                axis_angles(motion, 1..1 + SMPLX_BODY_JOINTS),
            ),
            Array::f32(
                "left_hand_pose",
                &[frames, 3 * SMPLX_HAND_JOINTS],
                axis_angles(motion, SMPLX52_LEFT_HAND..SMPLX52_LEFT_HAND + SMPLX_HAND_JOINTS),
            ),
            Array::f32(
                "right_hand_pose",
                &[frames, 3 * SMPLX_HAND_JOINTS],
                axis_angles(motion, SMPLX52_RIGHT_HAND..SMPLX52_RIGHT_HAND + SMPLX_HAND_JOINTS),
            ),
            Array::f32("jaw_pose", &[frames, 3], zeros(3)),
            Array::f32("leye_pose", &[frames, 3], zeros(3)),
            Array::f32("reye_pose", &[frames, 3], zeros(3)),
            Array::f32(
                "expression",
                &[frames, SMPLX_EXPRESSION_COEFFICIENTS],
                zeros(SMPLX_EXPRESSION_COEFFICIENTS),
            ),
            // The SMPL-X layer rotates about the rest pelvis and then adds `transl`.
            Array::f32(
                "transl",
                &[frames, 3],
                flatten(motion.root_positions.iter().map(|&root| root - pelvis_rest)),
            ),
            Array::f32("pelvis_rest", &[3], pelvis_rest.to_array().to_vec()),
        ]);
        if let Some(betas) = motion.body.and_then(|b| b.betas()) {
            // The shape the skeleton was made from, per frame as the layer takes it (at least
            // the layer's default number of coefficients, zeros after the given ones).
            let count = betas.len().max(SMPLX_DEFAULT_BETAS);
            let mut row = betas.to_vec();
            row.resize(count, 0.0);
            out.push(Array::f32("betas", &[frames, count], row.repeat(frames)));
        }
    }
    out
}

/// The bytes of `motion.npz` for a motion (layout in the module documentation and
/// `docs/FORMATS.md`).
///
/// # Shapes
/// - the motion's `local_rotations`: `[frames * joints]`; `root_positions`: `[frames]`; each
///   exported object's slot: `[frames]` rotations and positions
pub fn encode_npz(motion: &ExportMotion<'_>) -> Result<Vec<u8>> {
    let checked = motion.check()?;
    Ok(encode_arrays(&arrays(&checked))?)
}

/// Writes `motion.npz` atomically (see [`encode_npz`]).
///
/// # Shapes
/// - as [`encode_npz`]
pub fn write_npz(path: &Path, motion: &ExportMotion<'_>) -> Result<()> {
    let bytes = encode_npz(motion)?;
    write_file(path, &bytes)
}
