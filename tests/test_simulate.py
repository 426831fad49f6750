"""`selfshape simulate` end to end, and bad input."""
import json
import os

import meshio
import numpy as np
import pytest

from geometry.elements import Support
from geometry.patterns import parse_pattern
from selfshape.cli import main
from shellfem.errors import SelfshapeError
from shellfem.materials import Fabric, Plastic
from shellfem.sheet import Sheet

HERE = os.path.dirname(__file__)
EXAMPLE = os.path.join(HERE, "..", "examples", "strip_narrow.toml")


def test_simulate_strip_writes_outputs(tmp_path):
    out = tmp_path / "strip"
    assert main(["simulate", EXAMPLE, "-o", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    for key in ("converged", "newton_iterations", "energy", "gradient_norm", "wall_time_s", "n_vertices",
                "n_triangles", "bbox_mm"):
        assert key in s
    assert s["converged"] is True
    m = meshio.read(out / "deployed.vtu")
    assert {"region", "thickness_mm", "side"} <= set(m.cell_data)
    assert np.allclose(m.point_data["reference"][:, 2], 0)
    assert (out / "deployed.png").stat().st_size > 1000
    # the strip curls: shorter than printed, and lifted out of the plane
    assert s["bbox_mm"][0] < 30.0 / 1.0 and s["bbox_mm"][2] > 1.0


@pytest.mark.parametrize("kwargs,word", [
    (dict(stretch=0.9), "stretch"), (dict(thickness=-1), "thickness"), (dict(young_modulus=float("nan")), "young"),
])
def test_bad_fabric_parameters(kwargs, word):
    with pytest.raises(SelfshapeError, match=word):
        Fabric(**kwargs)


def test_degenerate_triangle_and_negative_thickness():
    pts = np.array([[0, 0], [1, 0], [2, 0], [0, 1]], float)
    with pytest.raises(SelfshapeError, match="degenerate"):
        Sheet(pts, np.array([[0, 1, 2], [0, 1, 3]]))
    with pytest.raises(SelfshapeError, match="thickness"):
        Sheet(pts, np.array([[0, 1, 3]]), thickness_front=np.array([-0.1]))


def test_support_that_misses_the_sheet(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text(open(EXAMPLE).read() + '\n[[support]]\npoints = [[0.0, 0.0]]\nfix = "z"\n')
    from forward.simulate import simulate_sheet
    from geometry.patterns import load_pattern
    from geometry.elements import Support
    pat = load_pattern(str(p))
    sheet = Sheet.rectangle(30, 3, 10, 2)
    with pytest.raises(SelfshapeError, match="does not hit the sheet"):
        simulate_sheet(sheet, pat.fabric, Plastic(), [Support(np.array([[80.0, 50.0]]), "z")])


def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text(open(EXAMPLE).read().replace("stretch = 1.35", "stretch = 0.8"))
    assert main(["simulate", str(p), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "stretch" in err
    assert not (tmp_path / "o" / "summary.json").exists()


def test_harmonic_extension_reproduces_a_uniform_scaling():
    from shellfem.boundary import graph_laplacian, harmonic_extension
    from shellfem.kinematics import build_topology
    sh = Sheet.rectangle(20, 10, 10, 5)
    P = sh.points
    rim = np.flatnonzero((P[:, 0] < 1e-9) | (P[:, 0] > 20 - 1e-9) | (P[:, 1] < 1e-9) | (P[:, 1] > 10 - 1e-9))
    u = harmonic_extension(graph_laplacian(sh.n_vertices, build_topology(sh.triangles).edges), rim, -0.25 * P[rim])
    assert np.abs(u + 0.25 * P).max() < 1e-12


def test_boundary_held_at_the_relaxed_fabric_is_the_exact_relaxed_sheet():
    # bare fabric whose whole rim is held "xyz" where the fabric relaxes to: the equilibrium is the
    # flat sheet scaled by 1/s with zero energy. Before the held motion was carried into the sheet
    # the first iterate had inverted triangles (energy not finite).
    from geometry.elements import Support
    from forward.simulate import simulate_sheet
    sh = Sheet.rectangle(20, 10, 10, 5)
    P = sh.points
    sim = simulate_sheet(sh, Fabric(stretch=(1.35, 1.2)), Plastic(),
                         [Support(points=np.zeros((0, 2)), fix="xyz", boundary=True)], max_iterations=50)
    assert len(sim.fixed) == 3 * 30
    assert sim.result.converged, sim.result.reason
    x = sim.model.split(sim.result.q)[0]
    assert np.abs(x[:, :2] - P / [1.35, 1.2]).max() < 1e-6
    assert np.abs(x[:, 2]).max() < 1e-6
    assert abs(sim.result.energy) < 1e-10


def test_boundary_support_holds_the_outer_edge_not_the_holes():
    # a bare frame of fabric (a rectangle with two holes) held "xyz" at its outer edge where the
    # fabric relaxes: the hole rims stay free, and the equilibrium is still the flat sheet
    # scaled by 1/s with zero energy (uniform relaxation moves the rims there by themselves)
    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from forward.simulate import simulate_sheet
    from forward.supports import outer_edge_vertices
    from geometry.meshops import unique_edges
    pat = load_pattern({"fabric": {"rectangle": [30.0, 20.0], "stretch": [1.3, 1.2],
                                   "holes": [[[5, 5], [12, 5], [12, 15], [5, 15]], [[18, 6], [25, 6], [21, 14]]]},
                        "mesh": {"size_mm": 2.5}})
    sh = mesh_pattern(pat)
    E, _, counts = unique_edges(sh.triangles)
    rim = np.unique(E[counts == 1])
    outer = outer_edge_vertices(sh.points, sh.triangles)
    P = sh.points
    on_edge = (np.isclose(P[:, 0], 0) | np.isclose(P[:, 0], 30) | np.isclose(P[:, 1], 0) | np.isclose(P[:, 1], 20))
    assert np.array_equal(outer, np.flatnonzero(on_edge)) and len(rim) > len(outer) + 10
    sim = simulate_sheet(sh, pat.fabric, Plastic(), [Support(points=np.zeros((0, 2)), fix="xyz", boundary=True)],
                         max_iterations=50)
    assert len(sim.fixed) == 3 * len(outer)
    assert sim.result.converged, sim.result.reason
    x = sim.model.split(sim.result.q)[0]
    assert np.abs(x[:, :2] - P / [1.3, 1.2]).max() < 1e-6 and np.abs(x[:, 2]).max() < 1e-6
    assert abs(sim.result.energy) < 1e-10


def test_support_boundary_key(tmp_path):
    from geometry.patterns import load_pattern
    raw = {"fabric": {"rectangle": [20.0, 10.0]}, "support": [{"boundary": True, "fix": "z"}], "mesh": {"size_mm": 2.0}}
    pat = load_pattern(raw)
    assert pat.supports[0].boundary and pat.supports[0].fix == "z"
    for bad, word in (({"boundary": "yes"}, "boundary must be true or false"),
                      ({"boundary": True, "points": [[0.0, 0.0]]}, "drop points"),
                      ({"fix": "z"}, "missing points")):
        with pytest.raises(SelfshapeError, match=word):
            load_pattern({**raw, "support": [bad]})


def test_metric_floor_reaches_the_same_equilibrium():
    """[solver] metric_floor changes the trust-region path only, not the equilibrium (narrow
    strip): the default (10) and plain Marquardt scaling (0) agree."""
    import tomllib

    from geometry.patterns import load_pattern
    from forward.simulate import simulate
    from shellfem.newton import DEFAULT_METRIC_FLOOR
    with open(EXAMPLE, "rb") as f:
        raw = tomllib.load(f)
    floored = simulate(load_pattern(raw))
    assert load_pattern(raw).metric_floor is None and DEFAULT_METRIC_FLOOR == 10.0   # None: the solver's default
    raw.setdefault("solver", {})["metric_floor"] = 0.0
    pat = load_pattern(raw)
    assert pat.metric_floor == 0.0
    plain = simulate(pat)
    assert plain.result.converged and floored.result.converged
    assert floored.result.energy == pytest.approx(plain.result.energy, rel=1e-9)
    assert np.abs(floored.positions - plain.positions).max() < 1e-5 * np.ptp(plain.positions[:, 0])


def test_edge_angle_relaxation_recovers_the_equilibrium_angles():
    """At an equilibrium's positions, relaxing zeroed edge angles finds the equilibrium's angles
    (the angle problem is a nonlinear elimination, not an approximation), the energy never
    rises, and a full Newton solve from there without the relaxation returns to the same
    equilibrium (narrow strip)."""
    from geometry.patterns import load_pattern
    from forward.simulate import simulate
    from shellfem.newton import newton
    from shellfem.relaxations import EdgeAngleRelaxation
    sim = simulate(load_pattern(EXAMPLE))
    r, M = sim.result, sim.model
    assert r.converged
    n = M.n_vertices
    free = np.ones(M.n_dofs, bool)
    free[sim.fixed] = False
    free[sim.gauge] = False
    start = r.q.copy()
    start[3 * n:] = 0.0
    E0 = M.energy(start)
    assert E0 > r.energy + 1e-3 * abs(r.energy)          # zeroed angles are far from equilibrium
    relaxed = EdgeAngleRelaxation(M, free, max_iterations=30)(start, abs(r.energy))
    assert M.energy(relaxed) == pytest.approx(r.energy, rel=1e-9)
    assert np.abs(relaxed[3 * n:] - r.q[3 * n:]).max() < 1e-6
    assert np.array_equal(relaxed[:3 * n], start[:3 * n])
    plain = newton(M, start, free, relax_angles=False, max_iterations=300)
    assert plain.converged
    assert plain.energy == pytest.approx(r.energy, rel=1e-9)
    # inadmissible angles (|psi| >= 0.49 pi, infinite energy) at good positions: re-solved from 0
    bad = r.q.copy()
    bad[3 * n:] = 2.0
    assert M.energy(bad) == np.inf
    again = newton(M, bad, free, max_iterations=20)
    assert again.converged and again.energy == pytest.approx(r.energy, rel=1e-9)


def _small_star_sheet(width=20.0, height=15.0):
    import os
    import tempfile

    import tomli_w

    from geometry.meshing import mesh_pattern
    from geometry.patterns import load_pattern
    from validation.cases import star_benchmark as pattern
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "stars.toml")
        with open(path, "wb") as f:
            tomli_w.dump(pattern(width, height), f)
        pat = load_pattern(path)
    return pat, mesh_pattern(pat)


def test_printed_region_relaxation_recovers_the_equilibrium():
    """Perturbing only the printed regions' DOFs of a star sheet's equilibrium, the printed
    relaxation (Newton on those DOFs, the rest frozen) returns to the equilibrium, never raises
    the energy and leaves the other DOFs alone; newton with and without it reaches the same
    equilibrium."""
    from forward.simulate import simulate_sheet
    from shellfem.newton import newton
    from shellfem.relaxations import StiffRegionRelaxation
    pat, sheet = _small_star_sheet()
    sim = simulate_sheet(sheet, pat.fabric, pat.plastic, seed=0, max_iterations=300)
    r, M = sim.result, sim.model
    assert r.converged
    mask = M.printed_dofs()
    n = M.n_vertices
    printed = (sheet.thickness_front > 0) | (sheet.thickness_back > 0)
    assert mask[:3 * n].reshape(n, 3).all(1).sum() == len(np.unique(sheet.triangles[printed]))
    assert mask[3 * n:].sum() == len(np.unique(M.topo.face_edges[printed]))
    assert 0.2 < mask.mean() < 0.9
    free = np.ones(M.n_dofs, bool)
    free[sim.fixed] = False
    free[sim.gauge] = False
    P = mask & free
    start = r.q.copy()
    start[P] += 0.02 * np.random.default_rng(0).standard_normal(int(P.sum()))
    E0 = M.energy(start)
    assert E0 > r.energy + 1e-2 * abs(r.energy)
    relax = StiffRegionRelaxation(M, free, mask, max_iterations=40)
    q, E = relax(start)
    assert E == pytest.approx(M.energy(q)) and E <= E0
    assert np.array_equal(q[~P], start[~P])
    assert E == pytest.approx(r.energy, rel=1e-9)
    assert np.abs(q - r.q).max() < 1e-5
    plain = newton(M, r.q, free, relax_printed=False, max_iterations=50)
    assert plain.converged and plain.energy == pytest.approx(r.energy, rel=1e-9)


def test_printed_region_relaxation_is_off_when_the_print_covers_the_sheet():
    """A strip printed all over: the printed DOFs are (nearly) all DOFs, the relaxation would be
    a second full Newton step, so newton does not use it."""
    from geometry.patterns import load_pattern
    from forward.simulate import simulate
    sim = simulate(load_pattern(EXAMPLE))
    assert sim.result.converged
    assert sim.model.printed_dofs().mean() > 0.9
    assert "printed_relaxations" not in sim.result.timings


def _printed(sheet, t):
    """The sheet with t mm of plastic on the front of every triangle."""
    return Sheet(sheet.points, sheet.triangles, thickness_front=np.full(sheet.n_triangles, t))


def test_the_exact_metric_solve_follows_a_truncated_predictor():
    """simulate_sheet solves with the truncated metric first and finishes with the exact one: the
    result is an equilibrium of the exact model (its gradient below tolerance there), not of
    the truncated one, and its energy differs from the truncated equilibrium's by O(kappa h)."""
    from forward.simulate import simulate_sheet
    from shellfem.model import ShellModel
    sheet = _printed(Sheet.rectangle(30.0, 3.0, 30, 3), 0.3)
    sim = simulate_sheet(sheet, Fabric(stretch=(1.35, 1.0)), Plastic(), [], max_iterations=200)
    levels = sim.result.timings["levels"]
    assert [lv["metric"] for lv in levels] == ["truncated", "exact"] and sim.result.converged
    assert sim.model.quad.thick.any()                       # the returned model is the exact one
    g = sim.model.gradient(sim.result.q)
    free = np.ones(sim.model.n_dofs, bool)
    free[sim.gauge] = False
    assert np.linalg.norm(g[free]) < 1e-6                   # N
    trunc = ShellModel.from_materials(sheet, Fabric(stretch=(1.35, 1.0)), Plastic(), exact_metric=False)
    assert np.linalg.norm(trunc.gradient(sim.result.q)[free]) > 1e3 * np.linalg.norm(g[free])
    assert 0.0 < sim.summary()["max_fibre_kz"] < 0.5


def test_fibre_bending_is_the_measure_the_exact_metric_fades_in():
    """ShellModel.fibre_bending = zmax^2 tr((a^-1 b)^2) per printed triangle, the rho of the
    compiled layer kernel (shellfem.layers.curvature_square), on a random bent state; 0 on bare
    fabric."""
    from shellfem.layers import curvature_square
    from shellfem.model import ShellModel
    base = Sheet.rectangle(10.0, 4.0, 10, 4)
    tf = np.where(np.arange(base.n_triangles) % 3 == 0, 0.0, 0.3)
    sheet = Sheet(base.points, base.triangles, thickness_front=tf)
    model = ShellModel.from_materials(sheet, Fabric(stretch=(1.35, 1.0)), Plastic())
    q = model.initial_state()
    rng = np.random.default_rng(3)
    q[:3 * sheet.n_vertices] += 0.3 * rng.standard_normal(3 * sheet.n_vertices)
    q[3 * sheet.n_vertices:] += 0.2 * rng.standard_normal(model.n_edges)
    rho = model.fibre_bending(q)
    a, b = model.fundamental_forms(q)
    ds, Hs = np.zeros(6), np.zeros((6, 6))
    s = np.array([curvature_square(np.concatenate([a[f], b[f]]), 0, ds, Hs) for f in range(sheet.n_triangles)])
    thick = model.quad.thick
    assert thick.sum() == np.count_nonzero(tf) and rho[thick].min() > 0
    assert rho[thick] == pytest.approx(np.max(model.quad.zspan[thick] ** 2, axis=1) * s[thick], rel=1e-10)
    assert np.all(rho[~thick] == 0)


def test_a_folded_result_is_not_converged(monkeypatch):
    """A state bent past |k z| = 1 on a printed triangle (a fibre at zero length, past the fold
    stop: the Kirchhoff body has folded) is reported as not converged, with the reason."""
    from forward.simulate import simulate_sheet
    from shellfem.model import ShellModel
    monkeypatch.setattr(ShellModel, "fibre_bending", lambda self, q: np.full(self.sheet.n_triangles, 1.44))
    sim = simulate_sheet(_printed(Sheet.rectangle(30.0, 3.0, 30, 3), 0.3), Fabric(stretch=(1.35, 1.0)), Plastic(), [],
                         max_iterations=200)
    assert not sim.result.converged and "folded" in sim.result.reason and "1.20" in sim.result.reason


def test_triangles_held_by_the_fold_stop_are_reported_not_failed(monkeypatch):
    """Between the thin-shell limit |k z| = 0.9 and the fold |k z| = 1 a printed triangle is held
    by the fold stop (shellfem.layers): the state converges, and summary.json's fold_stop says how
    many triangles, how much area and which share of the print are held there."""
    from forward.simulate import simulate_sheet
    from shellfem.model import ShellModel
    real = ShellModel.fibre_bending

    def bent(self, q):                   # the real measure, with two printed triangles held
        rho = real(self, q)
        rho[np.flatnonzero(self.quad.thick)[:2]] = 0.9 ** 2 + 0.01
        return rho
    monkeypatch.setattr(ShellModel, "fibre_bending", bent)
    sheet = _printed(Sheet.rectangle(30.0, 3.0, 30, 3), 0.3)
    sim = simulate_sheet(sheet, Fabric(stretch=(1.35, 1.0)), Plastic(), [], max_iterations=200)
    assert sim.result.converged
    fold = sim.summary()["fold_stop"]
    assert fold["triangles"] == 2 and fold["area_mm2"] == pytest.approx(2 * 0.5, rel=1e-12)
    assert fold["share_of_print"] == pytest.approx(2.0 / sheet.n_triangles, rel=1e-12)
    assert sim.summary()["max_fibre_kz"] == pytest.approx(np.sqrt(0.82), rel=1e-12)


def test_nothing_to_release_converges_and_a_stop_says_why(tmp_path, capsys):
    """A print at stretch 1 (a valid pattern: nothing contracts, the sheet stays flat) ends at
    E ~ 1e-28 N mm; it was reported "NOT converged" (the gauge's 1e-30 N mm round-off read as
    load, then the exact-metric solve's energy floor at 1e-25), exit 1 (issue 19). A run that
    does stop early says why on its one line."""
    p = tmp_path / "flat.toml"
    p.write_text("[fabric]\nrectangle = [20.0, 4.0]\nstretch = 1.0\n[[region]]\n"
                 "polygon = [[0, 0], [20, 0], [20, 4], [0, 4]]\nthickness_mm = 0.3\n[mesh]\nsize_mm = 2.0\n")
    assert main(["simulate", str(p), "-o", str(tmp_path / "s"), "--no-png"]) == 0
    s = json.load(open(tmp_path / "s" / "summary.json"))
    assert s["converged"] and s["energy"] < 1e-12
    capsys.readouterr()
    assert main(["simulate", str(p), "-o", str(tmp_path / "t"), "--no-png", "--max-iterations", "1",
                 "--coarse-levels", "0"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and out[0].startswith("NOT converged (maximum number of iterations reached)"), out


def test_without_the_metric_predictor_every_level_is_exact_and_lands_on_the_same_strip():
    """[solver] metric_predictor = false: no truncated-metric level (timings' levels all "exact",
    nested iteration included), and on a strip whose curl is far from the fold stop the same
    equilibrium as with the predictor (the two energies differ only where the curl is tight)."""
    from forward.simulate import simulate
    raw = {"fabric": {"rectangle": [40.0, 6.0], "stretch": 1.2, "thickness_mm": 0.25},
           "plastic": {"young_modulus_mpa": 72.3, "poisson": 0.5},
           "region": [{"polygon": [[0, 0], [40, 0], [40, 6], [0, 6]], "thickness_mm": 0.3}],
           "mesh": {"size_mm": 1.0}, "solver": {"coarse_levels": 1, "metric_predictor": False},
           "contact": {"enabled": False}}
    pat = parse_pattern(raw)
    assert pat.metric_predictor is False and parse_pattern({**raw, "solver": {}}).metric_predictor is True
    off = simulate(pat)
    assert off.result.converged
    assert [lv["metric"] for lv in off.result.timings["levels"]] == ["exact", "exact"]
    pat.metric_predictor = True
    on = simulate(pat)
    assert [lv["metric"] for lv in on.result.timings["levels"]] == ["truncated", "truncated", "exact"]
    assert off.result.energy == pytest.approx(on.result.energy, rel=1e-6)
    a, b = off.positions - off.positions.mean(0), on.positions - on.positions.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)                   # the best rotation of a onto b (Kabsch)
    r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    assert np.abs(a @ r - b).max() < 1e-4 * np.ptp(b, axis=0).max()


def test_a_simulation_on_one_thread_in_a_worker_has_the_bits_of_two_threads_here():
    """The refinement's workers (shellfem.forked) run on one thread: their results must be the
    serial run's to the last bit (MKL's conditional numerical reproducibility, fixed numba chunks),
    and a Simulation (contact included) must travel back from the worker."""
    from forward.simulate import simulate
    from geometry.patterns import load_pattern
    from shellfem import forked
    if not forked.available():
        pytest.skip("needs fork and two cores")
    here = os.path.join(os.path.dirname(__file__), "..", "examples", "window.toml")
    pat = load_pattern(here)
    mine = simulate(pat)
    theirs = forked.start(simulate, pat).result()
    assert mine.result.converged and theirs.result.converged
    assert mine.result.iterations == theirs.result.iterations
    np.testing.assert_array_equal(mine.result.q, theirs.result.q)
