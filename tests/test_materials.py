"""Fabric membrane models behind one interface: the registry, the third model
(orthotropic St.Venant-Kirchhoff) checked against finite differences and closed-form
stresses, and a model working from a pattern file to a converged equilibrium."""
import copy

import numpy as np
import pytest

from geometry.patterns import load_pattern
from shellfem.errors import SelfshapeError
from shellfem.layers import rest_area
from shellfem.materials import MEMBRANE_MODELS, Fabric, MembraneModel, Parameter, Plastic, RestState
from shellfem.materials.neo_hookean import NeoHookean
from shellfem.materials.orthotropic_stvk import OrthotropicStVK
from shellfem.model import ShellModel, edge_metric
from shellfem.sheet import Sheet

STVK = "orthotropic-stvk"
PARAMS = {"e1_mpa": 0.6, "e2_mpa": 1.4, "g12_mpa": 0.25, "nu12": 0.35}


def _triangle(m=1):
    P = np.tile(np.array([[0.0, 0.0], [1.3, 0.1], [0.4, 0.9]]), (m, 1, 1))
    abar = edge_metric(P)
    return P, RestState(points=P, metric=abar, area=rest_area(abar))


def _metric(P, course_deg, l1, l2):
    """First fundamental form (m, 3) after stretching by l1 along the course direction and by
    l2 across it, and its derivatives w.r.t. l1 and l2 (exact)."""
    c, s = np.cos(np.radians(course_deg)), np.sin(np.radians(course_deg))
    R = np.array([[c, s], [-s, c]])                          # printed -> course frame
    E = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], 2)   # columns E1, E2
    RE = np.einsum("ij,mjk->mik", R, E)

    def form(d):
        G = np.einsum("mik,i,mil->mkl", RE, d, RE)            # E^T R^T diag(d) R E
        return np.stack([G[:, 0, 0], G[:, 0, 1], G[:, 1, 1]], 1)
    return form(np.array([l1 * l1, l2 * l2])), form(np.array([2 * l1, 0.0])), form(np.array([0.0, 2 * l2]))


def test_registry_holds_the_three_models_and_their_schemas():
    assert {"neo-hookean", "orthotropic", STVK} <= set(MEMBRANE_MODELS)
    for name, model in MEMBRANE_MODELS.items():
        assert model.name == name and issubclass(model, MembraneModel)
        assert all(isinstance(p, Parameter) and p.unit for p in model.parameters)
    f = Fabric()
    assert set(f.parameters) == set(MEMBRANE_MODELS)
    assert f.parameters[STVK] == {"e1_mpa": 0.8, "e2_mpa": 1.3, "g12_mpa": 0.3, "nu12": 0.3}


def test_stvk_energy_gradient_and_hessian_against_finite_differences():
    rng = np.random.default_rng(5)
    m = 12
    P, rest = _triangle(m)
    M = OrthotropicStVK(rest, Fabric(model=STVK, course_angle_deg=35.0, parameters={STVK: PARAMS}))
    a0 = rest.metric * 1.3 + rng.normal(scale=0.05, size=(m, 3))
    W, g, H = M.energy(a0)
    assert np.isfinite(W).all()
    eps = 1e-6
    for k in range(3):
        ap, am = a0.copy(), a0.copy()
        ap[:, k] += eps
        am[:, k] -= eps
        assert np.allclose((M.energy(ap)[0] - M.energy(am)[0]) / (2 * eps), g[:, k], rtol=1e-7, atol=1e-12)
        assert np.allclose((M.energy(ap)[1] - M.energy(am)[1]) / (2 * eps), H[:, :, k], rtol=1e-7, atol=1e-12)
    inverted = a0.copy()
    inverted[:, 1] = np.sqrt(a0[:, 0] * a0[:, 2]) * 1.01          # det a < 0
    assert np.isinf(M.energy(inverted)[0]).all()


@pytest.mark.parametrize("course_deg", [0.0, 30.0, 90.0])
def test_stvk_uniaxial_and_equibiaxial_stress_of_one_triangle(course_deg):
    """Plane-stress orthotropic St.Venant-Kirchhoff in the course frame: uniaxial stress along
    the course, S11 = E1 e with lateral strain -nu12 e; along the wale, S22 = E2 e with lateral
    strain -nu12 E2 / E1 e; equibiaxial strain e: S11 = e (E1 + nu12 E2) / d,
    S22 = e E2 (1 + nu12) / d, d = 1 - nu12^2 E2 / E1. dW/dl = h A S_ii l_i."""
    P, rest = _triangle()
    fab = Fabric(model=STVK, course_angle_deg=course_deg, thickness=0.7, parameters={STVK: PARAMS})
    M = OrthotropicStVK(rest, fab)
    E1, E2, nu12 = PARAMS["e1_mpa"], PARAMS["e2_mpa"], PARAMS["nu12"]
    hA = 0.7 * rest.area[0]
    e = 0.08
    d = 1 - nu12 ** 2 * E2 / E1
    stretch = lambda strain: np.sqrt(1 + 2 * strain)  # noqa: E731  Green strain -> stretch
    cases = [((e, -nu12 * e), (E1 * e, 0.0)),
             ((-nu12 * E2 / E1 * e, e), (0.0, E2 * e)),
             ((e, e), (e * (E1 + nu12 * E2) / d, e * E2 * (1 + nu12) / d))]
    for (e11, e22), (S11, S22) in cases:
        l1, l2 = stretch(e11), stretch(e22)
        a, da1, da2 = _metric(P, course_deg, l1, l2)
        W, g, _ = M.energy(a)
        assert g[0] @ da1[0] == pytest.approx(hA * S11 * l1, rel=1e-12, abs=1e-15)
        assert g[0] @ da2[0] == pytest.approx(hA * S22 * l2, rel=1e-12, abs=1e-15)
        assert W[0] == pytest.approx(hA * 0.5 * (S11 * e11 + S22 * e22), rel=1e-12)


RIBBONS = {
    "fabric": {"rectangle": [24.0, 12.0], "stretch": 1.3, "thickness_mm": 0.8, "model": STVK,
               "course_angle_deg": 30.0, STVK: dict(PARAMS)},
    "plastic": {"young_modulus_mpa": 72.3, "poisson": 0.5},
    "ribbon": [{"path": [[1.0, y], [23.0, y]], "width_mm": 1.5, "thickness_mm": 0.4} for y in (3.0, 6.0, 9.0)],
    "mesh": {"size_mm": 1.5, "across": 1},
    "solver": {"seed": 0},
}


def test_a_model_from_a_pattern_file_reaches_a_converged_equilibrium(tmp_path):
    from forward.simulate import simulate
    from geometry.patterns import write_pattern

    path = tmp_path / "stvk.toml"
    write_pattern(path, RIBBONS)
    pat = load_pattern(path)
    assert pat.fabric.model == STVK and pat.fabric.model_parameters == PARAMS
    sim = simulate(pat)
    r = sim.result
    assert r.converged and r.stable, r.reason
    assert r.gradient_norm <= 1e-8 * r.history[0]["gradient_norm"]
    x = sim.positions
    assert np.ptp(x[:, 0]) < 24.0 and np.ptp(x[:, 2]) > 1.0      # contracted and curled
    # the membrane energy in use is the model's: the same state with other parameters differs
    other = copy.deepcopy(RIBBONS)
    other["fabric"][STVK]["e1_mpa"] = 1.2
    alt = ShellModel.from_materials(sim.sheet, load_pattern(other).fabric, pat.plastic)
    assert alt.energy(r.q) != pytest.approx(r.energy, rel=1e-6)


@pytest.mark.parametrize("entry,message", [
    ({"e1_mpa": -1.0}, "[fabric] orthotropic-stvk: e1_mpa must be in (0, 10000] MPa, got -1"),
    ({"g12_mpa": 0.0}, "[fabric] orthotropic-stvk: g12_mpa must be in (0, 10000] MPa, got 0"),
    ({"nu12": 1.5}, "[fabric] orthotropic-stvk: nu12 must be in [-0.99, 0.99], got 1.5"),
    ({"nu12": 0.9, "e1_mpa": 0.5, "e2_mpa": 1.0}, "fabric.orthotropic-stvk.nu12 = 0.9 must satisfy nu12^2 < e1_mpa / e2_mpa"),
    ({"e1_mpa": "stiff"}, "[fabric] orthotropic-stvk: e1_mpa must be a number"),
    ({"e3_mpa": 1.0}, "[fabric] orthotropic-stvk: unknown key 'e3_mpa'"),
])
def test_bad_model_parameters_name_the_entry(entry, message):
    raw = copy.deepcopy(RIBBONS)
    raw["fabric"][STVK].update(entry)
    with pytest.raises(SelfshapeError) as e:
        load_pattern(raw)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_bad_model_name_lists_the_registered_models():
    with pytest.raises(SelfshapeError, match='fabric.model must be one of "neo-hookean", "orthotropic", '):
        Fabric(model="linear")
    with pytest.raises(SelfshapeError, match="unknown membrane model"):
        Fabric(parameters={"linear": {}})


class _ScaledNeoHookean(MembraneModel):
    """A model defined outside the package: the neo-Hookean energy times a factor."""
    name = "scaled-neo-hookean"
    parameters = (Parameter("scale", 1.0, "1", "energy factor", lo=0.0, lo_open=True),)

    def __init__(self, rest, fabric):
        self.inner = NeoHookean(rest, fabric)
        self.scale = fabric.parameters[self.name]["scale"]

    def energy(self, a):
        W, g, H = self.inner.energy(a)
        return self.scale * W, self.scale * g, self.scale * H


def test_a_registered_model_plugs_into_the_record_the_pattern_and_the_shell(monkeypatch):
    """Registration is all a model needs: Fabric validates its table, the pattern reads
    [fabric.<name>], ShellModel dispatches to it."""
    monkeypatch.setitem(MEMBRANE_MODELS, _ScaledNeoHookean.name, _ScaledNeoHookean)
    raw = copy.deepcopy(RIBBONS)
    raw["fabric"]["model"] = _ScaledNeoHookean.name
    raw["fabric"][_ScaledNeoHookean.name] = {"scale": 2.0}
    pat = load_pattern(raw)
    assert pat.fabric.model_parameters == {"scale": 2.0}
    sheet = Sheet.rectangle(6, 4, 6, 4)                       # bare fabric only: the membrane and bending
    rng = np.random.default_rng(1)
    plain = ShellModel.from_materials(sheet, Fabric(stretch=1.3, bending_stiffness=0.0), Plastic())
    q = plain.initial_state()
    q[:3 * sheet.n_vertices] += rng.normal(scale=0.05, size=3 * sheet.n_vertices)
    for scale in (1.0, 2.0):
        fab = Fabric(stretch=1.3, bending_stiffness=0.0, model=_ScaledNeoHookean.name,
                     parameters={_ScaledNeoHookean.name: {"scale": scale}})
        assert ShellModel.from_materials(sheet, fab, Plastic()).energy(q) == pytest.approx(
            scale * plain.energy(q), rel=1e-12)
    raw["fabric"][_ScaledNeoHookean.name] = {"scale": -1.0}
    with pytest.raises(SelfshapeError, match=r"\[fabric\] scaled-neo-hookean: scale must be in \(0, 10\], got -1"):
        load_pattern(raw)
