"""Conforming triangle meshes of patterns with Gmsh (printed-state mm).

The fabric outline is cut by every printed polygon so that each Gmsh surface lies
entirely inside or outside each printed element. Two ways, same result (tested):
kernel "geo" (default) computes the planar arrangement with shapely (geometry.arrangement:
snap-rounded noding + polygonize, 0.1 s for 800 ribbons) and gives it to Gmsh's built-in
kernel with shared points and lines; kernel "occ" fragments the outline with all pieces in
OpenCASCADE (robust too, but its fragment and meshing take about 2x longer). Printed
regions are those of geometry.arrangement. A triangle's plastic
thickness on each face is the sum of the thicknesses of the elements covering it on that
face (front and back separately).

Mesh size: ``size_mm`` in bare fabric; inside a printed surface min(size_mm,
width / across) where width = 2 area / perimeter of the element and of the surface
(= the strip width for a ribbon or a star arm) and across = [mesh] across, default 2
(triangle rows across the narrowest feature; a surface narrower than its elements, e.g.
an overlap sliver, is refined at most 4x beyond them); the fabric grades from a feature's size
back to ``size_mm`` at ``grading`` mm per mm of distance (0.4). Sizes are quantised to
steps of 15 % (classes h_min * 1.15**k) so that a few Gmsh fields cover any number of
elements.
"""
from __future__ import annotations

import contextlib
import math
import time

import numpy as np
import shapely
from shapely.geometry import Polygon

from geometry.arrangement import GRID, arrangement, feature_width, piece_regions, printed_pieces
from geometry.mesh_quality import mesh_quality
from geometry.msh import add_physical_groups, write_msh
from geometry.schema import DETAIL_MM, MAX_POLYGON_VERTICES, MAX_TRIANGLES
from shellfem.errors import SelfshapeError
from shellfem.sheet import Sheet

ACROSS = 2.0          # triangle rows across the narrowest part of a printed feature
GRADING = 0.4         # growth of the fabric's target size per mm of distance to print, mm/mm
SIZE_STEP = 1.15      # ratio between quantised size classes
ALGORITHM = 6         # Gmsh 2D algorithm: 6 = Frontal-Delaunay (best angles), 5 = Delaunay
KERNEL = "geo"        # "geo": shapely arrangement + built-in kernel; "occ": OpenCASCADE fragment


@contextlib.contextmanager
def gmsh_session(name: str = "selfshape"):
    """Initialise Gmsh quietly (General.Terminal = 0) with a fresh model; always clean up.

    If Gmsh is already initialised by the caller, only the model is added and removed.
    """
    import gmsh
    own = not gmsh.isInitialized()
    if own:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(name)
        yield gmsh
    finally:
        if own:
            gmsh.finalize()
        else:
            with contextlib.suppress(Exception):
                gmsh.model.setCurrent(name)
                gmsh.model.remove()


# ---------------------------------------------------------------- mesh sizes

def quantise_size(h, size_mm: float, base: float | None = None) -> np.ndarray:
    """Round target sizes down to base * SIZE_STEP**k (k >= 0 integer), capped at size_mm.

    ``base`` defaults to the smallest of ``h``, so the finest features get exactly their size.
    """
    h = np.minimum(np.asarray(h, float), size_mm)
    base = float(h.min()) if base is None else min(float(base), size_mm)
    k = np.floor(np.log(h / base) / math.log(SIZE_STEP) + 1e-9)
    return np.where(h >= size_mm, size_mm, np.minimum(base * SIZE_STEP ** np.maximum(k, 0), size_mm))


def estimate_triangles(outline_area: float, piece_areas, piece_perimeters, piece_h, size_mm: float,
                       grading: float = GRADING) -> float:
    """Triangles a mesh will have, estimated before meshing (equilateral triangles of edge h
    cover sqrt(3)/4 h^2 each): the fabric at ``size_mm``, each printed piece at its size h_p,
    and the graded band around each piece, where the size grows as h_p + grading * d, which
    adds perimeter / grading * (1 / h_p - 1 / size_mm) per unit density. Overlaps are
    counted twice (an upper estimate); a Gmsh mesh has 0.5-2x this (0.5 where a print covers the whole fabric, up to 2 for small stars)."""
    c = 4.0 / math.sqrt(3.0)
    hp = np.minimum(np.asarray(piece_h, float), size_mm)
    n = outline_area / size_mm ** 2
    n += float(np.sum(np.asarray(piece_areas, float) / hp ** 2))
    n += float(np.sum(np.asarray(piece_perimeters, float) / grading * (1.0 / hp - 1.0 / size_mm)))
    return c * n


def check_mesh_budget(where: str, n_estimate: float, size_mm: float) -> None:
    """Refuse a mesh estimated above MAX_TRIANGLES, in one line, before Gmsh runs for hours."""
    if n_estimate > MAX_TRIANGLES:
        raise SelfshapeError(f"{where}: mesh size {size_mm:g} mm would need about {n_estimate:.3g} triangles, "
                             f"more than the {MAX_TRIANGLES:,} selfshape meshes; use a larger [mesh] size_mm "
                             f"(or --size) or a smaller [mesh] across")


def check_polygon_vertices(pattern, geoms, owner) -> None:
    """Refuse, before Gmsh, a fabric outline or printed piece with more than
    MAX_POLYGON_VERTICES vertices (after the DETAIL_MM simplification): Gmsh's set-up of a
    boundary loop grows with the square of its vertices (40,000 took 6.5 s, 100,000 > 60 s)."""
    counts = shapely.get_num_coordinates(np.asarray(geoms, dtype=object)) if len(geoms) else np.zeros(0, int)
    n_outline = shapely.get_num_coordinates(pattern.outline)
    if n_outline > MAX_POLYGON_VERTICES:
        raise SelfshapeError(f"{pattern.source}: the fabric outline has {n_outline:,} vertices, more than the "
                             f"{MAX_POLYGON_VERTICES:,} selfshape meshes; simplify it")
    if len(counts) and counts.max() > MAX_POLYGON_VERTICES:
        k = int(np.argmax(counts))
        e = pattern.elements[int(owner[k])]
        raise SelfshapeError(f"{pattern.source}: {getattr(e, 'label', None) or 'a printed element'} has "
                             f"{int(counts[k]):,} boundary vertices (detail above {DETAIL_MM:g} mm), more than the "
                             f"{MAX_POLYGON_VERTICES:,} selfshape meshes; simplify it")


# ---------------------------------------------------------------- gmsh model

class _Face:
    """A Gmsh surface: the pieces covering it, its boundary curves and their lengths, its width."""

    def __init__(self, pieces, curves, lengths, width):
        self.pieces, self.curves, self.lengths, self.width = pieces, curves, lengths, width


def _build_geo(gmsh, outline: Polygon, geoms) -> dict:
    """Built-in kernel on a shapely arrangement: shared points and lines, no booleans."""
    geo = gmsh.model.geo
    faces, cover = arrangement(outline, geoms)
    rings = [[np.asarray(r.coords)[:-1] for r in [f.exterior, *f.interiors]] for f in faces]
    allv = np.vstack([r for rs in rings for r in rs])
    uv, inv = np.unique(allv, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    ptag = [geo.addPoint(float(x), float(y), 0.0) for x, y in uv]
    seg, out, pos = {}, {}, 0
    for k, rs in enumerate(rings):
        loops, curves, lengths = [], [], []
        for r in rs:
            ids = inv[pos:pos + len(r)].tolist()
            pos += len(r)
            tags = []
            for a, b in zip(ids, ids[1:] + ids[:1]):
                key = (a, b) if a < b else (b, a)
                if key not in seg:
                    seg[key] = geo.addLine(ptag[key[0]], ptag[key[1]])
                tags.append(seg[key] if a == key[0] else -seg[key])
            loops.append(geo.addCurveLoop(tags))
            curves += [abs(t) for t in tags]
            lengths.append(np.linalg.norm(np.roll(r, -1, axis=0) - r, axis=1))
        tag = geo.addPlaneSurface(loops)
        out[tag] = _Face(cover[k], curves, np.concatenate(lengths), feature_width(faces[k:k + 1])[0])
    geo.synchronize()
    return out


def _occ_polygon(occ, poly: Polygon) -> int:
    """An OCC plane surface of ``poly``; every ring counter-clockwise (OCC finds the holes itself:
    a clockwise hole ring, as shapely orients it, was added to the area and never fragmented)."""
    loops = []
    for ring in [poly.exterior, *poly.interiors]:
        xy = np.asarray(ring.coords)[:-1] if ring.is_ccw else np.asarray(ring.coords)[-2::-1]
        pts = [occ.addPoint(float(x), float(y), 0.0) for x, y in xy]
        lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
        loops.append(occ.addCurveLoop(lines))
    return occ.addPlaneSurface(loops)


def _build_occ(gmsh, outline: Polygon, geoms, size_mm: float) -> dict:
    """OpenCASCADE kernel: fragment the outline with all pieces."""
    occ = gmsh.model.occ
    gmsh.option.setNumber("Geometry.OCCParallel", 0)
    fabric = _occ_polygon(occ, shapely.set_precision(outline, GRID))
    tags = [_occ_polygon(occ, g) for g in geoms]
    cover = {fabric: []}
    if tags:
        gmsh.option.setNumber("Geometry.ToleranceBoolean", 1e-6 * max(1.0, size_mm))
        _, fmap = occ.fragment([(2, fabric)], [(2, t) for t in tags])
        cover = {t: [] for d, t in fmap[0] if d == 2}
        for i, m in enumerate(fmap[1:]):
            for d, t in m:
                if d == 2 and t in cover:
                    cover[t].append(i)
        stray = [(2, t) for d, t in occ.getEntities(2) if t not in cover]
        if stray:                                 # bits of print outside the fabric (rounding)
            occ.remove(stray, recursive=True)
    occ.synchronize()
    out = {}
    for f, p in cover.items():
        curves = [abs(c) for _, c in gmsh.model.getBoundary([(2, f)], combined=False, oriented=False)]
        lengths = np.array([occ.getMass(1, c) for c in curves])
        out[f] = _Face(np.array(sorted(p), np.int64), curves, lengths,
                       2.0 * occ.getMass(2, f) / max(lengths.sum(), 1e-300))
    return out


def _cover_from_mesh(gmsh, faces: dict, geoms) -> None:
    """Set each face's covering pieces from one of its triangles (OCC fragment maps can
    drop a piece with holes); exact because the mesh conforms to every piece."""
    tree = shapely.STRtree(geoms) if len(geoms) else None
    for f, face in faces.items():
        _, _, nodes = gmsh.model.mesh.getElements(2, f)
        if tree is None or not len(nodes) or not len(nodes[0]):
            face.pieces = np.zeros(0, np.int64)
            continue
        xyz = np.array([gmsh.model.mesh.getNode(int(n))[0] for n in nodes[0][:3]])
        c = shapely.points(xyz[:, :2].mean(axis=0))
        face.pieces = np.sort(tree.query(c, predicate="within")).astype(np.int64)


def _size_fields(gmsh, faces: dict, face_size: dict, size_mm: float, grading: float) -> None:
    """Constant size inside printed faces, graded by distance in the fabric (one field per size class)."""
    field = gmsh.model.mesh.field
    classes = {}
    for f, h in face_size.items():
        classes.setdefault(float(h), []).append(f)
    fids = []
    for h, tags in sorted(classes.items()):
        curves = sorted({c for f in tags for c in faces[f].curves})
        lengths = np.concatenate([faces[f].lengths for f in tags])
        fc = field.add("Constant")
        field.setNumber(fc, "VIn", h)
        field.setNumber(fc, "VOut", size_mm)
        field.setNumbers(fc, "SurfacesList", tags)
        field.setNumber(fc, "IncludeBoundary", 1)
        fids.append(fc)
        if h < size_mm and curves:
            fd = field.add("Distance")
            field.setNumbers(fd, "CurvesList", curves)
            field.setNumber(fd, "Sampling", int(np.clip(np.ceil(np.median(lengths) / h) + 1, 4, 200)))
            ft = field.add("Threshold")
            field.setNumber(ft, "InField", fd)
            field.setNumber(ft, "SizeMin", h)
            field.setNumber(ft, "SizeMax", size_mm)
            field.setNumber(ft, "DistMin", 0.0)
            field.setNumber(ft, "DistMax", (size_mm - h) / grading)
            fids.append(ft)
    if fids:
        fm = field.add("Min")
        field.setNumbers(fm, "FieldsList", fids)
        field.setAsBackgroundMesh(fm)


def _extract(gmsh, faces: dict, thickness, side, regions):
    """Nodes and triangles of the fabric faces, with region and thickness per triangle."""
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(node_tags)
    node_tags, xyz = node_tags[order], coords.reshape(-1, 3)[order]
    tris, reg, tf, tb, etags = [], [], [], [], []
    for f in sorted(faces):
        types, el, nodes = gmsh.model.mesh.getElements(2, f)
        for ty, e, nd in zip(types, el, nodes):
            if ty != 2:
                raise RuntimeError(f"gmsh produced element type {ty} on surface {f}; expected 3-node triangles")
            t = nd.reshape(-1, 3)
            p = faces[f].pieces
            tris.append(t)
            etags.append(e)
            reg.append(np.full(len(t), regions[p[0]] if len(p) else 0, np.int64))
            tf.append(np.full(len(t), thickness[p][side[p] > 0].sum() if len(p) else 0.0))
            tb.append(np.full(len(t), thickness[p][side[p] < 0].sum() if len(p) else 0.0))
    t = np.vstack(tris)
    used, inv = np.unique(t, return_inverse=True)
    idx = np.searchsorted(node_tags, used)
    sheet = Sheet(xyz[idx, :2], inv.reshape(-1, 3), np.concatenate(reg), np.concatenate(tf), np.concatenate(tb))
    return sheet, np.concatenate(etags)


def _mesh_model(gmsh, pattern, size_mm, across, grading, algorithm, kernel):
    size = float(pattern.mesh_size if size_mm is None else size_mm)
    across = float(getattr(pattern, "mesh_across", ACROSS) if across is None else across)
    if not (math.isfinite(size) and size > 0):
        raise SelfshapeError(f"{pattern.source}: mesh size must be > 0 mm, got {size_mm!r}")
    if not (math.isfinite(across) and across > 0):
        raise SelfshapeError(f"{pattern.source}: mesh across must be > 0, got {across!r}")
    if kernel not in ("geo", "occ"):
        raise ValueError(f"kernel must be 'geo' or 'occ', got {kernel!r}")
    floor = size * 1e-3
    # the budget on the elements as given, before the per-piece work (snapping, detail, union)
    # that grows with their count: 100,000 stars took minutes there before the budget below
    raw_geoms = np.array([e.geometry for e in pattern.elements], dtype=object)
    if len(raw_geoms):
        check_mesh_budget(pattern.source, estimate_triangles(
            pattern.outline.area, shapely.area(raw_geoms), shapely.length(raw_geoms),
            np.maximum(feature_width(raw_geoms) / across, floor), size, grading), size)
    geoms, thick, side, owner = printed_pieces(pattern.elements)
    check_polygon_vertices(pattern, geoms, owner)
    piece_h = np.maximum(feature_width(geoms) / across, floor)
    check_mesh_budget(pattern.source, estimate_triangles(pattern.outline.area, shapely.area(geoms),
                                                         shapely.length(geoms), piece_h, size, grading), size)
    regions = piece_regions(geoms)
    faces = _build_geo(gmsh, pattern.outline, geoms) if kernel == "geo" else \
        _build_occ(gmsh, pattern.outline, geoms, size)
    printed = [f for f, face in faces.items() if len(face.pieces)]
    face_size = {}
    if printed:
        # a face narrower than its pieces (an overlap sliver) is refined at most 4x further
        hp = np.array([piece_h[faces[f].pieces].min() for f in printed])
        hf = np.array([faces[f].width / across for f in printed])
        h = np.maximum(np.minimum(hp, hf), np.maximum(hp / 4.0, floor))
        face_size = dict(zip(printed, quantise_size(h, size).tolist()))
    for opt, v in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 0),
                   ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.MeshSizeMax", size), ("Mesh.Algorithm", algorithm),
                   ("Mesh.MaxNumThreads2D", 1), ("Mesh.ElementOrder", 1)):
        gmsh.option.setNumber(opt, v)
    _size_fields(gmsh, faces, face_size, size, grading)
    gmsh.model.mesh.generate(2)
    if kernel == "occ":
        _cover_from_mesh(gmsh, faces, geoms)
        printed = [f for f, face in faces.items() if len(face.pieces)]
    k = int(regions.max(initial=0))
    add_physical_groups(gmsh, [[f for f in printed if regions[faces[f].pieces[0]] == r] for r in range(1, k + 1)],
                        [f for f, face in faces.items() if not len(face.pieces)])
    return _extract(gmsh, faces, thick, side, regions)


def mesh_pattern(pattern, size_mm: float | None = None, across: float | None = None, grading: float = GRADING,
                 algorithm: int = ALGORITHM, kernel: str = KERNEL) -> Sheet:
    """Conforming mesh of a Pattern as a Sheet (mm): region id and front/back plastic
    thickness per triangle. ``size_mm`` and ``across`` override the pattern's [mesh]
    size_mm and across (triangle rows across the narrowest printed feature)."""
    with gmsh_session() as gmsh:
        sheet, _ = _mesh_model(gmsh, pattern, size_mm, across, grading, algorithm, kernel)
    return sheet


def coarse_meshes(pattern, n_fine: int, size_mm: float | None = None, levels: int | str = "auto",
                  grading: float = GRADING, algorithm: int = ALGORITHM, kernel: str = KERNEL) -> list:
    """Coarser conforming meshes of the same pattern, coarsest first, for nested iteration
    (shellfem.multilevel). Candidate j has COARSENING**j times the fine mesh's fabric size and
    printed element size (width / across; ``size_mm`` overrides [mesh] size_mm as in
    mesh_pattern); n_fine: the fine mesh's vertex count. A candidate is kept if it has at most
    MAX_LEVEL_RATIO times the vertices of the last kept (finer) level and at least
    MIN_COARSE_VERTICES; the first below that floor ends the hierarchy. ``levels``: "auto" = as
    many as that rule keeps, none for a fine mesh under MIN_FINE_VERTICES; an int = at most that
    many, the floor then 100 vertices."""
    from shellfem.multilevel import (COARSENING, MAX_CANDIDATES, MAX_LEVEL_RATIO, MIN_COARSE_VERTICES,
                                     MIN_FINE_VERTICES)
    if levels == "auto" and n_fine < MIN_FINE_VERTICES:
        return []
    size = float(pattern.mesh_size if size_mm is None else size_mm)
    across = float(getattr(pattern, "mesh_across", ACROSS))
    cap = MAX_CANDIDATES if levels == "auto" else int(levels)
    out, finer = [], int(n_fine)
    for j in range(1, MAX_CANDIDATES + 1):
        if len(out) >= cap:
            break
        f = COARSENING ** j
        try:
            sheet = mesh_pattern(pattern, size * f, across / f, grading, algorithm, kernel)
        except Exception:       # a coarse level is an accelerator only: one Gmsh cannot make ends the list
            break
        if sheet.n_vertices < (MIN_COARSE_VERTICES if levels == "auto" else 100):
            break
        if sheet.n_vertices <= MAX_LEVEL_RATIO * finer:
            out.append(sheet)
            finer = sheet.n_vertices
    return out[::-1]


def mesh_pattern_file(pattern_path, out_msh, size_mm: float | None = None) -> dict:
    """Mesh a pattern file (.toml, or .gcode: see geometry.patterns) and write a Gmsh .msh
    (geometry.msh: physical groups per region, element data region and thickness). The output
    is checked before meshing and written atomically (shellfem.outfiles.check_output_file).
    Returns dict(n_vertices, n_triangles, n_regions, min_angle_deg, time_s).
    """
    from geometry.patterns import load_pattern
    t0 = time.perf_counter()
    pattern = load_pattern(pattern_path)
    from shellfem.outfiles import check_output_file, write_atomic
    out_msh = check_output_file(out_msh, inputs=[pattern_path], suffix=".msh", create_parents=False,
                                what="mesh output")
    with gmsh_session() as gmsh:
        sheet, etags = _mesh_model(gmsh, pattern, size_mm, None, GRADING, ALGORITHM, KERNEL)
        write_atomic(out_msh, lambda tmp: write_msh(gmsh, tmp, sheet, etags))
    q = mesh_quality(sheet)
    return dict(n_vertices=q["n_vertices"], n_triangles=q["n_triangles"], n_regions=q["n_regions"],
                min_angle_deg=q["min_angle_deg"], time_s=time.perf_counter() - t0)
