//! The scene a motion is generated in: objects from the catalogue or the user's meshes, and
//! where they stand at the start (on a table in front of the character unless placed).

use std::path::Path;

use glam::{Mat3, Vec2, Vec3};

use dex2hoi_data::catalogue::{CATALOGUE, catalogue_object};
use dex2hoi_data::character::Hand;
use dex2hoi_data::dataset::Dataset;
use dex2hoi_model::text::words;
use dex2hoi_repr::{Mesh, ObjectPose};

use crate::error::{Result, SampleError};

/// Height of the default table top (the middle of the procedural dataset's 0.86-0.94 m).
pub const DEFAULT_TABLE_HEIGHT: f32 = 0.90;
/// Distance of the default object places in front of the character (metres along +Z).
pub const DEFAULT_OBJECT_DEPTH: f32 = 0.39;
/// Sideways distance of a default place from the middle (metres along X; the left hand is
/// +X): each of two objects, or one object whose prompt names the hand that takes it (the
/// middle of the procedural dataset's 0.10-0.22 m, `dex2hoi_synth::plan`'s `side_x`).
pub const DEFAULT_OBJECT_SIDE: f32 = 0.16;
/// The default table's near edge (metres along +Z), for previews.
pub const DEFAULT_TABLE_NEAR_EDGE: f32 = 0.25;
/// The default table top's half extents (metres along X and Z), for previews.
pub const DEFAULT_TABLE_HALF_EXTENTS: Vec2 = Vec2::new(0.55, 0.30);
/// How far (metres) an object's lowest point may be from the table top for it to stand on the
/// table.
pub const ON_TABLE_TOLERANCE_M: f32 = 0.03;

/// The default table top, where previews and views draw it: only under objects that stand on
/// it, since a sequence's or a placed object's support may be something else.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneTable {
    /// Height of the top (metres).
    pub height: f32,
    /// Centre of the top, `(x, z)`.
    pub centre: Vec2,
    /// Half extents of the top, `(x, z)`.
    pub half_extents: Vec2,
}

impl SceneTable {
    /// The table of top `height` when one of the generated `objects` starts on it: unplaced
    /// (put on the table), or placed with its lowest point within [`ON_TABLE_TOLERANCE_M`] of
    /// the top.
    pub fn under(objects: &[(usize, SceneObject)], height: f32) -> Option<Self> {
        let on_table = objects.iter().any(|(_, o)| {
            o.placed.is_none_or(|pose| {
                let lowest = o.mesh.height_range(pose.rotation).0 + pose.position.y;
                (lowest - height).abs() < ON_TABLE_TOLERANCE_M
            })
        });
        on_table.then_some(Self {
            height,
            centre: Vec2::new(0.0, DEFAULT_TABLE_NEAR_EDGE + DEFAULT_TABLE_HALF_EXTENTS.y),
            half_extents: DEFAULT_TABLE_HALF_EXTENTS,
        })
    }
}

/// Where a lone object stands by default, sideways (metres along X): on the side of the hand
/// the prompt names first ("... with the right hand ..."), where the procedural dataset puts
/// the object of every one-handed task (pick and place, inspect, hand-over), so the model
/// reaches for it with that hand; in the middle, like the two-handed lift's object, when the
/// prompt names no single hand ("with both hands", or no hand at all).
///
/// A model of the procedural data reads the hand from the layout as well as from the words: the
/// model shipped before 2026-11-29 used the hand the words name in 78% of ten-second
/// generations with a lone object moved to the middle or across the body, against 94% with the
/// test split's own placements.
pub fn default_lone_object_side(prompt: &str) -> f32 {
    first_named_hand(&words(prompt)).map_or(0.0, |(_, hand)| hand.side() * DEFAULT_OBJECT_SIDE)
}

/// Where two unplaced objects stand by default, sideways (metres along X, in the order of
/// `names`): one on each side, [`DEFAULT_OBJECT_SIDE`] from the middle. The object the hand the
/// prompt names first belongs to stands on that hand's side, as the procedural dataset puts
/// the objects of its two-object tasks (the pouring hand's bottle on its side, the steadied
/// receiver on the other; each hand's object of "hold two" on its own side): the object named
/// last before that hand ("... holds the bowl with the left hand ..."), or, when the hand
/// comes first ("Using the right hand, ... the bottle ..."), the first named after it. Without
/// a named hand, or when the prompt names neither object, the first stands on the left.
///
/// The model reads the hands from the objects' places as well as from the words: with the
/// bottle on the left, "Take the bottle in your right hand, pour it into the bowl" had the left
/// hand pour and the right hand lift the bowl in two seeds of two.
pub fn default_pair_sides(prompt: &str, names: [&str; 2]) -> [f32; 2] {
    let tokens = words(prompt);
    let first_left = [DEFAULT_OBJECT_SIDE, -DEFAULT_OBJECT_SIDE];
    let Some((at, hand)) = first_named_hand(&tokens) else {
        return first_left;
    };
    // The mention nearest the hand before it, else the first after it (of two names at the
    // same word, the second before the hand and the first after it).
    let names = names.map(words);
    let named_at = |i: usize, name: &Vec<String>| !name.is_empty() && tokens[i..].starts_with(name);
    let before = (0..at).rev().find_map(|i| names.iter().rposition(|n| named_at(i, n)));
    let after = (at + 1..tokens.len()).find_map(|i| names.iter().position(|n| named_at(i, n)));
    match before.or(after) {
        Some(slot) => {
            let mut sides = [-hand.side() * DEFAULT_OBJECT_SIDE; 2];
            sides[slot] = hand.side() * DEFAULT_OBJECT_SIDE;
            sides
        }
        None => first_left,
    }
}

/// The first "left hand" or "right hand" of a prompt's words: where it is and the hand.
fn first_named_hand(tokens: &[String]) -> Option<(usize, Hand)> {
    tokens.windows(2).enumerate().find_map(|(i, pair)| match (pair[0].as_str(), pair[1].as_str()) {
        ("left", "hand") => Some((i, Hand::Left)),
        ("right", "hand") => Some((i, Hand::Right)),
        _ => None,
    })
}

/// An object of the scene: a name, a mesh centred on its bounding box, and where it stands.
#[derive(Debug, Clone)]
pub struct SceneObject {
    /// Name (catalogue name or file stem).
    pub name: String,
    /// Mesh, centred on its bounding box.
    pub mesh: Mesh,
    /// The object frame's pose at the start; `None` puts it upright on the table.
    pub placed: Option<ObjectPose>,
    /// Its rotation standing upright: the identity for the built-in catalogue and files; for a
    /// dataset's object, as the data stand it (real data keep each object's mesh in its own
    /// axes; see `data_upright`).
    pub upright: Mat3,
}

impl SceneObject {
    /// An object from a specification: a catalogue name (`mug`; with `dataset`, first a name
    /// of its object catalogue) or an OBJ/PLY file, optionally followed by `@x,y,z` (metres,
    /// character frame: +Z ahead, +X to the left, +Y up).
    pub fn parse(spec: &str, dataset: Option<&Dataset>) -> Result<Self> {
        let (what, position) = match spec.split_once('@') {
            Some((what, at)) => {
                let values: Vec<f32> = at
                    .split(',')
                    .map(|v| v.trim().parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| SampleError::invalid("object", spec, "NAME@x,y,z in metres", e))?;
                if values.len() != 3 || values.iter().any(|v| !v.is_finite()) {
                    return Err(SampleError::invalid(
                        "object",
                        spec,
                        "three finite numbers after @",
                        at,
                    ));
                }
                (what, Some(Vec3::new(values[0], values[1], values[2])))
            }
            None => (spec, None),
        };
        let what = what.trim();
        let place =
            |upright: Mat3| position.map(|position| ObjectPose { rotation: upright, position });
        if let Some((dataset, asset)) =
            dataset.and_then(|d| Some((d, d.objects.iter().find(|o| o.name == what)?)))
        {
            let upright = data_upright(dataset, what, &asset.mesh);
            return Ok(Self {
                name: asset.name.clone(),
                mesh: asset.mesh.clone(),
                placed: place(upright),
                upright,
            });
        }
        let upright = Mat3::IDENTITY;
        if let Some(object) = catalogue_object(what) {
            let (name, mesh) = (object.name.to_string(), object.mesh());
            return Ok(Self { name, mesh, placed: place(upright), upright });
        }
        let path = Path::new(what);
        let is_mesh = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("obj") || e.eq_ignore_ascii_case("ply"));
        if !is_mesh {
            let mut names: Vec<&str> = CATALOGUE.iter().map(|o| o.name).collect();
            if let Some(dataset) = dataset {
                names.extend(dataset.objects.iter().map(|o| o.name.as_str()));
            }
            return Err(SampleError::invalid(
                "object",
                what,
                format!("a catalogue object ({}) or an .obj/.ply file", names.join(", ")),
                "neither",
            ));
        }
        Ok(Self::from_mesh(Mesh::load(path)?, path, position))
    }

    /// An object from a mesh file's bytes (`.obj` or `.ply`, by the extension of `file_name`,
    /// which names it), upright as the file has it, at `position` if given: a mesh that comes
    /// from somewhere other than the file system, as a web page's file picker gives it.
    pub fn from_mesh_bytes(bytes: &[u8], file_name: &str, position: Option<Vec3>) -> Result<Self> {
        Ok(Self::from_mesh(Mesh::parse(bytes, file_name)?, Path::new(file_name), position))
    }

    /// A mesh read from the file that `path` names, named by the file's stem and recentred
    /// on its bounding box (docs/CONVENTIONS.md, "Object frame").
    fn from_mesh(mut mesh: Mesh, path: &Path, position: Option<Vec3>) -> Self {
        mesh.recenter();
        let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("object").to_string();
        let upright = Mat3::IDENTITY;
        let placed = position.map(|position| ObjectPose { rotation: upright, position });
        Self { name, mesh, placed, upright }
    }

    /// The starting pose: the given one, or upright on the table at `default_place`.
    pub fn start_pose(&self, default_place: (f32, f32), table_height: f32) -> ObjectPose {
        self.placed.unwrap_or_else(|| {
            // Resting on the table: its lowest point at the table's height.
            let (low, high) = self.mesh.height_range(self.upright);
            let above = (high - low) / 2.0 - (high + low) / 2.0;
            let position = Vec3::new(default_place.0, table_height + above, default_place.1);
            ObjectPose { rotation: self.upright, position }
        })
    }
}

/// How a dataset's object stands when nothing says otherwise: of the rotations it has on the
/// first frames of the sequences that have it, the one that keeps it lowest (a board lies flat,
/// a chair stands on its legs); the identity when no sequence has it.
fn data_upright(dataset: &Dataset, name: &str, mesh: &Mesh) -> Mat3 {
    let height = |rotation: &Mat3| {
        let (low, high) = mesh.height_range(*rotation);
        high - low
    };
    dataset
        .splits
        .values()
        .flatten()
        .filter_map(|s| {
            let slot = s.object_names.iter().position(|n| n.as_deref() == Some(name))?;
            Some(s.object_poses_at(0)[slot]?.rotation)
        })
        .min_by(|a, b| height(a).total_cmp(&height(b)))
        .unwrap_or(Mat3::IDENTITY)
}

/// The scene a sequence of a dataset starts in: its objects where they are on its first frame,
/// and its descriptions.
#[derive(Debug, Clone)]
pub struct SequenceScene {
    /// The sequence's source id.
    pub source_id: String,
    /// Its objects in slot order, placed as on its first frame.
    pub objects: Vec<SceneObject>,
    /// Its descriptions.
    pub texts: Vec<String>,
    /// Its length in frames.
    pub frames: usize,
}

impl SequenceScene {
    /// The sequence of `dataset` (either split) that `id` names
    /// ([`dex2hoi_data::processed::ProcessedSequence::is_named`]).
    pub fn of(dataset: &Dataset, id: &str) -> Result<Self> {
        let sequences = || dataset.splits.values().flatten();
        let sequence = sequences().find(|s| s.is_named(id)).ok_or_else(|| {
            let some: Vec<&str> = sequences().take(3).map(|s| s.source_id.as_str()).collect();
            SampleError::invalid(
                "sequence",
                id,
                format!(
                    "the source id of one of the dataset's sequences ({}, ...)",
                    some.join(", ")
                ),
                "none with that id",
            )
        })?;
        let poses = sequence.object_poses_at(0);
        let objects = sequence
            .object_names
            .iter()
            .zip(poses)
            .filter_map(|(name, pose)| Some((name.as_ref()?, pose?)))
            .map(|(name, pose)| {
                let asset = dataset.objects.iter().find(|o| &o.name == name).ok_or_else(|| {
                    SampleError::invalid("sequence", id, "objects of the dataset's catalogue", name)
                })?;
                Ok(SceneObject {
                    name: name.clone(),
                    mesh: asset.mesh.clone(),
                    placed: Some(pose),
                    upright: pose.rotation,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            source_id: sequence.source_id.clone(),
            objects,
            texts: sequence.texts.clone(),
            frames: sequence.frames,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_is_drawn_under_objects_that_stand_on_it() {
        let mug = SceneObject::parse("mug", None).unwrap();
        let height = DEFAULT_TABLE_HEIGHT;
        // Unplaced: put on the table.
        let table = SceneTable::under(&[(0, mug.clone())], height).unwrap();
        assert_eq!(table.height, height);
        assert_eq!(table.half_extents, DEFAULT_TABLE_HALF_EXTENTS);
        assert_eq!(table.centre.y - table.half_extents.y, DEFAULT_TABLE_NEAR_EDGE);
        // Placed with its bottom on the top (within the tolerance), or on the floor.
        let half_height = {
            let (low, high) = mug.mesh.height_range(Mat3::IDENTITY);
            (high - low) / 2.0
        };
        let at = |y: f32| {
            let spec = format!("mug@0.1,{y},0.4");
            vec![(0, SceneObject::parse(&spec, None).unwrap())]
        };
        let gap = ON_TABLE_TOLERANCE_M / 2.0;
        assert!(SceneTable::under(&at(height + half_height + gap), height).is_some());
        assert!(SceneTable::under(&at(half_height), height).is_none());
        assert!(SceneTable::under(&at(height + half_height + 0.2), height).is_none());
    }

    #[test]
    fn a_mesh_from_memory_is_named_by_its_file_and_recentred() {
        let obj = "v 1 1 1\nv 2 1 1\nv 1 2 1\nv 1 1 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
        let at = Vec3::new(0.0, 1.0, 0.4);
        let object = SceneObject::from_mesh_bytes(obj.as_bytes(), "Wedge.obj", Some(at)).unwrap();
        assert_eq!(object.name, "Wedge");
        let (low, high) = object.mesh.bounding_box();
        assert!((low + high).abs().max_element() < 1e-6, "{low} {high}");
        assert_eq!(object.placed.unwrap().position, at);
        let error = SceneObject::from_mesh_bytes(obj.as_bytes(), "wedge.stl", None).unwrap_err();
        assert!(error.to_string().contains("wedge.stl"), "{error}");
    }

    #[test]
    fn a_lone_object_stands_on_the_side_of_the_hand_the_prompt_names_first() {
        let right = -DEFAULT_OBJECT_SIDE;
        let left = DEFAULT_OBJECT_SIDE;
        let cases = [
            (
                "The person picks up the mug with the right hand and puts it down to the left.",
                right,
            ),
            ("The person picks up the bowl with the LEFT hand, turns it around.", left),
            // The hand that takes it first; the other one only receives it.
            ("The person picks up the ball with the left hand, passes it to the right hand", left),
            ("The person lifts the book with both hands and puts it back down.", 0.0),
            ("The person picks up the mug.", 0.0),
            // "left" alone is a direction, not a hand.
            ("The person moves the mug to the left.", 0.0),
            ("", 0.0),
        ];
        for (prompt, expected) in cases {
            assert_eq!(default_lone_object_side(prompt), expected, "{prompt}");
        }
    }

    #[test]
    fn two_objects_stand_where_the_hands_the_prompt_names_hold_them() {
        let (left, right) = (DEFAULT_OBJECT_SIDE, -DEFAULT_OBJECT_SIDE);
        let cases = [
            // The object named before the hand.
            (
                "The person holds the bowl with the left hand and pours from the bottle with the right hand.",
                ["bottle", "bowl"],
                [right, left],
            ),
            (
                "Take the bottle in your right hand, pour it into the bowl.",
                ["bottle", "bowl"],
                [right, left],
            ),
            (
                "Someone pours from the bottle into the bowl, steadying the bowl with the left hand.",
                ["bowl", "bottle"],
                [left, right],
            ),
            (
                "The person picks up the bottle with the left hand and the can with the right hand.",
                ["bottle", "can"],
                [left, right],
            ),
            // The hand first: the object named after it.
            (
                "Using the right hand, someone places the can beside the bowl.",
                ["bowl", "can"],
                [left, right],
            ),
            // A file's name is matched by its words.
            ("Grab my_cup with the right hand.", ["plate", "my_cup"], [left, right]),
            // No hand, or neither object named: the first on the left.
            ("The person swaps the places of the mug and the can.", ["can", "mug"], [left, right]),
            ("Lift it with the right hand.", ["mug", "can"], [left, right]),
            ("", ["mug", "can"], [left, right]),
        ];
        for (prompt, names, expected) in cases {
            assert_eq!(default_pair_sides(prompt, names), expected, "{prompt}");
        }
    }
}
