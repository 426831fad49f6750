"""Inverse design, seed chapter 5: a target surface -> a printable ribbon pattern (`selfshape design`).

    design(V, F)            arrays in, a Design record out (no files)
    design_file(path, dir)  the CLI verb: writes pattern.toml, flat.vtu, front/back.gcode,
                            pattern.png, report.json (and with verify deployed.vtu, verify.png)

Stages (times in Design.times / report.json "stages_s"):
 1. check (disk topology, one-line errors), centre and scale to a bounding-box diagonal
    (default 110 mm), Loop-refine until the mean edge is <= ``edge_mm`` (stripes of period
    2 mu2 >= 7.8 mm need several edges per period; the seed's meshes had 40k-160k faces);
 2. principal curvatures and the Knoppel 2013 line field (seed lambda);
 3. flattening with bounded directional stretch (geometry.flattening, bounds Sec. 5.3.4 from
    Eq. 5.15). Stop rule as the seed states it (Sec. 5.3.4): the *average* change of sigma1
    and of sigma2 between iterations below 1e-6, i.e. mean |d sigma| over the faces (flatten
    stop="mean"; the alternative ||d sigma||_2 / m is sqrt(m) times looser). Initialisation
    (seed: Tutte + SLIM): on the unrefined mesh Tutte + 2 SLIM iterations and the bounded
    flattening there, prolongated to the refined mesh (midpoint upsampling of the flat
    positions: same connectivity as Loop) as the start of the fine solve; without refinement,
    Tutte + 2 SLIM iterations on the mesh itself. Measured on the saddle at 131k faces under
    the seed's rule: Tutte + 0 SLIM needs 718 local/global iterations (60 s), + 2 SLIM 77
    iterations (but SLIM itself costs 4 s per iteration), coarse-to-fine 65 (+ 1014 cheap
    ones on the 2k-face mesh, 0.7 s);
 4. ribbon layout (inverse.layout: Eq. 5.15 spacing, two stripe fields, staggered dashes,
    clipping, trimming > 25 deg, front/back split by the sign of the target normal curvature
    along the ribbons, pieces < 2 mm dropped), stretches clamped into the bounds first, on the
    coarsest hierarchy level with edges <= ``layout_edge_mm`` (the stripes need a few edges per
    period, not the flattening's resolution); then the ribbons are kept ``gap_mm`` apart and
    inside the outline (`separate_ribbons`) so that the pattern meshes without slivers;
 5. thickness per ribbon from the curvature law (inverse.thickness_law) at the ribbon's mean
    |kappa| and transverse spacing mu2, rounded to layer-height multiples.

Units: mm, 1/mm; the flat pattern is in printed (pre-stretched) mm.
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from shellfem.errors import SelfshapeError

RIBBON_LENGTH_MM, RIBBON_WIDTH_MM = 15.0, 1.5
#: Every file design_file may write (removed from the output directory before a new run writes).
OUTPUTS = ("report.json", "pattern.toml", "flat.vtu", "front.gcode", "back.gcode", "pattern.png", "deployed.vtu",
           "verify.png")


# ----------------------------------------------------------------------------- record
@dataclass
class Design:
    """Everything the pipeline computed (mm). V, F: scaled and refined target; V_input, F_input:
    the scaled input before refinement; curvature, field: geometry.curvature / fields records;
    flat: geometry.flattening.FlatResult; kappa1 (m,): signed target normal curvature along the
    ribbon direction (> 0: front); outline (k, 2): flattened boundary polygon; ribbons:
    geometry.elements.Ribbon list with thickness_mm and side; thickness_info: clamp counts per
    side; times: seconds per stage."""
    V: np.ndarray
    F: np.ndarray
    V_input: np.ndarray
    F_input: np.ndarray
    curvature: object
    field: object
    flat: object
    kappa1: np.ndarray
    outline: np.ndarray
    ribbons: list
    stretch: float
    bounds: tuple
    refine_levels: int
    layout_levels: int = 0
    lam: float = 0.0
    stop: str = "mean"
    thickness_info: dict = field(default_factory=dict)
    law_source: str = ""
    law_plastic_mpa: float | None = None     # the plastic modulus the law holds for (MPa), if it says
    times: dict = field(default_factory=dict)
    cpu_times: dict = field(default_factory=dict)
    coarse_iterations: int = 0
    separation: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- stages
def refine_levels_for_edge(V, F, edge_mm: float, max_faces: int = 600_000) -> int:
    """Loop levels (each halves the edges, x4 faces) until the mean edge is <= edge_mm, at most
    while the face count stays <= max_faces."""
    e = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2).mean()
    lev = 0
    while e > edge_mm and len(F) * 4 ** (lev + 1) <= max_faces:
        e *= 0.5
        lev += 1
    return lev


def normal_curvature_along(curv, dirs: np.ndarray) -> np.ndarray:
    """Euler's formula per face: k1 cos^2 + k2 sin^2 of the angle between dirs (m, 3) and d1."""
    d = dirs / np.linalg.norm(dirs, axis=1)[:, None]
    c2 = np.einsum("ij,ij->i", d, curv.face_d1) ** 2
    return curv.face_k1 * c2 + curv.face_k2 * (1.0 - c2)


def boundary_polygon(uv: np.ndarray, F: np.ndarray, simplify_mm: float = 0.02) -> np.ndarray:
    """The flat mesh's boundary loop as a simple polygon (k, 2), counter-clockwise, simplified
    within ``simplify_mm``; SelfshapeError if it self-intersects (a flipped flattening)."""
    import igl
    import shapely

    loop = igl.boundary_loop(np.ascontiguousarray(F, dtype=np.int64))
    poly = shapely.Polygon(uv[loop])
    if not poly.is_valid:
        raise SelfshapeError(f"flattening: the flat boundary self-intersects ({shapely.is_valid_reason(poly)})")
    if simplify_mm > 0:
        simple = poly.simplify(simplify_mm, preserve_topology=True)
        if simple.is_valid and simple.geom_type == "Polygon":
            poly = simple
    poly = shapely.geometry.polygon.orient(poly, 1.0)
    return np.asarray(poly.exterior.coords)[:-1]


def flatten_multilevel(V0, F0, levels, V, F, dir1, bounds, lam, curv0=None, stop="mean", max_iter=1000):
    """Bounded flattening of the refined mesh (V, F) started from the flattening of the coarse
    mesh (V0, F0) prolongated by midpoint upsampling (levels = Loop levels between them).
    Returns (FlatResult, coarse FlatResult or None, wall and CPU seconds of the coarse stage)."""
    import igl

    from geometry.curvature import principal_curvature
    from geometry.fields import curvature_line_field
    from geometry.flattening import flatten

    if levels == 0:
        return flatten(V, F, dir1, bounds, stop=stop, slim_iterations=2, max_iter=max_iter), None, 0.0, 0.0
    t0, p0 = time.perf_counter(), time.process_time()
    c0 = principal_curvature(V0, F0) if curv0 is None else curv0
    lf0 = curvature_line_field(V0, F0, lam, c0)
    coarse = flatten(V0, F0, lf0.face_dirs, bounds, stop=stop, slim_iterations=2)
    uv3 = np.column_stack([coarse.uv, np.zeros(len(coarse.uv))])
    uv = igl.upsample(uv3, np.ascontiguousarray(F0, dtype=np.int64), int(levels))[0][:, :2]
    t1, c1 = time.perf_counter() - t0, time.process_time() - p0
    fine = flatten(V, F, dir1, bounds, stop=stop, uv_init=uv, isometric_iterations=0, max_iter=max_iter)
    return fine, coarse, t1, c1


def assign_thickness(ribbons, law, layer_height_mm: float) -> dict:
    """Set ribbon.thickness_mm from the law at (meta kappa_mean_abs, meta mu2, side); returns the
    clamp counts per side."""
    from inverse.thickness_law import thickness_for_curvature

    info = {}
    for side in ("front", "back"):
        idx = [i for i, r in enumerate(ribbons) if r.side == side]
        if not idx:
            continue
        k = np.array([ribbons[i].meta["kappa_mean_abs"] for i in idx])
        mu2 = np.array([ribbons[i].meta["mu2"] for i in idx])
        t, inf = thickness_for_curvature(law, k, mu2, side, layer_height_mm)
        for i, ti in zip(idx, t):
            ribbons[i].thickness_mm = float(round(ti, 6))
        info[side] = inf
    return info


def clean_path(p: np.ndarray, min_seg: float) -> np.ndarray:
    """Drop interior points closer than ``min_seg`` to the previous kept point, and the last
    interior point if the final segment would be shorter than ``min_seg``: a tiny end segment
    turns the flat end of the printed ribbon askew (and the mesh gets slivers). (k, 2)"""
    if len(p) <= 2:
        return p
    keep = [0]
    for i in range(1, len(p) - 1):
        if np.hypot(*(p[i] - p[keep[-1]])) >= min_seg:
            keep.append(i)
    if len(keep) > 1 and np.hypot(*(p[-1] - p[keep[-1]])) < min_seg:
        keep.pop()
    keep.append(len(p) - 1)
    return p[keep]


def _simplify_paths(ribbons, tol_mm: float):
    import shapely

    if not ribbons:
        return
    idx = np.repeat(np.arange(len(ribbons)), [len(r.path) for r in ribbons])
    lines = shapely.simplify(shapely.linestrings(np.concatenate([r.path for r in ribbons]), indices=idx), tol_mm)
    for r, ln in zip(ribbons, lines):
        p = clean_path(np.asarray(shapely.get_coordinates(ln)), 0.25)
        if len(p) >= 2:
            r.path = p


def coarsen_for_layout(F0, levels: int, coarse_levels: int, uv, area, dir1, sigma1, sigma2, kappa1):
    """The flat mesh and per-face fields at Loop level ``coarse_levels`` <= ``levels`` of the
    hierarchy built from F0. Loop/midpoint subdivision keep the coarser vertices first and put
    the 4^k children of face f at rows f 4^k .. (f + 1) 4^k - 1, so the coarse flat mesh is
    uv[:n_coarse] and per-face fields are area-weighted means over the children (the line
    direction dir1 through its doubled angle, sign-free). Returns (uv, F, dir1, sigma1,
    sigma2, kappa1) at the coarse level."""
    import igl

    F0 = np.ascontiguousarray(F0, dtype=np.int64)
    if coarse_levels == levels:
        return uv, None, dir1, sigma1, sigma2, kappa1
    if coarse_levels > 0:
        Fc = igl.upsample(np.zeros((int(F0.max()) + 1, 3)), F0, int(coarse_levels))[1]
    else:
        Fc = F0
    k = 4 ** (levels - coarse_levels)
    w = area.reshape(len(Fc), k)
    wsum = w.sum(axis=1)
    mean = lambda v: (w * v.reshape(len(Fc), k)).sum(axis=1) / wsum  # noqa: E731
    ang2 = 2.0 * np.arctan2(dir1[:, 1], dir1[:, 0])
    a = 0.5 * np.arctan2(mean(np.sin(ang2)), mean(np.cos(ang2)))
    return (uv[: int(Fc.max()) + 1], Fc, np.column_stack([np.cos(a), np.sin(a)]), mean(sigma1), mean(sigma2),
            mean(kappa1))


def _longest_line(geom):
    """The longest LineString of a (multi)line geometry (None if there is none)."""
    import shapely

    parts = [g for g in shapely.get_parts(shapely.line_merge(geom) if geom.geom_type == "MultiLineString" else geom)
             if g.geom_type == "LineString" and not g.is_empty]
    return max(parts, key=lambda g: g.length) if parts else None


def separate_ribbons(ribbons, outline, gap_mm: float = 0.5, min_length: float = 2.0):
    """Make the printed ribbons meshable: every ribbon polygon (flat ends) at least ``gap_mm``
    inside the outline and ``gap_mm`` away from every other ribbon (no overlaps, no slivers).

    Centre lines are clipped to the outline eroded by w/2 + gap (then the whole ribbon, which lies
    within w/2 of its centre line, is >= gap inside). Where two ribbons come closer than the gap
    (dashes that meet end to end where sigma1 = 1, stripes merging near singularities), the
    ribbon processed later (shorter ones later) loses the part of its centre line within
    w/2 + gap of the other ribbon; only the longest remaining piece is kept. Pieces shorter than
    ``min_length`` are dropped. Returns (ribbons, {"clipped", "trimmed", "dropped"})."""
    import shapely
    from shapely.geometry import LineString

    from geometry.patterns import ribbon_polygon

    region = shapely.Polygon(outline)
    stats = {"clipped": 0, "trimmed": 0, "dropped": 0}
    inner = {}
    out = []
    for r in ribbons:
        w = float(r.width_mm)
        if w not in inner:
            inner[w] = region.buffer(-(w / 2 + gap_mm))
            shapely.prepare(inner[w])
        line = LineString(r.path)
        if not inner[w].contains(line):
            line = _longest_line(line.intersection(inner[w]))
            stats["clipped"] += 1
            if line is None or line.length < min_length:
                stats["dropped"] += 1
                continue
            r.path = clean_path(np.asarray(line.coords), 0.25)
        out.append(r)
    if not out:
        return out, stats
    polys = np.array([ribbon_polygon(r.path, r.width_mm) for r in out], dtype=object)
    tree = shapely.STRtree(polys)
    a, b = tree.query(polys, predicate="dwithin", distance=gap_mm)
    conflict = np.zeros(len(out), bool)
    conflict[a[a != b]] = True
    lengths = np.array([LineString(r.path).length for r in out])
    order = np.lexsort((np.arange(len(out)), -lengths))
    kept = np.zeros(len(out), bool)
    for i in order:
        if conflict[i]:
            near = tree.query(polys[i], predicate="dwithin", distance=gap_mm)
            near = near[kept[near] & (near != i)]
            if len(near):
                r = out[i]
                block = shapely.union_all([p.buffer(r.width_mm / 2 + gap_mm) for p in polys[near]])
                line = _longest_line(LineString(r.path).difference(block))
                stats["trimmed"] += 1
                if line is None or line.length < min_length:
                    stats["dropped"] += 1
                    continue
                r.path = clean_path(np.asarray(line.coords), 0.25)
                polys[i] = ribbon_polygon(r.path, r.width_mm)
        kept[i] = True
    result = [r for i, r in enumerate(out) if kept[i]]
    for i, r in enumerate(result):
        r.label = f"ribbon[{i}]"
    return result, stats


def design(V, F, *, stretch: float = 1.6, diagonal_mm: float | None = 110.0, printer=None, lam: float = 0.0,
           thickness_law=None, edge_mm: float = 1.0, max_faces: int = 600_000, bounds=None,
           ribbon_length: float = RIBBON_LENGTH_MM, ribbon_width: float = RIBBON_WIDTH_MM, seed: int = 0,
           stop: str = "mean", flatten_max_iter: int = 1000, gap_mm: float = 0.5,
           layout_edge_mm: float | None = 2.0,
           where: str = "target") -> Design:
    """Inverse design of a disk-topology target (V (n, 3), F (m, 3)); see the module doc.

    stretch: fabric pre-stretch s (> 1). diagonal_mm: scale the target to this bounding-box
    diagonal (None: V is already in mm). printer: inverse.printer.Printer (layer height for
    the thickness). lam: the seed's field lambda (<= 0, 1/mm^2). thickness_law: a
    ThicknessLaw, a CSV path or None (the shipped law). edge_mm: refine until the mean edge
    is below it (None: no refinement). bounds: (s1min, s1max, s2min, s2max), default
    stretch_bounds(stretch, ribbon_length, ribbon_width). stop, flatten_max_iter: the
    flattening's stop rule ("mean": the seed's, "norm": ||d sigma||_2 / m) and its iteration cap
    on the fine mesh (reported as flatten_converged = false when reached). gap_mm: minimum distance between
    printed ribbons and to the outline (`separate_ribbons`). layout_edge_mm: the ribbon layout
    runs on the coarsest level of the refinement hierarchy whose mean edge is below it (None:
    on the flattening's mesh)."""
    from geometry.curvature import principal_curvature
    from geometry.fields import curvature_line_field
    from geometry.flattening import stretch_bounds
    from geometry.target import check_disk, normalize, refine
    from inverse.layout import ribbon_layout
    from inverse.printer import Printer
    from inverse.thickness_law import ThicknessLaw, load_thickness_law

    times, cpu = {}, {}
    t, c = time.perf_counter(), time.process_time()

    def lap(name):
        nonlocal t, c
        now, cnow = time.perf_counter(), time.process_time()
        times[name], cpu[name] = now - t, cnow - c
        t, c = now, cnow

    if not (isinstance(stretch, (int, float)) and math.isfinite(stretch) and stretch > 1.0):
        raise SelfshapeError(f"design: fabric stretch must be a number > 1, got {stretch!r}")
    printer = Printer() if printer is None else printer
    law = thickness_law if isinstance(thickness_law, ThicknessLaw) else load_thickness_law(thickness_law)
    bounds = stretch_bounds(stretch, ribbon_length, ribbon_width) if bounds is None else tuple(bounds)
    V0, F0 = check_disk(V, F, where=where)
    V0 = normalize(V0, diagonal_mm)
    total_area = float(0.5 * np.linalg.norm(np.cross(V0[F0[:, 1]] - V0[F0[:, 0]], V0[F0[:, 2]] - V0[F0[:, 0]]),
                                            axis=1).sum())
    if not total_area > 0:
        raise SelfshapeError(f"{where}: zero total area")
    levels = 0 if edge_mm is None else refine_levels_for_edge(V0, F0, edge_mm, max_faces)
    Vf, Ff = refine(V0, F0, levels) if levels else (V0, F0)
    Ff = np.ascontiguousarray(Ff, dtype=np.int64)
    lap("load_refine")

    curv = principal_curvature(Vf, Ff)
    lap("curvature")
    lf = curvature_line_field(Vf, Ff, lam, curv)
    lap("field")
    flat, coarse, t_coarse, c_coarse = flatten_multilevel(V0, F0, levels, Vf, Ff, lf.face_dirs, bounds, lam,
                                                          stop=stop, max_iter=flatten_max_iter)
    times["flatten_coarse"] = t_coarse
    lap("flatten")
    times["flatten"] -= t_coarse
    cpu["flatten_coarse"], cpu["flatten"] = c_coarse, cpu["flatten"] - c_coarse
    if flat.flipped:
        raise SelfshapeError(f"{where}: the flattening has {flat.flipped} flipped triangles; "
                             f"the surface cannot be flattened within the stretch bounds")

    kappa1 = normal_curvature_along(curv, lf.face_dirs)
    outline = boundary_polygon(flat.uv, Ff)
    s1 = np.clip(flat.sigma1, bounds[0], bounds[1])
    s2 = np.clip(flat.sigma2, bounds[2], bounds[3])
    # the stripes need a few edges per period (2 mu2 >= 7.8 mm), not the flattening's resolution
    lay_levels = levels
    if layout_edge_mm is not None:
        e0 = float(np.linalg.norm(V0[F0[:, [1, 2, 0]]] - V0[F0], axis=2).mean())
        while lay_levels > 0 and e0 / 2 ** (lay_levels - 1) <= layout_edge_mm:
            lay_levels -= 1
    area = 0.5 * np.linalg.norm(np.cross(Vf[Ff[:, 1]] - Vf[Ff[:, 0]], Vf[Ff[:, 2]] - Vf[Ff[:, 0]]), axis=1)
    uv_l, F_l, d_l, s1_l, s2_l, k_l = coarsen_for_layout(F0, levels, lay_levels, flat.uv, area, flat.dir1,
                                                         s1, s2, kappa1)
    ribbons = ribbon_layout(uv_l, Ff if F_l is None else F_l, d_l, s1_l, s2_l, k_l, stretch, outline=outline,
                            ribbon_length=ribbon_length, ribbon_width=ribbon_width, seed=seed)
    if not ribbons:
        raise SelfshapeError(f"{where}: the layout produced no ribbons (surface too small for "
                             f"{ribbon_length:g} x {ribbon_width:g} mm ribbons?)")
    _simplify_paths(ribbons, 0.01)
    ribbons, sep = separate_ribbons(ribbons, outline, gap_mm, min_length=2.0)
    if not ribbons:
        raise SelfshapeError(f"{where}: no ribbon is left after keeping them {gap_mm:g} mm apart")
    lap("layout")
    tinfo = assign_thickness(ribbons, law, printer.layer_height_mm)
    lap("thickness")
    return Design(V=Vf, F=Ff, V_input=V0, F_input=F0, curvature=curv, field=lf, flat=flat, kappa1=kappa1,
                  outline=outline, ribbons=ribbons, stretch=float(stretch), bounds=tuple(bounds),
                  refine_levels=levels, layout_levels=lay_levels, lam=float(lam), stop=stop, thickness_info=tinfo,
                  law_source=law.source, law_plastic_mpa=law.plastic_young_modulus_mpa,
                  times=times, cpu_times=cpu, separation=sep,
                  coarse_iterations=coarse.iterations if coarse is not None else 0)


# ----------------------------------------------------------------------------- outputs
def pattern_dict(d: Design, *, fabric=None, plastic=None, mesh_size_mm: float = 2.0,
                 mesh_across: float | None = None, seed: int = 0, target_name: str = "",
                 max_iterations: int | None = None, metric_floor: float | None = None) -> dict:
    """The pattern TOML (INTERFACE.md) of a design as a dict: [fabric] outline = flat boundary,
    [[ribbon]] per ribbon, [plastic] (default: the modulus the thickness law states), [mesh],
    [solver] (seed, and max_iterations when given: the Newton cap `selfshape simulate` uses for
    this pattern; metric_floor when given: shellfem.solver.lm_metric), [meta] provenance."""
    from shellfem.materials import Fabric, Plastic

    fab = fabric or Fabric()
    # the plastic the thickness law was computed for, so the pattern simulates what was designed
    pla = plastic or (Plastic(young_modulus=d.law_plastic_mpa) if d.law_plastic_mpa else Plastic())
    r4 = lambda a: np.round(np.asarray(a, float), 4).tolist()  # noqa: E731
    return {
        "meta": {"generator": "selfshape design (inverse.pipeline)", "target": target_name,
                 "stretch_bounds": list(d.bounds), "thickness_law": os.path.basename(d.law_source)},
        "fabric": {"outline": r4(d.outline), "stretch": d.stretch, "thickness_mm": fab.thickness,
                   "model": fab.model, "young_modulus_mpa": fab.young_modulus, "poisson": fab.poisson,
                   "bending_stiffness_nmm": fab.bending_stiffness},
        "plastic": {"young_modulus_mpa": pla.young_modulus, "poisson": pla.poisson,
                    "rest_curvature_per_mm": pla.rest_curvature},
        "ribbon": [{"path": r4(r.path), "width_mm": float(r.width_mm), "thickness_mm": float(r.thickness_mm),
                    "side": r.side} for r in d.ribbons],
        "mesh": {"size_mm": float(mesh_size_mm), **({} if mesh_across is None else {"across": float(mesh_across)})},
        "solver": {"seed": int(seed), **({} if max_iterations is None else {"max_iterations": int(max_iterations)}),
                   **({} if metric_floor is None else {"metric_floor": float(metric_floor)})},
    }


def write_flat_vtu(d: Design, path: str):
    """flat.vtu: flattened mesh (z = 0), cell data sigma1, sigma2, kappa1_per_mm; point data
    target (3D position)."""
    import meshio

    pts = np.column_stack([d.flat.uv, np.zeros(len(d.flat.uv))])
    meshio.write(path, meshio.Mesh(pts, [("triangle", d.F)], point_data={"target": d.V},
                                   cell_data={"sigma1": [d.flat.sigma1], "sigma2": [d.flat.sigma2],
                                              "kappa1_per_mm": [d.kappa1]}))


def plot_pattern(d: Design, path: str, title: str = ""):
    """pattern.png: outline and ribbons to scale (front red, back blue, darker = thicker)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import to_rgb

    ext = d.outline.max(0) - d.outline.min(0)
    fig, ax = plt.subplots(figsize=(8, 8 * max(ext[1], 1) / max(ext[0], 1) + 0.6))
    ax.fill(*d.outline.T, facecolor="0.94", edgecolor="0.3", lw=0.8)
    th = np.array([r.thickness_mm for r in d.ribbons])
    lo = th.min()
    polys, cols = [], []
    for r, t in zip(d.ribbons, th):
        g = shapely.LineString(r.path).buffer(r.width_mm / 2, cap_style="flat", join_style="mitre")
        for part in getattr(g, "geoms", [g]):
            if part.geom_type == "Polygon" and not part.is_empty:
                polys.append(np.asarray(part.exterior.coords))
                base = np.array(to_rgb("tab:red" if r.side == "front" else "tab:blue"))
                shade = 0.3 + 0.7 * t / th.max()
                cols.append(1 - shade * (1 - base))
    ax.add_collection(PolyCollection(polys, facecolors=cols, edgecolors="none"))
    ax.set_aspect("equal")
    ax.autoscale_view()
    n_f = sum(r.side == "front" for r in d.ribbons)
    ax.set_title(f"{title}  {n_f} front (red), {len(d.ribbons) - n_f} back (blue); "
                 f"thickness {lo:.1f}-{th.max():.1f} mm (darker = thicker)", fontsize=9)
    ax.set_xlabel("x (printed mm)")
    ax.set_ylabel("y (printed mm)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def thickness_histogram(ribbons) -> dict:
    """{"front": {"0.4": count, ...}, "back": {...}} of the ribbon thicknesses (mm)."""
    out = {}
    for side in ("front", "back"):
        t = [round(r.thickness_mm, 3) for r in ribbons if r.side == side]
        vals, counts = np.unique(t, return_counts=True) if t else ([], [])
        out[side] = {f"{v:g}": int(c) for v, c in zip(vals, counts)}
    return out


def report_dict(d: Design) -> dict:
    f = d.flat
    lengths = [float(np.linalg.norm(np.diff(r.path, axis=0), axis=1).sum()) for r in d.ribbons]
    return {
        "n_faces": int(len(d.F)), "n_faces_input": int(len(d.F_input)), "refine_levels": d.refine_levels,
        "n_faces_layout": int(len(d.F_input) * 4 ** d.layout_levels),
        "lambda": d.lam, "k1_deviation_deg": float(f.k1_deviation_deg),
        "sigma_bound_violation": [float(x) for x in f.sigma_bound_violation],
        "sigma_out_of_bounds_pct": [float(x) for x in f.sigma_out_of_bounds_pct],
        "residual_energy": float(f.residual_energy),
        "stretch": d.stretch, "stretch_bounds": list(d.bounds),
        "flatten_iterations": int(f.iterations), "flatten_coarse_iterations": int(d.coarse_iterations),
        "flatten_converged": bool(f.converged), "flatten_stop": d.stop,
        "flatten_last_change": [float(x) for x in f.history[-1]] if f.history else None,
        "field_t": None if not np.isfinite(d.field.t) else float(d.field.t),
        "sigma1_range": [float(f.sigma1.min()), float(f.sigma1.max())],
        "sigma2_range": [float(f.sigma2.min()), float(f.sigma2.max())],
        "flat_area_mm2": float(abs(_polygon_area(d.outline))),
        "n_ribbons": len(d.ribbons),
        "ribbons_per_side": {s: sum(r.side == s for r in d.ribbons) for s in ("front", "back")},
        "ribbon_length_mm": {"total": float(np.sum(lengths)), "mean": float(np.mean(lengths))},
        "thickness_histogram": thickness_histogram(d.ribbons),
        "ribbons_separated": d.separation,
        "thickness_clamped": d.thickness_info, "thickness_law": d.law_source,
        "plastic_young_modulus_mpa": d.law_plastic_mpa,
    }


def _polygon_area(P):
    x, y = P[:, 0], P[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


# ----------------------------------------------------------------------------- verification
def kabsch(X: np.ndarray, Y: np.ndarray, w=None):
    """Rotation R and translation t minimising sum w |R x + t - y|^2 (proper rotation, scale fixed)."""
    w = np.ones(len(X)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    cx, cy = w @ X, w @ Y
    H = (X - cx).T @ ((Y - cy) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cy - R @ cx


def register(X: np.ndarray, V: np.ndarray, F: np.ndarray, Y0: np.ndarray | None = None, iterations: int = 100,
             tol: float = 1e-9):
    """Rigid registration (scale fixed) of points X (k, 3) to the surface (V, F): Kabsch on the
    correspondences Y0 (if given), then point-to-plane ICP against the closest surface points
    (linearised rotation per step, mapped back to a rotation by Rodrigues). Point-to-plane steps
    can overshoot when the shapes differ a lot, so the pose with the smallest RMS distance seen
    (the Kabsch start included) is returned. Returns (registered X, closest-point distances
    (k,), ICP iterations)."""
    import igl

    F = np.ascontiguousarray(F, dtype=np.int64)
    if Y0 is not None:
        R, t = kabsch(X, Y0)
        X = X @ R.T + t
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N /= np.linalg.norm(N, axis=1)[:, None]
    prev = None
    best = (np.inf, X, None)
    it = 0
    for it in range(1, iterations + 1):
        d2, I, C = igl.point_mesh_squared_distance(X, V, F)
        rms = float(np.sqrt(d2.mean()))
        if rms < best[0]:
            best = (rms, X, d2)
        if prev is not None and prev - rms <= tol * prev:
            break
        prev = rms
        n = N[I]
        c = X.mean(axis=0)
        A = np.column_stack([np.cross(X - c, n), n])
        b = -np.einsum("ij,ij->i", X - C, n)
        w, t = np.split(np.linalg.lstsq(A, b, rcond=None)[0], 2)
        ang = float(np.linalg.norm(w))
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(ang, 1e-300)
        R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        X = (X - c) @ R.T + c + t
    d2, _, _ = igl.point_mesh_squared_distance(X, V, F)
    if float(np.sqrt(d2.mean())) > best[0]:
        _, X, d2 = best
    return X, np.sqrt(d2), it


def flat_to_target(points2d: np.ndarray, uv: np.ndarray, F: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Target positions (k, 3) of printed-state points (k, 2) through the flat mesh (closest
    flat triangle, barycentric coordinates)."""
    import igl

    P = np.column_stack([points2d, np.zeros(len(points2d))])
    U = np.column_stack([uv, np.zeros(len(uv))])
    F = np.ascontiguousarray(F, dtype=np.int64)
    _, I, C = igl.point_mesh_squared_distance(P, U, F)
    a, b, c = (U[F[I, k]] for k in range(3))
    B = igl.barycentric_coordinates(np.ascontiguousarray(C), np.ascontiguousarray(a), np.ascontiguousarray(b),
                                    np.ascontiguousarray(c))
    return np.einsum("kc,kcd->kd", B, V[F[I]])


def verify_design(d: Design, pattern_path: str, out_dir: str, written: list) -> dict:
    """Simulate pattern.toml, register the deployed surface to the target, closest-point
    distances in % of the target's bounding-box diagonal; writes deployed.vtu, verify.png."""
    from geometry.patterns import load_pattern
    from forward.simulate import simulate

    t0 = time.perf_counter()
    try:
        sim = simulate(load_pattern(pattern_path))
    except SelfshapeError as e:      # the design stays valid; the verification could not run
        return {"verify_converged": False, "verify_reason": f"simulation failed: {e}", "deviation_pct_bbox": None,
                "verify_note": "the simulation could not run; no deviation reported",
                "verify_simulation_s": round(time.perf_counter() - t0, 2)}
    s = sim.summary()
    out = {"verify_converged": bool(s["converged"]), "verify_reason": s["reason"],
           "verify_newton_iterations": s["newton_iterations"], "verify_n_triangles": s["n_triangles"],
           "verify_simulation_s": round(time.perf_counter() - t0, 2)}
    if not s["converged"]:
        out["deviation_pct_bbox"] = None
        out["verify_note"] = f"simulation did not converge ({s['reason']}); no deviation reported"
        return out
    X = sim.positions
    diag = float(np.linalg.norm(d.V_input.max(0) - d.V_input.min(0)))
    Y0 = flat_to_target(sim.sheet.points, d.flat.uv, d.F, d.V)
    Xr, dist, icp_it = register(X, d.V_input, d.F_input, Y0)
    pct = 100.0 * dist / diag
    import igl
    back = 100.0 * np.sqrt(igl.point_mesh_squared_distance(d.V_input, Xr, np.ascontiguousarray(
        sim.sheet.triangles, dtype=np.int64))[0]) / diag
    out.update({"deviation_pct_bbox": [float(pct.mean()), float(pct.max())],
                "deviation_target_to_deployed_pct_bbox": [float(back.mean()), float(back.max())],
                "deviation_p99_pct_bbox": float(np.percentile(pct, 99)), "icp_iterations": int(icp_it),
                "bbox_diagonal_mm": diag})
    import meshio
    p = os.path.join(out_dir, "deployed.vtu")
    written.append(p)
    meshio.write(p, meshio.Mesh(Xr, [("triangle", sim.sheet.triangles)],
                                point_data={"reference": np.column_stack([sim.sheet.points,
                                                                          np.zeros(len(Xr))]),
                                            "distance_pct_bbox": pct},
                                cell_data={"side": [np.asarray(sim.sheet.side)]}))
    p = os.path.join(out_dir, "verify.png")
    written.append(p)
    plot_verify(d, Xr, sim.sheet.triangles, pct, p)
    return out


def plot_verify(d: Design, X, T, pct, path: str):
    """verify.png: the registered simulated surface coloured by distance to the target (%),
    the target as a grey wireframe, two views."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, 5))
    col = pct[T].mean(axis=1)
    for k, (elev, azim) in enumerate(((25, -60), (70, 30))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        surf = ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=T, cmap="viridis", linewidth=0)
        surf.set_array(col)
        surf.set_clim(0, max(float(pct.max()), 1e-9))
        ax.plot_trisurf(d.V_input[:, 0], d.V_input[:, 1], d.V_input[:, 2], triangles=d.F_input,
                        color=(0.5, 0.5, 0.5, 0.08), edgecolor=(0.3, 0.3, 0.3, 0.15), linewidth=0.2)
        ax.view_init(elev, azim)
        ax.set_box_aspect(np.ptp(np.vstack([X, d.V_input]), axis=0))
        ax.set_axis_off()
    fig.colorbar(surf, ax=fig.axes, shrink=0.6, label="distance to target (% of bbox diagonal)")
    fig.suptitle(f"simulated (colour) vs target (grey): mean {pct.mean():.2f} %, max {pct.max():.2f} %")
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- the verb
def design_file(target_path, out_dir, verify: bool = False, diagonal_mm: float = 110.0, stretch: float = 1.6,
                *, printer=None, lam: float = 0.0, thickness_law=None, edge_mm: float = 1.0,
                mesh_size_mm: float = 2.0, mesh_across: float | None = None, seed: int = 0,
                verify_iterations: int | None = None, metric_floor: float | None = None) -> dict:
    """`selfshape design TARGET -o DIR`: writes DIR/pattern.toml, flat.vtu, front.gcode (and
    back.gcode when a ribbon is on the back), pattern.png and report.json (last); with
    ``verify`` also deployed.vtu and verify.png and the deviation in report.json. time_s is the
    design time (read to written outputs, Table 5.1's "Time"), total_time_s includes the
    verification. verify_iterations: Newton cap of the verification, written to pattern.toml's
    [solver] max_iterations (default: the simulator's 300); metric_floor: [solver] metric_floor of
    the verification (default: the simulator's 10). Outputs of an earlier run in the
    directory are removed first; on failure every file this run wrote is removed. Returns the
    report dict."""
    import tomli_w

    from geometry.target import read_mesh
    from inverse.gcode import ribbons_to_gcode_files

    t_start = time.perf_counter()
    from geometry.patterns import solver_options
    # the values go to pattern.toml's [solver]: checked as load_pattern will check them
    solver_options({k: v for k, v in (("max_iterations", verify_iterations), ("metric_floor", metric_floor))
                    if v is not None}, "verification [solver] (--verify-iterations, --metric-floor)")
    name = os.path.basename(str(target_path))
    V, F = read_mesh(target_path)
    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise SelfshapeError(f"{out_dir}: exists and is not a directory")
    created = not os.path.isdir(out_dir)
    written: list = []
    try:
        d = design(V, F, stretch=stretch, diagonal_mm=diagonal_mm, printer=printer, lam=lam,
                   thickness_law=thickness_law, edge_mm=edge_mm, seed=seed, where=name)
        t = time.perf_counter()
        os.makedirs(out_dir, exist_ok=True)
        for stale in OUTPUTS:                 # an earlier run's files must not mix with this run's
            if os.path.isfile(os.path.join(out_dir, stale)):
                os.remove(os.path.join(out_dir, stale))
        p = os.path.join(out_dir, "pattern.toml")
        written.append(p)
        with open(p, "wb") as f:
            tomli_w.dump(pattern_dict(d, mesh_size_mm=mesh_size_mm, mesh_across=mesh_across, seed=seed,
                                      target_name=name, max_iterations=verify_iterations,
                                      metric_floor=metric_floor), f)
        p = os.path.join(out_dir, "flat.vtu")
        written.append(p)
        write_flat_vtu(d, p)
        for side in ("front", "back"):
            written.append(os.path.join(out_dir, f"{side}.gcode"))
        ribbons_to_gcode_files(d.ribbons, out_dir, printer)
        p = os.path.join(out_dir, "pattern.png")
        written.append(p)
        plot_pattern(d, p, title=name)
        d.times["write"] = time.perf_counter() - t
        rep = {"target": os.path.abspath(str(target_path)), "time_s": None}
        rep.update(report_dict(d))
        rep["stages_s"] = {k: round(v, 3) for k, v in d.times.items()}
        rep["stages_cpu_s"] = {k: round(v, 3) for k, v in d.cpu_times.items()}
        rep["time_s"] = round(time.perf_counter() - t_start, 3)
        if verify:
            t = time.perf_counter()
            rep.update(verify_design(d, os.path.join(out_dir, "pattern.toml"), out_dir, written))
            rep["stages_s"]["verify"] = round(time.perf_counter() - t, 3)
        rep["total_time_s"] = round(time.perf_counter() - t_start, 3)
        rep["files"] = sorted(os.path.basename(p) for p in written if os.path.exists(p)) + ["report.json"]
        p = os.path.join(out_dir, "report.json")
        written.append(p)
        tmp = p + ".tmp"
        with open(tmp, "w") as f:
            json.dump(rep, f, indent=2)
        os.replace(tmp, p)
        return rep
    except BaseException:
        for p in written + [os.path.join(out_dir, "report.json.tmp")]:
            if os.path.exists(p):
                os.remove(p)
        if created and os.path.isdir(out_dir) and not os.listdir(out_dir):
            os.rmdir(out_dir)
        raise
