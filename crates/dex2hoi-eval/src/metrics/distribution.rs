//! Distribution metrics on evaluator embeddings (paper Sec. 4.2, following T2M / MDM): FID,
//! Diversity and MultiModality. FID's matrix square roots use the symmetric eigen-solver of
//! [`super::linalg`].

use rand::SeedableRng;
use rand::seq::index;
use rand_chacha::ChaCha8Rng;

use crate::error::{EvalError, Result};

use super::embedding::{distance, embedding_matrix};
use super::linalg::{multiply, psd_square_root, symmetric_eigen};

/// Random pairs for [`diversity`]: 300, as in T2M and MDM.
pub const DIVERSITY_PAIRS: usize = 300;

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
    /// A setting a 2-core CPU affords next to the test split: 8 prompts x 4 generations x
    /// 3 pairs (32 extra clips per replication). `dex2hoi evaluate --multimodality` shows and
    /// uses this default.
    fn default() -> Self {
        Self { prompts: 8, repeats: 4, pairs: 3 }
    }
}

impl MultimodalityProtocol {
    /// The paper's (T2M's) setting: 100 prompts x 30 generations x 10 pairs.
    pub fn paper() -> Self {
        Self { prompts: 100, repeats: 30, pairs: 10 }
    }

    /// Whether the protocol measures anything: at least one prompt with two generations to
    /// pair. (A protocol with no prompts, or one generation each, turns MultiModality off.)
    pub fn is_measured(&self) -> bool {
        self.prompts > 0 && self.repeats > 1
    }

    /// Refuses a measuring protocol whose pairs [`multimodality`] could not draw (0, or more
    /// than the generations per prompt), before any generation is spent on it.
    pub fn validate(&self) -> Result<()> {
        if self.is_measured() && !(1..=self.repeats).contains(&self.pairs) {
            return Err(EvalError::invalid(
                "multimodality pairs",
                format!("between 1 and the generations per prompt ({})", self.repeats),
                self.pairs,
            ));
        }
        Ok(())
    }
}

/// `PROMPTS,REPEATS,PAIRS`, as `dex2hoi evaluate --multimodality` takes it.
impl std::fmt::Display for MultimodalityProtocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{},{},{}", self.prompts, self.repeats, self.pairs)
    }
}

/// Parses `PROMPTS,REPEATS,PAIRS` (three whole numbers, spaces allowed around them) and
/// [validates](MultimodalityProtocol::validate) the result.
impl std::str::FromStr for MultimodalityProtocol {
    type Err = EvalError;

    fn from_str(text: &str) -> Result<Self> {
        let expected = "PROMPTS,REPEATS,PAIRS: three whole numbers separated by commas";
        let numbers = text
            .split(',')
            .map(|v| v.trim().parse::<usize>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|_| EvalError::invalid("multimodality protocol", expected, text))?;
        let [prompts, repeats, pairs] = numbers[..] else {
            return Err(EvalError::invalid("multimodality protocol", expected, text));
        };
        let protocol = Self { prompts, repeats, pairs };
        protocol.validate()?;
        Ok(protocol)
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
