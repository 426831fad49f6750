"""Uniform-state bilayer curvature: the engine's own energy, reduced to a fully printed strip.

A strip fully covered by plastic deforms (away from its ends) into a uniform state:
constant first and second fundamental forms. The layered energy of
:mod:`shellfem.layers` (exact Kirchhoff-Love metric) is quadratic in (a, b) apart from the
third fundamental form, so the uniform equilibrium is one small linear solve per strip
(the truncated metric's minimiser) followed by a few Newton steps with the exact Hessian,
vectorised over any number of strips. tests/test_strip.py checks
that the full finite-element simulation of a strip reproduces these values, so the
calibration and validation code may use them as "the project's own model".

Units: thickness mm, curvature 1/mm. Only the ratio E_plastic / E_fabric matters.
"""
from __future__ import annotations

import numpy as np

from shellfem.layers import QuadraticForm, layer_form

#: Strips solved at once: the layer forms hold a few (n, 6, 6) arrays, so 65,536 strips take
#: ~20 MB each; a calibration of 100,000 rows (71 ratios each) asked for 1.9 GB at once.
CHUNK = 65_536


def strip_state(plastic_thickness, fabric_thickness, stretch, modulus_ratio, *, plastic_poisson=0.5,
                fabric_poisson=0.3, rest_curvature=0.0, mode="narrow", exact_metric=True):
    """Uniform equilibrium (a11, a12, a22, b11, b12, b22) in printed Cartesian coordinates
    of a strip with plastic on the front (+z); arrays broadcast together.

    mode "narrow": no constraint (a narrow strip: transverse stress free, anticlastic
    freedom); "plate": transverse curvature b22 = 0 (a wide sheet rolling into a cylinder
    about y). The layers carry the exact Kirchhoff-Love metric (shellfem.layers); exact_metric=False:
    the truncated metric a - 2 z b, O(kappa h) off."""
    if mode not in ("narrow", "plate"):
        raise ValueError(f"mode must be 'narrow' or 'plate', got {mode!r}")
    arrays = np.broadcast_arrays(*(np.asarray(v, float) for v in (
        plastic_thickness, fabric_thickness, stretch, modulus_ratio, plastic_poisson, fabric_poisson,
        rest_curvature)))
    shape = arrays[0].shape
    flat = [v.ravel() for v in arrays]
    n = flat[0].size
    z = np.empty((n, 6))
    for a in range(0, n, CHUNK):     # bounded memory: the layer forms hold (n, 6, 6) arrays
        z[a:a + CHUNK] = _uniform_states(*(v[a:a + CHUNK] for v in flat), mode, exact_metric)
    return z.reshape(shape + (6,))


def _uniform_states(hp, hf, s, ratio, nup, nuf, kap, mode, exact_metric):
    """strip_state of 1-D arrays of one length: (n, 6)."""
    n = hp.size
    eye = np.tile([1.0, 0.0, 1.0], (n, 1))
    quad = QuadraticForm(n)
    # energies per unit printed area; each layer is integrated over its own rest area
    # (seed Eq. 3.9: sqrt(det a_r) dx dy), which for the fabric is 1/s^2 of the printed one
    quad.add(*layer_form(eye / (s * s)[:, None], np.zeros((n, 3)), 1.0, nuf, -hf / 2, hf / 2, area=1.0 / (s * s),
                         exact_metric=exact_metric))
    quad.add(*layer_form(eye, -kap[:, None] * eye, ratio, nup, hf / 2, hf / 2 + hp, area=np.ones(n),
                         exact_metric=exact_metric))
    return quad.minimiser() if mode == "narrow" else quad.minimiser(keep=[0, 1, 2, 3, 4])


def strip_curvature(plastic_thickness, fabric_thickness, stretch, modulus_ratio, *, plastic_poisson=0.5,
                    fabric_poisson=0.3, rest_curvature=0.0, mode="narrow", exact_metric=True):
    """Curvature (1/mm) of a released bilayer strip, > 0 when concave on the fabric side.

    plastic_thickness, fabric_thickness: mm; stretch: isotropic pre-stretch s >= 1;
    modulus_ratio: E_plastic / E_fabric; rest_curvature: plastic set (1/mm, same sign as
    the bilayer bend). Arrays broadcast. The curvature is b11 / a11 of the uniform state
    (normal curvature per unit deformed length along the strip)."""
    z = strip_state(plastic_thickness, fabric_thickness, stretch, modulus_ratio, plastic_poisson=plastic_poisson,
                    fabric_poisson=fabric_poisson, rest_curvature=rest_curvature, mode=mode,
                    exact_metric=exact_metric)
    return -z[..., 3] / z[..., 0]


def timoshenko_curvature(plastic_thickness, fabric_thickness, modulus_ratio, misfit):
    """Timoshenko (1925) bilayer curvature (1/mm) for a small misfit strain (beam theory):
    kappa = 6 eps (1 + m)^2 / (h (3 (1 + m)^2 + (1 + m n)(m^2 + 1/(m n)))),
    m = h1/h2, n = E1/E2, h = h1 + h2 (layer 1 = plastic)."""
    h1, h2 = np.asarray(plastic_thickness, float), np.asarray(fabric_thickness, float)
    m, n = h1 / h2, np.asarray(modulus_ratio, float)
    return 6 * misfit * (1 + m) ** 2 / ((h1 + h2) * (3 * (1 + m) ** 2 + (1 + m * n) * (m * m + 1 / (m * n))))
