//! `motion.npz`: a numpy archive of the motion (layout in `docs/FORMATS.md`, section "Exported
//! motions").
//!
//! Every skeleton gets its description (`skeleton`, `joint_names`, `parents`, `rest_offsets`),
//! the motion (`local_rotations`, `poses`, `root_positions`, `joints`), the objects, the text
//! and the frame rate. The SMPL-X skeleton also gets the parameters of the `smplx` Python
//! package's SMPL-X layer (`global_orient`, `body_pose`, the hand poses, `transl` and zero jaw,
//! eye and expression parameters), `float32`, shaped so that `model(**params)` takes them
//! as they are. Strings are numpy unicode arrays (`<U..`), so no array needs `allow_pickle`.
//!
//! The `.npy` members are written here (format version 1.0: magic, header dictionary padded to
//! 64 bytes, little-endian C-order data) and deflated into the zip archive with a fixed
//! timestamp, so the same motion always gives the same bytes.

use std::io::{Cursor, Write};
use std::path::Path;

use glam::Vec3;
use npyz::zip::write::FileOptions;
use npyz::zip::{CompressionMethod, DateTime, ZipWriter};

use dex2hoi_repr::SkeletonKind;
use dex2hoi_repr::rotation::matrix_to_axis_angle;

use crate::error::{ExportError, Result};
use crate::{Checked, ExportMotion, write_file};

/// Number of SMPL-X body joints after the pelvis in `body_pose` (joints 1-21).
pub const SMPLX_BODY_JOINTS: usize = 21;
/// Joints per hand in `left_hand_pose` and `right_hand_pose`.
pub const SMPLX_HAND_JOINTS: usize = 15;
/// Expression coefficients written (zeros) for the SMPL-X layer.
pub const SMPLX_EXPRESSION_COEFFICIENTS: usize = 10;

/// The first joint of the left hand in the 52-joint order (SMPL-X 25, after jaw and eyes).
const SMPLX52_LEFT_HAND: usize = 22;
/// The first joint of the right hand in the 52-joint order (SMPL-X 40).
const SMPLX52_RIGHT_HAND: usize = 37;

/// The values of one array.
#[derive(Debug, Clone, PartialEq)]
enum Values {
    F32(Vec<f32>),
    I64(Vec<i64>),
    Text(Vec<String>),
}

/// One named array of the archive.
#[derive(Debug, Clone, PartialEq)]
struct Array {
    name: &'static str,
    shape: Vec<usize>,
    values: Values,
}

impl Array {
    fn f32(name: &'static str, shape: &[usize], values: Vec<f32>) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), values.len(), "{name}");
        Self { name, shape: shape.to_vec(), values: Values::F32(values) }
    }

    fn i64(name: &'static str, shape: &[usize], values: Vec<i64>) -> Self {
        Self { name, shape: shape.to_vec(), values: Values::I64(values) }
    }

    fn text(name: &'static str, shape: &[usize], values: Vec<String>) -> Self {
        Self { name, shape: shape.to_vec(), values: Values::Text(values) }
    }

    /// The `.npy` bytes: magic, version 1.0, header, data.
    fn npy_bytes(&self) -> Vec<u8> {
        let descr = match &self.values {
            Values::F32(_) => "<f4".to_string(),
            Values::I64(_) => "<i8".to_string(),
            // numpy needs at least one character per element ('<U0' does not round-trip).
            Values::Text(texts) => {
                format!("<U{}", texts.iter().map(|t| t.chars().count()).max().unwrap_or(0).max(1))
            }
        };
        let shape = match self.shape.as_slice() {
            [] => "()".to_string(),
            [n] => format!("({n},)"),
            dims => {
                format!("({})", dims.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "))
            }
        };
        let mut header =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        // Magic (6) + version (2) + header length (2) + header + '\n', padded to 64 bytes.
        let unpadded = 10 + header.len() + 1;
        header.push_str(&" ".repeat(unpadded.next_multiple_of(64) - unpadded));
        header.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let header_length = u16::try_from(header.len()).unwrap_or(u16::MAX);
        bytes.extend_from_slice(&header_length.to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        match &self.values {
            Values::F32(values) => values.iter().for_each(|v| bytes.extend(v.to_le_bytes())),
            Values::I64(values) => values.iter().for_each(|v| bytes.extend(v.to_le_bytes())),
            Values::Text(texts) => {
                let width = descr[2..].parse::<usize>().unwrap_or(1);
                for text in texts {
                    let mut chars = text.chars().map(u32::from).collect::<Vec<_>>();
                    chars.resize(width, 0);
                    chars.iter().for_each(|c| bytes.extend(c.to_le_bytes()));
                }
            }
        }
        bytes
    }
}

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
    }
    out
}

fn zip_error(error: impl std::fmt::Display) -> ExportError {
    ExportError::invalid("npz archive", "an archive written in memory", error)
}

/// The bytes of `motion.npz` for a motion (layout in the module documentation and
/// `docs/FORMATS.md`).
///
/// # Shapes
/// - the motion's `local_rotations`: `[frames * joints]`; `root_positions`: `[frames]`; each
///   exported object's slot: `[frames]` rotations and positions
pub fn encode_npz(motion: &ExportMotion<'_>) -> Result<Vec<u8>> {
    let checked = motion.check()?;
    let options = FileOptions::default()
        .compression_method(CompressionMethod::Deflated)
        .last_modified_time(DateTime::default());
    let mut zip = ZipWriter::new(Cursor::new(Vec::new()));
    for array in arrays(&checked) {
        zip.start_file(format!("{}.npy", array.name), options).map_err(zip_error)?;
        zip.write_all(&array.npy_bytes()).map_err(zip_error)?;
    }
    Ok(zip.finish().map_err(zip_error)?.into_inner())
}

/// Writes `motion.npz` atomically (see [`encode_npz`]).
///
/// # Shapes
/// - as [`encode_npz`]
pub fn write_npz(path: &Path, motion: &ExportMotion<'_>) -> Result<()> {
    let bytes = encode_npz(motion)?;
    write_file(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_padded_to_64_bytes_and_ends_with_a_newline() {
        for array in [
            Array::f32("a", &[2, 3], vec![0.0; 6]),
            Array::f32("b", &[], vec![1.5]),
            Array::text("c", &[2], vec!["ab".into(), "".into()]),
            Array::i64("d", &[0], vec![]),
        ] {
            let bytes = array.npy_bytes();
            let header_length = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
            assert_eq!((10 + header_length) % 64, 0);
            assert_eq!(bytes[10 + header_length - 1], b'\n');
        }
    }

    #[test]
    fn npy_bytes_read_back_with_npyz() {
        let array = Array::f32("a", &[2, 3], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        let bytes = array.npy_bytes();
        let file = npyz::NpyFile::new(&bytes[..]).expect("a valid npy file");
        assert_eq!(file.shape(), &[2, 3]);
        assert_eq!(file.into_vec::<f32>().expect("f32 data"), vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        let text = Array::text("t", &[2], vec!["héllo".into(), "a".into()]);
        let bytes = text.npy_bytes();
        let file = npyz::NpyFile::new(&bytes[..]).expect("a valid npy file");
        assert_eq!(file.dtype().descr(), "'<U5'");
        assert_eq!(file.into_vec::<String>().expect("strings"), vec!["héllo", "a"]);
    }
}
