"""Sparse Cholesky with Intel MKL PARDISO: a thin ctypes binding to ``mkl_rt``.

Why (measured on a 63,634-unknown Hessian of the 85 x 60 mm benchmark sheet, 13.8M entries in
the factor, same fill as CHOLMOD's METIS ordering): numerical factorisation 0.22 s on one thread
and 0.12 s on two, against 1.14 s / 0.62 s for CHOLMOD's supernodal LL^T with OpenBLAS; a
failed (indefinite) attempt costs the same 0.22 s against CHOLMOD's 1.31 s. The symbolic
analysis (ordering) is done once per sparsity pattern (0.58 s there).

The MKL runtime comes from PyPI's ``mkl`` wheel (x86-64 only); :func:`available` says whether
it loaded. pypardiso wraps the same routine but re-analyses the pattern at every
factorisation through its public API, which doubles the cost here.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import site
import sys

import numpy as np
import scipy.sparse as sp

_LIB = None
_LOAD_ERROR = None



def _load():
    global _LIB, _LOAD_ERROR
    if _LIB is not None or _LOAD_ERROR is not None:
        return _LIB
    paths = []
    if os.environ.get("SELFSHAPE_MKL_RT"):
        paths.append(os.environ["SELFSHAPE_MKL_RT"])
    prefixes = [sys.prefix, sys.base_prefix]
    try:
        prefixes.append(site.getuserbase())
    except Exception:  # pragma: no cover
        pass
    for prefix in dict.fromkeys(prefixes):
        paths += sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")), key=len)
    found = ctypes.util.find_library("mkl_rt")
    if found:
        paths.append(found)
    # conditional numerical reproducibility (read when MKL initialises): MKL's default varied
    # between runs on 2 threads; CNR mode (AUTO: one code path per CPU, fixed reduction order
    # for a fixed thread count) is run-to-run bitwise repeatable (85 x 60 benchmark: the same
    # iterate bits in 3 of 3 runs, equal to STRICT's) and its factorisation 0.127 s against
    # STRICT's 0.146 s on that Hessian
    os.environ.setdefault("MKL_CBWR", "AUTO")
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
            fn = lib.pardiso
        except (OSError, AttributeError):
            continue
        i32p, vp = ctypes.POINTER(ctypes.c_int32), ctypes.c_void_p
        fn.restype = None
        # pardiso(pt, maxfct, mnum, mtype, phase, n, a, ia, ja, perm, nrhs, iparm, msglvl, b, x, error)
        fn.argtypes = [vp, i32p, i32p, i32p, i32p, i32p, vp, vp, vp, vp, i32p, vp, i32p, vp, vp, i32p]
        _LIB = lib
        return lib
    _LOAD_ERROR = "libmkl_rt not found (pip install mkl)"
    return None


def available() -> bool:
    """True if MKL's PARDISO could be loaded."""
    return _load() is not None


class PardisoError(RuntimeError):
    pass


class ZeroPivot(Exception):
    """The matrix is not positive definite (PARDISO error -4 in Cholesky mode)."""


_MESSAGES = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
             -4: "zero or negative pivot", -5: "unclassified internal error", -6: "reordering failed",
             -7: "diagonal matrix is singular", -8: "32-bit integer overflow", -9: "not enough memory for OOC",
             -10: "error opening OOC files", -11: "read/write error with OOC files"}


class PardisoCholesky:
    """Cholesky factorisations (mtype 2, real SPD) of matrices sharing the sparsity pattern of
    ``A`` (a symmetric CSR matrix given in full). The pattern must hold the whole diagonal.

    factor(data, shift) factorises the matrix with A's pattern and values ``data`` (in A's CSR
    order) plus ``diag(shift)``; raises ZeroPivot if it is not positive definite. solve(b)
    solves with the last successful factorisation. One factorisation is held at a time."""

    def __init__(self, A: sp.csr_matrix):
        lib = _load()
        if lib is None:
            raise PardisoError(_LOAD_ERROR)
        A = sp.csr_matrix(A)
        if not A.has_canonical_format:
            raise ValueError("PARDISO: the matrix must be in canonical CSR form (sorted, no duplicates)")
        n = A.shape[0]
        self.n = n
        rows = np.repeat(np.arange(n), np.diff(A.indptr))
        self._upper = A.indices >= rows
        self._all_upper = bool(self._upper.all())
        ur = rows[self._upper]
        self._ia = np.concatenate([[0], np.cumsum(np.bincount(ur, minlength=n))]).astype(np.int32)
        self._ja = np.ascontiguousarray(A.indices[self._upper], dtype=np.int32)
        self._diag = self._ia[:-1].astype(np.int64)
        if n and (np.any(np.diff(self._ia) == 0) or np.any(self._ja[self._diag] != np.arange(n))):
            raise ValueError("PARDISO: the sparsity pattern must contain the whole diagonal")
        self._pt = np.zeros(64, np.int64)
        self._iparm = np.zeros(64, np.int32)
        ip = self._iparm
        ip[0] = 1       # parameters given here
        ip[1] = 2       # nested dissection (METIS)
        ip[7] = 0       # no iterative refinement (no pivot perturbation in Cholesky mode)
        ip[9] = 13      # perturbation threshold 1e-13 (used by the indefinite modes only)
        ip[17] = -1     # report the factor's nonzeros
        ip[34] = 1      # zero-based indices
        self._factored = False
        self._alive = False
        self._a = np.zeros(len(self._ja))
        self._call(11, self._a, np.zeros(1), np.zeros(1), nrhs=1)     # symbolic analysis
        self._alive = True
        self.factor_nonzeros = int(ip[17])

    def _call(self, phase, a, b, x, nrhs=1):
        err = ctypes.c_int32(0)
        i32 = ctypes.c_int32
        # maxfct = mnum = 1 (one factor held), mtype 2 (real SPD), msglvl 0
        _LIB.pardiso(self._pt.ctypes.data, ctypes.byref(i32(1)), ctypes.byref(i32(1)), ctypes.byref(i32(2)),
                     ctypes.byref(i32(phase)), ctypes.byref(i32(self.n)), a.ctypes.data,
                     self._ia.ctypes.data, self._ja.ctypes.data, None, ctypes.byref(i32(nrhs)),
                     self._iparm.ctypes.data, ctypes.byref(i32(0)), b.ctypes.data, x.ctypes.data,
                     ctypes.byref(err))
        return err.value

    def factor(self, data: np.ndarray, shift: np.ndarray | float | None = None):
        a = np.array(data, dtype=np.float64) if self._all_upper else np.ascontiguousarray(data[self._upper],
                                                                                         dtype=np.float64)
        if shift is not None:
            a[self._diag] += shift
        self._a = a
        self._factored = False
        err = self._call(22, a, np.zeros(1), np.zeros(1))
        if err == -4:
            raise ZeroPivot("matrix is not positive definite")
        if err:
            raise PardisoError(f"PARDISO factorisation failed: {_MESSAGES.get(err, err)}")
        self._factored = True

    def solve(self, b: np.ndarray) -> np.ndarray:
        """x with (A + diag(shift)) x = b for one right-hand side b (n,) or several, the columns
        of b (n, k), in one call (PARDISO's multiple right-hand sides: the factor is read once
        for all of them)."""
        if not self._factored:
            raise PardisoError("PARDISO: solve without a successful factorisation")
        b = np.asarray(b, dtype=np.float64)
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise ValueError(f"PARDISO: right-hand side of shape {b.shape}, expected ({self.n},) or ({self.n}, k)")
        if b.ndim == 2 and b.shape[1] == 0:
            return np.zeros_like(b)
        b = np.asfortranarray(b)                  # PARDISO reads the right-hand sides column after column
        x = np.zeros_like(b, order="F")
        err = self._call(33, self._a, b, x, nrhs=1 if b.ndim == 1 else b.shape[1])
        if err:
            raise PardisoError(f"PARDISO solve failed: {_MESSAGES.get(err, err)}")
        return x

    def __del__(self):
        if getattr(self, "_alive", False) and _LIB is not None:
            try:
                self._call(-1, self._a, np.zeros(1), np.zeros(1))
            except Exception:  # pragma: no cover - interpreter shutdown
                pass
