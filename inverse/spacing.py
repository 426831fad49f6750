"""Ribbon spacing <-> homogenised stretch of a staggered dashed-ribbon pattern (seed Eq. 5.15).

A motif of length mu1 (one dash of length l_r plus a gap) contracts on release to
l_r + (mu1 - l_r) / s, so its stretch is sigma1 = mu1 / (l_r + (mu1 - l_r) / s); likewise across
the ribbons with the width w_r and spacing mu2. Inverting gives Eq. 5.15:

    mu1 = l_r (s - 1) sigma1 / (s - sigma1),    mu2 = w_r (s - 1) sigma2 / (s - sigma2).

All lengths in mm (printed, pre-stretched state); stretches are dimensionless.
"""
from __future__ import annotations

import numpy as np

from shellfem.errors import SelfshapeError


def _check_pattern(s: float, ribbon_length: float, ribbon_width: float, where: str) -> float:
    s = float(s)
    if not np.isfinite(s) or s <= 1.0:
        raise SelfshapeError(f"{where}: fabric pre-stretch s = {s} must be a finite number > 1")
    for name, val in (("ribbon_length", ribbon_length), ("ribbon_width", ribbon_width)):
        if not np.isfinite(val) or val <= 0.0:
            raise SelfshapeError(f"{where}: {name} = {val} mm must be a finite number > 0")
    return s


def _first_bad(name: str, mask: np.ndarray) -> str:
    """``name[i]`` for the first True entry of ``mask`` (``name`` alone for scalars)."""
    idx = np.argwhere(mask)[0]
    if len(idx) == 0:
        return name
    return f"{name}[{int(idx[0])}]" if len(idx) == 1 else f"{name}{list(int(i) for i in idx)}"


def _check_stretch(sigma: np.ndarray, s: float, name: str, where: str) -> None:
    bad = ~np.isfinite(sigma)
    if bad.any():
        raise SelfshapeError(f"{where}: {_first_bad(name, bad)} is not a finite number")
    bad = sigma >= s
    if bad.any():
        raise SelfshapeError(
            f"{where}: {_first_bad(name, bad)} = {sigma[bad][0]:.6g} >= pre-stretch s = {s:.6g} is impossible "
            f"(the fabric cannot end up more stretched than it was printed; spacing would be infinite)")
    bad = sigma < 1.0
    if bad.any():
        raise SelfshapeError(
            f"{where}: {_first_bad(name, bad)} = {sigma[bad][0]:.6g} < 1 is impossible "
            f"(the ribbons would have to overlap; the pattern cannot expand the fabric)")


def ribbon_spacing(sigma1, sigma2, s: float, ribbon_length: float = 15.0,
                   ribbon_width: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5.15: centre-to-centre spacing (mu1 along, mu2 across the ribbons, mm) that makes the
    pattern deploy with stretch (sigma1, sigma2) on fabric pre-stretched by s.

    sigma1, sigma2: arrays (broadcastable) with 1 <= sigma < s. ribbon_length l_r and
    ribbon_width w_r in mm. sigma = 1 gives mu = l_r (dashes touching) / w_r (ribbons touching).
    """
    where = "ribbon_spacing"
    s = _check_pattern(s, ribbon_length, ribbon_width, where)
    sigma1 = np.asarray(sigma1, dtype=float)
    sigma2 = np.asarray(sigma2, dtype=float)
    _check_stretch(sigma1, s, "sigma1", where)
    _check_stretch(sigma2, s, "sigma2", where)
    mu1 = ribbon_length * (s - 1.0) * sigma1 / (s - sigma1)
    mu2 = ribbon_width * (s - 1.0) * sigma2 / (s - sigma2)
    return mu1, mu2


def stretch_from_spacing(mu1, mu2, s: float, ribbon_length: float = 15.0,
                         ribbon_width: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of Eq. 5.15: deployed stretch (sigma1, sigma2) of a pattern with spacing
    mu1 >= l_r (along) and mu2 >= w_r (across), in mm, on fabric pre-stretched by s.
    sigma = mu s / (l (s - 1) + mu), which tends to s for very sparse patterns."""
    where = "stretch_from_spacing"
    s = _check_pattern(s, ribbon_length, ribbon_width, where)
    out = []
    for name, mu, length in (("mu1", mu1, ribbon_length), ("mu2", mu2, ribbon_width)):
        mu = np.asarray(mu, dtype=float)
        bad = ~np.isfinite(mu)
        if bad.any():
            raise SelfshapeError(f"{where}: {_first_bad(name, bad)} is not a finite number")
        bad = mu < length
        if bad.any():
            raise SelfshapeError(
                f"{where}: {_first_bad(name, bad)} = {mu[bad][0]:.6g} mm is smaller than the ribbon "
                f"{'length' if name == 'mu1' else 'width'} {length:.6g} mm (ribbons would overlap)")
        out.append(mu * s / (length * (s - 1.0) + mu))
    return out[0], out[1]
