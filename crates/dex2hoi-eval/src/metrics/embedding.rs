//! Shared checks of embedding rows for the distribution and matching metrics.

use crate::error::{EvalError, Result};

/// Rows of `f32` embeddings as one row-major `f64` matrix, checked: at least `min_rows` rows,
/// all of the same non-zero width, all finite.
pub(super) fn embedding_matrix(
    what: &str,
    rows: &[Vec<f32>],
    min_rows: usize,
) -> Result<(Vec<f64>, usize)> {
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
pub(super) fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt()
}
