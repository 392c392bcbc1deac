//! `motion.glb`: glTF 2.0 binary (one JSON chunk, one BIN chunk) that opens in Blender and
//! three.js.
//!
//! - One node per joint (node `j` is joint `j`), named as the rig names it (`mixamorig:Hips`,
//!   [`dex2hoi_repr::Skeleton::rig_joint_names`]) and parented as in the skeleton; the root
//!   joint is a root node of the scene. Each node's rest transform is in the rig's own bone
//!   frames ([`dex2hoi_repr::Skeleton::rest_orientations`]: Mixamo's for `mixamo65`, the
//!   world's for SMPL-X): translation `B_parent^T rel_j`, rotation `B_parent^T B_j`
//!   (docs/CONVENTIONS.md, "Rest orientations"). With an SMPL-X mesh, its jaw and eyes follow as
//!   three more nodes under the head, at rest.
//! - A skin over those joints whose inverse bind matrices are the inverse rest transforms
//!   `(T(rest_j) B_j)^-1`, and a body node carrying the body mesh: the SMPL-X model's
//!   ([`mod@crate::smplx_body`], its four largest weights per vertex), a Mixamo character's
//!   ([`mod@crate::character`]: its bone names and frames, its other bones at rest) or the capsules of
//!   [`mod@crate::body_mesh`] (one joint per vertex, weight 1). `POSITION` (with exact
//!   `min`/`max`), `NORMAL`, `JOINTS_0` (unsigned byte, or unsigned short beyond 256 joints),
//!   `WEIGHTS_0`, unsigned int indices.
//! - One node per object with its mesh, in the object frame.
//! - One animation, linear: the root joint's translation (its world position), every joint's
//!   rotation `B_parent^T R_j B_j` (unit quaternions `x, y, z, w`), each object's translation
//!   and rotation; key times `frame / fps` seconds with `min`/`max`.
//!
//! The scene's `extras` hold the text, the frame rate, the skeleton, the body and its betas.
//! Units are metres, Y up, as glTF.

use std::path::Path;

use glam::{Mat3, Mat4, Quat, Vec3};
use serde_json::{Value, json};

use dex2hoi_repr::rotation::matrix_to_quaternion;

use crate::body_mesh::body_mesh;
use crate::error::{ExportError, Result};
use crate::smplx_body::FACE_JOINT_NAMES;
use crate::{Body, Checked, ExportMotion, write_file};

/// glTF component types.
const FLOAT: u32 = 5126;
const UNSIGNED_BYTE: u32 = 5121;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_INT: u32 = 5125;
/// Buffer view targets.
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
/// GLB magic and chunk types (little-endian ASCII `glTF`, `JSON`, `BIN\0`).
const GLB_MAGIC: u32 = 0x4654_6C67;
const GLB_VERSION: u32 = 2;
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

/// Base colours (linear RGBA) of the body and the objects, as in the preview.
const BODY_COLOUR: [f32; 4] = [0.10, 0.26, 0.65, 1.0];
const OBJECT_COLOURS: [[f32; 4]; 3] =
    [[0.84, 0.20, 0.02, 1.0], [0.04, 0.45, 0.11, 1.0], [0.55, 0.05, 0.35, 1.0]];

/// The binary chunk under construction with its buffer views and accessors.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

/// An accessor's element type: its glTF name and number of components.
#[derive(Clone, Copy)]
enum Element {
    Scalar,
    Vec3,
    Vec4,
    Mat4,
}

impl Element {
    fn name(self) -> &'static str {
        match self {
            Self::Scalar => "SCALAR",
            Self::Vec3 => "VEC3",
            Self::Vec4 => "VEC4",
            Self::Mat4 => "MAT4",
        }
    }

    fn components(self) -> usize {
        match self {
            Self::Scalar => 1,
            Self::Vec3 => 3,
            Self::Vec4 => 4,
            Self::Mat4 => 16,
        }
    }
}

impl Builder {
    /// Appends bytes as a new buffer view (4-byte aligned) and returns its index.
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        self.bin.resize(self.bin.len().next_multiple_of(4), 0);
        let mut view = json!({
            "buffer": 0,
            "byteOffset": self.bin.len(),
            "byteLength": bytes.len(),
        });
        if let Some(target) = target {
            view["target"] = json!(target);
        }
        self.bin.extend_from_slice(bytes);
        self.views.push(view);
        self.views.len() - 1
    }

    fn accessor(&mut self, view: usize, component: u32, element: Element, count: usize) -> usize {
        self.accessors.push(json!({
            "bufferView": view,
            "componentType": component,
            "count": count,
            "type": element.name(),
        }));
        self.accessors.len() - 1
    }

    /// A float accessor; `bounds` adds the exact per-component `min` and `max`.
    fn floats(
        &mut self,
        values: &[f32],
        element: Element,
        target: Option<u32>,
        bounds: bool,
    ) -> usize {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let components = element.components();
        let index = self.accessor(view, FLOAT, element, values.len() / components);
        if bounds {
            let mut min = vec![f32::MAX; components];
            let mut max = vec![f32::MIN; components];
            for chunk in values.chunks_exact(components) {
                for (k, &v) in chunk.iter().enumerate() {
                    min[k] = min[k].min(v);
                    max[k] = max[k].max(v);
                }
            }
            // Widened to f64 so that the JSON numbers read back as exactly these f32 values.
            let widen = |v: Vec<f32>| v.into_iter().map(f64::from).collect::<Vec<_>>();
            self.accessors[index]["min"] = json!(widen(min));
            self.accessors[index]["max"] = json!(widen(max));
        }
        index
    }
}

fn vec3s(values: impl IntoIterator<Item = Vec3>) -> Vec<f32> {
    values.into_iter().flat_map(|v| v.to_array()).collect()
}

/// Unit quaternions `x, y, z, w` of rotation matrices.
fn quaternions(rotations: impl IntoIterator<Item = Mat3>) -> Vec<f32> {
    rotations.into_iter().flat_map(|r| matrix_to_quaternion(r).normalize().to_array()).collect()
}

fn material(name: &str, colour: [f32; 4]) -> Value {
    json!({
        "name": name,
        "pbrMetallicRoughness": {
            "baseColorFactor": colour,
            "metallicFactor": 0.0,
            "roughnessFactor": 0.8,
        },
    })
}

/// The skinned body: its rest vertices with up to four joints and weights each.
struct BodyMesh<'a> {
    vertices: &'a [Vec3],
    normals: &'a [Vec3],
    faces: &'a [[u32; 3]],
    joints: Vec<[u16; 4]>,
    weights: Vec<[f32; 4]>,
}

/// The skin's joints in the rig's own names and frames: the skeleton's joints, then (with an
/// SMPL-X mesh) the mesh's face joints as children of the head.
struct Rig {
    names: Vec<String>,
    children: Vec<Vec<usize>>,
    /// World rest orientation `B_j` of each skin joint.
    orientations: Vec<Quat>,
    rest_positions: Vec<Vec3>,
    /// Node rest translation and rotation in the parent's frame: `B_parent^T rel_j`,
    /// `B_parent^T B_j`.
    translations: Vec<Vec3>,
    /// Unit quaternions `x, y, z, w`, normalised in f64 so no component exceeds 1.
    rest_rotations: Vec<[f64; 4]>,
    parents: Vec<Option<usize>>,
}

impl Rig {
    fn new(motion: &Checked<'_>) -> Self {
        let skeleton = motion.skeleton;
        let mut names = skeleton.rig_joint_names();
        let mut children = skeleton.children();
        let mut orientations = skeleton.rest_orientations();
        let mut rest_positions = skeleton.rest_positions();
        let mut parents = skeleton.parents().to_vec();
        let mut add = |name: String, parent: usize, position: Vec3, orientation: Quat| {
            children[parent].push(names.len());
            names.push(name);
            children.push(Vec::new());
            orientations.push(orientation);
            rest_positions.push(position);
            parents.push(Some(parent));
        };
        match motion.body {
            Some(Body::Smplx(body)) => {
                let head = skeleton.joint_index("head").unwrap_or(0);
                for (name, position) in FACE_JOINT_NAMES.iter().zip(body.face_joints) {
                    add((*name).to_string(), head, position, Quat::IDENTITY);
                }
            }
            // The character's own bone names and frames, so the file drops onto its rig.
            Some(Body::Character(character)) => {
                for extra in &character.extra_joints {
                    add(extra.name.clone(), extra.parent, extra.rest_position, extra.orientation);
                }
                let joints = skeleton.joint_count();
                names[..joints].clone_from_slice(&character.bone_names);
                orientations[..joints].copy_from_slice(&character.orientations);
            }
            None => {}
        }
        let mut rig = Self {
            names,
            children,
            orientations,
            rest_positions,
            translations: Vec::new(),
            rest_rotations: Vec::new(),
            parents,
        };
        (rig.translations, rig.rest_rotations) = (0..rig.names.len())
            .map(|j| {
                let parent = rig.parent_orientation(j).conjugate();
                let base = rig.parents[j].map_or(Vec3::ZERO, |p| rig.rest_positions[p]);
                let rotation = (parent.as_dquat() * rig.orientations[j].as_dquat()).normalize();
                (parent * (rig.rest_positions[j] - base), rotation.to_array())
            })
            .unzip();
        rig
    }

    /// `B_parent` (identity for the root).
    fn parent_orientation(&self, joint: usize) -> Quat {
        self.parents[joint].map_or(Quat::IDENTITY, |p| self.orientations[p])
    }
}

/// The glTF JSON and binary chunk of a checked motion.
fn document(motion: &Checked<'_>) -> Result<(Value, Vec<u8>)> {
    let skeleton = motion.skeleton;
    let joints = skeleton.joint_count();
    let mut builder = Builder::default();
    let capsules;

    // Skeleton nodes and skin: our joints, then (with an SMPL-X mesh) its face joints at rest.
    let rig = Rig::new(motion);
    let skin_joints = rig.names.len();
    let mut nodes: Vec<Value> = (0..skin_joints)
        .map(|j| {
            let mut node = json!({
                "name": rig.names[j],
                "translation": rig.translations[j].to_array(),
                "rotation": rig.rest_rotations[j],
            });
            if !rig.children[j].is_empty() {
                node["children"] = json!(rig.children[j]);
            }
            node
        })
        .collect();
    let inverse_binds: Vec<f32> = rig
        .rest_positions
        .iter()
        .zip(&rig.orientations)
        .flat_map(|(&p, &b)| {
            // (T(p) B)^-1 = B^T T(-p), built directly so the last row is exactly (0, 0, 0, 1).
            Mat4::from_rotation_translation(b.conjugate(), -(b.conjugate() * p)).to_cols_array()
        })
        .collect();
    let inverse_binds = builder.floats(&inverse_binds, Element::Mat4, None, false);
    let skin = json!({
        "name": "skeleton",
        "joints": (0..skin_joints).collect::<Vec<_>>(),
        "inverseBindMatrices": inverse_binds,
        "skeleton": 0,
    });

    // The body mesh: the SMPL-X model's, or capsules bound rigidly to the joints.
    let body = match motion.body {
        Some(Body::Smplx(mesh)) => BodyMesh {
            vertices: &mesh.vertices,
            normals: &mesh.normals,
            faces: &mesh.faces,
            joints: mesh.joints.iter().map(|j| j.map(u16::from)).collect(),
            weights: mesh.weights.clone(),
        },
        Some(Body::Character(character)) => BodyMesh {
            vertices: &character.vertices,
            normals: &character.normals,
            faces: &character.faces,
            joints: character.joints.clone(),
            weights: character.weights.clone(),
        },
        None => {
            capsules = body_mesh(skeleton);
            BodyMesh {
                vertices: &capsules.vertices,
                normals: &capsules.normals,
                faces: &capsules.faces,
                joints: capsules.joints.iter().map(|&j| [j, 0, 0, 0]).collect(),
                weights: vec![[1.0, 0.0, 0.0, 0.0]; capsules.vertices.len()],
            }
        }
    };
    let positions = builder.floats(
        &vec3s(body.vertices.iter().copied()),
        Element::Vec3,
        Some(ARRAY_BUFFER),
        true,
    );
    let normals = builder.floats(
        &vec3s(body.normals.iter().copied()),
        Element::Vec3,
        Some(ARRAY_BUFFER),
        false,
    );
    let vertex_count = body.vertices.len();
    let joint_indices = if skin_joints <= 256 {
        let bytes: Vec<u8> = body.joints.iter().flatten().map(|&j| j as u8).collect();
        let view = builder.view(&bytes, Some(ARRAY_BUFFER));
        builder.accessor(view, UNSIGNED_BYTE, Element::Vec4, vertex_count)
    } else if skin_joints <= 65536 {
        let bytes: Vec<u8> = body.joints.iter().flatten().flat_map(|j| j.to_le_bytes()).collect();
        let view = builder.view(&bytes, Some(ARRAY_BUFFER));
        builder.accessor(view, UNSIGNED_SHORT, Element::Vec4, vertex_count)
    } else {
        return Err(ExportError::invalid("glTF skin", "at most 65536 joints", skin_joints));
    };
    let weights: Vec<f32> = body.weights.iter().flatten().copied().collect();
    let weights = builder.floats(&weights, Element::Vec4, Some(ARRAY_BUFFER), false);
    let indices = |faces: &[[u32; 3]], builder: &mut Builder| {
        let bytes: Vec<u8> = faces.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        let view = builder.view(&bytes, Some(ELEMENT_ARRAY_BUFFER));
        builder.accessor(view, UNSIGNED_INT, Element::Scalar, faces.len() * 3)
    };
    let body_indices = indices(body.faces, &mut builder);
    let mut meshes = vec![json!({
        "name": motion.body.map_or("body", |b| b.kind_name()),
        "primitives": [{
            "attributes": {
                "POSITION": positions,
                "NORMAL": normals,
                "JOINTS_0": joint_indices,
                "WEIGHTS_0": weights,
            },
            "indices": body_indices,
            "material": 0,
        }],
    })];
    let mut materials = vec![material("body", BODY_COLOUR)];
    let body_node = nodes.len();
    nodes.push(json!({ "name": "body", "mesh": 0, "skin": 0 }));

    // Objects.
    let mut object_nodes = Vec::new();
    for (k, object) in motion.objects.iter().enumerate() {
        let positions = builder.floats(
            &vec3s(object.mesh.vertices.iter().copied()),
            Element::Vec3,
            Some(ARRAY_BUFFER),
            true,
        );
        let object_indices = indices(&object.mesh.faces, &mut builder);
        materials.push(material(object.name, OBJECT_COLOURS[k.min(OBJECT_COLOURS.len() - 1)]));
        meshes.push(json!({
            "name": object.name,
            "primitives": [{
                "attributes": { "POSITION": positions },
                "indices": object_indices,
                "material": materials.len() - 1,
            }],
        }));
        object_nodes.push(nodes.len());
        let rotation: Quat = matrix_to_quaternion(object.rotations[0]).normalize();
        nodes.push(json!({
            "name": object.name,
            "mesh": meshes.len() - 1,
            "translation": object.positions[0].to_array(),
            "rotation": rotation.to_array(),
        }));
    }

    // The animation.
    let times: Vec<f32> = (0..motion.frames).map(|t| motion.time(t)).collect();
    let input = builder.floats(&times, Element::Scalar, None, true);
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    let mut animate = |node: usize, path: &str, output: usize| {
        samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
        channels.push(
            json!({ "sampler": samplers.len() - 1, "target": { "node": node, "path": path } }),
        );
    };
    let root_translation =
        builder.floats(&vec3s(motion.root_positions.iter().copied()), Element::Vec3, None, false);
    animate(0, "translation", root_translation);
    for joint in 0..joints {
        // In the rig's frames: L = B_parent^T R B_joint (docs/CONVENTIONS.md, "Rest orientations").
        let (parent, own) = (rig.parent_orientation(joint), rig.orientations[joint]);
        let rotations: Vec<f32> = (0..motion.frames)
            .flat_map(|t| {
                let local = matrix_to_quaternion(motion.local_rotations[t * joints + joint]);
                (parent.conjugate() * local.normalize() * own).normalize().to_array()
            })
            .collect();
        let output = builder.floats(&rotations, Element::Vec4, None, false);
        animate(joint, "rotation", output);
    }
    for (object, &node) in motion.objects.iter().zip(&object_nodes) {
        let translation =
            builder.floats(&vec3s(object.positions.iter().copied()), Element::Vec3, None, false);
        animate(node, "translation", translation);
        let rotation = builder.floats(
            &quaternions(object.rotations.iter().copied()),
            Element::Vec4,
            None,
            false,
        );
        animate(node, "rotation", rotation);
    }

    builder.bin.resize(builder.bin.len().next_multiple_of(4), 0);
    let scene_nodes: Vec<usize> = [0, body_node].into_iter().chain(object_nodes).collect();
    let document = json!({
        "asset": { "version": "2.0", "generator": concat!("dex2hoi-export ", env!("CARGO_PKG_VERSION")) },
        "scene": 0,
        "scenes": [{
            "name": "motion",
            "nodes": scene_nodes,
            "extras": {
                "text": motion.text,
                "fps": motion.fps,
                "skeleton": skeleton.kind().name(),
                "body": motion.body.map_or("capsules", |b| b.kind_name()),
                "betas": motion.body.and_then(|b| b.betas().map(<[f32]>::to_vec)),
            },
        }],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "skins": [skin],
        "animations": [{ "name": "motion", "samplers": samplers, "channels": channels }],
        "accessors": builder.accessors,
        "bufferViews": builder.views,
        "buffers": [{ "byteLength": builder.bin.len() }],
    });
    Ok((document, builder.bin))
}

/// A GLB container around a JSON document and a binary chunk.
fn glb_bytes(document: &Value, bin: &[u8]) -> Result<Vec<u8>> {
    let mut json = serde_json::to_vec(document)
        .map_err(|e| ExportError::invalid("glTF JSON", "serialisable values", e))?;
    json.resize(json.len().next_multiple_of(4), b' ');
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let total =
        u32::try_from(total).map_err(|_| ExportError::invalid("GLB size", "below 4 GiB", total))?;
    let mut out = Vec::with_capacity(total as usize);
    for word in [GLB_MAGIC, GLB_VERSION, total, json.len() as u32, CHUNK_JSON] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.extend_from_slice(&json);
    for word in [bin.len() as u32, CHUNK_BIN] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.extend_from_slice(bin);
    Ok(out)
}

/// The bytes of `motion.glb` for a motion (layout in the module documentation).
///
/// # Shapes
/// - the motion's `local_rotations`: `[frames * joints]`; `root_positions`: `[frames]`; each
///   exported object's slot: `[frames]` rotations and positions
pub fn encode_glb(motion: &ExportMotion<'_>) -> Result<Vec<u8>> {
    let checked = motion.check()?;
    let (document, bin) = document(&checked)?;
    glb_bytes(&document, &bin)
}

/// Writes `motion.glb` atomically (see [`encode_glb`]).
///
/// # Shapes
/// - as [`encode_glb`]
pub fn write_glb(path: &Path, motion: &ExportMotion<'_>) -> Result<()> {
    let bytes = encode_glb(motion)?;
    write_file(path, &bytes)
}
