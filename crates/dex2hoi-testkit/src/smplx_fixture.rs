//! A small SMPL-X model file for tests: the real key names, dtypes and layouts
//! (`v_template (V, 3)`, `shapedirs (V, 3, 10)`, `J_regressor (55, V)`, `kintree_table (2, 55)`
//! with the root's parent as uint32 max, `f (F, 3)` uint32, `weights (V, 55)`), on a body made
//! of the capsule mesh of the built-in skeleton. Its skinning weights look like a real model's:
//! each vertex mostly follows its bone's joint, blends into the next joint along the bone and
//! the one before, and has two small stray weights, so five or six joints influence it and
//! keeping the four largest matters. Its joint regressor averages the vertices nearest each
//! joint, as the real one averages a ring of vertices. The users' real model is licensed; the
//! tests use this one.
//!
//! It takes the built-in SMPL-X skeleton's rest joints, parents and capsule mesh as arguments
//! ([`BoundMesh`]: `dex2hoi_export::body_mesh`'s fields), so it names no dex2hoi crate.

use std::path::Path;

use glam::Vec3;

/// A rest-pose mesh bound to a skeleton's bones, as `dex2hoi_export::SkinnedMesh` holds it.
#[derive(Debug, Clone, Copy)]
pub struct BoundMesh<'a> {
    /// Vertex positions in the rest pose (metres).
    pub vertices: &'a [Vec3],
    /// The joint each vertex follows.
    pub joints: &'a [u16],
    /// The joint at the far end of each vertex's bone.
    pub bone_ends: &'a [u16],
    /// Triangles.
    pub faces: &'a [[u32; 3]],
}

/// Shape coefficients in the fixture.
pub const SHAPES: usize = 10;

/// Vertices each joint's regressor row averages.
const REGRESSOR_VERTICES: usize = 8;

/// Which entries to leave out or spoil, for the error tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Spoil {
    /// A complete model.
    None,
    /// Without the given key.
    Missing(&'static str),
    /// `weights` with 54 columns.
    WeightsShape,
    /// A face indexing past the last vertex.
    FaceIndex,
}

/// SMPL-X's index of each of our 52 joints: 0-21 stay, the fingers follow jaw and eyes.
fn smplx52_to_55(joint: usize) -> usize {
    if joint < 22 { joint } else { joint + 3 }
}

/// The fixture's 55 target joints: the built-in skeleton's 52 put in SMPL-X order, the jaw
/// and eyes in front of the head.
fn target_joints(rest: &[Vec3]) -> Vec<Vec3> {
    let head = rest[15];
    let mut joints = vec![Vec3::ZERO; 55];
    for (ours, position) in rest.iter().enumerate() {
        joints[smplx52_to_55(ours)] = *position;
    }
    joints[22] = head + Vec3::new(0.0, -0.04, 0.05);
    joints[23] = head + Vec3::new(0.03, 0.03, 0.08);
    joints[24] = head + Vec3::new(-0.03, 0.03, 0.08);
    joints
}

/// Writes the model to `path`, built on the built-in SMPL-X skeleton (`rest` positions and
/// `parents` of its 52 joints) and its capsule `mesh` (`dex2hoi_export::body_mesh`).
///
/// # Panics
/// When the file cannot be written: it is a test fixture.
pub fn write_smplx_model(
    path: &Path,
    rest: &[Vec3],
    parents: &[Option<usize>],
    mesh: BoundMesh<'_>,
    spoil: Spoil,
) {
    assert_eq!(rest.len(), 52, "the SMPL-X skeleton");
    let vertex_count = mesh.vertices.len();
    let targets = target_joints(rest);

    let v_template: Vec<f32> = mesh.vertices.iter().flat_map(|v| v.to_array()).collect();
    // Shape 0 grows the body about the floor, 1 widens it, 2 lengthens the legs, the rest are
    // small smooth ripples.
    let mut shapedirs = vec![0.0f32; vertex_count * 3 * SHAPES];
    for (v, position) in mesh.vertices.iter().enumerate() {
        let at = |axis: usize, shape: usize| (v * 3 + axis) * SHAPES + shape;
        for axis in 0..3 {
            shapedirs[at(axis, 0)] = 0.03 * position[axis];
        }
        shapedirs[at(0, 1)] = 0.04 * position.x;
        shapedirs[at(1, 2)] = 0.02 * (position.y - 1.0).min(0.0);
        for shape in 3..SHAPES {
            for axis in 0..3 {
                shapedirs[at(axis, shape)] =
                    0.002 * (shape as f32 * 1.7 * position[(axis + 1) % 3] + axis as f32).sin();
            }
        }
    }

    let mut weights = vec![0.0f32; vertex_count * 55];
    for (v, position) in mesh.vertices.iter().enumerate() {
        let bound = mesh.joints[v] as usize;
        let end = mesh.bone_ends[v] as usize;
        let bone = rest[end] - rest[bound];
        let along = if bone.length_squared() > 1e-12 {
            ((*position - rest[bound]).dot(bone) / bone.length_squared()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let row = &mut weights[v * 55..(v + 1) * 55];
        row[smplx52_to_55(bound)] += 1.0 - 0.5 * along;
        if end != bound {
            row[smplx52_to_55(end)] += 0.5 * along;
        }
        if let Some(before) = parents[bound] {
            row[smplx52_to_55(before)] += 0.15 * (1.0 - along);
        }
        row[v % 55] += 0.02;
        row[(v * 7 + 3) % 55] += 0.01;
        let total: f32 = row.iter().sum();
        row.iter_mut().for_each(|w| *w /= total);
    }

    let mut regressor = vec![0.0f32; 55 * vertex_count];
    for (joint, target) in targets.iter().enumerate() {
        let mut nearest: Vec<(f32, usize)> =
            mesh.vertices.iter().enumerate().map(|(v, p)| ((*p - *target).length(), v)).collect();
        nearest.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for &(_, v) in &nearest[..REGRESSOR_VERTICES] {
            regressor[joint * vertex_count + v] = 1.0 / REGRESSOR_VERTICES as f32;
        }
    }

    let mut faces: Vec<u32> = mesh.faces.iter().flatten().copied().collect();
    if spoil == Spoil::FaceIndex {
        faces[5] = vertex_count as u32;
    }
    // SMPL-X's tree: ours re-indexed, jaw and eyes under the head; the root's parent stored as
    // uint32 max, as the published files do.
    let mut parents55 = vec![u32::MAX; 55];
    for (joint, parent) in parents.iter().enumerate() {
        if let Some(parent) = parent {
            parents55[smplx52_to_55(joint)] = smplx52_to_55(*parent) as u32;
        }
    }
    parents55[22..25].fill(15);
    let mut kintree = parents55;
    kintree.extend(0..55u32);

    let mut npz = npyz::npz::NpzWriter::create(path).expect("fixture model file");
    let skip = |name: &str| matches!(spoil, Spoil::Missing(key) if key == name);
    put(&mut npz, "v_template", &[vertex_count, 3], &v_template, skip("v_template"));
    put(&mut npz, "shapedirs", &[vertex_count, 3, SHAPES], &shapedirs, skip("shapedirs"));
    put(&mut npz, "J_regressor", &[55, vertex_count], &regressor, skip("J_regressor"));
    if spoil == Spoil::WeightsShape {
        let narrow: Vec<f32> =
            weights.chunks_exact(55).flat_map(|row| row[..54].iter().copied()).collect();
        put(&mut npz, "weights", &[vertex_count, 54], &narrow, false);
    } else {
        put(&mut npz, "weights", &[vertex_count, 55], &weights, skip("weights"));
    }
    put(&mut npz, "f", &[faces.len() / 3, 3], &faces, skip("f"));
    put(&mut npz, "kintree_table", &[2, 55], &kintree, skip("kintree_table"));
}

type Writer = npyz::npz::NpzWriter<std::io::BufWriter<std::fs::File>>;

/// Writes one array (C order) unless `skip`.
fn put<T: npyz::AutoSerialize + Copy>(
    npz: &mut Writer,
    name: &str,
    shape: &[usize],
    values: &[T],
    skip: bool,
) {
    use npyz::WriterBuilder;
    if skip {
        return;
    }
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut writer = npz
        .array::<T>(name, Default::default())
        .expect("entry")
        .default_dtype()
        .shape(&shape)
        .begin_nd()
        .expect("header");
    writer.extend(values.iter().copied()).expect("values");
    writer.finish().expect("finished");
}
