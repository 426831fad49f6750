"""Scatter of dense element blocks into a sparse matrix over the free DOFs.

The sparsity pattern and the map from every element entry to its CSR slot are built
once per mesh; each Newton iteration is then a single ``np.bincount``
(toolchain.md: ~0.08 s for 8.6M entries versus ~0.44 s for COO -> CSR).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


class BlockScatter:
    """Assemble blocks (k_i, d_i, d_i) with DOF index arrays (k_i, d_i) into CSR.

    free: boolean mask over all DOFs; rows/columns of fixed DOFs are dropped.
    upper: keep only the upper triangle (row <= column) of the symmetric result: half the
    gather and sum work; what the Cholesky backends read (see shellfem.solver.SparseSPD).
    """

    def __init__(self, index_sets, n_dofs: int, free: np.ndarray, upper: bool = False):
        self.upper = upper
        self.n_dofs = n_dofs
        reduced = -np.ones(n_dofs, dtype=np.int64)
        reduced[free] = np.arange(int(free.sum()))
        self.reduced = reduced
        self.n_free = int(free.sum())
        rows, cols, keep = [], [], []
        for idx in index_sets:
            r = reduced[idx]                                   # (k, d)
            R = np.broadcast_to(r[:, :, None], r.shape + (r.shape[1],))
            C = np.broadcast_to(r[:, None, :], R.shape)
            ok = (R >= 0) & (C >= 0)
            if upper:
                ok &= R <= C
            rows.append(R[ok])
            cols.append(C[ok])
            keep.append(ok.ravel())
        self._keep = keep
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        key = rows * self.n_free + cols
        # np.unique(return_inverse) uses a stable sort; an unstable argsort and a cumulative
        # count do the same job in half the time (measured 4.6 s vs 9.5 s at 18M entries)
        order = np.argsort(key)
        ks = key[order]
        first = np.empty(len(ks), bool)
        first[:1] = True
        np.not_equal(ks[1:], ks[:-1], out=first[1:])
        inv = np.empty(len(ks), np.int64)
        inv[order] = np.cumsum(first) - 1
        uniq = ks[first]
        self._slot = inv
        self.nnz = len(uniq)
        self._indices = (uniq % self.n_free).astype(np.int64)
        r = uniq // self.n_free
        self._indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=self.n_free))]).astype(np.int64)

    def matrix(self, blocks) -> sp.csr_matrix:
        vals = np.concatenate([b.reshape(-1)[k] for b, k in zip(blocks, self._keep)])
        data = np.bincount(self._slot, weights=vals, minlength=self.nnz)
        return sp.csr_matrix((data, self._indices.copy(), self._indptr.copy()), shape=(self.n_free, self.n_free))


def symmetric_matvec(U: sp.csr_matrix, x: np.ndarray) -> np.ndarray:
    """A x for the symmetric A whose upper triangle (with diagonal) is U."""
    return U @ x + U.T @ x - U.diagonal() * x


def scatter_vector(index_sets, values, n_dofs: int) -> np.ndarray:
    """Sum element vectors (k_i, d_i) into a global vector of length n_dofs."""
    out = np.zeros(n_dofs)
    for idx, v in zip(index_sets, values):
        out += np.bincount(idx.ravel(), weights=v.ravel(), minlength=n_dofs)
    return out
