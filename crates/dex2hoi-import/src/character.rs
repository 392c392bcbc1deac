//! A skinned character in a glTF binary (a Mixamo rig exported by Blender, or the character
//! inside a HUMOTO GLB): its skin's bones with their rest transforms, and every mesh bound to
//! that skin in its rest pose (each vertex skinned by the bones' rest transforms and inverse bind
//! matrices, so a file whose rest pose is not its bind pose still reads as it stands at rest).
//! The animations of the file are not read.

use std::path::Path;

use glam::{Mat4, Vec3, Vec4};

use crate::error::{ImportError, Result};
use crate::glb::GlbScene;

/// A bone of the skin.
#[derive(Debug, Clone, PartialEq)]
pub struct SkinBone {
    /// The bone node's name.
    pub name: String,
    /// The nearest ancestor that is also a bone of the skin (index into the bones).
    pub parent: Option<usize>,
    /// World rest transform (the file's units; glTF is Y up).
    pub rest: Mat4,
}

/// A character read from a GLB.
#[derive(Debug, Clone, PartialEq)]
pub struct Character {
    /// The skin's bones, in the skin's order.
    pub bones: Vec<SkinBone>,
    /// The rest vertices of every mesh bound to the skin, one after the other.
    pub vertices: Vec<Vec3>,
    /// Their triangles.
    pub faces: Vec<[u32; 3]>,
    /// Four bones (indices into `bones`) per vertex.
    pub joints: Vec<[u16; 4]>,
    /// Their weights.
    pub weights: Vec<[f32; 4]>,
}

impl Character {
    /// Reads the character of a `.glb` file: the skin with the most skinned vertices.
    pub fn read(path: &Path) -> Result<Self> {
        let scene = GlbScene::read(path)?;
        Self::from_scene(&scene)
    }

    /// The character of a scene read already.
    pub fn from_scene(scene: &GlbScene) -> Result<Self> {
        let skinned = |node: &crate::glb::Node| -> Option<(usize, usize)> {
            let mesh = node.mesh?;
            scene.skinning(mesh)?;
            Some((mesh, node.skin?))
        };
        // The skin that binds the most vertices.
        let mut vertices_per_skin = vec![0usize; scene.skins.len()];
        for (mesh, skin) in scene.nodes.iter().filter_map(skinned) {
            vertices_per_skin[skin] += scene.mesh(mesh).0.len();
        }
        let skin = (0..scene.skins.len())
            .filter(|&s| vertices_per_skin[s] > 0)
            .max_by_key(|&s| vertices_per_skin[s])
            .ok_or_else(|| {
                ImportError::format(
                    scene.source_name(),
                    "character",
                    "a skinned mesh (a node with a mesh and a skin, JOINTS_0 and WEIGHTS_0)",
                    "none",
                )
            })?;
        let rig = &scene.skins[skin];
        let rest = scene.rest_world_matrices();
        let bone_of = |node: usize| rig.joints.iter().position(|&j| j == node);
        let bones: Vec<SkinBone> = rig
            .joints
            .iter()
            .map(|&node| {
                let mut ancestor = scene.nodes[node].parent;
                while let Some(a) = ancestor {
                    if bone_of(a).is_some() {
                        break;
                    }
                    ancestor = scene.nodes[a].parent;
                }
                SkinBone {
                    name: scene.nodes[node].name.clone(),
                    parent: ancestor.and_then(bone_of),
                    rest: rest[node],
                }
            })
            .collect();
        // Each bone's skinning matrix at rest: its world rest transform after its inverse bind.
        let skinning: Vec<Mat4> = rig
            .joints
            .iter()
            .zip(&rig.inverse_bind_matrices)
            .map(|(&node, inverse_bind)| rest[node] * *inverse_bind)
            .collect();
        let mut character = Self {
            bones,
            vertices: Vec::new(),
            faces: Vec::new(),
            joints: Vec::new(),
            weights: Vec::new(),
        };
        for (mesh, _) in scene.nodes.iter().filter_map(skinned).filter(|(_, s)| *s == skin) {
            let (vertices, faces) = scene.mesh(mesh);
            let weights = scene.skinning(mesh).expect("a skinned mesh");
            let base = character.vertices.len() as u32;
            for (k, (&v, (row, w))) in
                vertices.iter().zip(weights.joints.iter().zip(&weights.weights)).enumerate()
            {
                if let Some(&bone) = row.iter().find(|&&b| usize::from(b) >= skinning.len()) {
                    return Err(ImportError::format(
                        scene.source_name(),
                        format!("mesh {mesh}, vertex {k}"),
                        format!("skin joints below {}", skinning.len()),
                        bone,
                    ));
                }
                let total: f32 = w.iter().sum();
                if !(total.is_finite() && total > 0.0) {
                    return Err(ImportError::format(
                        scene.source_name(),
                        format!("mesh {mesh}, vertex {k}"),
                        "skin weights with a positive sum",
                        format!("{w:?}"),
                    ));
                }
                let point = Vec4::new(v.x, v.y, v.z, 1.0);
                let posed: Vec4 = row
                    .iter()
                    .zip(w)
                    .map(|(&bone, &weight)| skinning[usize::from(bone)] * point * (weight / total))
                    .sum();
                character.vertices.push(posed.truncate());
            }
            character.faces.extend(faces.iter().map(|f| f.map(|i| i + base)));
            character.joints.extend_from_slice(&weights.joints);
            character.weights.extend_from_slice(&weights.weights);
        }
        Ok(character)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::glb::{glb_bytes, seed_scene as seed};

    #[test]
    fn the_skin_is_read_at_rest_with_its_bones() {
        let scene = seed();
        let character = Character::from_scene(&scene).unwrap();
        let names: Vec<&str> = character.bones.iter().map(|b| b.name.as_str()).collect();
        assert_eq!(names, ["mixamorig:Hips", "mixamorig:Spine"]);
        assert_eq!([character.bones[0].parent, character.bones[1].parent], [None, Some(0)]);
        // The Armature's scale turns centimetres into metres.
        let hips = character.bones[0].rest.w_axis.truncate();
        assert!(hips.abs_diff_eq(Vec3::new(0.0, 0.88, 0.0), 1e-6), "{hips}");
        // Each vertex is its bind position taken through its bones' rest transforms and inverse
        // binds: where the rest pose is the bind pose, where the world puts the bind position.
        let (vertices, faces) = scene.mesh(0);
        assert_eq!(character.faces, *faces);
        let skin = &scene.skins[0];
        let rest = scene.rest_world_matrices();
        let weights = scene.skinning(0).unwrap();
        for (k, vertex) in character.vertices.iter().enumerate() {
            let expected: Vec3 = (0..4)
                .map(|i| {
                    let bone = usize::from(weights.joints[k][i]);
                    let matrix = rest[skin.joints[bone]] * skin.inverse_bind_matrices[bone];
                    matrix.transform_point3(vertices[k]) * weights.weights[k][i]
                })
                .sum::<Vec3>()
                / weights.weights[k].iter().sum::<f32>();
            assert!(vertex.abs_diff_eq(expected, 1e-6), "vertex {k}: {vertex} vs {expected}");
        }
    }

    #[test]
    fn a_file_without_a_skinned_mesh_is_refused() {
        let json = r#"{"asset":{"version":"2.0"},"nodes":[{"name":"mixamorig:Hips"}]}"#;
        let scene = GlbScene::from_bytes(&glb_bytes(json, &[]), "bones-only.glb").unwrap();
        let error = Character::from_scene(&scene).unwrap_err().to_string();
        assert!(error.contains("bones-only.glb") && error.contains("skinned mesh"), "{error}");
    }
}
