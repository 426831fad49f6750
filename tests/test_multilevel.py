"""Nested iteration across meshes: point location, interpolation, the mesh hierarchy, and a
coarse-to-fine solve reaching the same equilibrium as the direct one."""
import os
import tempfile

import numpy as np
import pytest

from shellfem.multilevel import MIN_FINE_VERTICES, locate_points, prolongate


def _square_mesh(n_ring: int, seed: int):
    """Delaunay mesh of the unit square with jittered interior points (a graded, unstructured mesh)."""
    from scipy.spatial import Delaunay
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n_ring + 1)[:-1]
    edge = np.concatenate([np.c_[t, 0 * t], np.c_[1 + 0 * t, t], np.c_[1 - t, 1 + 0 * t], np.c_[0 * t, 1 - t]])
    inner = rng.uniform(0.02, 0.98, (n_ring * n_ring // 2, 2)) ** 1.5      # denser towards the corner (0, 0)
    p = np.vstack([edge, inner])
    return p, Delaunay(p).simplices


def test_locate_points_reproduces_the_points():
    p, t = _square_mesh(12, 0)
    X = np.random.default_rng(1).uniform(0, 1, (500, 2))
    X = np.vstack([X, [[0, 0], [1, 1], [0.5, 0], [1, 0.3]]])        # corners and boundary points too
    tri, bary = locate_points(p, t, X)
    assert np.all(bary >= 0) and np.allclose(bary.sum(1), 1)
    assert np.abs(np.einsum("pk,pkd->pd", bary, p[t[tri]]) - X).max() < 1e-12


def test_locate_points_outside_is_clamped_to_the_nearest_triangle():
    p, t = _square_mesh(8, 2)
    tri, bary = locate_points(p, t, np.array([[1.0 + 1e-9, 0.5], [-1e-10, 0.2]]))
    y = np.einsum("pk,pkd->pd", bary, p[t[tri]])
    assert np.all(bary >= 0)
    assert np.abs(y - [[1.0, 0.5], [0.0, 0.2]]).max() < 1e-8


def test_prolongate_is_exact_for_affine_fields_between_unrelated_meshes():
    pc, tc = _square_mesh(10, 3)
    pf, tf = _square_mesh(25, 4)
    A = np.array([[1.3, -0.2], [0.4, 0.9], [2.0, -1.0]])
    b = np.array([0.5, -1.0, 3.0])
    vals = pc @ A.T + b
    out = prolongate(pc, tc, vals, pf)
    assert out.shape == (len(pf), 3)
    assert np.abs(out - (pf @ A.T + b)).max() < 1e-12
    # a curved field is only approximated, with the coarse mesh's O(h^2) error
    curved = prolongate(pc, tc, np.sin(3 * pc[:, :1]), pf)
    err = np.abs(curved[:, 0] - np.sin(3 * pf[:, 0])).max()
    assert 1e-4 < err < 0.1


def _star_pattern(width, height, seed=0):
    import tomli_w

    from geometry.patterns import load_pattern
    from validation.cases import star_benchmark as pattern
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "p.toml")
        with open(path, "wb") as f:
            tomli_w.dump(pattern(width, height, 1.0, seed=seed), f)
        return load_pattern(path)


def test_coarse_meshes_hierarchy():
    from geometry.meshing import coarse_meshes, mesh_pattern
    pat = _star_pattern(85.0, 60.0)
    fine = mesh_pattern(pat)
    levels = coarse_meshes(pat, fine.n_vertices)
    n = [s.n_vertices for s in levels] + [fine.n_vertices]
    # the benchmark sheet: 10,651 -> 4,321 -> 1,750 vertices (each level >= 1,500 and <= 0.8 of the next)
    assert len(levels) == 2
    assert all(a <= 0.8 * b for a, b in zip(n, n[1:])) and n[0] >= 1500
    for s in levels:           # same printed-state domain, same printed area
        assert np.allclose(s.points.min(0), fine.points.min(0)) and np.allclose(s.points.max(0), fine.points.max(0))
        def a(sh):
            e1 = sh.points[sh.triangles[:, 1]] - sh.points[sh.triangles[:, 0]]
            e2 = sh.points[sh.triangles[:, 2]] - sh.points[sh.triangles[:, 0]]
            return np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
        printed = lambda sh: a(sh)[sh.thickness > 0].sum()
        assert printed(s) == pytest.approx(printed(fine), rel=1e-9)
    assert len(coarse_meshes(pat, fine.n_vertices, levels=1)) == 1
    small = _star_pattern(30.0, 20.0)
    assert coarse_meshes(small, MIN_FINE_VERTICES - 1) == []


def test_nested_iteration_reaches_the_direct_equilibrium():
    """A 30 x 20 mm star sheet (seed 0): solved alone and from a coarser mesh's equilibrium, the
    same released state up to a rigid motion (energy to 1e-9, same curvatures). Where a pattern has several stable states close in
    energy, the two can settle in different ones (seed 1 with the exact metric: 24.716 vs 24.341 N mm)."""
    from forward.simulate import simulate
    pat = _star_pattern(30.0, 20.0, seed=0)
    direct = simulate(pat, coarse_levels=0)
    nested = simulate(pat, coarse_levels=1)
    assert direct.result.converged and nested.result.converged
    levels = nested.result.timings["levels"]
    # coarse and fine with the truncated metric, then the fine mesh with the exact metric
    assert [lv["metric"] for lv in levels] == ["truncated", "truncated", "exact"]
    assert levels[1]["interpolated"] and levels[1]["n_vertices"] == levels[2]["n_vertices"] == direct.sheet.n_vertices
    assert levels[0]["n_vertices"] <= 0.8 * levels[1]["n_vertices"]
    assert [lv["metric"] for lv in direct.result.timings["levels"]] == ["truncated", "exact"]
    assert nested.result.iterations == sum(level["iterations"] for level in levels)
    assert nested.result.energy == pytest.approx(direct.result.energy, rel=1e-9)
    k_direct = np.sort(direct.model.curvatures(direct.result.q)[1])       # mean curvature, 1/mm
    k_nested = np.sort(nested.model.curvatures(nested.result.q)[1])
    assert np.abs(k_direct - k_nested).max() < 1e-5


def test_coarse_levels_option_is_validated():
    from geometry.patterns import parse_pattern
    from shellfem.errors import SelfshapeError
    raw = {"fabric": {"rectangle": [30.0, 3.0], "stretch": 1.35},
           "region": [{"polygon": [[0, 0], [30, 0], [30, 3], [0, 3]], "thickness_mm": 0.3}]}
    assert parse_pattern(dict(raw)).coarse_levels == "auto"
    assert parse_pattern({**raw, "solver": {"coarse_levels": 2}}).coarse_levels == 2
    for bad in (-1, "many", 1.5, True):
        with pytest.raises(SelfshapeError, match="coarse_levels"):
            parse_pattern({**raw, "solver": {"coarse_levels": bad}})


def test_nested_iteration_with_held_rim_reaches_the_exact_relaxed_sheet():
    """Bare fabric with its whole rim held "xyz" where the fabric relaxes to: the exact
    equilibrium is the printed sheet scaled by 1/s with zero energy, from a coarser mesh too;
    being affine, its interpolation is exact and the fine mesh starts at its solution."""
    from geometry.elements import Support
    from shellfem.materials import Fabric, Plastic
    from shellfem.sheet import Sheet
    from forward.simulate import simulate_sheet
    fine, coarse = Sheet.rectangle(20, 10, 12, 6), Sheet.rectangle(20, 10, 5, 3)
    sim = simulate_sheet(fine, Fabric(stretch=(1.35, 1.2)), Plastic(),
                         [Support(points=np.zeros((0, 2)), fix="xyz", boundary=True)], max_iterations=50,
                         coarse=[coarse])
    levels = sim.result.timings["levels"]
    assert [lv["n_vertices"] for lv in levels] == [coarse.n_vertices, fine.n_vertices]
    assert levels[1]["interpolated"] and sim.result.converged, sim.result.reason
    # the exact solution is affine, so the interpolated coarse equilibrium is already the fine one
    assert levels[1]["iterations"] <= 2
    x = sim.model.split(sim.result.q)[0]
    assert np.abs(x[:, :2] - fine.points / [1.35, 1.2]).max() < 1e-6
    assert np.abs(x[:, 2]).max() < 1e-6
    assert abs(sim.result.energy) < 1e-10


def test_cli_coarse_levels(tmp_path, capsys):
    import json

    from selfshape.cli import main
    example = os.path.join(os.path.dirname(__file__), "..", "examples", "strip.toml")
    assert main(["simulate", example, "-o", str(tmp_path / "bad"), "--coarse-levels", "some"]) == 2
    assert main(["simulate", example, "-o", str(tmp_path / "s"), "--coarse-levels", "1", "--no-png"]) == 0
    s = json.loads((tmp_path / "s" / "summary.json").read_text())
    levels = s["timings_s"]["levels"]
    assert len(levels) == 3 and levels[1]["n_vertices"] == levels[2]["n_vertices"] == s["n_vertices"] == 535
    assert levels[2]["metric"] == "exact" and s["newton_iterations"] == sum(lv["iterations"] for lv in levels)
    assert (f"{levels[0]['n_vertices']} vertices: {levels[0]['iterations']} -> 535 vertices: {levels[1]['iterations']}"
            f" -> exact metric: {levels[2]['iterations']})") in capsys.readouterr().out


def test_a_coarse_mesh_that_cannot_be_made_ends_the_hierarchy(monkeypatch):
    import geometry.meshing as meshing
    pat = _star_pattern(85.0, 60.0)
    real = meshing.mesh_pattern
    calls = []

    def failing_second(pattern, size_mm=None, across=None, *args, **kwargs):
        calls.append(across)
        if len(calls) == 2:
            raise RuntimeError("Gmsh: cannot mesh")
        return real(pattern, size_mm, across, *args, **kwargs)

    monkeypatch.setattr(meshing, "mesh_pattern", failing_second)
    levels = meshing.coarse_meshes(pat, 10651)
    assert len(calls) == 2 and len(levels) == 1 and levels[0].n_vertices < 0.8 * 10651


def test_a_failed_coarse_level_is_not_interpolated(monkeypatch):
    """A coarse level that stopped for another reason than its iteration cap (here: made to
    report a collapsed trust region) is no predictor: the next mesh starts from its flat state."""
    import forward.simulate as simulate_module
    from geometry.elements import Support
    from shellfem.materials import Fabric, Plastic
    from shellfem.sheet import Sheet
    real = simulate_module.newton
    calls = []

    def first_fails(*args, **kwargs):
        r = real(*args, **kwargs)
        calls.append(r)
        if len(calls) == 1:
            r.converged, r.reason = False, "no decrease possible (trust region collapsed)"
        return r

    monkeypatch.setattr(simulate_module, "newton", first_fails)
    fine, coarse = Sheet.rectangle(20, 10, 12, 6), Sheet.rectangle(20, 10, 5, 3)
    sim = simulate_module.simulate_sheet(fine, Fabric(stretch=(1.35, 1.2)), Plastic(),
                                         [Support(points=np.zeros((0, 2)), fix="xyz", boundary=True)],
                                         max_iterations=50, coarse=[coarse])
    levels = sim.result.timings["levels"]
    assert len(calls) == 2 and not levels[0]["converged"] and not levels[1]["interpolated"]
    assert sim.result.converged and abs(sim.result.energy) < 1e-10
