"""The interface of a fabric membrane model, and the registry of the models.

A membrane model is the bare fabric's in-plane energy as a function of the first fundamental
form a alone (libshell's MaterialModel is the example): it knows nothing of meshes, patterns
or solvers. It declares

- ``name``: the value of ``[fabric] model`` in a pattern and of ``Fabric.model``;
- ``parameters``: its schema, a tuple of :class:`Parameter` (name, default, bounds, unit);
  a pattern's ``[fabric.<name>]`` table and ``Fabric.parameters[<name>]`` are validated
  against it (unknown keys and out-of-bounds values are one-line SelfshapeErrors naming
  ``fabric.<name>.<key>``);
- ``__init__(rest, fabric)``: per-face set-up from the rest state (:class:`RestState`) and
  the Fabric record (thickness, Poisson's ratio, course angle, its parameters);
- ``energy(a) -> (W (m,), dW/da (m, 3), d2W/da2 (m, 3, 3))``, N mm, with W = +inf outside
  the model's admissible set (inverted triangles, a strain barrier);
- optionally ``check(fabric)``: constraints across parameters and the rest of the record.

A model becomes available by listing its class in shellfem/materials/__init__.py.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from shellfem.errors import SelfshapeError, check_number
from shellfem.layers import SYM_BASIS


@dataclass(frozen=True)
class Parameter:
    """One model parameter: key in ``[fabric.<model>]``, default, bounds (lo exclusive when
    lo_open), unit and meaning."""
    name: str
    default: float
    unit: str
    doc: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False


@dataclass(frozen=True)
class RestState:
    """The bare fabric's triangles at rest (relaxed, unstretched fabric), printed axes.

    points: (m, 3, 2) corner positions, mm; metric: (m, 3) edge-basis metric abar, mm^2;
    area: (m,) rest areas, mm^2."""
    points: np.ndarray
    metric: np.ndarray
    area: np.ndarray


class MembraneModel:
    """Base class of the fabric membrane models (see the module docstring)."""
    name: ClassVar[str] = ""
    parameters: ClassVar[tuple[Parameter, ...]] = ()

    def __init__(self, rest: RestState, fabric):
        raise NotImplementedError

    def energy(self, a: np.ndarray):
        raise NotImplementedError

    @classmethod
    def check(cls, fabric) -> None:
        """Constraints beyond each parameter's bounds (nothing by default)."""

    @classmethod
    def defaults(cls) -> dict:
        return {p.name: p.default for p in cls.parameters}

    @classmethod
    def validated(cls, values: dict | None) -> dict:
        """The model's parameters: ``values`` over the defaults, each checked against its
        bounds (SelfshapeError naming fabric.<name>.<key>)."""
        out = cls.defaults()
        out.update(values or {})
        unknown = set(out) - {p.name for p in cls.parameters}
        if unknown:
            raise SelfshapeError(f"fabric.{cls.name}: unknown parameter(s) {sorted(unknown)}")
        for p in cls.parameters:
            out[p.name] = check_number(f"fabric.{cls.name}.{p.name}", out[p.name], lo=p.lo, hi=p.hi,
                                       lo_open=p.lo_open)
        return out


#: The registry: model name -> MembraneModel subclass (filled by shellfem.materials).
MEMBRANE_MODELS: dict[str, type[MembraneModel]] = {}


def register(model: type[MembraneModel]) -> type[MembraneModel]:
    """Make ``model`` available under ``model.name`` (pattern files, Fabric, ShellModel)."""
    if not model.name or model.name in MEMBRANE_MODELS:
        raise ValueError(f"membrane model name {model.name!r} is empty or taken")
    MEMBRANE_MODELS[model.name] = model
    return model


def membrane_model(name: str) -> type[MembraneModel]:
    """The registered model called ``name`` (one-line SelfshapeError listing the names otherwise)."""
    try:
        return MEMBRANE_MODELS[name]
    except (KeyError, TypeError):
        names = ", ".join(f'"{n}"' for n in MEMBRANE_MODELS)
        raise SelfshapeError(f"fabric.model must be one of {names}, got {name!r}") from None


def strain_map(rest_edges: np.ndarray):
    """Affine map a -> Voigt Green strain (e11, e22, 2 e12): eps = T a + (-1/2, -1/2, 0).

    rest_edges: (m, 2, 2) columns = rest edge vectors E1, E2 in the material frame (mm)."""
    Rinv = np.linalg.inv(rest_edges)
    G = np.einsum("mji,kjl,mln->mkin", Rinv, SYM_BASIS, Rinv)   # R^-T B_k R^-1
    T = np.stack([0.5 * G[:, :, 0, 0], 0.5 * G[:, :, 1, 1], G[:, :, 0, 1]], 1)
    return T


def course_strain_map(rest: RestState, course_angle_deg: float) -> np.ndarray:
    """T (m, 3, 3) of :func:`strain_map` in the course frame (axis 1 along the course
    direction, course_angle_deg from the printed +x axis): the Green strain of orthotropic
    models."""
    c, s = np.cos(np.radians(course_angle_deg)), np.sin(np.radians(course_angle_deg))
    Rot = np.array([[c, s], [-s, c]])                # printed frame -> course frame
    P = rest.points
    edges = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], 2)   # columns E1, E2
    return strain_map(np.einsum("ij,mjk->mik", Rot, edges))
