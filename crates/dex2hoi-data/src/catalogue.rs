//! The object catalogue: eight table-top objects with realistic sizes, their meshes (centred on
//! the bounding box, resting on their bottom face when upright), how a hand holds them, and the
//! BPS basis every object of a dataset is encoded with. The procedural dataset draws its objects
//! from it; sampling places them by name.

use glam::Vec3;

use crate::error::Result;
use crate::features::ObjectAsset;

use dex2hoi_repr::Mesh;
use dex2hoi_repr::mesh::{box_mesh, uv_sphere};

/// The primitive shape of a catalogue object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ObjectShape {
    /// An upright closed cylinder.
    Cylinder {
        /// Radius in metres.
        radius: f32,
        /// Height in metres.
        height: f32,
    },
    /// A box with these half extents.
    Box {
        /// Half extents in metres.
        half_extents: Vec3,
    },
    /// A ball.
    Sphere {
        /// Radius in metres.
        radius: f32,
    },
}

/// One catalogue entry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CatalogueObject {
    /// The name used in texts and files.
    pub name: &'static str,
    /// Its shape and size.
    pub shape: ObjectShape,
    /// Whether it is held with one hand from above (small objects).
    pub one_handed: bool,
    /// Whether it is lifted with both hands from the sides (wide objects).
    pub two_handed: bool,
    /// Whether something can be poured from it.
    pub pours: bool,
    /// Whether something can be poured into it.
    pub receives: bool,
}

const fn cylinder(radius: f32, height: f32) -> ObjectShape {
    ObjectShape::Cylinder { radius, height }
}

/// The catalogue, sizes in metres.
pub const CATALOGUE: [CatalogueObject; 8] = [
    CatalogueObject {
        name: "mug",
        shape: cylinder(0.040, 0.100),
        one_handed: true,
        two_handed: false,
        pours: true,
        receives: true,
    },
    CatalogueObject {
        name: "bottle",
        shape: cylinder(0.035, 0.240),
        one_handed: true,
        two_handed: false,
        pours: true,
        receives: false,
    },
    CatalogueObject {
        name: "box",
        shape: ObjectShape::Box { half_extents: Vec3::new(0.15, 0.10, 0.10) },
        one_handed: false,
        two_handed: true,
        pours: false,
        receives: false,
    },
    CatalogueObject {
        name: "ball",
        shape: ObjectShape::Sphere { radius: 0.055 },
        one_handed: true,
        two_handed: false,
        pours: false,
        receives: false,
    },
    CatalogueObject {
        name: "bowl",
        shape: cylinder(0.075, 0.060),
        one_handed: true,
        two_handed: true,
        pours: false,
        receives: true,
    },
    CatalogueObject {
        name: "book",
        shape: ObjectShape::Box { half_extents: Vec3::new(0.11, 0.016, 0.08) },
        one_handed: true,
        two_handed: true,
        pours: false,
        receives: false,
    },
    CatalogueObject {
        name: "can",
        shape: cylinder(0.033, 0.120),
        one_handed: true,
        two_handed: false,
        pours: true,
        receives: false,
    },
    CatalogueObject {
        name: "plate",
        shape: cylinder(0.110, 0.020),
        one_handed: true,
        two_handed: true,
        pours: false,
        receives: true,
    },
];

/// The catalogue entry of a name.
pub fn catalogue_object(name: &str) -> Option<&'static CatalogueObject> {
    CATALOGUE.iter().find(|o| o.name == name)
}

/// A closed cylinder along +Y centred on the origin, outward triangles.
pub fn cylinder_mesh(radius: f32, height: f32, segments: u32) -> Mesh {
    let h = height / 2.0;
    let mut vertices = vec![Vec3::new(0.0, h, 0.0), Vec3::new(0.0, -h, 0.0)];
    for s in 0..segments {
        let angle = std::f32::consts::TAU * s as f32 / segments as f32;
        let (x, z) = (angle.cos() * radius, angle.sin() * radius);
        vertices.push(Vec3::new(x, h, z));
        vertices.push(Vec3::new(x, -h, z));
    }
    let top = |s: u32| 2 + 2 * (s % segments);
    let bottom = |s: u32| 3 + 2 * (s % segments);
    let mut faces = Vec::new();
    for s in 0..segments {
        faces.push([0, top(s + 1), top(s)]);
        faces.push([1, bottom(s), bottom(s + 1)]);
        faces.push([top(s), top(s + 1), bottom(s + 1)]);
        faces.push([top(s), bottom(s + 1), bottom(s)]);
    }
    Mesh { vertices, faces }
}

impl CatalogueObject {
    /// The mesh, centred on its bounding box.
    pub fn mesh(&self) -> Mesh {
        match self.shape {
            ObjectShape::Cylinder { radius, height } => cylinder_mesh(radius, height, 32),
            ObjectShape::Box { half_extents } => box_mesh(half_extents),
            ObjectShape::Sphere { radius } => uv_sphere(radius, 12, 24),
        }
    }

    /// Half extents of the bounding box.
    pub fn half_extents(&self) -> Vec3 {
        match self.shape {
            ObjectShape::Cylinder { radius, height } => Vec3::new(radius, height / 2.0, radius),
            ObjectShape::Box { half_extents } => half_extents,
            ObjectShape::Sphere { radius } => Vec3::splat(radius),
        }
    }
}

/// BPS radius for table-top objects: the largest catalogue object (the 30 x 20 x 20 cm box)
/// has a half-diagonal of 0.21 m, so a 0.25 m ball holds every object with a margin while the
/// basis points stay close enough to the surfaces that their offsets describe the shape (a
/// 1 m ball, as CHOIS uses for furniture, would spend most points far from a mug).
pub const BPS_RADIUS: f32 = 0.25;
/// Seed of the shared BPS basis.
pub const BPS_SEED: u64 = 0x0B75;

/// The object assets of the whole catalogue with the shared BPS basis.
pub fn catalogue_assets() -> Result<Vec<ObjectAsset>> {
    let basis =
        dex2hoi_repr::BpsBasis::new(dex2hoi_repr::bps::DEFAULT_BPS_POINTS, BPS_RADIUS, BPS_SEED)?;
    CATALOGUE
        .iter()
        .enumerate()
        .map(|(k, o)| ObjectAsset::new(o.name, o.mesh(), &basis, k as u64))
        .collect()
}
