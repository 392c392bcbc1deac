//! A Mixamo-rigged character of the user's (a glTF skin, read by `dex2hoi-import`) to dress a
//! Mixamo-65 motion in: the motion is posed on the character's own rest skeleton, and
//! `motion.glb` carries the character's skinned mesh and its bones in their own frames, so it
//! drops onto the character's rig by bone name.
//!
//! The motion's local rotations are relative to the Mixamo T-pose of the built-in skeleton, so
//! the character must stand in that T-pose at rest (every Mixamo auto-rig does): a bone whose
//! rest direction is more than [`REST_POSE_TOLERANCE_DEGREES`] from the built-in skeleton's is
//! refused, as is a character that lacks a bone the motion turns. Bones of the skin that the
//! motion does not have (eyes, props) stay at rest under their parents; end bones the motion
//! has and the character lacks (`HeadTop_End`, the fourth finger bones, `Toe_End`) take the
//! built-in skeleton's offsets.

use std::path::PathBuf;

use glam::{Mat3, Mat4, Quat, Vec3};

use dex2hoi_repr::skeleton::MIXAMO_PREFIX;
use dex2hoi_repr::{Skeleton, SkeletonKind};

use crate::error::{ExportError, Result};

/// How far (degrees) a bone of the character's rest pose may point from the built-in
/// skeleton's T-pose.
pub const REST_POSE_TOLERANCE_DEGREES: f32 = 25.0;

/// The range of hip heights (metres) a character standing in its rest pose is taken to have:
/// outside it, the file's units are not metres.
const HIPS_HEIGHT_RANGE: std::ops::RangeInclusive<f32> = 0.3..=3.0;

/// A bone of the character's skin: its name, its parent bone (index into the same list) and its
/// world rest transform (metres, Y up; scale allowed).
#[derive(Debug, Clone, PartialEq)]
pub struct RigBone {
    /// The bone's name (`mixamorig:LeftArm` or `LeftArm`).
    pub name: String,
    /// The nearest ancestor that is a bone of the skin.
    pub parent: Option<usize>,
    /// World rest transform.
    pub rest: Mat4,
}

/// A bone of the character that the motion does not drive, kept at rest under its parent.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtraJoint {
    /// The bone's name in the character.
    pub name: String,
    /// Its parent among the skin joints (the skeleton's joints, then the extra joints).
    pub parent: usize,
    /// World rest position.
    pub rest_position: Vec3,
    /// World rest orientation of its bone frame.
    pub orientation: Quat,
}

/// A character ready to skin in `motion.glb`.
#[derive(Debug, Clone, PartialEq)]
pub struct CharacterMesh {
    /// The file it came from.
    pub path: PathBuf,
    /// The motion's topology on the character's rest offsets: pose the motion on it.
    pub skeleton: Skeleton,
    /// The character's name of each skeleton joint's bone (with or without `mixamorig:`, as
    /// the character names its bones).
    pub bone_names: Vec<String>,
    /// World rest orientation of each skeleton joint's bone in the character.
    pub orientations: Vec<Quat>,
    /// The skin's other bones (skin joints `J..`), each after its parent.
    pub extra_joints: Vec<ExtraJoint>,
    /// Rest vertices (world, metres, Y up).
    pub vertices: Vec<Vec3>,
    /// Unit vertex normals of the rest mesh (area-weighted face normals).
    pub normals: Vec<Vec3>,
    /// Triangles.
    pub faces: Vec<[u32; 3]>,
    /// Skin joints of each vertex: `0..J` the skeleton's joints, then the extra joints.
    pub joints: Vec<[u16; 4]>,
    /// Their weights, each row summing to 1.
    pub weights: Vec<[f32; 4]>,
}

/// The unit-scale rotation of a transform whose columns may be scaled.
fn rotation_of(matrix: &Mat4) -> Quat {
    let m = Mat3::from_mat4(*matrix);
    let columns = [m.x_axis, m.y_axis, m.z_axis].map(|c| c.normalize_or_zero());
    Quat::from_mat3(&Mat3::from_cols(columns[0], columns[1], columns[2])).normalize()
}

impl CharacterMesh {
    /// Builds the character from its skin's bones and its rest mesh (vertices skinned to the
    /// bones' rest transforms, with skin joints indexing `bones`), for motions on `motion`'s
    /// topology (Mixamo-65). `path` names the file in errors.
    pub fn new(
        path: PathBuf,
        motion: &Skeleton,
        bones: &[RigBone],
        vertices: Vec<Vec3>,
        faces: Vec<[u32; 3]>,
        joints: &[[u16; 4]],
        weights: &[[f32; 4]],
    ) -> Result<Self> {
        let context = || format!("character {}", path.display());
        if motion.kind() != SkeletonKind::Mixamo65 {
            return Err(ExportError::invalid(
                context(),
                "a motion on the mixamo65 skeleton (a model trained on Mixamo data, such as HUMOTO)",
                format!("a {} motion", motion.kind().name()),
            ));
        }
        let bare = |name: &str| name.strip_prefix(MIXAMO_PREFIX).unwrap_or(name).to_string();
        let names: Vec<String> = bones.iter().map(|b| bare(&b.name)).collect();
        let count = motion.joint_count();
        // Our joints found among the bones, by Mixamo name.
        let found: Vec<Option<usize>> =
            motion.joint_names().iter().map(|name| names.iter().position(|n| n == name)).collect();
        let children = motion.children();
        let missing: Vec<String> = (0..count)
            .filter(|&j| found[j].is_none() && !children[j].is_empty())
            .map(|j| format!("{MIXAMO_PREFIX}{}", motion.joint_names()[j]))
            .collect();
        if !missing.is_empty() {
            return Err(ExportError::invalid(
                context(),
                "every bone the motion turns, by Mixamo name (with or without `mixamorig:`)",
                format!("no {}", missing.join(", ")),
            ));
        }
        // Rest positions and bone frames of our joints; a missing end bone sits where the
        // built-in offset puts it, turned with its parent.
        let builtin = motion.rest_offsets();
        let mut positions = vec![Vec3::ZERO; count];
        let mut orientations = vec![Quat::IDENTITY; count];
        for joint in 0..count {
            match (found[joint], motion.parents()[joint]) {
                (Some(bone), _) => {
                    positions[joint] = bones[bone].rest.w_axis.truncate();
                    orientations[joint] = rotation_of(&bones[bone].rest);
                }
                (None, Some(parent)) => {
                    positions[joint] = positions[parent] + builtin[joint];
                    orientations[joint] = orientations[parent];
                }
                (None, None) => unreachable!("the root has children, so it was found"),
            }
        }
        let hips = positions[0].y;
        if !HIPS_HEIGHT_RANGE.contains(&hips) {
            return Err(ExportError::invalid(
                context(),
                format!(
                    "a character in metres, hips {:.1} to {:.1} m above the floor at rest",
                    HIPS_HEIGHT_RANGE.start(),
                    HIPS_HEIGHT_RANGE.end()
                ),
                format!("hips at {hips:.3} (of the file's units)"),
            ));
        }
        // The rest pose must be the motion's T-pose.
        for joint in 1..count {
            let parent = motion.parents()[joint].expect("only the root has no parent");
            let ours = positions[joint] - positions[parent];
            let theirs = builtin[joint];
            if ours.length() < 1e-4 || theirs.length() < 1e-4 {
                continue;
            }
            let angle = ours.angle_between(theirs).to_degrees();
            if angle > REST_POSE_TOLERANCE_DEGREES {
                return Err(ExportError::invalid(
                    context(),
                    format!(
                        "a rest pose within {REST_POSE_TOLERANCE_DEGREES} degrees of the Mixamo \
                         T-pose the motion is relative to"
                    ),
                    format!(
                        "{}{} {angle:.0} degrees away",
                        MIXAMO_PREFIX,
                        motion.joint_names()[joint]
                    ),
                ));
            }
        }
        let offsets: Vec<Vec3> = (0..count)
            .map(|j| match motion.parents()[j] {
                Some(p) => positions[j] - positions[p],
                None => positions[j],
            })
            .collect();
        let skeleton = motion.with_rest_offsets(offsets)?;
        let prefixed = bones.iter().any(|b| b.name.starts_with(MIXAMO_PREFIX));
        let bone_names: Vec<String> = (0..count)
            .map(|j| match found[j] {
                Some(bone) => bones[bone].name.clone(),
                None if prefixed => format!("{MIXAMO_PREFIX}{}", motion.joint_names()[j]),
                None => motion.joint_names()[j].clone(),
            })
            .collect();
        // The other bones, parents first, each under its nearest kept ancestor.
        let mut skin_joint: Vec<Option<usize>> = vec![None; bones.len()];
        for (joint, bone) in found.iter().enumerate() {
            if let Some(bone) = bone {
                skin_joint[*bone] = Some(joint);
            }
        }
        let mut extra_joints = Vec::new();
        loop {
            let mut placed_any = false;
            for (bone, rig_bone) in bones.iter().enumerate() {
                if skin_joint[bone].is_some() {
                    continue;
                }
                let parent = match rig_bone.parent {
                    None => Some(0),
                    Some(p) => skin_joint[p],
                };
                let Some(parent) = parent else { continue };
                skin_joint[bone] = Some(count + extra_joints.len());
                extra_joints.push(ExtraJoint {
                    name: rig_bone.name.clone(),
                    parent,
                    rest_position: rig_bone.rest.w_axis.truncate(),
                    orientation: rotation_of(&rig_bone.rest),
                });
                placed_any = true;
            }
            if !placed_any {
                break;
            }
        }
        if let Some(bone) = skin_joint.iter().position(Option::is_none) {
            return Err(ExportError::invalid(
                context(),
                "a tree of bones",
                format!("bone {} under no placed parent (a cycle of parents)", bones[bone].name),
            ));
        }
        if vertices.is_empty() || joints.len() != vertices.len() || weights.len() != vertices.len()
        {
            return Err(ExportError::invalid(
                context(),
                "a skinned mesh with four joints and weights per vertex",
                format!(
                    "{} vertices, {} joint rows, {} weight rows",
                    vertices.len(),
                    joints.len(),
                    weights.len()
                ),
            ));
        }
        if let Some(face) = faces.iter().find(|f| f.iter().any(|&i| i as usize >= vertices.len())) {
            return Err(ExportError::invalid(
                context(),
                format!("triangles of vertices below {}", vertices.len()),
                format!("{face:?}"),
            ));
        }
        let mut vertex_joints = Vec::with_capacity(vertices.len());
        let mut vertex_weights = Vec::with_capacity(vertices.len());
        for (vertex, (row, w)) in joints.iter().zip(weights).enumerate() {
            let total: f32 = w.iter().filter(|x| x.is_finite() && **x > 0.0).sum();
            // Finite non-negative terms: the sum is one too.
            if total <= 0.0 {
                return Err(ExportError::invalid(
                    format!("{}, skin weights of vertex {vertex}", context()),
                    "at least one positive weight",
                    format!("{w:?}"),
                ));
            }
            let mut kept_joints = [0u16; 4];
            let mut kept_weights = [0.0f32; 4];
            for k in 0..4 {
                if !(w[k].is_finite() && w[k] > 0.0) {
                    continue;
                }
                let bone = row[k] as usize;
                let joint = skin_joint.get(bone).copied().flatten().ok_or_else(|| {
                    ExportError::invalid(
                        format!("{}, skin joints of vertex {vertex}", context()),
                        format!("bones below {}", bones.len()),
                        bone,
                    )
                })?;
                kept_joints[k] = u16::try_from(joint).map_err(|_| {
                    ExportError::invalid(context(), "at most 65536 skin joints", joint)
                })?;
                kept_weights[k] = w[k] / total;
            }
            vertex_joints.push(kept_joints);
            vertex_weights.push(kept_weights);
        }
        let normals = crate::smplx_body::vertex_normals(&vertices, &faces);
        Ok(Self {
            path,
            skeleton,
            bone_names,
            orientations,
            extra_joints,
            vertices,
            normals,
            faces,
            joints: vertex_joints,
            weights: vertex_weights,
        })
    }

    /// Root positions of a motion made on `from` (the model's skeleton) for this character:
    /// scaled about the floor by the ratio of the hips' rest heights, so that a taller or
    /// shorter character keeps its feet on the floor and its stride in proportion.
    pub fn retarget_root(&self, from: &Skeleton, positions: &[Vec3]) -> Vec<Vec3> {
        let ratio = self.skeleton.rest_offsets()[0].y / from.rest_offsets()[0].y;
        positions.iter().map(|&p| p * ratio).collect()
    }

    /// Checks that a motion's skeleton can be shown on this character (a Mixamo-65 motion);
    /// pose it on [`CharacterMesh::skeleton`] for the export.
    pub fn fits(&self, skeleton: &Skeleton) -> Result<()> {
        let body = format!("the character {}", self.path.display());
        crate::check_skeleton_kind(body, &self.skeleton, skeleton)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The built-in Mixamo skeleton as a character's skin (bones named with `prefix`), with one
    /// triangle bound to `bound_to` (a bone index).
    fn rig(prefix: &str) -> Vec<RigBone> {
        let skeleton = Skeleton::mixamo();
        let positions = skeleton.rest_positions();
        let orientations = skeleton.rest_orientations();
        (0..skeleton.joint_count())
            .map(|j| RigBone {
                name: format!("{prefix}{}", skeleton.joint_names()[j]),
                parent: skeleton.parents()[j],
                rest: Mat4::from_rotation_translation(orientations[j], positions[j]),
            })
            .collect()
    }

    fn build(bones: &[RigBone], bound_to: u16) -> Result<CharacterMesh> {
        let vertices = vec![Vec3::new(0.0, 1.0, 0.1), Vec3::new(0.1, 1.0, 0.1), Vec3::Y];
        CharacterMesh::new(
            PathBuf::from("hero.glb"),
            &Skeleton::mixamo(),
            bones,
            vertices,
            vec![[0, 1, 2]],
            &[[bound_to, 0, 0, 0]; 3],
            &[[1.0, 0.0, 0.0, 0.0]; 3],
        )
    }

    /// Removes a bone, its children hanging from its parent (as a reader finds them).
    fn without(bones: &[RigBone], name: &str) -> Vec<RigBone> {
        let gone = bones.iter().position(|b| b.name.ends_with(name)).unwrap();
        let reindex = |p: usize| if p > gone { p - 1 } else { p };
        bones
            .iter()
            .enumerate()
            .filter(|(k, _)| *k != gone)
            .map(|(_, b)| {
                let parent = match b.parent {
                    Some(p) if p == gone => bones[gone].parent,
                    other => other,
                };
                RigBone { parent: parent.map(reindex), ..b.clone() }
            })
            .collect()
    }

    #[test]
    fn the_builtin_rig_is_its_own_character() {
        let builtin = Skeleton::mixamo();
        let character = build(&rig(MIXAMO_PREFIX), 0).unwrap();
        for (a, b) in character.skeleton.rest_offsets().iter().zip(builtin.rest_offsets()) {
            assert!(a.abs_diff_eq(*b, 1e-5), "{a} vs {b}");
        }
        assert_eq!(character.bone_names, builtin.rig_joint_names());
        for (a, b) in character.orientations.iter().zip(builtin.rest_orientations()) {
            assert!(a.abs_diff_eq(b, 1e-5) || a.abs_diff_eq(-b, 1e-5));
        }
        assert!(character.extra_joints.is_empty());
        assert_eq!(character.weights[0], [1.0, 0.0, 0.0, 0.0]);
        assert!(character.retarget_root(&builtin, &[Vec3::ONE])[0].abs_diff_eq(Vec3::ONE, 1e-5));
    }

    #[test]
    fn names_without_the_prefix_and_missing_end_bones_are_taken() {
        let mut bones = rig("");
        for end in ["HeadTop_End", "LeftToe_End", "RightHandPinky4"] {
            bones = without(&bones, end);
        }
        let character = build(&bones, 0).unwrap();
        let builtin = Skeleton::mixamo();
        assert_eq!(character.bone_names, builtin.joint_names());
        let end = builtin.joint_index("HeadTop_End").unwrap();
        assert!(
            character.skeleton.rest_offsets()[end].abs_diff_eq(builtin.rest_offsets()[end], 1e-6)
        );
    }

    #[test]
    fn other_bones_stay_at_rest_under_their_parents() {
        let mut bones = rig(MIXAMO_PREFIX);
        let head = bones.iter().position(|b| b.name == "mixamorig:Head").unwrap();
        let eye = Mat4::from_translation(bones[head].rest.w_axis.truncate() + Vec3::Z * 0.08);
        bones.push(RigBone { name: "mixamorig:LeftEye".into(), parent: Some(head), rest: eye });
        let character = build(&bones, 65).unwrap();
        assert_eq!(character.extra_joints.len(), 1);
        let extra = &character.extra_joints[0];
        assert_eq!((extra.name.as_str(), extra.parent), ("mixamorig:LeftEye", head));
        assert_eq!(character.joints[0][0], 65, "the vertex follows the extra bone");
    }

    #[test]
    fn characters_that_cannot_wear_the_motion_are_refused_with_the_reason() {
        let refused = |bones: &[RigBone], needle: &str| {
            let error = build(bones, 0).unwrap_err().to_string();
            assert!(error.contains("hero.glb") && error.contains(needle), "{needle}: {error}");
        };
        // A bone the motion turns.
        refused(&without(&rig(MIXAMO_PREFIX), "LeftForeArm"), "no mixamorig:LeftForeArm");
        // Centimetres.
        let centimetres: Vec<RigBone> = rig(MIXAMO_PREFIX)
            .into_iter()
            .map(|b| RigBone { rest: Mat4::from_scale(Vec3::splat(100.0)) * b.rest, ..b })
            .collect();
        refused(&centimetres, "in metres");
        // Arms down: not the T-pose.
        let mut a_pose = rig(MIXAMO_PREFIX);
        let arm = a_pose.iter().position(|b| b.name == "mixamorig:LeftArm").unwrap();
        let shoulder = a_pose[arm].rest.w_axis.truncate();
        for bone in a_pose.iter_mut().skip(arm + 1).take(22) {
            let p = bone.rest.w_axis.truncate() - shoulder;
            bone.rest.w_axis = (shoulder + Vec3::new(0.0, -p.length(), 0.0)).extend(1.0);
        }
        refused(&a_pose, "T-pose");
        // No weight on a vertex.
        let error = CharacterMesh::new(
            PathBuf::from("hero.glb"),
            &Skeleton::mixamo(),
            &rig(MIXAMO_PREFIX),
            vec![Vec3::Y; 3],
            vec![[0, 1, 2]],
            &[[0; 4]; 3],
            &[[0.0; 4]; 3],
        )
        .unwrap_err()
        .to_string();
        assert!(error.contains("vertex 0") && error.contains("positive weight"), "{error}");
    }
}
