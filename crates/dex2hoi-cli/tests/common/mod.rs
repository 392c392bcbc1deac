//! What every end-to-end test of the `dex2hoi` binary uses.

use std::process::{Command, Output};

/// Runs the binary built for these tests with arguments (no backtraces in its errors).
pub fn dex2hoi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dex2hoi"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("the binary runs")
}

/// An empty scratch directory path for one test, `dex2hoi-cli-{file}-{name}-{pid}` under the
/// system's temporary folder (removed if an earlier run left it; not created).
#[allow(dead_code)] // not every test binary needs scratch space
pub fn temp_dir(file: &str, name: &str) -> std::path::PathBuf {
    let dir =
        std::env::temp_dir().join(format!("dex2hoi-cli-{file}-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

/// Writes the fixture SMPL-X model (`dex2hoi_testkit::smplx_fixture`) on the built-in skeleton
/// and its capsule body.
#[allow(dead_code)] // only the tests that dress the body with a model use it
pub fn write_smplx_model(path: &std::path::Path) {
    use dex2hoi_testkit::smplx_fixture::{BoundMesh, Spoil, write_smplx_model};
    let poser = dex2hoi_data::character::Poser::new(glam::Vec3::ZERO);
    let skeleton = poser.skeleton();
    let mesh = dex2hoi_export::body_mesh(skeleton);
    let bound = BoundMesh {
        vertices: &mesh.vertices,
        joints: &mesh.joints,
        bone_ends: &mesh.bone_ends,
        faces: &mesh.faces,
    };
    write_smplx_model(path, &skeleton.rest_positions(), skeleton.parents(), bound, Spoil::None);
}
