//! Skeletons: joint names, parents, rest offsets, the left/right symmetry map and named joint
//! groups (paper Sec. 3.1: `J = 52` for SMPL-X, `J = 65` for Mixamo).
//!
//! Joints are ordered so that every parent comes before its children; the root is joint 0 and
//! its rest offset is its rest position. Rest poses are in metres, Y up, facing +Z, in a T-pose:
//! the character's left arm points along +X.

use glam::{Quat, Vec3};

use crate::error::{ReprError, Result};

/// Which built-in rig a skeleton is (or derives from, for user-supplied SMPL-X shapes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SkeletonKind {
    /// The 52 SMPL-X body and hand joints (jaw and eyes dropped).
    Smplx52,
    /// The 65-joint Mixamo rig of HUMOTO.
    Mixamo65,
}

impl SkeletonKind {
    /// A stable lower-case name for files and manifests.
    pub fn name(self) -> &'static str {
        match self {
            Self::Smplx52 => "smplx52",
            Self::Mixamo65 => "mixamo65",
        }
    }

    /// The kind with this [`SkeletonKind::name`].
    pub fn from_name(name: &str) -> Result<Self> {
        match name {
            "smplx52" => Ok(Self::Smplx52),
            "mixamo65" => Ok(Self::Mixamo65),
            other => Err(ReprError::invalid("skeleton name", "`smplx52` or `mixamo65`", other)),
        }
    }
}

/// Named groups of joints that the features, losses and metrics use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JointGroups {
    /// The left wrist: the frame of the left wrist offsets (Eq. 3).
    pub left_wrist: usize,
    /// The right wrist.
    pub right_wrist: usize,
    /// The left wrist and every left finger joint: what "the left hand" means for contact.
    pub left_hand: Vec<usize>,
    /// The right wrist and every right finger joint.
    pub right_hand: Vec<usize>,
    /// The last joint of each left finger (thumb, index, middle, ring, pinky order is not implied).
    pub left_fingertips: Vec<usize>,
    /// The last joint of each right finger.
    pub right_fingertips: Vec<usize>,
    /// Left ankle and toe joints (foot contact and sliding).
    pub left_foot: Vec<usize>,
    /// Right ankle and toe joints.
    pub right_foot: Vec<usize>,
}

/// A kinematic tree with a rest pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    kind: SkeletonKind,
    joint_names: Vec<String>,
    parents: Vec<Option<usize>>,
    rest_offsets: Vec<Vec3>,
    symmetry: Vec<usize>,
    groups: JointGroups,
}

/// SMPL-X joint names in the 52-joint order (docs/CONVENTIONS.md, "SMPL-X 52": SMPL-X without jaw
/// and eyes).
const SMPLX52_BODY_NAMES: [&str; 22] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
];

/// SMPL-X finger order within each hand.
const SMPLX_FINGERS: [&str; 5] = ["index", "middle", "pinky", "ring", "thumb"];

/// Parents of the 55 SMPL-X joints, `-1` for the root.
pub const SMPLX55_PARENTS: [i32; 55] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15, 20, 25,
    26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49,
    50, 21, 52, 53,
];

/// Parents of the 52 SMPL-X joints, `-1` for the root.
pub const SMPLX52_PARENTS: [i32; 52] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 22, 23, 20, 25,
    26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 21, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49,
    50,
];

/// For each of the 52 joints, its index in the 55-joint SMPL-X order (jaw 22 and eyes 23, 24
/// are dropped, so hand joints move down by three).
pub fn smplx52_to_55() -> [usize; 52] {
    std::array::from_fn(|i| if i < 22 { i } else { i + 3 })
}

/// The public SMPL body offsets (child minus parent, metres, Y up) for joints 1-21
/// (docs/CONVENTIONS.md, "Rest offsets").
const SMPL_BODY_OFFSETS: [[f32; 3]; 21] = [
    [0.0586, -0.0823, -0.0177],
    [-0.0603, -0.0905, -0.0135],
    [0.0044, 0.1244, -0.0384],
    [0.0435, -0.3865, 0.0080],
    [-0.0433, -0.3837, -0.0048],
    [0.0045, 0.1380, 0.0268],
    [-0.0148, -0.4269, -0.0374],
    [0.0191, -0.4200, -0.0346],
    [-0.0023, 0.0560, 0.0029],
    [0.0411, -0.0603, 0.1220],
    [-0.0348, -0.0621, 0.1303],
    [-0.0134, 0.2116, -0.0335],
    [0.0717, 0.1140, -0.0189],
    [-0.0830, 0.1125, -0.0237],
    [0.0101, 0.0889, 0.0504],
    [0.1229, 0.0452, -0.0190],
    [-0.1132, 0.0469, -0.0085],
    [0.2553, -0.0156, -0.0229],
    [-0.2601, -0.0144, -0.0313],
    [0.2657, 0.0127, -0.0074],
    [-0.2691, 0.0068, -0.0060],
];

/// Pelvis height of the default SMPL-X rest pose: the foot joints end about 2 cm above the floor
/// and the ankles about 8 cm, like a person standing in shoes.
const SMPLX_PELVIS_HEIGHT: f32 = 0.975;

/// Our finger design for the left hand, in SMPL-X finger order (index, middle, pinky, ring,
/// thumb), three phalanx joints each, offsets from the parent in the T-pose (palm down, fingers
/// along +X, thumb forward along +Z). Knuckles sit 8-9.5 cm past the wrist; phalanx lengths
/// follow adult hand anthropometry (proximal 3-4.5 cm, middle 2-2.8 cm); the thumb leaves the
/// wrist forward and down and runs at about 40 degrees to the other fingers.
const LEFT_FINGER_OFFSETS: [[[f32; 3]; 3]; 5] = [
    [[0.088, -0.006, 0.027], [0.037, -0.002, 0.002], [0.023, -0.002, 0.000]],
    [[0.094, -0.006, 0.006], [0.042, -0.002, 0.000], [0.026, -0.002, 0.000]],
    [[0.078, -0.010, -0.034], [0.029, -0.002, -0.004], [0.019, -0.002, -0.002]],
    [[0.088, -0.008, -0.014], [0.039, -0.002, -0.002], [0.025, -0.002, -0.001]],
    [[0.026, -0.014, 0.030], [0.030, -0.006, 0.024], [0.024, -0.004, 0.018]],
];

/// Mixamo bone names without the `mixamorig:` prefix, in HUMOTO's order.
fn mixamo_names() -> Vec<String> {
    let mut names: Vec<String> =
        ["Hips", "Spine", "Spine1", "Spine2", "Neck", "Head", "HeadTop_End"]
            .map(String::from)
            .to_vec();
    for side in ["Left", "Right"] {
        for part in ["Shoulder", "Arm", "ForeArm", "Hand"] {
            names.push(format!("{side}{part}"));
        }
        for finger in ["Thumb", "Index", "Middle", "Ring", "Pinky"] {
            for k in 1..=4 {
                names.push(format!("{side}Hand{finger}{k}"));
            }
        }
    }
    for side in ["Left", "Right"] {
        for part in ["UpLeg", "Leg", "Foot", "ToeBase", "Toe_End"] {
            names.push(format!("{side}{part}"));
        }
    }
    names
}

/// The prefix of every Mixamo bone name in the published files.
pub const MIXAMO_PREFIX: &str = "mixamorig:";

/// Parents of the 65 Mixamo joints (docs/CONVENTIONS.md, "Mixamo 65").
pub const MIXAMO65_PARENTS: [i32; 65] = [
    -1, 0, 1, 2, 3, 4, 5, 3, 7, 8, 9, 10, 11, 12, 13, 10, 15, 16, 17, 10, 19, 20, 21, 10, 23, 24,
    25, 10, 27, 28, 29, 3, 31, 32, 33, 34, 35, 36, 37, 34, 39, 40, 41, 34, 43, 44, 45, 34, 47, 48,
    49, 34, 51, 52, 53, 0, 55, 56, 57, 58, 0, 60, 61, 62, 63,
];

/// Rest positions (not offsets) of the 65 Mixamo joints of HUMOTO's character, in joint order,
/// metres, Y up, facing +Z: the bind pose of the published GLB release (the skin's inverse bind
/// matrices times the `Armature` node's scale 0.01; every sequence of the release shares it).
/// docs/CONVENTIONS.md, "Rest offsets".
pub const HUMOTO_REST_POSITIONS: [(&str, [f32; 3]); 65] = [
    ("Hips", [0.0000, 0.8827, 0.0000]),
    ("Spine", [0.0000, 0.9474, -0.0093]),
    ("Spine1", [0.0000, 1.0296, -0.0212]),
    ("Spine2", [0.0000, 1.1138, -0.0333]),
    ("Neck", [0.0000, 1.2882, -0.0367]),
    ("Head", [0.0000, 1.3709, -0.0381]),
    ("HeadTop_End", [0.0000, 1.5724, -0.0374]),
    ("LeftShoulder", [0.0616, 1.2782, -0.0591]),
    ("LeftArm", [0.1785, 1.2484, -0.0589]),
    ("LeftForeArm", [0.4214, 1.2487, -0.0587]),
    ("LeftHand", [0.6342, 1.2485, -0.0598]),
    ("LeftHandThumb1", [0.6516, 1.2304, -0.0366]),
    ("LeftHandThumb2", [0.6804, 1.2158, -0.0197]),
    ("LeftHandThumb3", [0.7068, 1.2010, -0.0064]),
    ("LeftHandThumb4", [0.7281, 1.1876, 0.0062]),
    ("LeftHandIndex1", [0.7228, 1.2467, -0.0374]),
    ("LeftHandIndex2", [0.7519, 1.2473, -0.0372]),
    ("LeftHandIndex3", [0.7837, 1.2476, -0.0370]),
    ("LeftHandIndex4", [0.8089, 1.2470, -0.0368]),
    ("LeftHandMiddle1", [0.7274, 1.2499, -0.0591]),
    ("LeftHandMiddle2", [0.7636, 1.2487, -0.0579]),
    ("LeftHandMiddle3", [0.7858, 1.2486, -0.0571]),
    ("LeftHandMiddle4", [0.8169, 1.2487, -0.0560]),
    ("LeftHandRing1", [0.7251, 1.2498, -0.0802]),
    ("LeftHandRing2", [0.7556, 1.2487, -0.0816]),
    ("LeftHandRing3", [0.7759, 1.2489, -0.0825]),
    ("LeftHandRing4", [0.8026, 1.2500, -0.0838]),
    ("LeftHandPinky1", [0.7153, 1.2455, -0.0980]),
    ("LeftHandPinky2", [0.7443, 1.2471, -0.0989]),
    ("LeftHandPinky3", [0.7635, 1.2470, -0.0995]),
    ("LeftHandPinky4", [0.7820, 1.2454, -0.1001]),
    ("RightShoulder", [-0.0616, 1.2782, -0.0592]),
    ("RightArm", [-0.1776, 1.2484, -0.0594]),
    ("RightForeArm", [-0.4214, 1.2487, -0.0585]),
    ("RightHand", [-0.6341, 1.2485, -0.0597]),
    ("RightHandThumb1", [-0.6516, 1.2311, -0.0362]),
    ("RightHandThumb2", [-0.6805, 1.2170, -0.0188]),
    ("RightHandThumb3", [-0.7067, 1.2020, -0.0051]),
    ("RightHandThumb4", [-0.7281, 1.1910, 0.0080]),
    ("RightHandIndex1", [-0.7227, 1.2463, -0.0367]),
    ("RightHandIndex2", [-0.7517, 1.2465, -0.0358]),
    ("RightHandIndex3", [-0.7833, 1.2463, -0.0349]),
    ("RightHandIndex4", [-0.8087, 1.2484, -0.0341]),
    ("RightHandMiddle1", [-0.7267, 1.2492, -0.0591]),
    ("RightHandMiddle2", [-0.7630, 1.2487, -0.0594]),
    ("RightHandMiddle3", [-0.7856, 1.2484, -0.0596]),
    ("RightHandMiddle4", [-0.8160, 1.2500, -0.0598]),
    ("RightHandRing1", [-0.7242, 1.2494, -0.0782]),
    ("RightHandRing2", [-0.7553, 1.2482, -0.0778]),
    ("RightHandRing3", [-0.7753, 1.2492, -0.0775]),
    ("RightHandRing4", [-0.8008, 1.2476, -0.0771]),
    ("RightHandPinky1", [-0.7145, 1.2463, -0.0977]),
    ("RightHandPinky2", [-0.7429, 1.2460, -0.0982]),
    ("RightHandPinky3", [-0.7622, 1.2458, -0.0985]),
    ("RightHandPinky4", [-0.7840, 1.2454, -0.0989]),
    ("LeftUpLeg", [0.0897, 0.8372, 0.0034]),
    ("LeftLeg", [0.0854, 0.4582, -0.0026]),
    ("LeftFoot", [0.0872, 0.0740, -0.0473]),
    ("LeftToeBase", [0.0754, 0.0058, 0.0986]),
    ("LeftToe_End", [0.0709, 0.0040, 0.1590]),
    ("RightUpLeg", [-0.0897, 0.8372, 0.0057]),
    ("RightLeg", [-0.0854, 0.4582, 0.0049]),
    ("RightFoot", [-0.0873, 0.0734, -0.0451]),
    ("RightToeBase", [-0.0756, 0.0058, 0.0963]),
    ("RightToe_End", [-0.0711, 0.0040, 0.1559]),
];

/// Rest orientations of the 65 Mixamo bones of HUMOTO's character, in joint order, as unit
/// quaternions `[x, y, z, w]` in world axes (Y up, facing +Z): each bone's bind-pose frame
/// (Mixamo's convention: the bone's +Y axis points along the bone). Read from the same skin as
/// [`HUMOTO_REST_POSITIONS`] (inverse bind matrices, the `Armature` scale divided out; their
/// scale is 1 to 5e-7). The exports put a Mixamo motion in these frames so that it plays on a
/// Mixamo character by bone name (docs/CONVENTIONS.md, "Rest orientations").
pub const HUMOTO_REST_ORIENTATIONS: [(&str, [f32; 4]); 65] = [
    ("Hips", [0.000000, 0.000050, -0.000010, 1.000000]),
    ("Spine", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("Spine1", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("Spine2", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("Neck", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("Head", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("HeadTop_End", [-0.071499, 0.000000, 0.000000, 0.997441]),
    ("LeftShoulder", [0.513282, 0.404082, -0.594364, 0.469032]),
    ("LeftArm", [0.460760, 0.460714, -0.535843, 0.536950]),
    ("LeftForeArm", [0.461544, 0.459932, -0.535528, 0.537261]),
    ("LeftHand", [0.471418, 0.523207, -0.529782, 0.472600]),
    ("LeftHandThumb1", [0.719202, 0.274967, -0.427173, 0.473989]),
    ("LeftHandThumb2", [0.731767, 0.263304, -0.434460, 0.454350]),
    ("LeftHandThumb3", [0.739241, 0.256023, -0.438789, 0.442085]),
    ("LeftHandThumb4", [0.739241, 0.256023, -0.438789, 0.442085]),
    ("LeftHandIndex1", [0.494355, 0.501505, -0.495103, 0.508899]),
    ("LeftHandIndex2", [0.497584, 0.498344, -0.498285, 0.505742]),
    ("LeftHandIndex3", [0.505277, 0.490648, -0.505865, 0.498057]),
    ("LeftHandIndex4", [0.505277, 0.490649, -0.505864, 0.498057]),
    ("LeftHandMiddle1", [0.514814, 0.481071, -0.500826, 0.502703]),
    ("LeftHandMiddle2", [0.507884, 0.487881, -0.494195, 0.509703]),
    ("LeftHandMiddle3", [0.506111, 0.489595, -0.492497, 0.511464]),
    ("LeftHandMiddle4", [0.506112, 0.489595, -0.492497, 0.511464]),
    ("LeftHandRing1", [0.495342, 0.499886, -0.522675, 0.481208]),
    ("LeftHandRing2", [0.483085, 0.512871, -0.509940, 0.493512]),
    ("LeftHandRing3", [0.476701, 0.519383, -0.503305, 0.499681]),
    ("LeftHandRing4", [0.476701, 0.519383, -0.503305, 0.499681]),
    ("LeftHandPinky1", [0.476525, 0.519470, -0.496091, 0.506921]),
    ("LeftHandPinky2", [0.491166, 0.504718, -0.511093, 0.492748]),
    ("LeftHandPinky3", [0.511260, 0.482999, -0.531665, 0.471866]),
    ("LeftHandPinky4", [0.511260, 0.482999, -0.531665, 0.471867]),
    ("RightShoulder", [0.512581, -0.404637, 0.594968, 0.468555]),
    ("RightArm", [0.461158, -0.459686, 0.535500, 0.537831]),
    ("RightForeArm", [0.460684, -0.460161, 0.536267, 0.537065]),
    ("RightHand", [0.477217, -0.519800, 0.525903, 0.474867]),
    ("RightHandThumb1", [0.719044, -0.275137, 0.418972, 0.481392]),
    ("RightHandThumb2", [0.736991, -0.258853, 0.429224, 0.453439]),
    ("RightHandThumb3", [0.723397, -0.271311, 0.421458, 0.474825]),
    ("RightHandThumb4", [0.723397, -0.271311, 0.421459, 0.474825]),
    ("RightHandIndex1", [0.504419, -0.493195, 0.491443, 0.510690]),
    ("RightHandIndex2", [0.508254, -0.489477, 0.495146, 0.506874]),
    ("RightHandIndex3", [0.484939, -0.511254, 0.472627, 0.529223]),
    ("RightHandIndex4", [0.484939, -0.511254, 0.472627, 0.529223]),
    ("RightHandMiddle1", [0.500330, -0.497573, 0.506253, 0.495781]),
    ("RightHandMiddle2", [0.501295, -0.496586, 0.507221, 0.494806]),
    ("RightHandMiddle3", [0.483014, -0.514660, 0.488872, 0.512666]),
    ("RightHandMiddle4", [0.483014, -0.514659, 0.488873, 0.512666]),
    ("RightHandRing1", [0.511796, -0.486002, 0.506845, 0.494950]),
    ("RightHandRing2", [0.489986, -0.507397, 0.485426, 0.516550]),
    ("RightHandRing3", [0.517984, -0.479584, 0.512922, 0.488470]),
    ("RightHandRing4", [0.517984, -0.479584, 0.512922, 0.488470]),
    ("RightHandPinky1", [0.497365, -0.500540, 0.507717, 0.494279]),
    ("RightHandPinky2", [0.497752, -0.500140, 0.508111, 0.493888]),
    ("RightHandPinky3", [0.499559, -0.498274, 0.509941, 0.492061]),
    ("RightHandPinky4", [0.499559, -0.498278, 0.509938, 0.492060]),
    ("LeftUpLeg", [0.000094, -0.007900, 0.999953, 0.005598]),
    ("LeftLeg", [-0.000125, 0.035066, -0.999377, 0.003917]),
    ("LeftFoot", [-0.036263, 0.481894, 0.875278, 0.018776]),
    ("LeftToeBase", [-0.022465, 0.695728, 0.717345, 0.029568]),
    ("LeftToe_End", [-0.022465, 0.695728, 0.717345, 0.029568]),
    ("RightUpLeg", [-0.000044, 0.001039, -0.999984, 0.005578]),
    ("RightLeg", [-0.000112, -0.043298, 0.999054, 0.003942]),
    ("RightFoot", [-0.036721, -0.476317, -0.878289, 0.019544]),
    ("RightToeBase", [-0.022269, -0.695533, -0.717500, 0.030502]),
    ("RightToe_End", [-0.022267, -0.695533, -0.717500, 0.030503]),
];

/// The name of the mirror joint: left and right swapped (`left_`/`right_`, `Left`/`Right`).
fn mirror_name(name: &str) -> String {
    const PAIRS: [(&str, &str); 4] =
        [("left", "right"), ("right", "left"), ("Left", "Right"), ("Right", "Left")];
    for (from, to) in PAIRS {
        if let Some(position) = name.find(from) {
            return format!("{}{to}{}", &name[..position], &name[position + from.len()..]);
        }
    }
    name.to_string()
}

fn parents_from_i32(parents: &[i32]) -> Vec<Option<usize>> {
    parents.iter().map(|&p| usize::try_from(p).ok()).collect()
}

impl Skeleton {
    /// Builds and validates a skeleton: names are unique, parents come before children, the
    /// root is joint 0 (and the only root), offsets are finite, the left/right map (derived from
    /// the names) is an involution that respects the tree, and the groups are in range.
    pub fn new(
        kind: SkeletonKind,
        joint_names: Vec<String>,
        parents: Vec<Option<usize>>,
        rest_offsets: Vec<Vec3>,
        groups: JointGroups,
    ) -> Result<Self> {
        let count = joint_names.len();
        if count == 0 || parents.len() != count || rest_offsets.len() != count {
            return Err(ReprError::invalid(
                "skeleton",
                "equally many names, parents and rest offsets (at least one)",
                format!("{count} names, {} parents, {} offsets", parents.len(), rest_offsets.len()),
            ));
        }
        for (joint, parent) in parents.iter().enumerate() {
            let valid = match parent {
                None => joint == 0,
                Some(p) => *p < joint,
            };
            if !valid {
                return Err(ReprError::invalid(
                    format!("parent of joint {joint} ({})", joint_names[joint]),
                    "the root at joint 0 only and every parent before its child",
                    format!("{parent:?}"),
                ));
            }
        }
        if let Some(index) = rest_offsets.iter().position(|v| !v.is_finite()) {
            return Err(ReprError::NonFinite {
                source_name: "skeleton".into(),
                what: "rest offset".into(),
                index,
            });
        }
        let index_of = |name: &str| joint_names.iter().position(|n| n == name);
        let mut symmetry = Vec::with_capacity(count);
        for (joint, name) in joint_names.iter().enumerate() {
            if index_of(name) != Some(joint) {
                return Err(ReprError::invalid("joint names", "unique names", name));
            }
            let mirror = index_of(&mirror_name(name)).ok_or_else(|| {
                ReprError::invalid(
                    format!("joint {name}"),
                    format!("a mirror joint named {}", mirror_name(name)),
                    "none",
                )
            })?;
            symmetry.push(mirror);
        }
        for joint in 0..count {
            let mirrored_parent = parents[joint].map(|p| symmetry[p]);
            if parents[symmetry[joint]] != mirrored_parent {
                return Err(ReprError::invalid(
                    format!("symmetry of joint {}", joint_names[joint]),
                    "the mirror of a joint's parent to be the parent of its mirror",
                    format!("{:?}", parents[symmetry[joint]]),
                ));
            }
        }
        let in_range = |&j: &usize| j < count;
        let all = [
            &groups.left_hand,
            &groups.right_hand,
            &groups.left_fingertips,
            &groups.right_fingertips,
            &groups.left_foot,
            &groups.right_foot,
        ];
        if !(in_range(&groups.left_wrist)
            && in_range(&groups.right_wrist)
            && all.iter().all(|g| !g.is_empty() && g.iter().all(in_range)))
        {
            return Err(ReprError::invalid(
                "joint groups",
                format!("non-empty groups of joints below {count}"),
                format!("{groups:?}"),
            ));
        }
        Ok(Self { kind, joint_names, parents, rest_offsets, symmetry, groups })
    }

    /// The default SMPL-X skeleton with 52 joints: the public SMPL body proportions and our
    /// finger design, pelvis 0.975 m above the floor, made exactly left/right symmetric (the
    /// public figures differ by up to 1 cm between sides; averaging them makes mirroring an exact
    /// augmentation).
    pub fn smplx() -> Self {
        let mut names: Vec<String> = SMPLX52_BODY_NAMES.map(String::from).to_vec();
        let mut offsets = vec![Vec3::new(0.0, SMPLX_PELVIS_HEIGHT, 0.0)];
        offsets.extend(SMPL_BODY_OFFSETS.iter().map(|&o| Vec3::from_array(o)));
        for (side, sign) in [("left", 1.0f32), ("right", -1.0)] {
            for (finger, phalanges) in SMPLX_FINGERS.iter().zip(LEFT_FINGER_OFFSETS) {
                for (k, offset) in phalanges.iter().enumerate() {
                    names.push(format!("{side}_{finger}{}", k + 1));
                    offsets.push(Vec3::new(sign * offset[0], offset[1], offset[2]));
                }
            }
        }
        let hand = |wrist: usize, first: usize| -> Vec<usize> {
            std::iter::once(wrist).chain(first..first + 15).collect()
        };
        let tips = |first: usize| (0..5).map(|f| first + 3 * f + 2).collect::<Vec<_>>();
        let groups = JointGroups {
            left_wrist: 20,
            right_wrist: 21,
            left_hand: hand(20, 22),
            right_hand: hand(21, 37),
            left_fingertips: tips(22),
            right_fingertips: tips(37),
            left_foot: vec![7, 10],
            right_foot: vec![8, 11],
        };
        let skeleton = Self::new(
            SkeletonKind::Smplx52,
            names,
            parents_from_i32(&SMPLX52_PARENTS),
            offsets,
            groups,
        )
        .expect("the built-in SMPL-X skeleton is valid");
        let symmetric = skeleton.symmetrised_offsets();
        skeleton.with_rest_offsets(symmetric).expect("symmetrising keeps the skeleton valid")
    }

    /// The Mixamo rig of HUMOTO with 65 joints (names without the `mixamorig:` prefix): HUMOTO's
    /// character ([`HUMOTO_REST_POSITIONS`]) made exactly left/right symmetric like
    /// [`Skeleton::smplx`] (the published bind pose differs by up to 2.5 mm between sides), so
    /// that mirroring is an exact augmentation.
    pub fn mixamo() -> Self {
        let skeleton = Self::humoto_character();
        let symmetric = skeleton.symmetrised_offsets();
        skeleton.with_rest_offsets(symmetric).expect("symmetrising keeps the skeleton valid")
    }

    /// HUMOTO's character exactly as published ([`HUMOTO_REST_POSITIONS`], not symmetrised): the
    /// rest skeleton of every HUMOTO sequence.
    pub fn humoto_character() -> Self {
        let names = mixamo_names();
        let parents = parents_from_i32(&MIXAMO65_PARENTS);
        let index = |name: &str| names.iter().position(|n| n == name).expect("known Mixamo bone");
        let mut rest = vec![Vec3::ZERO; names.len()];
        for (name, position) in HUMOTO_REST_POSITIONS {
            rest[index(name)] = Vec3::from_array(position);
        }
        let offsets = (0..names.len())
            .map(|j| match parents[j] {
                Some(p) => rest[j] - rest[p],
                None => rest[j],
            })
            .collect();
        let side = |s: &str| {
            let hand = index(&format!("{s}Hand"));
            let fingers = ["Thumb", "Index", "Middle", "Ring", "Pinky"];
            let mut all = vec![hand];
            all.extend(
                fingers
                    .iter()
                    .flat_map(|f| (1..=4).map(move |k| (f, k)))
                    .map(|(f, k)| index(&format!("{s}Hand{f}{k}"))),
            );
            let tips = fingers.iter().map(|f| index(&format!("{s}Hand{f}4"))).collect();
            let foot = vec![index(&format!("{s}Foot")), index(&format!("{s}ToeBase"))];
            (hand, all, tips, foot)
        };
        let (left_wrist, left_hand, left_fingertips, left_foot) = side("Left");
        let (right_wrist, right_hand, right_fingertips, right_foot) = side("Right");
        let groups = JointGroups {
            left_wrist,
            right_wrist,
            left_hand,
            right_hand,
            left_fingertips,
            right_fingertips,
            left_foot,
            right_foot,
        };
        Self::new(SkeletonKind::Mixamo65, names, parents, offsets, groups)
            .expect("the built-in Mixamo skeleton is valid")
    }

    /// Rest offsets made exactly symmetric: each joint's offset is averaged with the reflection
    /// (`x -> -x`) of its mirror joint's, and joints on the midline get `x = 0`.
    pub fn symmetrised_offsets(&self) -> Vec<Vec3> {
        let reflect = |v: Vec3| Vec3::new(-v.x, v.y, v.z);
        self.rest_offsets
            .iter()
            .zip(&self.symmetry)
            .map(|(offset, &mirror)| (*offset + reflect(self.rest_offsets[mirror])) * 0.5)
            .collect()
    }

    /// Rest offsets of the mirror image of this body (`x -> -x`): each joint takes the
    /// reflection of its mirror joint's offset. FK of mirrored rotations on them gives the
    /// mirrored joints exactly, symmetric body or not.
    pub fn mirrored_offsets(&self) -> Vec<Vec3> {
        self.mirror_offsets(&self.rest_offsets)
    }

    /// Other rest offsets of this topology (a sequence's own body) mirrored the same way as
    /// [`Skeleton::mirrored_offsets`].
    pub fn mirror_offsets(&self, rest_offsets: &[Vec3]) -> Vec<Vec3> {
        let reflect = |v: Vec3| Vec3::new(-v.x, v.y, v.z);
        self.symmetry.iter().map(|&mirror| reflect(rest_offsets[mirror])).collect()
    }

    /// The mirror image of this body (see [`Skeleton::mirrored_offsets`]).
    pub fn mirrored(&self) -> Self {
        Self { rest_offsets: self.mirrored_offsets(), ..self.clone() }
    }

    /// The built-in skeleton of a kind.
    pub fn builtin(kind: SkeletonKind) -> Self {
        match kind {
            SkeletonKind::Smplx52 => Self::smplx(),
            SkeletonKind::Mixamo65 => Self::mixamo(),
        }
    }

    /// The same topology, names and groups with other rest offsets (a user's body shape).
    pub fn with_rest_offsets(&self, rest_offsets: Vec<Vec3>) -> Result<Self> {
        Self::new(
            self.kind,
            self.joint_names.clone(),
            self.parents.clone(),
            rest_offsets,
            self.groups.clone(),
        )
    }

    /// Which rig this is.
    pub fn kind(&self) -> SkeletonKind {
        self.kind
    }

    /// Number of joints `J`.
    pub fn joint_count(&self) -> usize {
        self.joint_names.len()
    }

    /// Joint names in order.
    pub fn joint_names(&self) -> &[String] {
        &self.joint_names
    }

    /// The index of a joint by name (a Mixamo name may carry the `mixamorig:` prefix).
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        let name = name.strip_prefix(MIXAMO_PREFIX).unwrap_or(name);
        self.joint_names.iter().position(|n| n == name)
    }

    /// Joint names as the rig's own files spell them: `mixamorig:Hips` and so on for Mixamo
    /// ([`MIXAMO_PREFIX`]), the SMPL-X names unchanged. The exports use these.
    pub fn rig_joint_names(&self) -> Vec<String> {
        let prefix = match self.kind {
            SkeletonKind::Mixamo65 => MIXAMO_PREFIX,
            SkeletonKind::Smplx52 => "",
        };
        self.joint_names.iter().map(|name| format!("{prefix}{name}")).collect()
    }

    /// Each joint's rest frame in world axes as its rig defines it: Mixamo's bone orientations
    /// ([`HUMOTO_REST_ORIENTATIONS`]), identity for SMPL-X (whose rest frames are the world's).
    /// The local rotations of a motion stay relative to the identity rest pose; an export that
    /// keeps a rig's frames turns them into `B_parent^T R B_joint`.
    pub fn rest_orientations(&self) -> Vec<Quat> {
        match self.kind {
            SkeletonKind::Smplx52 => vec![Quat::IDENTITY; self.joint_count()],
            SkeletonKind::Mixamo65 => {
                let mut orientations = vec![Quat::IDENTITY; self.joint_count()];
                for (name, [x, y, z, w]) in HUMOTO_REST_ORIENTATIONS {
                    if let Some(joint) = self.joint_index(name) {
                        orientations[joint] = Quat::from_xyzw(x, y, z, w).normalize();
                    }
                }
                orientations
            }
        }
    }

    /// Parent of each joint, `None` for the root.
    pub fn parents(&self) -> &[Option<usize>] {
        &self.parents
    }

    /// Offset of each joint from its parent in the rest pose (the root's is its position).
    pub fn rest_offsets(&self) -> &[Vec3] {
        &self.rest_offsets
    }

    /// Rest positions of all joints (forward kinematics of the identity pose).
    pub fn rest_positions(&self) -> Vec<Vec3> {
        let mut positions: Vec<Vec3> = Vec::with_capacity(self.joint_count());
        for (joint, offset) in self.rest_offsets.iter().enumerate() {
            let base = self.parents[joint].map_or(Vec3::ZERO, |p| positions[p]);
            positions.push(base + *offset);
        }
        positions
    }

    /// For each joint, its mirror across the sagittal plane (itself on the midline).
    pub fn symmetry(&self) -> &[usize] {
        &self.symmetry
    }

    /// Named joint groups.
    pub fn groups(&self) -> &JointGroups {
        &self.groups
    }

    /// Children lists, derived from the parents.
    pub fn children(&self) -> Vec<Vec<usize>> {
        let mut children = vec![Vec::new(); self.joint_count()];
        for (joint, parent) in self.parents.iter().enumerate() {
            if let Some(p) = parent {
                children[*p].push(joint);
            }
        }
        children
    }

    /// Joints grouped by depth in the tree (root alone at depth 0). Joints of one depth only
    /// depend on joints of smaller depth, which the batched FK uses.
    pub fn depth_levels(&self) -> Vec<Vec<usize>> {
        let mut depth = vec![0usize; self.joint_count()];
        let mut levels: Vec<Vec<usize>> = Vec::new();
        for (joint, parent) in self.parents.iter().enumerate() {
            depth[joint] = parent.map_or(0, |p| depth[p] + 1);
            if levels.len() <= depth[joint] {
                levels.push(Vec::new());
            }
            levels[depth[joint]].push(joint);
        }
        levels
    }

    /// The 52-joint skeleton of an SMPL-X body's 55 rest joints (`J_regressor`'s order): jaw
    /// and eyes dropped, offsets child minus parent, the root's its own position; the names and
    /// groups of [`Skeleton::smplx`].
    ///
    /// # Shapes
    /// - `joints55`: `[55]`
    pub fn from_smplx_joints(joints55: &[Vec3]) -> Result<Self> {
        if joints55.len() != 55 {
            return Err(ReprError::invalid("SMPL-X rest joints", "55 joints", joints55.len()));
        }
        let to55 = smplx52_to_55();
        let parents = parents_from_i32(&SMPLX52_PARENTS);
        let offsets = (0..52)
            .map(|j| {
                let own = joints55[to55[j]];
                match parents[j] {
                    Some(p) => own - joints55[to55[p]],
                    None => own,
                }
            })
            .collect();
        Self::smplx().with_rest_offsets(offsets)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_skeletons_have_the_published_topology() {
        let smplx = Skeleton::smplx();
        assert_eq!(smplx.joint_count(), 52);
        assert_eq!(smplx.joint_names()[20], "left_wrist");
        assert_eq!(smplx.joint_names()[22], "left_index1");
        assert_eq!(smplx.joint_names()[36], "left_thumb3");
        assert_eq!(smplx.joint_names()[51], "right_thumb3");
        // 52 parents are the 55 parents re-indexed.
        let to55 = smplx52_to_55();
        let from55 = |i: i32| -> i32 {
            let i = i as usize;
            (if i < 22 { i } else { i - 3 }) as i32
        };
        for j in 1..52 {
            assert_eq!(SMPLX52_PARENTS[j], from55(SMPLX55_PARENTS[to55[j]]), "joint {j}");
        }
        let mixamo = Skeleton::mixamo();
        assert_eq!(mixamo.joint_count(), 65);
        assert_eq!(mixamo.joint_names()[10], "LeftHand");
        assert_eq!(mixamo.joint_names()[34], "RightHand");
        assert_eq!(mixamo.joint_index("mixamorig:LeftHandPinky4"), Some(30));
        assert_eq!(mixamo.groups().left_wrist, 10);
    }

    #[test]
    fn rest_poses_have_human_proportions() {
        for skeleton in [Skeleton::smplx(), Skeleton::mixamo()] {
            let rest = skeleton.rest_positions();
            let lowest = rest.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
            let highest = rest.iter().map(|p| p.y).fold(f32::NEG_INFINITY, f32::max);
            assert!((0.0..0.05).contains(&lowest), "{:?}: feet at {lowest}", skeleton.kind());
            assert!((1.45..1.8).contains(&highest), "{:?}: head at {highest}", skeleton.kind());
            let g = skeleton.groups();
            // Left is +X (facing +Z), arms span about 1.5 m wrist to wrist in the T-pose.
            let span = rest[g.left_wrist].x - rest[g.right_wrist].x;
            assert!((1.1..1.6).contains(&span), "wrist span {span}");
            // Fingertips 12-20 cm from the wrist, thumb included at 8-12 cm.
            for (&tip, wrist) in g.left_fingertips.iter().zip(std::iter::repeat(g.left_wrist)) {
                let reach = rest[tip].distance(rest[wrist]);
                assert!((0.07..0.2).contains(&reach), "{}: {reach}", skeleton.joint_names()[tip]);
            }
            // Exactly symmetric: mirrored joints have mirrored rest positions.
            for (j, &m) in skeleton.symmetry().iter().enumerate() {
                let mirrored = Vec3::new(-rest[m].x, rest[m].y, rest[m].z);
                assert!(rest[j].abs_diff_eq(mirrored, 1e-5), "{}", skeleton.joint_names()[j]);
                assert_eq!(skeleton.symmetry()[m], j);
            }
        }
    }

    #[test]
    fn invalid_skeletons_are_refused() {
        let s = Skeleton::smplx();
        let mut offsets = s.rest_offsets().to_vec();
        offsets[3].x = f32::NAN;
        assert!(matches!(s.with_rest_offsets(offsets), Err(ReprError::NonFinite { .. })));
        assert!(s.with_rest_offsets(vec![Vec3::ZERO; 3]).is_err());
        let mut parents = s.parents().to_vec();
        parents[5] = Some(7);
        let bad = Skeleton::new(
            s.kind(),
            s.joint_names().to_vec(),
            parents,
            s.rest_offsets().to_vec(),
            s.groups().clone(),
        );
        assert!(bad.is_err());
    }

    #[test]
    fn depth_levels_cover_every_joint_once() {
        let s = Skeleton::smplx();
        let levels = s.depth_levels();
        let mut all: Vec<usize> = levels.concat();
        all.sort_unstable();
        assert_eq!(all, (0..52).collect::<Vec<_>>());
        for (depth, level) in levels.iter().enumerate().skip(1) {
            for &j in level {
                let p = s.parents()[j].unwrap();
                assert!(levels[depth - 1].contains(&p));
            }
        }
    }
}
