//! Reading a GLB back: the container, accessors, and the node transforms its animation gives.

use glam::{Mat4, Quat, Vec3};
use serde_json::Value;

/// The JSON document and the binary chunk of a GLB, with the container checked.
pub fn parse_glb(bytes: &[u8]) -> (Value, Vec<u8>) {
    let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
    assert_eq!(&bytes[0..4], b"glTF");
    assert_eq!(word(4), 2, "version");
    assert_eq!(word(8) as usize, bytes.len(), "total length");
    let json_length = word(12) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    assert_eq!(json_length % 4, 0);
    let json: Value = serde_json::from_slice(&bytes[20..20 + json_length]).expect("JSON chunk");
    let bin_at = 20 + json_length;
    let bin_length = word(bin_at) as usize;
    assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
    assert_eq!(bin_length % 4, 0);
    assert_eq!(bin_at + 8 + bin_length, bytes.len());
    (json, bytes[bin_at + 8..].to_vec())
}

pub fn component_size(component: u64) -> usize {
    match component {
        5121 => 1,
        5123 => 2,
        5125 | 5126 => 4,
        other => panic!("unexpected component type {other}"),
    }
}

pub fn components(kind: &str) -> usize {
    match kind {
        "SCALAR" => 1,
        "VEC3" => 3,
        "VEC4" => 4,
        "MAT4" => 16,
        other => panic!("unexpected accessor type {other}"),
    }
}

/// The floats of a float accessor.
pub fn floats(json: &Value, bin: &[u8], accessor: usize) -> Vec<f32> {
    let accessor = &json["accessors"][accessor];
    assert_eq!(accessor["componentType"], 5126);
    let view = &json["bufferViews"][accessor["bufferView"].as_u64().expect("view") as usize];
    let start = view["byteOffset"].as_u64().expect("offset") as usize;
    let length = view["byteLength"].as_u64().expect("length") as usize;
    bin[start..start + length]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
        .collect()
}

/// The unsigned integers of a `JOINTS_0`-style accessor (unsigned byte or short).
pub fn unsigned(json: &Value, bin: &[u8], accessor: usize) -> Vec<u32> {
    let accessor = &json["accessors"][accessor];
    let view = &json["bufferViews"][accessor["bufferView"].as_u64().expect("view") as usize];
    let start = view["byteOffset"].as_u64().expect("offset") as usize;
    let length = view["byteLength"].as_u64().expect("length") as usize;
    let bytes = &bin[start..start + length];
    match accessor["componentType"].as_u64() {
        Some(5121) => bytes.iter().map(|&b| u32::from(b)).collect(),
        Some(5123) => {
            bytes.chunks_exact(2).map(|b| u32::from(u16::from_le_bytes([b[0], b[1]]))).collect()
        }
        other => panic!("unexpected component type {other:?}"),
    }
}

fn vec3_of(value: Option<&Value>, default: Vec3) -> Vec3 {
    value.map_or(default, |t| {
        Vec3::new(
            t[0].as_f64().unwrap_or(0.0) as f32,
            t[1].as_f64().unwrap_or(0.0) as f32,
            t[2].as_f64().unwrap_or(0.0) as f32,
        )
    })
}

/// World matrix of every node at every key frame of the first animation (keys are frames),
/// from the nodes' own TRS where no channel animates them.
///
/// # Shapes
/// - returns `[frames][nodes]`
pub fn node_worlds(json: &Value, bin: &[u8], frames: usize) -> Vec<Vec<Mat4>> {
    let nodes = json["nodes"].as_array().expect("nodes");
    let mut translations: Vec<Vec<Vec3>> =
        nodes.iter().map(|n| vec![vec3_of(n.get("translation"), Vec3::ZERO); frames]).collect();
    let mut rotations: Vec<Vec<Quat>> = nodes
        .iter()
        .map(|n| {
            let q = n.get("rotation").map_or(Quat::IDENTITY, |r| {
                Quat::from_xyzw(
                    r[0].as_f64().unwrap_or(0.0) as f32,
                    r[1].as_f64().unwrap_or(0.0) as f32,
                    r[2].as_f64().unwrap_or(0.0) as f32,
                    r[3].as_f64().unwrap_or(1.0) as f32,
                )
            });
            vec![q; frames]
        })
        .collect();
    let scales: Vec<Vec3> = nodes.iter().map(|n| vec3_of(n.get("scale"), Vec3::ONE)).collect();
    let animation = &json["animations"][0];
    for channel in animation["channels"].as_array().expect("channels") {
        let sampler =
            &animation["samplers"][channel["sampler"].as_u64().expect("sampler") as usize];
        let output = floats(json, bin, sampler["output"].as_u64().expect("output") as usize);
        let node = channel["target"]["node"].as_u64().expect("node") as usize;
        match channel["target"]["path"].as_str().expect("path") {
            "translation" => {
                translations[node] = output.chunks_exact(3).map(Vec3::from_slice).collect()
            }
            "rotation" => {
                rotations[node] = output.chunks_exact(4).map(Quat::from_slice).collect();
                assert!(rotations[node].iter().all(|q| (q.length() - 1.0).abs() < 1e-6));
            }
            other => panic!("unexpected path {other}"),
        }
    }
    let mut parent = vec![None; nodes.len()];
    for (index, node) in nodes.iter().enumerate() {
        for child in node["children"].as_array().into_iter().flatten() {
            parent[child.as_u64().expect("child") as usize] = Some(index);
        }
    }
    (0..frames)
        .map(|t| {
            let mut world: Vec<Option<Mat4>> = vec![None; nodes.len()];
            fn resolve(
                node: usize,
                parent: &[Option<usize>],
                local: &dyn Fn(usize) -> Mat4,
                world: &mut Vec<Option<Mat4>>,
            ) -> Mat4 {
                if let Some(m) = world[node] {
                    return m;
                }
                let m = match parent[node] {
                    Some(p) => resolve(p, parent, local, world) * local(node),
                    None => local(node),
                };
                world[node] = Some(m);
                m
            }
            let local = |n: usize| {
                Mat4::from_scale_rotation_translation(
                    scales[n],
                    rotations[n][t],
                    translations[n][t],
                )
            };
            (0..nodes.len()).map(|n| resolve(n, &parent, &local, &mut world)).collect()
        })
        .collect()
}

/// The skinned vertices of a node's mesh (first primitive) at every frame: linear blend
/// skinning by the skin's joints' world matrices times their inverse bind matrices.
///
/// # Shapes
/// - `worlds`: `[frames][nodes]` ([`node_worlds`]); returns `[frames][vertices]`
pub fn skinned_vertices(
    json: &Value,
    bin: &[u8],
    node: usize,
    worlds: &[Vec<Mat4>],
) -> Vec<Vec<Vec3>> {
    let node = &json["nodes"][node];
    let skin = &json["skins"][node["skin"].as_u64().expect("skinned node") as usize];
    let primitive = &json["meshes"][node["mesh"].as_u64().expect("mesh") as usize]["primitives"][0];
    let attribute = |name: &str| primitive["attributes"][name].as_u64().expect(name) as usize;
    let positions = floats(json, bin, attribute("POSITION"));
    let joints = unsigned(json, bin, attribute("JOINTS_0"));
    let weights = floats(json, bin, attribute("WEIGHTS_0"));
    let binds = floats(json, bin, skin["inverseBindMatrices"].as_u64().expect("ibm") as usize);
    let skin_nodes: Vec<usize> = skin["joints"]
        .as_array()
        .expect("joints")
        .iter()
        .map(|j| j.as_u64().expect("joint") as usize)
        .collect();
    worlds
        .iter()
        .map(|world| {
            let matrices: Vec<Mat4> = skin_nodes
                .iter()
                .enumerate()
                .map(|(k, &n)| world[n] * Mat4::from_cols_slice(&binds[16 * k..16 * k + 16]))
                .collect();
            positions
                .chunks_exact(3)
                .enumerate()
                .map(|(v, p)| {
                    let p = Vec3::from_slice(p);
                    (0..4).fold(Vec3::ZERO, |sum, k| {
                        let w = weights[4 * v + k];
                        sum + w * matrices[joints[4 * v + k] as usize].transform_point3(p)
                    })
                })
                .collect()
        })
        .collect()
}
