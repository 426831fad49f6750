"""Catalogue of candidate effects the bilayer-strip base model may lack, and the
composite model (base + chosen effects) that the validation loop fits.

Base model (step 1 of the validation loop, validation.loop): the project's bilayer model
(:func:`validation.strips.strip_model`, narrow strip) with the plastic flat at rest,
one parameter: the modulus ratio E_plastic / E_fabric.

Each effect is a physical extension with few parameters. An effect acts either on
the model's inputs (stage "inputs": thicknesses, stretch, modulus ratio, plastic
rest curvature, per row) or on its output curvature (stage "output", applied in
``order``). ``apply(rows, params, state)`` returns the modified state; ``prepare``
may compute auxiliary data from the training rows (stored in model.json).
Units: mm, 1/mm, MPa ratios; angles in degrees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from validation.strips import MEASURED, REST, strip_model

REFERENCE_STRETCH = 1.35  # seed section 3.3: the stretch used in all prints
REFERENCE_THICKNESS = 0.4  # mm, centre of the seed's 0.3-0.45 mm strip range


@dataclass(frozen=True)
class Effect:
    """A candidate effect: name, parameter names, initial values, bounds (natural
    units), which parameters are optimised in log space, the stage it acts on, the
    covariates that must vary in the data for it to be identifiable, and alternative
    starting values the loop also tries (validation.loop.fit_best)."""
    name: str
    params: tuple = ()
    init: tuple = ()
    bounds: tuple = ()
    log: tuple = ()
    stage: str = "inputs"
    order: int = 0
    varies: tuple = ()
    starts: tuple = ()  # alternative initial values (tuples like init) for multi-start fits

    def applicable(self, rows):
        """(True, "") or (False, reason) for these rows."""
        for c in self.varies:
            v = _covariate(rows, c)
            if np.unique(np.round(v, 12)).size < 2:
                return False, f"not identifiable: {c} does not vary in the data"
        return True, ""

    def prepare(self, rows) -> dict:
        return {}

    def apply(self, rows, p, state, aux):  # pragma: no cover - abstract
        raise NotImplementedError


class _BackFaceEffect(Effect):
    """Effects on the back face: need back rows; with back rows only they equal a
    global change and compete with it (reported as indistinguishable)."""

    def applicable(self, rows):
        if not np.any(rows["side"] == "back"):
            return False, "not identifiable: no strip printed on the back face"
        return True, ""


def _covariate(rows, name):
    if name == "side":
        return (rows["side"] == "back").astype(float)
    if name == "cos2theta":
        return np.cos(np.radians(2 * rows["orientation_deg"]))
    return np.asarray(rows[name], float)


class PlasticSetMeasured(Effect):
    """Plastic set (seed section 3.2.3, Fig. 3.4; Eq. 3.17's kappa-bar): the printed
    plastic is not flat at rest. Its rest curvature is the measured
    ``rest_curvature_per_mm`` of each strip; where a row has none, a law
    kbar = c0 + c1 h_p fitted to the measured rows (aux) is used. No free parameter."""

    def applicable(self, rows):
        m = np.isfinite(rows[REST])
        if not m.any():
            return False, "not applicable: rest_curvature_per_mm never measured"
        return True, ""

    def prepare(self, rows):
        m = np.isfinite(rows[REST])
        h, k = rows["plastic_thickness_mm"][m], rows[REST][m]
        if np.unique(h).size >= 2:
            c1, c0 = np.polyfit(h, k, 1)
        else:
            c0, c1 = float(k.mean()), 0.0
        return {"fallback_c0": float(c0), "fallback_c1": float(c1)}

    def apply(self, rows, p, state, aux):
        k = rows[REST]
        fallback = aux["fallback_c0"] + aux["fallback_c1"] * rows["plastic_thickness_mm"]
        state["rest_curvature"] = state["rest_curvature"] + np.where(np.isfinite(k), k, fallback)
        return state


SMOOTHING_COVARIATES = ("plastic_thickness_mm", "fabric_thickness_mm", "stretch", "side", "cos2theta",
                        "width_mm", "length_mm")


def _smoothing_design(rows, names):
    cols = [np.ones(len(rows["stretch"]))] + [_covariate(rows, c) for c in names]
    return np.stack(cols, 1)


class PlasticSetSmoothed(PlasticSetMeasured):
    """Plastic set from the measured rest curvatures with their peel-off scatter
    averaged out (errors in variables): kbar is the least-squares linear law of the
    measured rest curvature in the design covariates that vary (plastic and fabric
    thickness, stretch, side, cos 2 theta, width, length, taken in this order while
    the design stays full rank), fitted on the training rows (aux) and applied to
    every row. No free parameter (seed 3.3, Eq. 3.17)."""

    def prepare(self, rows):
        m = np.isfinite(rows[REST])
        sub = {k: v[m] for k, v in rows.items() if isinstance(v, np.ndarray)}
        names = []
        for c in SMOOTHING_COVARIATES:  # keep the design full rank with spare rows
            X = _smoothing_design(sub, names + [c])
            if X.shape[0] > X.shape[1] and np.linalg.matrix_rank(X) == X.shape[1]:
                names.append(c)
        X = _smoothing_design(sub, names)
        coef, *_ = np.linalg.lstsq(X, sub[REST], rcond=None)
        dof = max(X.shape[0] - X.shape[1], 1)
        s2 = float(((sub[REST] - X @ coef) ** 2).sum()) / dof
        se = np.sqrt(np.maximum(np.diag(s2 * np.linalg.pinv(X.T @ X)), 0.0))
        labels = ["rest_curvature_intercept_per_mm"] + [f"rest_curvature_slope_{c}" for c in names]
        return {"covariates": names, "coefficients": [float(c) for c in coef],
                "parameters": {q: [float(c), float(e)] for q, c, e in zip(labels, coef, se)}}

    def apply(self, rows, p, state, aux):
        law = _smoothing_design(rows, aux["covariates"]) @ np.asarray(aux["coefficients"])
        state["rest_curvature"] = state["rest_curvature"] + law
        return state


class PlasticSetConstant(Effect):
    """Plastic set as one fitted rest curvature kbar0 (1/mm) for all strips (seed
    3.2.3 when the rest curvature is not measured; 4.6 names plasticity as a likely
    cause of simulations that bend too little)."""

    def apply(self, rows, p, state, aux):
        state["rest_curvature"] = state["rest_curvature"] + p[0]
        return state


class PlasticSetThickness(Effect):
    """Thickness-dependent plastic set: kbar = k0 + k1 (h_p - 0.4 mm) (seed Fig. 3.4:
    thinner strips bend more and keep more curvature after peeling)."""

    def apply(self, rows, p, state, aux):
        state["rest_curvature"] = state["rest_curvature"] + p[0] + p[1] * (
            rows["plastic_thickness_mm"] - REFERENCE_THICKNESS)
        return state


class SideDeposition(_BackFaceEffect):
    """Front/back asymmetry by deposition (seed 5.3.5, Fig. 5.9): at the same nozzle
    height the plastic also fills the crevices of the rougher face, a fixed extra
    volume per area, so the effective plastic thickness on the back face is
    h_p + delta (mm; delta < 0 when the front is the rougher face)."""

    def apply(self, rows, p, state, aux):
        back = rows["side"] == "back"
        state["plastic_thickness"] = np.where(back, np.maximum(state["plastic_thickness"] + p[0], 0.02),
                                              state["plastic_thickness"])
        return state


class SideDepositionFactor(_BackFaceEffect):
    """Front/back asymmetry by deposition as a proportional change (seed 5.3.5,
    Fig. 5.9; e.g. a different flow on the rough face): back-face plastic
    thickness f h_p (front unchanged)."""

    def apply(self, rows, p, state, aux):
        back = rows["side"] == "back"
        state["plastic_thickness"] = np.where(back, state["plastic_thickness"] * p[0],
                                              state["plastic_thickness"])
        return state


class SideFabricStiffness(_BackFaceEffect):
    """Front/back asymmetry by the fabric (seed 5.3.5, second explanation; 4.4.3:
    the fabric's bending resistance differs between faces): the fabric modulus on
    the back face is a factor g times the front one."""

    def apply(self, rows, p, state, aux):
        back = rows["side"] == "back"
        state["modulus_ratio"] = np.where(back, state["modulus_ratio"] / p[0], state["modulus_ratio"])
        return state


class ThicknessBias(Effect):
    """Printer thickness bias (seed 5.3.5 lists printer fabrication errors and the
    bed calibration of 3.3): the printed thickness is h_p + delta (mm)."""

    def apply(self, rows, p, state, aux):
        state["plastic_thickness"] = np.maximum(state["plastic_thickness"] + p[0], 0.02)
        return state


class StretchModulus(Effect):
    """Stretch-dependent fabric modulus (seed 4.4.1: the knit's release modulus
    depends on how far it was stretched): E_fabric(s) = E_fabric (s / 1.35)^p."""

    def apply(self, rows, p, state, aux):
        state["modulus_ratio"] = state["modulus_ratio"] * (rows["stretch"] / REFERENCE_STRETCH) ** (-p[0])
        return state


class PlasticPrestrain(Effect):
    """Residual printing strain in the plastic (seed 5.3.5: "residual stress in the
    ribbons induced by the printing process"): the plastic's rest length is (1 - e)
    in printed coordinates, equivalent to an effective stretch s (1 - e)."""

    def apply(self, rows, p, state, aux):
        state["stretch"] = np.maximum(state["stretch"] * (1 - p[0]), 1.0)
        return state


class Orthotropy(Effect):
    """Fabric orthotropy (seed 4.4, Eq. 4.2-4.3; 4.6 suggests ribbons at several
    orientations to measure it): E_fabric(theta) = E_fabric (1 + c cos 2 theta),
    theta the strip axis from the course direction."""

    def apply(self, rows, p, state, aux):
        c2 = np.cos(np.radians(2 * rows["orientation_deg"]))
        state["modulus_ratio"] = state["modulus_ratio"] / (1 + p[0] * c2)
        return state


def flexural_rigidity(plastic_thickness, fabric_thickness, modulus_ratio):
    """Bending rigidity per width of the bilayer beam in units of E_fabric (mm^3)."""
    hp, hf, R = (np.asarray(v, float) for v in (plastic_thickness, fabric_thickness, modulus_ratio))
    a0 = hf + R * hp
    a1 = R * ((hf / 2 + hp) ** 2 - (hf / 2) ** 2) / 2
    zn = a1 / a0
    i_f = hf ** 3 / 12 + hf * zn ** 2
    zp = hf / 2 + hp / 2
    i_p = hp ** 3 / 12 + hp * (zp - zn) ** 2
    return i_f + R * i_p


class Gravity(Effect):
    """Gravity sag (seed 4.4.3 cantilever tests; strips are photographed lying
    down): the strip's own weight q per area bends each half (length L/2) like a
    cantilever, lowering the mean photographed curvature by g L^2 / (24 D), with
    g = q / E_fabric (the one weight parameter) and D the bilayer rigidity per
    width in units of E_fabric."""

    def apply(self, rows, p, state, aux):
        D = flexural_rigidity(state["plastic_thickness"], state["fabric_thickness"], state["modulus_ratio"])
        state["curvature"] = state["curvature"] - p[0] * rows["length_mm"] ** 2 / (24 * D)
        return state


class WidthTransition(Effect):
    """Narrow-strip to plate transition (seed 5.3.5: curvature depends on the fabric
    across the ribbon, and the rod model ignores ribbon width, Fig. 5.8): a wide
    strip cannot take the free (anticlastic/spherical) shape and rolls like a plate.
    kappa = k_narrow + phi (k_plate - k_narrow), phi = b^2 / (b^2 + b0^2),
    b = w^2 k_narrow / (h_p + h_f) the Searle number; b0 is fitted."""

    def apply(self, rows, p, state, aux):
        kn = state["curvature"]
        kp = strip_model(state["plastic_thickness"], state["fabric_thickness"], state["stretch"],
                         state["modulus_ratio"], rest_curvature=state["rest_curvature"], mode="plate")
        b = rows["width_mm"] ** 2 * np.abs(kn) / (state["plastic_thickness"] + state["fabric_thickness"])
        phi = b ** 2 / (b ** 2 + p[0] ** 2)
        state["curvature"] = kn + phi * (kp - kn)
        return state


class FabricCompression(Effect):
    """The fabric under the plastic is compressed (by the nozzle and the clamp of
    seed Fig. 3.6): effective fabric thickness c h_f."""

    def apply(self, rows, p, state, aux):
        state["fabric_thickness"] = state["fabric_thickness"] * p[0]
        return state


class PlasticSeeping(Effect):
    """Plastic seeping into the fabric (seed 5.3.5): the interface moves into the
    fabric by d (mm): plastic h_p + d, fabric h_f - d."""

    def apply(self, rows, p, state, aux):
        hf = state["fabric_thickness"]
        d = np.minimum(p[0], 0.9 * hf)
        state["plastic_thickness"] = state["plastic_thickness"] + d
        state["fabric_thickness"] = hf - d
        return state


CATALOGUE = (
    PlasticSetMeasured("plastic_set_measured"),
    PlasticSetSmoothed("plastic_set_smoothed"),
    PlasticSetConstant("plastic_set_constant", ("rest_curvature_per_mm",), (0.0,), ((-0.2, 0.2),),
                       starts=((0.01,), (-0.01,))),
    PlasticSetThickness("plastic_set_thickness", ("rest_curvature_per_mm", "slope_per_mm2"),
                        (0.0, 0.0), ((-0.2, 0.2), (-2.0, 2.0))),
    ThicknessBias("thickness_bias", ("delta_mm",), (0.0,), ((-0.2, 0.4),), starts=((0.1,), (-0.05,))),
    SideDeposition("side_deposition", ("back_extra_thickness_mm",), (0.0,), ((-0.2, 0.4),), starts=((0.1,), (-0.05,))),
    SideDepositionFactor("side_deposition_factor", ("back_thickness_factor",), (1.0,), ((0.4, 2.5),),
                         log=(True,), starts=((1.4,), (0.8,))),
    SideFabricStiffness("side_fabric_stiffness", ("back_fabric_modulus_factor",), (1.0,), ((0.1, 10.0),),
                        log=(True,), starts=((2.0,), (0.5,))),
    StretchModulus("stretch_modulus", ("exponent",), (0.0,), ((-30.0, 30.0),), varies=("stretch",),
                   starts=((5.0,), (-5.0,))),
    PlasticPrestrain("plastic_prestrain", ("strain",), (0.0,), ((-0.3, 0.3),), varies=("stretch",),
                     starts=((0.05,), (-0.05,))),
    Orthotropy("orthotropy", ("cos2theta_amplitude",), (0.0,), ((-0.9, 0.9),), varies=("cos2theta",),
               starts=((0.3,), (-0.3,))),
    Gravity("gravity", ("weight_over_fabric_modulus",), (1e-6,), ((0.0, 0.1),), stage="output", order=2,
            starts=((1e-4,), (1e-3,))),
    WidthTransition("width_transition", ("searle_number",), (10.0,), ((0.3, 1000.0),), log=(True,),
                    stage="output", order=1, varies=("width_mm",), starts=((2.0,), (50.0,))),
    FabricCompression("fabric_compression", ("thickness_factor",), (1.0,), ((0.3, 2.0),), log=(True,),
                      starts=((0.7,), (1.4,))),
    PlasticSeeping("plastic_seeping", ("depth_mm",), (0.02,), ((0.0, 0.6),), starts=((0.15,),)),
)
BY_NAME = {e.name: e for e in CATALOGUE}


# ---------------------------------------------------------------------------
# the composite model


def parameter_names(effects):
    """Names of the parameter vector: modulus_ratio then '<effect>.<param>'."""
    return ["modulus_ratio"] + [f"{e.name}.{q}" for e in effects for q in e.params]


def to_internal(effects, natural):
    """Natural parameter values -> optimiser variables (log for the modulus ratio
    and for log-flagged effect parameters)."""
    flags = [True] + [bool(e.log[i]) if e.log else False for e in effects for i in range(len(e.params))]
    v = np.asarray(natural, float)
    return np.where(flags, np.log(np.maximum(v, 1e-300)), v), np.array(flags)


def bounds_internal(effects):
    lo, hi = [np.log(1.0)], [np.log(1e7)]
    for e in effects:
        for i, (a, b) in enumerate(e.bounds):
            lg = bool(e.log[i]) if e.log else False
            lo.append(np.log(a) if lg else a)
            hi.append(np.log(b) if lg else b)
    return np.array(lo), np.array(hi)


def natural(effects, internal):
    t = np.asarray(internal, float)
    _, flags = to_internal(effects, np.ones(t.shape[-1]))
    return np.where(flags, np.exp(t), t)


def predict(rows, effects, theta, aux=None):
    """Curvature (1/mm) predicted for ``rows`` by the base model plus ``effects``
    (input-stage effects first, then output-stage ones by ``order``) at natural
    parameter values ``theta`` = [modulus_ratio, effect params...]. ``theta`` may be
    a batch (m, P): the result is then (m, n), one model call for all."""
    aux = aux or {}
    theta = np.asarray(theta, float)
    batch = theta.ndim == 2
    th = theta if batch else theta[None]
    n = len(rows["stretch"])
    col = lambda v: v[:, None]  # noqa: E731  (parameter per batch member, broadcast over rows)
    shape = (th.shape[0], n)
    state = {"plastic_thickness": np.broadcast_to(rows["plastic_thickness_mm"], shape).astype(float),
             "fabric_thickness": np.broadcast_to(rows["fabric_thickness_mm"], shape).astype(float),
             "stretch": np.broadcast_to(rows["stretch"], shape).astype(float),
             "modulus_ratio": np.broadcast_to(col(th[:, 0]), shape).astype(float),
             "rest_curvature": np.zeros(shape)}
    slices, k = [], 1
    for e in effects:
        slices.append([col(th[:, k + i]) for i in range(len(e.params))])
        k += len(e.params)
    staged = sorted(zip(effects, slices), key=lambda t: (t[0].stage != "inputs", t[0].order))
    for e, p in staged:
        if e.stage == "inputs":
            state = e.apply(rows, p, state, aux.get(e.name, {}))
    state["curvature"] = strip_model(state["plastic_thickness"], state["fabric_thickness"],
                                     state["stretch"], state["modulus_ratio"],
                                     rest_curvature=state["rest_curvature"], mode="narrow")
    for e, p in staged:
        if e.stage == "output":
            state = e.apply(rows, p, state, aux.get(e.name, {}))
    out = np.broadcast_to(state["curvature"], shape)
    return out if batch else out[0]


def measured(rows):
    return rows[MEASURED]
