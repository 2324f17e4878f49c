//! The block-sparse normal equations `(H + λD) h = −g` of a pose graph and their sparse Cholesky solve.
//!
//! `H` is symmetric with 3×3 blocks; we store its upper triangle in compressed-sparse-column form, with a
//! precomputed value offset for every block so that assembly is a plain scatter. The fill-reducing
//! ordering is approximate minimum degree on the *block* graph, expanded to scalars (cheaper than AMD on
//! the scalar matrix, and it keeps each pose's three columns together for supernodes). The symbolic
//! factorization is kept as long as the block pattern stays the same.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::{LltError, LltRegularization};
use faer::perm::PermRef;
use faer::reborrow::Reborrow as _;
use faer::sparse::linalg::amd;
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{FaerError, SparseColMatRef, SymbolicSparseColMat, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side, Spec};
use nalgebra::Matrix3;

/// Marks "no block" (an edge touching a fixed variable has no off-diagonal block).
pub(crate) const NO_BLOCK: u32 = u32::MAX;

/// Why the linear system could not be set up or solved.
#[derive(Debug, Clone, Copy, thiserror::Error)]
pub(crate) enum LinearSystemError {
    /// faer could not allocate or order the matrix (a failed scratch allocation arrives as faer's own
    /// `FaerError::OutOfMemory`, its `From<AllocError>`).
    #[error("could not order or analyse the linear system's sparsity pattern")]
    Symbolic(#[source] FaerError),
    /// The damped matrix is not numerically positive definite (faer's error names the failing pivot).
    #[error("the damped linear system is not numerically positive definite")]
    NotPositiveDefinite(#[source] LltError),
}

/// Sparsity pattern of the upper triangle of a block-symmetric matrix with 3×3 blocks.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct BlockPattern {
    n_blocks: usize,
    /// Block-level upper CSC: `block_col_ptr[c]..block_col_ptr[c+1]` index `block_rows` (sorted, ending with `c`).
    block_col_ptr: Vec<usize>,
    block_rows: Vec<usize>,
    /// Per block (same enumeration as `block_rows`), the value offset of its first entry in each of the
    /// block column's three scalar columns.
    block_offsets: Vec<[usize; 3]>,
    /// Index of each scalar diagonal entry in the value array.
    diagonal_offsets: Vec<usize>,
    scalar_col_ptr: Vec<usize>,
    scalar_rows: Vec<usize>,
}

impl BlockPattern {
    /// Builds the pattern of `n_blocks` diagonal blocks plus the blocks joining each `(a, b)` pair
    /// (`a ≠ b`, duplicates allowed).
    pub(crate) fn new(n_blocks: usize, pairs: impl Iterator<Item = (u32, u32)>) -> Self {
        let mut entries: Vec<(u32, u32)> = pairs.map(|(a, b)| (a.max(b), a.min(b))).collect();
        entries.extend((0..n_blocks as u32).map(|c| (c, c)));
        entries.sort_unstable();
        entries.dedup();

        let mut block_col_ptr = Vec::with_capacity(n_blocks + 1);
        let mut block_rows = Vec::with_capacity(entries.len());
        block_col_ptr.push(0);
        let mut next = 0;
        for c in 0..n_blocks as u32 {
            while next < entries.len() && entries[next].0 == c {
                block_rows.push(entries[next].1 as usize);
                next += 1;
            }
            block_col_ptr.push(block_rows.len());
        }

        let n = 3 * n_blocks;
        let off_diagonal = block_rows.len() - n_blocks;
        let nnz = 9 * off_diagonal + 6 * n_blocks;
        let mut block_offsets = vec![[0; 3]; block_rows.len()];
        let mut diagonal_offsets = vec![0; n];
        let mut scalar_col_ptr = Vec::with_capacity(n + 1);
        let mut scalar_rows = Vec::with_capacity(nnz);
        scalar_col_ptr.push(0);
        for c in 0..n_blocks {
            for k in 0..3 {
                for block in block_col_ptr[c]..block_col_ptr[c + 1] {
                    let r = block_rows[block];
                    block_offsets[block][k] = scalar_rows.len();
                    let rows = if r == c { k + 1 } else { 3 };
                    scalar_rows.extend((0..rows).map(|i| 3 * r + i));
                }
                diagonal_offsets[3 * c + k] = scalar_rows.len() - 1;
                scalar_col_ptr.push(scalar_rows.len());
            }
        }
        Self {
            n_blocks,
            block_col_ptr,
            block_rows,
            block_offsets,
            diagonal_offsets,
            scalar_col_ptr,
            scalar_rows,
        }
    }

    /// Number of scalar unknowns.
    pub(crate) fn dim(&self) -> usize {
        3 * self.n_blocks
    }

    /// Number of stored (upper-triangle) values.
    pub(crate) fn nnz(&self) -> usize {
        self.scalar_rows.len()
    }

    /// The block index of `(row, col)` with `row ≤ col`, or [`NO_BLOCK`].
    pub(crate) fn block(&self, row: u32, col: u32) -> u32 {
        let col = col as usize;
        let rows = &self.block_rows[self.block_col_ptr[col]..self.block_col_ptr[col + 1]];
        rows.binary_search(&(row as usize))
            .map_or(NO_BLOCK, |k| (self.block_col_ptr[col] + k) as u32)
    }

    /// Adds `m` (rows of the block row, columns of the block column) to an off-diagonal block.
    #[inline]
    pub(crate) fn add_off_diagonal(&self, values: &mut [f64], block: u32, m: &Matrix3<f64>) {
        let offsets = &self.block_offsets[block as usize];
        for (k, &offset) in offsets.iter().enumerate() {
            let column = &mut values[offset..offset + 3];
            column[0] += m[(0, k)];
            column[1] += m[(1, k)];
            column[2] += m[(2, k)];
        }
    }

    /// Adds the upper triangle of the symmetric `m` to a diagonal block.
    #[inline]
    pub(crate) fn add_diagonal(&self, values: &mut [f64], block: u32, m: &Matrix3<f64>) {
        let [o0, o1, o2] = self.block_offsets[block as usize];
        values[o0] += m[(0, 0)];
        values[o1] += m[(0, 1)];
        values[o1 + 1] += m[(1, 1)];
        values[o2] += m[(0, 2)];
        values[o2 + 1] += m[(1, 2)];
        values[o2 + 2] += m[(2, 2)];
    }

    /// Value indices of the scalar diagonal entries.
    pub(crate) fn diagonal_offsets(&self) -> &[usize] {
        &self.diagonal_offsets
    }

    /// Approximate-minimum-degree ordering of the block graph, expanded to scalars `(forward, inverse)`.
    fn scalar_ordering(&self) -> Result<(Vec<usize>, Vec<usize>), LinearSystemError> {
        let n = self.n_blocks;
        let mut block_perm = vec![0usize; n];
        let mut block_perm_inv = vec![0usize; n];
        let pattern =
            SymbolicSparseColMatRef::new_checked(n, n, &self.block_col_ptr, None, &self.block_rows);
        let mut mem = MemBuffer::try_new(amd::order_scratch::<usize>(n, self.block_rows.len()))
            .map_err(|e| LinearSystemError::Symbolic(FaerError::from(e)))?;
        amd::order(
            &mut block_perm,
            &mut block_perm_inv,
            pattern,
            amd::Control::default(),
            MemStack::new(&mut mem),
        )
        .map_err(LinearSystemError::Symbolic)?;
        let forward: Vec<usize> = block_perm
            .iter()
            .flat_map(|&b| [3 * b, 3 * b + 1, 3 * b + 2])
            .collect();
        let mut inverse = vec![0; forward.len()];
        for (new, &old) in forward.iter().enumerate() {
            inverse[old] = new;
        }
        Ok((forward, inverse))
    }
}

/// A sparse Cholesky solver bound to one [`BlockPattern`]: symbolic analysis once, numeric per solve.
pub(crate) struct SparseCholesky {
    pattern: BlockPattern,
    matrix: SymbolicSparseColMat<usize>,
    symbolic: SymbolicCholesky<usize>,
    factor_values: Vec<f64>,
    mem: MemBuffer,
}

impl std::fmt::Debug for SparseCholesky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparseCholesky")
            .field("dim", &self.pattern.dim())
            .field("nnz", &self.pattern.nnz())
            .field("factor_nnz", &self.factor_values.len())
            .finish_non_exhaustive()
    }
}

impl SparseCholesky {
    /// Orders the pattern and computes the symbolic factorization.
    pub(crate) fn new(pattern: BlockPattern) -> Result<Self, LinearSystemError> {
        let n = pattern.dim();
        let matrix = SymbolicSparseColMat::new_checked(
            n,
            n,
            pattern.scalar_col_ptr.clone(),
            None,
            pattern.scalar_rows.clone(),
        );
        let (forward, inverse) = pattern.scalar_ordering()?;
        let perm = PermRef::new_checked(&forward, &inverse, n);
        let symbolic = factorize_symbolic_cholesky(
            matrix.rb(),
            Side::Upper,
            SymmetricOrdering::Custom(perm),
            CholeskySymbolicParams::default(),
        )
        .map_err(LinearSystemError::Symbolic)?;
        let req = StackReq::any_of(&[
            symbolic.factorize_numeric_llt_scratch::<f64>(Par::Seq, Spec::default()),
            symbolic.solve_in_place_scratch::<f64>(1, Par::Seq),
        ]);
        let mem =
            MemBuffer::try_new(req).map_err(|e| LinearSystemError::Symbolic(FaerError::from(e)))?;
        let factor_values = vec![0.0; symbolic.len_val()];
        Ok(Self {
            pattern,
            matrix,
            symbolic,
            factor_values,
            mem,
        })
    }

    /// Values stored for the Cholesky factor `L`: its nonzeros, fill-in included, and the zeros its dense
    /// supernode blocks hold (what a numeric factorization and a solve cost grows with).
    pub(crate) fn factor_nonzeros(&self) -> usize {
        self.factor_values.len()
    }

    /// The pattern this solver was built for.
    pub(crate) fn pattern(&self) -> &BlockPattern {
        &self.pattern
    }

    /// Factors the matrix with upper-triangle `values` (laid out by [`Self::pattern`]) and overwrites
    /// `rhs` with the solution.
    pub(crate) fn solve(
        &mut self,
        values: &[f64],
        rhs: &mut [f64],
    ) -> Result<(), LinearSystemError> {
        let n = self.pattern.dim();
        let matrix = SparseColMatRef::new(self.matrix.rb(), values);
        let stack = MemStack::new(&mut self.mem);
        let llt = self
            .symbolic
            .factorize_numeric_llt(
                &mut self.factor_values,
                matrix,
                Side::Upper,
                LltRegularization::default(),
                Par::Seq,
                stack,
                Spec::default(),
            )
            .map_err(LinearSystemError::NotPositiveDefinite)?;
        let stack = MemStack::new(&mut self.mem);
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(rhs, n, 1),
            Par::Seq,
            stack,
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Builds a random symmetric positive-definite block matrix on `pattern`, returning its values and dense copy.
    fn random_spd(
        pattern: &BlockPattern,
        pairs: &[(u32, u32)],
        seed: u64,
    ) -> (Vec<f64>, nalgebra::DMatrix<f64>) {
        use rand::{Rng as _, SeedableRng as _};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let n = pattern.dim();
        let mut values = vec![0.0; pattern.nnz()];
        let mut dense = nalgebra::DMatrix::zeros(n, n);
        for &(a, b) in pairs {
            // A random J = [Ja Jb] contributes JᵀJ.
            let ja = Matrix3::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let jb = Matrix3::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let (r, c, m) = if a < b {
                (a, b, ja.transpose() * jb)
            } else {
                (b, a, jb.transpose() * ja)
            };
            pattern.add_off_diagonal(&mut values, pattern.block(r, c), &m);
            pattern.add_diagonal(&mut values, pattern.block(a, a), &(ja.transpose() * ja));
            pattern.add_diagonal(&mut values, pattern.block(b, b), &(jb.transpose() * jb));
            let (a, b) = (3 * a as usize, 3 * b as usize);
            let jaja = ja.transpose() * ja;
            let jbjb = jb.transpose() * jb;
            let jajb = ja.transpose() * jb;
            for i in 0..3 {
                for j in 0..3 {
                    dense[(a + i, a + j)] += jaja[(i, j)];
                    dense[(b + i, b + j)] += jbjb[(i, j)];
                    dense[(a + i, b + j)] += jajb[(i, j)];
                    dense[(b + j, a + i)] += jajb[(i, j)];
                }
            }
        }
        for &d in pattern.diagonal_offsets() {
            values[d] += 1.0;
        }
        for i in 0..n {
            dense[(i, i)] += 1.0;
        }
        (values, dense)
    }

    #[test]
    fn sparse_solve_matches_dense_solve() {
        let pairs = [
            (0, 1),
            (1, 2),
            (2, 3),
            (3, 4),
            (4, 0),
            (1, 3),
            (3, 1),
            (5, 2),
        ];
        let pattern = BlockPattern::new(6, pairs.iter().copied());
        assert_eq!(
            pattern.nnz(),
            6 * 6 + 9 * 7,
            "duplicate pair (1,3)/(3,1) is one block"
        );
        let (values, dense) = random_spd(&pattern, &pairs, 7);
        let rhs: Vec<f64> = (0..18).map(|i| f64::from(i) * 0.37 - 2.0).collect();
        let mut x = rhs.clone();
        let mut solver = SparseCholesky::new(BlockPattern::new(6, pairs.iter().copied())).unwrap();
        solver.solve(&values, &mut x).unwrap();
        let expected = dense
            .cholesky()
            .unwrap()
            .solve(&nalgebra::DVector::from_vec(rhs));
        for (got, want) in x.iter().zip(expected.iter()) {
            assert!(
                (got - want).abs() < 1e-9 * (1.0 + want.abs()),
                "{got} vs {want}"
            );
        }
    }

    #[test]
    fn indefinite_matrix_is_reported() {
        let pattern = BlockPattern::new(2, [(0u32, 1u32)].into_iter());
        let mut values = vec![0.0; pattern.nnz()];
        for &d in pattern.diagonal_offsets() {
            values[d] = -1.0;
        }
        let mut solver = SparseCholesky::new(pattern).unwrap();
        let mut rhs = vec![1.0; 6];
        assert!(matches!(
            solver.solve(&values, &mut rhs),
            Err(LinearSystemError::NotPositiveDefinite(
                LltError::NonPositivePivot { .. }
            ))
        ));
    }
}
