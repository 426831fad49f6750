"""Sparse symmetric positive definite factorisation for the Newton solver and its relaxations.

:class:`SparseSPD` factorises A (or A + diag(shift)) with the fastest backend installed
(:func:`default_backend`: MKL PARDISO through shellfem.pardiso, else CHOLMOD from
scikit-sparse, else SciPy's SuperLU), raises :class:`NotPositiveDefinite` when A is not
positive definite (the solver's test of a stable state and its trigger for a larger
Levenberg-Marquardt shift), and keeps the symbolic analysis (fill-reducing ordering)
while the sparsity pattern stays the same, as it does over a Newton loop.
"""
from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from threadpoolctl import ThreadpoolController

from shellfem import pardiso

try:  # CHOLMOD: ~2x faster than SuperLU here and it reports non-definiteness (toolchain.md)
    # (PARDISO, shellfem.pardiso, is 5x faster again and is preferred when MKL is installed)
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze
    HAVE_CHOLMOD = True
except Exception:  # pragma: no cover - exercised on machines without scikit-sparse
    HAVE_CHOLMOD = False

    class CholmodNotPositiveDefiniteError(Exception):
        pass


class NotPositiveDefinite(Exception):
    """The matrix (with its shift) is not positive definite: a factorisation met a
    non-positive pivot."""


def default_backend() -> str:
    """The fastest sparse Cholesky here: MKL PARDISO (shellfem.pardiso; 5x CHOLMOD on the
    benchmark's Hessian), else CHOLMOD (scikit-sparse), else SciPy's SuperLU."""
    if pardiso.available():
        return "pardiso"
    return "cholmod" if HAVE_CHOLMOD else "superlu"


def same_frozen(a: np.ndarray, b: np.ndarray) -> bool:
    """a and b are read-only views of the same memory (so equal, now and later)."""
    return (not a.flags.writeable and not b.flags.writeable and a.shape == b.shape and a.dtype == b.dtype
            and a.ctypes.data == b.ctypes.data and a.strides == b.strides)


class SparseSPD:
    """Factorise SPD matrices; raise NotPositiveDefinite. The symbolic analysis (ordering) is
    kept while the sparsity pattern stays the same (as in a Newton loop).

    backend: "auto" (:func:`default_backend`), "pardiso", "cholmod" or "superlu"."""

    def __init__(self, backend: str = "auto"):
        self.backend = default_backend() if backend == "auto" else backend
        if self.backend not in ("pardiso", "cholmod", "superlu"):
            raise ValueError(f"unknown sparse solver backend {backend!r}")
        if self.backend == "pardiso" and not pardiso.available():
            raise ValueError("sparse solver backend 'pardiso' needs MKL (pip install mkl)")
        if self.backend == "cholmod" and not HAVE_CHOLMOD:
            raise ValueError("sparse solver backend 'cholmod' needs scikit-sparse")
        self._symbolic = None
        self._pattern = None

    def _same_pattern(self, A) -> bool:
        """True if A (CSR or CSC) has the pattern of the last analysis; else remember A's."""
        p = self._pattern
        if p is not None and p[0] == A.shape and same_frozen(p[1], A.indptr) and same_frozen(p[2], A.indices):
            return True           # the same read-only index arrays (BlockScatter's matrices)
        if (p is not None and p[0] == A.shape and len(p[2]) == len(A.indices) and np.array_equal(p[1], A.indptr)
                and np.array_equal(p[2], A.indices)):
            return True
        shared = not (A.indptr.flags.writeable or A.indices.flags.writeable)
        self._pattern = (A.shape, A.indptr if shared else A.indptr.copy(), A.indices if shared else A.indices.copy())
        return False

    def factor(self, A: sp.csr_matrix, shift=None, upper: bool = False):
        """A solve function for A + diag(shift) (shift: (n,) array, scalar or None). upper:
        A holds only the upper triangle of the symmetric matrix (BlockScatter(upper=True))."""
        if self.backend == "pardiso":     # reads the upper triangle either way
            A = A if isinstance(A, sp.csr_matrix) else sp.csr_matrix(A)
            if not A.has_canonical_format:
                A = A.copy()
                A.sum_duplicates()
            if not self._same_pattern(A):
                self._symbolic = pardiso.PardisoCholesky(A)
            try:
                self._symbolic.factor(A.data, shift)
            except pardiso.ZeroPivot as e:
                raise NotPositiveDefinite(str(e)) from None
            return self._symbolic.solve
        if upper:
            if self.backend == "cholmod":     # CHOLMOD reads the lower triangle of a CSC matrix
                A = sp.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)
            else:
                A = A + sp.triu(A, k=1, format="csr").T
        if shift is not None:
            A = A + sp.diags(np.broadcast_to(shift, A.shape[0]))
        A = A.tocsc()
        if self.backend == "cholmod":
            if not self._same_pattern(A):
                self._symbolic = analyze(A, mode="supernodal", ordering_method="metis")
            try:
                f = self._symbolic.cholesky(A)
            except CholmodNotPositiveDefiniteError as e:
                raise NotPositiveDefinite(str(e)) from None
            return f
        # SuperLU has no definiteness test: check the pivots' signs via the diagonal of U
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
        d = lu.U.diagonal()
        if np.any(d <= 0) or not np.all(np.isfinite(d)):
            raise NotPositiveDefinite("non-positive pivot")
        return lu.solve


def one_openblas_thread(fn):
    """``fn`` run with every loaded OpenBLAS (numpy's, scipy's, CHOLMOD's) on one thread.

    OpenBLAS threads busy-wait after the many small batched products of the assembly and take
    the second core from the compiled kernels and PARDISO, and their round-off depends on the
    thread count (the refinement's lowest mode and Gauss-Newton matrix differed in their last
    digits between one and two OpenBLAS threads on the 110 mm saddle); MKL (PARDISO) keeps its
    threads, and its results do not depend on their count. The libraries are looked up at each
    call (a solver backend may load its BLAS after import); the counts are restored on return."""
    @functools.wraps(fn)
    def limited(*args, **kwargs):
        with ThreadpoolController().select(internal_api="openblas").limit(limits=1):
            return fn(*args, **kwargs)
    return limited
