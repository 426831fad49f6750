"""Scatter of dense element blocks into a sparse matrix over the free DOFs.

The sparsity pattern and, for every CSR slot, the list of element entries that sum into it
are built once per mesh; each Newton iteration is then one compiled gather over the slots
(parallel, each slot summed in a fixed order, so bitwise repeatable): 0.02 s for the 7.3M
entries of the 85 x 60 benchmark's upper triangle, against 0.07 s for a gather of the kept
entries and ``np.bincount`` (and ~0.44 s for COO -> CSR, toolchain.md). Building the pattern
and the slot lists (compiled, linear in the entries) takes 0.28 s there; the solver builds three per mesh (full Hessian, edge
angles, printed block), and nested iteration one set per level.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from shellfem.linalg import same_frozen


class BlockScatter:
    """Assemble blocks (k_i, d_i, d_i) with DOF index arrays (k_i, d_i) into CSR.

    free: boolean mask over all DOFs; rows/columns of fixed DOFs are dropped.
    upper: keep only the upper triangle (row <= column) of the symmetric result: half the
    gather and sum work; what the Cholesky backends read (see shellfem.linalg.SparseSPD).
    """

    def __init__(self, index_sets, n_dofs: int, free: np.ndarray, upper: bool = False):
        self.upper = upper
        self.n_dofs = n_dofs
        reduced = -np.ones(n_dofs, dtype=np.int64)
        reduced[free] = np.arange(int(free.sum()))
        self.reduced = reduced
        self.n_free = int(free.sum())
        self._sizes = [int(np.prod(idx.shape) * idx.shape[1]) for idx in index_sets]
        sets = [np.ascontiguousarray(reduced[idx], dtype=np.int64) for idx in index_sets]
        first, second = sets[0], (sets[1] if len(sets) > 1 else np.zeros((0, 1), np.int64))
        if len(sets) > 2:
            raise ValueError("BlockScatter takes one or two index sets")
        # entries grouped by row in block order (one counting pass), then per row its distinct
        # columns (sorted) and each slot's entries in block order, so a slot sums its element
        # entries in block order: O(entries), against 0.76 s for an argsort of the 7.3M
        # upper-triangle keys of the 85 x 60 benchmark
        counts = np.zeros(self.n_free, np.int64)
        _visit_rows(first, second, upper, counts, np.empty(0, np.int64), np.empty(0, np.int64), False)
        row_start = np.concatenate([[0], np.cumsum(counts)])
        cols, raw = np.empty(row_start[-1], np.int64), np.empty(row_start[-1], np.int64)
        _visit_rows(first, second, upper, row_start[:-1].copy(), cols, raw, True)
        slots = _distinct_per_row(cols, row_start, self.n_free)
        self.nnz = int(slots.sum())
        itype = np.int32 if max(self.nnz, self.n_free) < 2 ** 31 - 1 else np.int64
        indptr = np.concatenate([[0], np.cumsum(slots)])
        indices, ptr, src = _slot_lists(cols, raw, row_start, indptr, self.n_free)
        # int32 where it fits: scipy would otherwise convert (copy) them in every matrix
        self._indices = indices.astype(itype)
        self._indptr = indptr.astype(itype)
        # slot s sums the raw block entries _src[_ptr[s]:_ptr[s + 1]]
        self._ptr = np.append(ptr, row_start[-1]).astype(np.int64)
        self._src = src.astype(np.int32 if sum(self._sizes) < 2 ** 31 else np.int64)
        # every matrix shares these (read-only: an in-place change would raise, not corrupt);
        # solvers recognise the pattern by identity
        self._indices.flags.writeable = False
        self._indptr.flags.writeable = False

    def matrix(self, blocks) -> sp.csr_matrix:
        """CSR matrix (n_free, n_free) of the blocks, one (k_i, d_i, d_i) array per index set."""
        flat = [np.ascontiguousarray(b, dtype=float).reshape(-1) for b in blocks]
        if [len(f) for f in flat] != self._sizes:
            raise ValueError(f"block sizes {[len(f) for f in flat]} do not match the index sets {self._sizes}")
        if len(flat) == 1:
            first, second = flat[0], flat[0][:0]
        elif len(flat) == 2:
            first, second = flat
        else:
            first, second = np.concatenate(flat), flat[0][:0]
        data = _gather_sum(first, second, self._src, self._ptr)
        M = sp.csr_matrix((data, self._indices, self._indptr), shape=(self.n_free, self.n_free), copy=False)
        M.has_canonical_format = True      # sorted, no duplicates by construction (saves a scan)
        return M


@njit(cache=True)
def _visit_rows(first, second, upper, pos, cols, raw, fill):
    """Every kept block entry (free row and column, row <= column if upper) in block order:
    pos[row] += 1 (count pass, pos = zeros), or with ``fill`` also its column and raw index
    written at pos[row] (pos = the rows' start offsets): entries grouped by row."""
    offset = 0
    for blocks in (first, second):
        d = blocks.shape[1]
        for e in range(blocks.shape[0]):
            for i in range(d):
                r = blocks[e, i]
                if r < 0:
                    continue
                for j in range(d):
                    c = blocks[e, j]
                    if c >= 0 and (not upper or r <= c):
                        if fill:
                            cols[pos[r]] = c
                            raw[pos[r]] = offset + (e * d + i) * d + j
                        pos[r] += 1
        offset += blocks.shape[0] * d * d


_CHUNKS = 64


@njit(cache=True, parallel=True)
def _distinct_per_row(cols, row_start, n_cols):
    n = len(row_start) - 1
    slots = np.zeros(n, np.int64)
    for ch in prange(_CHUNKS):
        mark = np.full(n_cols, -1, np.int64)
        for r in range(ch * n // _CHUNKS, (ch + 1) * n // _CHUNKS):
            k = 0
            for t in range(row_start[r], row_start[r + 1]):
                if mark[cols[t]] != r:
                    mark[cols[t]] = r
                    k += 1
            slots[r] = k
    return slots


@njit(cache=True, parallel=True)
def _slot_lists(cols, raw, row_start, indptr, n_cols):
    """CSR column indices (sorted per row), each slot's first position in src, and src: the
    raw entries grouped by slot, in block order within a slot."""
    n = len(row_start) - 1
    indices = np.empty(indptr[-1], np.int64)
    ptr = np.empty(indptr[-1], np.int64)
    src = np.empty(len(raw), np.int64)
    for ch in prange(_CHUNKS):
        mark = np.full(n_cols, -1, np.int64)
        local = np.zeros(n_cols, np.int64)
        for r in range(ch * n // _CHUNKS, (ch + 1) * n // _CHUNKS):
            a = indptr[r]
            k = 0
            for t in range(row_start[r], row_start[r + 1]):
                c = cols[t]
                if mark[c] != r:
                    mark[c] = r
                    indices[a + k] = c
                    k += 1
            for u in range(a + 1, a + k):         # insertion sort of the row's few columns
                v = indices[u]
                w = u - 1
                while w >= a and indices[w] > v:
                    indices[w + 1] = indices[w]
                    w -= 1
                indices[w + 1] = v
            for s in range(k):
                local[indices[a + s]] = 0
            for t in range(row_start[r], row_start[r + 1]):
                local[cols[t]] += 1
            p = row_start[r]
            for s in range(k):                    # slot starts; local becomes the fill position
                c = indices[a + s]
                ptr[a + s] = p
                cnt = local[c]
                local[c] = p
                p += cnt
            for t in range(row_start[r], row_start[r + 1]):
                c = cols[t]
                src[local[c]] = raw[t]
                local[c] += 1
    return indices, ptr, src


@njit(cache=True, parallel=True)
def _gather_sum(first, second, src, ptr):
    """out[s] = sum of the entries src[ptr[s]:ptr[s+1]] of the concatenation (first, second)."""
    n = len(ptr) - 1
    n0 = len(first)
    out = np.empty(n)
    for s in prange(n):
        v = 0.0
        for j in range(ptr[s], ptr[s + 1]):
            k = src[j]
            v += first[k] if k < n0 else second[k - n0]
        out[s] = v
    return out


def symmetric_matvec(U: sp.csr_matrix, x: np.ndarray) -> np.ndarray:
    """A x for the symmetric A whose upper triangle (with diagonal) is U."""
    return U @ x + U.T @ x - U.diagonal() * x


def scatter_vector(index_sets, values, n_dofs: int) -> np.ndarray:
    """Sum element vectors (k_i, d_i) into a global vector of length n_dofs."""
    out = np.zeros(n_dofs)
    for idx, v in zip(index_sets, values):
        out += np.bincount(idx.ravel(), weights=v.ravel(), minlength=n_dofs)
    return out


class PatternUnion:
    """The sum A + B of a fixed-pattern CSR matrix A (a BlockScatter's, over the free DOFs,
    upper triangle) and a CSR matrix B whose pattern changes between calls (the contact
    Hessian), on a pattern that only grows: the union of A's pattern and every B's seen so
    far, with read-only index arrays. The solver keeps its symbolic analysis while the pattern
    does not grow (shellfem.linalg.SparseSPD recognises it by identity), so a contact set that
    settles costs no re-analysis; entries of earlier contacts stay as explicit zeros."""

    def __init__(self):
        self._keys = None          # sorted row * n + col of the union
        self._base = None          # A's index arrays the union was built for
        self._pos_a = None
        self._indptr = self._indices = None

    @staticmethod
    def _csr_keys(M):
        rows = np.repeat(np.arange(M.shape[0], dtype=np.int64), np.diff(M.indptr))
        return rows * M.shape[1] + M.indices.astype(np.int64)

    def add(self, A: sp.csr_matrix, B: sp.csr_matrix | None) -> sp.csr_matrix:
        """A + B on the union pattern (A itself while B never had an entry)."""
        if self._keys is None and (B is None or B.nnz == 0):
            return A
        # the same read-only index arrays as last time (scipy wraps BlockScatter's arrays in
        # new views, so identity ``is`` never held: the union was rebuilt on every call, 0.2 s
        # each on the 2.5k-vertex dome, 38 % of its solve with the ground on)
        base_same = self._base is not None and same_frozen(self._base[0], A.indptr) and same_frozen(self._base[1], A.indices)
        if not base_same:
            self._keys = None
        kb = self._csr_keys(B) if B is not None and B.nnz else np.zeros(0, np.int64)
        if self._keys is None:
            self._keys = np.union1d(self._csr_keys(A), kb)
            self._grow(A)
        elif len(kb):
            pos = np.searchsorted(self._keys, kb)
            known = pos < len(self._keys)
            known[known] = self._keys[pos[known]] == kb[known]
            if not known.all():
                self._grow(A, np.unique(kb[~known]))
        data = np.zeros(len(self._keys))
        data[self._pos_a] = A.data
        if len(kb):
            data[np.searchsorted(self._keys, kb)] += B.data
        M = sp.csr_matrix((data, self._indices, self._indptr), shape=A.shape, copy=False)
        M.has_canonical_format = True
        return M

    def _grow(self, A, new=None):
        """Index arrays of the union: built from ``self._keys`` (new None), or the sorted keys
        ``new`` (absent from the union) merged into it by insertion, without sorting the
        union again (a rolling sheet adds contact entries on most iterations; re-sorting the
        whole union each time was a fifth of a 14k-vertex contact solve)."""
        n = A.shape[1]
        itype = np.int32 if max(len(self._keys) + (0 if new is None else len(new)), n) < 2 ** 31 - 1 else np.int64
        if new is None:
            keys = self._keys
            self._indices = (keys % n).astype(itype)
            self._indptr = np.searchsorted(keys // n, np.arange(A.shape[0] + 1)).astype(itype)
            self._pos_a = np.searchsorted(keys, self._csr_keys(A))
        else:
            at = np.searchsorted(self._keys, new)          # insertion points in the old union
            self._keys = np.insert(self._keys, at, new)
            self._indices = np.insert(self._indices, at, (new % n).astype(itype)).astype(itype, copy=False)
            self._indptr = (self._indptr + np.searchsorted(new // n, np.arange(A.shape[0] + 1))).astype(itype)
            self._pos_a = self._pos_a + np.searchsorted(at, self._pos_a, side="right")
        self._indices.flags.writeable = False
        self._indptr.flags.writeable = False
        self._base = (A.indptr, A.indices)      # read-only views of the scatter's arrays


def reduce_upper(M: sp.spmatrix, reduced: np.ndarray, n_free: int) -> sp.csr_matrix:
    """The upper triangle (row <= column) of M (over all DOFs; COO-convertible) restricted to
    the free DOFs, renumbered by ``reduced`` (BlockScatter.reduced: -1 for held DOFs)."""
    C = M.tocoo()
    r, c = reduced[C.row], reduced[C.col]
    keep = (r >= 0) & (c >= 0) & (r <= c)
    out = sp.csr_matrix((C.data[keep], (r[keep], c[keep])), shape=(n_free, n_free))
    out.sum_duplicates()
    return out
