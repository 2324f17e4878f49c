//! Eigendecomposition of the dense symmetric matrices sparsification works on (the marginal
//! information over a trimmed submap's Markov blanket: a few hundred rows).
//!
//! faer's blocked divide-and-conquer decomposition does this several times faster than nalgebra's
//! `SymmetricEigen` at these sizes (which made sparsification two thirds of a lifelong session's pose
//! graph refinement); nalgebra's stays as the fallback if faer's fails to converge.

use faer::{MatRef, Side};
use nalgebra::{DMatrix, DVector};

/// Eigenvalues (ascending) and the matching orthonormal eigenvectors (columns) of the symmetric part
/// `½(m + mᵀ)` of a square matrix.
pub(crate) struct SymmetricEigen {
    pub eigenvalues: DVector<f64>,
    pub eigenvectors: DMatrix<f64>,
}

/// See [`SymmetricEigen`].
pub(crate) fn symmetric_eigen(m: &DMatrix<f64>) -> SymmetricEigen {
    let n = m.nrows();
    let symmetric = 0.5 * (m + m.transpose());
    let view = MatRef::from_column_major_slice(symmetric.as_slice(), n, n);
    if let Ok(eigen) = view.self_adjoint_eigen(Side::Lower) {
        let u = eigen.U();
        let s = eigen.S().column_vector();
        return SymmetricEigen {
            eigenvalues: DVector::from_fn(n, |i, _| s[i]),
            eigenvectors: DMatrix::from_fn(n, n, |i, j| u[(i, j)]),
        };
    }
    let eigen = symmetric.symmetric_eigen();
    SymmetricEigen {
        eigenvalues: eigen.eigenvalues,
        eigenvectors: eigen.eigenvectors,
    }
}

/// `m · diag(d)`: each column of `m` times its entry of `d` (without a dense product with a diagonal
/// matrix, which costs as much as a full matrix product).
pub(crate) fn scale_columns(m: &DMatrix<f64>, d: &DVector<f64>) -> DMatrix<f64> {
    let mut scaled = m.clone();
    for (mut column, &factor) in scaled.column_iter_mut().zip(d.iter()) {
        column *= factor;
    }
    scaled
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A symmetric matrix with a known spectrum, built from a rotation-like orthonormal basis.
    fn spd(n: usize, seed: u64) -> DMatrix<f64> {
        let mut state = seed;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let a = DMatrix::from_fn(n, n, |_, _| next());
        &a * a.transpose() + DMatrix::identity(n, n) * 1e-3
    }

    #[test]
    fn matches_nalgebra_and_reconstructs_the_matrix() {
        for (n, seed) in [(1, 1), (3, 2), (40, 3), (120, 4)] {
            let m = spd(n, seed);
            let eigen = symmetric_eigen(&m);
            let reference = m.clone().symmetric_eigen();
            let mut expected: Vec<f64> = reference.eigenvalues.iter().copied().collect();
            expected.sort_by(f64::total_cmp);
            for (got, want) in eigen.eigenvalues.iter().zip(&expected) {
                assert!(
                    (got - want).abs() <= 1e-9 * (1.0 + want.abs()),
                    "{got} vs {want}"
                );
            }
            let rebuilt = &eigen.eigenvectors
                * DMatrix::from_diagonal(&eigen.eigenvalues)
                * eigen.eigenvectors.transpose();
            assert!((rebuilt - &m).amax() <= 1e-9 * m.amax(), "n = {n}");
            let identity = eigen.eigenvectors.transpose() * &eigen.eigenvectors;
            assert!((identity - DMatrix::identity(n, n)).amax() <= 1e-10);
        }
    }

    #[test]
    fn scaling_columns_is_a_product_with_a_diagonal_matrix() {
        let m = spd(7, 9);
        let d = DVector::from_fn(7, |i, _| i as f64 - 2.5);
        let expected = &m * DMatrix::from_diagonal(&d);
        assert!((scale_columns(&m, &d) - expected).amax() < 1e-12);
    }

    #[test]
    fn only_the_symmetric_part_counts() {
        let m = DMatrix::from_row_slice(2, 2, &[2.0, 1.0, 3.0, 2.0]);
        let eigen = symmetric_eigen(&m);
        // ½(m + mᵀ) = [[2, 2], [2, 2]]: eigenvalues 0 and 4.
        assert!((eigen.eigenvalues[0]).abs() < 1e-12);
        assert!((eigen.eigenvalues[1] - 4.0).abs() < 1e-12);
    }
}
