//! Tests of `dex2hoi_eval::metrics` against values computed by hand or by scipy.

use dex2hoi_eval::metrics::{
    ANKLE_HEIGHT_M, CONTACT_RADIUS_M, ContactCounts, ContactScores, DIVERSITY_PAIRS,
    EmbeddingStatistics, MotionSample, MultimodalityProtocol, PENETRATION_TOLERANCE_M,
    R_PRECISION_BATCH, Retrieval, TOE_HEIGHT_M, contact_counts, contact_flags, contact_scores,
    diversity, fid, fid_from_statistics, fingertip_distances, foot_sliding, hand_contact,
    hand_object_distances, matching_distance, mean_interval, mixture_agreement,
    mixture_agreement_counts, mixture_weights_from_features, multimodality, penetration, quantile,
    r_precision, r_precision_of_ranks, r_precision_with, retrieval_ranks, runtime, symmetric_eigen,
    top_k_shares,
};
use dex2hoi_repr::mesh::box_mesh;
use dex2hoi_repr::{MeshQuery, Skeleton};
use glam::{Mat3, Vec3};

// ---------------------------------------------------------------------------------------------
// FID against scipy.
// ---------------------------------------------------------------------------------------------

/// Rows of an embedding set from a closed-form formula, rounded to f32 as the Python script does.
fn rows(count: usize, dim: usize, value: impl Fn(usize, usize) -> f64) -> Vec<Vec<f32>> {
    (0..count).map(|i| (0..dim).map(|j| value(i, j) as f32).collect()).collect()
}

/// `case_small` of `tests/fixtures/fid_golden.py` (the same operations in the same order).
fn case_small() -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
    let generated = rows(64, 8, |i, j| {
        let (i, j) = (i as f64, j as f64);
        (0.37 * i + 1.3 * j).sin() + 0.1 * (0.11 * i * j).cos()
    });
    let reference = rows(64, 8, |i, j| {
        let (i, j) = (i as f64, j as f64);
        (0.29 * i + 0.7 * j + 0.5).cos() * (1.0 + 0.05 * j) + 0.2
    });
    (generated, reference)
}

/// `nearly_singular_row` of the Python script.
fn nearly_singular_row(i: usize, dim: usize, phase: f64) -> Vec<f64> {
    let half = dim / 2;
    let fi = i as f64;
    let first: Vec<f64> =
        (0..half).map(|j| (0.13 * fi * (j as f64 + 1.0) + 0.7 * j as f64 + phase).sin()).collect();
    let second: Vec<f64> = (0..half)
        .map(|j| {
            0.5 * first[j]
                + 0.25 * first[(j + 1) % half]
                + 1e-4 * (0.31 * fi + 0.17 * j as f64 + phase).cos()
        })
        .collect();
    first.into_iter().chain(second).collect()
}

/// `case_nearly_singular` of the Python script: dim 32, covariances of numerical rank ~18.
fn case_nearly_singular() -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
    let generated = (0..200)
        .map(|i| nearly_singular_row(i, 32, 0.0).into_iter().map(|v| v as f32).collect())
        .collect();
    let reference = (0..200)
        .map(|i| {
            nearly_singular_row(i, 32, 0.4).into_iter().map(|v| (v * 1.1 + 0.05) as f32).collect()
        })
        .collect();
    (generated, reference)
}

/// `case_unequal` of the Python script: 100 against 150 rows of dim 16.
fn case_unequal() -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
    let generated = rows(100, 16, |i, j| {
        let (fi, fj) = (i as f64, j as f64);
        (0.21 * fi * (1 + j % 3) as f64 + 0.5 * fj).sin() * (1.0 + 0.1 * fj)
            + 0.3 * (0.05 * fi).cos()
    });
    let reference = rows(150, 16, |i, j| {
        let (i, j) = (i as f64, j as f64);
        (0.17 * i + 0.9 * j).cos() - 0.4 + 0.02 * j
    });
    (generated, reference)
}

// Golden values printed by `python3 crates/dex2hoi-eval/tests/fixtures/fid_golden.py`
// (scipy 1.17.1, numpy 2.4.6): `sqrtm(sigma1.dot(sigma2)).real`, as pytorch-fid and T2M.
const FID_SMALL: f64 = 7.176734953583436;
const FID_NEARLY_SINGULAR: f64 = 0.1881843499695428;
const FID_UNEQUAL: f64 = 32.1307309832752;

fn assert_relative(actual: f64, expected: f64, tolerance: f64, what: &str) {
    let error = (actual - expected).abs() / expected.abs().max(1e-300);
    assert!(
        error <= tolerance,
        "{what}: {actual} against {expected}, relative error {error:e} > {tolerance:e}"
    );
}

#[test]
fn fid_matches_scipy_golden_values() {
    for (what, (generated, reference), expected) in [
        ("dim 8, 64 rows", case_small(), FID_SMALL),
        ("dim 32, 200 rows, nearly singular", case_nearly_singular(), FID_NEARLY_SINGULAR),
        ("dim 16, 100 against 150 rows", case_unequal(), FID_UNEQUAL),
    ] {
        let value = fid(&generated, &reference).unwrap();
        assert_relative(value, expected, 1e-4, what);
    }
}

#[test]
fn fid_of_a_set_with_itself_is_zero_and_fid_is_symmetric() {
    for (generated, reference) in [case_small(), case_nearly_singular(), case_unequal()] {
        let itself = fid(&generated, &generated).unwrap();
        assert!(itself.abs() < 1e-9, "FID of a set with itself: {itself}");
        let forward = fid(&generated, &reference).unwrap();
        let backward = fid(&reference, &generated).unwrap();
        assert_relative(backward, forward, 1e-9, "FID symmetry");
    }
}

#[test]
fn fid_of_a_shifted_copy_is_the_squared_shift() {
    // Same covariance, means differ by (1, -2, 0.5, 0, ...): FID = 1 + 4 + 0.25 = 5.25.
    let (generated, _) = case_small();
    let shift = [1.0f32, -2.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
    let shifted: Vec<Vec<f32>> =
        generated.iter().map(|r| r.iter().zip(&shift).map(|(v, s)| v + s).collect()).collect();
    let value = fid(&generated, &shifted).unwrap();
    // The f32 rounding of the shifted values perturbs the covariance by ~1e-7.
    assert!((value - 5.25).abs() < 1e-5, "FID {value}");
}

#[test]
fn fid_statistics_follow_numpy_cov() {
    // Rows (0, 0), (2, 0), (1, 3): mean (1, 1); cov with ddof = 1:
    // xx = (1 + 1 + 0) / 2 = 1, yy = (1 + 1 + 4) / 2 = 3, xy = (1 - 1 + 0) / 2 = 0.
    let stats =
        EmbeddingStatistics::from_embeddings(&[vec![0.0, 0.0], vec![2.0, 0.0], vec![1.0, 3.0]])
            .unwrap();
    assert_eq!(stats.mean, vec![1.0, 1.0]);
    assert_eq!(stats.covariance, vec![1.0, 0.0, 0.0, 3.0]);
    // FID between N(0, diag(1, 3)) and N(0, diag(4, 3)) = 1 + 4 - 2 * 2 + 2 * (3 - 3) = 1.
    let other = EmbeddingStatistics {
        mean: vec![1.0, 1.0],
        covariance: vec![4.0, 0.0, 0.0, 3.0],
        ..stats.clone()
    };
    let value = fid_from_statistics(&stats, &other).unwrap();
    assert!((value - 1.0).abs() < 1e-12, "{value}");
}

#[test]
fn fid_rejects_bad_embeddings() {
    let good = vec![vec![0.0f32, 1.0], vec![1.0, 0.0], vec![2.0, 2.0]];
    assert!(fid(&good[..1], &good).is_err(), "one row");
    assert!(fid(&good, &[vec![0.0, 1.0], vec![1.0]]).is_err(), "ragged rows");
    assert!(fid(&good, &[vec![0.0, f32::NAN], vec![1.0, 0.0]]).is_err(), "NaN");
    assert!(fid(&good, &[vec![0.0, 1.0, 2.0], vec![1.0, 0.0, 2.0]]).is_err(), "other width");
    assert!(fid(&good, &[vec![], vec![]]).is_err(), "empty rows");
}

#[test]
fn symmetric_eigen_reconstructs_the_matrix() {
    // [[2, 1], [1, 2]] has eigenvalues 1 and 3.
    let eigen = symmetric_eigen(&[2.0, 1.0, 1.0, 2.0], 2, true).unwrap();
    assert!((eigen.values[0] - 1.0).abs() < 1e-12 && (eigen.values[1] - 3.0).abs() < 1e-12);
    // A 6x6 symmetric matrix from a formula: V diag(l) V^T must give it back, V orthonormal.
    let n = 6;
    let m: Vec<f64> = (0..n * n)
        .map(|k| {
            let (i, j) = (k / n, k % n);
            ((i + j) as f64 * 0.7).sin() + if i == j { i as f64 } else { 0.0 }
        })
        .collect();
    let eigen = symmetric_eigen(&m, n, true).unwrap();
    assert!(eigen.values.windows(2).all(|w| w[0] <= w[1]), "ascending");
    let v = &eigen.vectors;
    for i in 0..n {
        for j in 0..n {
            let rebuilt: f64 = (0..n).map(|k| v[i * n + k] * eigen.values[k] * v[j * n + k]).sum();
            assert!((rebuilt - m[i * n + j]).abs() < 1e-10, "A[{i}][{j}]");
            let dot: f64 = (0..n).map(|k| v[k * n + i] * v[k * n + j]).sum();
            assert!((dot - f64::from(u8::from(i == j))).abs() < 1e-10, "V^T V [{i}][{j}]");
        }
    }
    let values_only = symmetric_eigen(&m, n, false).unwrap();
    for (a, b) in values_only.values.iter().zip(&eigen.values) {
        assert!((a - b).abs() < 1e-10);
    }
    assert!(symmetric_eigen(&m[..35], n, false).is_err(), "wrong size");
    assert!(symmetric_eigen(&[f64::NAN], 1, false).is_err(), "NaN");
}

// ---------------------------------------------------------------------------------------------
// Diversity, MultiModality.
// ---------------------------------------------------------------------------------------------

/// `count` points, the first half at the origin and the second half at (3, 4): every pair is 0
/// or 5 apart.
fn two_clusters(count: usize) -> Vec<Vec<f32>> {
    (0..count).map(|i| if i < count / 2 { vec![0.0, 0.0] } else { vec![3.0, 4.0] }).collect()
}

#[test]
fn diversity_of_two_clusters_averages_to_half_the_gap() {
    // Independent uniform draws land in different clusters with probability 1/2, so the mean
    // distance is 2.5 in expectation; averaged over 40 seeds of 300 pairs the standard error is
    // 2.5 / sqrt(12000) ~ 0.023.
    let points = two_clusters(1000);
    let mean: f64 =
        (0..40).map(|seed| diversity(&points, DIVERSITY_PAIRS, seed).unwrap()).sum::<f64>() / 40.0;
    assert!((mean - 2.5).abs() < 0.1, "mean diversity {mean}");
    // Every single value is a multiple of 5 / 300.
    let one = diversity(&points, DIVERSITY_PAIRS, 7).unwrap();
    let steps = one * 300.0 / 5.0;
    assert!((steps - steps.round()).abs() < 1e-9, "{one}");
    // Same seed, same value; scaled points, scaled value.
    assert_eq!(one, diversity(&points, DIVERSITY_PAIRS, 7).unwrap());
    let doubled: Vec<Vec<f32>> =
        points.iter().map(|r| r.iter().map(|v| 2.0 * v).collect()).collect();
    assert!((diversity(&doubled, DIVERSITY_PAIRS, 7).unwrap() - 2.0 * one).abs() < 1e-12);
    // Identical points: 0.
    assert_eq!(diversity(&vec![vec![1.0, 2.0]; 400], DIVERSITY_PAIRS, 3).unwrap(), 0.0);
}

#[test]
fn diversity_rejects_bad_input() {
    let points = two_clusters(10);
    assert!(diversity(&points, 11, 0).is_err(), "more pairs than rows");
    assert!(diversity(&points, 0, 0).is_err(), "no pairs");
    assert!(diversity(&[vec![0.0], vec![f32::INFINITY]], 1, 0).is_err(), "infinity");
    assert!(diversity(&[], 1, 0).is_err(), "no rows");
}

#[test]
fn multimodality_averages_pair_distances_over_prompts() {
    let protocol = MultimodalityProtocol::paper();
    assert_eq!((protocol.prompts, protocol.repeats, protocol.pairs), (100, 30, 10));
    let small = MultimodalityProtocol::default();
    assert!(small.repeats >= small.pairs && small.prompts > 0);

    // Each prompt's generations on two clusters: expected pair distance 2.5 (as diversity).
    let group = two_clusters(30);
    let groups = vec![group.clone(); 4];
    let mean: f64 =
        (0..200).map(|seed| multimodality(&groups, 10, seed).unwrap()).sum::<f64>() / 200.0;
    // The same indices serve every prompt, so the spread is that of one prompt: 2.5 / sqrt(2000)
    // ~ 0.056 standard error.
    assert!((mean - 2.5).abs() < 0.25, "mean multimodality {mean}");
    // Prompts scaled by 1 and 3 share the draws: the average is twice one prompt's value.
    let tripled: Vec<Vec<f32>> =
        group.iter().map(|r| r.iter().map(|v| 3.0 * v).collect()).collect();
    let single = multimodality(std::slice::from_ref(&group), 10, 5).unwrap();
    let mixed = multimodality(&[group.clone(), tripled], 10, 5).unwrap();
    assert!((mixed - 2.0 * single).abs() < 1e-12, "{mixed} against 2 x {single}");
    // A prompt whose generations are all equal has MultiModality 0.
    assert_eq!(multimodality(&[vec![vec![0.5, 0.5]; 10]], 5, 1).unwrap(), 0.0);
}

#[test]
fn multimodality_rejects_bad_groups() {
    let group = two_clusters(10);
    assert!(multimodality(&[], 5, 0).is_err(), "no prompts");
    assert!(multimodality(&[group.clone(), group[..9].to_vec()], 5, 0).is_err(), "sizes differ");
    assert!(multimodality(std::slice::from_ref(&group), 11, 0).is_err(), "pairs > repeats");
    assert!(multimodality(&[group.clone(), vec![vec![0.0, 0.0, 0.0]; 10]], 5, 0).is_err());
}

// ---------------------------------------------------------------------------------------------
// R-precision, MMdist, replications, runtime.
// ---------------------------------------------------------------------------------------------

fn line(count: usize, offset: f32) -> Vec<Vec<f32>> {
    (0..count).map(|i| vec![i as f32 + offset, 0.0]).collect()
}

#[test]
fn r_precision_is_one_when_texts_equal_motions() {
    let motion = line(70, 0.0);
    for seed in 0..3 {
        assert_eq!(r_precision(&motion, &motion, R_PRECISION_BATCH, seed).unwrap(), [1.0; 3]);
    }
}

#[test]
fn r_precision_with_texts_shifted_towards_the_next_motion() {
    // Motions at x = i, texts at x = i + 0.6: for text i the motion i + 1 (0.4 away) is nearer
    // than its own (0.6 away) and every other is farther than 1.4. In one batch of all 32,
    // only the last text has no motion i + 1: top-1 = 1/32, top-2 = top-3 = 1.
    let motion = line(32, 0.0);
    let text = line(32, 0.6);
    let [top1, top2, top3] = r_precision(&motion, &text, 32, 11).unwrap();
    assert!((top1 - 1.0 / 32.0).abs() < 1e-12, "top-1 {top1}");
    assert_eq!((top2, top3), (1.0, 1.0));
    // With 70 pairs in batches of 32 the last 6 are dropped: 64 ranked texts. The own motion is
    // never worse than second, and top-1 counts the texts whose motion i + 1 is in another
    // batch, a whole number out of 64.
    let motion = line(70, 0.0);
    let text = line(70, 0.6);
    let [top1, top2, _] = r_precision(&motion, &text, 32, 3).unwrap();
    assert_eq!(top2, 1.0);
    let hits = top1 * 64.0;
    assert!((hits - hits.round()).abs() < 1e-9 && top1 > 0.0 && top1 < 1.0, "top-1 {top1}");
}

#[test]
fn r_precision_directions_differ_as_computed_by_hand() {
    // Motions at 0, 1, 10; texts at 0.9, 1.0, 10.
    // Text to motion: text 0 (0.9) is nearer motion 1 (0.1) than motion 0 (0.9): top-1 = 2/3.
    // Motion to text: motion 0 (0) is nearer text 0 (0.9) than text 1 (1.0); motion 1 (1) is on
    // text 1: top-1 = 1.
    let motion = vec![vec![0.0f32], vec![1.0], vec![10.0]];
    let text = vec![vec![0.9f32], vec![1.0], vec![10.0]];
    let t2m = r_precision_with(&motion, &text, 3, 0, Retrieval::TextToMotion).unwrap();
    assert!((t2m[0] - 2.0 / 3.0).abs() < 1e-12 && t2m[1] == 1.0 && t2m[2] == 1.0, "{t2m:?}");
    assert_eq!(r_precision(&motion, &text, 3, 0).unwrap(), t2m, "T2M's direction by default");
    let m2t = r_precision_with(&motion, &text, 3, 0, Retrieval::MotionToText).unwrap();
    assert_eq!(m2t, [1.0; 3]);
}

#[test]
fn retrieval_ranks_by_hand_and_per_subset() {
    // The hand-computed case above: text 0 has motion 1 nearer than its own (rank 1), texts 1
    // and 2 retrieve their own first.
    let motion = vec![vec![0.0f32], vec![1.0], vec![10.0]];
    let text = vec![vec![0.9f32], vec![1.0], vec![10.0]];
    let ranks = retrieval_ranks(&motion, &text, 3, 0, Retrieval::TextToMotion).unwrap();
    assert_eq!(ranks, vec![Some(1), Some(0), Some(0)]);
    // A subset's shares: texts 0 and 1 only, then text 0 alone.
    assert_eq!(top_k_shares([1, 0]), Some([0.5, 1.0, 1.0]));
    assert_eq!(top_k_shares([1]), Some([0.0, 1.0, 1.0]));
    assert_eq!(top_k_shares([3, 2]), Some([0.0, 0.0, 0.5]));
    assert_eq!(top_k_shares(std::iter::empty()), None);
    assert!(r_precision_of_ranks(&[None, None]).is_err(), "nothing ranked");
}

#[test]
fn retrieval_ranks_leave_out_the_dropped_remainder() {
    // 70 pairs in batches of 32: 64 ranked, 6 left out. A text's own motion is never worse than
    // second (motion i + 1 may be nearer), and some texts find motion i + 1 in their batch.
    let motion = line(70, 0.0);
    let text = line(70, 0.6);
    for seed in 0..3 {
        let ranks = retrieval_ranks(&motion, &text, 32, seed, Retrieval::TextToMotion).unwrap();
        assert_eq!(ranks.iter().filter(|r| r.is_none()).count(), 6);
        assert!(ranks.iter().flatten().all(|&r| r <= 1), "own motion first or second");
        let shares = r_precision_of_ranks(&ranks).unwrap();
        assert!(shares[0] < 1.0 && shares[1] == 1.0, "{shares:?}");
    }
}

#[test]
fn r_precision_and_matching_distance_reject_bad_input() {
    let motion = line(10, 0.0);
    assert!(r_precision(&motion, &motion, 11, 0).is_err(), "batch larger than the set");
    assert!(r_precision(&motion, &motion, 0, 0).is_err(), "batch 0");
    assert!(r_precision(&motion, &motion[..9], 4, 0).is_err(), "row counts differ");
    let wide: Vec<Vec<f32>> = (0..10).map(|i| vec![i as f32, 0.0, 0.0]).collect();
    assert!(r_precision(&motion, &wide, 4, 0).is_err(), "widths differ");
    assert!(matching_distance(&motion, &wide).is_err(), "widths differ");
    assert!(matching_distance(&[], &[]).is_err(), "no pairs");
}

#[test]
fn matching_distance_by_hand() {
    // Pairs ((0,0),(3,4)) and ((1,1),(1,1)): distances 5 and 0, mean 2.5.
    let motion = vec![vec![0.0f32, 0.0], vec![1.0, 1.0]];
    let text = vec![vec![3.0f32, 4.0], vec![1.0, 1.0]];
    assert_eq!(matching_distance(&motion, &text).unwrap(), 2.5);
}

#[test]
fn mean_interval_and_runtime_by_hand() {
    // 1, 2, 3, 4: mean 2.5, population variance 1.25, half-width 1.96 sqrt(1.25) / 2.
    let (mean, half) = mean_interval(&[1.0, 2.0, 3.0, 4.0]);
    assert_eq!(mean, 2.5);
    assert!((half - 1.96 * 1.25f64.sqrt() / 2.0).abs() < 1e-12, "{half}");
    assert_eq!(mean_interval(&[0.7]), (0.7, 0.0));
    let (mean, half) = mean_interval(&[]);
    assert!(mean.is_nan() && half.is_nan());
    let (mean, std) = runtime(&[0.2, 0.3]);
    assert!((mean - 0.25).abs() < 1e-12 && (std - 0.05).abs() < 1e-12, "{mean} {std}");
}

// ---------------------------------------------------------------------------------------------
// Motion metrics.
// ---------------------------------------------------------------------------------------------

/// Where unused joints wait: far from every object and above the feet thresholds.
const FAR: Vec3 = Vec3::new(10.0, 10.0, 10.0);

/// `[T, J, 3]` joints all at [`FAR`], then `place(t, j)` overrides.
fn joints_with(
    skeleton: &Skeleton,
    frames: usize,
    place: impl Fn(usize, usize) -> Option<Vec3>,
) -> Vec<f32> {
    let mut out = Vec::new();
    for t in 0..frames {
        for j in 0..skeleton.joint_count() {
            out.extend(place(t, j).unwrap_or(FAR).to_array());
        }
    }
    out
}

/// `[T, 2, 3, 3]` row-major rotations and `[T, 2, 3]` positions, the same pose every frame.
fn poses(frames: usize, slots: [(Mat3, Vec3); 2]) -> (Vec<f32>, Vec<f32>) {
    let mut rotations = Vec::new();
    let mut positions = Vec::new();
    for _ in 0..frames {
        for (rotation, position) in slots {
            rotations.extend(rotation.transpose().to_cols_array());
            positions.extend(position.to_array());
        }
    }
    (rotations, positions)
}

/// A 1 x 0.4 x 0.6 box turned 45 degrees about Y, its rotation and position: a wrong rotation
/// convention (R instead of R^T) would turn local points by 90 degrees and put them outside.
fn turned_box() -> (MeshQuery, Mat3, Vec3) {
    let query = MeshQuery::new(&box_mesh(Vec3::new(0.5, 0.2, 0.3))).unwrap();
    (query, Mat3::from_rotation_y(std::f32::consts::FRAC_PI_4), Vec3::new(1.0, 0.5, -2.0))
}

/// A sample whose first slot holds `query` at the poses of `slots`, the second slot empty.
fn first_slot_sample<'a>(
    skeleton: &'a Skeleton,
    joints: &'a [f32],
    slots: &'a (Vec<f32>, Vec<f32>),
    query: &'a MeshQuery,
) -> MotionSample<'a> {
    MotionSample {
        skeleton,
        joints,
        object_rotations: &slots.0,
        object_positions: &slots.1,
        present: [true, false],
        objects: [Some(query), None],
        mixture_weights: None,
    }
}

#[test]
fn penetration_of_joints_at_known_depths() {
    let skeleton = Skeleton::smplx();
    let (query, rotation, position) = turned_box();
    let world = |local: Vec3| rotation * local + position;
    // Depth below the x = 0.5 face: 0.5 - x (the y and z faces are farther).
    let depths = [
        (0, 0, 0.100), // frame 0, joint 0: 100 mm deep
        (0, 1, 0.003), // below the 5 mm tolerance: not counted
        (2, 3, 0.150), // frame 2: 150 mm and 50 mm
        (2, 5, 0.050),
    ];
    let frames = 3;
    let joints = joints_with(&skeleton, frames, |t, j| {
        depths
            .iter()
            .find(|&&(ft, fj, _)| ft == t && fj == j)
            .map(|&(_, _, depth)| world(Vec3::new(0.5 - depth, 0.0, 0.0)))
    });
    let slots = poses(frames, [(rotation, position), (Mat3::IDENTITY, Vec3::ZERO)]);
    let sample = first_slot_sample(&skeleton, &joints, &slots, &query);
    let result = penetration(&sample, PENETRATION_TOLERANCE_M).unwrap();
    assert_eq!(result.penetrating_joint_frames, 3);
    assert_eq!(result.penetrating_frames, 2);
    assert_eq!(result.frames, 3);
    assert!((result.mean_depth_mm - 300.0 / 3.0).abs() < 1e-3, "{}", result.mean_depth_mm);
    assert!((result.frame_share - 2.0 / 3.0).abs() < 1e-12);
    // Deepest per frame: 100, 0, 150 over three frames.
    assert!((result.mean_frame_depth_mm - 250.0 / 3.0).abs() < 1e-3);
    // A 2 mm tolerance counts the 3 mm joint too.
    let loose = penetration(&sample, 0.002).unwrap();
    assert_eq!(loose.penetrating_joint_frames, 4);
    // Pooling two copies changes counts, not ratios.
    let pooled = dex2hoi_eval::metrics::Penetration::pooled(&[result, result]);
    assert_eq!(pooled.frames, 6);
    assert!((pooled.mean_depth_mm - result.mean_depth_mm).abs() < 1e-9);

    // The second slot holds a unit cube at the origin of the world; joint 0 of frame 1 sits
    // 0.2 deep in it. Slot 1 absent: not counted; present: counted.
    let cube = MeshQuery::new(&box_mesh(Vec3::splat(0.5))).unwrap();
    let joints = joints_with(&skeleton, frames, |t, j| {
        (t == 1 && j == 0).then_some(Vec3::new(0.3, 0.0, 0.0))
    });
    let sample_two =
        MotionSample { joints: &joints, objects: [Some(&query), Some(&cube)], ..sample };
    assert_eq!(penetration(&sample_two, PENETRATION_TOLERANCE_M).unwrap().penetrating_frames, 0);
    let sample_two = MotionSample { present: [true, true], ..sample_two };
    let result = penetration(&sample_two, PENETRATION_TOLERANCE_M).unwrap();
    assert_eq!(result.penetrating_frames, 1);
    assert!((result.mean_depth_mm - 200.0).abs() < 1e-3, "{}", result.mean_depth_mm);
}

#[test]
fn fingertip_distances_on_the_ground_truths_contact_frames() {
    let skeleton = Skeleton::smplx();
    let groups = skeleton.groups().clone();
    // A fingertip `d` outside the turned box's x = 0.5 face sits at local x = 0.5 + d.
    let (query, rotation, position) = turned_box();
    let at = |d: f32| rotation * Vec3::new(0.5 + d, 0.0, 0.0) + position;
    let frames = 3;
    // Left fingertip k at 2k mm outside (k = 0..5), the right ones 4 mm inside; the rest far.
    let joints = joints_with(&skeleton, frames, |_, j| {
        if let Some(k) = groups.left_fingertips.iter().position(|&f| f == j) {
            return Some(at(0.002 * k as f32));
        }
        groups.right_fingertips.contains(&j).then(|| at(-0.004))
    });
    let slots = poses(frames, [(rotation, position), (Mat3::IDENTITY, Vec3::ZERO)]);
    let sample = first_slot_sample(&skeleton, &joints, &slots, &query);
    // `[T, slot, hand]`: frame 0 the left hand on slot 0, frame 1 nothing, frame 2 both hands
    // on slot 0; slot 1 (absent) flagged on frame 1 and not measured.
    let contact = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0];
    let distances = fingertip_distances(&sample, &contact).unwrap();
    let left: Vec<f32> = (0..5).map(|k| 0.002 * k as f32).collect();
    let expected: Vec<f32> = left.iter().chain(&left).chain(&[-0.004; 5]).copied().collect();
    assert_eq!(distances.len(), expected.len());
    for (d, e) in distances.iter().zip(&expected) {
        assert!((d - e).abs() < 1e-5, "{distances:?}");
    }
    assert!(fingertip_distances(&sample, &contact[..8]).is_err());
    assert!(fingertip_distances(&sample, &[f32::NAN; 12]).is_err());

    // Quantiles as numpy's default (linear): [1, 2, 3, 4] -> 5th percentile 1.15, median 2.5.
    let values = [4.0, 1.0, 3.0, 2.0];
    assert!((quantile(&values, 0.05).unwrap() - 1.15).abs() < 1e-12);
    assert!((quantile(&values, 0.5).unwrap() - 2.5).abs() < 1e-12);
    assert_eq!(quantile(&values, 1.0), Some(4.0));
    assert_eq!(quantile(&[], 0.5), None);
}

#[test]
fn penetration_rejects_bad_samples() {
    let skeleton = Skeleton::smplx();
    let query = MeshQuery::new(&box_mesh(Vec3::splat(0.5))).unwrap();
    let joints = joints_with(&skeleton, 2, |_, _| None);
    let (rotations, positions) = poses(2, [(Mat3::IDENTITY, Vec3::ZERO); 2]);
    let good = MotionSample {
        skeleton: &skeleton,
        joints: &joints,
        object_rotations: &rotations,
        object_positions: &positions,
        present: [true, false],
        objects: [Some(&query), None],
        mixture_weights: None,
    };
    assert!(penetration(&good, PENETRATION_TOLERANCE_M).is_ok());
    assert!(penetration(&good, -0.001).is_err(), "negative tolerance");
    assert!(penetration(&good, f32::NAN).is_err(), "NaN tolerance");
    let no_mesh = MotionSample { objects: [None, None], ..good };
    assert!(penetration(&no_mesh, 0.005).is_err(), "present slot without a mesh");
    let short = MotionSample { joints: &joints[..joints.len() - 3], ..good };
    assert!(penetration(&short, 0.005).is_err(), "joints not [T, J, 3]");
    let few = MotionSample { object_positions: &positions[..6], ..good };
    assert!(penetration(&few, 0.005).is_err(), "positions of one frame for two");
    let mut nan_joints = joints.clone();
    nan_joints[4] = f32::NAN;
    let nan = MotionSample { joints: &nan_joints, ..good };
    assert!(penetration(&nan, 0.005).is_err(), "NaN joint");
    let weights = vec![0.0f32; 5];
    let bad_weights = MotionSample { mixture_weights: Some(&weights), ..good };
    assert!(bad_weights.frames().is_err(), "mixture weights not [T, 2, 3]");
    let empty = MotionSample { joints: &[], ..good };
    assert!(empty.frames().is_err(), "no frames");
}

#[test]
fn contact_scores_by_hand() {
    let skeleton = Skeleton::smplx();
    let groups = skeleton.groups().clone();
    let query = MeshQuery::new(&box_mesh(Vec3::splat(0.5))).unwrap();
    let position = Vec3::new(0.0, 1.0, 0.0);
    // Frame 0: left wrist 3 cm above the top face (contact). Frame 1: 8 cm (none).
    // Frame 2: a right fingertip 1 cm inside (contact, distance 0). Frame 3: nothing near.
    let right_tip = groups.right_fingertips[0];
    let joints = joints_with(&skeleton, 4, |t, j| match (t, j) {
        (0, j) if j == groups.left_wrist => Some(position + Vec3::new(0.1, 0.53, 0.0)),
        (1, j) if j == groups.left_wrist => Some(position + Vec3::new(0.1, 0.58, 0.0)),
        (2, j) if j == right_tip => Some(position + Vec3::new(0.0, 0.0, 0.49)),
        _ => None,
    });
    let (rotations, positions) =
        poses(4, [(Mat3::IDENTITY, position), (Mat3::IDENTITY, Vec3::ZERO)]);
    let sample = MotionSample {
        skeleton: &skeleton,
        joints: &joints,
        object_rotations: &rotations,
        object_positions: &positions,
        present: [true, false],
        objects: [Some(&query), None],
        mixture_weights: None,
    };
    let distances = hand_object_distances(&sample).unwrap();
    assert!((distances[0][0][0] - 0.03).abs() < 1e-5, "{:?}", distances[0]);
    assert!((distances[1][0][0] - 0.08).abs() < 1e-5);
    assert!((distances[2][0][1] + 0.01).abs() < 1e-5);
    assert_eq!(distances[0][1], [f32::INFINITY; 2], "empty slot");
    let contact = hand_contact(&sample, CONTACT_RADIUS_M).unwrap();
    assert_eq!(contact, vec![[true, false], [false, false], [true, false], [false, false]]);

    // Ground truth [T, 2, 2]: contact in frames 0 and 1 (left hand); slot 1 flags are ignored
    // because slot 1 is empty. TP = 1 (frame 0), FN = 1 (frame 1), FP = 1 (frame 2), TN = 1.
    #[rustfmt::skip]
    let truth = [
        1.0, 0.0,  1.0, 1.0,
        0.0, 1.0,  1.0, 1.0,
        0.0, 0.0,  1.0, 1.0,
        0.0, 0.0,  1.0, 1.0,
    ];
    let scores = contact_scores(&sample, &truth, CONTACT_RADIUS_M).unwrap();
    assert_eq!((scores.counts.true_positives, scores.counts.false_positives), (1, 1), "{scores:?}");
    assert_eq!((scores.counts.false_negatives, scores.counts.true_negatives), (1, 1));
    assert_eq!((scores.precision, scores.recall, scores.f1), (0.5, 0.5, 0.5));
    // Distances on the ground-truth contact frames: 30 mm and 80 mm.
    let mean = scores.mean_distance_on_contact_mm.unwrap();
    assert!((mean - 55.0).abs() < 0.01, "{mean}");
    // A 10 cm radius also catches frame 1: recall 1, precision 2/3.
    let wide = contact_scores(&sample, &truth, 0.10).unwrap();
    assert_eq!(wide.recall, 1.0);
    assert!((wide.precision - 2.0 / 3.0).abs() < 1e-12);
    assert!(contact_scores(&sample, &truth[..12], CONTACT_RADIUS_M).is_err(), "3 truth frames");
    assert!(contact_scores(&sample, &truth, -1.0).is_err(), "negative radius");
    assert!(hand_contact(&sample, f32::INFINITY).is_err(), "infinite radius");
}

#[test]
fn contact_counts_on_hand_made_flags() {
    let predicted = [[true, false], [true, true], [false, true], [false, false], [true, true]];
    let truth = [[true, true], [false, true], [false, false], [true, false], [true, true]];
    // Slot 0: TP (0, 4), FP (1), FN (3), TN (2). Slot 1: TP (1, 4), FP (2), FN (0), TN (3).
    let both = contact_counts(&predicted, &truth, [true, true]).unwrap();
    assert_eq!(
        (both.true_positives, both.false_positives, both.false_negatives, both.true_negatives),
        (4, 2, 2, 2)
    );
    let scores = ContactScores::from_counts(both);
    assert!((scores.precision - 4.0 / 6.0).abs() < 1e-12);
    assert!((scores.recall - 4.0 / 6.0).abs() < 1e-12);
    assert!((scores.f1 - 4.0 / 6.0).abs() < 1e-12);
    assert_eq!(scores.mean_distance_on_contact_mm, None);
    // Slot 0 only: P = 2/3, R = 2/3.
    let first = contact_counts(&predicted, &truth, [true, false]).unwrap();
    assert_eq!((first.true_positives, first.false_positives, first.false_negatives), (2, 1, 1));
    // Precision 1, recall 1/3: F1 = 2 * 1/3 / (4/3) = 1/2.
    let counts = ContactCounts { true_positives: 1, false_negatives: 2, ..Default::default() };
    assert!((ContactScores::from_counts(counts).f1 - 0.5).abs() < 1e-12);
    let merged = counts.merge(counts);
    assert_eq!((merged.true_positives, merged.false_negatives), (2, 4));
    // Nothing predicted, nothing true: the undefined ratios are 0.
    let none = ContactScores::from_counts(ContactCounts::default());
    assert_eq!((none.precision, none.recall, none.f1), (0.0, 0.0, 0.0));
    assert!(contact_counts(&predicted[..4], &truth, [true, true]).is_err());
    // [T, 2, 2] numbers to flags.
    assert_eq!(
        contact_flags(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).unwrap(),
        vec![[true, false], [false, true]]
    );
    assert!(contact_flags(&[1.0, 0.0, 0.0]).is_err());
}

#[test]
fn foot_sliding_of_a_constructed_trajectory() {
    let skeleton = Skeleton::smplx();
    let groups = skeleton.groups().clone();
    let (left_ankle, left_toe) = (groups.left_foot[0], *groups.left_foot.last().unwrap());
    let (right_ankle, right_toe) = (groups.right_foot[0], *groups.right_foot.last().unwrap());
    // Left ankle on the floor sliding 1 cm per frame along x: weight 2 - 2^0 = 1, 10 mm.
    // Left toe at 2 cm sliding 1 cm per frame along z: weight 2 - 2^(0.02/0.04) = 2 - sqrt 2.
    // Right ankle at 10 cm (above 8 cm) sliding: not counted. Right toe on the floor, still.
    // Vertical motion of the right toe (none) and of the body (all at FAR, still) adds nothing.
    let frames = 5;
    let joints = joints_with(&skeleton, frames, |t, j| {
        let s = 0.01 * t as f32;
        match j {
            j if j == left_ankle => Some(Vec3::new(s, 0.0, 0.0)),
            j if j == left_toe => Some(Vec3::new(0.0, 0.02, s)),
            j if j == right_ankle => Some(Vec3::new(s, 0.10, 0.0)),
            j if j == right_toe => Some(Vec3::new(0.3, 0.0, 0.0)),
            _ => None,
        }
    });
    let value = foot_sliding(&joints, &skeleton).unwrap();
    let expected = (10.0 + 10.0 * (2.0 - 2f64.sqrt())) / 4.0;
    assert!((value - expected).abs() < 1e-3, "{value} against {expected}");
    assert_eq!((ANKLE_HEIGHT_M, TOE_HEIGHT_M), (0.08, 0.04));

    // The same ankle 8 cm up (the threshold itself) does not count.
    let lifted = joints_with(&skeleton, frames, |t, j| {
        (j == left_ankle).then(|| Vec3::new(0.01 * t as f32, ANKLE_HEIGHT_M, 0.0))
    });
    assert_eq!(foot_sliding(&lifted, &skeleton).unwrap(), 0.0);
    assert!(foot_sliding(&joints[..skeleton.joint_count() * 3], &skeleton).is_err(), "1 frame");
    assert!(foot_sliding(&joints[1..], &skeleton).is_err(), "not [T, J, 3]");
}

#[test]
fn mixture_agreement_by_hand() {
    // Slot 0 present, slot 1 empty. Ground truth: frame 0 left only, frame 1 right only,
    // frame 2 both hands, frame 3 none. Slot 1 claims the left hand every frame (ignored).
    #[rustfmt::skip]
    let truth = [
        1.0, 0.0,  1.0, 0.0,
        0.0, 1.0,  1.0, 0.0,
        1.0, 1.0,  1.0, 0.0,
        0.0, 0.0,  1.0, 0.0,
    ];
    // Weights (left, right, global): frame 0 picks left (agrees), frame 1 picks left (does not).
    #[rustfmt::skip]
    let weights = [
        0.7, 0.2, 0.1,  0.0, 0.0, 1.0,
        0.6, 0.3, 0.1,  0.0, 0.0, 1.0,
        0.1, 0.1, 0.8,  0.0, 0.0, 1.0,
        0.1, 0.1, 0.8,  0.0, 0.0, 1.0,
    ];
    assert_eq!(mixture_agreement_counts(&weights, &truth, [true, false]).unwrap(), (1, 2));
    assert_eq!(mixture_agreement(&weights, &truth, [true, false]).unwrap(), Some(0.5));
    // Slot 1 present too: 4 more single-hand frames, none agreeing (global wins there).
    assert_eq!(mixture_agreement_counts(&weights, &truth, [true, true]).unwrap(), (1, 6));
    // No single-hand frames: None.
    assert_eq!(mixture_agreement(&weights, &[0.0; 16], [true, true]).unwrap(), None);
    assert!(mixture_agreement(&weights[..21], &truth, [true, false]).is_err(), "3 frames");
    let mut nan = weights;
    nan[0] = f32::NAN;
    assert!(mixture_agreement(&nan, &truth, [true, false]).is_err(), "NaN weight");
}

#[test]
fn mixture_weights_are_the_softmax_of_the_feature_logits() {
    let mut features = vec![0.0f32; 2 * 18];
    features[15..18].copy_from_slice(&[0.0, 2f32.ln(), 0.0]); // weights 1/4, 1/2, 1/4
    let weights = mixture_weights_from_features(&features).unwrap();
    let expected = [0.25, 0.5, 0.25, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0];
    for (w, e) in weights.iter().zip(expected) {
        assert!((w - e).abs() < 1e-6, "{weights:?}");
    }
    assert!(mixture_weights_from_features(&features[..35]).is_err());
    features[16] = f32::NAN;
    assert!(mixture_weights_from_features(&features).is_err());
}

// ---------------------------------------------------------------------------------------------
// Instruction following and object behaviour.
// ---------------------------------------------------------------------------------------------

/// A scene for the instruction metrics: the body stands in its rest pose (left is +X), each
/// hand is at `hand(t, hand)` (or far away), and the two objects are at `objects(t)`.
struct Scene {
    joints: Vec<f32>,
    rotations: Vec<f32>,
    positions: Vec<f32>,
}

impl Scene {
    fn new(
        skeleton: &Skeleton,
        frames: usize,
        hand: impl Fn(usize, usize) -> Option<Vec3>,
        objects: impl Fn(usize) -> [Vec3; 2],
    ) -> Self {
        let rest = skeleton.rest_positions();
        let groups = skeleton.groups();
        let joints = joints_with(skeleton, frames, |t, j| {
            let side = [&groups.left_hand, &groups.right_hand].iter().position(|g| g.contains(&j));
            match side {
                Some(side) => hand(t, side),
                None => Some(rest[j]),
            }
        });
        let mut rotations = Vec::new();
        let mut positions = Vec::new();
        for t in 0..frames {
            for position in objects(t) {
                rotations.extend(Mat3::IDENTITY.to_cols_array());
                positions.extend(position.to_array());
            }
        }
        Self { joints, rotations, positions }
    }

    fn sample<'a>(&'a self, skeleton: &'a Skeleton, box_query: &'a MeshQuery) -> MotionSample<'a> {
        MotionSample {
            skeleton,
            joints: &self.joints,
            object_rotations: &self.rotations,
            object_positions: &self.positions,
            present: [true, true],
            objects: [Some(box_query), Some(box_query)],
            mixture_weights: None,
        }
    }
}

#[test]
fn instruction_following_by_hand() {
    use dex2hoi_eval::metrics::{
        instruction_following, median, object_sinking, object_start_jumps, object_start_turns,
        turn_degrees, untouched_object_speeds, untouched_object_turn_rates,
    };
    let skeleton = Skeleton::smplx();
    let query = MeshQuery::new(&box_mesh(Vec3::splat(0.04))).unwrap();
    let pelvis = skeleton.rest_positions()[0];
    let frames = 6;
    // Ground truth: the right hand lifts object 0 by 4 cm per frame from frame 1 and carries it
    // 30 cm to the body's right; object 1 stays. Generated: the left hand lifts object 0 and
    // puts it 30 cm to the left; object 1 slides 6 cm per frame with no hand near it.
    let start = [pelvis + Vec3::new(0.0, 0.0, 0.4), pelvis + Vec3::new(0.4, 0.0, 0.4)];
    let lifted = |t: usize, across: f32| {
        let k = t.saturating_sub(1) as f32 / (frames - 2) as f32;
        start[0] + Vec3::new(across * k, 0.04 * t.saturating_sub(1) as f32, 0.0)
    };
    let truth = Scene::new(
        &skeleton,
        frames,
        |t, side| (t >= 1 && side == 1).then(|| lifted(t, -0.3)),
        |t| [lifted(t, -0.3), start[1]],
    );
    let generated = Scene::new(
        &skeleton,
        frames,
        |t, side| (t >= 1 && side == 0).then(|| lifted(t, 0.3)),
        |t| [lifted(t, 0.3), start[1] + Vec3::new(0.0, 0.0, 0.06 * t as f32)],
    );
    let (truth, generated) = (truth.sample(&skeleton, &query), generated.sample(&skeleton, &query));
    let counts = instruction_following(&generated, &truth).unwrap();
    assert_eq!((counts.moved_in_truth, counts.moved_in_both), (1, 1));
    assert_eq!((counts.still_in_truth, counts.moved_unasked), (1, 1));
    // Five holding frames (1-5), all with the other hand.
    assert_eq!((counts.held_frames, counts.same_holder_frames), (5, 0));
    assert_eq!(counts.same_side, 0, "one ends left, the other right");
    assert!((counts.end_distances_m[0] - 0.6).abs() < 1e-5, "{:?}", counts.end_distances_m);
    assert_eq!(counts.moved_share(), Some(1.0));
    assert_eq!(counts.holder_share(), Some(0.0));
    // The ground truth against itself agrees everywhere.
    let same = instruction_following(&truth, &truth).unwrap();
    assert_eq!((same.same_holder_frames, same.same_side, same.moved_unasked), (5, 1, 0));
    assert_eq!(same.median_end_distance_m(), Some(0.0));
    // Merging adds counts.
    let both = counts.clone().merge(&same);
    assert_eq!((both.held_frames, both.same_holder_frames), (10, 5));
    assert_eq!(both.holder_share(), Some(0.5));

    // Start jumps from the last prefix positions: 3 cm for object 0, none for object 1.
    let prefix = [start[0] - Vec3::new(0.0, 0.0, 0.03), start[1]];
    let jumps = object_start_jumps(&generated, prefix).unwrap();
    assert!((jumps[0].unwrap() - 0.03).abs() < 1e-6 && jumps[1] == Some(0.0), "{jumps:?}");
    // Untouched speeds at 20 fps: the ground truth's object 1 stands still on its 5 steps
    // (object 0 is touched from frame 1 on: its step 0 -> 1 does not count); the generated
    // object 1 slides 6 cm per frame, 1.2 m/s.
    let still = untouched_object_speeds(&truth, 20.0).unwrap();
    assert_eq!(still, vec![0.0; 5]);
    let sliding = untouched_object_speeds(&generated, 20.0).unwrap();
    assert_eq!(sliding.len(), 5);
    assert!(sliding.iter().all(|v| (v - 1.2).abs() < 1e-4), "{sliding:?}");
    // Sinking below the resting heights: the lifted object never goes below; object 1, lowered
    // by 2 cm per frame, reaches 10 cm below on frame 5 and is more than 1 cm below on frames
    // 1-5.
    let sinking = object_sinking(&generated, start).unwrap();
    assert_eq!(
        (sinking.deepest_m.clone(), sinking.frames_below, sinking.frames),
        (vec![0.0, 0.0], 0, 6)
    );
    let mut lowered = generated.object_positions.to_vec();
    for t in 0..frames {
        lowered[(t * 2 + 1) * 3 + 1] -= 0.02 * t as f32;
    }
    let sunk = MotionSample { object_positions: &lowered, ..generated };
    let sinking = object_sinking(&sunk, start).unwrap();
    assert!(
        sinking.deepest_m[0] == 0.0 && (sinking.deepest_m[1] - 0.10).abs() < 1e-6,
        "{sinking:?}"
    );
    assert_eq!((sinking.frames_below, sinking.frames), (5, 6));
    assert!(object_sinking(&sunk, [Vec3::ZERO, Vec3::NAN]).is_err());
    // Turns: the generated object 1, untouched, also turns 2 degrees per frame about the
    // vertical, 40 degrees per second at 20 fps; the ground truth's stands still.
    let row_major = |m: Mat3| m.transpose().to_cols_array();
    let mut turning = generated.object_rotations.to_vec();
    for t in 0..frames {
        let r = (t * 2 + 1) * 9;
        let turn = Mat3::from_rotation_y((2.0 * t as f32).to_radians());
        turning[r..r + 9].copy_from_slice(&row_major(turn));
    }
    let turned = MotionSample { object_rotations: &turning, ..generated };
    let rates = untouched_object_turn_rates(&turned, 20.0).unwrap();
    assert_eq!(rates.len(), 5);
    assert!(rates.iter().all(|v| (v - 40.0).abs() < 1e-2), "{rates:?}");
    assert_eq!(untouched_object_turn_rates(&truth, 20.0).unwrap(), vec![0.0; 5]);
    // Start turns from the last prefix rotations: 10 degrees about X for object 0, none for
    // object 1 (its first frame is unturned).
    let prefix = [Mat3::from_rotation_x(10f32.to_radians()), Mat3::IDENTITY];
    let turns = object_start_turns(&turned, prefix).unwrap();
    assert!((turns[0].unwrap() - 10.0).abs() < 1e-3 && turns[1] == Some(0.0), "{turns:?}");
    assert!(object_start_turns(&turned, [Mat3::NAN, Mat3::IDENTITY]).is_err());
    assert!(untouched_object_turn_rates(&truth, f32::NAN).is_err());
    let quarter = turn_degrees(Mat3::IDENTITY, Mat3::from_rotation_z(std::f32::consts::FRAC_PI_2));
    assert!((quarter - 90.0).abs() < 1e-4, "{quarter}");
    let half =
        turn_degrees(Mat3::from_rotation_x(0.3), Mat3::from_rotation_x(0.3 + std::f32::consts::PI));
    assert!((half - 180.0).abs() < 0.1, "{half}");
    assert_eq!(median(&[3.0, 1.0, 2.0, 10.0]), Some(2.5));
    assert_eq!(median(&[]), None);

    // Bad input: different frame counts or objects, a bad frame rate, a NaN prefix.
    let short = MotionSample {
        joints: &generated.joints[..generated.joints.len() - skeleton.joint_count() * 3],
        object_rotations: &generated.object_rotations[..(frames - 1) * 18],
        object_positions: &generated.object_positions[..(frames - 1) * 6],
        ..generated
    };
    assert!(instruction_following(&short, &truth).is_err());
    let one = MotionSample { present: [true, false], ..generated };
    assert!(instruction_following(&one, &truth).is_err());
    assert!(untouched_object_speeds(&truth, 0.0).is_err());
    assert!(object_start_jumps(&truth, [Vec3::NAN, Vec3::ZERO]).is_err());
}

#[test]
fn long_generation_by_hand() {
    use dex2hoi_eval::metrics::{
        LIFT_M, LongCounts, lift_count, long_generation, long_medians, seam_course,
    };
    let skeleton = Skeleton::smplx();
    let half = 0.04;
    let query = MeshQuery::new(&box_mesh(Vec3::splat(half))).unwrap();
    let pelvis = skeleton.rest_positions()[0];
    let frames = 60;
    let start = [pelvis + Vec3::new(0.0, 0.0, 0.4), pelvis + Vec3::new(0.4, 0.0, 0.4)];
    let support = start.map(|p| p.y - half);
    // A lift of object 0 by `hand` over frames `from..to`: 10 cm up, `across` sideways, back
    // down on frame `to`; the hand holds it on those frames.
    let carry = |t: usize, (from, to): (usize, usize), across: f32| -> Option<Vec3> {
        (from..to).contains(&t).then(|| {
            let k = (t - from) as f32 / (to - from - 1) as f32;
            let up = 0.10 * (std::f32::consts::PI * k).sin();
            start[0] + Vec3::new(across * k, up, 0.0)
        })
    };
    let resting = |t: usize, lifts: &[((usize, usize), f32)]| {
        let mut at = start[0];
        for &(span, across) in lifts {
            if t >= span.1 {
                at = start[0] + Vec3::new(across, 0.0, 0.0);
            }
            if let Some(p) = carry(t, span, across) {
                return p;
            }
        }
        at
    };
    // Ground truth: the right hand (side 1) puts object 0 30 cm to the right over frames
    // 10-20; object 1 stays.
    let once = [((10, 21), -0.3)];
    let truth = Scene::new(
        &skeleton,
        frames,
        |t, side| (side == 1).then(|| carry(t, once[0].0, -0.3)).flatten(),
        |t| [resting(t, &once), start[1]],
    );
    // Generated: the same, then the right hand lifts object 0 again over frames 35-45 and puts
    // it back where it was; object 1 sinks 0.1 cm a frame, untouched (3 cm in 30 frames, then
    // it stays).
    let twice = [((10, 21), -0.3), ((35, 46), 0.0)];
    let again = |t: usize| {
        carry(t, (10, 21), -0.3).or(carry(t, (35, 46), 0.0).map(|p| p + Vec3::new(-0.3, 0.0, 0.0)))
    };
    let generated = Scene::new(
        &skeleton,
        frames,
        |t, side| (side == 1).then(|| again(t)).flatten(),
        |t| {
            let sink = 0.001 * t.min(30) as f32;
            let first = match t {
                35..46 => again(t).unwrap(),
                _ => resting(t, &twice[..1]),
            };
            [first, start[1] - Vec3::new(0.0, sink, 0.0)]
        },
    );
    let (truth, generated) = (truth.sample(&skeleton, &query), generated.sample(&skeleton, &query));
    let counts = long_generation(&generated, &truth, start, support, 20.0).unwrap();
    assert_eq!((counts.generations, counts.as_asked, counts.objects), (1, 1, 2));
    assert_eq!((counts.moved_in_truth, counts.moved_agree), (1, 2));
    assert_eq!((counts.hands_agree, counts.travel_agrees), (1, 1));
    assert_eq!(counts.lifted_again, 1, "object 0 lifted a second time, unasked");
    assert!((counts.deepest_sink_m[1] - 0.03).abs() < 1e-5, "{:?}", counts.deepest_sink_m);
    assert_eq!(counts.highest_float_m, vec![0.0, 0.0]);
    assert_eq!(counts.start_jumps_m, vec![0.0, 0.0]);
    let [off, sink, float, _, jump, ..] = long_medians(&counts);
    assert!((off.unwrap() - 0.015).abs() < 1e-5 && (sink.unwrap() - 0.015).abs() < 1e-5);
    assert_eq!((float, jump), (Some(0.0), Some(0.0)));
    // The ground truth against itself: the task as asked, nothing lifted again, nothing off its
    // support or moving while untouched.
    let same = long_generation(&truth, &truth, start, support, 20.0).unwrap();
    assert_eq!((same.as_asked, same.lifted_again), (1, 0));
    assert_eq!(same.off_support_m(), vec![0.0, 0.0]);
    assert!(same.untouched_speeds.iter().all(|&v| v == 0.0) && !same.untouched_speeds.is_empty());
    // The other hand, the other side: not as asked.
    let wrong = Scene::new(
        &skeleton,
        frames,
        |t, side| (side == 0).then(|| carry(t, once[0].0, 0.3)).flatten(),
        |t| [resting(t, &[((10, 21), 0.3)]), start[1]],
    );
    let wrong = wrong.sample(&skeleton, &query);
    let counts = long_generation(&wrong, &truth, start, support, 20.0).unwrap();
    assert_eq!((counts.as_asked, counts.hands_agree, counts.travel_agrees), (0, 0, 0));
    // A floating object: placed 2 cm above its support, it floats 2 cm, and jumps 2 cm at the
    // start.
    let raised = Scene::new(
        &skeleton,
        frames,
        |_, _| None,
        |_| [start[0] + Vec3::new(0.0, 0.02, 0.0), start[1]],
    );
    let raised = raised.sample(&skeleton, &query);
    let counts = long_generation(&raised, &truth, start, support, 20.0).unwrap();
    assert!((counts.highest_float_m[0] - 0.02).abs() < 1e-5, "{:?}", counts.highest_float_m);
    assert!((counts.start_jumps_m[0] - 0.02).abs() < 1e-5);
    assert_eq!((counts.moved_agree, counts.as_asked), (1, 0), "object 0 never moves");
    // Lifts: runs above LIFT_M, a gap of fewer than 3 frames merged, runs under 2 frames dropped.
    let up = LIFT_M + 0.01;
    let heights = [0.0, up, up, 0.0, up, up, 0.0, 0.0, 0.0, up, up, 0.0, 0.0, 0.0, 0.0, up];
    assert_eq!(lift_count(&heights, 2, 3), 2);
    assert_eq!(lift_count(&heights, 2, 1), 3);
    assert_eq!(lift_count(&heights, 1, 1), 4);
    // Seams of windows of 20 frames: the whole body rises 2 cm on frames 20 and 40, object 0
    // moves 3 cm on frame 40, and nothing moves between them.
    let rest = skeleton.rest_positions();
    let risen = Scene {
        joints: joints_with(&skeleton, frames, |t, j| {
            Some(rest[j] + Vec3::Y * (0.02 * (t / 20) as f32))
        }),
        ..Scene::new(
            &skeleton,
            frames,
            |_, _| None,
            |t| [start[0] + Vec3::X * if t >= 40 { 0.03 } else { 0.0 }, start[1]],
        )
    };
    let seams = seam_course(&risen.sample(&skeleton, &query), 20).unwrap();
    let near = |got: &[f64], want: &[f64]| {
        got.len() == want.len() && got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5)
    };
    assert!(near(&seams.body_jumps_m, &[0.02, 0.02]), "{:?}", seams.body_jumps_m);
    // Per seam, slot 0 then slot 1.
    assert!(near(&seams.object_jumps_m, &[0.0, 0.0, 0.03, 0.0]), "{:?}", seams.object_jumps_m);
    assert!((seams.floor_drift_m - 0.04).abs() < 1e-5, "{}", seams.floor_drift_m);
    let counts = LongCounts::default().with_seams(&seams).with_seams(&seams);
    let [.., body_seam, object_seam, floor] = long_medians(&counts);
    assert!((body_seam.unwrap() - 0.02).abs() < 1e-5 && (floor.unwrap() - 0.04).abs() < 1e-5);
    assert_eq!(object_seam, Some(0.0), "three of every four object jumps are 0");
    // A motion that never moves: no jump at any seam, no drift; a window of the whole motion
    // has no seam.
    let still = seam_course(&raised, 20).unwrap();
    assert!(near(&still.body_jumps_m, &[0.0, 0.0]) && still.floor_drift_m == 0.0);
    assert!(seam_course(&raised, frames).unwrap().body_jumps_m.is_empty());
    assert!(seam_course(&raised, 0).is_err());
    // Bad input.
    assert!(long_generation(&generated, &truth, start, [0.0, f32::NAN], 20.0).is_err());
    assert!(long_generation(&generated, &truth, start, support, 0.0).is_err());
    let one = MotionSample { present: [true, false], ..generated };
    assert!(long_generation(&one, &truth, start, support, 20.0).is_err());
}
