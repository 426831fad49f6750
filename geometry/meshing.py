"""Conforming triangle meshes of patterns with Gmsh (printed-state mm).

The fabric outline is cut by every printed polygon so that each Gmsh surface lies
entirely inside or outside each printed element. Two ways, same result (tested):
kernel "geo" (default) computes the planar arrangement with shapely (snap-rounded noding
+ polygonize, 0.1 s for 800 ribbons) and gives it to Gmsh's built-in kernel with shared
points and lines; kernel "occ" fragments the outline with all pieces in OpenCASCADE
(robust too, but its fragment and meshing take about 2x longer). A printed *region* is a
connected component of the union of the printed geometry (region 0 = bare fabric, regions
1..K numbered in the order of their first element in the pattern). A triangle's plastic
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
import os
import re
import time

import numpy as np
import shapely
from shapely.geometry import Polygon

from shellfem.errors import SelfshapeError
from shellfem.sheet import Sheet

ACROSS = 2.0          # triangle rows across the narrowest part of a printed feature
GRADING = 0.4         # growth of the fabric's target size per mm of distance to print, mm/mm
SIZE_STEP = 1.15      # ratio between quantised size classes
ALGORITHM = 6         # Gmsh 2D algorithm: 6 = Frontal-Delaunay (best angles), 5 = Delaunay
KERNEL = "geo"        # "geo": shapely arrangement + built-in kernel; "occ": OpenCASCADE fragment
GRID = 1e-5           # mm: geometry is snap-rounded to this grid (merges round-off slivers)


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


# ---------------------------------------------------------------- printed geometry

def printed_pieces(elements, tol: float = None):
    """Split elements into simple polygon pieces (arrays in, arrays out).

    Returns (geoms, thickness, side, element): shapely Polygons snapped to a ``tol`` mm
    grid (default GRID), their plastic thickness (mm), side (+1 front, -1 back) and source element index.
    """
    tol = GRID if tol is None else tol
    geoms, thick, side, owner = [], [], [], []
    for i, e in enumerate(elements):
        g = shapely.set_precision(e.geometry, tol)
        for p in shapely.get_parts(g):
            if p.geom_type == "Polygon" and p.area > 0:
                geoms.append(p)
                thick.append(float(e.thickness_mm))
                side.append(1 if e.side == "front" else -1)
                owner.append(i)
    return (np.array(geoms, dtype=object), np.array(thick, float), np.array(side, np.int64),
            np.array(owner, np.int64))


def piece_regions(geoms) -> np.ndarray:
    """Region id (1..K) per piece: connected components of the union, numbered by first piece."""
    if len(geoms) == 0:
        return np.zeros(0, np.int64)
    parts = np.array(shapely.get_parts(shapely.union_all(geoms)), dtype=object)
    tree = shapely.STRtree(parts)
    pts = shapely.point_on_surface(geoms)
    ip, ic = tree.query(pts, predicate="intersects")
    comp = np.full(len(geoms), -1, np.int64)
    comp[ip] = ic                                   # a point on a piece lies in exactly one component
    if (comp < 0).any():
        raise RuntimeError("internal error: a printed piece is not inside the union of the print")
    first = np.full(len(parts), len(geoms), np.int64)
    np.minimum.at(first, comp, np.arange(len(geoms)))
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(parts), np.int64)
    rank[order] = np.arange(len(parts))
    return rank[comp] + 1


def region_elements(pattern) -> list[list[int]]:
    """For region k (index k - 1), the indices of the pattern's elements that form it."""
    geoms, _, _, owner = printed_pieces(pattern.elements)
    reg = piece_regions(geoms)
    return [sorted(set(owner[reg == k].tolist())) for k in range(1, int(reg.max(initial=0)) + 1)]


def feature_width(geoms) -> np.ndarray:
    """2 area / perimeter: the width of a strip, about the arm width of a star (mm)."""
    return 2.0 * shapely.area(geoms) / np.maximum(shapely.length(geoms), 1e-300)


def quantise_size(h, size_mm: float, base: float | None = None) -> np.ndarray:
    """Round target sizes down to base * SIZE_STEP**k (k >= 0 integer), capped at size_mm.

    ``base`` defaults to the smallest of ``h``, so the finest features get exactly their size.
    """
    h = np.minimum(np.asarray(h, float), size_mm)
    base = float(h.min()) if base is None else min(float(base), size_mm)
    k = np.floor(np.log(h / base) / math.log(SIZE_STEP) + 1e-9)
    return np.where(h >= size_mm, size_mm, np.minimum(base * SIZE_STEP ** np.maximum(k, 0), size_mm))


# ---------------------------------------------------------------- gmsh model

def arrangement(outline: Polygon, geoms, grid: float = None):
    """Planar subdivision of ``outline`` by the boundaries of the pieces ``geoms``.

    Returns (faces, cover): an array of Polygons that tile the outline without overlap,
    and per face the sorted indices of the pieces that contain it. The linework is
    snap-rounded to a ``grid`` mm grid (default GRID) so that the noding is exact, shared
    edges match and round-off slivers vanish; a face belongs to a piece when more than
    half of its area lies in it.
    """
    grid = GRID if grid is None else grid
    lines = shapely.union_all(shapely.boundary(np.concatenate([[outline], np.asarray(geoms, dtype=object)])),
                              grid_size=grid)
    faces = np.array(shapely.get_parts(shapely.polygonize(shapely.get_parts(lines))), dtype=object)
    pts = shapely.point_on_surface(faces)
    faces = faces[shapely.contains_xy(outline.buffer(10 * grid), shapely.get_x(pts), shapely.get_y(pts))]
    cover = [[] for _ in faces]
    if len(geoms):
        fi, pi = shapely.STRtree(geoms).query(faces, predicate="intersects")
        share = shapely.area(shapely.intersection(faces[fi], geoms[pi])) / shapely.area(faces[fi])
        for f, p in zip(fi[share > 0.5].tolist(), pi[share > 0.5].tolist()):
            cover[f].append(p)
    total = float(shapely.area(faces).sum())
    if abs(total - outline.area) > 1e-5 * outline.area:
        raise RuntimeError(f"internal error: the planar arrangement covers {total:.9g} mm^2 of a "
                           f"{outline.area:.9g} mm^2 fabric")
    return faces, [np.array(sorted(c), np.int64) for c in cover]


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
    loops = []
    for ring in [poly.exterior, *poly.interiors]:
        xy = np.asarray(ring.coords)[:-1]
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
    scale = math.sqrt(pattern.outline.area)
    if scale / size > 5e3:
        raise SelfshapeError(f"{pattern.source}: mesh size {size:g} mm is too small for a {scale:.4g} mm fabric")
    if kernel not in ("geo", "occ"):
        raise ValueError(f"kernel must be 'geo' or 'occ', got {kernel!r}")
    geoms, thick, side, _ = printed_pieces(pattern.elements)
    regions = piece_regions(geoms)
    floor = size * 1e-3
    piece_h = np.maximum(feature_width(geoms) / across, floor)
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
    for r in range(1, k + 1):
        gmsh.model.addPhysicalGroup(2, [f for f in printed if regions[faces[f].pieces[0]] == r], tag=r,
                                    name=f"region_{r}")
    bare = [f for f, face in faces.items() if not len(face.pieces)]
    if bare:
        gmsh.model.addPhysicalGroup(2, bare, tag=k + 1, name="fabric")
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
    """Mesh a pattern file (.toml, or .gcode: see geometry.patterns) and write a Gmsh .msh.

    The .msh (format 4.1) has one physical surface group per printed region, named
    "region_k" with tag k, and "fabric" (tag K + 1) for bare fabric, plus element data
    "region", "thickness_front" and "thickness_back" (mm). Written atomically.
    Returns dict(n_vertices, n_triangles, n_regions, min_angle_deg, time_s).
    """
    from geometry.patterns import load_pattern
    t0 = time.perf_counter()
    pattern = load_pattern(pattern_path)
    out_msh = os.fspath(out_msh)
    root, ext = os.path.splitext(out_msh)
    if ext.lower() != ".msh":
        raise SelfshapeError(f"{out_msh}: the mesh output must be a .msh file")
    d = os.path.dirname(os.path.abspath(out_msh))
    if not os.path.isdir(d):
        raise SelfshapeError(f"{out_msh}: directory {d} does not exist")
    tmp = f"{root}.partial{os.getpid()}.msh"
    try:
        with gmsh_session() as gmsh:
            sheet, etags = _mesh_model(gmsh, pattern, size_mm, None, GRADING, ALGORITHM, KERNEL)
            gmsh.option.setNumber("Mesh.SaveAll", 0)
            gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
            gmsh.option.setNumber("PostProcessing.SaveMesh", 0)
            gmsh.option.setNumber("PostProcessing.SaveInterpolationMatrices", 0)
            gmsh.write(tmp)
            order = np.argsort(etags)          # element data in the file's element order
            model = gmsh.model.getCurrent()
            for name, values in (("region", sheet.region.astype(float)), ("thickness_front", sheet.thickness_front),
                                 ("thickness_back", sheet.thickness_back)):
                v = gmsh.view.add(name)
                gmsh.view.addHomogeneousModelData(v, 0, model, "ElementData", etags[order].tolist(),
                                                  values[order].tolist())
                gmsh.view.write(v, tmp, append=True)
        os.replace(tmp, out_msh)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    q = mesh_quality(sheet)
    return dict(n_vertices=q["n_vertices"], n_triangles=q["n_triangles"], n_regions=q["n_regions"],
                min_angle_deg=q["min_angle_deg"], time_s=time.perf_counter() - t0)


def read_msh(path) -> Sheet:
    """Read a .msh written by mesh_pattern_file (or any planar triangle .msh) as a Sheet.

    Region ids come from the physical names ("fabric" -> 0, "region_k" -> k); without
    physical names every triangle is region 0. Thickness comes from the element data
    "thickness_front"/"thickness_back" when present, else 0.
    """
    import meshio
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SelfshapeError(f"{path}: file not found")
    with open(path, "rb") as f:
        if b"$MeshFormat" not in f.read(4096):
            raise SelfshapeError(f"{path}: cannot read Gmsh mesh (no $MeshFormat header)")
    try:
        m = meshio.read(path, file_format="gmsh")
    except (Exception, SystemExit) as e:       # meshio exits on some malformed files
        raise SelfshapeError(f"{path}: cannot read Gmsh mesh ({' '.join(str(e).split()) or type(e).__name__})") from None
    for k in [k for k in m.cell_sets if k.startswith("gmsh:")]:
        del m.cell_sets[k]
    blocks = [i for i, c in enumerate(m.cells) if c.type == "triangle"]
    if not blocks:
        raise SelfshapeError(f"{path}: no triangles in the mesh")
    tri = np.vstack([m.cells[i].data for i in blocks])

    def cell_values(name, default):
        if name not in m.cell_data:
            return np.full(len(tri), default)
        return np.concatenate([np.asarray(m.cell_data[name][i]).reshape(-1) for i in blocks])

    names = {int(v[0]): k for k, v in m.field_data.items() if len(v) > 1 and int(v[1]) == 2}
    phys = cell_values("gmsh:physical", 0).astype(np.int64)
    region = np.zeros(len(tri), np.int64)
    if names:
        lut = {}
        for tag, name in names.items():
            mm = re.fullmatch(r"region_(\d+)", name)
            if name == "fabric":
                lut[tag] = 0
            elif mm:
                lut[tag] = int(mm.group(1))
            else:
                raise SelfshapeError(f"{path}: physical group {name!r} is neither \"fabric\" nor \"region_k\"")
        unknown = sorted(set(np.unique(phys)) - set(lut))
        if unknown:
            raise SelfshapeError(f"{path}: triangles in physical group {unknown[0]} which has no name")
        keys = np.array(sorted(lut))
        region = np.array([lut[k] for k in keys], np.int64)[np.searchsorted(keys, phys)]
    pts = np.asarray(m.points, float)
    if pts.shape[1] == 3:
        span = max(float(np.ptp(pts[:, :2], axis=0).max()), 1e-300)
        if np.abs(pts[:, 2]).max() > 1e-9 * span:
            raise SelfshapeError(f"{path}: the mesh is not flat (z != 0); a Sheet is a planar printed state")
    used, inv = np.unique(tri, return_inverse=True)
    return Sheet(pts[used, :2], inv.reshape(-1, 3), region, cell_values("thickness_front", 0.0),
                 cell_values("thickness_back", 0.0))


def triangle_angles(points, triangles) -> np.ndarray:
    """(m, 3) interior angles in degrees (at vertex 0, 1, 2)."""
    p = np.asarray(points, float)[np.asarray(triangles)]
    a = np.linalg.norm(p[:, 2] - p[:, 1], axis=1)    # opposite vertex 0
    b = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    c = np.linalg.norm(p[:, 1] - p[:, 0], axis=1)
    def ang(opp, s1, s2):
        return np.degrees(np.arccos(np.clip((s1 * s1 + s2 * s2 - opp * opp) / (2 * s1 * s2), -1.0, 1.0)))
    return np.column_stack([ang(a, b, c), ang(b, c, a), ang(c, a, b)])


def mesh_quality(sheet: Sheet) -> dict:
    """Counts, angles (deg), areas (mm^2) and edge lengths (mm) of a Sheet."""
    ang = triangle_angles(sheet.points, sheet.triangles)
    p = sheet.points[sheet.triangles]
    area = 0.5 * np.abs((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                        - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
    e = np.sort(np.vstack([sheet.triangles[:, [0, 1]], sheet.triangles[:, [1, 2]], sheet.triangles[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    L = np.linalg.norm(sheet.points[e[:, 0]] - sheet.points[e[:, 1]], axis=1)
    tmin = ang.min(axis=1)
    printed = sheet.printed
    return dict(
        n_vertices=int(sheet.n_vertices), n_triangles=int(sheet.n_triangles),
        n_regions=int(len(np.unique(sheet.region[sheet.region > 0]))),
        min_angle_deg=float(tmin.min()), max_angle_deg=float(ang.max()),
        mean_min_angle_deg=float(tmin.mean()), pct_min_angle_below_30=float(100.0 * (tmin < 30).mean()),
        area_mm2=float(area.sum()), printed_area_mm2=float(area[printed].sum()),
        edge_min_mm=float(L.min()), edge_median_mm=float(np.median(L)), edge_max_mm=float(L.max()),
    )
