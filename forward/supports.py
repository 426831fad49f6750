"""Supports of a simulated sheet: the DOFs a pattern's [[support]] tables hold and their values,
and the harmonic carrying of a moving support's displacement into the free vertices (mm)."""
from __future__ import annotations

import numpy as np

from shellfem.boundary import graph_laplacian, harmonic_extension, nearest_vertices
from shellfem.errors import SelfshapeError
from shellfem.sheet import Sheet


def outer_edge_vertices(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The vertices (sorted) of the boundary loop that is the fabric's outer edge: the loop
    reaching least x (holes lie inside the outer edge, so their rims never reach it).
    points (n, >=2) printed-state mm; triangles (m, 3)."""
    from geometry.meshops import boundary_loops
    return np.sort(min(boundary_loops(points, triangles), key=lambda loop: points[loop, 0].min()))


def support_constraints(sheet: Sheet, supports, fabric, tol: float, plane_z: float = 0.0):
    """(dofs (k,), values (k,)) held by the pattern's [[support]]s on the sheet (printed-state mm):
    "z" holds the vertices' z at ``plane_z``, "xyz" holds them at ``position`` or at their relaxed
    (printed / stretch) positions at z = ``plane_z``; ``tol`` (mm) is how far a support point may
    lie from its vertex; a boundary support holds the fabric's outer edge (:func:`outer_edge_vertices`).
    plane_z (mm): where the sheet rests on the table, 0 without a ground (the plane z = 0); with
    a ground, the top of its barrier's band (forward.simulate.support_plane)."""
    dofs, vals = [], []
    sx, sy = fabric.stretch
    for k, sup in enumerate(supports):
        label = sup.label or f"[[support]] #{k + 1}"
        if sup.boundary:
            idx = outer_edge_vertices(sheet.points, sheet.triangles)
        else:
            idx = nearest_vertices(sheet.points, sup.points, tol, label)
        if sup.fix == "z":
            dofs.append(3 * idx + 2)
            vals.append(np.full(len(idx), float(plane_z)))
        elif sup.fix == "xyz":
            if sup.position is not None:
                pos = np.asarray(sup.position, float).reshape(-1, 3)
            else:
                p = sheet.points[idx]
                pos = np.column_stack([p[:, 0] / sx, p[:, 1] / sy, np.full(len(idx), float(plane_z))])
            dofs.append((3 * idx[:, None] + np.arange(3)).ravel())
            vals.append(pos.ravel())
        else:
            raise SelfshapeError(f"{label}: fix must be \"z\" or \"xyz\", got {sup.fix!r}")
    if not dofs:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    d, v = np.concatenate(dofs), np.concatenate(vals)
    d, first = np.unique(d, return_index=True)
    return d, v[first]


def carry_support_motion(model, plain, q, fixed, free):
    """Supports that move ("xyz" at relaxed positions, or "z" on the ground under a perturbed
    start) would leave their neighbours behind and invert or kink triangles: carry each held
    component's motion into the free vertices harmonically, when that start has finite energy."""
    n = model.n_vertices
    held = np.zeros(3 * n, bool)
    held[fixed] = True
    held = held.reshape(n, 3)
    movable = free[:3 * n].reshape(n, 3)
    jump = (plain - q)[:3 * n].reshape(n, 3)
    moved = plain.copy()
    pos = moved[:3 * n].reshape(n, 3)
    L = None
    for c in range(3):
        h = np.flatnonzero(held[:, c])
        if len(h) == 0 or np.abs(jump[h, c]).max() == 0:
            continue
        L = graph_laplacian(n, model.topo.edges) if L is None else L
        u = harmonic_extension(L, h, jump[h, c])[:, 0]
        pos[:, c] += np.where(movable[:, c], u, 0.0)
    if L is not None and np.isfinite(model.energy(moved)):
        return moved
    return plain
