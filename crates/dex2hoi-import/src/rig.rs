//! From a posed rig as a dataset stores it to dex2hoi's motion: local rotations on fixed rest
//! offsets plus a root position (docs/CONVENTIONS.md, "Forward kinematics").
//!
//! Animation rigs (HUMOTO's Mixamo skin, in its GLB and its pickle) also animate the
//! translations of a few bones: HUMOTO's `Spine` moves up to 1.5 cm against the hips and its
//! `LeftHand` up to 9 mm against the forearm, capture-solver stretch that fixed rest offsets
//! cannot hold. Dropping those translations leaves the whole upper body, hands included, up to
//! 1.5 cm off, which matters for contact with objects. [`PosedRig::fold`] keeps the hands and
//! feet where the data put them instead:
//! - the root takes the stretch of its largest child (the spine): the upper body lands exactly,
//!   and only the hips and the heads of the thighs keep an error of the stretch's size (the
//!   feet are put back as below, so the knees bend a little: on HUMOTO's
//!   `examining_cutting_board-141`, 1.5 cm at the hips and 2.3 cm at the knees on the worst
//!   frame, 0.3 mm over all joints and frames);
//! - a limb end that is off (a foot after the root moved, a stretched hand) is put back by a
//!   two-bone inverse kinematics step on its two parent bones (thigh and shin, upper arm and
//!   forearm): the bend angle changes, the bone lengths stay, the bend plane and the end's own
//!   world rotation are kept.

use glam::{Mat3, Quat, Vec3};

use dex2hoi_repr::Skeleton;
use dex2hoi_repr::rotation::{matrix_to_sixd, sixd_to_matrix};

/// Joint errors below this (metres) are left alone.
const FOLD_TOLERANCE: f32 = 5e-4;

/// A posed rig: world joint positions and world joint rotations relative to the rest pose
/// (`W'_j = W_j B_j^-1`, the identity in the rest pose), per frame.
#[derive(Debug, Clone)]
pub struct PosedRig {
    /// The rest skeleton (offsets in the rest pose, metres, Y up).
    pub skeleton: Skeleton,
    /// World rotation of each joint relative to its rest orientation, frame-major
    /// `[frames * joints]`.
    pub world_rotations: Vec<Mat3>,
    /// World position of each joint, frame-major `[frames * joints]`.
    pub positions: Vec<Vec3>,
}

/// A rig folded onto fixed rest offsets, and how far its joints ended from the data's.
#[derive(Debug, Clone)]
pub struct FoldedRig {
    /// Local rotations, frame-major `[frames * joints]`.
    pub local_rotations: Vec<Mat3>,
    /// Root position per frame.
    pub root_positions: Vec<Vec3>,
    /// Mean over frames and joints of the distance between the folded rig's joints and the
    /// data's (metres).
    pub mean_error: f32,
    /// The largest such distance, and the joint it is at.
    pub max_error: (f32, usize),
}

impl PosedRig {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.positions.len() / self.skeleton.joint_count().max(1)
    }

    /// Local rotations and root positions on the skeleton's fixed rest offsets (see the module
    /// documentation), with the joint errors that remain.
    pub fn fold(&self) -> FoldedRig {
        let skeleton = &self.skeleton;
        let joints = skeleton.joint_count();
        let parents = skeleton.parents();
        let offsets = skeleton.rest_offsets();
        let children = skeleton.children();
        // The root's child with the largest subtree (the spine) carries the root's stretch.
        let subtree = subtree_sizes(&children);
        let trunk = children[0].iter().copied().max_by_key(|&c| subtree[c]);
        let mut local_rotations = Vec::with_capacity(self.positions.len());
        let mut root_positions = Vec::with_capacity(self.frames());
        let (mut sum, mut max) = (0.0f64, (0.0f32, 0));
        for frame in 0..self.frames() {
            let range = frame * joints..(frame + 1) * joints;
            let target = &self.positions[range.clone()];
            let mut world: Vec<Mat3> =
                self.world_rotations[range].iter().map(|r| orthonormalised(*r)).collect();
            let mut root = target[0];
            if let Some(trunk) = trunk {
                root = target[trunk] - world[0] * offsets[trunk];
            }
            let mut posed = positions(parents, offsets, &world, root);
            for j in 0..joints {
                let Some(p) = parents[j] else { continue };
                let Some(g) = parents[p] else { continue };
                if parents[g].is_none()
                    || children[p].len() != 1
                    || posed[j].distance(target[j]) <= FOLD_TOLERANCE
                {
                    continue;
                }
                two_bone(&mut world, [g, p, j], &posed, target[j], offsets);
                posed = positions(parents, offsets, &world, root);
            }
            for j in 0..joints {
                let error = posed[j].distance(target[j]);
                sum += f64::from(error);
                if error > max.0 {
                    max = (error, j);
                }
                local_rotations.push(match parents[j] {
                    Some(p) => orthonormalised(world[p].transpose() * world[j]),
                    None => world[j],
                });
            }
            root_positions.push(root);
        }
        let count = (self.frames() * joints).max(1);
        FoldedRig {
            local_rotations,
            root_positions,
            mean_error: (sum / count as f64) as f32,
            max_error: max,
        }
    }
}

/// Joint positions of one frame from world rotations and a root position.
fn positions(parents: &[Option<usize>], offsets: &[Vec3], world: &[Mat3], root: Vec3) -> Vec<Vec3> {
    let mut out = Vec::with_capacity(parents.len());
    for (j, parent) in parents.iter().enumerate() {
        out.push(match parent {
            Some(p) => out[*p] + world[*p] * offsets[j],
            None => root,
        });
    }
    out
}

/// Moves joint `end` of the chain `[base, middle, end]` to `target` by turning the base and
/// middle bones: the law of cosines gives the bend, the plane through the base, the target and
/// the middle joint's current position is kept, and each bone turns by the smallest rotation
/// that points it where it must go (so its twist stays). An unreachable target is approached
/// as far as the bone lengths allow.
fn two_bone(
    world: &mut [Mat3],
    [base, middle, end]: [usize; 3],
    posed: &[Vec3],
    target: Vec3,
    offsets: &[Vec3],
) {
    let upper = offsets[middle].length();
    let lower = offsets[end].length();
    let start = posed[base];
    let reach = target - start;
    let distance = reach.length();
    if upper < 1e-6 || lower < 1e-6 || distance < 1e-6 {
        return;
    }
    let axis = reach / distance;
    let clamped = distance.clamp((upper - lower).abs() + 1e-6, upper + lower - 1e-6);
    let cos_bend = ((upper * upper + clamped * clamped - lower * lower) / (2.0 * upper * clamped))
        .clamp(-1.0, 1.0);
    let sin_bend = (1.0 - cos_bend * cos_bend).sqrt();
    let current = posed[middle] - start;
    let mut pole = current - axis * current.dot(axis);
    if pole.length_squared() < 1e-12 {
        pole = axis.any_orthonormal_vector();
    }
    let pole = pole.normalize();
    let knee = start + upper * (cos_bend * axis + sin_bend * pole);
    let end_point = start + axis * clamped;
    world[base] = turn(world[base] * offsets[middle], knee - start) * world[base];
    world[middle] = turn(world[middle] * offsets[end], end_point - knee) * world[middle];
}

/// The smallest rotation taking the direction of `from` to the direction of `to`.
fn turn(from: Vec3, to: Vec3) -> Mat3 {
    Mat3::from_quat(Quat::from_rotation_arc(from.normalize(), to.normalize()))
}

/// The rotation of a matrix that is one up to rounding or a uniform scale: the project's one
/// Gram-Schmidt, the decode of its 6D form (first two rows).
pub fn orthonormalised(m: Mat3) -> Mat3 {
    sixd_to_matrix(matrix_to_sixd(m))
}

fn subtree_sizes(children: &[Vec<usize>]) -> Vec<usize> {
    let mut sizes = vec![1; children.len()];
    for j in (0..children.len()).rev() {
        for &c in &children[j] {
            sizes[j] += sizes[c];
        }
    }
    sizes
}

#[cfg(test)]
mod tests {
    use super::*;
    use dex2hoi_repr::fk::forward_kinematics;
    use dex2hoi_repr::rotation::axis_angle_to_matrix;

    /// A posed Mixamo rig from local rotations, with some bones stretched.
    fn stretched_rig(stretch: &[(usize, Vec3)]) -> PosedRig {
        let skeleton = Skeleton::mixamo();
        let joints = skeleton.joint_count();
        let parents = skeleton.parents().to_vec();
        let mut world_rotations = Vec::new();
        let mut positions = Vec::new();
        for frame in 0..4 {
            let angle = 0.3 + 0.2 * frame as f32;
            let mut world = vec![Mat3::IDENTITY; joints];
            let mut posed = vec![Vec3::ZERO; joints];
            for j in 0..joints {
                let local = axis_angle_to_matrix(Vec3::new(angle, -0.5 * angle, 0.2) * 0.4);
                let mut offset = skeleton.rest_offsets()[j];
                for (joint, delta) in stretch {
                    if *joint == j {
                        offset += *delta;
                    }
                }
                match parents[j] {
                    Some(p) => {
                        world[j] = world[p] * local;
                        posed[j] = posed[p] + world[p] * offset;
                    }
                    None => {
                        world[j] = local;
                        posed[j] = Vec3::new(0.1, 0.9, 0.2 * frame as f32);
                    }
                }
            }
            world_rotations.extend(world);
            positions.extend(posed);
        }
        PosedRig { skeleton, world_rotations, positions }
    }

    #[test]
    fn an_unstretched_rig_folds_exactly() {
        let rig = stretched_rig(&[]);
        let folded = rig.fold();
        assert!(folded.max_error.0 < 1e-5, "{:?}", folded.max_error);
        let fk = forward_kinematics(&rig.skeleton, &folded.local_rotations, &folded.root_positions)
            .unwrap();
        for (a, b) in fk.positions.iter().zip(&rig.positions) {
            assert!(a.distance(*b) < 1e-5);
        }
    }

    #[test]
    fn stretch_is_folded_into_the_root_and_the_limbs() {
        let skeleton = Skeleton::mixamo();
        let spine = skeleton.joint_index("Spine").unwrap();
        let hand = skeleton.joint_index("LeftHand").unwrap();
        let rig = stretched_rig(&[
            (spine, Vec3::new(0.004, 0.012, -0.006)),
            // Shorter: a straight arm cannot reach further than its bones.
            (hand, Vec3::new(-0.006, -0.004, 0.003)),
        ]);
        let folded = rig.fold();
        let joints = skeleton.joint_count();
        let fk =
            forward_kinematics(&skeleton, &folded.local_rotations, &folded.root_positions).unwrap();
        let stretch = Vec3::new(0.004, 0.012, -0.006).length();
        for (k, (a, b)) in fk.positions.iter().zip(&rig.positions).enumerate() {
            let name = &skeleton.joint_names()[k % joints];
            let error = a.distance(*b);
            // The upper body lands, the hand included; the hips and the heads of the thighs keep
            // the spine's stretch; the knees and the elbow bend to keep the feet and the hand
            // (a nearly straight limb bends a few centimetres to absorb a few millimetres), and
            // a foot the straight leg cannot reach stays off by what is missing.
            let allowed = if name == "Hips" || name.contains("Leg") {
                0.06
            } else if name.contains("Foot") || name.contains("Toe") {
                stretch
            } else if name == "LeftForeArm" {
                0.06
            } else {
                1e-4
            };
            assert!(error <= allowed, "{name}: {error}");
        }
        // Bone rotations stay rotations.
        for r in &folded.local_rotations {
            assert!(dex2hoi_repr::rotation::is_rotation(*r, 1e-4));
        }
    }
}
