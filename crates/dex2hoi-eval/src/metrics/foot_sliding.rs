//! Foot sliding (MANN's weighted foot displacement; docs/CONVENTIONS.md, "Physical metrics").

use dex2hoi_repr::Skeleton;
use glam::Vec3;

use crate::error::{EvalError, Result};

use super::sample::joint_frames;

/// Height under which an ankle joint counts as on the ground for [`foot_sliding`]: 8 cm.
pub const ANKLE_HEIGHT_M: f32 = 0.08;
/// Height under which a toe joint counts as on the ground for [`foot_sliding`]: 4 cm.
pub const TOE_HEIGHT_M: f32 = 0.04;

/// Foot sliding in mm per frame (Zhang et al. 2018, MANN; docs/CONVENTIONS.md, "Physical metrics"). The foot
/// joints are the first (ankle) and the last (toe) joint of the skeleton groups `left_foot`
/// and `right_foot` (one joint if a group has only one). For each foot joint and each pair of
/// consecutive frames, with `h` the joint's mean height over the two frames and `H` its
/// threshold ([`ANKLE_HEIGHT_M`] = 0.08 m, [`TOE_HEIGHT_M`] = 0.04 m): when `h < H` the
/// horizontal (XZ) displacement `s` counts with weight `2 - 2^(h/H)` (1 on the floor, 0 at the
/// threshold, up to 2 below the floor). The result is the weighted displacement averaged over
/// all foot joints and frame pairs, in mm.
///
/// # Shapes
/// - `joints`: `[T, J, 3]`, `T >= 2`, metres, Y up, floor at `y = 0`.
///
/// # Errors
/// Fewer than two frames, a length that does not match the skeleton, non-finite positions, a
/// skeleton without foot joints.
pub fn foot_sliding(joints: &[f32], skeleton: &Skeleton) -> Result<f64> {
    let joint_count = skeleton.joint_count();
    let frames = joint_frames(joints, joint_count, "joint positions for foot sliding")?;
    if frames < 2 {
        return Err(EvalError::invalid(
            "joint positions for foot sliding",
            "at least 2 frames",
            frames,
        ));
    }
    let groups = skeleton.groups();
    let mut feet: Vec<(usize, f32)> = Vec::new();
    for foot in [&groups.left_foot, &groups.right_foot] {
        match foot.as_slice() {
            [] => {
                return Err(EvalError::invalid(
                    "skeleton foot groups",
                    "an ankle (and a toe) joint per foot",
                    "an empty foot group",
                ));
            }
            [ankle] => feet.push((*ankle, ANKLE_HEIGHT_M)),
            [ankle, .., toe] => {
                feet.push((*ankle, ANKLE_HEIGHT_M));
                feet.push((*toe, TOE_HEIGHT_M));
            }
        }
    }
    let position = |t: usize, j: usize| {
        let base = (t * joint_count + j) * 3;
        Vec3::from_slice(&joints[base..base + 3])
    };
    let mut total = 0.0f64;
    for t in 0..frames - 1 {
        for &(joint, threshold) in &feet {
            let (a, b) = (position(t, joint), position(t + 1, joint));
            let height = 0.5 * (a.y + b.y);
            if height < threshold {
                let weight = 2.0 - 2f64.powf(f64::from(height / threshold));
                let step = f64::from((b.x - a.x).hypot(b.z - a.z));
                total += weight * step;
            }
        }
    }
    Ok(total * 1000.0 / ((frames - 1) * feet.len()) as f64)
}
