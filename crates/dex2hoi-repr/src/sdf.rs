//! Signed nearest-surface distances from points to a triangle mesh (negative inside), for
//! `L_dist` (paper Eq. 11), contact labels, mixture targets and penetration metrics.
//!
//! The nearest point comes from parry3d's bounding-volume hierarchy over the triangles. The sign
//! comes from angle-weighted pseudo-normals (Baerentzen and Aanaes, 2005): the vector from the
//! nearest point to the query is compared with the pseudo-normal of the feature it lands on
//! (the face normal inside a face, the sum of the adjacent face normals on an edge, the
//! angle-weighted sum of the incident face normals at a vertex). On a closed, consistently
//! oriented mesh this gives the exact inside/outside answer.
//!
//! **Open meshes** (a cup without a bottom, a scan with holes): the distance is still exact; the
//! sign says on which side of the *nearest* surface patch the point lies, judged by that patch's
//! orientation. Points near a hole's rim are classed by the rim's pseudo-normal, so "inside"
//! means "behind the nearest surface", not "enclosed". Meshes with inconsistent face orientation
//! give inconsistent signs; vertices at identical positions are merged before the pseudo-normals
//! are built, so seams in the file do not matter.

use std::collections::HashMap;

use glam::{Mat3, Vec3};
use parry3d::query::PointQueryWithLocation;
use parry3d::shape::{TriMesh, TrianglePointLocation};
use rayon::prelude::*;

use crate::error::{ReprError, Result};
use crate::mesh::Mesh;

/// The nearest surface point to a query and the signed distance to it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    /// The nearest point on the surface.
    pub point: Vec3,
    /// `|query - point|`, negative when the query is inside.
    pub signed_distance: f32,
    /// The triangle the nearest point lies on (index into the query's triangles, which are the
    /// mesh's faces without degenerate ones).
    pub triangle: u32,
}

/// Distance to a surface under which a hand joint touches an object: 5 cm, as in CHOIS. The
/// one threshold of the contact targets, the contact metrics and the preview's contact colour.
pub const CONTACT_RADIUS_M: f32 = 0.05;

/// Depth inside an object beyond which a joint counts as penetrating it: 5 mm. The one
/// threshold of the penetration metric and the preview's penetration colour.
pub const PENETRATION_TOLERANCE_M: f32 = 0.005;

/// A mesh prepared for nearest-point and signed-distance queries.
pub struct MeshQuery {
    trimesh: TriMesh,
    face_normals: Vec<Vec3>,
    vertex_normals: Vec<Vec3>,
    /// Per triangle, the pseudo-normals of its edges AB, BC, CA (parry's edge order is AB, BC,
    /// AC; CA and AC are the same edge).
    edge_normals: Vec<[Vec3; 3]>,
}

impl std::fmt::Debug for MeshQuery {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshQuery").field("triangles", &self.face_normals.len()).finish()
    }
}

impl MeshQuery {
    /// Builds the hierarchy and pseudo-normals. Degenerate (zero-area) triangles are dropped; a
    /// mesh with none left is an error.
    pub fn new(mesh: &Mesh) -> Result<Self> {
        // Weld vertices with identical coordinates so that pseudo-normals see across seams.
        let mut welded: HashMap<[u32; 3], u32> = HashMap::new();
        let mut vertices: Vec<Vec3> = Vec::new();
        let remap: Vec<u32> = mesh
            .vertices
            .iter()
            .map(|v| {
                // +0.0 and -0.0 are the same point.
                let key = (*v + Vec3::ZERO).to_array().map(f32::to_bits);
                *welded.entry(key).or_insert_with(|| {
                    vertices.push(*v);
                    vertices.len() as u32 - 1
                })
            })
            .collect();
        let mut triangles: Vec<[u32; 3]> = Vec::with_capacity(mesh.faces.len());
        let mut face_normals = Vec::with_capacity(mesh.faces.len());
        for face in &mesh.faces {
            let tri = face.map(|i| remap[i as usize]);
            let [a, b, c] = tri.map(|i| vertices[i as usize]);
            let normal = (b - a).cross(c - a);
            let length = normal.length();
            if tri[0] == tri[1]
                || tri[1] == tri[2]
                || tri[0] == tri[2]
                || length.is_nan()
                || length <= 1e-20
            {
                continue;
            }
            triangles.push(tri);
            face_normals.push(normal / length);
        }
        if triangles.is_empty() {
            return Err(ReprError::EmptyMesh { source_name: "signed-distance query".into() });
        }
        let mut vertex_normals = vec![Vec3::ZERO; vertices.len()];
        let mut edge_sums: HashMap<(u32, u32), Vec3> = HashMap::new();
        for (tri, normal) in triangles.iter().zip(&face_normals) {
            for k in 0..3 {
                let (i, j, l) = (tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]);
                let p = vertices[i as usize];
                let e1 = (vertices[j as usize] - p).normalize_or_zero();
                let e2 = (vertices[l as usize] - p).normalize_or_zero();
                let angle = e1.dot(e2).clamp(-1.0, 1.0).acos();
                vertex_normals[i as usize] += *normal * angle;
                *edge_sums.entry((i.min(j), i.max(j))).or_insert(Vec3::ZERO) += *normal;
            }
        }
        let edge = |i: u32, j: u32| edge_sums[&(i.min(j), i.max(j))];
        let edge_normals = triangles
            .iter()
            .map(|t| [edge(t[0], t[1]), edge(t[1], t[2]), edge(t[2], t[0])])
            .collect();
        let trimesh = TriMesh::new(vertices, triangles).map_err(|error| {
            ReprError::format("signed-distance query", "triangle mesh", "a valid mesh", error)
        })?;
        Ok(Self { trimesh, face_normals, vertex_normals, edge_normals })
    }

    /// The height (world Y) of the mesh's lowest point when its frame is placed at
    /// `rotation`, `position`: where an object standing on a support touches it.
    pub fn lowest_height(&self, rotation: Mat3, position: Vec3) -> f32 {
        self.trimesh
            .vertices()
            .iter()
            .map(|v| (rotation * *v + position).y)
            .fold(f32::INFINITY, f32::min)
    }

    /// Number of triangles in the query structure.
    pub fn triangle_count(&self) -> usize {
        self.face_normals.len()
    }

    /// The nearest surface point and the signed distance of one point.
    pub fn closest(&self, point: Vec3) -> SurfacePoint {
        let (projection, (triangle, location)) =
            self.trimesh.project_local_point_and_get_location(point, false);
        let t = triangle as usize;
        let tri = self.trimesh.indices()[t];
        let pseudo_normal = match location {
            TrianglePointLocation::OnVertex(k) => self.vertex_normals[tri[k as usize] as usize],
            TrianglePointLocation::OnEdge(0, _) => self.edge_normals[t][0],
            TrianglePointLocation::OnEdge(1, _) => self.edge_normals[t][1],
            TrianglePointLocation::OnEdge(_, _) => self.edge_normals[t][2],
            TrianglePointLocation::OnFace(..) | TrianglePointLocation::OnSolid => {
                self.face_normals[t]
            }
        };
        let offset = point - projection.point;
        let distance = offset.length();
        let inside = offset.dot(pseudo_normal) < 0.0;
        SurfacePoint {
            point: projection.point,
            signed_distance: if inside { -distance } else { distance },
            triangle,
        }
    }

    /// The signed distance of one point (negative inside).
    pub fn signed_distance(&self, point: Vec3) -> f32 {
        self.closest(point).signed_distance
    }

    /// Signed distances of many points, in parallel.
    pub fn signed_distances(&self, points: &[Vec3]) -> Vec<f32> {
        points.par_iter().map(|p| self.signed_distance(*p)).collect()
    }

    /// Nearest surface points of many points, in parallel.
    pub fn closest_points(&self, points: &[Vec3]) -> Vec<SurfacePoint> {
        points.par_iter().map(|p| self.closest(*p)).collect()
    }
}

/// The nearest point on a triangle to `p` by brute force (Ericson, Real-Time Collision
/// Detection, 5.1.5); the reference the tests and the benchmark baseline use.
pub fn closest_point_on_triangle(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denominator = 1.0 / (va + vb + vc);
    a + ab * (vb * denominator) + ac * (vc * denominator)
}

/// The unsigned distance from `p` to a mesh by scanning every triangle: the brute-force
/// reference for tests and benchmarks.
pub fn brute_force_distance(mesh: &Mesh, p: Vec3) -> f32 {
    mesh.faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| mesh.vertices[i as usize]);
            closest_point_on_triangle(p, a, b, c).distance(p)
        })
        .fold(f32::INFINITY, f32::min)
}
