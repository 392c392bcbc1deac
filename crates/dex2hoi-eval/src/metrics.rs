//! Metrics of the paper's tables: distribution metrics on embeddings and physical metrics on
//! motions (paper Sec. 4.2; docs/CONVENTIONS.md, "Evaluation protocols").
//!
//! **Embedding metrics** follow the MDM / T2M evaluation protocol: [`fid`], [`diversity`],
//! [`multimodality`], [`r_precision`] and [`matching_distance`] (MMdist), all computed in `f64`
//! on rows of evaluator embeddings, and [`mean_interval`] for the mean and 95% interval over
//! replications. Random draws (pairs, shuffles) come from a seeded ChaCha8 generator, so a seed
//! reproduces a number exactly.
//!
//! **Motion metrics** work on one sample at a time, described by a [`MotionSample`] (joint
//! positions, object poses, object meshes, optional mixture weights): [`penetration`],
//! [`hand_contact`] and [`contact_scores`] (CHOIS), [`foot_sliding`] (MANN's weighted foot
//! displacement), [`mixture_agreement`] (does the mixture of Eq. 4 pick the hand that holds the
//! object?) and [`runtime`]. Each per-sample result carries its counts so that a test set can be
//! pooled ([`Penetration::pooled`], [`ContactCounts::merge`]).
//!
//! Conventions: metres, Y up, floor at `y = 0`; object meshes in their own (bounding-box-centred)
//! frame and object rotations stored row-major as in
//! [`ProcessedSequence`](dex2hoi_data::features::ProcessedSequence); object slots are the two of
//! [`MAX_OBJECTS`].

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_repr::object_repr::{MIXTURE_RANGE, OBJECT_FEATURE_SIZE, softmax3};
use dex2hoi_repr::{MeshQuery, ObjectPose, Skeleton};
use glam::{Mat3, Vec3};
use rand::SeedableRng;
use rand::seq::{SliceRandom, index};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::error::{EvalError, Result};

/// Random pairs for [`diversity`]: 300, as in T2M and MDM.
pub const DIVERSITY_PAIRS: usize = 300;
/// Batch size of [`r_precision`]: 32 motion-text pairs, as in T2M.
pub const R_PRECISION_BATCH: usize = 32;
/// Depth beyond which a joint inside an object counts as penetrating: 5 mm.
pub const PENETRATION_TOLERANCE_M: f32 = 0.005;
/// Distance under which a hand joint touches an object: 5 cm, as in CHOIS.
pub const CONTACT_RADIUS_M: f32 = 0.05;
/// Height under which an ankle joint counts as on the ground for [`foot_sliding`]: 8 cm.
pub const ANKLE_HEIGHT_M: f32 = 0.08;
/// Height under which a toe joint counts as on the ground for [`foot_sliding`]: 4 cm.
pub const TOE_HEIGHT_M: f32 = 0.04;
/// The normal quantile of a two-sided 95% interval, as in T2M's `get_metric_statistics`.
pub const CONFIDENCE_Z: f64 = 1.96;

// ---------------------------------------------------------------------------------------------
// Embeddings: validation and statistics.
// ---------------------------------------------------------------------------------------------

/// Rows of `f32` embeddings as one row-major `f64` matrix, checked: at least `min_rows` rows,
/// all of the same non-zero width, all finite.
fn embedding_matrix(what: &str, rows: &[Vec<f32>], min_rows: usize) -> Result<(Vec<f64>, usize)> {
    if rows.len() < min_rows {
        return Err(EvalError::invalid(
            what,
            format!("at least {min_rows} embedding rows"),
            format!("{} rows", rows.len()),
        ));
    }
    let dim = rows.first().map_or(0, Vec::len);
    if dim == 0 {
        return Err(EvalError::invalid(what, "embeddings with at least one number", "empty rows"));
    }
    let mut matrix = Vec::with_capacity(rows.len() * dim);
    for (i, row) in rows.iter().enumerate() {
        if row.len() != dim {
            return Err(EvalError::invalid(
                what,
                format!("every row with {dim} numbers (as row 0)"),
                format!("row {i} with {}", row.len()),
            ));
        }
        if let Some(k) = row.iter().position(|v| !v.is_finite()) {
            return Err(EvalError::invalid(
                what,
                "finite numbers",
                format!("{} at row {i}, column {k}", row[k]),
            ));
        }
        matrix.extend(row.iter().map(|&v| f64::from(v)));
    }
    Ok((matrix, dim))
}

/// Euclidean distance between two rows.
fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt()
}

/// The mean and the sample covariance of a set of embeddings: the Gaussian that [`fid`]
/// compares. Computing it once for the ground truth saves work over replications.
#[derive(Debug, Clone, PartialEq)]
pub struct EmbeddingStatistics {
    /// Embedding width `D`.
    pub dim: usize,
    /// Number of rows the statistics were computed from.
    pub count: usize,
    /// `[D]` mean of the rows.
    pub mean: Vec<f64>,
    /// `[D, D]` row-major sample covariance with `ddof = 1`
    /// (`numpy.cov(rows, rowvar=False)`).
    pub covariance: Vec<f64>,
}

impl EmbeddingStatistics {
    /// Mean and covariance of `embeddings`, in `f64`.
    ///
    /// # Shapes
    /// - `embeddings`: `[N, D]` as `N` rows of `D` numbers, `N >= 2`.
    ///
    /// # Errors
    /// Fewer than two rows, ragged or empty rows, non-finite numbers.
    pub fn from_embeddings(embeddings: &[Vec<f32>]) -> Result<Self> {
        let (matrix, dim) = embedding_matrix("embeddings for FID statistics", embeddings, 2)?;
        let count = embeddings.len();
        let mut mean = vec![0.0; dim];
        for row in matrix.chunks_exact(dim) {
            for (m, v) in mean.iter_mut().zip(row) {
                *m += v;
            }
        }
        for m in &mut mean {
            *m /= count as f64;
        }
        let mut covariance = vec![0.0; dim * dim];
        let mut centred = vec![0.0; dim];
        for row in matrix.chunks_exact(dim) {
            for ((c, v), m) in centred.iter_mut().zip(row).zip(&mean) {
                *c = v - m;
            }
            for i in 0..dim {
                let ci = centred[i];
                let out = &mut covariance[i * dim..(i + 1) * dim];
                for (o, cj) in out[i..].iter_mut().zip(&centred[i..]) {
                    *o += ci * cj;
                }
            }
        }
        let scale = 1.0 / (count as f64 - 1.0);
        for i in 0..dim {
            for j in i..dim {
                let v = covariance[i * dim + j] * scale;
                covariance[i * dim + j] = v;
                covariance[j * dim + i] = v;
            }
        }
        Ok(Self { dim, count, mean, covariance })
    }
}

/// Frechet Inception Distance between two sets of embeddings (Heusel et al. 2017), as in
/// pytorch-fid and T2M:
/// `FID = |mu1 - mu2|^2 + tr(S1 + S2 - 2 (S1 S2)^{1/2})` with sample covariances
/// (`ddof = 1`). See [`fid_from_statistics`] for how the matrix square root is taken.
///
/// # Shapes
/// - `generated`: `[N1, D]`, `reference`: `[N2, D]` (rows of `D` numbers), `N1, N2 >= 2`.
///
/// # Errors
/// Fewer than two rows, ragged rows, different widths, non-finite numbers.
pub fn fid(generated: &[Vec<f32>], reference: &[Vec<f32>]) -> Result<f64> {
    let generated = EmbeddingStatistics::from_embeddings(generated)?;
    let reference = EmbeddingStatistics::from_embeddings(reference)?;
    fid_from_statistics(&generated, &reference)
}

/// FID between two Gaussians given by their statistics.
///
/// `tr (S1 S2)^{1/2}` is computed without a non-symmetric matrix square root. `S1 S2` has the
/// eigenvalues of `S1^{1/2} S2 S1^{1/2} = B B^T` with `B = S1^{1/2} S2^{1/2}`, so the trace is
/// the sum of the singular values of `B` (its nuclear norm). Those are taken as the positive
/// eigenvalues of the symmetric Jordan-Wielandt matrix `[[0, B], [B^T, 0]]` (eigenvalues
/// `+-sigma_i`; the sum used is `sum |lambda| / 2`), which keeps every step a symmetric
/// eigen-decomposition ([`symmetric_eigen`]) and the result accurate to round-off even for
/// singular covariances, where the square roots of `B B^T`'s eigenvalues would turn round-off
/// of 1e-16 into errors of 1e-8. `S^{1/2} = V diag(sqrt(lambda)) V^T` with the eigenvalues at
/// the round-off level, `lambda <= D * eps * max |lambda|` (negative ones included), **set to
/// 0**: a covariance of rank below `D` (fewer rows than dimensions, or dependent dimensions)
/// has exact zeros there. On the test cases this agrees with scipy's `sqrtm(S1.dot(S2)).real`
/// (the pytorch-fid / T2M reference) to 6e-7 relative or better, and with a 60-digit mpmath
/// evaluation of the same formula to 1.1e-8 (scipy: 5.8e-7 on a nearly singular case). It
/// never needs T2M's `1e-6 I` retry because it cannot produce a non-finite result.
///
/// # Errors
/// Different widths, covariances of the wrong size or with non-finite numbers, or an
/// eigen-decomposition that does not converge.
pub fn fid_from_statistics(
    generated: &EmbeddingStatistics,
    reference: &EmbeddingStatistics,
) -> Result<f64> {
    let dim = generated.dim;
    for (what, stats) in [("generated statistics", generated), ("reference statistics", reference)]
    {
        if stats.dim != dim || stats.mean.len() != dim || stats.covariance.len() != dim * dim {
            return Err(EvalError::invalid(
                what,
                format!("a mean of {dim} and a covariance of {dim}x{dim} numbers"),
                format!(
                    "width {}, {} mean and {} covariance numbers",
                    stats.dim,
                    stats.mean.len(),
                    stats.covariance.len()
                ),
            ));
        }
        if stats.mean.iter().chain(&stats.covariance).any(|v| !v.is_finite()) {
            return Err(EvalError::invalid(what, "finite numbers", "NaN or infinity"));
        }
    }
    let mean_term: f64 =
        generated.mean.iter().zip(&reference.mean).map(|(a, b)| (a - b) * (a - b)).sum();
    let trace = |m: &[f64]| (0..dim).map(|i| m[i * dim + i]).sum::<f64>();
    let root_generated = psd_square_root(&generated.covariance, dim)?;
    let root_reference = psd_square_root(&reference.covariance, dim)?;
    let b = multiply(&root_generated, &root_reference, dim);
    let wide = 2 * dim;
    let mut jordan_wielandt = vec![0.0; wide * wide];
    for i in 0..dim {
        for j in 0..dim {
            jordan_wielandt[i * wide + dim + j] = b[i * dim + j];
            jordan_wielandt[(dim + j) * wide + i] = b[i * dim + j];
        }
    }
    let eigen = symmetric_eigen(&jordan_wielandt, wide, false)?;
    let trace_root = 0.5 * eigen.values.iter().map(|l| l.abs()).sum::<f64>();
    Ok(mean_term + trace(&generated.covariance) + trace(&reference.covariance) - 2.0 * trace_root)
}

/// `A B` for row-major `n x n` matrices.
fn multiply(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut out = vec![0.0; n * n];
    for i in 0..n {
        let row = &mut out[i * n..(i + 1) * n];
        for k in 0..n {
            let aik = a[i * n + k];
            if aik == 0.0 {
                continue;
            }
            for (o, bkj) in row.iter_mut().zip(&b[k * n..(k + 1) * n]) {
                *o += aik * bkj;
            }
        }
    }
    out
}

/// Square roots of the eigenvalues of a positive semi-definite matrix, with the ones at the
/// round-off level (`lambda <= n * eps * max |lambda|`, negative ones included) set to 0.
fn psd_roots(values: &[f64]) -> Vec<f64> {
    let largest = values.iter().fold(0.0f64, |m, l| m.max(l.abs()));
    let floor = values.len() as f64 * f64::EPSILON * largest;
    values.iter().map(|&l| if l <= floor { 0.0 } else { l.sqrt() }).collect()
}

/// The symmetric square root `V diag(sqrt(lambda)) V^T` of a symmetric positive semi-definite
/// matrix (round-off eigenvalues as 0, see [`psd_roots`]).
fn psd_square_root(m: &[f64], n: usize) -> Result<Vec<f64>> {
    let eigen = symmetric_eigen(m, n, true)?;
    let roots = psd_roots(&eigen.values);
    let v = &eigen.vectors;
    let mut out = vec![0.0; n * n];
    for i in 0..n {
        for j in i..n {
            let s: f64 = (0..n).map(|k| v[i * n + k] * roots[k] * v[j * n + k]).sum();
            out[i * n + j] = s;
            out[j * n + i] = s;
        }
    }
    Ok(out)
}

/// The eigen-decomposition of a real symmetric matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct SymmetricEigen {
    /// `[n]` eigenvalues in ascending order.
    pub values: Vec<f64>,
    /// `[n, n]` row-major; column `k` is the unit eigenvector of `values[k]`. Empty when the
    /// vectors were not asked for.
    pub vectors: Vec<f64>,
}

/// Eigenvalues (and optionally eigenvectors) of a real symmetric matrix: Householder
/// reduction to tridiagonal form, then the QL algorithm with implicit shifts (the EISPACK
/// routines `tred2` and `tql2`; Wilkinson and Reinsch, Handbook for Automatic Computation II,
/// 1971). `O(n^3)`; only the lower triangle of `matrix` is read.
///
/// # Shapes
/// - `matrix`: `[n, n]` row-major.
///
/// # Errors
/// A matrix of the wrong size or with non-finite numbers, or no convergence after `30 n` QL
/// iterations (which does not happen for finite symmetric input in practice).
pub fn symmetric_eigen(matrix: &[f64], n: usize, with_vectors: bool) -> Result<SymmetricEigen> {
    if matrix.len() != n * n {
        return Err(EvalError::invalid(
            "symmetric matrix",
            format!("{n}x{n} = {} numbers", n * n),
            matrix.len(),
        ));
    }
    if let Some(i) = matrix.iter().position(|v| !v.is_finite()) {
        return Err(EvalError::invalid(
            "symmetric matrix",
            "finite numbers",
            format!("{} at row {}, column {}", matrix[i], i / n, i % n),
        ));
    }
    if n == 0 {
        return Ok(SymmetricEigen { values: Vec::new(), vectors: Vec::new() });
    }
    // `v` starts as the matrix (lower triangle mirrored) and ends as the eigenvectors.
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            v[i * n + j] = matrix[i * n + j];
            v[j * n + i] = matrix[i * n + j];
        }
    }
    let mut d = vec![0.0; n];
    let mut e = vec![0.0; n];
    householder_tridiagonal(&mut v, &mut d, &mut e, n);
    tridiagonal_ql(&mut v, &mut d, &mut e, n, with_vectors)?;
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| d[a].total_cmp(&d[b]));
    let values = order.iter().map(|&k| d[k]).collect();
    let vectors = if with_vectors {
        let mut sorted = vec![0.0; n * n];
        for (new, &old) in order.iter().enumerate() {
            for i in 0..n {
                sorted[i * n + new] = v[i * n + old];
            }
        }
        sorted
    } else {
        Vec::new()
    };
    Ok(SymmetricEigen { values, vectors })
}

/// Householder reduction of the symmetric matrix in `v` to tridiagonal form (`tred2`): on return
/// `d` holds the diagonal, `e[1..]` the sub-diagonal, and `v` the orthogonal transformation.
fn householder_tridiagonal(v: &mut [f64], d: &mut [f64], e: &mut [f64], n: usize) {
    let at = |i: usize, j: usize| i * n + j;
    for j in 0..n {
        d[j] = v[at(n - 1, j)];
    }
    for i in (1..n).rev() {
        let scale: f64 = d[..i].iter().map(|x| x.abs()).sum();
        let mut h = 0.0;
        if scale == 0.0 {
            e[i] = d[i - 1];
            for j in 0..i {
                d[j] = v[at(i - 1, j)];
                v[at(i, j)] = 0.0;
                v[at(j, i)] = 0.0;
            }
        } else {
            for k in 0..i {
                d[k] /= scale;
                h += d[k] * d[k];
            }
            let mut f = d[i - 1];
            let mut g = h.sqrt();
            if f > 0.0 {
                g = -g;
            }
            e[i] = scale * g;
            h -= f * g;
            d[i - 1] = f - g;
            e[..i].fill(0.0);
            for j in 0..i {
                f = d[j];
                v[at(j, i)] = f;
                g = e[j] + v[at(j, j)] * f;
                for k in j + 1..i {
                    g += v[at(k, j)] * d[k];
                    e[k] += v[at(k, j)] * f;
                }
                e[j] = g;
            }
            f = 0.0;
            for j in 0..i {
                e[j] /= h;
                f += e[j] * d[j];
            }
            let hh = f / (h + h);
            for j in 0..i {
                e[j] -= hh * d[j];
            }
            for j in 0..i {
                let (f, g) = (d[j], e[j]);
                for k in j..i {
                    v[at(k, j)] -= f * e[k] + g * d[k];
                }
                d[j] = v[at(i - 1, j)];
                v[at(i, j)] = 0.0;
            }
        }
        d[i] = h;
    }
    // Accumulate the transformations.
    for i in 0..n - 1 {
        v[at(n - 1, i)] = v[at(i, i)];
        v[at(i, i)] = 1.0;
        let h = d[i + 1];
        if h != 0.0 {
            for k in 0..=i {
                d[k] = v[at(k, i + 1)] / h;
            }
            for j in 0..=i {
                let g: f64 = (0..=i).map(|k| v[at(k, i + 1)] * v[at(k, j)]).sum();
                for k in 0..=i {
                    v[at(k, j)] -= g * d[k];
                }
            }
        }
        for k in 0..=i {
            v[at(k, i + 1)] = 0.0;
        }
    }
    for j in 0..n {
        d[j] = v[at(n - 1, j)];
        v[at(n - 1, j)] = 0.0;
    }
    v[at(n - 1, n - 1)] = 1.0;
    e[0] = 0.0;
}

/// QL iterations with implicit shifts on the tridiagonal matrix `(d, e)` (`tql2`): `d` ends as
/// the eigenvalues and, with `with_vectors`, `v` as the eigenvectors of the original matrix.
fn tridiagonal_ql(
    v: &mut [f64],
    d: &mut [f64],
    e: &mut [f64],
    n: usize,
    with_vectors: bool,
) -> Result<()> {
    let at = |i: usize, j: usize| i * n + j;
    for i in 1..n {
        e[i - 1] = e[i];
    }
    e[n - 1] = 0.0;
    let mut f = 0.0;
    let mut largest: f64 = 0.0;
    let eps = f64::EPSILON;
    let max_iterations = 30 * n.max(1);
    let mut iterations = 0;
    for l in 0..n {
        largest = largest.max(d[l].abs() + e[l].abs());
        let mut m = l;
        while m < n - 1 && e[m].abs() > eps * largest {
            m += 1;
        }
        if m > l {
            loop {
                iterations += 1;
                if iterations > max_iterations {
                    return Err(EvalError::invalid(
                        "symmetric eigen-decomposition",
                        format!("convergence within {max_iterations} QL iterations"),
                        format!("no convergence for {n}x{n}"),
                    ));
                }
                let mut g = d[l];
                let mut p = (d[l + 1] - g) / (2.0 * e[l]);
                let mut r = p.hypot(1.0);
                if p < 0.0 {
                    r = -r;
                }
                d[l] = e[l] / (p + r);
                d[l + 1] = e[l] * (p + r);
                let dl1 = d[l + 1];
                let mut h = g - d[l];
                for x in &mut d[l + 2..n] {
                    *x -= h;
                }
                f += h;
                p = d[m];
                let (mut c, mut c2, mut c3) = (1.0, 1.0, 1.0);
                let el1 = e[l + 1];
                let (mut s, mut s2) = (0.0, 0.0);
                for i in (l..m).rev() {
                    c3 = c2;
                    c2 = c;
                    s2 = s;
                    g = c * e[i];
                    h = c * p;
                    r = p.hypot(e[i]);
                    e[i + 1] = s * r;
                    s = e[i] / r;
                    c = p / r;
                    p = c * d[i] - s * g;
                    d[i + 1] = h + s * (c * g + s * d[i]);
                    if with_vectors {
                        for k in 0..n {
                            let h = v[at(k, i + 1)];
                            v[at(k, i + 1)] = s * v[at(k, i)] + c * h;
                            v[at(k, i)] = c * v[at(k, i)] - s * h;
                        }
                    }
                }
                p = -s * s2 * c3 * el1 * e[l] / dl1;
                e[l] = s * p;
                d[l] = c * p;
                if e[l].abs() <= eps * largest {
                    break;
                }
            }
        }
        d[l] += f;
        e[l] = 0.0;
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Diversity, MultiModality, R-precision, MMdist, replications.
// ---------------------------------------------------------------------------------------------

/// Diversity (T2M): the mean Euclidean distance over `pairs` random pairs of embeddings. As in
/// T2M's `calculate_diversity`, two index sets of size `pairs` are drawn independently, each
/// without replacement (`np.random.choice(N, pairs, replace=False)`), and row `a_i` is paired
/// with row `b_i`; a pair may hold the same row twice (distance 0). The paper uses
/// [`DIVERSITY_PAIRS`] = 300.
///
/// # Shapes
/// - `embeddings`: `[N, D]`, `N >= pairs`.
///
/// # Errors
/// `pairs` of 0 or more than `N`, ragged rows, non-finite numbers.
pub fn diversity(embeddings: &[Vec<f32>], pairs: usize, seed: u64) -> Result<f64> {
    let (matrix, dim) = embedding_matrix("embeddings for diversity", embeddings, 1)?;
    let count = embeddings.len();
    if pairs == 0 || pairs > count {
        return Err(EvalError::invalid(
            "diversity pairs",
            format!("between 1 and the number of embeddings ({count}), drawn without replacement"),
            pairs,
        ));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let first = index::sample(&mut rng, count, pairs).into_vec();
    let second = index::sample(&mut rng, count, pairs).into_vec();
    let row = |i: usize| &matrix[i * dim..(i + 1) * dim];
    let total: f64 = first.iter().zip(&second).map(|(&a, &b)| distance(row(a), row(b))).sum();
    Ok(total / pairs as f64)
}

/// The sizes of a MultiModality run: how many prompts (or action labels), how many generations
/// per prompt, and how many random pairs within each prompt's generations.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MultimodalityProtocol {
    /// Prompts (text descriptions or, on GRAB, action labels).
    pub prompts: usize,
    /// Generations per prompt.
    pub repeats: usize,
    /// Random pairs per prompt.
    pub pairs: usize,
}

impl Default for MultimodalityProtocol {
    /// A CPU-friendly setting: 32 prompts x 10 generations x 5 pairs.
    fn default() -> Self {
        Self { prompts: 32, repeats: 10, pairs: 5 }
    }
}

impl MultimodalityProtocol {
    /// The paper's (T2M's) setting: 100 prompts x 30 generations x 10 pairs.
    pub fn paper() -> Self {
        Self { prompts: 100, repeats: 30, pairs: 10 }
    }
}

/// MultiModality (T2M): per prompt, the mean Euclidean distance over `pairs` random pairs of
/// its generations, averaged over prompts. As in T2M's `calculate_multimodality`, one pair of
/// index sets of size `pairs` is drawn (each without replacement) and used for every prompt.
///
/// # Shapes
/// - `groups`: `[prompts, repeats, D]`: per prompt, the embeddings of its `repeats`
///   generations; every prompt has the same `repeats >= pairs`.
///
/// # Errors
/// No groups, groups of different sizes, `pairs` of 0 or more than `repeats`, ragged rows or
/// widths that differ between groups, non-finite numbers.
pub fn multimodality(groups: &[Vec<Vec<f32>>], pairs: usize, seed: u64) -> Result<f64> {
    let Some(first_group) = groups.first() else {
        return Err(EvalError::invalid("multimodality groups", "at least one prompt", "none"));
    };
    let repeats = first_group.len();
    if pairs == 0 || pairs > repeats {
        return Err(EvalError::invalid(
            "multimodality pairs",
            format!("between 1 and the generations per prompt ({repeats})"),
            pairs,
        ));
    }
    let mut matrices = Vec::with_capacity(groups.len());
    let mut dim = None;
    for (g, group) in groups.iter().enumerate() {
        if group.len() != repeats {
            return Err(EvalError::invalid(
                "multimodality groups",
                format!("{repeats} generations per prompt (as prompt 0)"),
                format!("{} for prompt {g}", group.len()),
            ));
        }
        let (matrix, width) = embedding_matrix(&format!("embeddings of prompt {g}"), group, 1)?;
        if *dim.get_or_insert(width) != width {
            return Err(EvalError::invalid(
                "multimodality groups",
                format!("{} numbers per embedding (as prompt 0)", dim.unwrap_or(width)),
                format!("{width} for prompt {g}"),
            ));
        }
        matrices.push(matrix);
    }
    let dim = dim.unwrap_or(0);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let first = index::sample(&mut rng, repeats, pairs).into_vec();
    let second = index::sample(&mut rng, repeats, pairs).into_vec();
    let mut total = 0.0;
    for matrix in &matrices {
        let row = |i: usize| &matrix[i * dim..(i + 1) * dim];
        total += first.iter().zip(&second).map(|(&a, &b)| distance(row(a), row(b))).sum::<f64>();
    }
    Ok(total / (pairs * groups.len()) as f64)
}

/// Which side is ranked in [`r_precision_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Retrieval {
    /// For each text, rank the batch's motions (T2M's code: `dist_mat` has texts as rows and
    /// `np.argsort(dist_mat, axis=1)`). What [`r_precision`] does.
    TextToMotion,
    /// For each motion, rank the batch's texts.
    MotionToText,
}

/// R-precision top-1/2/3 by the T2M protocol: the matched pairs are shuffled (seeded), cut
/// into batches of `batch` pairs ([`R_PRECISION_BATCH`] = 32 in the paper) with the last
/// incomplete batch dropped (T2M's data loader uses `drop_last=True`), and within each batch,
/// for each text, the batch's motions are ranked by Euclidean distance
/// ([`Retrieval::TextToMotion`], as T2M's code does). Top-k is the share of texts whose own
/// motion is among the `k` nearest. Ties count in favour of the matched pair (its rank is the
/// number of candidates strictly nearer).
///
/// # Shapes
/// - `motion`, `text`: `[N, D]`, row `i` of each is the same pair; `N >= batch`.
///
/// # Errors
/// `batch` of 0 or more than `N`, different row counts or widths, ragged rows, non-finite
/// numbers.
pub fn r_precision(
    motion: &[Vec<f32>],
    text: &[Vec<f32>],
    batch: usize,
    seed: u64,
) -> Result<[f64; 3]> {
    r_precision_with(motion, text, batch, seed, Retrieval::TextToMotion)
}

/// [`r_precision`] with the ranking direction chosen (see [`Retrieval`]).
///
/// # Shapes
/// - `motion`, `text`: `[N, D]`, row `i` of each is the same pair; `N >= batch`.
///
/// # Errors
/// As [`r_precision`].
pub fn r_precision_with(
    motion: &[Vec<f32>],
    text: &[Vec<f32>],
    batch: usize,
    seed: u64,
    retrieval: Retrieval,
) -> Result<[f64; 3]> {
    let (motion, text, dim) = matched_pairs(motion, text)?;
    let count = motion.len() / dim;
    if batch == 0 || batch > count {
        return Err(EvalError::invalid(
            "R-precision batch",
            format!("between 1 and the number of pairs ({count})"),
            batch,
        ));
    }
    let (queries, candidates) = match retrieval {
        Retrieval::TextToMotion => (&text, &motion),
        Retrieval::MotionToText => (&motion, &text),
    };
    fn row(m: &[f64], i: usize, dim: usize) -> &[f64] {
        &m[i * dim..(i + 1) * dim]
    }
    let mut order: Vec<usize> = (0..count).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let mut hits = [0usize; 3];
    let mut ranked = 0usize;
    for members in order.chunks_exact(batch) {
        for &q in members {
            let query = row(queries, q, dim);
            let own = distance(query, row(candidates, q, dim));
            let nearer = members
                .iter()
                .filter(|&&c| c != q && distance(query, row(candidates, c, dim)) < own)
                .count();
            for (k, hit) in hits.iter_mut().enumerate() {
                if nearer <= k {
                    *hit += 1;
                }
            }
            ranked += 1;
        }
    }
    Ok(hits.map(|h| h as f64 / ranked as f64))
}

/// Checks matched motion and text embeddings and returns them as `f64` matrices and the width.
fn matched_pairs(motion: &[Vec<f32>], text: &[Vec<f32>]) -> Result<(Vec<f64>, Vec<f64>, usize)> {
    if motion.len() != text.len() {
        return Err(EvalError::invalid(
            "matched motion and text embeddings",
            "as many text rows as motion rows",
            format!("{} motions and {} texts", motion.len(), text.len()),
        ));
    }
    let (motion, dim) = embedding_matrix("motion embeddings", motion, 1)?;
    let (text, text_dim) = embedding_matrix("text embeddings", text, 1)?;
    if dim != text_dim {
        return Err(EvalError::invalid(
            "matched motion and text embeddings",
            "the same width",
            format!("{dim} for motions and {text_dim} for texts"),
        ));
    }
    Ok((motion, text, dim))
}

/// MMdist (multimodal distance, T2M's "matching score"): the mean Euclidean distance between
/// each motion embedding and the embedding of its own text, over all pairs. (T2M sums the
/// trace of each R-precision batch's distance matrix, so it leaves out the dropped remainder;
/// here every pair counts.)
///
/// # Shapes
/// - `motion`, `text`: `[N, D]`, row `i` of each is the same pair.
///
/// # Errors
/// No rows, different row counts or widths, ragged rows, non-finite numbers.
pub fn matching_distance(motion: &[Vec<f32>], text: &[Vec<f32>]) -> Result<f64> {
    let (motion, text, dim) = matched_pairs(motion, text)?;
    let count = motion.len() / dim;
    let total: f64 =
        motion.chunks_exact(dim).zip(text.chunks_exact(dim)).map(|(m, t)| distance(m, t)).sum();
    Ok(total / count as f64)
}

/// Mean and population standard deviation (`ddof = 0`, numpy's default). `NaN`s for no values.
fn mean_std(values: &[f64]) -> (f64, f64) {
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let variance = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
    (mean, variance.sqrt())
}

/// The mean over replications and the half-width of its 95% interval,
/// `1.96 * std / sqrt(n)`, exactly as T2M's `get_metric_statistics`: `std` is numpy's default
/// population standard deviation (`ddof = 0`), so one value gives a half-width of 0.
/// `(NaN, NaN)` for no values.
pub fn mean_interval(values: &[f64]) -> (f64, f64) {
    let (mean, std) = mean_std(values);
    (mean, CONFIDENCE_Z * std / (values.len() as f64).sqrt())
}

/// Runtime per sample: the mean and the population standard deviation (`ddof = 0`) of the
/// seconds each sample took (the paper times a 60-frame sample). `(NaN, NaN)` for no values.
pub fn runtime(seconds: &[f64]) -> (f64, f64) {
    mean_std(seconds)
}

// ---------------------------------------------------------------------------------------------
// Motion samples.
// ---------------------------------------------------------------------------------------------

/// One motion with its objects, borrowed, as the physical metrics read it.
#[derive(Debug, Clone, Copy)]
pub struct MotionSample<'a> {
    /// The skeleton of `joints` (its groups name the hand and foot joints).
    pub skeleton: &'a Skeleton,
    /// `[T, J, 3]` joint positions in metres, Y up, floor at `y = 0`.
    pub joints: &'a [f32],
    /// `[T, 2, 3, 3]` object rotations (object to world), each matrix **row-major** as
    /// [`ProcessedSequence::object_rotations`](dex2hoi_data::features::ProcessedSequence::object_rotations) stores them.
    pub object_rotations: &'a [f32],
    /// `[T, 2, 3]` object positions (the origin of the mesh's frame in the world).
    pub object_positions: &'a [f32],
    /// Which object slots hold an object.
    pub present: [bool; MAX_OBJECTS],
    /// The mesh of each present slot, in its own frame (`None` for an empty slot).
    pub objects: [Option<&'a MeshQuery>; MAX_OBJECTS],
    /// `[T, 2, 3]` mixture weights (left, right, global) per slot, or logits (only their
    /// argmax is used); `None` for motions without a model, such as the ground truth.
    pub mixture_weights: Option<&'a [f32]>,
}

impl MotionSample<'_> {
    /// Checks every array against the skeleton and returns the number of frames `T`.
    ///
    /// # Errors
    /// No frames, lengths that do not match `[T, J, 3]`, `[T, 2, 3, 3]`, `[T, 2, 3]`, a present
    /// slot without a mesh, non-finite numbers.
    pub fn frames(&self) -> Result<usize> {
        let joints = self.skeleton.joint_count();
        let frames = joint_frames(self.joints, joints, "sample joint positions")?;
        let arrays = [
            ("object rotations", self.object_rotations, MAX_OBJECTS * 9, "[T, 2, 3, 3]"),
            ("object positions", self.object_positions, MAX_OBJECTS * 3, "[T, 2, 3]"),
        ];
        for (what, values, per_frame, shape) in arrays {
            check_array(what, values, frames * per_frame, shape, frames)?;
        }
        if let Some(weights) = self.mixture_weights {
            check_array("mixture weights", weights, frames * MAX_OBJECTS * 3, "[T, 2, 3]", frames)?;
        }
        for slot in 0..MAX_OBJECTS {
            if self.present[slot] && self.objects[slot].is_none() {
                return Err(EvalError::invalid(
                    "motion sample objects",
                    "a mesh for every present slot",
                    format!("slot {slot} present without a mesh"),
                ));
            }
        }
        Ok(frames)
    }

    /// The position of joint `j` at frame `t` (indices already checked).
    fn joint(&self, t: usize, j: usize) -> Vec3 {
        let base = (t * self.skeleton.joint_count() + j) * 3;
        Vec3::from_slice(&self.joints[base..base + 3])
    }

    /// The pose of slot `slot` at frame `t` (indices already checked).
    fn object_pose(&self, t: usize, slot: usize) -> ObjectPose {
        let base = (t * MAX_OBJECTS + slot) * 9;
        let rows: [f32; 9] = std::array::from_fn(|k| self.object_rotations[base + k]);
        let base = (t * MAX_OBJECTS + slot) * 3;
        ObjectPose {
            rotation: Mat3::from_cols_array(&rows).transpose(),
            position: Vec3::from_slice(&self.object_positions[base..base + 3]),
        }
    }

    /// The present slots with their meshes.
    fn present_objects(&self) -> impl Iterator<Item = (usize, &MeshQuery)> + '_ {
        (0..MAX_OBJECTS)
            .filter(|&slot| self.present[slot])
            .filter_map(|slot| self.objects[slot].map(|mesh| (slot, mesh)))
    }
}

/// The number of frames of `[T, J, 3]` joint positions, checked (at least one frame, finite).
fn joint_frames(joints: &[f32], joint_count: usize, what: &str) -> Result<usize> {
    let per_frame = joint_count * 3;
    if per_frame == 0 || joints.is_empty() || !joints.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            what,
            format!("[T, {joint_count}, 3] with T >= 1"),
            format!("{} numbers", joints.len()),
        ));
    }
    let frames = joints.len() / per_frame;
    check_array(what, joints, frames * per_frame, "[T, J, 3]", frames)?;
    Ok(frames)
}

/// Checks an array's length and that it is finite.
fn check_array(
    what: &str,
    values: &[f32],
    expected: usize,
    shape: &str,
    frames: usize,
) -> Result<()> {
    if values.len() != expected {
        return Err(EvalError::invalid(
            what,
            format!("{shape} with T = {frames} ({expected} numbers)"),
            format!("{} numbers", values.len()),
        ));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(EvalError::invalid(what, "finite numbers", format!("{} at {i}", values[i])));
    }
    Ok(())
}

/// The mixture weights `softmax(alpha)` (Eq. 4) of object features.
///
/// # Shapes
/// - `object_features`: `[T, 2, 18]` (the logits sit at [`MIXTURE_RANGE`]); returns
///   `[T, 2, 3]`.
///
/// # Errors
/// A length that is not a multiple of `2 * 18`, non-finite logits.
pub fn mixture_weights_from_features(object_features: &[f32]) -> Result<Vec<f32>> {
    let per_frame = MAX_OBJECTS * OBJECT_FEATURE_SIZE;
    if !object_features.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            "object features",
            format!("[T, {MAX_OBJECTS}, {OBJECT_FEATURE_SIZE}]"),
            format!("{} numbers", object_features.len()),
        ));
    }
    let mut weights = Vec::with_capacity(object_features.len() / OBJECT_FEATURE_SIZE * 3);
    for (i, features) in object_features.chunks_exact(OBJECT_FEATURE_SIZE).enumerate() {
        let logits: [f32; 3] = std::array::from_fn(|k| features[MIXTURE_RANGE.start + k]);
        if logits.iter().any(|v| !v.is_finite()) {
            return Err(EvalError::invalid(
                "mixture logits",
                "finite numbers",
                format!("{logits:?} at frame {}, slot {}", i / MAX_OBJECTS, i % MAX_OBJECTS),
            ));
        }
        weights.extend(softmax3(logits));
    }
    Ok(weights)
}

// ---------------------------------------------------------------------------------------------
// Penetration.
// ---------------------------------------------------------------------------------------------

/// Penetration of a motion into its objects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Penetration {
    /// Mean depth in mm over the penetrating joint-frames (0 when none penetrates).
    pub mean_depth_mm: f64,
    /// Share of frames with at least one penetrating joint.
    pub frame_share: f64,
    /// Mean over **all** frames of the frame's deepest penetration in mm (0 for a frame without
    /// one): "the mean interpenetration distance across frames" of the paper's Sec. 4.2.
    pub mean_frame_depth_mm: f64,
    /// Joint-frames deeper than the tolerance.
    pub penetrating_joint_frames: usize,
    /// Frames with at least one penetrating joint.
    pub penetrating_frames: usize,
    /// Frames of the motion.
    pub frames: usize,
    /// Sum of the depths of the penetrating joint-frames, mm.
    pub depth_sum_mm: f64,
    /// Sum over frames of the deepest penetration, mm.
    pub frame_depth_sum_mm: f64,
}

impl Penetration {
    /// The figures of several motions pooled (sums of counts and depths, then the ratios).
    pub fn pooled(items: &[Penetration]) -> Penetration {
        let mut total = Penetration {
            mean_depth_mm: 0.0,
            frame_share: 0.0,
            mean_frame_depth_mm: 0.0,
            penetrating_joint_frames: 0,
            penetrating_frames: 0,
            frames: 0,
            depth_sum_mm: 0.0,
            frame_depth_sum_mm: 0.0,
        };
        for item in items {
            total.penetrating_joint_frames += item.penetrating_joint_frames;
            total.penetrating_frames += item.penetrating_frames;
            total.frames += item.frames;
            total.depth_sum_mm += item.depth_sum_mm;
            total.frame_depth_sum_mm += item.frame_depth_sum_mm;
        }
        total.finish()
    }

    /// Fills the ratios from the sums.
    fn finish(mut self) -> Self {
        let ratio = |a: f64, b: usize| if b == 0 { 0.0 } else { a / b as f64 };
        self.mean_depth_mm = ratio(self.depth_sum_mm, self.penetrating_joint_frames);
        self.frame_share = ratio(self.penetrating_frames as f64, self.frames);
        self.mean_frame_depth_mm = ratio(self.frame_depth_sum_mm, self.frames);
        self
    }
}

/// Penetration (CHOIS; paper Sec. 4.2 "hand and body-object interpenetration"): **every joint**
/// of the skeleton (body and fingers) is moved into each present object's frame
/// (`R^T (p - t)`) and its signed distance to the mesh is taken (negative inside). A joint
/// penetrates when its depth (`-signed distance`, the deepest over the objects) exceeds
/// `tolerance_m` ([`PENETRATION_TOLERANCE_M`] = 5 mm by default); its full depth is counted.
/// Reports the mean depth over penetrating joint-frames, the share of frames with any
/// penetration and the per-frame deepest penetration averaged over all frames.
///
/// # Errors
/// A negative or non-finite tolerance, or a sample that fails [`MotionSample::frames`].
pub fn penetration(sample: &MotionSample<'_>, tolerance_m: f32) -> Result<Penetration> {
    if !(tolerance_m >= 0.0 && tolerance_m.is_finite()) {
        return Err(EvalError::invalid(
            "penetration tolerance",
            "a finite distance >= 0 m",
            tolerance_m,
        ));
    }
    let frames = sample.frames()?;
    let joint_count = sample.skeleton.joint_count();
    let per_frame: Vec<(usize, f64, f64)> = (0..frames)
        .into_par_iter()
        .map(|t| {
            let mut depth = vec![0.0f32; joint_count];
            for (slot, mesh) in sample.present_objects() {
                let pose = sample.object_pose(t, slot);
                let to_object = pose.rotation.transpose();
                for (j, d) in depth.iter_mut().enumerate() {
                    let local = to_object * (sample.joint(t, j) - pose.position);
                    *d = d.max(-mesh.signed_distance(local));
                }
            }
            let mut count = 0;
            let mut sum = 0.0;
            let mut deepest = 0.0f64;
            for &d in depth.iter().filter(|&&d| d > tolerance_m) {
                let mm = f64::from(d) * 1000.0;
                count += 1;
                sum += mm;
                deepest = deepest.max(mm);
            }
            (count, sum, deepest)
        })
        .collect();
    let mut result = Penetration::pooled(&[]);
    result.frames = frames;
    for (count, sum, deepest) in per_frame {
        result.penetrating_joint_frames += count;
        result.penetrating_frames += usize::from(count > 0);
        result.depth_sum_mm += sum;
        result.frame_depth_sum_mm += deepest;
    }
    Ok(result.finish())
}

// ---------------------------------------------------------------------------------------------
// Hand-object contact.
// ---------------------------------------------------------------------------------------------

/// Per frame, per object slot, per hand (left, right): the nearest signed distance in metres
/// from the hand's joints (the skeleton groups `left_hand` / `right_hand`: wrist and fingers)
/// to the object's surface, negative inside; `f32::INFINITY` for an empty slot.
///
/// # Errors
/// A sample that fails [`MotionSample::frames`], or a skeleton without hand joints.
pub fn hand_object_distances(sample: &MotionSample<'_>) -> Result<Vec<[[f32; 2]; MAX_OBJECTS]>> {
    let frames = sample.frames()?;
    let groups = sample.skeleton.groups();
    if groups.left_hand.is_empty() || groups.right_hand.is_empty() {
        return Err(EvalError::invalid(
            "skeleton hand groups",
            "joints in both hands",
            format!("{} left, {} right", groups.left_hand.len(), groups.right_hand.len()),
        ));
    }
    Ok((0..frames)
        .into_par_iter()
        .map(|t| {
            let mut out = [[f32::INFINITY; 2]; MAX_OBJECTS];
            for (slot, mesh) in sample.present_objects() {
                let pose = sample.object_pose(t, slot);
                let to_object = pose.rotation.transpose();
                for (hand, joints) in
                    [&groups.left_hand, &groups.right_hand].into_iter().enumerate()
                {
                    out[slot][hand] = joints
                        .iter()
                        .map(|&j| {
                            mesh.signed_distance(to_object * (sample.joint(t, j) - pose.position))
                        })
                        .fold(f32::INFINITY, f32::min);
                }
            }
            out
        })
        .collect())
}

/// Hand-object contact per frame and object slot (CHOIS): `true` when a joint of either hand is
/// within `radius_m` ([`CONTACT_RADIUS_M`] = 5 cm by default) of the object's surface (or
/// inside it). Always `false` for an empty slot.
///
/// # Errors
/// A negative or non-finite radius, or the errors of [`hand_object_distances`].
pub fn hand_contact(sample: &MotionSample<'_>, radius_m: f32) -> Result<Vec<[bool; MAX_OBJECTS]>> {
    check_radius(radius_m)?;
    Ok(hand_object_distances(sample)?
        .iter()
        .map(|slots| slots.map(|[left, right]| left.min(right) <= radius_m))
        .collect())
}

fn check_radius(radius_m: f32) -> Result<()> {
    if radius_m >= 0.0 && radius_m.is_finite() {
        Ok(())
    } else {
        Err(EvalError::invalid("contact radius", "a finite distance >= 0 m", radius_m))
    }
}

/// Ground-truth contact per frame and slot from `[T, 2, 2]` flags (slot, then left and right
/// hand; as [`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)): `true` when either hand's flag is above 0.5.
///
/// # Shapes
/// - `truth_contact`: `[T, 2, 2]`.
///
/// # Errors
/// A length that is not a multiple of 4, non-finite flags.
pub fn contact_flags(truth_contact: &[f32]) -> Result<Vec<[bool; MAX_OBJECTS]>> {
    Ok(hand_flags(truth_contact)?.into_iter().map(|slots| slots.map(|[l, r]| l || r)).collect())
}

/// `[T, 2, 2]` contact numbers as booleans (above 0.5).
fn hand_flags(truth_contact: &[f32]) -> Result<Vec<[[bool; 2]; MAX_OBJECTS]>> {
    let per_frame = MAX_OBJECTS * 2;
    if !truth_contact.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            format!("[T, {MAX_OBJECTS}, 2] flags"),
            format!("{} numbers", truth_contact.len()),
        ));
    }
    if let Some(i) = truth_contact.iter().position(|v| !v.is_finite()) {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            "finite flags",
            format!("{} at {i}", truth_contact[i]),
        ));
    }
    Ok(truth_contact
        .chunks_exact(per_frame)
        .map(|f| std::array::from_fn(|slot| [f[slot * 2] > 0.5, f[slot * 2 + 1] > 0.5]))
        .collect())
}

/// The confusion counts of per-frame, per-object contact, and the hand-object distance summed
/// over ground-truth contact frames. Counts of several motions add up with [`Self::merge`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactCounts {
    /// Predicted contact where the ground truth has contact.
    pub true_positives: usize,
    /// Predicted contact where the ground truth has none.
    pub false_positives: usize,
    /// No predicted contact where the ground truth has contact.
    pub false_negatives: usize,
    /// Neither.
    pub true_negatives: usize,
    /// Sum over ground-truth contact frames of the nearest hand-object distance, mm.
    pub distance_sum_mm: f64,
    /// Ground-truth contact frames with a distance (slot-frames).
    pub distance_count: usize,
}

impl ContactCounts {
    /// The sum of two sets of counts.
    pub fn merge(self, other: Self) -> Self {
        Self {
            true_positives: self.true_positives + other.true_positives,
            false_positives: self.false_positives + other.false_positives,
            false_negatives: self.false_negatives + other.false_negatives,
            true_negatives: self.true_negatives + other.true_negatives,
            distance_sum_mm: self.distance_sum_mm + other.distance_sum_mm,
            distance_count: self.distance_count + other.distance_count,
        }
    }
}

/// Contact precision, recall and F1 and the mean hand-object distance on ground-truth contact
/// frames (CHOIS, docs/CONVENTIONS.md, "Physical metrics").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactScores {
    /// `TP / (TP + FP)`; 0 when nothing is predicted in contact.
    pub precision: f64,
    /// `TP / (TP + FN)`; 0 when the ground truth has no contact.
    pub recall: f64,
    /// `2 P R / (P + R)`; 0 when both are 0.
    pub f1: f64,
    /// Mean over ground-truth contact slot-frames of the nearest hand joint's distance to the
    /// object's surface in mm (0 for a joint on or inside the surface); `None` without
    /// ground-truth contact or without distances.
    pub mean_distance_on_contact_mm: Option<f64>,
    /// The counts behind the scores.
    pub counts: ContactCounts,
}

impl ContactScores {
    /// Scores from counts (e.g. the counts of a whole test set merged, which avoids the
    /// undefined ratios of single motions without contact). Undefined ratios are 0, as
    /// scikit-learn's `zero_division=0`.
    pub fn from_counts(counts: ContactCounts) -> Self {
        let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        let precision =
            ratio(counts.true_positives, counts.true_positives + counts.false_positives);
        let recall = ratio(counts.true_positives, counts.true_positives + counts.false_negatives);
        let f1 = if precision + recall > 0.0 {
            2.0 * precision * recall / (precision + recall)
        } else {
            0.0
        };
        let mean_distance_on_contact_mm = (counts.distance_count > 0)
            .then(|| counts.distance_sum_mm / counts.distance_count as f64);
        Self { precision, recall, f1, mean_distance_on_contact_mm, counts }
    }
}

/// Confusion counts of predicted against ground-truth contact flags, over the frames of the
/// present slots only (no distances).
///
/// # Shapes
/// - `predicted`, `truth`: `[T]` of per-slot flags, the same `T`.
///
/// # Errors
/// Different frame counts.
pub fn contact_counts(
    predicted: &[[bool; MAX_OBJECTS]],
    truth: &[[bool; MAX_OBJECTS]],
    present: [bool; MAX_OBJECTS],
) -> Result<ContactCounts> {
    if predicted.len() != truth.len() {
        return Err(EvalError::invalid(
            "contact flags",
            "as many predicted frames as ground-truth frames",
            format!("{} predicted, {} ground truth", predicted.len(), truth.len()),
        ));
    }
    let mut counts = ContactCounts::default();
    for (p, g) in predicted.iter().zip(truth) {
        for slot in (0..MAX_OBJECTS).filter(|&s| present[s]) {
            match (p[slot], g[slot]) {
                (true, true) => counts.true_positives += 1,
                (true, false) => counts.false_positives += 1,
                (false, true) => counts.false_negatives += 1,
                (false, false) => counts.true_negatives += 1,
            }
        }
    }
    Ok(counts)
}

/// Contact scores of a generated motion against ground-truth contact: a slot-frame is predicted
/// in contact when a hand joint of `generated` is within `radius_m` of the object
/// ([`hand_contact`]); precision, recall and F1 over the frames of the present slots; and the
/// mean nearest hand-object distance (negative distances, i.e. inside, count as 0) on the
/// slot-frames where the ground truth has contact.
///
/// # Shapes
/// - `truth_contact`: `[T, 2, 2]` ([`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)), the same `T` as the
///   sample.
///
/// # Errors
/// A bad radius, a bad sample, ground-truth flags of another length.
pub fn contact_scores(
    generated: &MotionSample<'_>,
    truth_contact: &[f32],
    radius_m: f32,
) -> Result<ContactScores> {
    check_radius(radius_m)?;
    let distances = hand_object_distances(generated)?;
    let truth = contact_flags(truth_contact)?;
    if truth.len() != distances.len() {
        return Err(EvalError::invalid(
            "ground-truth hand contact",
            format!("[T, 2, 2] with the sample's T = {}", distances.len()),
            format!("{} frames", truth.len()),
        ));
    }
    let nearest: Vec<[f32; MAX_OBJECTS]> =
        distances.iter().map(|slots| slots.map(|[l, r]| l.min(r))).collect();
    let predicted: Vec<[bool; MAX_OBJECTS]> =
        nearest.iter().map(|slots| slots.map(|d| d <= radius_m)).collect();
    let mut counts = contact_counts(&predicted, &truth, generated.present)?;
    for (slots, flags) in nearest.iter().zip(&truth) {
        for slot in (0..MAX_OBJECTS).filter(|&s| generated.present[s] && flags[s]) {
            counts.distance_sum_mm += f64::from(slots[slot].max(0.0)) * 1000.0;
            counts.distance_count += 1;
        }
    }
    Ok(ContactScores::from_counts(counts))
}

// ---------------------------------------------------------------------------------------------
// Foot sliding.
// ---------------------------------------------------------------------------------------------

/// Foot sliding in mm per frame (Zhang et al. 2018, MANN; docs/CONVENTIONS.md, "Physical metrics").
/// The foot joints are the first (ankle) and the last (toe) joint of the skeleton groups
/// `left_foot` and `right_foot` (one joint if a group has only one). For each foot joint and each
/// pair of consecutive frames, with `h` the joint's mean height over the two frames and `H` its
/// threshold ([`ANKLE_HEIGHT_M`] = 0.08 m, [`TOE_HEIGHT_M`] = 0.04 m): when `h < H` the horizontal
/// (XZ) displacement `s` counts with weight `2 - 2^(h/H)` (1 on the floor, 0 at the threshold, up
/// to 2 below the floor). The result is the weighted displacement averaged over all foot joints and
/// frame pairs, in mm.
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

// ---------------------------------------------------------------------------------------------
// Mixture agreement.
// ---------------------------------------------------------------------------------------------

/// The counts behind [`mixture_agreement`]: `(agreeing, judged)` slot-frames.
///
/// # Shapes
/// - `weights`: `[T, 2, 3]` (left, right, global; weights or logits), `truth_contact`:
///   `[T, 2, 2]`, the same `T`.
///
/// # Errors
/// Lengths that do not match, non-finite numbers.
pub fn mixture_agreement_counts(
    weights: &[f32],
    truth_contact: &[f32],
    present: [bool; MAX_OBJECTS],
) -> Result<(usize, usize)> {
    let truth = hand_flags(truth_contact)?;
    let frames = truth.len();
    check_array("mixture weights", weights, frames * MAX_OBJECTS * 3, "[T, 2, 3]", frames)?;
    let mut agree = 0;
    let mut judged = 0;
    for (t, hands) in truth.iter().enumerate() {
        for slot in (0..MAX_OBJECTS).filter(|&s| present[s]) {
            let holder = match hands[slot] {
                [true, false] => 0,
                [false, true] => 1,
                _ => continue,
            };
            let base = (t * MAX_OBJECTS + slot) * 3;
            let w = &weights[base..base + 3];
            // The first of equal maxima wins (left before right before global).
            let argmax = (1..3).fold(0, |best, k| if w[k] > w[best] { k } else { best });
            judged += 1;
            agree += usize::from(argmax == holder);
        }
    }
    Ok((agree, judged))
}

/// Mixture agreement: over the slot-frames of present objects where **exactly one** hand holds
/// the object in the ground truth, the share where the argmax of the predicted mixture weights
/// (Eq. 4: left, right, global) is that hand. `None` when there are no such slot-frames.
///
/// # Shapes
/// - `weights`: `[T, 2, 3]` (weights or logits), `truth_contact`: `[T, 2, 2]`
///   ([`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)), the same `T`.
///
/// # Errors
/// As [`mixture_agreement_counts`].
pub fn mixture_agreement(
    weights: &[f32],
    truth_contact: &[f32],
    present: [bool; MAX_OBJECTS],
) -> Result<Option<f64>> {
    let (agree, judged) = mixture_agreement_counts(weights, truth_contact, present)?;
    Ok((judged > 0).then(|| agree as f64 / judged as f64))
}
