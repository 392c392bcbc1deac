//! The default character on the built-in SMPL-X skeleton and how it is posed: torso lean,
//! analytic two-bone arm IK to a wrist target, wrist orientation, finger curls that touch an
//! object's surface; and its standing pose, the first frame of every generation.

use glam::{Mat3, Quat, Vec3};

use dex2hoi_repr::fk::forward_kinematics_frame;
use dex2hoi_repr::rotation::axis_angle_to_matrix;
use dex2hoi_repr::{MeshQuery, Skeleton};

/// Height of the default character's pelvis.
pub const PELVIS_HEIGHT: f32 = 0.975;

/// A hand of the character.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Hand {
    /// The left hand (the character's left, +X in its own frame).
    Left,
    /// The right hand.
    Right,
}

impl Hand {
    /// Both hands, left first.
    pub const BOTH: [Hand; 2] = [Hand::Left, Hand::Right];

    /// `+1` for left, `-1` for right: the sign of X on the hand's side.
    pub fn side(self) -> f32 {
        match self {
            Hand::Left => 1.0,
            Hand::Right => -1.0,
        }
    }

    /// The word used in texts.
    pub fn word(self) -> &'static str {
        match self {
            Hand::Left => "left",
            Hand::Right => "right",
        }
    }

    /// The other hand.
    pub fn other(self) -> Hand {
        match self {
            Hand::Left => Hand::Right,
            Hand::Right => Hand::Left,
        }
    }

    /// 0 for left, 1 for right.
    pub fn index(self) -> usize {
        match self {
            Hand::Left => 0,
            Hand::Right => 1,
        }
    }
}

/// SMPL-X joints the poser drives.
mod joint {
    pub const SPINE: [usize; 3] = [3, 6, 9];
    pub const NECK: usize = 12;
    pub const HEAD: usize = 15;
    pub const COLLAR: [usize; 2] = [13, 14];
    pub const SHOULDER: [usize; 2] = [16, 17];
    pub const ELBOW: [usize; 2] = [18, 19];
    pub const WRIST: [usize; 2] = [20, 21];
    /// First finger joint of each hand; fingers follow in index, middle, pinky, ring, thumb
    /// order, three joints each.
    pub const FIRST_FINGER: [usize; 2] = [22, 37];
}

/// Curl of every finger when the hand is relaxed (radians per joint).
pub const OPEN_CURL: f32 = 0.15;

/// The largest curl per joint the grasp search tries.
const MAX_CURL: f32 = 1.5;

/// Where a wrist should be and how the fingers are curled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HandPose {
    /// World wrist position.
    pub position: Vec3,
    /// World wrist rotation.
    pub rotation: Mat3,
    /// Curl per finger (index, middle, pinky, ring, thumb), radians per joint.
    pub curls: [f32; 5],
}

impl HandPose {
    /// Interpolates position, rotation (slerp) and curls.
    pub fn lerp(&self, other: &HandPose, s: f32) -> HandPose {
        let a = Quat::from_mat3(&self.rotation);
        let b = Quat::from_mat3(&other.rotation);
        HandPose {
            position: self.position.lerp(other.position, s),
            rotation: Mat3::from_quat(a.slerp(b, s)),
            curls: std::array::from_fn(|k| self.curls[k] + (other.curls[k] - self.curls[k]) * s),
        }
    }
}

/// The wrist rotation whose fingers point along `fingers` and whose palm faces `-outward`
/// (toward the object whose surface normal at the grasp is `outward`).
pub fn wrist_rotation(hand: Hand, fingers: Vec3, outward: Vec3) -> Mat3 {
    let y = outward.normalize();
    let finger_dir = (fingers - y * fingers.dot(y)).normalize();
    // SMPL-X rest hands: fingers along +X (left) or -X (right), palm facing -Y.
    let x = finger_dir * hand.side();
    Mat3::from_cols(x, y, x.cross(y))
}

/// A pose-able character: the skeleton, where it stands, and the arm geometry.
#[derive(Debug, Clone)]
pub struct Poser {
    skeleton: Skeleton,
    root_position: Vec3,
    upper_arm: f32,
    forearm: f32,
    /// Curl axis of each finger in the hand frame, per hand.
    finger_axes: [[Vec3; 5]; 2],
    /// Shoulder positions for the lean grid `0, LEAN_STEP, ...`.
    shoulders_by_lean: Vec<[Vec3; 2]>,
}

/// Lean grid step (radians) and size.
const LEAN_STEP: f32 = 0.02;
const LEAN_STEPS: usize = 41;

impl Poser {
    /// A character on the built-in SMPL-X skeleton with its pelvis at `root_position`, facing +Z.
    pub fn new(root_position: Vec3) -> Self {
        let skeleton = Skeleton::smplx();
        let offsets = skeleton.rest_offsets();
        let upper_arm = offsets[joint::ELBOW[0]].length();
        let forearm = offsets[joint::WRIST[0]].length();
        let finger_axes = [0, 1].map(|h| {
            std::array::from_fn(|f| {
                let d = offsets[joint::FIRST_FINGER[h] + 3 * f + 1].normalize();
                Vec3::new(d.z, 0.0, -d.x).normalize()
            })
        });
        let mut poser = Self {
            skeleton,
            root_position,
            upper_arm,
            forearm,
            finger_axes,
            shoulders_by_lean: Vec::new(),
        };
        poser.shoulders_by_lean = (0..LEAN_STEPS)
            .map(|k| {
                let positions = poser.body_positions(k as f32 * LEAN_STEP, 0.0);
                [positions[joint::SHOULDER[0]], positions[joint::SHOULDER[1]]]
            })
            .collect();
        poser
    }

    /// The skeleton.
    pub fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }

    /// The length of the arm from shoulder to wrist.
    pub fn arm_length(&self) -> f32 {
        self.upper_arm + self.forearm
    }

    fn body_locals(&self, lean: f32, sway: f32) -> Vec<Mat3> {
        let mut local = vec![Mat3::IDENTITY; self.skeleton.joint_count()];
        for (k, spine) in joint::SPINE.iter().enumerate() {
            let side = if k == 1 { sway } else { 0.0 };
            local[*spine] = axis_angle_to_matrix(Vec3::new(lean / 3.0, side, sway * 0.5));
        }
        local[joint::NECK] = axis_angle_to_matrix(Vec3::X * (-lean * 0.3));
        local[joint::HEAD] = axis_angle_to_matrix(Vec3::new(0.1 + sway, sway * 2.0, 0.0));
        local
    }

    /// Global positions and rotations of a pose.
    fn global(&self, local: &[Mat3]) -> (Vec<Vec3>, Vec<Mat3>) {
        let joints = self.skeleton.joint_count();
        let mut positions = vec![Vec3::ZERO; joints];
        let mut rotations = vec![Mat3::IDENTITY; joints];
        forward_kinematics_frame(
            &self.skeleton,
            local,
            self.root_position,
            &mut positions,
            &mut rotations,
        );
        (positions, rotations)
    }

    fn body_positions(&self, lean: f32, sway: f32) -> Vec<Vec3> {
        self.global(&self.body_locals(lean, sway)).0
    }

    /// The smallest lean (radians) that brings `target` within 95% of the arm's length of the
    /// hand's shoulder; the largest lean of the grid when none does.
    pub fn lean_to_reach(&self, hand: Hand, target: Vec3) -> f32 {
        let reach = 0.95 * self.arm_length();
        self.shoulders_by_lean
            .iter()
            .position(|s| s[hand.index()].distance(target) <= reach)
            .unwrap_or(LEAN_STEPS - 1) as f32
            * LEAN_STEP
    }

    /// Whether `target` is reachable at the largest lean.
    pub fn reachable(&self, hand: Hand, target: Vec3) -> bool {
        let reach = 0.95 * self.arm_length();
        self.shoulders_by_lean.last().is_some_and(|s| s[hand.index()].distance(target) <= reach)
    }

    /// A relaxed hanging hand beside the hip.
    pub fn idle_hand(&self, hand: Hand) -> HandPose {
        let shoulder = self.shoulders_by_lean[0][hand.index()];
        let position = shoulder + Vec3::new(hand.side() * 0.03, -0.49, 0.06);
        // Fingers down, palm toward the thigh.
        let rotation = wrist_rotation(hand, -Vec3::Y, Vec3::X * hand.side());
        HandPose { position, rotation, curls: [OPEN_CURL; 5] }
    }

    /// Local rotations of the fingers of one hand for the given curls.
    fn finger_locals(&self, hand: Hand, curls: &[f32; 5]) -> [Mat3; 5] {
        std::array::from_fn(|f| axis_angle_to_matrix(self.finger_axes[hand.index()][f] * curls[f]))
    }

    /// World positions of one finger's three joints for a wrist pose and a curl.
    fn finger_joints(
        &self,
        hand: Hand,
        finger: usize,
        wrist: Vec3,
        rotation: Mat3,
        curl: f32,
    ) -> [Vec3; 3] {
        let offsets = self.skeleton.rest_offsets();
        let bend = axis_angle_to_matrix(self.finger_axes[hand.index()][finger] * curl);
        let first = joint::FIRST_FINGER[hand.index()] + 3 * finger;
        let mut global = rotation;
        let mut position = wrist;
        let mut out = [Vec3::ZERO; 3];
        for (k, slot) in out.iter_mut().enumerate() {
            position += global * offsets[first + k];
            global *= bend;
            *slot = position;
        }
        out
    }

    /// Curls each finger until one of its joints is within `touch` of the surface of an object
    /// (its mesh query and its pose), without any joint going deeper than 5 mm inside; a finger
    /// that cannot reach keeps the curl of its closest approach.
    pub fn grasp_curls(
        &self,
        hand: Hand,
        wrist: Vec3,
        rotation: Mat3,
        object: &MeshQuery,
        object_rotation: Mat3,
        object_position: Vec3,
        touch: f32,
    ) -> [f32; 5] {
        let to_object = object_rotation.transpose();
        let distance = |p: Vec3| object.signed_distance(to_object * (p - object_position));
        std::array::from_fn(|finger| {
            let mut best = (f32::INFINITY, OPEN_CURL);
            let mut curl = OPEN_CURL;
            while curl <= MAX_CURL {
                let joints = self.finger_joints(hand, finger, wrist, rotation, curl);
                let nearest = joints.iter().map(|p| distance(*p)).fold(f32::INFINITY, f32::min);
                if nearest < -0.005 {
                    break;
                }
                if nearest < best.0 {
                    best = (nearest, curl);
                }
                if nearest <= touch {
                    return curl;
                }
                curl += 0.03;
            }
            best.1
        })
    }

    /// Local rotations of the whole body for a lean, an idle sway and both hands' targets.
    pub fn pose(&self, lean: f32, sway: f32, hands: &[HandPose; 2]) -> Vec<Mat3> {
        let mut local = self.body_locals(lean, sway);
        let (positions, rotations) = self.global(&local);
        let offsets = self.skeleton.rest_offsets();
        for hand in Hand::BOTH {
            let h = hand.index();
            let target = hands[h];
            let shoulder = positions[joint::SHOULDER[h]];
            let collar_rotation = rotations[joint::COLLAR[h]];
            let (a, b) = (self.upper_arm, self.forearm);
            let to_target = target.position - shoulder;
            let distance = to_target.length().clamp((a - b).abs() + 1e-4, (a + b) * 0.9999);
            let u = to_target.normalize();
            // The elbow bends down, out and back.
            let pole = Vec3::new(hand.side() * 0.5, -1.0, -0.4);
            let v = (pole - u * pole.dot(u)).normalize_or(Vec3::NEG_Y);
            let cos_alpha =
                ((a * a + distance * distance - b * b) / (2.0 * a * distance)).clamp(-1.0, 1.0);
            let elbow = shoulder + (u * cos_alpha + v * (1.0 - cos_alpha * cos_alpha).sqrt()) * a;
            let wrist = shoulder + u * distance;
            let shoulder_global =
                swing(collar_rotation * offsets[joint::ELBOW[h]], elbow - shoulder)
                    * collar_rotation;
            let elbow_global =
                swing(shoulder_global * offsets[joint::WRIST[h]], wrist - elbow) * shoulder_global;
            local[joint::SHOULDER[h]] = collar_rotation.transpose() * shoulder_global;
            local[joint::ELBOW[h]] = shoulder_global.transpose() * elbow_global;
            local[joint::WRIST[h]] = elbow_global.transpose() * target.rotation;
            let fingers = self.finger_locals(hand, &target.curls);
            for (f, rotation) in fingers.iter().enumerate() {
                for k in 0..3 {
                    local[joint::FIRST_FINGER[h] + 3 * f + k] = *rotation;
                }
            }
        }
        local
    }
}

/// The smallest rotation taking direction `from` to direction `to`.
pub fn swing(from: Vec3, to: Vec3) -> Mat3 {
    Mat3::from_quat(Quat::from_rotation_arc(from.normalize(), to.normalize()))
}
