"""The one exception type users see: a problem with their input, said in one line."""


class SelfshapeError(ValueError):
    """Bad input or an impossible request. ``str(err)`` is a one-line message that
    names the problem and where it is (file, entry, index)."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def check_number(name: str, value, lo=None, hi=None, lo_open: bool = False) -> float:
    """``value`` as a finite float within [lo, hi] (or (lo, hi] with lo_open), else a
    SelfshapeError that names ``name``."""
    import math
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SelfshapeError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise SelfshapeError(f"{name} must be finite, got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise SelfshapeError(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise SelfshapeError(f"{name} must be <= {hi:g}, got {v:g}")
    return v
