//! Dense linear algebra for FID: the eigen-decomposition of a real symmetric matrix and the
//! square root of a positive semi-definite one, on row-major `f64` matrices.

use crate::error::{EvalError, Result};

/// `A B` for row-major `n x n` matrices.
pub(super) fn multiply(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
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
pub(super) fn psd_square_root(m: &[f64], n: usize) -> Result<Vec<f64>> {
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
