"""Isotropic compressible neo-Hookean fabric membrane (seed Eq. 3.2).

    W = h A_rest / 2 [mu (I1 - 2 - 2 ln J) + lambda (ln J)^2],
    I1 = tr(abar^-1 a), J^2 = det a / det abar, lambda = E nu / (1 - nu^2), mu = E / (2 (1 + nu))

with E = Fabric.young_modulus (MPa), nu = Fabric.poisson, h = Fabric.thickness (mm): no
parameters of its own. W = +inf where a triangle is inverted or degenerate (det a <= 0).
"""
from __future__ import annotations

import numpy as np

from shellfem.layers import rest_area
from shellfem.materials.base import MembraneModel, RestState

_DET_HESS = np.array([[0.0, 0.0, 1.0], [0.0, -2.0, 0.0], [1.0, 0.0, 0.0]])


def neo_hookean(a, abar, E, nu, h, area=None):
    """Seed Eq. 3.2 per triangle; returns W (m,), dW/da (m,3), d2W/da2 (m,3,3).
    W = +inf where the triangle is inverted or degenerate (det a <= 0)."""
    A = rest_area(abar) if area is None else area
    lam, mu = E * nu / (1 - nu ** 2), E / (2 * (1 + nu))
    D = a[:, 0] * a[:, 2] - a[:, 1] ** 2
    Dbar = abar[:, 0] * abar[:, 2] - abar[:, 1] ** 2
    t = np.stack([abar[:, 2], -2 * abar[:, 1], abar[:, 0]], 1) / Dbar[:, None]    # tr(abar^-1 a) = t . a
    bad = D <= 0
    Ds = np.where(bad, 1.0, D)
    lnD = np.log(Ds) - np.log(Dbar)
    I1 = np.einsum("mi,mi->m", t, a)
    c = h * A / 2
    W = c * (mu * (I1 - 2 - lnD) + lam / 4 * lnD ** 2)
    gD = np.stack([a[:, 2], -2 * a[:, 1], a[:, 0]], 1)
    glnD = gD / Ds[:, None]
    HlnD = _DET_HESS[None] / Ds[:, None, None] - glnD[:, :, None] * glnD[:, None, :]
    g = c[:, None] * (mu * (t - glnD) + lam / 2 * lnD[:, None] * glnD)
    H = c[:, None, None] * (-mu * HlnD + lam / 2 * glnD[:, :, None] * glnD[:, None, :]
                            + lam / 2 * lnD[:, None, None] * HlnD)
    W = np.where(bad, np.inf, W)
    return W, g, H


class NeoHookean(MembraneModel):
    """The fabric's isotropic law at its young_modulus and poisson (the default model)."""
    name = "neo-hookean"

    def __init__(self, rest: RestState, fabric):
        self.abar, self.area = rest.metric, rest.area
        self.E, self.nu, self.h = fabric.young_modulus, fabric.poisson, fabric.thickness

    def energy(self, a):
        return neo_hookean(a, self.abar, self.E, self.nu, self.h, self.area)
