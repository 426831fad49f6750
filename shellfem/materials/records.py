"""Material parameters of the fabric and the printed plastic (mm, N, MPa).

Plain records with validation; the fabric's membrane energies are the models of
shellfem.materials (the registry), the layered energies are in shellfem.layers.
Defaults are the seed's Table 4.1 (spandex + TPU95A).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from shellfem.errors import SelfshapeError, check_number
from shellfem.materials.base import MEMBRANE_MODELS, membrane_model


def _check(name: str, value, lo=None, hi=None, lo_open=False):
    return check_number(name, value, lo=lo, hi=hi, lo_open=lo_open)


@dataclass
class Fabric:
    """Pre-stretched fabric.

    stretch: (sx, sy) pre-stretch factors along printed x and y (>= 1); the fabric's
        rest (unstretched) metric is diag(1/sx^2, 1/sy^2) in printed coordinates.
    thickness: mm. model: the bare fabric's membrane model, a name in
        shellfem.materials.MEMBRANE_MODELS ("neo-hookean", "orthotropic", ...).
    young_modulus: MPa, the neo-Hookean modulus and the fabric layer's modulus E2
        inside printed bilayers (the seed's pseudo-Young modulus at release).
    poisson: fabric Poisson's ratio. bending_stiffness: k_B, N mm (moment per width
        per unit curvature). course_angle_deg: course direction from +x.
    areal_weight: N/mm^2 of relaxed fabric; > 0 adds gravity along -z.
    parameters: {model name: {parameter: value}}, the membrane models' own parameters
        (pattern tables [fabric.<name>]); every registered model's table is filled with
        its defaults and validated against its schema, whichever model is in use.
    """
    stretch: tuple = (1.35, 1.35)
    thickness: float = 0.8
    model: str = "neo-hookean"
    young_modulus: float = 1.05
    poisson: float = 0.3
    bending_stiffness: float = 0.0192
    course_angle_deg: float = 0.0
    areal_weight: float = 0.0
    parameters: dict = field(default_factory=dict)

    def __post_init__(self):
        s = self.stretch
        if isinstance(s, (int, float)):
            s = (s, s)
        try:
            s = tuple(s)
        except TypeError:
            raise SelfshapeError(f"fabric.stretch must be a number or [sx, sy], got {self.stretch!r}") from None
        if len(s) != 2:
            raise SelfshapeError(f"fabric.stretch must be a number or [sx, sy], got {self.stretch!r}")
        self.stretch = (_check("fabric.stretch[0]", s[0], 1.0), _check("fabric.stretch[1]", s[1], 1.0))
        self.thickness = _check("fabric.thickness_mm", self.thickness, 0.0, lo_open=True)
        self.young_modulus = _check("fabric.young_modulus_mpa", self.young_modulus, 0.0, lo_open=True)
        self.poisson = _check("fabric.poisson", self.poisson, -0.99, 0.499)
        self.bending_stiffness = _check("fabric.bending_stiffness_nmm", self.bending_stiffness, 0.0)
        self.course_angle_deg = _check("fabric.course_angle_deg", self.course_angle_deg)
        self.areal_weight = _check("fabric.areal_weight_n_per_mm2", self.areal_weight, 0.0)
        model = membrane_model(self.model)
        given = dict(self.parameters or {})
        unknown = [k for k in given if k not in MEMBRANE_MODELS]
        if unknown:
            raise SelfshapeError(f"fabric.parameters: unknown membrane model(s) {sorted(unknown)}")
        self.parameters = {name: m.validated(given.get(name)) for name, m in MEMBRANE_MODELS.items()}
        model.check(self)

    @property
    def model_parameters(self) -> dict:
        """The parameters of the membrane model in use."""
        return self.parameters[self.model]


@dataclass
class Plastic:
    """Printed plastic (TPU95A by default).

    young_modulus: MPa. poisson: Poisson's ratio (the seed uses 0.5 for TPU; values
    up to 0.5 are accepted). rest_curvature: 1/mm, the plastic set (seed Fig. 3.4,
    Eq. 3.4-3.9): the curvature of the plastic alone after peeling, with the same sign
    as the bilayer bend (towards the fabric side).
    """
    young_modulus: float = 72.3
    poisson: float = 0.5
    rest_curvature: float = 0.0

    def __post_init__(self):
        self.young_modulus = _check("plastic.young_modulus_mpa", self.young_modulus, 0.0, lo_open=True)
        self.poisson = _check("plastic.poisson", self.poisson, -0.99, 0.5)
        self.rest_curvature = _check("plastic.rest_curvature_per_mm", self.rest_curvature)
