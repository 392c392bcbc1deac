//! Rotations on the CPU (`glam`, `f32`): axis-angle, quaternions, matrices, the 6D form and the
//! geodesic angle. [`tensor`] has the batched, differentiable candle versions used by the losses.
//!
//! # Conventions
//! - Matrices act on column vectors: `v_world = R * v_local`.
//! - Axis-angle is the rotation vector `angle * axis` (radians), as in SMPL-X.
//! - Quaternions are `glam::Quat` (stored `x, y, z, w`); [`quaternion_from_wxyz`] reads the
//!   scalar-first order that HUMOTO uses.
//! - The 6D form follows PyTorch3D (Zhou et al. 2019, as used by MDM and HOIDiNi): the six numbers
//!   are the **first two rows** of `R`, `[R00, R01, R02, R10, R11, R12]`. Decoding normalises the
//!   first row, removes its component from the second row and normalises it (Gram-Schmidt), and
//!   takes the third row as their cross product.

pub mod tensor;

use glam::{Mat3, Quat, Vec3};

/// The epsilon added under the square root when normalising 6D rows, shared with the tensor
/// version so that both give the same numbers (and a finite gradient at zero).
pub(crate) const NORMALISE_EPS: f32 = 1e-12;

/// Below this squared angle the axis-angle formulas switch to their Taylor series.
pub(crate) const SMALL_ANGLE_SQ: f32 = 1e-6;

/// Builds a matrix from its rows.
pub fn mat3_from_rows(row0: Vec3, row1: Vec3, row2: Vec3) -> Mat3 {
    Mat3::from_cols(row0, row1, row2).transpose()
}

/// The cross-product matrix `[v]x`, so that `[v]x * w = v x w`.
pub fn skew(v: Vec3) -> Mat3 {
    mat3_from_rows(Vec3::new(0.0, -v.z, v.y), Vec3::new(v.z, 0.0, -v.x), Vec3::new(-v.y, v.x, 0.0))
}

/// Rodrigues' formula `R = I + A [v]x + B [v]x^2` with `A = sin(t)/t`, `B = (1 - cos(t))/t^2`,
/// `t = |v|`; Taylor series below a small angle so that it is exact at zero.
pub fn axis_angle_to_matrix(rotation_vector: Vec3) -> Mat3 {
    let (a, b) = rodrigues_coefficients(rotation_vector.length_squared());
    let k = skew(rotation_vector);
    Mat3::IDENTITY + k * a + (k * k) * b
}

/// `(sin(t)/t, (1 - cos(t))/t^2)` for `t^2 = angle_sq`.
fn rodrigues_coefficients(angle_sq: f32) -> (f32, f32) {
    if angle_sq < SMALL_ANGLE_SQ {
        (1.0 - angle_sq / 6.0, 0.5 - angle_sq / 24.0)
    } else {
        let angle = angle_sq.sqrt();
        (angle.sin() / angle, (1.0 - angle.cos()) / angle_sq)
    }
}

/// The rotation vector of `R`, with angle in `[0, pi]`. Goes through the quaternion (Shepperd's
/// method), which stays accurate near 0 and near pi where the trace formula does not. At exactly
/// pi both `v` and `-v` are correct; either may be returned.
pub fn matrix_to_axis_angle(rotation: Mat3) -> Vec3 {
    quaternion_to_axis_angle(matrix_to_quaternion(rotation))
}

/// The rotation vector of a unit quaternion (it is normalised first), angle in `[0, pi]`.
pub fn quaternion_to_axis_angle(quaternion: Quat) -> Vec3 {
    let q = quaternion.normalize();
    // q and -q are the same rotation: take w >= 0 so that the angle is at most pi.
    let q = if q.w < 0.0 { -q } else { q };
    let xyz = Vec3::new(q.x, q.y, q.z);
    let sin_half = xyz.length();
    let angle = 2.0 * sin_half.atan2(q.w);
    if sin_half < 1e-6 {
        // angle / sin(angle/2) -> 2 / w as the angle goes to zero.
        xyz * (2.0 / q.w)
    } else {
        xyz * (angle / sin_half)
    }
}

/// The rotation vector as a unit quaternion.
pub fn axis_angle_to_quaternion(rotation_vector: Vec3) -> Quat {
    let angle_sq = rotation_vector.length_squared();
    if angle_sq < SMALL_ANGLE_SQ {
        let half = rotation_vector * 0.5 * (1.0 - angle_sq / 24.0);
        Quat::from_xyzw(half.x, half.y, half.z, 1.0 - angle_sq / 8.0).normalize()
    } else {
        let angle = angle_sq.sqrt();
        Quat::from_axis_angle(rotation_vector / angle, angle)
    }
}

/// The rotation matrix of a quaternion (normalised first, so any non-zero quaternion works).
pub fn quaternion_to_matrix(quaternion: Quat) -> Mat3 {
    Mat3::from_quat(quaternion.normalize())
}

/// The unit quaternion of a rotation matrix, with `w >= 0`. Shepperd's method: the largest of
/// `w, x, y, z` is computed from the diagonal, the others from off-diagonal sums, so no branch
/// divides by a small number.
pub fn matrix_to_quaternion(rotation: Mat3) -> Quat {
    let r = |i: usize, j: usize| rotation.col(j)[i];
    let trace = r(0, 0) + r(1, 1) + r(2, 2);
    let candidates = [trace, r(0, 0), r(1, 1), r(2, 2)];
    let largest = (0..4).max_by(|&a, &b| candidates[a].total_cmp(&candidates[b])).unwrap_or(0);
    let q = match largest {
        0 => {
            let s = (1.0 + trace).max(0.0).sqrt() * 2.0; // s = 4w
            Quat::from_xyzw(
                (r(2, 1) - r(1, 2)) / s,
                (r(0, 2) - r(2, 0)) / s,
                (r(1, 0) - r(0, 1)) / s,
                0.25 * s,
            )
        }
        1 => {
            let s = (1.0 + r(0, 0) - r(1, 1) - r(2, 2)).max(0.0).sqrt() * 2.0; // s = 4x
            Quat::from_xyzw(
                0.25 * s,
                (r(0, 1) + r(1, 0)) / s,
                (r(0, 2) + r(2, 0)) / s,
                (r(2, 1) - r(1, 2)) / s,
            )
        }
        2 => {
            let s = (1.0 + r(1, 1) - r(0, 0) - r(2, 2)).max(0.0).sqrt() * 2.0; // s = 4y
            Quat::from_xyzw(
                (r(0, 1) + r(1, 0)) / s,
                0.25 * s,
                (r(1, 2) + r(2, 1)) / s,
                (r(0, 2) - r(2, 0)) / s,
            )
        }
        _ => {
            let s = (1.0 + r(2, 2) - r(0, 0) - r(1, 1)).max(0.0).sqrt() * 2.0; // s = 4z
            Quat::from_xyzw(
                (r(0, 2) + r(2, 0)) / s,
                (r(1, 2) + r(2, 1)) / s,
                0.25 * s,
                (r(1, 0) - r(0, 1)) / s,
            )
        }
    };
    let q = q.normalize();
    if q.w < 0.0 { -q } else { q }
}

/// A quaternion from scalar-first components `[w, x, y, z]` (HUMOTO's order).
pub fn quaternion_from_wxyz(wxyz: [f32; 4]) -> Quat {
    Quat::from_xyzw(wxyz[1], wxyz[2], wxyz[3], wxyz[0])
}

/// The 6D form of a rotation: its first two rows (PyTorch3D convention).
pub fn matrix_to_sixd(rotation: Mat3) -> [f32; 6] {
    let (r0, r1) = (rotation.row(0), rotation.row(1));
    [r0.x, r0.y, r0.z, r1.x, r1.y, r1.z]
}

/// `v / sqrt(|v|^2 + eps)`: the normalisation that the tensor version uses too.
fn normalise(v: Vec3) -> Vec3 {
    v / (v.length_squared() + NORMALISE_EPS).sqrt()
}

/// Decodes the 6D form (first two rows, PyTorch3D convention) into a rotation matrix by
/// Gram-Schmidt. Any two non-parallel 3-vectors give a rotation; parallel or zero rows give a
/// degenerate matrix (zero rows), never NaN.
pub fn sixd_to_matrix(sixd: [f32; 6]) -> Mat3 {
    let a1 = Vec3::new(sixd[0], sixd[1], sixd[2]);
    let a2 = Vec3::new(sixd[3], sixd[4], sixd[5]);
    let b1 = normalise(a1);
    let b2 = normalise(a2 - b1 * b1.dot(a2));
    let b3 = b1.cross(b2);
    mat3_from_rows(b1, b2, b3)
}

/// The geodesic distance between two rotations: the angle of `a^T b`, in `[0, pi]`.
/// Uses `atan2(sin, cos)` from the skew part and the trace, accurate at 0 and at pi.
pub fn geodesic_angle(a: Mat3, b: Mat3) -> f32 {
    let relative = a.transpose() * b;
    let r = |i: usize, j: usize| relative.col(j)[i];
    let sin_times_two = Vec3::new(r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1)).length();
    let cos_times_two = r(0, 0) + r(1, 1) + r(2, 2) - 1.0;
    sin_times_two.atan2(cos_times_two)
}

/// `true` when `R` is a rotation to within `tolerance`: `R^T R = I` and `det R = 1`.
pub fn is_rotation(rotation: Mat3, tolerance: f32) -> bool {
    let gram = rotation.transpose() * rotation;
    gram.abs_diff_eq(Mat3::IDENTITY, tolerance) && (rotation.determinant() - 1.0).abs() <= tolerance
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f32::consts::PI;

    fn unit_vector() -> impl Strategy<Value = Vec3> {
        (-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0)
            .prop_filter("non-zero", |(x, y, z)| x * x + y * y + z * z > 1e-2)
            .prop_map(|(x, y, z)| Vec3::new(x, y, z).normalize())
    }

    fn rotation_vector(max_angle: f32) -> impl Strategy<Value = Vec3> {
        (unit_vector(), 0.0f32..max_angle).prop_map(|(axis, angle)| axis * angle)
    }

    proptest! {
        #[test]
        fn sixd_round_trip(v in rotation_vector(PI)) {
            let r = axis_angle_to_matrix(v);
            let back = sixd_to_matrix(matrix_to_sixd(r));
            prop_assert!(back.abs_diff_eq(r, 1e-5), "{r:?} vs {back:?}");
            let sixd = matrix_to_sixd(r);
            let again = matrix_to_sixd(back);
            for k in 0..6 { prop_assert!((sixd[k] - again[k]).abs() < 1e-5); }
        }

        #[test]
        fn sixd_decode_is_a_rotation(values in proptest::array::uniform6(-3.0f32..3.0)) {
            let a1 = Vec3::new(values[0], values[1], values[2]);
            let a2 = Vec3::new(values[3], values[4], values[5]);
            prop_assume!(a1.length() > 0.1 && a2.length() > 0.1);
            prop_assume!(a1.normalize().cross(a2.normalize()).length() > 0.05);
            let r = sixd_to_matrix(values);
            prop_assert!(is_rotation(r, 1e-5), "{r:?}");
            // The first row keeps the direction of the first 6D vector.
            prop_assert!(r.row(0).abs_diff_eq(a1.normalize(), 1e-5));
        }

        #[test]
        fn axis_angle_round_trip_away_from_pi(v in rotation_vector(PI - 0.05)) {
            let back = matrix_to_axis_angle(axis_angle_to_matrix(v));
            prop_assert!(back.abs_diff_eq(v, 2e-4), "{v:?} vs {back:?}");
        }

        #[test]
        fn axis_angle_round_trip_near_pi(axis in unit_vector(), gap in 0.0f32..0.05) {
            let v = axis * (PI - gap);
            let r = axis_angle_to_matrix(v);
            let back = matrix_to_axis_angle(r);
            // Near pi the vector may flip sign, but the rotation must come back.
            prop_assert!(axis_angle_to_matrix(back).abs_diff_eq(r, 1e-4));
            prop_assert!((back.length() - v.length()).abs() < 1e-3);
            let same = back.abs_diff_eq(v, 2e-3) || back.abs_diff_eq(-v, 2e-3);
            prop_assert!(same || gap < 1e-3, "{v:?} vs {back:?}");
        }

        #[test]
        fn axis_angle_round_trip_near_zero(axis in unit_vector(), angle in 0.0f32..1e-3) {
            let v = axis * angle;
            let back = matrix_to_axis_angle(axis_angle_to_matrix(v));
            prop_assert!(back.abs_diff_eq(v, 1e-6), "{v:?} vs {back:?}");
        }

        #[test]
        fn axis_angle_matrix_is_a_rotation(v in rotation_vector(10.0)) {
            prop_assert!(is_rotation(axis_angle_to_matrix(v), 1e-5));
        }

        #[test]
        fn quaternion_round_trip(v in rotation_vector(PI)) {
            let r = axis_angle_to_matrix(v);
            let q = matrix_to_quaternion(r);
            prop_assert!((q.length() - 1.0).abs() < 1e-5);
            prop_assert!(quaternion_to_matrix(q).abs_diff_eq(r, 1e-5));
            // Same rotation as the axis-angle quaternion, up to sign.
            let expected = axis_angle_to_quaternion(v);
            prop_assert!(q.abs_diff_eq(expected, 1e-4) || q.abs_diff_eq(-expected, 1e-4));
            let back = quaternion_to_axis_angle(q);
            prop_assert!(axis_angle_to_matrix(back).abs_diff_eq(r, 1e-4));
        }

        #[test]
        fn geodesic_angle_matches_the_relative_rotation(
            a in rotation_vector(PI), axis in unit_vector(), angle in 0.0f32..PI
        ) {
            let ra = axis_angle_to_matrix(a);
            let rb = ra * axis_angle_to_matrix(axis * angle);
            prop_assert!((geodesic_angle(ra, rb) - angle).abs() < 2e-4);
            prop_assert!((geodesic_angle(rb, ra) - angle).abs() < 2e-4);
        }
    }

    #[test]
    fn known_rotations() {
        // A quarter turn about +Y takes +Z to +X.
        let r = axis_angle_to_matrix(Vec3::Y * (PI / 2.0));
        assert!((r * Vec3::Z).abs_diff_eq(Vec3::X, 1e-6));
        // Scalar-first quaternion of a half turn about +X.
        let q = quaternion_from_wxyz([0.0, 1.0, 0.0, 0.0]);
        assert!((quaternion_to_matrix(q) * Vec3::Y).abs_diff_eq(-Vec3::Y, 1e-6));
        // The 6D form of the identity is [1,0,0, 0,1,0].
        assert_eq!(matrix_to_sixd(Mat3::IDENTITY), [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        // Exactly pi: the axis comes back up to sign.
        let v = Vec3::new(0.0, 0.6, 0.8) * PI;
        let back = matrix_to_axis_angle(axis_angle_to_matrix(v));
        assert!(back.abs_diff_eq(v, 1e-3) || back.abs_diff_eq(-v, 1e-3), "{back:?}");
        assert_eq!(matrix_to_axis_angle(Mat3::IDENTITY), Vec3::ZERO);
        assert!(geodesic_angle(Mat3::IDENTITY, Mat3::IDENTITY).abs() < 1e-7);
    }

    #[test]
    fn degenerate_sixd_is_finite() {
        let r = sixd_to_matrix([0.0; 6]);
        assert!(r.to_cols_array().iter().all(|x| x.is_finite()));
    }
}
