//! Tensor versions against the CPU versions, and finite-difference gradient checks of every
//! differentiable function the losses use (6D decode, axis-angle, FK, the mixture decode).

mod common;

use candle_core::{DType, Device, Tensor};
use common::*;
use glam::{Mat3, Vec3};
use rand::Rng;

use dex2hoi_repr::Skeleton;
use dex2hoi_repr::fk::{
    forward_kinematics, tensor_forward_kinematics, tensor_forward_kinematics_composite,
    tensor_forward_kinematics_composite_per_sample, tensor_forward_kinematics_per_sample,
};
use dex2hoi_repr::object_repr::{
    HandRelativeObject, ObjectPose, TensorWrists, WristPose, Wrists, tensor_decode_position,
    tensor_decode_rotation, tensor_mixture_weights, tensor_wrist_offset,
};
use dex2hoi_repr::rotation::{self, tensor as rt};

#[test]
fn tensor_rotations_agree_with_cpu() {
    let mut rng = rng(1);
    let sixd: Vec<[f32; 6]> =
        (0..24).map(|_| std::array::from_fn(|_| rng.random_range(-2.0f32..2.0))).collect();
    let flat_sixd: Vec<f32> = sixd.iter().flatten().copied().collect();
    let tensor = Tensor::from_vec(flat_sixd, (2, 3, 4, 6), &Device::Cpu).unwrap();
    let decoded = rt::sixd_to_matrix(&tensor).unwrap();
    assert_eq!(decoded.dims(), &[2, 3, 4, 3, 3]);
    let expected: Vec<f32> =
        sixd.iter().flat_map(|s| mat3_values(rotation::sixd_to_matrix(*s))).collect();
    assert_close(&flat(&decoded), &expected, 1e-5, "sixd_to_matrix");
    let encoded = rt::matrix_to_sixd(&decoded).unwrap();
    assert_eq!(encoded.dims(), &[2, 3, 4, 6]);
    let expected: Vec<f32> =
        sixd.iter().flat_map(|s| rotation::matrix_to_sixd(rotation::sixd_to_matrix(*s))).collect();
    assert_close(&flat(&encoded), &expected, 1e-5, "matrix_to_sixd");

    let mut vectors: Vec<Vec3> = (0..30).map(|_| random_vec3(&mut rng, 3.0)).collect();
    vectors.extend([Vec3::ZERO, Vec3::new(1e-5, -2e-5, 0.0), Vec3::new(0.0, 0.0, 3.1)]);
    let tensor = vecs_to_tensor(&vectors, &[vectors.len(), 3]);
    let matrices = rt::axis_angle_to_matrix(&tensor).unwrap();
    let expected: Vec<f32> =
        vectors.iter().flat_map(|v| mat3_values(rotation::axis_angle_to_matrix(*v))).collect();
    assert_close(&flat(&matrices), &expected, 1e-5, "axis_angle_to_matrix");
}

#[test]
fn tensor_shapes_are_checked() {
    let bad = Tensor::zeros((4, 5), DType::F32, &Device::Cpu).unwrap();
    assert!(rt::sixd_to_matrix(&bad).is_err());
    assert!(rt::axis_angle_to_matrix(&bad).is_err());
    assert!(rt::matrix_to_sixd(&bad).is_err());
    let ints = Tensor::zeros((4, 6), DType::U32, &Device::Cpu).unwrap();
    assert!(rt::sixd_to_matrix(&ints).is_err());
}

#[test]
fn gradients_of_rotation_functions() {
    let mut rng = rng(2);
    let sixd: Vec<f64> = (0..18).map(|_| rng.random_range(-1.5..1.5)).collect();
    let sixd = Tensor::from_vec(sixd, (3, 6), &Device::Cpu).unwrap();
    gradient_check(&sixd, rt::sixd_to_matrix, "sixd_to_matrix");
    let aa: Vec<f64> = vec![0.3, -1.2, 0.8, 2.5, 0.1, -0.4, 1e-4, 2e-4, -1e-4, 0.0, 0.0, 0.0];
    let aa = Tensor::from_vec(aa, (4, 3), &Device::Cpu).unwrap();
    gradient_check(&aa, rt::axis_angle_to_matrix, "axis_angle_to_matrix");
}

fn random_pose(
    rng: &mut rand_chacha::ChaCha8Rng,
    joints: usize,
    frames: usize,
) -> (Vec<Mat3>, Vec<Vec3>) {
    let rotations = (0..frames * joints).map(|_| random_rotation(rng, 1.2)).collect();
    let roots = (0..frames).map(|_| random_vec3(rng, 1.0) + Vec3::Y).collect();
    (rotations, roots)
}

#[test]
fn zero_pose_gives_the_rest_joints() {
    for skeleton in [Skeleton::smplx(), Skeleton::mixamo()] {
        let j = skeleton.joint_count();
        let root = skeleton.rest_offsets()[0];
        let out = forward_kinematics(&skeleton, &vec![Mat3::IDENTITY; j], &[root]).unwrap();
        for (a, b) in out.frame_positions(0).iter().zip(skeleton.rest_positions()) {
            assert!(a.abs_diff_eq(b, 1e-6));
        }
        assert!(out.rotations.iter().all(|r| r.abs_diff_eq(Mat3::IDENTITY, 1e-6)));
    }
}

#[test]
fn rotating_the_root_rotates_every_joint_about_the_pelvis() {
    let skeleton = Skeleton::smplx();
    let mut rng = rng(3);
    let (mut local, roots) = random_pose(&mut rng, 52, 1);
    let before = forward_kinematics(&skeleton, &local, &roots).unwrap();
    let turn = random_rotation(&mut rng, 3.0);
    local[0] = turn * local[0];
    let after = forward_kinematics(&skeleton, &local, &roots).unwrap();
    let pelvis = roots[0];
    for j in 0..52 {
        let expected = pelvis + turn * (before.position(0, j) - pelvis);
        assert!(after.position(0, j).abs_diff_eq(expected, 1e-5), "joint {j}");
        assert!(after.rotation(0, j).abs_diff_eq(turn * before.rotation(0, j), 1e-5));
    }
    // Bone lengths never change.
    for (j, parent) in skeleton.parents().iter().enumerate() {
        if let Some(p) = parent {
            let length = after.position(0, j).distance(after.position(0, *p));
            assert!((length - skeleton.rest_offsets()[j].length()).abs() < 1e-5);
        }
    }
}

type FkFn = fn(&Skeleton, &Tensor, &Tensor) -> dex2hoi_repr::Result<(Tensor, Tensor)>;

#[test]
fn candle_fk_equals_glam_fk() {
    for skeleton in [Skeleton::smplx(), Skeleton::mixamo()] {
        let j = skeleton.joint_count();
        let mut rng = rng(4);
        let (local, roots) = random_pose(&mut rng, j, 6);
        let cpu = forward_kinematics(&skeleton, &local, &roots).unwrap();
        let local_t = mats_to_tensor(&local, &[2, 3, j, 3, 3]);
        let roots_t = vecs_to_tensor(&roots, &[2, 3, 3]);
        for (name, fk) in [
            ("op", tensor_forward_kinematics as FkFn),
            ("composite", tensor_forward_kinematics_composite as FkFn),
        ] {
            let (positions, rotations) = fk(&skeleton, &local_t, &roots_t).unwrap();
            assert_eq!(positions.dims(), &[2, 3, j, 3]);
            assert_eq!(rotations.dims(), &[2, 3, j, 3, 3]);
            let expected: Vec<f32> = cpu.positions.iter().flat_map(|v| v.to_array()).collect();
            assert_close(&flat(&positions), &expected, 1e-5, name);
            let expected: Vec<f32> = cpu.rotations.iter().flat_map(|m| mat3_values(*m)).collect();
            assert_close(&flat(&rotations), &expected, 1e-5, name);
        }
    }
}

type PerSampleFkFn =
    fn(&Skeleton, &Tensor, &Tensor, &Tensor) -> dex2hoi_repr::Result<(Tensor, Tensor)>;

/// Rest offsets of a differently proportioned body: every bone scaled by its own factor.
fn reshaped_offsets(rng: &mut rand_chacha::ChaCha8Rng, skeleton: &Skeleton) -> Vec<Vec3> {
    skeleton.rest_offsets().iter().map(|o| *o * rng.random_range(0.7f32..1.3)).collect()
}

#[test]
fn per_sample_fk_poses_each_sample_on_its_own_body() {
    for skeleton in [Skeleton::smplx(), Skeleton::mixamo()] {
        let j = skeleton.joint_count();
        let mut rng = rng(14);
        let (samples, frames) = (3, 4);
        let bodies: Vec<Vec<Vec3>> =
            (0..samples).map(|_| reshaped_offsets(&mut rng, &skeleton)).collect();
        let (local, roots) = random_pose(&mut rng, j, samples * frames);
        let mut expected_positions = Vec::new();
        let mut expected_rotations = Vec::new();
        for (g, body) in bodies.iter().enumerate() {
            let own = skeleton.with_rest_offsets(body.clone()).unwrap();
            let span = g * frames..(g + 1) * frames;
            let cpu = forward_kinematics(&own, &local[span.start * j..span.end * j], &roots[span])
                .unwrap();
            expected_positions.extend(cpu.positions.iter().flat_map(|v| v.to_array()));
            expected_rotations.extend(cpu.rotations.iter().flat_map(|m| mat3_values(*m)));
        }
        let rest = vecs_to_tensor(&bodies.concat(), &[samples, j, 3]);
        // Two inner leading dimensions: the offsets are shared by every frame of a sample.
        let local_t = mats_to_tensor(&local, &[samples, 2, 2, j, 3, 3]);
        let roots_t = vecs_to_tensor(&roots, &[samples, 2, 2, 3]);
        for (name, fk) in [
            ("op", tensor_forward_kinematics_per_sample as PerSampleFkFn),
            ("composite", tensor_forward_kinematics_composite_per_sample as PerSampleFkFn),
        ] {
            let (positions, rotations) = fk(&skeleton, &rest, &local_t, &roots_t).unwrap();
            assert_eq!(positions.dims(), &[samples, 2, 2, j, 3]);
            assert_close(&flat(&positions), &expected_positions, 1e-5, name);
            assert_close(&flat(&rotations), &expected_rotations, 1e-5, name);
        }
        // The skeleton's own offsets for every sample give the plain FK.
        let own = vecs_to_tensor(&skeleton.rest_offsets().repeat(samples), &[samples, j, 3]);
        let plain = tensor_forward_kinematics(&skeleton, &local_t, &roots_t).unwrap();
        let same = tensor_forward_kinematics_per_sample(&skeleton, &own, &local_t, &roots_t);
        assert_eq!(flat(&plain.0), flat(&same.unwrap().0));
    }
}

#[test]
fn per_sample_fk_refuses_offsets_of_another_shape() {
    let skeleton = Skeleton::smplx();
    let local = Tensor::zeros((2, 5, 52, 3, 3), DType::F32, &Device::Cpu).unwrap();
    let root = Tensor::zeros((2, 5, 3), DType::F32, &Device::Cpu).unwrap();
    for shape in [(3, 52, 3), (2, 51, 3), (1, 52, 3)] {
        let rest = Tensor::zeros(shape, DType::F32, &Device::Cpu).unwrap();
        for fk in [
            tensor_forward_kinematics_per_sample as PerSampleFkFn,
            tensor_forward_kinematics_composite_per_sample as PerSampleFkFn,
        ] {
            assert!(fk(&skeleton, &rest, &local, &root).is_err(), "{shape:?}");
        }
    }
}

#[test]
fn gradient_of_per_sample_fk() {
    // Two samples of two frames on different bodies, f64, with respect to the 6D input and
    // the roots: the backward pass must use each frame's own offsets.
    let skeleton = Skeleton::mixamo();
    let j = skeleton.joint_count();
    let mut rng = rng(15);
    let bodies: Vec<Vec3> = (0..2).flat_map(|_| reshaped_offsets(&mut rng, &skeleton)).collect();
    let rest = vecs_to_tensor(&bodies, &[2, j, 3]).to_dtype(DType::F64).unwrap();
    let clean: Vec<f32> =
        (0..4 * j).flat_map(|_| rotation::matrix_to_sixd(random_rotation(&mut rng, 1.0))).collect();
    let sixd: Vec<f64> =
        clean.iter().map(|&x| f64::from(x) + rng.random_range(-0.1..0.1)).collect();
    let sixd = Tensor::from_vec(sixd, (2, 2, j, 6), &Device::Cpu).unwrap();
    let roots: Vec<f64> = (0..12).map(|_| rng.random_range(-1.0..1.0)).collect();
    let root = Tensor::from_vec(roots, (2, 2, 3), &Device::Cpu).unwrap();
    for (name, fk) in [
        ("op", tensor_forward_kinematics_per_sample as PerSampleFkFn),
        ("composite", tensor_forward_kinematics_composite_per_sample as PerSampleFkFn),
    ] {
        let (root_clone, rest_clone, skeleton_clone) =
            (root.clone(), rest.clone(), skeleton.clone());
        gradient_check(
            &sixd,
            move |x| {
                let rotations = rt::sixd_to_matrix(x)?;
                let (positions, global) =
                    fk(&skeleton_clone, &rest_clone, &rotations, &root_clone)?;
                Ok(Tensor::cat(&[positions.flatten_all()?, global.flatten_all()?], 0)?)
            },
            &format!("per-sample FK ({name}) wrt 6D"),
        );
        let rotations = rt::sixd_to_matrix(&sixd).unwrap();
        let (rest_clone, skeleton_clone) = (rest.clone(), skeleton.clone());
        gradient_check(
            &root,
            move |r| Ok(fk(&skeleton_clone, &rest_clone, &rotations, r)?.0),
            &format!("per-sample FK ({name}) wrt root"),
        );
    }
}

#[test]
fn fk_refuses_mismatched_shapes() {
    let skeleton = Skeleton::smplx();
    assert!(forward_kinematics(&skeleton, &[Mat3::IDENTITY; 10], &[Vec3::ZERO]).is_err());
    let local = Tensor::zeros((2, 51, 3, 3), DType::F32, &Device::Cpu).unwrap();
    let root = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
    assert!(tensor_forward_kinematics(&skeleton, &local, &root).is_err());
    let local = Tensor::zeros((2, 52, 3, 3), DType::F32, &Device::Cpu).unwrap();
    let root = Tensor::zeros((3, 3), DType::F32, &Device::Cpu).unwrap();
    assert!(tensor_forward_kinematics(&skeleton, &local, &root).is_err());
}

#[test]
fn gradient_of_fk_through_6d() {
    // The losses differentiate FK of 6D-decoded rotations: check the whole chain on a short
    // skeleton path (all 52 joints, two frames) with respect to the 6D input and the root.
    let skeleton = Skeleton::smplx();
    let mut rng = rng(5);
    let clean: Vec<f32> = (0..2 * 52)
        .flat_map(|_| rotation::matrix_to_sixd(random_rotation(&mut rng, 1.0)))
        .collect();
    let sixd: Vec<f64> =
        clean.iter().map(|&x| f64::from(x) + rng.random_range(-0.1..0.1)).collect();
    let sixd = Tensor::from_vec(sixd, (2, 52, 6), &Device::Cpu).unwrap();
    let root =
        Tensor::from_vec(vec![0.1f64, 0.9, -0.2, 0.0, 1.0, 0.3], (2, 3), &Device::Cpu).unwrap();
    for (name, fk) in [
        ("op", tensor_forward_kinematics as FkFn),
        ("composite", tensor_forward_kinematics_composite as FkFn),
    ] {
        let (root_clone, skeleton_clone) = (root.clone(), skeleton.clone());
        gradient_check(
            &sixd,
            move |x| {
                let rotations = rt::sixd_to_matrix(x)?;
                let (positions, global) = fk(&skeleton_clone, &rotations, &root_clone)?;
                Ok(Tensor::cat(&[positions.flatten_all()?, global.flatten_all()?], 0)?)
            },
            &format!("FK ({name}) wrt 6D"),
        );
        let rotations = rt::sixd_to_matrix(&sixd).unwrap();
        let skeleton_clone = skeleton.clone();
        gradient_check(
            &root,
            move |r| Ok(fk(&skeleton_clone, &rotations, r)?.0),
            &format!("FK ({name}) wrt root"),
        );
    }
}

fn random_wrists(rng: &mut rand_chacha::ChaCha8Rng) -> Wrists {
    Wrists {
        left: WristPose { position: random_vec3(rng, 1.0), rotation: random_rotation(rng, 3.0) },
        right: WristPose { position: random_vec3(rng, 1.0), rotation: random_rotation(rng, 3.0) },
    }
}

#[test]
fn tensor_decode_agrees_with_cpu_decode() {
    let mut rng = rng(6);
    let n = 16;
    let mut features = Vec::new();
    let mut wrists = Vec::new();
    let mut expected_positions = Vec::new();
    let mut expected_rotations = Vec::new();
    let mut expected_weights = Vec::new();
    let mut object_positions = Vec::new();
    for _ in 0..n {
        let w = random_wrists(&mut rng);
        let object = ObjectPose {
            rotation: random_rotation(&mut rng, 3.0),
            position: random_vec3(&mut rng, 1.0),
        };
        let logits =
            [rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0)];
        let mut encoded = HandRelativeObject::encode(object, w, logits);
        // Perturb the branches so that they disagree, as predictions do.
        encoded.left_offset += random_vec3(&mut rng, 0.05);
        encoded.global_position += random_vec3(&mut rng, 0.05);
        features.extend(encoded.to_array());
        expected_positions.push(encoded.decode_position(w));
        expected_rotations.push(encoded.decode_rotation());
        expected_weights.extend(encoded.mixture_weights());
        object_positions.push(object.position);
        wrists.push(w);
    }
    let features = Tensor::from_vec(features, (4, 4, 18), &Device::Cpu).unwrap();
    let tensor_wrists = TensorWrists {
        left_position: vecs_to_tensor(
            &wrists.iter().map(|w| w.left.position).collect::<Vec<_>>(),
            &[4, 4, 3],
        ),
        left_rotation: mats_to_tensor(
            &wrists.iter().map(|w| w.left.rotation).collect::<Vec<_>>(),
            &[4, 4, 3, 3],
        ),
        right_position: vecs_to_tensor(
            &wrists.iter().map(|w| w.right.position).collect::<Vec<_>>(),
            &[4, 4, 3],
        ),
        right_rotation: mats_to_tensor(
            &wrists.iter().map(|w| w.right.rotation).collect::<Vec<_>>(),
            &[4, 4, 3, 3],
        ),
    };
    let decoded = tensor_decode_position(&features, &tensor_wrists).unwrap();
    let expected: Vec<f32> = expected_positions.iter().flat_map(|v| v.to_array()).collect();
    assert_close(&flat(&decoded), &expected, 1e-5, "decoded position");
    let rotations = tensor_decode_rotation(&features).unwrap();
    let expected: Vec<f32> = expected_rotations.iter().flat_map(|m| mat3_values(*m)).collect();
    assert_close(&flat(&rotations), &expected, 1e-5, "decoded rotation");
    let weights = tensor_mixture_weights(&features).unwrap();
    assert_close(&flat(&weights), &expected_weights, 1e-6, "mixture weights");
    // The tensor offsets of Eq. 3 match the CPU ones.
    let objects = vecs_to_tensor(&object_positions, &[4, 4, 3]);
    let offsets =
        tensor_wrist_offset(&objects, &tensor_wrists.left_position, &tensor_wrists.left_rotation)
            .unwrap();
    let expected: Vec<f32> = object_positions
        .iter()
        .zip(&wrists)
        .flat_map(|(p, w)| dex2hoi_repr::object_repr::wrist_offset(*p, w.left).to_array())
        .collect();
    assert_close(&flat(&offsets), &expected, 1e-5, "wrist offsets");
}

#[test]
fn gradient_of_the_mixture_decode() {
    let mut rng = rng(7);
    let w = random_wrists(&mut rng);
    let features: Vec<f64> = (0..2 * 18).map(|_| rng.random_range(-1.0..1.0)).collect();
    let features = Tensor::from_vec(features, (2, 18), &Device::Cpu).unwrap();
    let to64 = |t: Tensor| t.to_dtype(DType::F64).unwrap();
    let wrists = TensorWrists {
        left_position: to64(vecs_to_tensor(&[w.left.position, w.right.position], &[2, 3])),
        left_rotation: to64(mats_to_tensor(&[w.left.rotation, w.right.rotation], &[2, 3, 3])),
        right_position: to64(vecs_to_tensor(&[w.right.position, w.left.position], &[2, 3])),
        right_rotation: to64(mats_to_tensor(&[w.right.rotation, w.left.rotation], &[2, 3, 3])),
    };
    let wrists_clone = wrists.clone();
    gradient_check(
        &features,
        move |f| tensor_decode_position(f, &wrists_clone),
        "decode wrt features",
    );
    let features_clone = features.clone();
    let right_rotation = wrists.right_rotation.clone();
    let right_position = wrists.right_position.clone();
    let left_rotation = wrists.left_rotation.clone();
    gradient_check(
        &wrists.left_position,
        move |p| {
            let w = TensorWrists {
                left_position: p.clone(),
                left_rotation: left_rotation.clone(),
                right_position: right_position.clone(),
                right_rotation: right_rotation.clone(),
            };
            tensor_decode_position(&features_clone, &w)
        },
        "decode wrt wrist position",
    );
}
