//! Triangle meshes: OBJ (triangles, quads and larger polygons, fan-triangulated) and PLY (ASCII
//! and binary) loading, validation, re-centring on the bounding-box centre, and seeded,
//! area-weighted surface sampling with normals.

use std::io::BufReader;
use std::path::Path;

use glam::{Mat3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::{ReprError, Result};

/// An indexed triangle mesh, in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<Vec3>,
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
}

/// Points on a surface with the outward normals of the faces they lie on.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceSamples {
    /// Sample positions.
    pub points: Vec<Vec3>,
    /// Unit outward normals, one per point.
    pub normals: Vec<Vec3>,
}

impl Mesh {
    /// Builds a mesh and validates it: at least one face, finite vertices, indices in range.
    /// `source_name` (a path or a description) goes into the error messages.
    pub fn new(vertices: Vec<Vec3>, faces: Vec<[u32; 3]>, source_name: &str) -> Result<Self> {
        if faces.is_empty() {
            return Err(ReprError::EmptyMesh { source_name: source_name.into() });
        }
        if let Some(index) = vertices.iter().position(|v| !v.is_finite()) {
            return Err(ReprError::NonFinite {
                source_name: source_name.into(),
                what: "vertex".into(),
                index,
            });
        }
        let count = vertices.len();
        if let Some((face, bad)) = faces
            .iter()
            .enumerate()
            .find_map(|(f, tri)| tri.iter().find(|&&i| i as usize >= count).map(|&i| (f, i)))
        {
            return Err(ReprError::format(
                source_name,
                format!("face {face}"),
                format!("vertex indices below {count}"),
                bad,
            ));
        }
        Ok(Self { vertices, faces })
    }

    /// Loads an `.obj` or `.ply` file by its extension.
    pub fn load(path: &Path) -> Result<Self> {
        match MeshFormat::of(path) {
            Some(MeshFormat::Obj) => Self::load_obj(path),
            Some(MeshFormat::Ply) => Self::load_ply(path),
            None => Err(MeshFormat::refusal(path)),
        }
    }

    /// An `.obj` or `.ply` file's bytes, read by the extension of `file_name` (which names
    /// the source in errors): a mesh that comes from somewhere other than the file system.
    pub fn parse(bytes: &[u8], file_name: &str) -> Result<Self> {
        let name = Path::new(file_name);
        match MeshFormat::of(name) {
            Some(MeshFormat::Obj) => Self::parse_obj(bytes, file_name),
            Some(MeshFormat::Ply) => Self::parse_ply(bytes, file_name),
            None => Err(MeshFormat::refusal(name)),
        }
    }

    /// Loads a Wavefront OBJ file; every object and group goes into one mesh, polygons are
    /// fan-triangulated, materials, normals and texture coordinates are ignored.
    pub fn load_obj(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).map_err(|source| ReprError::Io { path: path.into(), source })?;
        Self::parse_obj(&bytes, &path.display().to_string())
    }

    /// [`Mesh::load_obj`] from memory; `name` names the source in errors.
    pub fn parse_obj(bytes: &[u8], name: &str) -> Result<Self> {
        check_obj_indices(bytes).map_err(|(line, what)| {
            ReprError::format(
                name,
                format!("OBJ line {line}"),
                "face indices of existing vertices",
                what,
            )
        })?;
        let options = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ignore_points: true,
            ignore_lines: true,
        };
        let (models, _materials) = tobj::load_obj_buf(&mut BufReader::new(bytes), &options, |_| {
            // Materials are not used; a missing .mtl file must not fail the load.
            Ok((Vec::new(), Default::default()))
        })
        .map_err(|error| ReprError::format(name, "OBJ content", "a valid OBJ file", error))?;
        let mut vertices = Vec::new();
        let mut faces = Vec::new();
        for model in &models {
            let base = u32::try_from(vertices.len()).map_err(|_| {
                ReprError::format(name, "vertex count", "fewer than 2^32", vertices.len())
            })?;
            let mesh = &model.mesh;
            vertices.extend(mesh.positions.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])));
            faces.extend(
                mesh.indices.chunks_exact(3).map(|t| [t[0] + base, t[1] + base, t[2] + base]),
            );
        }
        Self::new(vertices, faces, name)
    }

    /// Loads a PLY file (ASCII, binary little- or big-endian): `x, y, z` of the `vertex`
    /// element and the `vertex_indices` (or `vertex_index`) lists of the `face` element;
    /// polygons are fan-triangulated. Header lines that start with no PLY keyword (some
    /// exporters write free text there, as Blender 2.47 did) are read as comments, as assimp
    /// reads them.
    pub fn load_ply(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).map_err(|source| ReprError::Io { path: path.into(), source })?;
        Self::parse_ply(&bytes, &path.display().to_string())
    }

    /// [`Mesh::load_ply`] from memory; `name` names the source in errors.
    pub fn parse_ply(bytes: &[u8], name: &str) -> Result<Self> {
        use ply_rs_bw::parser::Parser;
        use ply_rs_bw::ply::{DefaultElement, Property};
        let bytes = tolerant_ply_header(bytes).ok_or_else(|| {
            ReprError::format(name, "PLY header", "a header ending in `end_header`", "none")
        })?;
        check_ply_counts(&bytes).map_err(|what| {
            ReprError::format(name, "PLY header", "element counts the data can hold", what)
        })?;
        let ply = Parser::<DefaultElement>::new()
            .read_ply(&mut bytes.as_slice())
            .map_err(|error| ReprError::format(name, "PLY content", "a valid PLY file", error))?;
        let vertex_elements = ply
            .payload
            .get("vertex")
            .ok_or_else(|| ReprError::format(name, "elements", "a `vertex` element", "none"))?;
        let mut vertices = Vec::with_capacity(vertex_elements.len());
        for (index, element) in vertex_elements.iter().enumerate() {
            let coordinate = |key: &str| -> Result<f32> {
                element.get(key).and_then(Property::to_f32_lossy).ok_or_else(|| {
                    ReprError::format(
                        name,
                        format!("vertex {index}"),
                        format!("a numeric `{key}`"),
                        "none",
                    )
                })
            };
            vertices.push(Vec3::new(coordinate("x")?, coordinate("y")?, coordinate("z")?));
        }
        let face_elements = ply.payload.get("face").map(Vec::as_slice).unwrap_or_default();
        let mut faces = Vec::with_capacity(face_elements.len());
        for (index, element) in face_elements.iter().enumerate() {
            let polygon = ["vertex_indices", "vertex_index"]
                .iter()
                .find_map(|key| element.get(*key))
                .and_then(Property::to_u32_list)
                .ok_or_else(|| {
                    ReprError::format(
                        name,
                        format!("face {index}"),
                        "a `vertex_indices` list",
                        "none",
                    )
                })?;
            fan_triangulate(&polygon, &mut faces);
        }
        Self::new(vertices, faces, name)
    }

    /// The axis-aligned bounding box `(min, max)`.
    pub fn bounding_box(&self) -> (Vec3, Vec3) {
        self.vertices
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| (lo.min(*v), hi.max(*v)))
    }

    /// The lowest and highest height (Y) of the vertices turned by `rotation`: how the mesh
    /// stands on a support in that orientation.
    pub fn height_range(&self, rotation: Mat3) -> (f32, f32) {
        self.vertices
            .iter()
            .map(|v| (rotation * *v).y)
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(low, high), y| (low.min(y), high.max(y)))
    }

    /// Moves the mesh so that its bounding-box centre is the origin (the object frame of
    /// docs/CONVENTIONS.md, "Object frame") and returns the old centre, so that a pose given for
    /// the original frame can be corrected: `p_centred = p_original + R c`.
    pub fn recenter(&mut self) -> Vec3 {
        let (lo, hi) = self.bounding_box();
        let centre = (lo + hi) * 0.5;
        for v in &mut self.vertices {
            *v -= centre;
        }
        centre
    }

    /// The (unnormalised) normal of a face: the cross product of two edges, length twice the
    /// area.
    pub fn face_area_normal(&self, face: usize) -> Vec3 {
        let [a, b, c] = self.faces[face].map(|i| self.vertices[i as usize]);
        (b - a).cross(c - a)
    }

    /// Total surface area.
    pub fn surface_area(&self) -> f32 {
        (0..self.faces.len()).map(|f| self.face_area_normal(f).length() * 0.5).sum()
    }

    /// `count` points sampled uniformly over the surface (faces chosen with probability
    /// proportional to their area, points uniform inside the triangle), with their faces'
    /// normals. The same seed gives the same samples.
    pub fn sample_surface(&self, count: usize, seed: u64) -> Result<SurfaceSamples> {
        let mut cumulative = Vec::with_capacity(self.faces.len());
        let mut total = 0.0f64;
        for f in 0..self.faces.len() {
            total += f64::from(self.face_area_normal(f).length());
            cumulative.push(total);
        }
        if total <= 0.0 {
            return Err(ReprError::EmptyMesh { source_name: "surface sampling".into() });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut points = Vec::with_capacity(count);
        let mut normals = Vec::with_capacity(count);
        for _ in 0..count {
            let target = rng.random::<f64>() * total;
            let face = cumulative.partition_point(|&c| c <= target).min(self.faces.len() - 1);
            let [a, b, c] = self.faces[face].map(|i| self.vertices[i as usize]);
            // Uniform in the triangle: reflect the unit square's upper half.
            let (mut u, mut v): (f32, f32) = (rng.random(), rng.random());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            points.push(a + (b - a) * u + (c - a) * v);
            normals.push(self.face_area_normal(face).normalize_or_zero());
        }
        Ok(SurfaceSamples { points, normals })
    }
}

/// Checks every face's vertex, texture and normal indices (1-based, or negative: relative to
/// the elements read so far) against the elements defined before it, as OBJ requires. `tobj`
/// 4.0 resolves them unchecked: a relative index before the start wraps around and overflows
/// (found by the `mesh` fuzz target). Lines are checked as `tobj` reads them, one by one: it
/// knows no continuation lines, so a face behind a trailing backslash is a face of its own.
/// `Err((line, what))` for the first bad one.
fn check_obj_indices(bytes: &[u8]) -> std::result::Result<(), (usize, String)> {
    let text = String::from_utf8_lossy(bytes);
    // [v, vt, vn] defined so far.
    let mut counts = [0i64; 3];
    for (number, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => counts[0] += 1,
            Some("vt") => counts[1] += 1,
            Some("vn") => counts[2] += 1,
            Some("f") => {
                for vertex in words {
                    for (kind, index) in vertex.split('/').enumerate().take(3) {
                        if index.is_empty() {
                            continue;
                        }
                        let Ok(index) = index.parse::<i64>() else { continue };
                        let resolved = if index < 0 { counts[kind] + index } else { index - 1 };
                        if index == 0 || !(0..counts[kind]).contains(&resolved) {
                            let kinds = ["vertex", "texture coordinate", "normal"];
                            return Err((
                                number + 1,
                                format!(
                                    "{} index {index} with {} defined before it",
                                    kinds[kind], counts[kind]
                                ),
                            ));
                        }
                    }
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// The PLY file with every header line that starts with no PLY keyword turned into a comment;
/// `None` when there is no `end_header` line.
fn tolerant_ply_header(bytes: &[u8]) -> Option<Vec<u8>> {
    const KEYWORDS: [&str; 7] =
        ["ply", "format", "comment", "element", "property", "obj_info", "end_header"];
    let mut out = Vec::with_capacity(bytes.len() + 64);
    let mut rest = bytes;
    loop {
        let end = rest.iter().position(|&b| b == b'\n')?;
        let line = &rest[..=end];
        rest = &rest[end + 1..];
        let text = String::from_utf8_lossy(line);
        let first = text.split_whitespace().next().unwrap_or("");
        if !first.is_empty() && !KEYWORDS.contains(&first) {
            out.extend_from_slice(b"comment ");
        }
        out.extend_from_slice(line);
        if first == "end_header" {
            out.extend_from_slice(rest);
            return Some(out);
        }
    }
}

/// Checks the element counts of a PLY header against its payload before `ply-rs-bw` 4.0 reads
/// it: the parser reserves an entry per declared element whatever the data hold, so a header
/// declaring billions of entries (of an element without properties, which reads no bytes)
/// exhausts memory (found by the `mesh` fuzz target). Every entry takes at least one byte of
/// payload, binary or ASCII, and an element with entries must have properties.
fn check_ply_counts(bytes: &[u8]) -> std::result::Result<(), String> {
    let mut elements: Vec<(String, u64, usize)> = Vec::new();
    let mut rest = bytes;
    loop {
        let Some(end) = rest.iter().position(|&b| b == b'\n') else { return Ok(()) };
        let text = String::from_utf8_lossy(&rest[..end]).into_owned();
        rest = &rest[end + 1..];
        let mut words = text.split_whitespace();
        match words.next() {
            Some("element") => {
                let name = words.next().unwrap_or_default().to_string();
                // An unreadable count is left to the parser's own error.
                let count = words.next().and_then(|c| c.parse().ok()).unwrap_or(0);
                elements.push((name, count, 0));
            }
            Some("property") => {
                if let Some(element) = elements.last_mut() {
                    element.2 += 1;
                }
            }
            Some("end_header") => break,
            _ => {}
        }
    }
    let payload = rest.len() as u64;
    let mut total = 0u64;
    for (name, count, properties) in &elements {
        if *count > 0 && *properties == 0 {
            return Err(format!("element `{name}` with {count} entries and no properties"));
        }
        total = total.saturating_add(*count);
    }
    if total > payload {
        return Err(format!("{total} entries declared for a payload of {payload} bytes"));
    }
    Ok(())
}

/// Splits a polygon into a fan of triangles around its first vertex.
fn fan_triangulate(polygon: &[u32], faces: &mut Vec<[u32; 3]>) {
    for k in 1..polygon.len().saturating_sub(1) {
        faces.push([polygon[0], polygon[k], polygon[k + 1]]);
    }
}

/// A unit cube `[-h, h]^3` with outward-facing triangles (tests, examples and the catalogue).
pub fn box_mesh(half_extents: Vec3) -> Mesh {
    let h = half_extents;
    let vertices = (0..8)
        .map(|i| {
            Vec3::new(
                if i & 1 == 0 { -h.x } else { h.x },
                if i & 2 == 0 { -h.y } else { h.y },
                if i & 4 == 0 { -h.z } else { h.z },
            )
        })
        .collect();
    // Quads counter-clockwise seen from outside.
    let quads =
        [[0, 4, 6, 2], [1, 3, 7, 5], [0, 1, 5, 4], [2, 6, 7, 3], [0, 2, 3, 1], [4, 5, 7, 6]];
    let mut faces = Vec::new();
    for quad in quads {
        fan_triangulate(&quad, &mut faces);
    }
    Mesh { vertices, faces }
}

/// A UV sphere with `rings` latitude bands and `segments` longitude bands, outward triangles.
pub fn uv_sphere(radius: f32, rings: u32, segments: u32) -> Mesh {
    let rings = rings.max(2);
    let segments = segments.max(3);
    let mut vertices = vec![Vec3::new(0.0, radius, 0.0)];
    for r in 1..rings {
        let polar = std::f32::consts::PI * r as f32 / rings as f32;
        for s in 0..segments {
            let azimuth = std::f32::consts::TAU * s as f32 / segments as f32;
            vertices.push(
                Vec3::new(polar.sin() * azimuth.cos(), polar.cos(), polar.sin() * azimuth.sin())
                    * radius,
            );
        }
    }
    vertices.push(Vec3::new(0.0, -radius, 0.0));
    let bottom = vertices.len() as u32 - 1;
    let ring_start = |r: u32| 1 + (r - 1) * segments;
    let mut faces = Vec::new();
    for s in 0..segments {
        let next = (s + 1) % segments;
        faces.push([0, ring_start(1) + next, ring_start(1) + s]);
        let last = ring_start(rings - 1);
        faces.push([bottom, last + s, last + next]);
    }
    for r in 1..rings - 1 {
        for s in 0..segments {
            let next = (s + 1) % segments;
            let (a, b) = (ring_start(r) + s, ring_start(r) + next);
            let (c, d) = (ring_start(r + 1) + s, ring_start(r + 1) + next);
            faces.push([a, b, d]);
            faces.push([a, d, c]);
        }
    }
    Mesh { vertices, faces }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_element_counts_are_checked_before_the_parser() {
        let header = |element: &str| {
            format!(
                "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n\
                 property float y\nproperty float z\n{element}end_header\n"
            )
            .into_bytes()
        };
        // One vertex and no face passes the count check (and fails later, as an empty mesh).
        let mut payload = header("");
        payload.extend(std::iter::repeat_n(0u8, 12));
        if let Err(error) = Mesh::parse_ply(&payload, "one.ply") {
            assert!(!error.to_string().contains("entries"), "{error}");
        }
        // Found by the mesh fuzz target: billions of entries of an element with no properties.
        let mut empty = header("element face 11111122222\n");
        empty.extend(std::iter::repeat_n(0u8, 12));
        let mut many = header("");
        many = String::from_utf8(many).unwrap().replace("vertex 1", "vertex 99999").into_bytes();
        many.extend(std::iter::repeat_n(0u8, 12));
        for (bytes, needle) in [(empty, "no properties"), (many, "99999 entries declared")] {
            let error = Mesh::parse_ply(&bytes, "bad.ply").unwrap_err().to_string();
            assert!(error.contains("bad.ply") && error.contains(needle), "{error}");
        }
    }

    #[test]
    fn obj_face_indices_are_checked_before_tobj() {
        // Relative (negative) indices, texture and normal indices that exist: read.
        let good = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf -3/1/1 -2/-1/1 -1//-1\n";
        let mesh = Mesh::parse_obj(good, "good.obj").unwrap();
        assert_eq!(mesh.faces, [[0, 1, 2]]);
        // Indices before the start or past the end, found by the mesh fuzz target in `tobj`
        // (a relative texture index wrapped around and overflowed): clear errors.
        for (text, needle) in [
            (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nf 1//1 2/-5 3//1\n".as_slice(), "line 5"),
            (b"v 0 0 0\nv 1 0 0\nf 1 2 3\n".as_slice(), "vertex index 3 with 2 defined"),
            (b"v 0 0 0\nf -4 1 1\n".as_slice(), "vertex index -4"),
            (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 0 1 2\n".as_slice(), "vertex index 0"),
            // tobj reads no continuation lines: a face after a comment ending in a backslash
            // is checked as the face it reads.
            (
                b"v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\n# x \\\nf 1/-9223372036854775807 2 3\n"
                    .as_slice(),
                "texture coordinate index -9223372036854775807",
            ),
        ] {
            let error = Mesh::parse_obj(text, "bad.obj").unwrap_err().to_string();
            assert!(error.contains("bad.obj") && error.contains(needle), "{error}");
        }
    }

    #[test]
    fn bad_meshes_are_refused() {
        let v = vec![Vec3::ZERO, Vec3::X, Vec3::Y];
        assert!(matches!(Mesh::new(v.clone(), vec![], "m"), Err(ReprError::EmptyMesh { .. })));
        assert!(Mesh::new(v.clone(), vec![[0, 1, 3]], "m").is_err());
        let mut nan = v;
        nan[1].y = f32::NAN;
        let error = Mesh::new(nan, vec![[0, 1, 2]], "cup.obj").unwrap_err();
        assert!(error.to_string().contains("cup.obj"), "{error}");
    }

    #[test]
    fn primitives_are_closed_and_outward() {
        for mesh in [box_mesh(Vec3::new(0.1, 0.2, 0.3)), uv_sphere(0.5, 16, 24)] {
            // Signed volume by the divergence theorem is positive for outward faces.
            let volume: f32 = mesh
                .faces
                .iter()
                .map(|f| {
                    let [a, b, c] = f.map(|i| mesh.vertices[i as usize]);
                    a.dot(b.cross(c)) / 6.0
                })
                .sum();
            assert!(volume > 0.0);
        }
        let cube = box_mesh(Vec3::splat(0.5));
        assert!((cube.surface_area() - 6.0).abs() < 1e-5);
    }

    #[test]
    fn sampling_is_seeded_and_on_the_surface() {
        let cube = box_mesh(Vec3::splat(0.5));
        let a = cube.sample_surface(500, 7).unwrap();
        assert_eq!(a, cube.sample_surface(500, 7).unwrap());
        assert_ne!(a, cube.sample_surface(500, 8).unwrap());
        for (p, n) in a.points.iter().zip(&a.normals) {
            // On the face whose normal it carries.
            assert!((p.dot(*n) - 0.5).abs() < 1e-5, "{p:?} {n:?}");
        }
        // Area weighting: a flat box gets most samples on its large faces.
        let flat = box_mesh(Vec3::new(0.5, 0.01, 0.5));
        let samples = flat.sample_surface(2000, 1).unwrap();
        let top_bottom = samples.normals.iter().filter(|n| n.y.abs() > 0.5).count();
        assert!(top_bottom > 1800, "{top_bottom}");
    }

    #[test]
    fn recenter_moves_the_box_centre_to_the_origin() {
        let mut mesh = box_mesh(Vec3::splat(0.1));
        for v in &mut mesh.vertices {
            *v += Vec3::new(1.0, 2.0, 3.0);
        }
        let centre = mesh.recenter();
        assert!(centre.abs_diff_eq(Vec3::new(1.0, 2.0, 3.0), 1e-6));
        let (lo, hi) = mesh.bounding_box();
        assert!((lo + hi).abs_diff_eq(Vec3::ZERO, 1e-6));
    }
}

/// The mesh file formats read, by file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MeshFormat {
    Obj,
    Ply,
}

impl MeshFormat {
    /// The format of a file by its extension (any case).
    fn of(path: &Path) -> Option<Self> {
        let extension = path.extension()?.to_str()?.to_ascii_lowercase();
        match extension.as_str() {
            "obj" => Some(Self::Obj),
            "ply" => Some(Self::Ply),
            _ => None,
        }
    }

    /// The error for a file of neither format.
    fn refusal(path: &Path) -> ReprError {
        ReprError::format(
            path.display(),
            "file extension",
            "`.obj` or `.ply`",
            format!("{:?}", path.extension().unwrap_or_default()),
        )
    }
}
