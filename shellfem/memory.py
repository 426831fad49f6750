"""Process-level memory tuning for the solver's large per-element temporaries.

A Newton iteration on a 10k-vertex sheet allocates and frees tens of arrays of 10-100 MB
(per-triangle Hessian blocks, CHOLMOD factors). glibc serves each from a fresh mmap and
returns it on free, so every iteration page-faults ~150k pages back in: measured on the
85 x 60 mm star benchmark, 0.6 s of kernel time per iteration (1.19M minor faults in 8
iterations). Keeping large blocks on the heap removes that (31k faults, -4.9 s system
time over the same 8 iterations) at the price of a higher resident size (918 -> 1116 MB).
"""
from __future__ import annotations

_DONE = False


def keep_freed_memory(trim_threshold_bytes: int = 1 << 30, top_pad_bytes: int = 64 << 20) -> bool:
    """Tell glibc malloc to serve large allocations from the heap (no mmap) and to keep up
    to ``trim_threshold_bytes`` of freed memory for reuse. Affects the whole process; call it
    once from an application (the ``selfshape`` command and the validation scripts do).
    Returns False (and changes nothing) where the C library is not glibc."""
    global _DONE
    if _DONE:
        return True
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4
        ok = (libc.mallopt(M_MMAP_MAX, 0) == 1 and libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold_bytes)) == 1
              and libc.mallopt(M_TOP_PAD, int(top_pad_bytes)) == 1)
    except (OSError, AttributeError):
        return False
    _DONE = bool(ok)
    return _DONE
