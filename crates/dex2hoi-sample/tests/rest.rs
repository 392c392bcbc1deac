//! Objects at rest: the sampler's rule for objects no hand holds, on hand-made features.

use candle_core::{Device, Tensor};
use glam::{Mat3, Vec3};

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::{ObjectDecoding, decode_features};
use dex2hoi_data::layout::FeatureLayout;
use dex2hoi_data::start::StartPose;
use dex2hoi_repr::mesh::box_mesh;
use dex2hoi_repr::object_repr::{GLOBAL_POSITION_RANGE, MIXTURE_RANGE};
use dex2hoi_repr::{MeshQuery, ObjectPose, Skeleton};
use dex2hoi_sample::PrefixEncoding;
use dex2hoi_sample::rest::ObjectsAtRest;

const HALF: f32 = 0.05;
const TABLE: f32 = 0.9;

/// `frames` standing frames with a box on the table in slot 0, as `[1, 2, frames, D]`
/// streams, and its pose.
fn standing(frames: usize) -> (Vec<f32>, Vec<f32>, ObjectPose) {
    let pose = ObjectPose { rotation: Mat3::IDENTITY, position: Vec3::new(0.1, TABLE + HALF, 0.4) };
    let (body, objects) =
        StartPose::smplx_standing().features(&Skeleton::smplx(), [Some(pose), None]).unwrap();
    (body.repeat(frames), objects.repeat(frames), pose)
}

fn streams(layout: FeatureLayout, body: &[f32], objects: &[f32], frames: usize) -> Tensor {
    let values = layout.frames_to_streams(body, objects).unwrap();
    Tensor::from_vec(values, (1, MAX_OBJECTS, frames, layout.stream_width()), &Device::Cpu).unwrap()
}

fn object_positions(encoding: &PrefixEncoding<'_>, layout: FeatureLayout, t: &Tensor) -> Vec<Vec3> {
    let values: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
    let (body, objects) = layout.streams_to_frames(&values).unwrap();
    let motion = decode_features(
        encoding.skeleton,
        &body,
        &objects,
        encoding.present,
        encoding.root_start,
        ObjectDecoding::Mixture,
    )
    .unwrap();
    motion.objects[0].as_ref().unwrap().1.clone()
}

#[test]
fn free_objects_stay_at_rest_on_their_support_and_held_ones_move() {
    let skeleton = Skeleton::smplx();
    let layout = FeatureLayout::of_skeleton(&skeleton);
    let encoding = PrefixEncoding {
        skeleton: &skeleton,
        root_start: StartPose::smplx_standing().root(),
        present: [true, false],
    };
    let query = MeshQuery::new(&box_mesh(Vec3::splat(HALF))).unwrap();
    let rule = ObjectsAtRest { meshes: [Some(&query), None] };
    let (body, objects, pose) = standing(4);
    let prefix = streams(layout, &body, &objects, 4);
    let mut states = rule.start(&encoding, &prefix, layout).unwrap();

    // A window of 6 frames: the free box drifts 3 cm sideways and sinks 1 cm a frame (frames
    // 0-1), the left hand holds it (frames 2-3), then it is free again, 5 cm further and 4 cm
    // above the table (frames 4-5).
    let (body, mut objects, _) = standing(6);
    let width = layout.objects_width();
    for t in 0..6 {
        let row = &mut objects[t * width..][..18];
        let p = &mut row[GLOBAL_POSITION_RANGE];
        let (dx, dy) = match t {
            0 | 1 => (0.03 * (t + 1) as f32, -0.01 * (t + 1) as f32),
            2 | 3 => (0.0, 0.10),
            _ => (0.05, 0.04),
        };
        p[0] += dx;
        p[1] += dy;
        // Held frames give the mixture to the left hand (which decodes the pose from the
        // wrist offset); free ones to the global branch.
        let logits = &mut row[MIXTURE_RANGE];
        logits.copy_from_slice(if (2..4).contains(&t) {
            &[5.0, -5.0, -5.0]
        } else {
            &[-5.0, -5.0, 5.0]
        });
    }
    let window = streams(layout, &body, &objects, 6);
    let before = object_positions(&encoding, layout, &window);
    let settled = rule.settle(&encoding, &window, layout, &mut states).unwrap();
    let after = object_positions(&encoding, layout, &settled);
    for t in 0..2 {
        assert!((after[t] - pose.position).length() < 1e-4, "frame {t}: {} kept at rest", after[t]);
    }
    for t in 2..4 {
        assert!((after[t] - before[t]).length() < 1e-4, "frame {t}: held, as generated");
    }
    // Released where it was let go (frame 4), lowered onto the table, and kept there.
    let released = Vec3::new(before[4].x, TABLE + HALF, before[4].z);
    for t in 4..6 {
        assert!((after[t] - released).length() < 1e-4, "frame {t}: {} vs {released}", after[t]);
    }
    // The state carries over: a later window with the box free keeps it where it was put.
    let next = streams(layout, &body, &objects, 6);
    let again = rule.settle(&encoding, &next, layout, &mut states).unwrap();
    let again = object_positions(&encoding, layout, &again);
    assert!((again[0] - released).length() < 1e-4);
    // A present object without a mesh is refused.
    let blind = ObjectsAtRest { meshes: [None, None] };
    assert!(blind.start(&encoding, &prefix, layout).is_err());
}
