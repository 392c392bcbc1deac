//! `motion.bvh`: written, parsed back, and the parsed motion's forward kinematics gives the
//! same joint positions (to 0.1 mm) on both skeletons.

mod common;

use glam::Vec3;

use dex2hoi_export::{BvhMotion, encode_bvh, read_bvh, write_bvh};
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::fk::forward_kinematics_frame;
use dex2hoi_repr::skeleton::HUMOTO_REST_POSITIONS;

/// Forward kinematics of a parsed BVH (joints in hierarchy order).
fn bvh_joint_positions(bvh: &BvhMotion, frame: usize) -> Vec<Vec3> {
    let joints = bvh.joint_names.len();
    let mut rotations = vec![glam::Mat3::IDENTITY; joints];
    let mut positions = vec![Vec3::ZERO; joints];
    for j in 0..joints {
        let local = bvh.local_rotations[frame * joints + j];
        match bvh.parents[j] {
            None => {
                rotations[j] = local;
                positions[j] = bvh.root_positions[frame];
            }
            Some(p) => {
                rotations[j] = rotations[p] * local;
                positions[j] = positions[p] + rotations[p] * bvh.offsets[j];
            }
        }
    }
    positions
}

fn round_trip(skeleton: &Skeleton, frames: usize) {
    let motion = common::wavy_motion(skeleton, frames, 0);
    let export = common::export(skeleton, &motion, &[], "");
    let dir = common::scratch_dir(&format!("bvh-{}", skeleton.kind().name()));
    let path = dir.join("motion.bvh");
    write_bvh(&path, &export).expect("written");
    let bvh = read_bvh(&path).expect("parsed");
    let joints = skeleton.joint_count();
    assert_eq!(bvh.joint_names.len(), joints);
    assert_eq!(bvh.root_positions.len(), frames);
    assert!((bvh.frame_time - 0.05).abs() < 1e-6);
    // Every joint keeps its name, its parent (by name) and its rest offset.
    let index: Vec<usize> = bvh
        .joint_names
        .iter()
        .map(|name| skeleton.joint_index(name).expect("a skeleton joint"))
        .collect();
    // Named as the rig names them (`mixamorig:Hips`, `pelvis`).
    let rig_names = skeleton.rig_joint_names();
    for (b, &j) in index.iter().enumerate() {
        assert_eq!(bvh.joint_names[b], rig_names[j]);
    }
    for (b, &j) in index.iter().enumerate() {
        assert_eq!(bvh.parents[b].map(|p| index[p]), skeleton.parents()[j]);
        if j != 0 {
            assert!((bvh.offsets[b] - skeleton.rest_offsets()[j]).length() < 1e-6);
        }
    }
    let mut worst = 0.0f32;
    let mut positions = vec![Vec3::ZERO; joints];
    let mut rotations = vec![glam::Mat3::IDENTITY; joints];
    for t in 0..frames {
        forward_kinematics_frame(
            skeleton,
            &motion.local_rotations[t * joints..(t + 1) * joints],
            motion.root_positions[t],
            &mut positions,
            &mut rotations,
        );
        for (b, p) in bvh_joint_positions(&bvh, t).iter().enumerate() {
            worst = worst.max((*p - positions[index[b]]).length());
        }
    }
    assert!(worst < 1e-4, "{}: joints differ by up to {worst} m", skeleton.kind().name());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn smplx_bvh_round_trips_to_the_same_joint_positions() {
    round_trip(&Skeleton::smplx(), 12);
}

#[test]
fn mixamo_bvh_round_trips_to_the_same_joint_positions() {
    round_trip(&Skeleton::mixamo(), 5);
}

#[test]
fn mixamo_bvh_names_every_bone_as_mixamo_does_with_its_rest_positions() {
    // HUMOTO's character as published, so the offsets are Mixamo's to the last digit written.
    let skeleton = Skeleton::humoto_character();
    let motion = common::wavy_motion(&skeleton, 2, 0);
    let text = encode_bvh(&common::export(&skeleton, &motion, &[], "")).expect("encoded");
    assert!(text.starts_with("HIERARCHY\nROOT mixamorig:Hips\n"));
    let bvh = dex2hoi_export::parse_bvh(&text).expect("parsed");
    let rest: std::collections::HashMap<String, Vec3> = bvh
        .joint_names
        .iter()
        .enumerate()
        .map(|(b, name)| {
            let mut position = bvh.offsets[b];
            let mut parent = bvh.parents[b];
            while let Some(p) = parent {
                position += if bvh.parents[p].is_some() { bvh.offsets[p] } else { Vec3::ZERO };
                parent = bvh.parents[p];
            }
            (name.clone(), position)
        })
        .collect();
    let hips = HUMOTO_REST_POSITIONS[0].1;
    for (name, position) in HUMOTO_REST_POSITIONS {
        let got = rest[&format!("mixamorig:{name}")] + Vec3::from_array(hips);
        assert!((got - Vec3::from_array(position)).length() < 2e-6, "{name}: {got}");
    }
    assert_eq!(rest.len(), 65);
}

#[test]
fn bvh_layout_has_a_six_channel_root_end_sites_and_the_frame_count() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 3, 0);
    let text = encode_bvh(&common::export(&skeleton, &motion, &[], "")).expect("encoded");
    assert!(text.starts_with("HIERARCHY\nROOT pelvis\n{\n\tOFFSET 0.000000 0.000000 0.000000\n"));
    assert!(
        text.contains("CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
    );
    assert_eq!(text.matches("CHANNELS 3 Zrotation Xrotation Yrotation").count(), 51);
    // Leaves: head, two feet and ten fingertips.
    assert_eq!(text.matches("End Site").count(), 13);
    assert_eq!(text.matches('{').count(), text.matches('}').count());
    assert!(text.contains("MOTION\nFrames: 3\nFrame Time: 0.0500000\n"));
    let motion_lines = text.split("Frame Time: 0.0500000\n").nth(1).expect("motion lines");
    for line in motion_lines.lines() {
        assert_eq!(line.split_whitespace().count(), 3 + 3 * 52);
    }
}

#[test]
fn a_truncated_bvh_names_the_problem() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 2, 0);
    let text = encode_bvh(&common::export(&skeleton, &motion, &[], "")).expect("encoded");
    // Drop the last frame's line.
    let cut = &text[..text.trim_end().rfind('\n').expect("several lines") + 1];
    let error = parse_error(cut);
    assert!(error.contains("channel value") && error.contains("end of the file"), "{error}");
}

fn parse_error(text: &str) -> String {
    dex2hoi_export::parse_bvh(text).expect_err("malformed").to_string()
}

/// A real BVH file from another tool (CMU motion capture in Debian's assimp test models,
/// installed by `scripts/setup.sh`): the reader takes its ZYX channel order.
#[test]
fn the_reader_takes_a_cmu_motion_capture_file() {
    let path = std::path::Path::new("/usr/share/assimp/models/BVH/01_01.bvh");
    if !path.exists() {
        assert!(!common::in_ci(), "CI needs {} (scripts/setup.sh)", path.display());
        println!("skipped: {} is not installed", path.display());
        return;
    }
    let bvh = read_bvh(path).expect("parsed");
    assert_eq!(bvh.joint_names.len(), 31);
    assert_eq!(bvh.joint_names[0], "Hips");
    assert_eq!(bvh.root_positions.len(), 2752);
    assert_eq!(bvh.local_rotations.len(), 2752 * 31);
    assert!(bvh.local_rotations.iter().all(|r| dex2hoi_repr::rotation::is_rotation(*r, 1e-4)));
    // The feet stay below the hips.
    let positions = bvh_joint_positions(&bvh, 100);
    let foot = bvh.joint_names.iter().position(|n| n == "LeftFoot").expect("LeftFoot");
    assert!(positions[foot].y < positions[0].y);
}
