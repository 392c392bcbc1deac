//! Binary glTF (`.glb`) scenes as animation sources, through the `gltf` crate: the node tree with
//! its rest transforms, node animations sampled at any time (`LINEAR` with spherical
//! interpolation of rotations, `STEP`), world matrices, skins with their inverse bind matrices,
//! and triangle meshes. Only the GLB's own binary chunk is read: a file that points at external
//! or embedded-URI buffers is refused.

use std::path::Path;

use glam::{Mat4, Quat, Vec3};
use gltf::accessor::{DataType, Dimensions};
use gltf::animation::util::ReadOutputs;
use gltf::animation::{Interpolation, Property};

use crate::error::{ImportError, Result};

/// The most keyframes one animation channel may have (an hour at 240 fps): a guard against a
/// file that claims more than any capture holds.
pub const MAX_KEYFRAMES: usize = 864_000;

/// The bytes the reader may decode per byte of the binary chunk. One accessor can be referenced
/// by any number of meshes, skins and animation channels, and each reference reads it again: a
/// small file would otherwise decode gigabytes. HUMOTO's published GLBs decode to 0.6 to 0.9
/// times their binary chunk (keyframe times shared by every channel of a clip, values widened
/// to four lanes, indices to `u32`), so 8 leaves a wide margin.
pub const READ_FACTOR: usize = 8;

/// A node of the scene tree.
#[derive(Debug, Clone)]
pub struct Node {
    /// Its name (empty when the file gives none).
    pub name: String,
    /// Its parent node.
    pub parent: Option<usize>,
    /// Rest translation, rotation and scale.
    pub rest: (Vec3, Quat, Vec3),
    /// The mesh it instantiates.
    pub mesh: Option<usize>,
    /// The skin its mesh is bound to.
    pub skin: Option<usize>,
}

/// How a track interpolates between keyframes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    Linear,
    Constant,
}

/// One animated property of one node.
#[derive(Debug, Clone)]
struct Track {
    node: usize,
    property: Property,
    times: Vec<f32>,
    /// Translations and scales as `[x, y, z, 0]`, rotations as `[x, y, z, w]`.
    values: Vec<[f32; 4]>,
    step: Step,
}

/// A skin: its joint nodes and their inverse bind matrices.
#[derive(Debug, Clone)]
pub struct Skin {
    /// Joint node indices, in the skin's order.
    pub joints: Vec<usize>,
    /// Inverse bind matrix per joint (identity when the file gives none).
    pub inverse_bind_matrices: Vec<Mat4>,
}

/// Four skin joints and weights per vertex (glTF's `JOINTS_0`, `WEIGHTS_0`), weights as
/// floats.
#[derive(Debug, Clone, PartialEq)]
pub struct Skinning {
    /// Skin joint indices.
    pub joints: Vec<[u16; 4]>,
    /// Their weights.
    pub weights: Vec<[f32; 4]>,
}

/// A GLB scene read into memory.
#[derive(Debug, Clone)]
pub struct GlbScene {
    source_name: String,
    /// The nodes, in file order.
    pub nodes: Vec<Node>,
    /// The skins.
    pub skins: Vec<Skin>,
    meshes: Vec<(Vec<Vec3>, Vec<[u32; 3]>)>,
    /// Per mesh, the skin joints (indices into a skin's joints) and weights of each vertex,
    /// when every primitive has `JOINTS_0` and `WEIGHTS_0`.
    skinning: Vec<Option<Skinning>>,
    tracks: Vec<Track>,
    /// Every node, each after its parent.
    order: Vec<usize>,
}

/// What the reader may still decode ([`READ_FACTOR`] times the binary chunk).
struct ReadBudget {
    left: usize,
    total: usize,
}

impl ReadBudget {
    /// Takes `bytes_per_element` decoded bytes per element of `accessor`; `Err` says what was
    /// asked.
    fn take(
        &mut self,
        accessor: &gltf::Accessor<'_>,
        bytes_per_element: usize,
    ) -> std::result::Result<(), String> {
        let bytes = accessor.count().saturating_mul(bytes_per_element);
        if bytes > self.left {
            return Err(format!(
                "accessor {} read again past {} decoded bytes ({READ_FACTOR} times the binary \
                 chunk): another {bytes}",
                accessor.index(),
                self.total
            ));
        }
        self.left -= bytes;
        Ok(())
    }
}

/// What a read past the budget is refused as.
const WITHIN_BUDGET: &str = "reads within the binary chunk's budget";

impl GlbScene {
    /// Reads a `.glb` file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(ImportError::io(path))?;
        Self::from_bytes(&bytes, &path.display().to_string())
    }

    /// Reads a GLB from memory; `source_name` names it in errors.
    pub fn from_bytes(bytes: &[u8], source_name: &str) -> Result<Self> {
        let bad = |what: &str, expected: &str, got: &dyn std::fmt::Display| {
            ImportError::format(source_name, what, expected, got)
        };
        if bytes.get(..4) != Some(b"glTF".as_slice()) {
            return Err(bad("header", "a binary glTF file (magic `glTF`)", &"other bytes"));
        }
        // The header's length is checked here: `gltf` 1.4 subtracts the header size from it
        // unchecked, which overflows (a panic with overflow checks) below 12 (found by the `glb`
        // fuzz target).
        let declared = bytes
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .unwrap_or_default();
        if !(12..=bytes.len()).contains(&declared) {
            return Err(bad(
                "header length",
                &format!("12 to {} bytes (the header and the file's size)", bytes.len()),
                &declared,
            ));
        }
        // Parsed first, checked for the references gltf's own validation trips over, then
        // validated.
        let gltf::Gltf { document, blob } = gltf::Gltf::from_slice_without_validation(bytes)
            .map_err(|e| bad("glTF", "a valid glTF 2.0 binary", &e))?;
        check_references(document.as_json())
            .map_err(|(what, expected, got)| bad(&what, expected, &got))?;
        let document = gltf::Document::from_json(document.into_json())
            .map_err(|e| bad("glTF", "a valid glTF 2.0 binary", &e))?;
        let document = &document;
        let blob = blob.as_deref().unwrap_or(&[]);
        for buffer in document.buffers() {
            match buffer.source() {
                gltf::buffer::Source::Bin if buffer.length() <= blob.len() => {}
                gltf::buffer::Source::Bin => {
                    return Err(bad(
                        &format!("buffer {}", buffer.index()),
                        &format!("{} bytes in the binary chunk", buffer.length()),
                        &blob.len(),
                    ));
                }
                gltf::buffer::Source::Uri(_) => {
                    return Err(bad(
                        &format!("buffer {}", buffer.index()),
                        "the GLB's binary chunk",
                        &"an external or URI buffer",
                    ));
                }
            }
        }
        let data = |_: gltf::Buffer<'_>| Some(blob);
        let mut nodes: Vec<Node> = document
            .nodes()
            .map(|n| {
                let (t, r, s) = n.transform().decomposed();
                Node {
                    name: n.name().unwrap_or_default().to_string(),
                    parent: None,
                    rest: (Vec3::from_array(t), Quat::from_array(r), Vec3::from_array(s)),
                    mesh: n.mesh().map(|m| m.index()),
                    skin: n.skin().map(|s| s.index()),
                }
            })
            .collect();
        for node in document.nodes() {
            for child in node.children() {
                nodes[child.index()].parent = Some(node.index());
            }
        }
        // glTF's validation refuses cycles only partly: walk each chain to be sure, once per
        // node (a node met again on the chain being walked closes a cycle), and list the nodes
        // parents first for `world_matrices`, which then needs no recursion.
        let order = parents_first(&nodes)
            .map_err(|node| bad("node tree", "a tree", &format!("a cycle through node {node}")))?;
        let mut budget = ReadBudget {
            left: blob.len().saturating_mul(READ_FACTOR),
            total: blob.len().saturating_mul(READ_FACTOR),
        };
        let mut skins = Vec::new();
        for skin in document.skins() {
            let joints: Vec<usize> = skin.joints().map(|j| j.index()).collect();
            if let Some(accessor) = skin.inverse_bind_matrices() {
                check_accessor(&accessor, Dimensions::Mat4, &[DataType::F32], blob.len())
                    .map_err(|got| bad(&format!("skin {}", skin.index()), MATRICES, &got))?;
                budget
                    .take(&accessor, 64)
                    .map_err(|got| bad(&format!("skin {}", skin.index()), WITHIN_BUDGET, &got))?;
            }
            let inverse_bind_matrices = match skin.reader(data).read_inverse_bind_matrices() {
                Some(matrices) => matrices.map(|m| Mat4::from_cols_array_2d(&m)).collect(),
                None if skin.inverse_bind_matrices().is_some() => {
                    return Err(bad(
                        &format!("skin {}", skin.index()),
                        "readable inverse bind matrices",
                        &"an accessor outside the binary chunk",
                    ));
                }
                None => vec![Mat4::IDENTITY; joints.len()],
            };
            if inverse_bind_matrices.len() != joints.len() {
                return Err(bad(
                    &format!("skin {}", skin.index()),
                    &format!("{} inverse bind matrices (one per joint)", joints.len()),
                    &inverse_bind_matrices.len(),
                ));
            }
            skins.push(Skin { joints, inverse_bind_matrices });
        }
        let mut meshes = Vec::new();
        let mut skinning = Vec::new();
        for mesh in document.meshes() {
            let mut vertices = Vec::new();
            let mut faces = Vec::new();
            let mut mesh_skinning = Some(Skinning { joints: Vec::new(), weights: Vec::new() });
            for primitive in mesh.primitives() {
                let what = format!("mesh {} ({})", mesh.index(), mesh.name().unwrap_or_default());
                if primitive.mode() != gltf::mesh::Mode::Triangles {
                    return Err(bad(&what, "triangles", &format!("{:?}", primitive.mode())));
                }
                let position = primitive
                    .get(&gltf::Semantic::Positions)
                    .ok_or_else(|| bad(&what, "vertex positions", &"none"))?;
                check_accessor(&position, Dimensions::Vec3, &[DataType::F32], blob.len())
                    .map_err(|got| bad(&what, "positions of VEC3 float", &got))?;
                if let Some(indices) = primitive.indices() {
                    let types = [DataType::U8, DataType::U16, DataType::U32];
                    check_accessor(&indices, Dimensions::Scalar, &types, blob.len())
                        .map_err(|got| bad(&what, "indices of unsigned integers", &got))?;
                    budget.take(&indices, 4).map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                }
                // Positions, and the indices made for them when the primitive has none.
                let per_vertex = if primitive.indices().is_some() { 12 } else { 16 };
                budget
                    .take(&position, per_vertex)
                    .map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                let reader = primitive.reader(data);
                let base = vertices.len();
                let positions = reader
                    .read_positions()
                    .ok_or_else(|| bad(&what, "readable vertex positions", &"none"))?;
                vertices.extend(positions.map(Vec3::from_array));
                let count = vertices.len() - base;
                let indices: Vec<u32> = match reader.read_indices() {
                    Some(indices) => indices.into_u32().collect(),
                    None => (0..count as u32).collect(),
                };
                if !indices.len().is_multiple_of(3) {
                    return Err(bad(&what, "a multiple of 3 indices", &indices.len()));
                }
                if let Some(&i) = indices.iter().find(|&&i| i as usize >= count) {
                    return Err(bad(&what, &format!("indices below {count}"), &i));
                }
                faces.extend(
                    indices.chunks_exact(3).map(|f| [f[0], f[1], f[2]].map(|i| i + base as u32)),
                );
                let joints = primitive.get(&gltf::Semantic::Joints(0));
                let weights = primitive.get(&gltf::Semantic::Weights(0));
                let (Some(joints), Some(weights), Some(kept)) =
                    (joints, weights, &mut mesh_skinning)
                else {
                    mesh_skinning = None;
                    continue;
                };
                check_accessor(
                    &joints,
                    Dimensions::Vec4,
                    &[DataType::U8, DataType::U16],
                    blob.len(),
                )
                .map_err(|got| bad(&what, "JOINTS_0 of unsigned byte or short VEC4", &got))?;
                let types = [DataType::F32, DataType::U8, DataType::U16];
                check_accessor(&weights, Dimensions::Vec4, &types, blob.len())
                    .map_err(|got| bad(&what, "WEIGHTS_0 of float or normalised VEC4", &got))?;
                if joints.count() != count || weights.count() != count {
                    return Err(bad(
                        &what,
                        &format!("JOINTS_0 and WEIGHTS_0 for each of the {count} vertices"),
                        &format!("{} and {}", joints.count(), weights.count()),
                    ));
                }
                budget.take(&joints, 8).map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                budget.take(&weights, 16).map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                let unreadable = || bad(&what, "readable JOINTS_0 and WEIGHTS_0", &"none");
                kept.joints.extend(reader.read_joints(0).ok_or_else(unreadable)?.into_u16());
                kept.weights.extend(reader.read_weights(0).ok_or_else(unreadable)?.into_f32());
            }
            meshes.push((vertices, faces));
            skinning.push(mesh_skinning.filter(|s| !s.joints.is_empty()));
        }
        let mut tracks = Vec::new();
        for animation in document.animations() {
            for channel in animation.channels() {
                let what = format!("animation {} channel", animation.index());
                let step = match channel.sampler().interpolation() {
                    Interpolation::Linear => Step::Linear,
                    Interpolation::Step => Step::Constant,
                    Interpolation::CubicSpline => {
                        return Err(bad(&what, "LINEAR or STEP interpolation", &"CUBICSPLINE"));
                    }
                };
                let property = channel.target().property();
                if property == Property::MorphTargetWeights {
                    continue;
                }
                if channel.sampler().input().count() > MAX_KEYFRAMES {
                    return Err(bad(
                        &what,
                        &format!("at most {MAX_KEYFRAMES} keyframes"),
                        &channel.sampler().input().count(),
                    ));
                }
                let sampler = channel.sampler();
                check_accessor(&sampler.input(), Dimensions::Scalar, &[DataType::F32], blob.len())
                    .map_err(|got| bad(&what, "keyframe times of float scalars", &got))?;
                let (dimensions, types, expected) = match property {
                    Property::Rotation => (Dimensions::Vec4, ROTATION_TYPES, "VEC4 rotations"),
                    _ => (Dimensions::Vec3, [DataType::F32].as_slice(), "VEC3 float values"),
                };
                check_accessor(&sampler.output(), dimensions, types, blob.len())
                    .map_err(|got| bad(&what, expected, &got))?;
                budget.take(&sampler.input(), 4).map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                budget
                    .take(&sampler.output(), 16)
                    .map_err(|got| bad(&what, WITHIN_BUDGET, &got))?;
                let reader = channel.reader(data);
                let times: Vec<f32> = reader
                    .read_inputs()
                    .ok_or_else(|| bad(&what, "readable keyframe times", &"none"))?
                    .collect();
                let values: Vec<[f32; 4]> = match reader.read_outputs() {
                    Some(ReadOutputs::Translations(v) | ReadOutputs::Scales(v)) => {
                        v.map(|[x, y, z]| [x, y, z, 0.0]).collect()
                    }
                    Some(ReadOutputs::Rotations(r)) => r.into_f32().collect(),
                    _ => return Err(bad(&what, "readable keyframe values", &"none")),
                };
                if times.is_empty() || values.len() != times.len() {
                    return Err(bad(
                        &what,
                        "one value per keyframe time, at least one",
                        &format!("{} times, {} values", times.len(), values.len()),
                    ));
                }
                if times
                    .windows(2)
                    .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
                    || !times[0].is_finite()
                {
                    return Err(bad(&what, "increasing finite keyframe times", &"others"));
                }
                if values.iter().flatten().any(|v| !v.is_finite()) {
                    return Err(bad(&what, "finite keyframe values", &"NaN or infinity"));
                }
                let node = channel.target().node().index();
                tracks.push(Track { node, property, times, values, step });
            }
        }
        Ok(Self {
            source_name: source_name.to_string(),
            nodes,
            skins,
            meshes,
            skinning,
            tracks,
            order,
        })
    }

    /// The name used in errors (the file).
    pub fn source_name(&self) -> &str {
        &self.source_name
    }

    /// The keyframe times of the animation: those of the track with the most keyframes (the
    /// exporters write every animated property of a clip on one time grid; shorter tracks are
    /// constant ones). A scene without animation has one frame at time 0.
    pub fn keyframe_times(&self) -> Vec<f32> {
        self.tracks
            .iter()
            .max_by_key(|t| t.times.len())
            .map_or_else(|| vec![0.0], |t| t.times.clone())
    }

    /// The keyframes the animation tracks store, all tracks together: what the file holds to
    /// sample, which bounds how many samples a reader should take from it.
    pub fn stored_keyframes(&self) -> usize {
        self.tracks.iter().map(|t| t.times.len()).sum()
    }

    /// The local transform of every node at `time`.
    fn local_transforms(&self, time: f32) -> Vec<(Vec3, Quat, Vec3)> {
        let mut local: Vec<(Vec3, Quat, Vec3)> = self.nodes.iter().map(|n| n.rest).collect();
        for track in &self.tracks {
            let value = track.sample(time);
            let entry = &mut local[track.node];
            match track.property {
                Property::Translation => entry.0 = Vec3::new(value[0], value[1], value[2]),
                Property::Rotation => entry.1 = Quat::from_array(value).normalize(),
                Property::Scale => entry.2 = Vec3::new(value[0], value[1], value[2]),
                Property::MorphTargetWeights => {}
            }
        }
        local
    }

    /// The world matrix of every node at `time`.
    pub fn world_matrices(&self, time: f32) -> Vec<Mat4> {
        self.world_of(&self.local_transforms(time))
    }

    /// The world matrix of every node in the rest pose (the nodes' own transforms, no
    /// animation).
    pub fn rest_world_matrices(&self) -> Vec<Mat4> {
        let local: Vec<(Vec3, Quat, Vec3)> = self.nodes.iter().map(|n| n.rest).collect();
        self.world_of(&local)
    }

    /// World matrices from local transforms.
    fn world_of(&self, local: &[(Vec3, Quat, Vec3)]) -> Vec<Mat4> {
        let mut world = vec![Mat4::IDENTITY; self.nodes.len()];
        // Parents come first in `order`: each parent's matrix is ready for its children.
        for &node in &self.order {
            let (t, r, s) = local[node];
            let own = Mat4::from_scale_rotation_translation(s, r, t);
            world[node] = match self.nodes[node].parent {
                Some(p) => world[p] * own,
                None => own,
            };
        }
        world
    }

    /// The vertices and triangles of mesh `mesh` (all its primitives).
    pub fn mesh(&self, mesh: usize) -> &(Vec<Vec3>, Vec<[u32; 3]>) {
        &self.meshes[mesh]
    }

    /// The skin joints and weights of mesh `mesh`'s vertices, when all its primitives have them.
    pub fn skinning(&self, mesh: usize) -> Option<&Skinning> {
        self.skinning[mesh].as_ref()
    }
}

/// The nodes ordered so that each comes after its parent, or `Err` with a node on a cycle of
/// parents. Each node is walked over once (an explicit chain, no recursion): a deep tree costs
/// no stack and a long chain no quadratic time.
fn parents_first(nodes: &[Node]) -> std::result::Result<Vec<usize>, usize> {
    #[derive(Clone, Copy, PartialEq)]
    enum Seen {
        Not,
        OnChain,
        Placed,
    }
    let mut seen = vec![Seen::Not; nodes.len()];
    let mut order = Vec::with_capacity(nodes.len());
    let mut chain = Vec::new();
    for start in 0..nodes.len() {
        let mut node = Some(start);
        while let Some(n) = node {
            match seen[n] {
                Seen::Placed => break,
                Seen::OnChain => return Err(n),
                Seen::Not => {
                    seen[n] = Seen::OnChain;
                    chain.push(n);
                    node = nodes[n].parent;
                }
            }
        }
        // The chain runs child to parent: placed from its far end.
        for n in chain.drain(..).rev() {
            seen[n] = Seen::Placed;
            order.push(n);
        }
    }
    Ok(order)
}

/// What inverse bind matrices must be.
const MATRICES: &str = "inverse bind matrices of MAT4 float";

/// The component types glTF allows for rotation keyframes (normalised integers or floats).
const ROTATION_TYPES: &[DataType] =
    &[DataType::F32, DataType::I8, DataType::U8, DataType::I16, DataType::U16];

/// Checks an accessor before `gltf` 1.4 reads it: its readers assert the element type only in
/// debug builds (reading another type is a panic there and garbage otherwise), compute
/// `count - 1` and the extent without checks, and do not bound sparse accessors (all found by
/// the `glb` fuzz target). Sparse accessors are not read. `Err` says what was found.
fn check_accessor(
    accessor: &gltf::Accessor<'_>,
    dimensions: Dimensions,
    types: &[DataType],
    blob: usize,
) -> std::result::Result<(), String> {
    let index = accessor.index();
    if accessor.sparse().is_some() {
        return Err(format!("accessor {index}: a sparse accessor"));
    }
    if accessor.dimensions() != dimensions || !types.contains(&accessor.data_type()) {
        return Err(format!(
            "accessor {index}: {:?} of {:?}",
            accessor.dimensions(),
            accessor.data_type()
        ));
    }
    let count = accessor.count();
    if count == 0 {
        return Err(format!("accessor {index}: no elements"));
    }
    let view = accessor.view().ok_or_else(|| format!("accessor {index}: no buffer view"))?;
    let size = accessor.size();
    let stride = view.stride().unwrap_or(size);
    let extent = stride
        .checked_mul(count - 1)
        .and_then(|n| n.checked_add(size))
        .and_then(|n| n.checked_add(accessor.offset()));
    let view_end = view.offset().checked_add(view.length());
    match (extent, view_end) {
        (Some(extent), Some(end)) if stride >= size && extent <= view.length() && end <= blob => {
            Ok(())
        }
        _ => Err(format!(
            "accessor {index}: {count} elements of {size} bytes (stride {stride}) outside its \
             buffer view or the binary chunk"
        )),
    }
}

/// A reference that is wrong: where, what was expected, what was found.
type BadReference = (String, &'static str, String);

/// References that `gltf` 1.4 does not check before it follows them (each found by the `glb`
/// fuzz target): its validation indexes a primitive's `POSITION` accessor unchecked, and it
/// leaves animation channel targets unvalidated, so reading an unknown target path
/// (`"tr`nslation"`) or node through its wrappers panics.
fn check_references(root: &gltf::json::Root) -> std::result::Result<(), BadReference> {
    let accessors = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            let used = primitive.attributes.values().chain(&primitive.indices);
            if let Some(index) = used.map(|i| i.value()).find(|&i| i >= accessors) {
                let what = format!("mesh {m} primitive {p}");
                return Err((what, "accessors that exist", format!("accessor {index}")));
            }
        }
    }
    for (a, animation) in root.animations.iter().enumerate() {
        for (c, channel) in animation.channels.iter().enumerate() {
            let target = &channel.target;
            let what = || format!("animation {a} channel {c}");
            let expected = "a target node and one of translation, rotation, scale, weights";
            if !matches!(target.path, gltf::json::validation::Checked::Valid(_)) {
                return Err((what(), expected, "an unknown path".into()));
            }
            if target.node.value() >= root.nodes.len() {
                return Err((what(), expected, format!("node {}", target.node.value())));
            }
        }
    }
    Ok(())
}

impl Track {
    /// The value at `time`: clamped outside the keyframes, linear (spherical for rotations) or
    /// constant between them.
    fn sample(&self, time: f32) -> [f32; 4] {
        let last = self.times.len() - 1;
        if time <= self.times[0] {
            return self.values[0];
        }
        if time >= self.times[last] {
            return self.values[last];
        }
        let next = self.times.partition_point(|&t| t <= time);
        let k = next - 1;
        if self.step == Step::Constant {
            return self.values[k];
        }
        let alpha = (time - self.times[k]) / (self.times[next] - self.times[k]);
        let (a, b) = (self.values[k], self.values[next]);
        if self.property == Property::Rotation {
            let q = Quat::from_array(a).normalize().slerp(Quat::from_array(b).normalize(), alpha);
            return q.to_array();
        }
        std::array::from_fn(|i| a[i] + (b[i] - a[i]) * alpha)
    }
}

/// The fuzz corpus's seed GLB (`fuzz/make_seeds.py`), for tests: a triangle skinned to two
/// joints under a scaled `Armature`, a LINEAR translation and a STEP rotation, an animated
/// object.
#[cfg(test)]
pub(crate) fn seed_scene() -> GlbScene {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/corpus/glb/skinned_animated.glb");
    GlbScene::read(&path).unwrap()
}

/// A GLB of a JSON document and a binary chunk, for tests that make hostile files.
#[cfg(test)]
pub(crate) fn glb_bytes(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut text = json.as_bytes().to_vec();
    text.resize(text.len().next_multiple_of(4), b' ');
    let mut bin = bin.to_vec();
    bin.resize(bin.len().next_multiple_of(4), 0);
    let mut body = (text.len() as u32).to_le_bytes().to_vec();
    body.extend(b"JSON");
    body.extend(&text);
    if !bin.is_empty() {
        body.extend((bin.len() as u32).to_le_bytes());
        body.extend(b"BIN\0");
        body.extend(&bin);
    }
    let mut bytes = b"glTF".to_vec();
    bytes.extend(2u32.to_le_bytes());
    bytes.extend((12 + body.len() as u32).to_le_bytes());
    bytes.extend(body);
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    use super::seed_scene as seed;

    #[test]
    fn a_skinned_animated_scene_is_read_and_sampled() {
        let scene = seed();
        assert_eq!(scene.nodes.len(), 5);
        assert_eq!(scene.nodes[2].parent, Some(1));
        assert_eq!(scene.skins.len(), 1);
        assert_eq!(scene.skins[0].joints, [1, 2]);
        let times = scene.keyframe_times();
        assert_eq!(times.len(), 3);
        // Halfway between the first two keys: the hips' translation is interpolated, the
        // spine's STEP rotation is still the first key's; the Armature's scale applies.
        let world = scene.world_matrices(times[0] * 0.5 + times[1] * 0.5);
        let hips = world[1].w_axis.truncate();
        assert!(hips.abs_diff_eq(Vec3::new(0.0, 0.00905, 0.00005), 1e-6), "{hips}");
        let spine = Quat::from_mat4(&world[2]).normalize();
        assert!(
            spine.abs_diff_eq(Quat::IDENTITY, 1e-5) || spine.abs_diff_eq(-Quat::IDENTITY, 1e-5)
        );
        // After the last key, every track holds its last value.
        let end = scene.world_matrices(10.0);
        assert!(end[3].w_axis.truncate().abs_diff_eq(Vec3::new(0.0, 0.92, 0.02), 1e-6));
        let (vertices, faces) = scene.mesh(0);
        assert_eq!((vertices.len(), faces.as_slice()), (3, [[0, 1, 2]].as_slice()));
    }

    #[test]
    fn broken_files_are_refused_with_the_file_named() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../fuzz/corpus/glb/skinned_animated.glb");
        let bytes = std::fs::read(path).unwrap();
        for (bytes, needle) in [
            (b"not a glb".to_vec(), "magic `glTF`"),
            (bytes[..bytes.len() / 2].to_vec(), "header length"),
            (
                {
                    // The JSON without its required `asset`.
                    let at = bytes.windows(7).position(|w| w == b"\"asset\"").unwrap();
                    let mut broken = bytes.clone();
                    broken[at + 5] = b'x';
                    broken
                },
                "a valid glTF 2.0 binary",
            ),
        ] {
            let error = GlbScene::from_bytes(&bytes, "broken.glb").unwrap_err().to_string();
            assert!(error.contains("broken.glb") && error.contains(needle), "{error}");
        }
    }

    /// Fuzz findings, kept as regression tests: each must be a clear error, not a panic.
    #[test]
    fn fuzz_findings_are_errors() {
        let seed = std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../fuzz/corpus/glb/skinned_animated.glb"),
        )
        .unwrap();
        let patch = |from: &str, to: &str| {
            // Same length: the GLB's chunk lengths stay right.
            assert_eq!(from.len(), to.len());
            let at = seed.windows(from.len()).position(|w| w == from.as_bytes()).expect(from);
            let mut bytes = seed.clone();
            bytes[at..at + to.len()].copy_from_slice(to.as_bytes());
            bytes
        };
        for (bytes, needle) in [
            // A channel target path gltf 1.4 does not validate.
            (patch(r#""path":"translation""#, r#""path":"tr`nslation""#), "unknown path"),
            // A channel target node out of range.
            (patch(r#""node":1,"path""#, r#""node":9,"path""#), "node 9"),
            // Positions whose accessor is not VEC3 (gltf asserts the type only in debug builds).
            (patch(r#""type":"VEC3""#, r#""type":"VEC4""#), "VEC3 float"),
            // A primitive whose POSITION accessor does not exist (gltf's validation indexes it).
            (patch(r#""POSITION":0"#, r#""POSITION":9"#), "accessor 9"),
            // A header length below the header's own 12 bytes.
            (
                {
                    let mut bytes = seed.clone();
                    bytes[8..12].copy_from_slice(&4u32.to_le_bytes());
                    bytes
                },
                "header length",
            ),
        ] {
            let error = GlbScene::from_bytes(&bytes, "fuzzed.glb").unwrap_err().to_string();
            assert!(error.contains("fuzzed.glb") && error.contains(needle), "{error}");
        }
    }

    /// A buffer of `count` VEC3 positions and its accessor, for the documents below.
    fn positions(count: usize) -> (String, Vec<u8>) {
        let bin: Vec<u8> = (0..count * 3).flat_map(|i| (i as f32 * 1e-3).to_le_bytes()).collect();
        let json = format!(
            r#""buffers":[{{"byteLength":{n}}}],"bufferViews":[{{"buffer":0,"byteLength":{n}}}],
            "accessors":[{{"bufferView":0,"componentType":5126,"count":{count},"type":"VEC3",
            "min":[0,0,0],"max":[1,1,1]}}]"#,
            n = bin.len()
        );
        (json, bin)
    }

    #[test]
    fn an_accessor_read_again_and_again_stops_at_the_budget() {
        // 4,000 meshes of one 12 kB positions accessor: 48 MB decoded from a 200 kB file
        // (scaled up, gigabytes from megabytes).
        let (accessors, bin) = positions(999);
        let meshes = vec![r#"{"primitives":[{"attributes":{"POSITION":0}}]}"#; 4000].join(",");
        let json = format!(r#"{{"asset":{{"version":"2.0"}},{accessors},"meshes":[{meshes}]}}"#);
        let bytes = glb_bytes(&json, &bin);
        let started = std::time::Instant::now();
        let error = GlbScene::from_bytes(&bytes, "again.glb").unwrap_err().to_string();
        assert!(error.contains("again.glb") && error.contains("read again"), "{error}");
        assert!(started.elapsed().as_secs_f32() < 2.0);
        // Read once, it is fine.
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},{accessors},"meshes":[{}]}}"#,
            r#"{"primitives":[{"attributes":{"POSITION":0}}]}"#
        );
        let scene = GlbScene::from_bytes(&glb_bytes(&json, &bin), "once.glb").unwrap();
        assert_eq!(scene.mesh(0).0.len(), 999);
    }

    #[test]
    fn deep_node_chains_and_cycles() {
        // A chain of 100,000 nodes: the cycle check walked it once per node (quadratic) and
        // the world matrices recursed once per level.
        let count = 100_000;
        let mut nodes: Vec<String> =
            (1..count).map(|c| format!(r#"{{"children":[{c}]}}"#)).collect();
        nodes[0] = r#"{"children":[1],"translation":[1,2,3]}"#.into();
        nodes.push("{}".into());
        let json = format!(r#"{{"asset":{{"version":"2.0"}},"nodes":[{}]}}"#, nodes.join(","));
        let started = std::time::Instant::now();
        let scene = GlbScene::from_bytes(&glb_bytes(&json, &[]), "deep.glb").unwrap();
        let world = scene.world_matrices(0.0);
        assert_eq!(world.len(), count);
        assert!(world[count - 1].w_axis.truncate().abs_diff_eq(Vec3::new(1.0, 2.0, 3.0), 1e-6));
        assert!(started.elapsed().as_secs_f32() < 5.0);
        // Two nodes each the other's child.
        let json = r#"{"asset":{"version":"2.0"},"nodes":[{"children":[1]},{"children":[0]}]}"#;
        match GlbScene::from_bytes(&glb_bytes(json, &[]), "cycle.glb") {
            Ok(_) => panic!("a cycle was read"),
            Err(error) => {
                let error = error.to_string();
                assert!(error.contains("cycle.glb") && error.contains("cycle"), "{error}");
            }
        }
    }
}
