"""Set-ups of the shell-engine verification cases (mm, N, MPa), shared by the tests
(tests/test_shell_benchmarks.py) and the studies (studies/sze.py, studies/natural_curvature.py,
studies/convergence.py). Their reference answers are in validation.references.

A clamp is a held row of elements: the positions of its vertices and the angles of its
edges (including the edges on the clamped line) are fixed, so the mid-edge normals on
the clamped line stay those of the flat held row. Loads are dead loads
(``ShellModel.external_force``). Load paths are followed with a secant predictor.
"""
from __future__ import annotations

import time

import numpy as np

from shellfem.boundary import gauge_dofs, smooth_perturbation
from shellfem.layers import QuadraticForm, sym_to_mat
from shellfem.kinematics import build_topology
from shellfem.materials import Fabric, Plastic
from shellfem.model import ShellModel
from shellfem.sheet import Sheet
from shellfem.newton import newton
from validation.references import SZE_B, SZE_E, SZE_END_MOMENT, SZE_END_SHEAR, SZE_H, SZE_SLIT, \
    disk_ritz_curvatures, narrow_curvature

# --------------------------------------------------------------------------- meshes


def polar_sheet(r_in: float, r_out: float, n_r: int, n_theta: int, angle: float = 2 * np.pi,
                ghost_rows: int = 0) -> Sheet:
    """Structured annular sector r in [r_in, r_out], theta in [-ghost, angle] (quads split
    along alternating diagonals). ``ghost_rows`` extra element rows of the same angular
    pitch at theta < 0 (a clamp row; they overlap the other end in the plane, which the
    energy does not see)."""
    dt = angle / n_theta
    base = Sheet.rectangle(r_out - r_in, (n_theta + ghost_rows) * dt, n_r, n_theta + ghost_rows)
    r = r_in + base.points[:, 0]
    t = base.points[:, 1] - ghost_rows * dt
    return Sheet(np.column_stack([r * np.cos(t), r * np.sin(t)]), base.triangles)


def polar_coordinates(sheet: Sheet, ghost_angle: float = 0.0):
    """(r, theta) of the sheet's vertices, theta in [-ghost_angle, 2 pi - ghost_angle)."""
    p = sheet.points
    t = np.mod(np.arctan2(p[:, 1], p[:, 0]) + ghost_angle, 2 * np.pi) - ghost_angle
    return np.hypot(p[:, 0], p[:, 1]), t


def disk_sheet(radius: float, n_rings: int) -> Sheet:
    """Structured-ish disk: concentric rings of 6k points (k = 1..n_rings) + centre,
    Delaunay triangulated (near-equilateral triangles, edge ~ radius / n_rings)."""
    from scipy.spatial import Delaunay
    pts = [np.zeros((1, 2))]
    for k in range(1, n_rings + 1):
        a = 2 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
        pts.append(radius * k / n_rings * np.column_stack([np.cos(a), np.sin(a)]))
    p = np.vstack(pts)
    return Sheet(p, Delaunay(p).simplices)


def gmsh_rectangle(width: float, height: float, size: float, seed: int = 0) -> Sheet:
    """Unstructured Frontal-Delaunay triangulation of [0, width] x [0, height] (mm) with
    target edge ``size`` (gmsh); deterministic for a given gmsh version and seed."""
    from geometry.meshing import gmsh_session
    with gmsh_session("rectangle") as gmsh:
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        gmsh.option.setNumber("Mesh.RandomSeed", seed + 1)
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.occ.addRectangle(0, 0, 0, width, height)
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.generate(2)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        types, _, nodes = gmsh.model.mesh.getElements(2)
        tri = np.asarray(nodes[list(types).index(2)], dtype=np.int64).reshape(-1, 3)
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    pts = xyz.reshape(-1, 3)[:, :2]
    used = np.unique(index[tri])
    remap = -np.ones(len(pts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return Sheet(pts[used], remap[index[tri]])


# --------------------------------------------------------------------------- supports


def clamp_free_mask(sheet: Sheet, held_vertices: np.ndarray) -> np.ndarray:
    """Free-DOF mask holding the positions of ``held_vertices`` and the angle of every
    edge whose two ends are held (a clamped row of elements)."""
    n = sheet.n_vertices
    topo = build_topology(sheet.triangles)
    held = np.zeros(n, bool)
    held[held_vertices] = True
    free = np.ones(3 * n + topo.n_edges, bool)
    free[:3 * n].reshape(n, 3)[held] = False
    free[3 * n:] = ~held[topo.edges].all(1)
    return free


def line_loads(points: np.ndarray, total: float) -> np.ndarray:
    """Consistent P1 nodal forces of a uniform line load of resultant ``total`` along the
    polyline through ``points`` (ordered, (k, 2|3))."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    f = np.zeros(len(points))
    f[:-1] += 0.5 * seg
    f[1:] += 0.5 * seg
    return total * f / seg.sum()


def load_path(models, q0: np.ndarray, free: np.ndarray, max_iterations: int = 200, rtol: float = 1e-8,
              gradient_reference: float | None = None, loads=None):
    """Equilibria along a sequence of models (load steps), each Newton solve started from
    the secant prediction of the previous two (scaled by the ratio of load increments when
    the load levels ``loads`` are given). Returns the list of SolveResults; raises
    RuntimeError if a step does not converge (a benchmark must not report a wrong state).
    ``gradient_reference`` (N): scale of the convergence test ||g|| <= rtol * reference
    (default: each step's starting gradient); stiff thin plates (E t ~ 1e6 N/mm) need a
    fixed reference such as the full load, as their round-off floor is ~1e-8 N."""
    q, q_prev, out = q0, None, []
    opts = dict(max_iterations=max_iterations, rtol=rtol, gradient_reference=gradient_reference)
    for k, M in enumerate(models):
        ratio = 1.0 if loads is None or k < 2 else (loads[k] - loads[k - 1]) / (loads[k - 1] - loads[k - 2])
        guess = q if q_prev is None else q + ratio * (q - q_prev)
        r = newton(M, guess, free, **opts)
        if not r.converged:
            r = newton(M, q, free, **opts)     # retry from the last state
        if not r.converged:
            raise RuntimeError(f"load step {k + 1}/{len(models)} did not converge: {r.reason}")
        q_prev, q = q, r.q
        out.append(r)
    return out


# --------------------------------------------------------------------------- Sze et al. (2004)

def cantilever(L: float, nx: int, ny: int = 2, width: float = SZE_B):
    """Strip [0, L] x [0, width] with a clamped row of elements at x in [-L/nx, 0].
    Returns (sheet, free mask, tip vertex indices ordered by y)."""
    dx = L / nx
    sh = Sheet.rectangle(L + dx, width, nx + 1, ny)
    sh = Sheet(sh.points - [dx, 0.0], sh.triangles)
    free = clamp_free_mask(sh, np.flatnonzero(sh.points[:, 0] <= 1e-9))
    tip = np.flatnonzero(np.abs(sh.points[:, 0] - L) < 1e-9)
    return sh, free, tip[np.argsort(sh.points[tip, 1])]


def end_shear(nx: int = 40, steps: int = 8, P_max: float = SZE_END_SHEAR["P_max"]) -> dict:
    """Sze 3.1: cantilever (L = 10, b = 1, h = 0.1, E = 1.2e6, nu = 0) under a transverse
    tip force P. Returns load fractions and tip (-u, w) per step."""
    L = SZE_END_SHEAR["L"]
    sh, free, tip = cantilever(L, nx)
    models = []
    for frac in np.arange(1, steps + 1) / steps:
        M = ShellModel.homogeneous(sh, SZE_E, 0.0, SZE_H)
        f = np.zeros((sh.n_vertices, 3))
        f[tip, 2] = line_loads(sh.points[tip], P_max * frac)
        M.external_force = f
        models.append(M)
    res = load_path(models, models[0].initial_state(), free)
    u, w = [], []
    for M, r in zip(models, res):
        x = M.split(r.q)[0]
        u.append(L - x[tip, 0].mean())
        w.append(x[tip, 2].mean())
    return {"load_fraction": (np.arange(1, steps + 1) / steps).tolist(), "tip_u": u, "tip_w": w,
            "newton_iterations": [r.iterations for r in res], "n_triangles": sh.n_triangles}


def _with_rest_curvature_on(sheet: Sheet, mask: np.ndarray, kappa_xx: float, E: float, nu: float, h: float):
    """Homogeneous shell with rest curvature kappa_xx (1/mm) about y on the masked triangles."""
    curved = ShellModel.homogeneous(sheet, E, nu, h, rest_curvature=[[kappa_xx, 0.0], [0.0, 0.0]])
    flat = ShellModel.homogeneous(sheet, E, nu, h)
    quad = QuadraticForm(sheet.n_triangles)
    quad.add_form(curved.quad, mask)
    quad.add_form(flat.quad, ~mask)
    curved.quad = quad
    return curved


def end_moment(nx: int = 48, steps: int = 16) -> dict:
    """Sze 3.2: cantilever (L = 12) rolled by a tip moment M; a uniform moment on the free
    part has the same potential as the natural curvature -M/EI (nu = 0), which is how it is
    applied. Returns load fractions and tip (-u, w) per step."""
    L, Mmax = SZE_END_MOMENT["L"], SZE_END_MOMENT["M_max"]
    sh, free, tip = cantilever(L, nx)
    EI = SZE_E * SZE_B * SZE_H ** 3 / 12
    inside = sh.points[sh.triangles].mean(1)[:, 0] > 0
    fracs = np.arange(1, steps + 1) / steps
    models = [_with_rest_curvature_on(sh, inside, -f * Mmax / EI, SZE_E, 0.0, SZE_H) for f in fracs]
    res = load_path(models, models[0].initial_state(), free)
    u, w = [], []
    for M, r in zip(models, res):
        x = M.split(r.q)[0]
        u.append(L - x[tip, 0].mean())
        w.append(abs(x[tip, 2].mean()))
    return {"load_fraction": fracs.tolist(), "tip_u": u, "tip_w": w,
            "newton_iterations": [r.iterations for r in res], "n_triangles": sh.n_triangles}


def load_fractions(steps: int, first: float = 0.02) -> np.ndarray:
    """``steps`` load levels in (0, 1], geometric from ``first`` to 1: small steps where the
    flat plate's response is most nonlinear."""
    return np.geomspace(first, 1.0, steps)


def slit_annular_plate(n_r: int = 6, n_theta: int = 48, steps: int = 12, q_max: float = SZE_SLIT["q_max"]) -> dict:
    """Sze 3.3: annular plate R_i = 6, R_o = 10, t = 0.03, E = 21e6, nu = 0, slit along
    theta = 0; the edge theta = 0 is clamped (one held row of elements at theta < 0), the
    edge theta = 2 pi carries a transverse line force q per unit length (resultant
    q (R_o - R_i)). Structured polar mesh n_r x n_theta quads split in two.
    Returns load fractions, w_A (inner corner) and w_B (outer corner) per step."""
    c = SZE_SLIT
    dt = 2 * np.pi / n_theta
    sh = polar_sheet(c["r_in"], c["r_out"], n_r, n_theta, ghost_rows=1)
    # vertex k of Sheet.rectangle has grid index (i, j) = divmod(k, n_theta + 2); j = 0, 1 are the clamp row
    i, j = np.divmod(np.arange(sh.n_vertices), n_theta + 2)
    free = clamp_free_mask(sh, np.flatnonzero(j <= 1))
    edge = np.flatnonzero(j == n_theta + 1)
    edge = edge[np.argsort(i[edge])]                                     # inner -> outer
    A, B = edge[0], edge[-1]
    fracs = load_fractions(steps)
    models = []
    for f in fracs:
        M = ShellModel.homogeneous(sh, c["E"], c["nu"], c["t"])
        F = np.zeros((sh.n_vertices, 3))
        F[edge, 2] = line_loads(sh.points[edge], f * q_max * (c["r_out"] - c["r_in"]))
        M.external_force = F
        models.append(M)
    # converged when the residual force is < 1e-5 of the full load: the solver stalls at
    # ~1e-6 of it on some steps (E t = 6.3e5 N/mm against a 3.2 N load)
    res = load_path(models, models[0].initial_state(), free, rtol=1e-5,
                    gradient_reference=float(np.linalg.norm(models[-1].external_force)), loads=fracs)
    wA, wB = [], []
    for M, r in zip(models, res):
        x = M.split(r.q)[0]
        wA.append(float(x[A, 2]))
        wB.append(float(x[B, 2]))
    return {"load_fraction": fracs.tolist(), "q": (fracs * q_max).tolist(), "w_A": wA, "w_B": wB,
            "newton_iterations": [r.iterations for r in res], "mesh": f"{n_r} x {n_theta} quads split, +1 clamp row",
            "n_triangles": sh.n_triangles, "clamp_angle_rad": dt}


# --------------------------------------------------------------------------- natural-curvature disk


def quadric_curvatures(x: np.ndarray) -> np.ndarray:
    """Principal curvatures (1/mm, descending) at the centroid of a shallow point patch x
    (k, 3): least-squares fit w = c + a u + b v + (A u^2 + 2 B uv + C v^2) / 2 in the frame
    of the patch's principal axes (w along the smallest), eigenvalues of [[A, B], [B, C]]."""
    y = x - x.mean(0)
    _, _, Vt = np.linalg.svd(y, full_matrices=False)
    u, v, w = (y @ Vt.T).T
    G = np.column_stack([np.ones_like(u), u, v, 0.5 * u * u, u * v, 0.5 * v * v])
    c = np.linalg.lstsq(G, w, rcond=None)[0]
    return np.linalg.eigvalsh([[c[3], c[4]], [c[4], c[5]]])[::-1]


def natural_curvature_disk(kappa0_R2_over_h: float, *, radius: float = 10.0, h: float = 0.1, nu: float = 0.3,
                           E: float = 1000.0, n_rings: int = 10, seed: int = 0) -> dict:
    """Free disk (radius, thickness h in mm) with rest curvature kappa0 * I, started from a
    cylinder z = kappa0 x^2 / 2 plus a seeded smooth perturbation (1 % of the size), so that
    both outcomes (spherical, cylindrical) are reached from the same kind of start. Returns
    the principal curvatures (|k|max, |k|min) / kappa0 of the least-squares quadric through
    the deformed vertices within R/2 of the centre, and the Ritz prediction."""
    kappa0 = kappa0_R2_over_h * h / radius ** 2
    sh = disk_sheet(radius, n_rings)
    M = ShellModel.homogeneous(sh, E, nu, h, rest_curvature=kappa0 * np.eye(2))
    q = M.initial_state()
    x, _ = M.split(q)
    x[:, 2] += 0.5 * kappa0 * sh.points[:, 0] ** 2 + smooth_perturbation(sh.points, seed, 0.01 * 2 * radius)
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, np.int64))] = False
    r = newton(M, q, free, max_iterations=400)
    if not r.converged:
        raise RuntimeError(f"disk kappa0 R^2/h = {kappa0_R2_over_h}: {r.reason}")
    inner = np.hypot(*sh.points.T) < 0.5 * radius
    kmax, kmin = np.sort(np.abs(quadric_curvatures(M.split(r.q)[0][inner])))[::-1]
    ritz = disk_ritz_curvatures(kappa0_R2_over_h, nu)
    kmax, kmin = float(kmax), float(kmin)
    return {"kappa0_R2_over_h": kappa0_R2_over_h, "k_max_over_kappa0": kmax / kappa0,
            "k_min_over_kappa0": kmin / kappa0, "ratio": kmin / kmax,
            "ritz_k_max_over_kappa0": ritz[0], "ritz_k_min_over_kappa0": ritz[1],
            "newton_iterations": r.iterations, "n_triangles": sh.n_triangles}


# --------------------------------------------------------------------------- wide bilayer sheet


def bilayer_roll(length: float, width: float, size: float, stretch: float = 1.05, plastic_thickness: float = 0.3,
                 fabric=None, plastic=None, seed: int = 0) -> dict:
    """A rectangle [0, length] x [0, width] fully covered by front plastic, released from a
    cylinder about the x axis (z = kappa_plate y^2 / 2, plus a seeded 1 % perturbation), so
    that it rolls about the x axis. Returns the median principal curvatures k_max, k_min
    (1/mm, > 0) of the triangles in the middle third of the length (every y), the plate and
    narrow values of shellfem.strip and sqrt(R h) (R = 1 / plate curvature, h = total
    thickness). The interior approaches the plate value as the axis length grows
    (studies/natural_curvature.py: deficit 6.7 % at 40 mm, 0.6 % at 120 mm)."""
    from shellfem.strip import strip_curvature
    fabric = fabric or Fabric(stretch=stretch)
    plastic = plastic or Plastic()
    nx, ny = max(2, int(round(length / size))), max(2, int(round(width / size)))
    sh = Sheet.rectangle(length, width, nx, ny)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, plastic_thickness))
    args = dict(plastic_poisson=plastic.poisson, fabric_poisson=fabric.poisson)
    ratio = plastic.young_modulus / fabric.young_modulus
    s = fabric.stretch[0]
    k_plate = float(strip_curvature(plastic_thickness, fabric.thickness, s, ratio, mode="plate", **args))
    k_narrow = float(strip_curvature(plastic_thickness, fabric.thickness, s, ratio, **args))
    M = ShellModel.from_materials(sh, fabric, plastic, gravity=False)
    q = M.initial_state()
    x, _ = M.split(q)
    x[:, 2] -= 0.5 * k_plate * (sh.points[:, 1] - width / 2) ** 2       # front plastic bends towards -z
    x[:, 2] += smooth_perturbation(sh.points, seed, 0.01 * max(length, width))
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, np.int64))] = False
    r = newton(M, q, free, max_iterations=400)
    if not r.converged:
        raise RuntimeError(f"bilayer roll {length} x {width}: {r.reason}")
    k, _, _ = M.curvatures(r.q)
    c = sh.points[sh.triangles].mean(1)
    mid = np.abs(c[:, 0] - length / 2) < length / 6
    ka = np.sort(np.abs(k[mid]), axis=1)
    x = M.split(r.q)[0]
    return {"length": length, "width": width, "k_max": float(np.median(ka[:, 1])),
            "k_min": float(np.median(ka[:, 0])), "k_plate": k_plate, "k_narrow": k_narrow,
            "sqrt_Rh": float(np.sqrt((fabric.thickness + plastic_thickness) / k_plate)),
            "newton_iterations": r.iterations, "n_triangles": sh.n_triangles,
            "extent": (x.max(0) - x.min(0)).tolist()}


# --------------------------------------------------------------------------- released bilayer sheets (mesh convergence)
#
# Every release starts from the same smooth guess on every mesh: the printed sheet wrapped on a
# sphere of curvature 1/2 of the closed-form narrow-strip value, bending towards the fabric (-z).
# A flat start can end in a second, stable state of higher energy, and a convergence study must
# compare the same branch on every mesh.


def cartesian_forms(sheet: Sheet, a: np.ndarray, b: np.ndarray):
    """Edge-basis fundamental forms (m, 3) -> (m, 2, 2) matrices in printed x, y."""
    P = sheet.points[sheet.triangles]
    Ei = np.linalg.inv(np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], 2))
    to_xy = lambda s: np.einsum("mji,mjk,mkl->mil", Ei, sym_to_mat(s), Ei)   # noqa: E731
    return to_xy(a), to_xy(b)


def triangle_areas(sheet: Sheet) -> np.ndarray:
    P = sheet.points[sheet.triangles]
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def sphere_start(points: np.ndarray, kappa: float) -> np.ndarray:
    """Printed points (n, 2) wrapped isometrically along x onto a sphere of curvature kappa
    (1/mm) centred below the sheet's centre (-z): x -> longitude, y -> latitude."""
    c = 0.5 * (points.min(0) + points.max(0))
    R = 1.0 / kappa
    psi, phi = (points[:, 0] - c[0]) / R, (points[:, 1] - c[1]) / R
    return np.column_stack([R * np.cos(phi) * np.sin(psi), R * np.sin(phi), R * (np.cos(phi) * np.cos(psi) - 1)])


def release(sheet: Sheet, fabric: Fabric, plastic: Plastic, kappa_start: float, seed: int = 0):
    """Free equilibrium from sphere_start(kappa_start) + a seeded 0.1 % perturbation.
    Returns (model, SolveResult); raises RuntimeError if not converged."""
    M = ShellModel.from_materials(sheet, fabric, plastic, gravity=False)
    q = M.initial_state()
    x, _ = M.split(q)
    size = float(np.linalg.norm(np.ptp(sheet.points, 0)))
    x[:] = sphere_start(sheet.points, kappa_start)
    x[:, 2] += smooth_perturbation(sheet.points, seed, 1e-3 * size)
    free = np.ones(M.n_dofs, bool)
    free[gauge_dofs(x, np.zeros(0, np.int64))] = False
    r = newton(M, q, free, max_iterations=400)
    if not r.converged:
        raise RuntimeError(f"release of a {sheet.n_triangles}-triangle sheet: {r.reason}")
    return M, r


def strip_case(size: float, length: float = 40.0, width: float = 2.0, stretch: float = 1.05,
               plastic_thickness: float = 0.3, seed: int = 0) -> dict:
    """Released free bilayer strip on a Gmsh mesh of target edge ``size``: longitudinal
    curvature (1/mm, > 0 when concave on the fabric side) area-averaged over the middle half."""
    sh = gmsh_rectangle(length, width, size)
    sh = Sheet(sh.points, sh.triangles, thickness_front=np.full(sh.n_triangles, plastic_thickness))
    fabric, plastic = Fabric(stretch=stretch), Plastic()
    t0 = time.perf_counter()
    M, r = release(sh, fabric, plastic, 0.5 * narrow_curvature(fabric, plastic, plastic_thickness), seed)
    A, B = cartesian_forms(sh, *M.fundamental_forms(r.q))
    c = sh.points[sh.triangles].mean(1)
    mid = np.abs(c[:, 0] - length / 2) < length / 4
    w = triangle_areas(sh)[mid]
    kx = -B[mid, 0, 0] / A[mid, 0, 0]
    return {"size_mm": size, "n_triangles": sh.n_triangles, "curvature_per_mm": float(np.sum(w * kx) / w.sum()),
            "newton_iterations": r.iterations, "seconds": round(time.perf_counter() - t0, 2)}


def gradient_case(size: float, length: float = 40.0, width: float = 3.0, t0: float = 0.15, t1: float = 0.45,
                  stretch: float = 1.05, seed: int = 0):
    """Released free sheet with plastic thickness t0 + (t1 - t0) x / length (per triangle at
    its centroid) on a Gmsh mesh of target edge ``size``. Returns (sheet, deployed positions, info)."""
    sh = gmsh_rectangle(length, width, size)
    cx = sh.points[sh.triangles].mean(1)[:, 0]
    sh = Sheet(sh.points, sh.triangles, thickness_front=t0 + (t1 - t0) * cx / length)
    tic = time.perf_counter()
    fabric, plastic = Fabric(stretch=stretch), Plastic()
    M, r = release(sh, fabric, plastic, 0.5 * narrow_curvature(fabric, plastic, 0.5 * (t0 + t1)), seed)
    x = M.split(r.q)[0]
    tip = x[np.argmax(sh.points[:, 0])] - x[np.argmin(sh.points[:, 0])]
    return sh, x, {"size_mm": size, "n_triangles": sh.n_triangles, "end_to_end_mm": float(np.linalg.norm(tip)),
                   "newton_iterations": r.iterations, "seconds": round(time.perf_counter() - tic, 2)}
