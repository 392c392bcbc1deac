//! Signed distances and BPS against analytic values, and SMPL-X model files.

mod common;

use common::*;
use glam::Vec3;

use dex2hoi_repr::mesh::{Mesh, box_mesh, uv_sphere};
use dex2hoi_repr::sdf::{MeshQuery, brute_force_distance};
use dex2hoi_repr::{BpsBasis, ReprError, Skeleton};

/// The exact signed distance to an axis-aligned box centred on the origin.
fn box_sdf(p: Vec3, half: Vec3) -> f32 {
    let q = p.abs() - half;
    q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
}

#[test]
fn signed_distance_to_a_cube_is_exact() {
    let half = Vec3::new(0.1, 0.05, 0.2);
    let cube = box_mesh(half);
    let query = MeshQuery::new(&cube).unwrap();
    let mut rng = rng(11);
    let points: Vec<Vec3> = (0..4000).map(|_| random_vec3(&mut rng, 0.4)).collect();
    let distances = query.signed_distances(&points);
    let mut inside = 0;
    for (p, d) in points.iter().zip(&distances) {
        let expected = box_sdf(*p, half);
        assert!((d - expected).abs() < 1e-5, "{p:?}: {d} vs {expected}");
        inside += usize::from(expected < 0.0);
    }
    assert!(inside > 50, "the sample must cover the inside too ({inside})");
    // Points exactly above edges and corners take the edge and vertex pseudo-normals.
    for p in [Vec3::new(0.15, 0.1, 0.0), Vec3::new(0.2, 0.2, 0.3), Vec3::new(0.09, 0.0, 0.19)] {
        assert!((query.signed_distance(p) - box_sdf(p, half)).abs() < 1e-5, "{p:?}");
    }
}

#[test]
fn signed_distance_to_a_sphere_matches_the_analytic_value() {
    let radius = 0.3;
    let sphere = uv_sphere(radius, 64, 128);
    let query = MeshQuery::new(&sphere).unwrap();
    // The tessellation's chords lie at most r (1 - cos(pi/64)) inside the true sphere.
    let tolerance = radius * (1.0 - (std::f32::consts::PI / 64.0).cos()) * 2.0 + 1e-5;
    let mut rng = rng(12);
    for _ in 0..2000 {
        let p = random_vec3(&mut rng, 0.6);
        let d = query.signed_distance(p);
        assert!((d - (p.length() - radius)).abs() < tolerance, "{p:?}: {d}");
        // The unsigned distance equals a brute-force scan exactly.
        assert!((d.abs() - brute_force_distance(&sphere, p)).abs() < 1e-6);
    }
}

#[test]
fn open_meshes_are_signed_by_the_nearest_patch() {
    // A square in the XZ plane facing +Y: above is outside, below is "inside".
    let square = Mesh::new(
        vec![
            Vec3::new(-1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(-1.0, 0.0, 1.0),
        ],
        vec![[0, 2, 1], [0, 3, 2]],
        "square",
    )
    .unwrap();
    let query = MeshQuery::new(&square).unwrap();
    assert!((query.signed_distance(Vec3::new(0.2, 0.5, 0.1)) - 0.5).abs() < 1e-6);
    assert!((query.signed_distance(Vec3::new(0.2, -0.5, 0.1)) + 0.5).abs() < 1e-6);
    // Past the rim the distance is to the rim, signed by the rim's pseudo-normal.
    let d = query.signed_distance(Vec3::new(2.0, 1.0, 0.0));
    assert!((d - 2f32.sqrt()).abs() < 1e-5, "{d}");
}

#[test]
fn degenerate_meshes_are_refused() {
    let flat =
        Mesh::new(vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0], vec![[0, 1, 2]], "line").unwrap();
    assert!(matches!(MeshQuery::new(&flat), Err(ReprError::EmptyMesh { .. })));
}

#[test]
fn bps_of_a_sphere_points_to_the_surface() {
    let radius = 0.1;
    let sphere = uv_sphere(radius, 48, 96);
    let query = MeshQuery::new(&sphere).unwrap();
    let basis = BpsBasis::new(1024, 0.25, 3).unwrap();
    assert_eq!(basis, BpsBasis::new(1024, 0.25, 3).unwrap(), "seeded");
    assert_ne!(basis, BpsBasis::new(1024, 0.25, 4).unwrap());
    assert!(basis.points().iter().all(|p| p.length() <= 0.25));
    // Uniform in volume: about (1/2)^3 of the points lie within half the radius.
    let inner = basis.points().iter().filter(|p| p.length() < 0.125).count();
    assert!((90..170).contains(&inner), "{inner}");
    let features = basis.encode(&query);
    assert_eq!(features.len(), 1024);
    // Radially the facets sit within the chord error of the sphere; sideways the foot of the
    // perpendicular may land anywhere on a facet, up to about one facet width (r pi / 48) away.
    let radial_tolerance = radius * (1.0 - (std::f32::consts::PI / 48.0).cos()) * 2.0 + 1e-5;
    let tangential_tolerance = radius * std::f32::consts::PI / 48.0;
    for (b, offset) in basis.points().iter().zip(&features) {
        if b.length() < 1e-3 {
            continue; // the centre has no unique nearest point
        }
        let expected = b.normalize() * (radius - b.length());
        assert!(
            (offset.length() - expected.length()).abs() < radial_tolerance,
            "{b:?}: {offset:?}"
        );
        assert!(
            offset.abs_diff_eq(expected, tangential_tolerance),
            "{b:?}: {offset:?} vs {expected:?}"
        );
    }
    assert_eq!(basis.encode_flat(&query).len(), 3072);
    assert!(BpsBasis::new(0, 1.0, 0).is_err());
    assert!(BpsBasis::new(8, f32::NAN, 0).is_err());
}

/// Writes a small SMPL-X-like model: the real key names and layouts, few vertices, shapedirs in
/// Fortran order as some conversions store it, the root's parent as uint32 max.
fn write_fake_smplx(
    path: &std::path::Path,
    skip: Option<&str>,
    kintree_columns: usize,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    use npyz::WriterBuilder;
    let vertices = 40;
    let shapes = 4;
    let mut rng = rng(13);
    let v_template: Vec<f32> = (0..vertices * 3).map(|_| random_vec3(&mut rng, 1.0).x).collect();
    let shapedirs: Vec<f32> =
        (0..vertices * 3 * shapes).map(|_| random_vec3(&mut rng, 0.01).y).collect();
    let mut regressor = vec![0.0f32; 55 * vertices];
    for joint in 0..55 {
        for k in 0..3 {
            regressor[joint * vertices + (joint * 7 + k * 11) % vertices] = 1.0 / 3.0;
        }
    }
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    let mut put = |name: &str, shape: &[u64], values: &[f32], order: npyz::Order| {
        if Some(name) == skip {
            return;
        }
        let mut w = npz
            .array::<f32>(name, Default::default())
            .unwrap()
            .default_dtype()
            .shape(shape)
            .order(order)
            .begin_nd()
            .unwrap();
        w.extend(values.iter().copied()).unwrap();
        w.finish().unwrap();
    };
    put("v_template", &[vertices as u64, 3], &v_template, npyz::Order::C);
    // Fortran order: index (v, a, s) at v + V*a + 3V*s.
    let mut fortran = vec![0.0f32; shapedirs.len()];
    for v in 0..vertices {
        for a in 0..3 {
            for s in 0..shapes {
                fortran[v + vertices * a + 3 * vertices * s] = shapedirs[(v * 3 + a) * shapes + s];
            }
        }
    }
    put("shapedirs", &[vertices as u64, 3, shapes as u64], &fortran, npyz::Order::Fortran);
    put("J_regressor", &[55, vertices as u64], &regressor, npyz::Order::C);
    if skip != Some("kintree_table") {
        let mut kintree: Vec<u32> =
            dex2hoi_repr::skeleton::SMPLX55_PARENTS.iter().map(|&p| p as u32).collect();
        kintree.extend(0..55u32);
        kintree.truncate(kintree_columns * 2);
        let mut w = npz
            .array::<u32>("kintree_table", Default::default())
            .unwrap()
            .default_dtype()
            .shape(&[2, kintree_columns as u64])
            .begin_nd()
            .unwrap();
        w.extend(kintree).unwrap();
        w.finish().unwrap();
    }
    (v_template, shapedirs, regressor)
}

/// An `.npz` with one raw `v_template.npy` entry of the given bytes.
fn write_raw_entry(path: &std::path::Path, npy: &[u8]) {
    use std::io::Write;
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    npz.zip_writer().start_file("v_template.npy", Default::default()).unwrap();
    npz.zip_writer().write_all(npy).unwrap();
    npz.zip_writer().finish().unwrap();
}

#[test]
fn hostile_smplx_model_files_are_refused_before_allocating() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-smplx-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A version-2 header claiming 4 GiB in a file of a few hundred bytes: npyz allocated the
    // whole header before reading it.
    let mut npy = b"\x93NUMPY\x02\x00".to_vec();
    npy.extend(0xFFFF_FFF0u32.to_le_bytes());
    npy.extend(b"{'descr': '<f8'");
    let huge_header = dir.join("huge_header.npz");
    write_raw_entry(&huge_header, &npy);
    // Shapes whose size overflows, or exceeds the entry's bytes.
    let shaped = |shape: &str| {
        let header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}\n");
        let mut npy = b"\x93NUMPY\x01\x00".to_vec();
        npy.extend((header.len() as u16).to_le_bytes());
        npy.extend(header.as_bytes());
        npy.extend([0u8; 48]);
        npy
    };
    let overflow = dir.join("overflow.npz");
    write_raw_entry(&overflow, &shaped("(4294967296, 4294967296, 3)"));
    let too_big = dir.join("too_big.npz");
    write_raw_entry(&too_big, &shaped("(1000000000, 3)"));
    for (path, needle) in
        [(&huge_header, "header length"), (&overflow, "shape"), (&too_big, "bytes of data")]
    {
        let started = std::time::Instant::now();
        let error = Skeleton::from_smplx_model(path, &[]).unwrap_err().to_string();
        let name = path.file_name().unwrap().to_str().unwrap();
        assert!(error.contains(name) && error.contains(needle), "{error}");
        assert!(started.elapsed().as_secs_f32() < 1.0, "{error}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn rest_joints_from_an_smplx_model_file() {
    let dir = std::env::temp_dir().join(format!("dex2hoi-smplx-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("SMPLX_FAKE.npz");
    let (v_template, shapedirs, regressor) = write_fake_smplx(&path, None, 55);
    let betas = [0.5f32, -1.0, 2.0];
    let skeleton = Skeleton::from_smplx_model(&path, &betas).unwrap();
    assert_eq!(skeleton.joint_count(), 52);
    // Independent computation of J = R (T + S b), then 55 -> 52 and offsets.
    let vertices = 40;
    let shaped: Vec<f32> = (0..vertices * 3)
        .map(|i| v_template[i] + (0..3).map(|s| shapedirs[i * 4 + s] * betas[s]).sum::<f32>())
        .collect();
    let joint = |j: usize| -> Vec3 {
        let mut sum = Vec3::ZERO;
        for v in 0..vertices {
            sum += Vec3::from_slice(&shaped[v * 3..v * 3 + 3]) * regressor[j * vertices + v];
        }
        sum
    };
    let rest = skeleton.rest_positions();
    for j in 0..52 {
        let j55 = if j < 22 { j } else { j + 3 };
        assert!(rest[j].abs_diff_eq(joint(j55), 1e-5), "joint {j}");
    }
    // Errors name the file and what is wrong.
    let missing = dir.join("missing_key.npz");
    write_fake_smplx(&missing, Some("J_regressor"), 55);
    let error = Skeleton::from_smplx_model(&missing, &[]).unwrap_err();
    assert!(matches!(error, ReprError::MissingKey { .. }), "{error}");
    assert!(
        error.to_string().contains("missing_key.npz") && error.to_string().contains("J_regressor")
    );
    let bad_shape = dir.join("bad_shape.npz");
    write_fake_smplx(&bad_shape, None, 54);
    let error = Skeleton::from_smplx_model(&bad_shape, &[]).unwrap_err();
    assert!(matches!(error, ReprError::Shape { .. }), "{error}");
    assert!(Skeleton::from_smplx_model(&path, &[0.0; 5]).is_err(), "more betas than shapedirs");
    assert!(Skeleton::from_smplx_model(&dir.join("absent.npz"), &[]).is_err());
    std::fs::write(dir.join("corrupt.npz"), b"PK\x03\x04 not really a zip").unwrap();
    assert!(Skeleton::from_smplx_model(&dir.join("corrupt.npz"), &[]).is_err());
    std::fs::remove_dir_all(&dir).ok();
}
