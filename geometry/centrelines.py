"""Fabric meshes with the printed arms' centre lines as mesh edges (the rods model).

The seed's chapter-3 simulator collocates the rods of the star arms with the fabric's
vertices: "the fabric mesh must have edges that align with the star arms: we first
discretize the rods ... and then we generate the fabric mesh using constrained Delaunay
triangulation". Here each centre-line segment is a Gmsh line embedded in the fabric's
plane surface (gmsh.model.mesh.embed) with a fixed number of equal sub-segments
(transfinite), so the rods' resolution is chosen first and the fabric mesh conforms to it;
segments meeting at a star centre share its Gmsh point, hence its vertex.

Centre lines are clipped to the outline shrunk by a quarter of the rod segment length (an
embedded line may not touch the outline); pieces shorter than half a segment are dropped.
The sheet carries no printed thickness: the rods model's fabric is bare everywhere and the
printed plastic is in the rods (shellfem.rods). Units mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString

from geometry.meshing import ALGORITHM, gmsh_session
from geometry.schema import MAX_TRIANGLES
from shellfem.errors import SelfshapeError
from shellfem.sheet import Sheet


@dataclass
class RodMesh:
    """A sheet with rods on its edges: edges (ne, 2) vertex ids, per edge the plastic
    thickness, width (mm) and side (+1 front, -1 back), and line (ne,) the index of the
    centre line (in pattern order) it came from."""
    sheet: Sheet
    edges: np.ndarray
    thickness: np.ndarray
    width: np.ndarray
    side: np.ndarray
    line: np.ndarray


def pattern_centrelines(pattern) -> list:
    """[(polyline (k, 2), thickness, width, side)] of the pattern's elements with centre
    lines (geometry.elements.PrintedElement.centrelines)."""
    out = []
    for el in pattern.elements:
        for path in el.centrelines or ():
            out.append((np.asarray(path, float), float(el.thickness_mm), float(el.width_mm), el.side))
    return out


def mesh_centrelines(outline, lines, size_mm: float, segment_mm: float | None = None, where: str = "pattern",
                     algorithm: int = ALGORITHM) -> RodMesh:
    """Mesh ``outline`` (shapely Polygon) at ``size_mm`` with the centre lines ``lines``
    [(polyline, thickness, width, side)] as embedded edges of length at most ``segment_mm``
    (default: size_mm, and at least 4 per line)."""
    size = float(size_mm)
    seg = size if segment_mm is None else float(segment_mm)
    est = 4.0 / math.sqrt(3.0) * outline.area / size ** 2
    if est > MAX_TRIANGLES:
        raise SelfshapeError(f"{where}: mesh size {size:g} mm would need about {est:.3g} triangles, more than the "
                             f"{MAX_TRIANGLES:,} selfshape meshes; use a larger [mesh] size_mm")
    # each centre line is cut into segments of at most seg (and at least 4), each an edge of the
    # mesh with a triangle on either side: counted before the per-line work and Gmsh
    lengths = np.array([float(np.linalg.norm(np.diff(np.asarray(path, float), axis=0), axis=1).sum())
                        for path, _, _, _ in lines])
    est += 2.0 * float(np.maximum(np.ceil(lengths / seg), 4).sum())
    if est > MAX_TRIANGLES:
        raise SelfshapeError(f"{where}: the rods model's mesh would need about {est:.3g} triangles ({len(lines):,} "
                             f"centre lines at {seg:g} mm segments), more than the {MAX_TRIANGLES:,} selfshape meshes; "
                             f"use a larger [mesh] size_mm or fewer stars")
    inner = outline.buffer(-0.25 * seg)
    pieces = []                     # (polyline, line id, segment length)
    for i, (path, _, _, _) in enumerate(lines):
        clipped = shapely.intersection(LineString(path), inner)
        for part in shapely.get_parts(shapely.line_merge(clipped) if clipped.geom_type == "MultiLineString"
                                      else clipped):
            if part.geom_type != "LineString" or part.length < 0.5 * seg:
                continue
            xy = np.asarray(part.coords)
            h = min(seg, part.length / 4)
            pieces.append((xy, i, h))
    if not pieces:
        raise SelfshapeError(f"{where}: no printed centre line lies inside the fabric for the rods model")
    with gmsh_session("selfshape-rods") as gmsh:
        geo = gmsh.model.geo
        ring = np.asarray(outline.exterior.coords)[:-1]
        loops = []
        for r in [ring] + [np.asarray(h.coords)[:-1] for h in outline.interiors]:
            pts = [geo.addPoint(float(x), float(y), 0.0, size) for x, y in r]
            loops.append(geo.addCurveLoop([geo.addLine(pts[k], pts[(k + 1) % len(pts)]) for k in range(len(pts))]))
        surf = geo.addPlaneSurface(loops)
        # shared points (a star's centre), one line per polyline segment, n equal sub-segments
        allxy = np.vstack([p[0] for p in pieces])
        key = np.round(allxy / (1e-6 * max(1.0, size)))
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        hmin = np.full(len(first), np.inf)
        pos = 0
        for xy, _, h in pieces:
            np.minimum.at(hmin, inv[pos:pos + len(xy)], h)
            pos += len(xy)
        ptag = [geo.addPoint(float(allxy[j, 0]), float(allxy[j, 1]), 0.0, float(hmin[u])) for u, j in enumerate(first)]
        line_of, tags, seen = [], [], {}
        pos = 0
        for xy, i, h in pieces:
            ids = inv[pos:pos + len(xy)]
            pos += len(xy)
            for a, b, p, q in zip(ids[:-1], ids[1:], xy[:-1], xy[1:]):
                if a == b or (min(a, b), max(a, b)) in seen:
                    continue
                seen[(min(a, b), max(a, b))] = True
                t = geo.addLine(ptag[a], ptag[b])
                geo.mesh.setTransfiniteCurve(t, int(math.ceil(np.linalg.norm(q - p) / h - 1e-9)) + 1)
                tags.append(t)
                line_of.append(i)
        geo.synchronize()
        gmsh.model.mesh.embed(1, tags, 2, surf)
        for opt, v in (("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.MeshSizeFromPoints", 1),
                       ("Mesh.MeshSizeFromCurvature", 0), ("Mesh.MeshSizeMax", size), ("Mesh.Algorithm", algorithm),
                       ("Mesh.MaxNumThreads2D", 1), ("Mesh.ElementOrder", 1)):
            gmsh.option.setNumber(opt, v)
        gmsh.model.mesh.generate(2)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        order = np.argsort(node_tags)
        node_tags, xyz = node_tags[order], coords.reshape(-1, 3)[order]
        _, _, nodes = gmsh.model.mesh.getElements(2, surf)
        tri = nodes[0].reshape(-1, 3)
        seg_nodes, seg_line = [], []
        for t, i in zip(tags, line_of):
            _, _, nd = gmsh.model.mesh.getElements(1, t)
            e = nd[0].reshape(-1, 2)
            seg_nodes.append(e)
            seg_line.append(np.full(len(e), i, np.int64))
    used, inv_t = np.unique(tri, return_inverse=True)
    sheet = Sheet(xyz[np.searchsorted(node_tags, used), :2], inv_t.reshape(-1, 3))
    e = np.vstack(seg_nodes)
    edges = np.searchsorted(used, e)
    if not np.array_equal(used[edges], e):
        raise RuntimeError("gmsh: an embedded centre-line node is not a vertex of the fabric mesh")
    line = np.concatenate(seg_line)
    th = np.array([lines[i][1] for i in line])
    wd = np.array([lines[i][2] for i in line])
    sd = np.array([1.0 if lines[i][3] == "front" else -1.0 for i in line])
    return RodMesh(sheet, edges.astype(np.int64), th, wd, sd, line)


def mesh_pattern_rods(pattern, size_mm: float | None = None) -> RodMesh:
    """The rods model's mesh of a pattern ([solver] model = "rods"): its fabric at [mesh]
    size_mm (or ``size_mm``) with its elements' centre lines as edges."""
    size = float(pattern.mesh_size if size_mm is None else size_mm)
    return mesh_centrelines(pattern.outline, pattern_centrelines(pattern), size, where=pattern.source)
