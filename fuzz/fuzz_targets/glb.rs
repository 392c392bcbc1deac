//! Binary glTF scenes: parsing, sampling every keyframe, reading every mesh.
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
        }
    }
});
