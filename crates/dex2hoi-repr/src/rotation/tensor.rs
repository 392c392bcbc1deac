//! Batched, differentiable rotation conversions on candle tensors. Every function works over any
//! number of leading dimensions, in any float dtype, and is built only from operations that have
//! a backward pass. They agree with the CPU versions in [`crate::rotation`] to 1e-5 in `f32`.

use candle_core::{D, DType, Tensor};

use super::{NORMALISE_EPS, SMALL_ANGLE_SQ};
use crate::error::{ReprError, Result};

/// Checks that the last dimension of `tensor` is `size` and returns the leading dimensions.
pub(crate) fn leading_dims(tensor: &Tensor, size: usize, what: &str) -> Result<Vec<usize>> {
    let dims = tensor.dims();
    match dims.split_last() {
        Some((&last, leading)) if last == size => Ok(leading.to_vec()),
        _ => Err(ReprError::invalid(
            what,
            format!("a tensor of shape [..., {size}]"),
            format!("{dims:?}"),
        )),
    }
}

/// Checks that the last two dimensions are `[3, 3]` and returns the leading dimensions.
pub(crate) fn leading_dims_matrix(tensor: &Tensor, what: &str) -> Result<Vec<usize>> {
    let dims = tensor.dims();
    let rank = dims.len();
    if rank < 2 || dims[rank - 2] != 3 || dims[rank - 1] != 3 {
        return Err(ReprError::invalid(what, "a tensor of shape [..., 3, 3]", format!("{dims:?}")));
    }
    Ok(dims[..rank - 2].to_vec())
}

/// Checks that a tensor holds floats.
pub(crate) fn require_float(tensor: &Tensor, what: &str) -> Result<()> {
    match tensor.dtype() {
        DType::F16 | DType::BF16 | DType::F32 | DType::F64 => Ok(()),
        other => Err(ReprError::invalid(what, "a floating-point tensor", format!("{other:?}"))),
    }
}

/// `v / sqrt(|v|^2 + eps)` over the last dimension.
fn normalise(v: &Tensor) -> Result<Tensor> {
    let norm = (v.sqr()?.sum_keepdim(D::Minus1)? + f64::from(NORMALISE_EPS))?.sqrt()?;
    Ok(v.broadcast_div(&norm)?)
}

/// The cross product of two `[..., 3]` tensors.
pub fn cross(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let c = |t: &Tensor, i: usize| t.narrow(D::Minus1, i, 1);
    let (ax, ay, az) = (c(a, 0)?, c(a, 1)?, c(a, 2)?);
    let (bx, by, bz) = (c(b, 0)?, c(b, 1)?, c(b, 2)?);
    let x = ((&ay * &bz)? - (&az * &by)?)?;
    let y = ((&az * &bx)? - (&ax * &bz)?)?;
    let z = ((&ax * &by)? - (&ay * &bx)?)?;
    Ok(Tensor::cat(&[x, y, z], D::Minus1)?)
}

/// Stacks three `[..., 3]` row tensors into `[..., 3, 3]` matrices.
fn stack_rows(rows: [Tensor; 3]) -> Result<Tensor> {
    let rank = rows[0].rank();
    Ok(Tensor::stack(&rows, rank - 1)?)
}

/// Decodes the 6D form (first two rows, PyTorch3D convention) by Gram-Schmidt.
///
/// # Shapes
/// - `sixd`: `[..., 6]`
/// - returns: `[..., 3, 3]`
pub fn sixd_to_matrix(sixd: &Tensor) -> Result<Tensor> {
    leading_dims(sixd, 6, "6D rotation tensor")?;
    require_float(sixd, "6D rotation tensor")?;
    let a1 = sixd.narrow(D::Minus1, 0, 3)?;
    let a2 = sixd.narrow(D::Minus1, 3, 3)?;
    let b1 = normalise(&a1)?;
    let projection = (&b1 * &a2)?.sum_keepdim(D::Minus1)?;
    let b2 = normalise(&(a2 - b1.broadcast_mul(&projection)?)?)?;
    let b3 = cross(&b1, &b2)?;
    stack_rows([b1, b2, b3])
}

/// The 6D form of rotation matrices: their first two rows.
///
/// # Shapes
/// - `rotation`: `[..., 3, 3]`
/// - returns: `[..., 6]`
pub fn matrix_to_sixd(rotation: &Tensor) -> Result<Tensor> {
    let mut dims = leading_dims_matrix(rotation, "rotation matrix tensor")?;
    let rows = rotation.narrow(dims.len(), 0, 2)?.contiguous()?;
    dims.push(6);
    Ok(rows.reshape(dims)?)
}

/// The cross-product matrices `[v]x` of `[..., 3]` vectors, `[..., 3, 3]`.
pub fn skew(v: &Tensor) -> Result<Tensor> {
    leading_dims(v, 3, "vector tensor")?;
    let c = |i: usize| v.narrow(D::Minus1, i, 1);
    let (x, y, z) = (c(0)?, c(1)?, c(2)?);
    let zero = x.zeros_like()?;
    stack_rows([
        Tensor::cat(&[&zero, &z.neg()?, &y], D::Minus1)?,
        Tensor::cat(&[&z, &zero, &x.neg()?], D::Minus1)?,
        Tensor::cat(&[&y.neg()?, &x, &zero], D::Minus1)?,
    ])
}

/// Rodrigues' formula for rotation vectors, `R = I + A [v]x + B (v v^T - |v|^2 I)`, with the
/// Taylor series of `A = sin(t)/t` and `B = (1 - cos t)/t^2` for small angles; the exact branch
/// never sees a zero angle, so the gradient is finite everywhere.
///
/// # Shapes
/// - `rotation_vector`: `[..., 3]`
/// - returns: `[..., 3, 3]`
pub fn axis_angle_to_matrix(rotation_vector: &Tensor) -> Result<Tensor> {
    leading_dims(rotation_vector, 3, "axis-angle tensor")?;
    require_float(rotation_vector, "axis-angle tensor")?;
    let v = rotation_vector;
    let angle_sq = v.sqr()?.sum_keepdim(D::Minus1)?; // [..., 1]
    let small = angle_sq.lt(f64::from(SMALL_ANGLE_SQ))?;
    let safe_sq = small.where_cond(&angle_sq.ones_like()?, &angle_sq)?;
    let angle = safe_sq.sqrt()?;
    let a_exact = (angle.sin()? / &angle)?;
    let b_exact = ((angle.cos()?.neg()? + 1.0)? / &safe_sq)?;
    let a = small.where_cond(&angle_sq.affine(-1.0 / 6.0, 1.0)?, &a_exact)?;
    let b = small.where_cond(&angle_sq.affine(-1.0 / 24.0, 0.5)?, &b_exact)?;
    let (a, b, angle_sq) =
        (a.unsqueeze(D::Minus1)?, b.unsqueeze(D::Minus1)?, angle_sq.unsqueeze(D::Minus1)?);
    let eye = Tensor::eye(3, v.dtype(), v.device())?;
    let outer = v.unsqueeze(D::Minus1)?.broadcast_mul(&v.unsqueeze(D::Minus2)?)?;
    let k_squared = (outer - angle_sq.broadcast_mul(&eye)?)?;
    let rotation = (skew(v)?.broadcast_mul(&a)? + k_squared.broadcast_mul(&b)?)?;
    Ok(rotation.broadcast_add(&eye)?)
}

/// Applies rotations to vectors: `R v`.
///
/// # Shapes
/// - `rotation`: `[..., 3, 3]`
/// - `vector`: `[..., 3]` (broadcast against the rotation's leading dimensions)
/// - returns: `[..., 3]`
pub fn rotate(rotation: &Tensor, vector: &Tensor) -> Result<Tensor> {
    leading_dims_matrix(rotation, "rotation matrix tensor")?;
    leading_dims(vector, 3, "vector tensor")?;
    Ok(rotation.broadcast_mul(&vector.unsqueeze(D::Minus2)?)?.sum(D::Minus1)?)
}

/// Applies transposed rotations to vectors: `R^T v`.
///
/// # Shapes
/// - `rotation`: `[..., 3, 3]`
/// - `vector`: `[..., 3]`
/// - returns: `[..., 3]`
pub fn rotate_inverse(rotation: &Tensor, vector: &Tensor) -> Result<Tensor> {
    leading_dims_matrix(rotation, "rotation matrix tensor")?;
    leading_dims(vector, 3, "vector tensor")?;
    Ok(rotation.broadcast_mul(&vector.unsqueeze(D::Minus1)?)?.sum(D::Minus2)?)
}
