//! A simple body for a skeleton: a capsule along every bone and a sphere for the head, each
//! vertex bound rigidly to one joint. The glTF export skins it (one joint per vertex, weight 1)
//! and the preview poses it with the same rigid transforms.
//!
//! A bone from parent `p` to child `c` moves with `p` (its rotation turns the segment), so its
//! capsule is bound to `p`; a head sphere is bound to its own (leaf) joint. Radii follow the
//! kind of bone: torso bones on the midline are thick, limb bones get thinner away from the
//! torso, finger bones are about a finger thick.

use glam::{Mat3, Vec3};

use dex2hoi_repr::Skeleton;

/// Radius of midline bones whose child has limbs below it (pelvis, spine).
const TORSO_RADIUS: f32 = 0.10;
/// Radius of midline bones whose child leads only to midline joints (neck, head).
const NECK_RADIUS: f32 = 0.05;
/// Radius of a head sphere at each midline leaf.
const HEAD_RADIUS: f32 = 0.10;
/// How far past the leaf (along its bone) the head sphere's centre sits.
const HEAD_CENTRE_PAST_LEAF: f32 = 0.05;
/// Radius of a limb bone next to the torso, and how much it shrinks per joint further out.
const LIMB_RADIUS: f32 = 0.08;
const LIMB_TAPER: f32 = 0.012;
/// Smallest limb radius (toes).
const MIN_LIMB_RADIUS: f32 = 0.02;
/// Radius of the bones from a wrist to the finger bases (the palm).
const PALM_RADIUS: f32 = 0.012;
/// Radius of finger bones.
const FINGER_RADIUS: f32 = 0.009;

/// A triangle mesh whose every vertex follows one joint rigidly.
#[derive(Debug, Clone, PartialEq)]
pub struct SkinnedMesh {
    /// Vertex positions in the rest pose (world, metres).
    pub vertices: Vec<Vec3>,
    /// Unit outward vertex normals in the rest pose.
    pub normals: Vec<Vec3>,
    /// The joint each vertex follows.
    pub joints: Vec<u16>,
    /// The joint at the far end of the bone each vertex's capsule draws (a head sphere's own
    /// joint): with `joints`, the bone a vertex belongs to (the preview colours hand bones by
    /// their contact).
    pub bone_ends: Vec<u16>,
    /// Triangles, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

impl SkinnedMesh {
    fn empty() -> Self {
        Self {
            vertices: Vec::new(),
            normals: Vec::new(),
            joints: Vec::new(),
            bone_ends: Vec::new(),
            faces: Vec::new(),
        }
    }

    /// Appends a capsule from `a` to `b` (a sphere when they coincide) bound to `joint`, drawing
    /// the bone that ends at `bone_end`: `segments` around the axis, `cap_rings` latitude rings
    /// per half sphere.
    #[allow(clippy::too_many_arguments)] // the capsule's geometry, resolution and binding
    fn add_capsule(
        &mut self,
        a: Vec3,
        b: Vec3,
        radius: f32,
        segments: u32,
        cap_rings: u32,
        joint: u16,
        bone_end: u16,
    ) {
        let length = (b - a).length();
        let axis = if length > 1e-6 { (b - a) / length } else { Vec3::Y };
        // (u, v, axis) right-handed, so the angle runs counter-clockwise seen from +axis.
        let u = axis.any_orthonormal_vector();
        let v = axis.cross(u);
        let base = self.vertices.len() as u32;
        let mut push = |centre: Vec3, normal: Vec3| {
            self.vertices.push(centre + normal * radius);
            self.normals.push(normal);
            self.joints.push(joint);
            self.bone_ends.push(bone_end);
        };
        push(a, -axis);
        // Latitudes from the `a` pole to the equator at `a`, then from the equator at `b` on.
        let quarter = std::f32::consts::FRAC_PI_2;
        let rings: Vec<(Vec3, f32)> = (1..=cap_rings)
            .map(|k| (a, -quarter + quarter * k as f32 / cap_rings as f32))
            .chain((0..cap_rings).map(|k| (b, quarter * k as f32 / cap_rings as f32)))
            .collect();
        for &(centre, latitude) in &rings {
            for s in 0..segments {
                let angle = std::f32::consts::TAU * s as f32 / segments as f32;
                let around = u * angle.cos() + v * angle.sin();
                push(centre, around * latitude.cos() + axis * latitude.sin());
            }
        }
        push(b, axis);
        let ring = |r: u32, s: u32| base + 1 + r * segments + s % segments;
        let last_ring = rings.len() as u32 - 1;
        let top = base + 2 + rings.len() as u32 * segments - 1;
        for s in 0..segments {
            // Around +axis the ring runs counter-clockwise (u then v), so the `a` cap faces
            // outward as (pole, s + 1, s) and the `b` cap as (pole, s, s + 1).
            self.faces.push([base, ring(0, s + 1), ring(0, s)]);
            for r in 0..last_ring {
                self.faces.push([ring(r, s), ring(r, s + 1), ring(r + 1, s + 1)]);
                self.faces.push([ring(r, s), ring(r + 1, s + 1), ring(r + 1, s)]);
            }
            self.faces.push([top, ring(last_ring, s), ring(last_ring, s + 1)]);
        }
    }

    /// Vertex positions in a pose given by each joint's world rotation and position:
    /// `v' = G_j (v - rest_j) + p_j` for the joint `j` of each vertex.
    ///
    /// # Shapes
    /// - `rest_positions`, `rotations`, `positions`: `[joints]`
    pub fn posed(
        &self,
        rest_positions: &[Vec3],
        rotations: &[Mat3],
        positions: &[Vec3],
    ) -> Vec<Vec3> {
        self.vertices
            .iter()
            .zip(&self.joints)
            .map(|(&v, &j)| {
                let j = j as usize;
                rotations[j] * (v - rest_positions[j]) + positions[j]
            })
            .collect()
    }
}

/// The capsule body of a skeleton in its rest pose.
pub fn body_mesh(skeleton: &Skeleton) -> SkinnedMesh {
    let rest = skeleton.rest_positions();
    let parents = skeleton.parents();
    let symmetry = skeleton.symmetry();
    let children = skeleton.children();
    let groups = skeleton.groups();
    let midline = |j: usize| symmetry[j] == j;
    let wrists = [groups.left_wrist, groups.right_wrist];
    let in_hand = |j: usize| groups.left_hand.contains(&j) || groups.right_hand.contains(&j);

    // Joints away from the midline on the way to the root: 1 for a hip or collar, 4 for a wrist.
    let mut limb_depth = vec![0u32; skeleton.joint_count()];
    // Whether a joint's subtree holds only midline joints (the neck and head chain).
    let mut only_midline_below = vec![true; skeleton.joint_count()];
    for joint in 0..skeleton.joint_count() {
        limb_depth[joint] =
            parents[joint].map_or(0, |p| limb_depth[p]) + u32::from(!midline(joint));
    }
    for joint in (0..skeleton.joint_count()).rev() {
        only_midline_below[joint] =
            midline(joint) && children[joint].iter().all(|&c| only_midline_below[c]);
    }

    let mut mesh = SkinnedMesh::empty();
    for (joint, parent) in parents.iter().enumerate() {
        let Some(p) = *parent else { continue };
        let (a, b) = (rest[p], rest[joint]);
        let bound = p as u16;
        if in_hand(joint) && !wrists.contains(&joint) {
            let radius = if wrists.contains(&p) { PALM_RADIUS } else { FINGER_RADIUS };
            mesh.add_capsule(a, b, radius, 6, 2, bound, joint as u16);
        } else if midline(p) && midline(joint) {
            let radius = if only_midline_below[joint] { NECK_RADIUS } else { TORSO_RADIUS };
            mesh.add_capsule(a, b, radius, 14, 4, bound, joint as u16);
            if children[joint].is_empty() {
                let centre = b + (b - a).normalize_or_zero() * HEAD_CENTRE_PAST_LEAF;
                mesh.add_capsule(centre, centre, HEAD_RADIUS, 14, 5, joint as u16, joint as u16);
            }
        } else {
            let radius = (LIMB_RADIUS - LIMB_TAPER * limb_depth[joint] as f32).max(MIN_LIMB_RADIUS);
            mesh.add_capsule(a, b, radius, 12, 3, bound, joint as u16);
        }
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume of a closed mesh: positive when its faces wind outward.
    fn signed_volume(vertices: &[Vec3], faces: &[[u32; 3]]) -> f32 {
        faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| vertices[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn a_capsule_is_closed_outward_and_has_the_capsule_volume() {
        let mut mesh = SkinnedMesh::empty();
        let (a, b, radius) = (Vec3::new(0.1, 0.2, 0.3), Vec3::new(0.5, 0.2, 0.1), 0.05);
        mesh.add_capsule(a, b, radius, 48, 16, 0, 0);
        let length = (b - a).length();
        let exact = std::f32::consts::PI * radius * radius * (length + 4.0 / 3.0 * radius);
        let volume = signed_volume(&mesh.vertices, &mesh.faces);
        assert!((volume / exact - 1.0).abs() < 0.02, "{volume} vs {exact}");
        // Every edge is shared by exactly two faces (closed, manifold).
        let mut edges = std::collections::HashMap::new();
        for face in &mesh.faces {
            for k in 0..3 {
                let (i, j) = (face[k], face[(k + 1) % 3]);
                *edges.entry((i.min(j), i.max(j))).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&n| n == 2));
        // Normals point away from the axis.
        for (vertex, normal) in mesh.vertices.iter().zip(&mesh.normals) {
            let along = ((*vertex - a).dot(b - a) / (b - a).length_squared()).clamp(0.0, 1.0);
            let nearest = a + (b - a) * along;
            assert!((*vertex - nearest).normalize().dot(*normal) > 0.99);
        }
    }

    #[test]
    fn the_smplx_body_is_outward_bound_to_valid_joints_and_covers_the_pelvis() {
        let skeleton = Skeleton::smplx();
        let mesh = body_mesh(&skeleton);
        assert_eq!(mesh.vertices.len(), mesh.normals.len());
        assert_eq!(mesh.vertices.len(), mesh.joints.len());
        assert!(mesh.joints.iter().all(|&j| (j as usize) < skeleton.joint_count()));
        assert!(signed_volume(&mesh.vertices, &mesh.faces) > 0.03);
        let (min, max) = mesh
            .vertices
            .iter()
            .fold((Vec3::MAX, Vec3::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        // About a person: 1.6-1.9 m tall, arms spread 1.5-1.9 m in the T-pose.
        let size = max - min;
        assert!((1.6..1.9).contains(&size.y) && (1.5..1.9).contains(&size.x), "{size}");
        // The identity pose reproduces the rest mesh.
        let rest = skeleton.rest_positions();
        let posed = mesh.posed(&rest, &vec![Mat3::IDENTITY; rest.len()], &rest);
        let worst =
            posed.iter().zip(&mesh.vertices).map(|(a, b)| (*a - *b).length()).fold(0.0, f32::max);
        assert!(worst < 1e-6, "{worst}");
    }
}
