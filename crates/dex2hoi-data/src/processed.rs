//! What the feature pipeline produces ([`crate::features`]) and the layout indexes
//! ([`crate::layout`]): a processed sequence and the per-mesh object assets.

use glam::{Mat3, Vec3};

use dex2hoi_repr::{BpsBasis, Mesh, MeshQuery, ObjectPose, Skeleton, SurfaceSamples};

use crate::error::Result;
use crate::sequence::MAX_OBJECTS;

/// What the features of one object mesh need, computed once per mesh: BPS and surface samples.
#[derive(Debug, Clone)]
pub struct ObjectAsset {
    /// The object's name.
    pub name: String,
    /// The canonical (bounding-box-centred) mesh.
    pub mesh: Mesh,
    /// BPS offsets `[points]` in the object frame.
    pub bps: Vec<Vec3>,
    /// Surface samples with normals in the object frame (penetration terms).
    pub samples: SurfaceSamples,
}

/// Number of surface samples stored per object.
pub const SURFACE_SAMPLES: usize = 512;

/// Half-width of the centre band when the side an object ends on is judged: an object ends
/// to a side of where it stood when it ends more than this far to that side along the body's
/// left axis (docs/CONVENTIONS.md, "The long-generation protocol").
pub const SIDE_MARGIN_M: f32 = 0.05;

/// Where an object is, or how far it travelled, across the body: along the body's left axis,
/// beyond [`SIDE_MARGIN_M`] or within it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// More than [`SIDE_MARGIN_M`] to the body's left.
    Left,
    /// Within [`SIDE_MARGIN_M`] of the body's midline.
    Centre,
    /// More than [`SIDE_MARGIN_M`] to the body's right.
    Right,
}

impl Side {
    /// The side of a distance along the body's left axis (metres, positive to the left).
    pub fn of_across(across: f32) -> Self {
        if across > SIDE_MARGIN_M {
            Side::Left
        } else if across < -SIDE_MARGIN_M {
            Side::Right
        } else {
            Side::Centre
        }
    }
}

impl ObjectAsset {
    /// BPS and surface samples of a mesh (the samples are seeded by `seed`).
    pub fn new(name: &str, mesh: Mesh, basis: &BpsBasis, seed: u64) -> Result<Self> {
        let query = MeshQuery::new(&mesh)?;
        Ok(Self {
            name: name.into(),
            bps: basis.encode(&query),
            samples: mesh.sample_surface(SURFACE_SAMPLES, seed)?,
            mesh,
        })
    }
}

/// A sequence after feature extraction, in the canonical frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ProcessedSequence {
    /// Number of frames `T`.
    pub frames: usize,
    /// Number of joints `J`.
    pub joints: usize,
    /// `[T, 6J + 3]`: 6D local rotations then the root displacement from the first frame.
    pub body: Vec<f32>,
    /// `[T, 2, 18]`: the hand-relative representation of each object slot (zeros when absent).
    pub objects: Vec<f32>,
    /// Which object slots hold an object.
    pub object_present: [bool; MAX_OBJECTS],
    /// Names of the objects in the slots.
    pub object_names: [Option<String>; MAX_OBJECTS],
    /// `[T, J, 3]` joint positions.
    pub joint_positions: Vec<f32>,
    /// `[T, 2, H]` signed distance of every hand joint (left hand then right hand joints of the
    /// skeleton's groups) to each object; [`ABSENT_DISTANCE`](crate::features::ABSENT_DISTANCE) for an absent object.
    pub hand_distances: Vec<f32>,
    /// `[T, 2, 2]` contact flags (object slot, then left and right hand), 0 or 1.
    pub hand_contact: Vec<f32>,
    /// `[T, 4]` foot contact flags: left ankle, left toe, right ankle, right toe.
    pub foot_contact: Vec<f32>,
    /// `[T, 2, 3, 3]` object rotations (identity when absent).
    pub object_rotations: Vec<f32>,
    /// `[T, 2, 3]` object positions (zero when absent).
    pub object_positions: Vec<f32>,
    /// The root position at the first frame in the canonical frame, `(0, height, 0)`.
    pub root_start: Vec3,
    /// `[J]` rest offsets of the sequence's own body (a subject's proportions): the features
    /// are posed on them, and `joint_positions` is their FK.
    pub rest_offsets: Vec<Vec3>,
    /// Descriptions.
    pub texts: Vec<String>,
    /// Descriptions in phrasings held out of training, for evaluating how a model reads words
    /// it knows in phrasings it never saw; training never reads them. Empty for sources without
    /// them.
    pub held_out_texts: Vec<String>,
    /// Action label.
    pub action: Option<String>,
    /// Source id.
    pub source_id: String,
}

impl ProcessedSequence {
    /// Whether a user's `id` names this sequence: its whole source id, or the part after the
    /// source's prefix (`examining_cutting_board-141` for
    /// `humoto/examining_cutting_board-141`).
    pub fn is_named(&self, id: &str) -> bool {
        self.source_id == id || self.source_id.split_once('/').is_some_and(|(_, own)| own == id)
    }

    /// The object poses on frame `frame` (`None` for an empty slot), in the canonical frame.
    pub fn object_poses_at(&self, frame: usize) -> [Option<ObjectPose>; MAX_OBJECTS] {
        std::array::from_fn(|slot| {
            self.object_present[slot].then(|| {
                let base = frame * MAX_OBJECTS + slot;
                ObjectPose {
                    // Stored row by row.
                    rotation: Mat3::from_cols_slice(&self.object_rotations[base * 9..][..9])
                        .transpose(),
                    position: Vec3::from_slice(&self.object_positions[base * 3..][..3]),
                }
            })
        })
    }

    /// The sequence's own body: the topology, names and groups of `topology` (the dataset's
    /// built-in skeleton, [`crate::dataset::Manifest::builtin_skeleton`]) on the sequence's
    /// rest offsets.
    pub fn skeleton(&self, topology: &Skeleton) -> Result<Skeleton> {
        Ok(topology.with_rest_offsets(self.rest_offsets.clone())?)
    }

    /// Whether some object ends more than [`SIDE_MARGIN_M`] to the person's left of where it
    /// stood at the first frame, and whether some object ends that far to the right: `[left,
    /// right]`, along +X of the canonical frame, the first frame's left
    /// (docs/CONVENTIONS.md, "Coordinate frames and units").
    pub fn objects_travel(&self) -> [bool; 2] {
        let mut sides = [false; 2];
        if self.frames == 0 {
            return sides;
        }
        let [first, last] = [self.object_poses_at(0), self.object_poses_at(self.frames - 1)];
        for (start, end) in first.iter().zip(&last) {
            if let (Some(start), Some(end)) = (start, end) {
                match Side::of_across(end.position.x - start.position.x) {
                    Side::Left => sides[0] = true,
                    Side::Right => sides[1] = true,
                    Side::Centre => {}
                }
            }
        }
        sides
    }
}
