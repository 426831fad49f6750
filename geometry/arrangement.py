"""Printed pieces of a pattern and the planar arrangement they cut the fabric into (printed-state mm).

Every printed element is split into simple polygons (pieces) snapped to a GRID mm grid. A
printed *region* is a connected component of the union of the pieces (region 0 = bare
fabric, regions 1..K numbered in the order of their first element in the pattern). The
arrangement tiles the fabric outline by the pieces' boundaries (snap-rounded noding +
polygonize), so that each tile lies entirely inside or outside each piece: the conforming
mesh is made tile by tile (geometry.meshing).
"""
from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

from geometry.outlines import without_detail

GRID = 1e-5           # mm: geometry is snap-rounded to this grid (merges round-off slivers)


def printed_pieces(elements, tol: float = None):
    """Split elements into simple polygon pieces (arrays in, arrays out).

    Returns (geoms, thickness, side, element): shapely Polygons snapped to a ``tol`` mm
    grid (default GRID) without detail below geometry.schema.DETAIL_MM, their plastic
    thickness (mm), side (+1 front, -1 back) and source element index.
    """
    tol = GRID if tol is None else tol
    geoms, thick, side, owner = [], [], [], []
    for i, e in enumerate(elements):
        # snapped, then detail below DETAIL_MM dropped (G-code beads, stars, ribbons alike)
        g = without_detail(shapely.set_precision(e.geometry, tol))
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
