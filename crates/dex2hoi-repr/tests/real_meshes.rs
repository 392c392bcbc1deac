//! Real meshes that nobody here wrote (docs/CONVENTIONS.md, "Test assets"), installed by
//! `scripts/setup.sh`: pybullet's OBJ files (PyPI `pybullet`) and assimp's PLY files (Debian
//! `assimp-testmodels`). They load, their counts match the files, and their bounding boxes and
//! signed distances are sane.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::*;
use glam::Vec3;

use dex2hoi_repr::sdf::brute_force_distance;
use dex2hoi_repr::{Mesh, MeshQuery};

const SETUP_HINT: &str = "install the test assets with `bash scripts/setup.sh`";

fn pybullet_data() -> PathBuf {
    if let Some(dir) = std::env::var_os("DEX2HOI_PYBULLET_DATA") {
        return PathBuf::from(dir);
    }
    let output = Command::new("python3")
        .args(["-c", "import pybullet_data, sys; sys.stdout.write(pybullet_data.getDataPath())"])
        .output()
        .unwrap_or_else(|e| panic!("cannot run python3 to find pybullet_data ({e}); {SETUP_HINT}"));
    assert!(output.status.success(), "pybullet_data is not installed; {SETUP_HINT}");
    PathBuf::from(String::from_utf8(output.stdout).expect("a UTF-8 path"))
}

fn assimp_models() -> PathBuf {
    std::env::var_os("DEX2HOI_ASSIMP_MODELS")
        .map_or_else(|| PathBuf::from("/usr/share/assimp/models"), PathBuf::from)
}

fn asset(path: PathBuf) -> PathBuf {
    assert!(path.is_file(), "{} is missing; {SETUP_HINT}", path.display());
    path
}

/// Vertex and triangle counts read straight from an OBJ file's `v` and `f` lines.
fn obj_counts(path: &Path) -> (usize, usize) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut vertices = 0;
    let mut triangles = 0;
    for line in text.lines() {
        let mut tokens = line.split_whitespace();
        match tokens.next() {
            Some("v") => vertices += 1,
            Some("f") => triangles += tokens.count().saturating_sub(2),
            _ => {}
        }
    }
    (vertices, triangles)
}

/// `element` counts from a PLY header.
fn ply_header_count(path: &Path, element: &str) -> usize {
    let bytes = std::fs::read(path).unwrap();
    let header = String::from_utf8_lossy(&bytes[..bytes.len().min(4096)]).into_owned();
    header
        .lines()
        .find_map(|l| l.strip_prefix(&format!("element {element} ")))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("{}: no element {element}", path.display()))
}

/// Checks that apply to any real mesh: finite box, the unsigned distance equals a brute-force
/// scan, points well outside the box are outside, and surface points pushed along their normal
/// change sign (allowing for thin parts and imperfect files).
fn check_sane(mesh: &Mesh, name: &str, min_sign_agreement: f32) {
    let (lo, hi) = mesh.bounding_box();
    assert!(
        lo.is_finite() && hi.is_finite() && (hi - lo).min_element() > 0.0,
        "{name}: {lo:?} {hi:?}"
    );
    let query = MeshQuery::new(mesh).unwrap();
    let diagonal = (hi - lo).length();
    let centre = (lo + hi) * 0.5;
    let mut rng = rng(21);
    for _ in 0..200 {
        let p = centre + random_vec3(&mut rng, 1.0) * (hi - lo);
        let d = query.signed_distance(p);
        let reference = brute_force_distance(mesh, p);
        assert!(
            (d.abs() - reference).abs() <= 1e-5 * diagonal.max(1.0),
            "{name}: {p:?} {d} vs {reference}"
        );
    }
    for direction in [Vec3::X, -Vec3::Y, Vec3::Z] {
        let p = centre + direction * diagonal;
        assert!(
            query.signed_distance(p) >= diagonal * 0.5 - 1e-5,
            "{name}: {p:?} should be outside"
        );
    }
    let samples = mesh.sample_surface(2000, 5).unwrap();
    let eps = 1e-3 * diagonal;
    let agreeing = samples
        .points
        .iter()
        .zip(&samples.normals)
        .filter(|(p, n)| {
            let outside = query.signed_distance(**p + **n * eps);
            let inside = query.signed_distance(**p - **n * eps);
            outside > 0.0
                && inside < 0.0
                && (outside - eps).abs() < eps
                && (inside + eps).abs() < eps
        })
        .count() as f32
        / 2000.0;
    assert!(
        agreeing >= min_sign_agreement,
        "{name}: only {agreeing} of surface samples signed right"
    );
}

#[test]
fn pybullet_obj_meshes() {
    let data = pybullet_data();
    for (file, min_sign_agreement) in
        [("objects/mug.obj", 0.98), ("duck.obj", 0.98), ("bunny.obj", 0.98)]
    {
        let path = asset(data.join(file));
        let mesh = Mesh::load(&path).unwrap();
        let (vertices, triangles) = obj_counts(&path);
        assert_eq!(mesh.vertices.len(), vertices, "{file}");
        assert_eq!(mesh.faces.len(), triangles, "{file}");
        check_sane(&mesh, file, min_sign_agreement);
    }
    // The mug is 8 x 12 x 10 cm and mostly quads (456 faces, 408 of them quads).
    let mut mug = Mesh::load(&data.join("objects/mug.obj")).unwrap();
    assert_eq!((mug.vertices.len(), mug.faces.len()), (446, 864));
    let (lo, hi) = mug.bounding_box();
    assert!((hi - lo).abs_diff_eq(Vec3::new(0.082, 0.1206, 0.1), 2e-3), "{:?}", hi - lo);
    // Re-centred on its box, its cavity's axis passes through the origin: the centre of the box
    // lies in the open cup, outside the mesh, within a few centimetres of the wall.
    mug.recenter();
    let (lo, hi) = mug.bounding_box();
    assert!((lo + hi).abs_diff_eq(Vec3::ZERO, 1e-6));
    let d = MeshQuery::new(&mug).unwrap().signed_distance(Vec3::ZERO);
    assert!(d > 0.0 && d < 0.05, "{d}");
}

#[test]
fn assimp_ply_meshes() {
    let models = assimp_models();
    let ascii_path = asset(models.join("PLY/cube.ply"));
    let binary_path = asset(models.join("PLY/cube_binary.ply"));
    let ascii = Mesh::load(&ascii_path).unwrap();
    let binary = Mesh::load(&binary_path).unwrap();
    assert_eq!(ascii.vertices.len(), ply_header_count(&ascii_path, "vertex"));
    assert_eq!(binary.vertices.len(), ply_header_count(&binary_path, "vertex"));
    // The ASCII cube stores 6 quads, the binary one 12 triangles: both are 12 triangles here.
    assert_eq!(ply_header_count(&ascii_path, "face"), 6);
    assert_eq!(ply_header_count(&binary_path, "face"), 12);
    assert_eq!((ascii.faces.len(), binary.faces.len()), (12, 12));
    for cube in [&ascii, &binary] {
        assert_eq!(cube.bounding_box(), (Vec3::ZERO, Vec3::ONE));
        let query = MeshQuery::new(cube).unwrap();
        assert!((query.signed_distance(Vec3::splat(0.5)) + 0.5).abs() < 1e-6);
        assert!((query.signed_distance(Vec3::new(0.5, 0.5, 2.0)) - 1.0).abs() < 1e-6);
        check_sane(cube, "cube", 1.0);
    }
    let wuson_path = asset(models.join("PLY/Wuson.ply"));
    let wuson = Mesh::load(&wuson_path).unwrap();
    assert_eq!(wuson.vertices.len(), 11184);
    assert_eq!(wuson.vertices.len(), ply_header_count(&wuson_path, "vertex"));
    assert_eq!(wuson.faces.len(), ply_header_count(&wuson_path, "face"));
    // The file's vertices are unwelded (three per triangle); the query welds them.
    check_sane(&wuson, "Wuson", 0.9);
}

#[test]
fn broken_files_give_errors_that_name_them() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-broken-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cases: [(&str, &[u8]); 5] = [
        ("empty.obj", b"# nothing here\n"),
        ("nan.obj", b"v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n"),
        ("index.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n"),
        ("truncated.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0\n"),
        ("noheader.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"),
    ];
    for (name, content) in cases {
        let path = dir.join(name);
        std::fs::write(&path, content).unwrap();
        let error = Mesh::load(&path).expect_err(name);
        assert!(error.to_string().contains(name), "{name}: {error}");
    }
    let error = Mesh::load(&dir.join("absent.ply")).unwrap_err();
    assert!(error.to_string().contains("absent.ply"), "{error}");
    let error = Mesh::load(&dir.join("mesh.stl")).unwrap_err();
    assert!(error.to_string().contains("mesh.stl"), "{error}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn meshes_read_from_memory_equal_the_files_and_name_them() {
    let mug = asset(pybullet_data().join("objects/mug.obj"));
    let cube = asset(assimp_models().join("PLY/cube_binary.ply"));
    for (path, file_name) in [(&mug, "Mug.OBJ"), (&cube, "cube.ply")] {
        let from_file = Mesh::load(path).unwrap();
        let from_bytes = Mesh::parse(&std::fs::read(path).unwrap(), file_name).unwrap();
        assert_eq!(from_bytes.vertices, from_file.vertices, "{file_name}");
        assert_eq!(from_bytes.faces, from_file.faces, "{file_name}");
    }
    let refused = Mesh::parse(b"v 0 0 0\n", "mesh.stl").unwrap_err().to_string();
    assert!(refused.contains("mesh.stl") && refused.contains("`.obj` or `.ply`"), "{refused}");
    let broken = Mesh::parse(b"v 0 0 0\nf 1 2 3\n", "broken.obj").unwrap_err().to_string();
    assert!(broken.contains("broken.obj") && broken.contains("line 2"), "{broken}");
}
