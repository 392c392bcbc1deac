//! Binary glTF scenes: parsing, sampling every keyframe, reading every mesh and its skin
//! weights, and the character of a skinned scene (`--character`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(scene) = dex2hoi_import::glb::GlbScene::from_bytes(data, "fuzz.glb") else { return };
    for time in scene.keyframe_times().into_iter().take(64) {
        let _ = scene.world_matrices(time);
    }
    for node in &scene.nodes {
        if let Some(mesh) = node.mesh {
            let _ = scene.mesh(mesh);
            let _ = scene.skinning(mesh);
        }
    }
    let _ = dex2hoi_import::character::Character::from_scene(&scene);
});
