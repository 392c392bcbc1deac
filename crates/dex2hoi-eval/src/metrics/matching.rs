//! Text-motion matching metrics on evaluator embeddings (paper Sec. 4.2, T2M's protocol):
//! R-precision and MMdist.

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

use crate::error::{EvalError, Result};

use super::embedding::{distance, embedding_matrix};

/// Batch size of [`r_precision`]: 32 motion-text pairs, as in T2M.
pub const R_PRECISION_BATCH: usize = 32;

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
    r_precision_of_ranks(&retrieval_ranks(motion, text, batch, seed, retrieval)?)
}

/// R-precision top-1/2/3 from [`retrieval_ranks`]' output.
///
/// # Errors
/// No ranked pair.
pub fn r_precision_of_ranks(ranks: &[Option<usize>]) -> Result<[f64; 3]> {
    top_k_shares(ranks.iter().flatten().copied())
        .ok_or_else(|| EvalError::invalid("R-precision", "at least one ranked pair", "none"))
}

/// Each pair's rank in [`r_precision_with`]'s protocol: how many of its batch's candidates lie
/// strictly nearer its query than its own match (0: retrieved first); `None` for the pairs of
/// the dropped incomplete batch. [`top_k_shares`] of the ranks of any subset of pairs (a task
/// family, say) is that subset's R-precision.
///
/// # Shapes
/// - `motion`, `text`: `[N, D]`, row `i` of each is the same pair; returns `[N]`
///
/// # Errors
/// As [`r_precision`].
pub fn retrieval_ranks(
    motion: &[Vec<f32>],
    text: &[Vec<f32>],
    batch: usize,
    seed: u64,
    retrieval: Retrieval,
) -> Result<Vec<Option<usize>>> {
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
    let mut ranks = vec![None; count];
    for members in order.chunks_exact(batch) {
        for &q in members {
            let query = row(queries, q, dim);
            let own = distance(query, row(candidates, q, dim));
            let nearer = members
                .iter()
                .filter(|&&c| c != q && distance(query, row(candidates, c, dim)) < own)
                .count();
            ranks[q] = Some(nearer);
        }
    }
    Ok(ranks)
}

/// Top-1/2/3 shares of ranks from [`retrieval_ranks`]: the share of ranks below 1, 2 and 3;
/// `None` for no ranks.
pub fn top_k_shares(ranks: impl IntoIterator<Item = usize>) -> Option<[f64; 3]> {
    let mut hits = [0usize; 3];
    let mut ranked = 0usize;
    for rank in ranks {
        for (k, hit) in hits.iter_mut().enumerate() {
            if rank <= k {
                *hit += 1;
            }
        }
        ranked += 1;
    }
    (ranked > 0).then(|| hits.map(|h| h as f64 / ranked as f64))
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
