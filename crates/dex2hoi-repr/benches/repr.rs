//! `cargo xtask bench repr`: forward kinematics and signed-distance throughput.
//!
//! Prints medians over repeated runs, and ratios against baselines measured in the same run:
//! FK on one thread (baseline) against FK over frames in parallel and the batched candle FK the
//! losses use (the custom operation and the composite fallback, forward and forward + backward); BVH signed-distance queries against a brute-force scan of every triangle.

use std::hint::black_box;
use std::time::{Duration, Instant};

use candle_core::{Device, Tensor, Var};
use glam::{Mat3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::fk::{
    forward_kinematics, forward_kinematics_frame, tensor_forward_kinematics,
    tensor_forward_kinematics_composite,
};
use dex2hoi_repr::mesh::uv_sphere;
use dex2hoi_repr::rotation::axis_angle_to_matrix;
use dex2hoi_repr::sdf::brute_force_distance;
use dex2hoi_repr::{BpsBasis, MeshQuery, Skeleton};

type FkFn = fn(&Skeleton, &Tensor, &Tensor) -> dex2hoi_repr::Result<(Tensor, Tensor)>;

/// Median wall time of `runs` calls after one warm-up call.
fn median_time(runs: usize, mut f: impl FnMut()) -> Duration {
    f();
    let mut times: Vec<Duration> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed()
        })
        .collect();
    times.sort();
    times[runs / 2]
}

fn report(name: &str, items: usize, unit: &str, time: Duration) -> f64 {
    let rate = items as f64 / time.as_secs_f64();
    println!(
        "{name:<48} {rate:>14.0} {unit}/s   (median {:.3} ms for {items})",
        time.as_secs_f64() * 1e3
    );
    rate
}

fn main() {
    let threads = rayon::current_num_threads();
    println!("dex2hoi-repr benchmarks ({threads} rayon threads; medians)\n");
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let random_vec3 = |rng: &mut ChaCha8Rng| {
        Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
    };

    // Forward kinematics, SMPL-X 52 joints.
    let skeleton = Skeleton::smplx();
    let joints = skeleton.joint_count();
    let frames = 4096;
    let local: Vec<Mat3> =
        (0..frames * joints).map(|_| axis_angle_to_matrix(random_vec3(&mut rng) * 0.8)).collect();
    let roots: Vec<Vec3> = (0..frames).map(|_| random_vec3(&mut rng)).collect();
    let mut positions = vec![Vec3::ZERO; joints];
    let mut rotations = vec![Mat3::IDENTITY; joints];
    let single = median_time(21, || {
        for (frame, root) in roots.iter().enumerate() {
            let local = &local[frame * joints..(frame + 1) * joints];
            forward_kinematics_frame(&skeleton, local, *root, &mut positions, &mut rotations);
            black_box(&positions);
        }
    });
    let single_rate = report("FK glam, one thread (baseline)", frames, "frames", single);
    let parallel = median_time(21, || {
        black_box(forward_kinematics(&skeleton, &local, &roots).unwrap());
    });
    let parallel_rate = report("FK glam, frames in parallel", frames, "frames", parallel);
    let flat_local: Vec<f32> = local.iter().flat_map(|m| m.transpose().to_cols_array()).collect();
    let local_t = Tensor::from_vec(flat_local, (64, 64, joints, 3, 3), &Device::Cpu).unwrap();
    let roots_t = Tensor::from_vec(
        roots.iter().flat_map(|v| v.to_array()).collect::<Vec<_>>(),
        (64, 64, 3),
        &Device::Cpu,
    )
    .unwrap();
    let candle = median_time(11, || {
        black_box(tensor_forward_kinematics(&skeleton, &local_t, &roots_t).unwrap());
    });
    let candle_rate =
        report("FK candle op, batch 64 x 64 frames (forward)", frames, "frames", candle);
    let composite = median_time(11, || {
        black_box(tensor_forward_kinematics_composite(&skeleton, &local_t, &roots_t).unwrap());
    });
    let composite_rate = report("FK candle composite (forward)", frames, "frames", composite);
    let local_var = Var::from_tensor(&local_t).unwrap();
    let backward = |fk: FkFn| {
        median_time(11, || {
            let (positions, _) = fk(&skeleton, local_var.as_tensor(), &roots_t).unwrap();
            black_box(positions.sqr().unwrap().sum_all().unwrap().backward().unwrap());
        })
    };
    let op_train_rate = report(
        "FK candle op, forward + backward",
        frames,
        "frames",
        backward(tensor_forward_kinematics),
    );
    let composite_train_rate = report(
        "FK candle composite, forward + backward",
        frames,
        "frames",
        backward(tensor_forward_kinematics_composite),
    );
    println!(
        "  ratios to the one-thread baseline: glam parallel {:.2}x, op {:.2}x, composite {:.2}x",
        parallel_rate / single_rate,
        candle_rate / single_rate,
        composite_rate / single_rate
    );
    println!(
        "  op over composite: forward {:.1}x, forward + backward {:.1}x\n",
        candle_rate / composite_rate,
        op_train_rate / composite_train_rate
    );

    // Signed distance against a 10,000-triangle mesh.
    let sphere = uv_sphere(0.1, 51, 100);
    assert_eq!(sphere.faces.len(), 10_000);
    let build = median_time(11, || {
        black_box(MeshQuery::new(&sphere).unwrap());
    });
    println!(
        "{:<48} {:>14.3} ms",
        "SDF query structure build (10k triangles)",
        build.as_secs_f64() * 1e3
    );
    let query = MeshQuery::new(&sphere).unwrap();
    let points: Vec<Vec3> = (0..20_000).map(|_| random_vec3(&mut rng) * 0.2).collect();
    let one_thread = median_time(11, || {
        for p in &points {
            black_box(query.signed_distance(*p));
        }
    });
    let one_thread_rate = report("SDF BVH, one thread", points.len(), "queries", one_thread);
    let parallel = median_time(11, || {
        black_box(query.signed_distances(&points));
    });
    let parallel_rate = report("SDF BVH, parallel", points.len(), "queries", parallel);
    let brute_points = &points[..200];
    let brute = median_time(5, || {
        for p in brute_points {
            black_box(brute_force_distance(&sphere, *p));
        }
    });
    let brute_rate =
        report("SDF brute force, one thread (baseline)", brute_points.len(), "queries", brute);
    println!(
        "  ratios to brute force: BVH one thread {:.0}x, BVH parallel {:.0}x\n",
        one_thread_rate / brute_rate,
        parallel_rate / brute_rate
    );

    let basis = BpsBasis::new(1024, 0.3, 0).unwrap();
    let bps = median_time(11, || {
        black_box(basis.encode(&query));
    });
    report("BPS encode, 1024 basis points (10k triangles)", 1, "objects", bps);
}
