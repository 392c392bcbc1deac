//! Encode/decode of the hand-relative object representation (Eq. 2-4) and the mixture targets.

mod common;

use common::*;
use glam::Vec3;
use proptest::prelude::*;

use dex2hoi_repr::object_repr::{
    HandRelativeObject, MixtureTargetConfig, ObjectPose, REST_HEIGHT_M, WristPose, Wrists,
    mixture_targets, mixture_targets_at_rest, resting_frames, softmax3,
};
use dex2hoi_repr::rotation::axis_angle_to_matrix;

fn vec3(range: f32) -> impl Strategy<Value = Vec3> {
    (-range..range, -range..range, -range..range).prop_map(|(x, y, z)| Vec3::new(x, y, z))
}

fn wrist() -> impl Strategy<Value = WristPose> {
    (vec3(1.5), vec3(3.0))
        .prop_map(|(position, aa)| WristPose { position, rotation: axis_angle_to_matrix(aa) })
}

proptest! {
    #[test]
    fn decode_of_encode_is_the_pose_for_any_mixture(
        left in wrist(), right in wrist(), position in vec3(2.0), aa in vec3(3.0),
        logits in proptest::array::uniform3(-8.0f32..8.0)
    ) {
        let wrists = Wrists { left, right };
        let object = ObjectPose { rotation: axis_angle_to_matrix(aa), position };
        let encoded = HandRelativeObject::encode(object, wrists, logits);
        prop_assert!(encoded.decode_position(wrists).abs_diff_eq(position, 2e-5));
        prop_assert!(encoded.decode_rotation().abs_diff_eq(object.rotation, 1e-5));
        // The 18 numbers round-trip exactly.
        let back = HandRelativeObject::from_slice(&encoded.to_array()).unwrap();
        prop_assert_eq!(back, encoded);
        let weights = encoded.mixture_weights();
        prop_assert!((weights.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn offsets_are_positions_in_the_wrist_frame(left in wrist(), right in wrist(), position in vec3(2.0)) {
        let wrists = Wrists { left, right };
        let object = ObjectPose { rotation: glam::Mat3::IDENTITY, position };
        let e = HandRelativeObject::encode(object, wrists, [0.0; 3]);
        prop_assert!((e.left_offset.length() - position.distance(left.position)).abs() < 1e-4);
        prop_assert!((left.position + left.rotation * e.left_offset).abs_diff_eq(position, 2e-5));
        prop_assert!((right.position + right.rotation * e.right_offset).abs_diff_eq(position, 2e-5));
    }
}

#[test]
fn a_wrong_length_is_an_error() {
    assert!(HandRelativeObject::from_slice(&[0.0; 17]).is_err());
}

#[test]
fn mixture_targets_follow_the_rule() {
    let config = MixtureTargetConfig { smoothing_radius: 0, ..Default::default() };
    let near = 0.01;
    let far = 0.2;
    let targets =
        mixture_targets(&[near, far, near, far, -0.01], &[far, near, near, far, f32::NAN], &config)
            .unwrap();
    let expected =
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]];
    for (logits, want) in targets.iter().zip(expected) {
        let weights = softmax3(*logits);
        assert_close(&weights, &want, 2.1e-3, "weights");
        assert!(logits.iter().all(|l| l.is_finite()));
        assert!(logits.iter().sum::<f32>().abs() < 1e-5, "centred");
    }
}

#[test]
fn mixture_targets_are_smoothed_over_time() {
    let config = MixtureTargetConfig::default(); // radius 2
    let mut left = vec![0.0f32; 10];
    left[5..].fill(1.0); // the left hand lets go at frame 5...
    let mut right = vec![1.0f32; 10];
    right[5..].fill(0.0); // ...as the right hand takes the object
    let targets = mixture_targets(&left, &right, &config).unwrap();
    let left_weight: Vec<f32> = targets.iter().map(|l| softmax3(*l)[0]).collect();
    assert!(left_weight[0] > 0.99 && left_weight[9] < 0.01);
    // A ramp over the 5-frame window around the hand-over, monotone.
    assert!((left_weight[4] - 0.6).abs() < 0.01, "{left_weight:?}");
    assert!((left_weight[5] - 0.4).abs() < 0.01, "{left_weight:?}");
    assert!(left_weight.windows(2).all(|w| w[1] <= w[0] + 1e-6));
    // Softmax of the stored logits gives the smoothed weights back and they sum to one.
    for l in &targets {
        assert!((softmax3(*l).iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }
    assert!(mixture_targets(&[0.0], &[0.0, 1.0], &config).is_err());
}

#[test]
fn hand_distances_use_the_object_pose_and_the_hand_groups() {
    use dex2hoi_repr::mesh::box_mesh;
    use dex2hoi_repr::object_repr::hand_distances;
    use dex2hoi_repr::{MeshQuery, Skeleton};
    let skeleton = Skeleton::smplx();
    let rest = skeleton.rest_positions();
    let groups = skeleton.groups();
    // A 10 cm cube turned a quarter about Y and placed 5 cm below the left wrist.
    let cube = MeshQuery::new(&box_mesh(Vec3::splat(0.05))).unwrap();
    let wrist = rest[groups.left_wrist];
    let object = ObjectPose {
        rotation: axis_angle_to_matrix(Vec3::Y * std::f32::consts::FRAC_PI_2),
        position: wrist - Vec3::Y * 0.1,
    };
    let (left, right) = hand_distances(&cube, object, &rest, groups);
    // The wrist is 5 cm above the top face; finger joints hang lower but stay outside.
    assert!(left > 0.0 && left <= 0.05 + 1e-5, "{left}");
    assert!(right > 1.0, "the right hand is across the body: {right}");
    // Moving the object into the hand makes the distance negative (penetration counts as contact).
    let inside = ObjectPose { position: wrist, ..object };
    assert!(hand_distances(&cube, inside, &rest, groups).0 < 0.0);
}

#[test]
fn resting_frames_are_the_still_frames_on_the_support() {
    use dex2hoi_repr::MeshQuery;
    use dex2hoi_repr::mesh::box_mesh;
    let cube = MeshQuery::new(&box_mesh(Vec3::splat(0.05))).unwrap();
    let table = Vec3::new(0.1, 0.8, 0.4);
    let at = |offset: Vec3| ObjectPose { rotation: glam::Mat3::IDENTITY, position: table + offset };
    let mut poses = Vec::new();
    poses.extend((0..5).map(|_| at(Vec3::ZERO))); // 0-4 still on the table
    poses.extend((1..=5).map(|k| at(Vec3::Y * 0.01 * k as f32))); // 5-9 lifted
    poses.extend((0..5).map(|_| at(Vec3::Y * 0.05))); // 10-14 still, in the air
    poses.extend((0..5).map(|k| at(Vec3::new(0.02 * k as f32, 0.04 - 0.01 * k as f32, 0.0)))); // 15-19 down, sideways
    poses.extend((0..5).map(|_| at(Vec3::new(0.1, 0.0, 0.0)))); // 20-24 still, put down elsewhere
    // 25 as before; 26-29 turned 10 degrees about Y in place (the bottom stays on the table).
    let turned = glam::Mat3::from_rotation_y(0.17);
    poses.push(at(Vec3::new(0.1, 0.0, 0.0)));
    poses.extend((0..4).map(|_| ObjectPose { rotation: turned, position: table + Vec3::X * 0.1 }));
    // 30-32 just within the support's height, still: at rest where both neighbours are still;
    // 33-35 just beyond it: not.
    poses.extend((0..3).map(|_| at(Vec3::new(0.1, REST_HEIGHT_M * 0.9, 0.0))));
    poses.extend((0..3).map(|_| at(Vec3::new(0.1, REST_HEIGHT_M * 1.5, 0.0))));
    let resting = resting_frames(&cube, &poses);
    assert_eq!(resting.len(), poses.len());
    let expected: Vec<bool> =
        (0..poses.len()).map(|t| matches!(t, 0..=3 | 21..=24 | 27..=28 | 31)).collect();
    for (t, (got, want)) in resting.iter().zip(&expected).enumerate() {
        assert_eq!(got, want, "frame {t}: {resting:?}");
    }
    assert!(resting_frames(&cube, &[]).is_empty());
}

#[test]
fn an_object_at_rest_is_held_by_no_hand() {
    let near = [0.01f32; 4];
    let resting = [true, true, false, false];
    let free =
        MixtureTargetConfig { smoothing_radius: 0, free_at_rest: true, ..Default::default() };
    assert!(!MixtureTargetConfig::default().free_at_rest, "the paper's rule by default");
    let weights: Vec<[f32; 3]> = mixture_targets_at_rest(&near, &near, &resting, &free)
        .unwrap()
        .iter()
        .map(|l| softmax3(*l))
        .collect();
    for (t, want) in
        [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0], [0.5, 0.5, 0.0]].iter().enumerate()
    {
        assert_close(&weights[t], want, 2.1e-3, "free at rest");
    }
    // The paper's rule: proximity alone, resting or not; no flags: never at rest.
    let paper = MixtureTargetConfig { free_at_rest: false, ..free };
    let proximity = mixture_targets(&near, &near, &free).unwrap();
    assert_eq!(mixture_targets_at_rest(&near, &near, &resting, &paper).unwrap(), proximity);
    assert_eq!(mixture_targets_at_rest(&near, &near, &[], &free).unwrap(), proximity);
    assert!(mixture_targets_at_rest(&near, &near, &[true], &free).is_err());
}
