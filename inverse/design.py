"""Inverse design, seed chapter 5: a target surface -> a printable ribbon pattern (`selfshape design`).

    design(V, F)            arrays in, a Design record out (no files)
    design_file(path, dir)  the CLI verb: writes pattern.toml, flat.vtu, front/back.gcode,
                            pattern.png, pattern.dxf/.svg, index.html, report.json (and with
                            verify deployed.vtu/.obj/.stl/.ply, verify.png; with refine
                            refine.png)

Stages (times in Design.times / report.json "stages_s"):
 1. check (a disk, possibly with holes; one-line errors), centre and scale to a bounding-box diagonal
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
    Tutte + 2 SLIM iterations on the mesh itself;
 4. ribbon layout (inverse.layout: Eq. 5.15 spacing, two stripe fields, staggered dashes,
    clipping, trimming > 25 deg, front/back split by the sign of the target normal curvature
    along the ribbons, pieces < 2 mm dropped), stretches clamped into the bounds first, on the
    coarsest hierarchy level with edges <= ``layout_edge_mm`` (the stripes need a few edges per
    period, not the flattening's resolution); then the ribbons are kept ``gap_mm`` apart and
    inside the outline (inverse.separation) so that the pattern meshes without slivers;
 5. thickness per ribbon from the curvature law (inverse.thickness_law) at the ribbon's mean
    |kappa| and transverse spacing mu2, rounded to layer-height multiples.

The files: inverse.to_pattern (pattern.toml), inverse.vtu (flat.vtu, deployed.vtu),
inverse.plots (pattern.png, verify.png), inverse.report (report.json), inverse.gcode
(front/back.gcode); the verification: inverse.verify with inverse.registration.

Units: mm, 1/mm; the flat pattern is in printed (pre-stretched) mm.
"""
from __future__ import annotations

import itertools
import os
import time
from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from geometry.meshops import face_areas, signed_areas
from inverse.plots import plot_pattern
from inverse.record import Design
from inverse.report import report_dict
from inverse.separation import separate_ribbons, simplify_paths
from inverse.to_pattern import VERIFY_ITERATIONS, VERIFY_MESH_ACROSS, VERIFY_MESH_SIZE_MM, pattern_dict
from inverse.verify import SimulationBeside, register_simulation, verify_design
from inverse.vtu import write_flat_vtu
from shellfem.errors import SelfshapeError

RIBBON_LENGTH_MM, RIBBON_WIDTH_MM = 15.0, 1.5
#: Every file design_file may write (removed from the output directory before a new run writes).
OUTPUTS = ("report.json", "pattern.toml", "flat.vtu", "front.gcode", "back.gcode", "pattern.png", "pattern.dxf",
           "pattern.svg", "deployed.vtu", "deployed.obj", "deployed.stl", "deployed.ply", "verify.png", "refine.png",
           "index.html")


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


def bend_share(k1: np.ndarray, kappa_along: np.ndarray, areas: np.ndarray) -> float:
    """The share of the target's bending that the ribbon directions follow: the area-weighted
    |normal curvature along the field| over the area-weighted largest |principal curvature|.
    k1 (m,): each face's principal curvature of larger |k|; kappa_along (m,): the normal
    curvature along the ribbon field; areas (m,) (1/mm, 1/mm, mm^2). 1 on a field along the
    principal direction of larger |k| or on an umbilic surface; near 0 where the field runs
    along asymptotic directions, as on a minimal surface, where the target twists under the
    ribbons instead of bending along them. 1.0 for a flat target."""
    top = float(np.sum(areas * np.abs(k1)))
    return float(np.sum(areas * np.abs(kappa_along)) / top) if top > 0 else 1.0


def boundary_polygons(uv: np.ndarray, F: np.ndarray, simplify_mm: float = 0.02, where: str = "flattening"
                      ) -> tuple[np.ndarray, list]:
    """The flat mesh's boundary as (outline (k, 2), holes [(k, 2), ...]): the outer loop (the one
    enclosing the most area) counter-clockwise and the holes' rims clockwise, simplified within
    ``simplify_mm``. SelfshapeError if a loop self-intersects (a flipped flattening) or the
    fabric between a hole and the edge or another hole is narrower than the pattern format
    allows (geometry.outlines.with_holes)."""
    import shapely

    from geometry.meshops import boundary_loops
    from geometry.outlines import with_holes

    rings = [shapely.Polygon(uv[loop]) for loop in boundary_loops(np.column_stack([uv, np.zeros(len(uv))]), F)]
    for ring in rings:
        if not ring.is_valid:
            raise SelfshapeError(f"{where}: the flat boundary self-intersects ({shapely.is_valid_reason(ring)})")
    rings.sort(key=lambda r: -r.area)
    outer = rings[0]
    if len(rings) > 1:
        pts = lambda r: np.asarray(r.exterior.coords)[:-1]  # noqa: E731
        # the pattern format's bridge, with a margin for the simplification below and the 1e-4 mm
        # rounding of pattern.toml
        outer = with_holes(outer, [pts(r).tolist() for r in rings[1:]], f"{where}: the flattened holes",
                           min_bridge_mm=0.1 + 2.0 * simplify_mm + 1e-3)
    if simplify_mm > 0:
        simple = outer.simplify(simplify_mm, preserve_topology=True)
        if simple.is_valid and simple.geom_type == "Polygon" and len(simple.interiors) == len(outer.interiors):
            outer = simple
    poly = shapely.geometry.polygon.orient(outer, 1.0)
    return np.asarray(poly.exterior.coords)[:-1], [np.asarray(h.coords)[:-1] for h in poly.interiors]


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


@dataclass(frozen=True)
class DesignOptions:
    """The choices of an inverse design (mm, 1/mm).

    stretch: fabric pre-stretch s (> 1), or "auto" (default): the shipped law's stretch that fits
    the target best (`choose_stretch`; a stretch whose law cannot reach the target's low
    curvature over-curls the ribbons, e.g. a shallow vault designed at 1.6 rolls into a tube).
    diagonal_mm: scale the target to this bounding-box
    diagonal (None: V is already in mm). printer: inverse.printer.Printer (its layer height
    rounds the thickness; None: the default printer). lam: the seed's line-field lambda
    (<= 0, 1/mm^2). thickness_law: a ThicknessLaw, a CSV path or None (the shipped law made at
    ``stretch``; a law stating another stretch is refused).
    edge_mm: Loop-refine until the mean edge is below it (None: no refinement), while the
    face count stays <= max_faces. bounds: (s1min, s1max, s2min, s2max), default the
    contraction model's (Eq. 5.15's: geometry.flattening.stretch_bounds). ribbon_length, ribbon_width: the
    printed dash size. seed: seed of the stagger of the dashes (also the pattern's [solver]
    seed). stop, flatten_max_iter: the flattening's stop rule ("mean": the seed's, "norm":
    ||d sigma||_2 / m) and its iteration cap on the fine mesh (reported as flatten_converged =
    false when reached). gap_mm: minimum distance between printed ribbons and to the outline
    (`inverse.separation.separate_ribbons`). layout_edge_mm: the ribbon layout runs on the
    coarsest level of the refinement hierarchy whose mean edge is below it (None: on the
    flattening's mesh). contraction: how stretches map to row spacings and which stretches a
    pattern can realise (inverse.contraction.contraction_for): "auto" (default: the shipped
    table of simulated patches at ``stretch`` for the spacings where there is one, else Eq.
    5.15), "seed" (Eq. 5.15), "table", "table-polygon" (the table's admissible polygon as the
    flattening's bounds too), a table path or a model; it also gives the default ``bounds``.
    Whatever the model, the report's ``contraction.check`` compares the layout's spacings with
    the shipped table at the stretch, where there is one.
    proxy: design for a proxy surface (`proxy_surface`) where the target's flattening leaves the
    stretch bounds on more than PROXY_MIN_OOB_PCT % of the area: the nearest surface found whose
    metric the bounds admit, smooth at wavelengths down to ``proxy_smooth_mm`` (mm); the
    verification and the refinement still measure against the target. "auto" (design_file with
    verification): the design for the target and the one for its proxy are both verified and the
    one that deploys nearer the target is kept (`_verify_candidates`); without verification
    "auto" designs for the target. None (default): "auto" in design_file with ``refine``, else
    off: refined, the 110 mm hemisphere ends at 1.8 % from its proxy's design against 4.7 % from
    its own and the hat at 1.29 % against 1.60 %; a Gaussian bump at 0.95 % released free against
    0.75 % on a jig (a nearer open loop need not refine nearer; docs/notes.md, sessions 45-46); a
    verification alone stays one simulation of the design asked for.
    stretch_candidates: with stretch "auto" and a verification (design_file), the designs at this
    many best stretches by `reach_score` (for the target, and for its proxy with proxy "auto")
    are all simulated and the one that deploys nearest the target is kept (1: the score's
    choice alone, as without verification)."""
    stretch: float | str = "auto"
    diagonal_mm: float | None = 110.0
    printer: object = None
    lam: float = 0.0
    thickness_law: object = None
    edge_mm: float | None = 1.0
    max_faces: int = 600_000
    bounds: tuple | None = None
    ribbon_length: float = RIBBON_LENGTH_MM
    ribbon_width: float = RIBBON_WIDTH_MM
    seed: int = 0
    stop: str = "mean"
    flatten_max_iter: int = 1000
    gap_mm: float = 0.5
    layout_edge_mm: float | None = 2.0
    contraction: object = "auto"
    proxy: bool | str | None = None
    proxy_smooth_mm: float = 30.0
    stretch_candidates: int = 1


#: A proxy surface (DesignOptions.proxy) is sought only where the target's flattening leaves the
#: stretch bounds on more than this % of its area (either stretch), as the refine block's
#: feasibility statement; the target is kept where the bounds admit it to a stretch of 1 % on all
#: but 1 % of the faces (geometry.reachable; the saddle at s 1.2: 15 / 20 % of its input mesh's
#: faces out of bounds, all within that).
PROXY_MIN_OOB_PCT = 1.0

#: the command-line words of DesignOptions.proxy (selfshape design --proxy, the study scripts; no
#: word: None, the default)
PROXY_WORDS = {"on": True, "off": False, "auto": "auto"}


def proxy_surface(V, F, bounds, lam: float, smooth_mm: float, stop: str = "mean"):
    """The surface a design is made for instead of the target (V (n, 3) mm, F): the target
    itself where its bounded flattening (on this mesh, the line field of ``lam``) leaves the
    stretch ``bounds`` on at most PROXY_MIN_OOB_PCT % of the area or within the tolerance of
    geometry.reachable.reachable_surface, else the nearest surface found
    whose faces the bounds admit along the same ribbon directions, with V + smooth changes of
    wavelength >= ``smooth_mm`` (geometry.reachable.reachable_surface). Returns (surface (n, 3),
    info dict for the report: used, out_of_bounds_pct of the target, and when used the proxy's
    distance to the target both ways (mean, max, % of the diagonal), its faces still out of
    bounds (%), smooth_mm, seconds). Why: at s 1.2 the 110 mm hemisphere designed for its proxy
    (2.6 % from it) deploys 2.3 % from the hemisphere (mean of the diagonal), designed for itself
    5.4 %: a target far beyond the bounds gets a flattening that is out of them nearly everywhere,
    whose ribbons ask for a shape no release reaches. The hat and the beetle gain nothing
    (docs/notes.md, session 43), so it is an option."""
    from geometry.curvature import principal_curvature
    from geometry.fields import curvature_line_field
    from geometry.flattening import flatten
    from geometry.reachable import reachable_surface

    t = time.perf_counter()
    lf = curvature_line_field(V, F, lam, principal_curvature(V, F))
    fr = flatten(V, F, lf.face_dirs, bounds, stop=stop)
    oob = [round(float(x), 2) for x in fr.sigma_out_of_bounds_pct]
    info = {"used": False, "out_of_bounds_pct": oob, "min_out_of_bounds_pct": PROXY_MIN_OOB_PCT}
    if max(oob) <= PROXY_MIN_OOB_PCT:
        info["seconds"] = round(time.perf_counter() - t, 2)
        return np.asarray(V, float), info
    r = reachable_surface(V, F, lf.face_dirs, bounds, fr.uv, smooth_mm=smooth_mm)
    if not r.history:                    # the target within the bounds' tolerance: designed for itself
        info["seconds"] = round(time.perf_counter() - t, 2)
        return np.asarray(V, float), info
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    info.update(used=True, smooth_mm=float(smooth_mm), distance_pct=[round(100.0 * x / diag, 4) for x in r.distance_mm],
                proxy_out_of_bounds_pct=round(r.out_of_bounds_pct, 2), seconds=round(time.perf_counter() - t, 2))
    return r.S, info


def _check_fits_bed(uv, printer, ribbon_length, diagonal_mm, where):
    """One-line error before the layout when the flattened pattern (printed-state mm) cannot
    fit the printer's bed: the ribbons fill the outline to within a ribbon length of its edge,
    so an outline more than two ribbon lengths longer than the bed in x or y cannot print
    (the G-code writer refuses the marginal cases ribbon by ribbon)."""
    ext = np.ptp(uv, axis=0)
    bed = np.asarray(printer.bed_size, float)
    if np.any(ext - 2.0 * ribbon_length > bed):
        hint = f"lower --diagonal (now {diagonal_mm:g} mm)" if diagonal_mm is not None else "scale the target down"
        raise SelfshapeError(f"{where}: the flattened pattern is {ext[0]:.0f} x {ext[1]:.0f} mm, larger than the "
                             f"printer's {bed[0]:g} x {bed[1]:g} mm bed; {hint} or give a printer with a larger "
                             f"bed_size")


#: The bed check before the flattening refuses a target only when its flat pattern's lower
#: bounds exceed what the bed takes by more than this factor: the bounds hold where the flattening
#: keeps its stretch bounds, and it can leave them on part of the area (on the shipped targets at
#: 110 mm the flat diameter is 1.08-1.64 x the target's times the smallest stretch bound, the
#: flat area 1.05-1.32 x the target's times the product of the lowest bounds; docs/notes.md
#: session 23).
BED_PRECHECK_SLACK = 1.1


def _fibonacci_directions(n: int = 200) -> np.ndarray:
    """n unit vectors spread over the sphere (a Fibonacci lattice), for diameter lower bounds."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _check_fits_bed_before_flattening(V, F, bounds, printer, ribbon_length, diagonal_mm, where):
    """One-line error before the refinement and flattening when the target (mm) cannot fit the
    printer's bed at any flattening within the stretch ``bounds``: every flat distance is at
    least the smallest stretch bound times the target's (geodesic >= straight), and the flat
    area at least the product of the two lowest bounds times the target's area, while
    `_check_fits_bed` admits an outline of at most (bed + 2 ribbon lengths) per side, so a
    diameter beyond that box's diagonal or an area beyond its area cannot print. Both bounds
    are divided by BED_PRECHECK_SLACK; the marginal cases go on to `_check_fits_bed` after the
    flattening. A 5000 mm target on the default bed was refused only after flattening (2 min
    with --stretch auto's three candidates)."""
    b = np.asarray(bounds, float)
    smin1, smin2 = (b[0], b[2]) if b.ndim == 1 else (b[:, 0].min(), b[:, 1].min())
    box = np.asarray(printer.bed_size, float) + 2.0 * ribbon_length
    d3 = float(np.ptp(V @ _fibonacci_directions().T, axis=0).max())        # <= the target's diameter
    a3 = float(face_areas(V, F).sum())
    d_flat, a_flat = min(smin1, smin2) * d3, smin1 * smin2 * a3
    d_box, a_box = float(np.hypot(*box)), float(np.prod(box))
    excess = max(d_flat / d_box, (a_flat / a_box) ** 0.5) / BED_PRECHECK_SLACK
    if excess <= 1.0:
        return
    bed = np.asarray(printer.bed_size, float)
    hint = (f"lower --diagonal (now {diagonal_mm:g} mm; above {diagonal_mm / excess:.0f} mm this target cannot fit)"
            if diagonal_mm is not None else "scale the target down")
    raise SelfshapeError(f"{where}: the flat pattern needs at least {d_flat:.0f} mm across and {a_flat:.4g} mm^2 "
                         f"(the target's {d3:.0f} mm and {a3:.4g} mm^2 times the stretch bounds), more than the "
                         f"printer's {bed[0]:g} x {bed[1]:g} mm bed takes ({box[0]:g} x {box[1]:g} mm with a ribbon "
                         f"length over each side); {hint} or give a printer with a larger bed_size")


#: A target whose vertices all lie within this fraction of its bounding-box diagonal of one
#: plane is flat: there is no curvature to design for (0.11 mm at the default 110 mm).
FLAT_REL = 1e-3


def _check_curved(V, where: str) -> None:
    """Refuse a flat target (a single triangle is one) in one line: its curvature is zero
    everywhere, so the layout would print arbitrary ribbons that curl it away from flat;
    the design of a flat sheet is to print nothing."""
    c = V - V.mean(axis=0)
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    normal = np.linalg.svd(c, full_matrices=False)[2][-1]
    off = float(np.abs(c @ normal).max())
    if off <= FLAT_REL * diag:
        raise SelfshapeError(f"{where}: the target is flat ({len(V)} vertices within {off:.2g} mm of a plane, "
                             f"{FLAT_REL:g} of its {diag:.4g} mm diagonal): a flat sheet has no curvature to "
                             f"design for")


#: The stages of `design` in order, as its progress events name them (the stage that starts)
DESIGN_STAGES = ("load and refine", "curvature", "line field", "flattening", "ribbon layout", "thickness")


def check_design_numbers(o: DesignOptions) -> None:
    """The numbers of ``o`` in their geometry.schema.DESIGN_NUMBERS ranges (None turns an
    option off; stretch may be "auto"), before anything runs: a one-line SelfshapeError naming
    the option otherwise (a NaN gap or a stretch of 5 would run and write nonsense)."""
    from geometry.schema import DESIGN_BOUND, DESIGN_NUMBERS, DESIGN_STOPS, number
    for key, spec in DESIGN_NUMBERS.items():
        v = getattr(o, key)
        if v is not None and not (key == "stretch" and v == "auto"):
            number(v, f"design: {key}", spec)
    if o.ribbon_width > o.ribbon_length:
        raise SelfshapeError(f"design: ribbon_width ({o.ribbon_width:g} mm) must be at most ribbon_length "
                             f"({o.ribbon_length:g} mm): a ribbon is longer than wide")
    if o.proxy not in (True, False, "auto", None):
        raise SelfshapeError(f"design: proxy must be true, false or 'auto', got {o.proxy!r:.40}")
    if o.stop not in DESIGN_STOPS:
        raise SelfshapeError(f"design: stop must be one of {', '.join(map(repr, DESIGN_STOPS))}, got {o.stop!r:.40}")
    if o.bounds is not None:
        b = o.bounds
        if isinstance(b, (str, bytes)) or not hasattr(b, "__len__") or len(b) != 4:
            raise SelfshapeError(f"design: bounds must be 4 numbers (s1min, s1max, s2min, s2max), got {b!r:.60}")
        b = [number(v, f"design: bounds[{i}]", DESIGN_BOUND) for i, v in enumerate(b)]
        for i in (0, 2):
            if b[i] > b[i + 1]:
                raise SelfshapeError(f"design: bounds[{i}] = {b[i]:g} is above bounds[{i + 1}] = {b[i + 1]:g} "
                                     f"(s1min, s1max, s2min, s2max)")


# The design is the same at every thread count: multithreaded OpenBLAS (CHOLMOD's supernodal
# factorisations and numpy's products) sums in an order that depends on the thread count, and the
# flattening's iterations carry that round-off into the pattern (the saddle at 1 and 2 threads:
# coordinates a median 0.001 mm and up to 0.45 mm apart, one ribbon point fewer), which a
# multistable sheet can turn into another equilibrium. One BLAS thread here (restored on return).
@threadpool_limits.wrap(limits=1, user_api="blas")
def design(V, F, options: DesignOptions | None = None, *, where: str = "target", progress=None,
           **overrides) -> Design:
    """Inverse design of a target that is a disk, possibly with holes (V (n, 3), F (m, 3)); see the module doc.

    ``options`` (default DesignOptions()) with any of its fields overridden by keyword, e.g.
    ``design(V, F, stretch=1.4, edge_mm=None)``; ``where`` names the target in messages.
    ``progress``: called with {"stage": "design", "step": name, "index": i, "steps": n} as each
    of DESIGN_STAGES starts (the CLI's status line). ``stretch = "auto"`` designs at each shipped
    law's stretch and returns the best (`choose_stretch`)."""
    import shapely

    from geometry.curvature import principal_curvature
    from geometry.fields import curvature_line_field
    from geometry.flattening import project_stretches
    from geometry.target import check_disk, normalize, refine
    from geometry.stripes import MeshTooCoarse
    from inverse.layout import ribbon_layout
    from inverse.printer import Printer
    from inverse.thickness_law import (ThicknessLaw, check_law_stretch, curvature_reach, law_for_stretch,
                                       load_thickness_law, reach_warning)

    o = replace(options or DesignOptions(), **overrides)
    check_design_numbers(o)
    if o.stretch == "auto":
        return choose_stretch(V, F, o, where=where, progress=progress)[0]
    stretch, printer, thickness_law, bounds = o.stretch, o.printer, o.thickness_law, o.bounds
    ribbon_length, ribbon_width, stop, gap_mm = o.ribbon_length, o.ribbon_width, o.stop, o.gap_mm
    times, cpu = {}, {}
    t, c = time.perf_counter(), time.process_time()

    def lap(name):
        nonlocal t, c
        now, cnow = time.perf_counter(), time.process_time()
        times[name], cpu[name] = now - t, cnow - c
        t, c = now, cnow
        done[0] += 1
        stage(done[0])

    done = [0]

    def stage(i):
        if progress is not None and i < len(DESIGN_STAGES):
            progress({"stage": "design", "step": DESIGN_STAGES[i], "index": i + 1, "steps": len(DESIGN_STAGES)})

    stage(0)

    printer = Printer() if printer is None else printer
    if isinstance(thickness_law, ThicknessLaw):
        law = thickness_law
    else:
        law = law_for_stretch(stretch) if thickness_law is None else load_thickness_law(thickness_law)
    check_law_stretch(law, stretch)
    from inverse.contraction import contraction_for
    contraction = contraction_for(stretch, ribbon_length, ribbon_width, o.contraction)
    bounds = contraction.bounds() if bounds is None else bounds
    repairs: list = []
    V0, F0 = check_disk(V, F, where=where, repairs=repairs, holes=True)
    V0 = normalize(V0, o.diagonal_mm)
    total_area = float(face_areas(V0, F0).sum())
    if not total_area > 0:
        raise SelfshapeError(f"{where}: zero total area")
    _check_curved(V0, where)
    _check_fits_bed_before_flattening(V0, F0, bounds, printer, ribbon_length, o.diagonal_mm, where)
    levels = 0 if o.edge_mm is None else refine_levels_for_edge(V0, F0, o.edge_mm, o.max_faces)
    V_design, proxy_info, V_goal = V0, None, None
    if o.proxy != "auto" and o.proxy:
        V_design, proxy_info = proxy_surface(V0, F0, bounds, o.lam, o.proxy_smooth_mm, stop)
    Vf, Ff = refine(V_design, F0, levels) if levels else (V_design, F0)
    Ff = np.ascontiguousarray(Ff, dtype=np.int64)
    if proxy_info is not None and proxy_info["used"]:
        V_goal, F_goal = refine(V0, F0, levels) if levels else (V0, F0)
        if not np.array_equal(np.asarray(F_goal, np.int64), Ff):     # the refinement's topology is the input's
            raise SelfshapeError(f"{where}: the proxy surface refined to another mesh than the target")
    lap("load_refine")

    curv = principal_curvature(Vf, Ff)
    lap("curvature")
    lf = curvature_line_field(Vf, Ff, o.lam, curv)
    lap("field")
    flat, coarse, t_coarse, c_coarse = flatten_multilevel(V_design, F0, levels, Vf, Ff, lf.face_dirs, bounds, o.lam,
                                                          stop=stop, max_iter=o.flatten_max_iter)
    times["flatten_coarse"] = t_coarse
    lap("flatten")
    times["flatten"] -= t_coarse
    cpu["flatten_coarse"], cpu["flatten"] = c_coarse, cpu["flatten"] - c_coarse
    if flat.flipped:
        raise SelfshapeError(f"{where}: the flattening has {flat.flipped} flipped triangles; "
                             f"the surface cannot be flattened within the stretch bounds")

    _check_fits_bed(flat.uv, printer, ribbon_length, o.diagonal_mm, where)
    kappa1 = normal_curvature_along(curv, lf.face_dirs)
    outline, holes = boundary_polygons(flat.uv, Ff, where=f"{where}: flattening")
    fabric = shapely.Polygon(outline, holes)
    s1, s2 = project_stretches(flat.sigma1, flat.sigma2, bounds)
    # the stripes need a few edges per period (2 mu2 >= 7.8 mm), not the flattening's resolution
    lay_levels = levels
    if o.layout_edge_mm is not None:
        e0 = float(np.linalg.norm(V0[F0[:, [1, 2, 0]]] - V0[F0], axis=2).mean())
        while lay_levels > 0 and e0 / 2 ** (lay_levels - 1) <= o.layout_edge_mm:
            lay_levels -= 1
    area = face_areas(Vf, Ff)
    while True:     # the coarsest level whose edges resolve the stripes (non-uniform meshes need finer)
        uv_l, F_l, d_l, s1_l, s2_l, k_l = coarsen_for_layout(F0, levels, lay_levels, flat.uv, area, flat.dir1,
                                                             s1, s2, kappa1)
        try:
            ribbons = ribbon_layout(uv_l, Ff if F_l is None else F_l, d_l, s1_l, s2_l, k_l, stretch,
                                    outline=fabric, ribbon_length=ribbon_length, ribbon_width=ribbon_width,
                                    seed=o.seed, contraction=contraction)
            break
        except MeshTooCoarse as e:
            if lay_levels >= levels:
                raise SelfshapeError(f"{where}: the target's mesh is too coarse for the ribbon spacing after "
                                     f"{levels} refinements ({e}); give a finer target mesh") from None
            lay_levels += 1
    # the layout's spacings against the simulated contraction (the shipped table at this stretch)
    from inverse.contraction import TableContraction, realisation_check, shipped_table
    table = contraction if isinstance(contraction, TableContraction) else \
        shipped_table(stretch, ribbon_length, ribbon_width)
    check = None
    if table is not None:
        area_l = np.abs(signed_areas(uv_l, Ff if F_l is None else F_l))
        # the table as the model: its own nearest spacings; else the model's
        mu_l = (None, None) if contraction is table else contraction.spacing(s1_l, s2_l)[:2]
        check = realisation_check(table, s1_l, s2_l, area_l, *mu_l)
    if not ribbons:
        raise SelfshapeError(f"{where}: the layout produced no ribbons (surface too small for "
                             f"{ribbon_length:g} x {ribbon_width:g} mm ribbons?)")
    simplify_paths(ribbons, 0.01)
    ribbons, sep = separate_ribbons(ribbons, fabric, gap_mm, min_length=2.0)
    if not ribbons:
        raise SelfshapeError(f"{where}: no ribbon is left after keeping them {gap_mm:g} mm apart")
    lap("layout")
    tinfo = assign_thickness(ribbons, law, printer.layer_height_mm)
    reach = curvature_reach(law, [r.meta["kappa_mean_abs"] for r in ribbons], [r.meta["mu2"] for r in ribbons],
                            [r.side for r in ribbons],
                            [r.length_mm for r in ribbons],
                            printer.layer_height_mm, diagonal_mm=float(np.linalg.norm(np.ptp(V0, axis=0))),
                            min_diagonal_mm=4.0 * ribbon_length)
    reach["bend_share"] = round(bend_share(curv.face_k1, kappa1, area), 4)
    reach["warning"] = reach_warning(reach)
    lap("thickness")
    return Design(V=Vf, F=Ff, V_input=V0, F_input=F0, curvature=curv, field=lf, flat=flat, kappa1=kappa1,
                  outline=outline, holes=holes, ribbons=ribbons, stretch=float(stretch),
                  bounds=bounds if isinstance(bounds, np.ndarray) else tuple(bounds),
                  refine_levels=levels, layout_levels=lay_levels, lam=float(o.lam), stop=stop, thickness_info=tinfo,
                  law_source=law.source, law_plastic_mpa=law.plastic_young_modulus_mpa,
                  times=times, cpu_times=cpu, separation=sep, curvature_reach=reach, target_repairs=repairs,
                  coarse_iterations=coarse.iterations if coarse is not None else 0,
                  contraction={**contraction.describe(), "check": check}, V_goal=V_goal, proxy=proxy_info)


def reach_score(d: Design) -> dict:
    """How well a design's law and flattening fit its target, for ranking stretches: the
    ``log_excess`` of the asked curvature (inverse.thickness_law.curvature_reach: length-weighted
    within a side; the sides averaged by their ribbon counts), the flattening's mean out-of-bounds area fraction,
    and their sum ``score`` (lower is better; a factor e off in curvature on average costs as much
    as all of the area out of the stretch bounds)."""
    reach = d.curvature_reach or {}
    ex, wsum = 0.0, 0.0
    for side in ("front", "back"):
        r = reach.get(side)
        if r:
            n = sum(rb.side == side for rb in d.ribbons)
            ex, wsum = ex + n * r["log_excess"], wsum + n
    ex = ex / wsum if wsum else 0.0
    oob = float(np.mean(d.flat.sigma_out_of_bounds_pct)) / 100.0
    return {"stretch": d.stretch, "log_excess": round(ex, 4), "out_of_bounds": round(oob, 4),
            "score": round(ex + oob, 4), "bend_share": reach.get("bend_share")}


def choose_stretch(V, F, options: DesignOptions | None = None, *, where: str = "target", progress=None,
                   **overrides):
    """`design --stretch auto`: the design at each stretch a law exists for, and the best by
    `reach_score`. With no thickness_law, the candidates are the shipped laws' stretches
    (inverse.thickness_law.shipped_laws); with a law that states its stretch, that one only; a law
    that does not state it cannot choose (one-line error). Ties go to the larger stretch (more
    contraction for the flattening). Returns (Design, {"candidates": [...], "chosen": s}).
    ``progress``: as for `design`, each event with "candidate": "stretch s (i/n)"."""
    ranked, record = rank_stretches(V, F, options, where=where, progress=progress, keep=1, **overrides)
    return ranked[0], record


def rank_stretches(V, F, options: DesignOptions | None = None, *, where: str = "target", progress=None,
                   keep: int = 1, **overrides):
    """`choose_stretch` keeping the ``keep`` best designs: ([Design, ...] best first by
    `reach_score`, at most ``keep`` of them, {"candidates": [...], "chosen": the best's s}). The
    ranked designs are what DesignOptions.stretch_candidates verifies: the score is read off
    the flattening and the law, and on a torus band it took 1.3 where the design at 1.2 deploys
    nearer (docs/notes.md, session 44)."""
    from inverse.thickness_law import ThicknessLaw, load_thickness_law, shipped_laws

    o = replace(options or DesignOptions(), **overrides)
    check_design_numbers(o)
    if o.thickness_law is None:
        candidates = sorted(shipped_laws(), reverse=True)
    else:
        law = o.thickness_law if isinstance(o.thickness_law, ThicknessLaw) else load_thickness_law(o.thickness_law)
        if law.stretch is None:
            raise SelfshapeError(f"{law.source}: --stretch auto needs a law that states its fabric stretch "
                                 f"(a '# fabric_stretch = s' line); give --stretch instead")
        candidates = [law.stretch]
        o = replace(o, thickness_law=law)         # read once, not again per design
    scored, rows, failed = [], [], None
    for i, s in enumerate(candidates):
        tag = f"stretch {s:g} ({i + 1}/{len(candidates)})"
        each = None if progress is None else (lambda e, tag=tag: progress({**e, "candidate": tag}))
        try:
            d = design(V, F, o, where=where, stretch=s, progress=each)
        except SelfshapeError as e:
            # this stretch cannot make the design (e.g. its pattern does not fit the bed): the
            # others may; the error is kept in the choice and raised if no stretch can
            failed = e
            rows.append({"stretch": s, "error": str(e)})
            continue
        row = reach_score(d)
        rows.append(row)
        # ties keep the earlier (larger) stretch: a later one must score lower by more than 1e-9
        pos = sum(1 for _, r in scored if r["score"] <= row["score"] + 1e-9)
        scored.insert(pos, (d, row))
        del scored[max(int(keep), 1):]       # the designs not kept are not held
    if not scored:
        raise failed
    return [d for d, _ in scored], {"candidates": rows, "chosen": scored[0][1]["stretch"]}


# ----------------------------------------------------------------------------- the verb
VERIFY_KEYS = ("verify_converged", "verify_reason", "verify_newton_iterations", "verify_n_triangles",
               "verify_simulation_s", "deviation_pct_bbox", "deviation_target_to_deployed_pct_bbox",
               "deviation_p99_pct_bbox", "icp_iterations", "verify_note", "flat_deviation_pct_bbox",
               "flat_deviation_target_to_flat_pct_bbox", "verify_warning")


def _write_design_files(out, d, raw, printer, title):
    """pattern.toml, flat.vtu, front.gcode (back.gcode when a ribbon is on the back),
    pattern.png and pattern.dxf/.svg (geometry.cad: the fabric outline and the ribbons as the
    pattern clips them, a layer per side and thickness) of design d into the OutputDir ``out``,
    each atomically; pattern.toml's numbers must be finite (shellfem.outfiles.NonFiniteOutput)."""
    from geometry import cad
    from geometry.patterns import parse_pattern, write_pattern
    from inverse.gcode import ribbons_to_gcode_files
    from shellfem.outfiles import check_finite

    check_finite(raw, "pattern.toml")
    out.write("pattern.toml", lambda tmp: write_pattern(tmp, raw))
    out.write("flat.vtu", lambda tmp: write_flat_vtu(d, tmp))
    out.written += ribbons_to_gcode_files(d.ribbons, out.makedirs(), printer)   # atomic on their own
    out.write("pattern.png", lambda tmp: plot_pattern(d, tmp, title=title))
    p_toml = out.file("pattern.toml")
    drawing = cad.pattern_drawing(parse_pattern(raw, p_toml, os.path.dirname(os.path.abspath(p_toml))))
    for n in ("pattern.dxf", "pattern.svg"):
        out.write(n, lambda tmp: cad.write_drawing(tmp, drawing))


def _means(rep) -> list | None:
    """[deployed -> target mean, target -> deployed mean] (% of the diagonal) of a verification,
    None if it has none (did not converge)."""
    a, b = rep.get("deviation_pct_bbox"), rep.get("deviation_target_to_deployed_pct_bbox")
    return [float(a[0]), float(b[0])] if rep.get("verify_converged") and a and b else None


def _deviation_score(rep) -> float | None:
    """Mean of the two one-way mean deviations (% of the diagonal) of a verification, None if
    it has none (did not converge)."""
    m = _means(rep)
    return None if m is None else 0.5 * (m[0] + m[1])


def _verify_candidates(cands, pattern_kw, base_file, parallel=None, progress=None):
    """Simulate the open-loop designs ``cands`` [(label, Design)] and keep the one that deploys
    nearest the target (_deviation_score: the mean of the two one-way mean deviations; a
    simulation that fails or does not converge loses; ties keep the earlier). Two at a time: the
    second of each pair in a forked worker (shellfem.forked) beside this process when
    ``parallel``. Why measured, not decided from the flattening: at s 1.2 the 110 mm hemisphere
    lands at 2.3 % for its proxy (DesignOptions.proxy) against 5.4 % for itself, while the hat
    and the beetle, as far out of their bounds, deploy as near or nearer designed for
    themselves; the stretch choice's score took 1.3 for a torus band whose design at 1.2
    deploys nearer (docs/notes.md, sessions 43-45). ``pattern_kw``:
    inverse.to_pattern.pattern_dict's keywords; ``base_file``: the pattern.toml path the
    patterns are read as. Returns (index kept, its Simulation or None, its verification's
    report entries, [_means per candidate])."""
    from geometry.patterns import parse_pattern
    from shellfem import forked

    base_dir = os.path.dirname(os.path.abspath(base_file))
    reps, best = [None] * len(cands), None          # best: (score, index, Simulation)
    for i in range(0, len(cands), 2):
        pair = [(k, parse_pattern(pattern_dict(cands[k][1], **pattern_kw), base_file, base_dir))
                for k in range(i, min(i + 2, len(cands)))]
        beside = None
        if len(pair) == 2 and forked.wanted(parallel) and getattr(pair[1][1], "solver_model", "shell") == "shell":
            try:
                beside = SimulationBeside(pair[1][1], label=f"the verification of the {cands[pair[1][0]][0]} design")
            except SelfshapeError:  # its meshing error: reported as the serial verification below reports it
                beside = None
        try:
            for n, (k, pattern) in enumerate(pair):
                sims = []
                reps[k] = verify_design(cands[k][1], pattern, None, sims=sims,
                                        progress=progress if n == 0 or beside is None else None,
                                        beside=beside if n == 1 else None)
                score = _deviation_score(reps[k])
                if best is None or (score is not None and (best[0] is None or score < best[0])):
                    best = (score, k, sims[0] if sims else None)       # the others' Simulations are dropped
        except BaseException:             # Ctrl-C or an internal error here: the worker does not outlive it
            if beside is not None:
                beside.cancel()
            raise
    return best[1], best[2], reps[best[1]], [None if m is None else [round(x, 4) for x in m]
                                              for m in map(_means, reps)]


def _fmt(x) -> str:
    return "n/a (not converged)" if x is None else f"{x:.2f}"


#: (posts, release steps) of the jig releases tried in turn: more posts hold more of the shape,
#: continuation steps move them from flat in smaller increments. Always in steps: a one-step
#: release drags the sheet from flat to the posts' positions at once, and on the 110 mm vault and
#: hemisphere it ran into the Newton cap or a degenerate state where the stepped one converged
#: (docs/notes.md, sessions 28, 31, 34)
JIG_TRIALS = ((4, 4), (8, 4))
#: Newton cap per mesh level of a jig release: the posts start the sheet near the refined state,
#: a release that needs more is not reaching it (a 110 mm hat on 4 posts ran > 25 min uncapped)
JIG_MAX_ITERATIONS = 600


def jig_patterns(refined_raw, printed_points, triangles, near_x) -> list:
    """[(posts, release steps, pattern dict)] of the JIG_TRIALS: the refined pattern with the posts
    (inverse.jig) at the state nearest the target as [[support]], its release stepped and capped."""
    from inverse.jig import jig_supports

    out = []
    for k, steps in JIG_TRIALS:
        raw_j = {**refined_raw, "support": jig_supports(printed_points, near_x, k, triangles=triangles)}
        solver = dict(raw_j.get("solver", {}))
        solver["max_iterations"] = min(int(solver.get("max_iterations", JIG_MAX_ITERATIONS)), JIG_MAX_ITERATIONS)
        if steps > 1:
            solver["release_steps"] = steps
        raw_j["solver"] = solver
        out.append((k, steps, raw_j))
    return out


def _simulate_dict(raw_, path, base_dir):
    """The simulation of a pattern dict (read as the file ``path`` would be): run in a worker."""
    from forward.simulate import simulate
    from geometry.patterns import parse_pattern

    return simulate(parse_pattern(raw_, path, base_dir))


class _JigQueue:
    """The jig releases (jig_patterns), each simulated beside the parent's work in a forked
    worker (shellfem.forked) when ``parallel``: the next jig is started while the previous one
    (or the release from flat) is being decided, and cancelled when not needed. Why: when the
    two refinement starts settled in different states, release from flat missed the refined
    state in 6 of 7 targets, and 4 posts missed it in 5 of those 6 (docs/notes.md, session 39)."""

    def __init__(self, trials, path, parallel):
        self.trials, self.path, self.parallel = trials, path, parallel
        self.jobs = {}

    def start(self, i):
        """Start jig i beside this process (nothing if not parallel, started or out of range)."""
        from shellfem import forked

        if self.parallel and i < len(self.trials) and i not in self.jobs:
            raw_j = self.trials[i][2]
            self.jobs[i] = forked.start(_simulate_dict, raw_j, self.path, os.path.dirname(os.path.abspath(self.path)),
                                        label=f"the {self.trials[i][0]}-post jig release")

    def simulation(self, i):
        """Jig i's Simulation from its worker; None when it was not started or its run failed
        (the caller then simulates it itself, and reports the failure as a serial run would)."""
        job = self.jobs.pop(i, None)
        if job is None:
            return None
        try:
            return job.result()
        except SelfshapeError:
            return None

    def cancel(self):
        for job in self.jobs.values():
            job.cancel()
        self.jobs = {}


def _try_jig(block, rep, candidates, trials, name, write_and_verify, reaches_near, queue=None):
    """Release the refined design held on jig posts (inverse.jig) at its state nearest the target,
    with the JIG_TRIALS posts and release steps (``trials``: jig_patterns) in turn until one reaches that state; records block["jig"] (posts, the
    deviations, the largest post reaction in N, whether the state was reached) and sets
    candidates["jig"] = (score, verification, pattern dict with the posts as [[support]], its simulation) for the
    first jig that reaches the state or, when none does, the converged one that deploys nearest the target: posts
    that hold the sheet near (not at) the refined state still give a design, which the caller keeps only if it
    deploys nearer than the free releases (a 110 mm bump: 8 posts 0.75 / 3.24 % at 0.034 N against the open
    loop's 2.20 / 4.48 %, with the refined state at 0.69 / 2.68 %). ``queue``: a _JigQueue whose
    workers simulate the jigs ahead (the next one starts while this one is decided)."""
    from inverse.jig import support_reactions

    tried = []
    for i, (k, steps, raw_j) in enumerate(trials):
        sims_j: list = []
        ahead = None
        if queue is not None:
            queue.start(i)
            queue.start(i + 1)
            ahead = queue.simulation(i)
        try:
            write_and_verify(raw_j, name + " (refined, on a jig)", sims_j, simulation=ahead)
        except SelfshapeError as e:        # this jig cannot be simulated: the next one, or no jig
            tried.append({"posts": k, "release_steps": steps, "reached": False, "error": str(e)})
            continue
        reached = reaches_near(rep)
        reaction = float(support_reactions(sims_j[0]).max(initial=0.0)) if sims_j and rep.get("verify_converged") \
            else None
        tried.append({"posts": k, "release_steps": steps, "reached": bool(reached), "max_post_reaction_n": reaction,
                      **{key: rep.get(key) for key in ("deviation_pct_bbox", "deviation_target_to_deployed_pct_bbox",
                                                       "verify_newton_iterations", "verify_reason")}})
        score = _deviation_score(rep)
        if reached or (score is not None and ("jig" not in candidates or score < candidates["jig"][0])):
            candidates["jig"] = (score, {key: rep[key] for key in VERIFY_KEYS if key in rep}, raw_j,
                                 sims_j[0] if sims_j else None)
            block["jig"] = tried[-1]
        if reached:
            block["jig"] = {**tried[-1], "tried": tried}
            if queue is not None:
                queue.cancel()
            return
    note = ("no jig tried (posts, release steps: " + ", ".join(map(str, JIG_TRIALS)) + ") selected the refined state")
    if "jig" in candidates:
        block["jig"] = {**block["jig"], "tried": tried, "note": note + f"; the {block['jig']['posts']} posts hold the "
                        f"sheet nearest the target of them"}
    else:
        block["jig"] = {"posts": None, "reached": False, "tried": tried, "note": note}


def _write_before_after(out, d, before, after, label, name):
    """refine.png (inverse.plots.plot_before_after): the open-loop simulation ``before`` and the
    refined one ``after`` (forward.simulate.Simulation, either None or not converged: left out),
    each registered to the target as the verification does; nothing when neither converged."""
    from inverse.plots import plot_before_after

    states = []
    for lab, sim in (("open loop", before), (label, after)):
        if sim is None or not sim.summary()["converged"]:
            continue
        Xr, pct, back, _ = register_simulation(d, sim)
        states.append((lab, Xr, sim.sheet.triangles, pct, back))
    if states:
        out.write("refine.png", lambda tmp: plot_before_after(d, states, tmp, title=f"{name}: --refine"))


def _refine_and_rewrite(d, o, rep, pattern, sims, name, out, refine_options, smoothness, verbose, pattern_kw,
                        raw, progress=None, parallel=None, beside=None):
    """The --refine stage of design_file: refine, then rewrite pattern.toml, G-code, pattern.png
    and the verification (into the OutputDir ``out``) for the rounded refined thicknesses; on
    failure keep the open-loop design and record why (report "refine": {"ok": false, "reason": ...}).
    A refined design whose release from flat deploys farther from the target than the open loop
    (mean of both one-way mean deviations) is not kept either: the open-loop files (``raw``, its
    pattern dict) are written again and re-verified, and "refine" records both ("kept"). When
    release from flat misses the refined state (the equilibrium nearest the target), the
    release is tried again held on jig posts at that state (_try_jig); a jig that reaches it and
    deploys nearest the target is written into pattern.toml as [[support]] ("refined, on a jig").
    ``beside``: the open-loop verification's inverse.verify.SimulationBeside, still releasing the
    sheet in its worker while the refinement starts from the target (``sims`` then empty): its
    verification is written into ``rep`` here, once the refinement no longer runs."""
    from geometry.patterns import parse_pattern
    from inverse.design_refine import refine_design
    from inverse.printer import Printer
    from shellfem import forked

    t = time.perf_counter()
    printer = o.printer or Printer()
    oob = rep.get("sigma_out_of_bounds_pct")
    nothing = {"ok": False, "reason": "the open-loop simulation could not run: nothing to refine from"}
    if beside is None and not sims:
        rep["refine"] = nothing
        return
    before = [r.thickness_mm for r in d.ribbons]

    def restore_open_loop():
        """The ribbons' open-loop thicknesses back (refine_design set the rounded refined ones)."""
        for r, t0 in zip(d.ribbons, before):
            r.thickness_mm = t0
    failed = None
    try:
        block, near_x = refine_design(d, pattern, beside if beside is not None else sims[0], printer, refine_options,
                                      smoothness=smoothness, verbose=verbose, progress=progress, parallel=parallel)
    except SelfshapeError as e:
        failed = e
    except BaseException:                           # Ctrl-C or a bug: no worker left behind
        if beside is not None:
            beside.cancel()
        raise
    if beside is not None:
        # the open-loop verification, simulated beside the refinement: registered and written now
        # (from the worker's simulation and the target; the ribbons' thicknesses are not read)
        t_v = time.perf_counter()
        rep.update(verify_design(d, pattern, out, sims=sims, beside=beside))
        rep["stages_s"]["verify"] = round(float(rep.get("verify_simulation_s") or 0.0) + time.perf_counter() - t_v, 3)
        rep["verify_beside_refine"] = True
        if not sims:
            restore_open_loop()
            rep["refine"] = nothing
            return
    if failed is not None:
        restore_open_loop()
        rep["refine"] = {"ok": False, "reason": str(failed), "seconds": round(time.perf_counter() - t, 2),
                         "note": "the open-loop design is kept"}
        return
    rep["open_loop"] = {k: rep[k] for k in VERIFY_KEYS if k in rep}
    rep["open_loop"]["thickness_histogram"] = rep.get("thickness_histogram")

    verified = {}

    def write_and_verify(raw_, title, sims_=None, simulation=None, beside=None):
        """Write the design files of ``raw_`` and replace the report's verification by its own;
        verified["last"]: its simulation (None if it could not run). ``simulation``: the one
        an earlier call (or a worker) ran for this same ``raw_``, written instead of re-simulated.
        ``beside``: called once the files are written, before the simulation (to start a worker)."""
        sims_ = [] if sims_ is None else sims_
        verified["last"], verified["raw"] = None, raw_
        p_toml = out.file("pattern.toml")
        _write_design_files(out, d, raw_, o.printer, title)
        if beside is not None:
            beside()
        rep.update(report_dict(d))
        for k in VERIFY_KEYS:
            rep.pop(k, None)
        if progress is not None:
            progress({"stage": "verify"})
        rep.update(verify_design(d, parse_pattern(raw_, p_toml, os.path.dirname(os.path.abspath(p_toml))), out,
                                 sims=sims_, progress=progress, simulation=simulation))
        verified["last"] = sims_[-1] if sims_ else None
    refined_raw = pattern_dict(d, seed=o.seed, target_name=name, **pattern_kw)
    near = block.get("rounded", {})

    def reaches_near(rep_):
        """Release reaches the refined state if its deviations match the state nearest the target."""
        rel = rep_.get("deviation_pct_bbox")
        if not (near.get("deviation_pct_bbox") and rel and rep_.get("verify_converged")):
            return False
        return all(abs(a - b) <= 0.25 + 0.1 * b for a, b in zip(
            rel + rep_["deviation_target_to_deployed_pct_bbox"],
            near["deviation_pct_bbox"] + near["deviation_target_to_deployed_pct_bbox"]))
    trials = jig_patterns(refined_raw, sims[0].sheet.points, sims[0].sheet.triangles, near_x) \
        if near_x is not None and near.get("deviation_pct_bbox") else []
    # two refinement starts that settled in different states: a multistable sheet, whose release
    # from flat mostly misses the refined state; the first jig is then simulated beside that release
    two_states = sum(1 for r in block.get("starts", []) if r.get("converged")) >= 2
    queue = _JigQueue(trials, out.file("pattern.toml"), forked.wanted(parallel) and two_states) if trials else None
    try:
        write_and_verify(refined_raw, name + " (refined)", beside=(lambda: queue.start(0)) if queue else None)
        verified["refined"] = verified["last"]
        if near.get("deviation_pct_bbox"):
            block["release_reaches_refined_state"] = reaches_near(rep)
        candidates = {"refined": (_deviation_score(rep), {k: rep[k] for k in VERIFY_KEYS if k in rep}, refined_raw,
                                  verified["refined"])}
        if trials and not block["release_reaches_refined_state"]:
            _try_jig(block, rep, candidates, trials, name, write_and_verify, reaches_near, queue)
    finally:
        if queue is not None:
            queue.cancel()
    open_score = _deviation_score(rep["open_loop"])
    scored = {k: v for k, v in candidates.items() if v[0] is not None}
    best = min(scored, key=lambda k: scored[k][0]) if scored else None
    if best is not None and (open_score is None or scored[best][0] <= open_score):
        block["kept"] = "refined" if best == "refined" else "refined, on a jig"
        if best != "refined":
            j = block["jig"]
            held = ("the sheet reaches it" if j["reached"] else
                    f"the sheet deploys near it, its posts carrying up to {_fmt(j.get('max_post_reaction_n'))} N")
            block["release_note"] = (f"release from flat lands in another equilibrium than the one nearest the target "
                                     f"(mean of both directions {_fmt(candidates['refined'][0])} %); held on the "
                                     f"{j['posts']} jig posts of pattern.toml's [[support]] while "
                                     f"released, {held} ({scored[best][0]:.2f} %)")
        if verified.get("raw") is not scored[best][2]:
            write_and_verify(scored[best][2], name + (" (refined)" if best == "refined" else " (refined, on a jig)"),
                             simulation=scored[best][3])
    else:
        # the refined design, rounded and released from flat (and on a jig, if one was tried),
        # deploys farther from the target than the open loop: keep the open loop
        block["refined_released"] = candidates["refined"][1]
        block["refined_thickness_mm"] = [r.thickness_mm for r in d.ribbons]
        restore_open_loop()
        write_and_verify(raw, name, simulation=sims[0])      # its verification, written again, not re-run
        block["kept"] = "open loop"
        block["kept_note"] = (f"the refined design deploys from flat farther from the target than the open loop "
                              f"(mean of both directions {_fmt(candidates['refined'][0])} % against {_fmt(open_score)} %"
                              + (f"; on a jig {_fmt(candidates['jig'][0])} %" if "jig" in candidates else "")
                              + "): the open-loop design is kept and written")
        if block.get("release_reaches_refined_state") is False and "jig" not in candidates:
            block["release_note"] = "release from flat lands in another equilibrium than the one nearest the target"
    if block["kept"] == "open loop":
        after, label = verified.get("refined"), "refined, released from flat (not kept)"
    else:
        after = verified.get("last")
        label = "refined, released from flat" if block["kept"] == "refined" else \
            f"refined, released on {block['jig']['posts']} jig posts"
    _write_before_after(out, d, sims[0], after, label, name)
    if oob is not None and max(oob) > 1.0:
        block["feasibility"] = (f"the flattening is out of the stretch bounds on {oob[0]:.1f} % / {oob[1]:.1f} % "
                                f"of the area (sigma1 / sigma2): the fabric cannot reach the target there; "
                                f"the best design found is returned")
    block["ok"] = True
    rep["refine"] = block
    rep["stages_s"]["refine"] = round(time.perf_counter() - t, 3)


def design_file(target_path, out_dir, options: DesignOptions | None = None, *, verify: bool = False,
                mesh_size_mm: float = VERIFY_MESH_SIZE_MM, mesh_across: float | None = VERIFY_MESH_ACROSS,
                verify_iterations: int | None = VERIFY_ITERATIONS,
                metric_floor: float | None = None, refine: bool = False, refine_options=None,
                refine_smoothness: float = 0.05, verbose: bool = False, inputs=(), progress=None, parallel=None,
                **overrides) -> dict:
    """`selfshape design TARGET -o DIR`: writes DIR/pattern.toml, flat.vtu, front.gcode (and
    back.gcode when a ribbon is on the back), pattern.png and report.json (last); with
    ``verify`` also deployed.vtu, deployed.obj/.stl/.ply, verify.png and the deviation in
    report.json; with ``refine`` refine.png (the open-loop and the refined deployment);
    pattern.dxf/.svg (the flat pattern for CAD and laser cutting) and index.html (forward.view:
    deployed surface, target ghost and flat pattern in a browser) always.

    ``options``/``overrides``: the design's DesignOptions, as for `design`. mesh_size_mm,
    mesh_across: pattern.toml's [mesh] (default: inverse.to_pattern.VERIFY_MESH_SIZE_MM / _ACROSS,
    the discretisation of the README's design figures; None: the pattern defaults). verify_iterations: Newton cap of
    the verification, written to pattern.toml's [solver] max_iterations (default
    inverse.to_pattern.VERIFY_ITERATIONS; None: the simulator's 300);
    metric_floor: [solver] metric_floor (default: the simulator's 10). The verification
    simulates the written pattern from memory (`inverse.verify.verify_design`). ``refine``
    (implies verify): the thicknesses are then refined with the shell in the loop
    (inverse.design_refine; ``refine_options``: inverse.refine.RefineOptions,
    ``refine_smoothness`` its regulariser weight), rounded to the printer's layers, and the
    files and the report's deviations are the refined design's; report.json "open_loop" keeps
    the open-loop verification and "refine" the iteration. A refinement that fails keeps the
    open-loop design and says why in "refine". time_s is the
    design time (read to written outputs, Table 5.1's "Time"), total_time_s includes the
    verification. The output folder is checked before the design runs and the outputs of an
    earlier run there (OUTPUTS, no other file) are removed first; every file is written
    atomically, none with a non-finite number; on failure (Ctrl-C included) every file this run
    wrote is removed (shellfem.outfiles.OutputDir). ``inputs``: other input files the outputs
    must not overwrite (the CLI's --printer TOML). ``progress``: called with a dict per event
    (`design`'s stages, {"stage": "write"}, {"stage": "verify"} and then the simulation's,
    forward.simulate.simulate_sheet; {"stage": "refine"}), for the CLI's status line.
    ``parallel`` (None: when the machine has two or more cores): the refinement's independent
    solves side by side in forked workers, one core each (the open-loop verification beside the
    refinement from the target, which needs only the mesh; its two starts; the jig releases
    beside the release from flat; report.json "verify_beside_refine"), to the same bits as one
    after the other (docs/notes.md has the timings). Returns the report dict."""
    from geometry.target import read_mesh
    from shellfem import forked
    from shellfem.outfiles import OutputDir

    t_start = time.perf_counter()
    from geometry.patterns import parse_pattern, solver_options
    # the values go to pattern.toml's [solver]: checked as load_pattern will check them
    solver_options({k: v for k, v in (("max_iterations", verify_iterations), ("metric_floor", metric_floor))
                    if v is not None}, "verification [solver] (--verify-iterations, --metric-floor)")
    # [mesh] of the written pattern, checked before the design runs (named as the caller gave them)
    from geometry.schema import PATTERN_NUMBERS, number
    number(mesh_size_mm, "design: mesh size (--mesh-size, mesh_size_mm)", PATTERN_NUMBERS["mesh"]["size_mm"])
    if mesh_across is not None:
        number(mesh_across, "design: rows across a ribbon (--mesh-across, mesh_across)", PATTERN_NUMBERS["mesh"]["across"])
    name = os.path.basename(str(target_path))
    o = replace(options or DesignOptions(), **overrides)
    check_design_numbers(o)
    if o.proxy is None:
        o = replace(o, proxy="auto" if refine else False)
    V, F = read_mesh(target_path)
    law = o.thickness_law if isinstance(o.thickness_law, (str, os.PathLike)) else None
    # checked before the design runs; an earlier run's files are removed first (shellfem.outfiles)
    out = OutputDir(out_dir, OUTPUTS, inputs=[target_path, law, *inputs])
    with out:
        choice = None
        verifying = verify or refine
        # stretch_candidates: the designs at the best stretches, verified below when there is a verification
        keep = o.stretch_candidates if o.stretch == "auto" and verifying else 1
        # proxy "auto": the target's own designs first (their stretch chosen for the target), then the proxy's
        o_first = replace(o, proxy=False) if o.proxy == "auto" else o
        if o.stretch == "auto":
            ds, choice = rank_stretches(V, F, o_first, where=name, progress=progress, keep=keep)
        else:
            ds = [design(V, F, o_first, where=name, progress=progress)]
        cands = [("target", dd) for dd in ds]
        choices = {"target": choice}
        if o.proxy == "auto" and verifying:
            # the proxy is sought where the target's first design leaves the stretch bounds; where
            # its bounds admit the target (the saddle), the proxy's designs would be the target's
            d0 = ds[0]
            _, info = proxy_surface(d0.V_input, d0.F_input, d0.bounds, d0.lam, o.proxy_smooth_mm, o.stop)
            if info["used"]:
                # the proxy's designs choose their own stretches (the proxy's flattening is within other bounds)
                o_p = replace(o, proxy=True)
                alts, choices["proxy"] = rank_stretches(V, F, o_p, where=name, progress=progress, keep=keep) \
                    if o.stretch == "auto" else ([design(V, F, o_p, where=name, progress=progress)], None)
                info, s_checked = alts[0].proxy, alts[0].stretch
            else:
                s_checked = d0.stretch
            if info["used"]:
                # paired target / proxy at each rank: the first pair is simulated side by side
                cands = [c for pair in itertools.zip_longest(cands, [("proxy", a) for a in alts]) for c in pair if c]
            else:
                for dd in ds:
                    dd.proxy = {**info, "auto": {"target": None, "proxy": None, "kept": "target", "stretch": s_checked}}
        elif o.proxy == "auto":
            for dd in ds:
                dd.proxy = {"used": False, "auto": "not verified: designed for the target"}
        pattern_kw = dict(mesh_size_mm=mesh_size_mm, mesh_across=mesh_across, seed=o.seed, target_name=name,
                          max_iterations=verify_iterations, metric_floor=metric_floor)
        verified = None             # several candidates: (Simulation or None, report entries, seconds) of the kept
        if len(cands) > 1:
            t = time.perf_counter()
            if progress is not None:
                progress({"stage": "verify"})
            k, sim_v, rep_v, means = _verify_candidates(cands, pattern_kw, out.file("pattern.toml"), parallel, progress)
            label, d = cands[k]
            verified = (sim_v, rep_v, time.perf_counter() - t)
            if any(lab == "proxy" for lab, _ in cands):
                # each kind's nearest verified design (its best by the score where none converged)
                best = {lab: min(((dd, m) for (l2, dd), m in zip(cands, means) if l2 == lab),
                                 key=lambda dm: np.inf if dm[1] is None else sum(dm[1])) for lab in ("target", "proxy")}
                d.proxy = {**best["proxy"][0].proxy, "used": label == "proxy",
                           "auto": {"target": best["target"][1], "proxy": best["proxy"][1], "kept": label}}
            choice = choices[label]
            if keep > 1 and choice is not None:
                choice = {**choice, "chosen": d.stretch, "by": "verification",
                          "verified": [{"design": lab, "stretch": dd.stretch, "deviation_means_pct": m}
                                       for (lab, dd), m in zip(cands, means)]}
        else:
            d = ds[0]
        t = time.perf_counter()
        if progress is not None:
            progress({"stage": "write"})
        raw = pattern_dict(d, **pattern_kw)
        _write_design_files(out, d, raw, o.printer, name)
        d.times["write"] = time.perf_counter() - t
        rep = {"target": os.path.abspath(str(target_path)), "time_s": None}
        rep.update(report_dict(d))
        if choice is not None:
            rep["stretch_choice"] = choice
        rep["stages_s"] = {k: round(v, 3) for k, v in d.times.items()}
        rep["stages_cpu_s"] = {k: round(v, 3) for k, v in d.cpu_times.items()}
        rep["time_s"] = round(time.perf_counter() - t_start - (verified[2] if verified is not None else 0.0), 3)
        if verify or refine:
            t = time.perf_counter()
            p_toml = out.file("pattern.toml")
            pattern = parse_pattern(raw, p_toml, os.path.dirname(os.path.abspath(p_toml)))
            sims = []
            beside = None
            if progress is not None and verified is None:    # else said before the candidates' verifications
                progress({"stage": "verify"})
            if verified is not None:         # both open loops verified above: the kept one's files
                sim_v, rep_v, seconds_v = verified
                rep.update(verify_design(d, pattern, out, sims=sims, simulation=sim_v) if sim_v is not None else rep_v)
                rep["stages_s"]["verify"] = round(seconds_v, 3)
            elif refine and forked.wanted(parallel) and getattr(pattern, "solver_model", "shell") == "shell":
                # the refinement from the target needs only the mesh: the open-loop verification's
                # release from flat runs beside it in a worker (a meshing error: the verification
                # below reports it as a serial run does)
                try:
                    beside = SimulationBeside(pattern, label="the open-loop verification")
                except SelfshapeError:
                    beside = None
            if beside is None and verified is None:
                rep.update(verify_design(d, pattern, out, sims=sims, progress=progress))
                rep["stages_s"]["verify"] = round(time.perf_counter() - t, 3)
            if refine:
                if progress is not None:
                    progress({"stage": "refine"})
                _refine_and_rewrite(d, o, rep, pattern, sims, name, out, refine_options, refine_smoothness, verbose,
                                    dict(mesh_size_mm=mesh_size_mm, mesh_across=mesh_across,
                                         max_iterations=verify_iterations, metric_floor=metric_floor),
                                    raw=raw, progress=progress, parallel=parallel, beside=beside)
        rep["total_time_s"] = round(time.perf_counter() - t_start, 3)
        from forward.view import folder_page
        out.write_text("index.html", folder_page(out.path, rep))        # the 3D page (forward.view)
        rep["files"] = sorted({os.path.basename(p) for p in out.written if os.path.exists(p)} | {"report.json"})
        out.write_json("report.json", rep)          # last: a folder with a report.json is complete
        return rep
