//! Raw motion sequences: what every dataset loader produces and the feature pipeline consumes.

use glam::{Mat3, Vec3};

use dex2hoi_repr::{Mesh, Skeleton};

use crate::error::{DataError, Result};

/// The most objects a sequence (and the dual-stream model) handles.
pub const MAX_OBJECTS: usize = 2;

/// One object of a sequence: a canonical mesh centred on its bounding box and its pose per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceObject {
    /// Catalogue or dataset name.
    pub name: String,
    /// The mesh in its own frame, centred on its bounding-box centre.
    pub mesh: Mesh,
    /// Object-to-world rotation per frame.
    pub rotations: Vec<Mat3>,
    /// World position of the object frame's origin per frame.
    pub translations: Vec<Vec3>,
}

/// A motion sequence before feature extraction.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// The skeleton the rotations drive.
    pub skeleton: Skeleton,
    /// Frames per second.
    pub fps: f32,
    /// Local joint rotations, frame-major `[frames * joints]`.
    pub local_rotations: Vec<Mat3>,
    /// World position of the root joint per frame.
    pub root_positions: Vec<Vec3>,
    /// Zero, one or two objects.
    pub objects: Vec<SequenceObject>,
    /// One or more descriptions.
    pub texts: Vec<String>,
    /// An action label (a task family, a GRAB intent), if the dataset has one.
    pub action: Option<String>,
    /// Where the sequence comes from (file name, generator id).
    pub source_id: String,
}

impl Sequence {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.root_positions.len()
    }

    /// Checks that the arrays agree in length, values are finite, rotations are rotations, and
    /// there are at most two objects and at least one non-empty text.
    pub fn validate(&self) -> Result<()> {
        let id = &self.source_id;
        let frames = self.frames();
        let joints = self.skeleton.joint_count();
        if frames == 0 {
            return Err(DataError::invalid(id, "at least one frame", 0));
        }
        if !(self.fps > 0.0 && self.fps.is_finite()) {
            return Err(DataError::invalid(id, "a positive frame rate", self.fps));
        }
        if self.local_rotations.len() != frames * joints {
            return Err(DataError::invalid(
                id,
                format!("{frames} x {joints} local rotations"),
                self.local_rotations.len(),
            ));
        }
        if self.objects.len() > MAX_OBJECTS {
            return Err(DataError::invalid(id, "at most two objects", self.objects.len()));
        }
        if self.texts.is_empty() || self.texts.iter().any(|t| t.trim().is_empty()) {
            return Err(DataError::invalid(
                id,
                "one or more non-empty texts",
                format!("{:?}", self.texts),
            ));
        }
        if let Some(i) = self.root_positions.iter().position(|p| !p.is_finite()) {
            return Err(DataError::invalid(
                id,
                "finite root positions",
                format!("a NaN at frame {i}"),
            ));
        }
        if let Some(i) =
            self.local_rotations.iter().position(|r| !dex2hoi_repr::rotation::is_rotation(*r, 1e-3))
        {
            return Err(DataError::invalid(
                id,
                "rotation matrices",
                format!("a non-rotation at frame {}, joint {}", i / joints, i % joints),
            ));
        }
        for object in &self.objects {
            if object.rotations.len() != frames || object.translations.len() != frames {
                return Err(DataError::invalid(
                    format!("{id}: object {}", object.name),
                    format!("{frames} rotations and translations"),
                    format!("{} and {}", object.rotations.len(), object.translations.len()),
                ));
            }
            let bad_rotation =
                object.rotations.iter().any(|r| !dex2hoi_repr::rotation::is_rotation(*r, 1e-3));
            if bad_rotation || object.translations.iter().any(|t| !t.is_finite()) {
                return Err(DataError::invalid(
                    format!("{id}: object {}", object.name),
                    "finite translations and rotation matrices",
                    "a NaN or a non-rotation",
                ));
            }
        }
        Ok(())
    }
}
