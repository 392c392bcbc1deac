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

/// Runs the binary, asserts that it succeeds and returns its standard output.
#[allow(dead_code)] // not every test binary runs commands this way
pub fn succeed(args: &[&str]) -> String {
    let run = dex2hoi(args);
    assert!(run.status.success(), "{args:?}:\n{}", String::from_utf8_lossy(&run.stderr));
    String::from_utf8_lossy(&run.stdout).into_owned()
}

/// Runs the binary, asserts that it fails and returns its standard error.
#[allow(dead_code)] // not every test binary runs commands this way
pub fn fail(args: &[&str]) -> String {
    let run = dex2hoi(args);
    assert!(!run.status.success(), "{args:?} should fail");
    String::from_utf8_lossy(&run.stderr).into_owned()
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

/// The largest angle (radians) between the two files' parent-relative rotations of the same
/// `mixamorig:` bone at time 0 (scale divided out; the root is left out, prepare turns it).
#[allow(dead_code)] // the tests that look at HUMOTO's GLBs use it
pub fn worst_bone_rotation_gap(published: &std::path::Path, ours: &std::path::Path) -> f32 {
    use dex2hoi_import::glb::GlbScene;
    let relative = |path: &std::path::Path| {
        let scene = GlbScene::read(path).unwrap();
        let world = scene.world_matrices(0.0);
        let rotation = |node: usize| {
            let m = glam::Mat3::from_mat4(world[node]);
            glam::Mat3::from_cols(m.x_axis.normalize(), m.y_axis.normalize(), m.z_axis.normalize())
        };
        let skin = &scene.skins[0];
        skin.joints
            .iter()
            .filter_map(|&node| {
                let parent = scene.nodes[node].parent.filter(|p| skin.joints.contains(p))?;
                let name = scene.nodes[node].name.clone();
                Some((name, rotation(parent).transpose() * rotation(node)))
            })
            .collect::<std::collections::HashMap<_, _>>()
    };
    let (published, ours) = (relative(published), relative(ours));
    assert_eq!(published.len(), 64, "every bone but the hips");
    published
        .iter()
        .map(|(name, rotation)| {
            let theirs = ours.get(name).unwrap_or_else(|| panic!("no bone {name} in ours"));
            let q = glam::Quat::from_mat3(&(rotation.transpose() * *theirs));
            // atan2 keeps small angles that acos(w) would round to zero in f32.
            2.0 * q.xyz().length().atan2(q.w.abs())
        })
        .fold(0.0, f32::max)
}

/// Whether the tests run under CI (`CI` set to anything but empty, `0` or `false`).
#[allow(dead_code)] // only the tests that need outside tools use it
pub fn in_ci() -> bool {
    std::env::var_os("CI").is_some_and(|v| !v.is_empty() && v != "0" && v != "false")
}

/// The Python with Blender's `bpy`: `DEX2HOI_BLENDER_PYTHON`, or the virtual environment of
/// `scripts/setup.sh`; `None` (skipped) without it, a failure under CI.
#[allow(dead_code)] // only the tests that import into Blender use it
pub fn blender_python() -> Option<std::path::PathBuf> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = std::env::var_os("DEX2HOI_BLENDER_PYTHON")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| root.join("target/blender-venv/bin/python"));
    if python.is_file() {
        return Some(python);
    }
    assert!(!in_ci(), "CI needs Blender's bpy at {} (scripts/setup.sh)", python.display());
    println!("skipped: no Blender (bpy) at {} (scripts/setup.sh installs it)", python.display());
    None
}

/// An array of a `motion.npz` as `f32` (C order), and its shape.
#[allow(dead_code)] // the tests that read motion.npz use it
pub fn npz_array(path: &std::path::Path, name: &str) -> (Vec<f32>, Vec<usize>) {
    let file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut npz = npyz::npz::NpzArchive::new(std::io::BufReader::new(file)).unwrap();
    let array =
        npz.by_name(name).unwrap().unwrap_or_else(|| panic!("no {name} in {}", path.display()));
    let shape = array.shape().iter().map(|&d| d as usize).collect();
    (array.into_vec::<f32>().unwrap(), shape)
}

/// The glTF JSON chunk of a GLB.
#[allow(dead_code)] // the tests that read motion.glb use it
pub fn glb_json(path: &std::path::Path) -> serde_json::Value {
    let bytes = std::fs::read(path).unwrap();
    let length = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    serde_json::from_slice(&bytes[20..20 + length]).unwrap()
}

/// The public HUMOTO sequences in `../shared/realdata` beside the checkout (their folder of
/// sequence folders); `None` (skipped) without them, a failure under CI.
#[allow(dead_code)] // only the tests on real HUMOTO files use it
pub fn humoto_glb() -> Option<std::path::PathBuf> {
    let glb = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/realdata/humoto/glb");
    if glb.is_dir() {
        return Some(glb);
    }
    assert!(!in_ci(), "CI needs {}", glb.display());
    eprintln!("skipped: no real HUMOTO samples at {}", glb.display());
    None
}

/// `dex2hoi data prepare --format humoto` of `glb` into `out`; its standard output.
#[allow(dead_code)] // only the tests on real HUMOTO files use it
pub fn prepare_humoto(glb: &std::path::Path, out: &str) -> String {
    succeed(&[
        "data",
        "prepare",
        "--format",
        "humoto",
        "--root",
        glb.to_str().unwrap(),
        "--out",
        out,
    ])
}
