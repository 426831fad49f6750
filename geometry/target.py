"""Target surfaces for inverse design: read, validate (a disk, possibly with holes), scale, refine.

All public functions take and return plain arrays: V (n, 3) float vertex positions and
F (m, 3) int triangle indices. After `load_target` lengths are millimetres.
"""
from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from geometry.meshops import boundary_loop_count, face_areas, halfedges, remove_unreferenced, unique_edges
from geometry.schema import DESIGN_NUMBERS, number
from shellfem.errors import SelfshapeError
from shellfem.infiles import read_input_bytes, read_meshio

#: A face whose area is below this fraction of the squared bounding-box diagonal is "zero area".
ZERO_AREA_REL = 1e-12
#: Largest |coordinate| of a target vertex in its file's units: beyond it squared lengths
#: overflow (1e300 would make every face "zero area"); any unit from nm to km fits.
MAX_COORD = 1e15
#: Largest face index an input may hold (int64, what the mesh arrays use).
MAX_INDEX = np.iinfo(np.int64).max


# ----------------------------------------------------------------------------- reading
def read_obj(path) -> tuple[np.ndarray, np.ndarray]:
    """Minimal OBJ reader: `v` and `f` records only (texture/normal indices ignored,
    negative indices resolved, polygons fan-triangulated)."""
    name = os.path.basename(str(path))
    verts, polys = [], []
    text = read_input_bytes(path, "target mesh (.obj)", name).decode("utf-8-sig", errors="replace")
    for lineno, line in enumerate(text.split("\n"), 1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "v":
            verts.append(tok[1:4])
        elif tok[0] == "f":
            try:
                idx = [int(t.split("/")[0]) for t in tok[1:]]
            except ValueError:
                raise SelfshapeError(f"{name}: line {lineno}: malformed face record") from None
            if any(abs(i) > MAX_INDEX for i in idx):
                raise SelfshapeError(f"{name}: line {lineno}: a face index is beyond the int64 range")
            if len(idx) < 3:
                raise SelfshapeError(f"{name}: line {lineno}: face with fewer than 3 vertices")
            nv = len(verts)  # OBJ negative indices count back from the current vertex
            polys.append([i - 1 if i > 0 else nv + i for i in idx])
    try:
        V = np.asarray(verts, dtype=float).reshape(-1, 3)
    except ValueError:
        raise SelfshapeError(f"{name}: malformed vertex record") from None
    try:
        return V, _fan_triangulate(polys)
    except SelfshapeError as e:
        raise SelfshapeError(f"{name}: {e}") from None


def _fan_triangulate(polys) -> np.ndarray:
    tris = []
    sizes = np.array([len(p) for p in polys], dtype=int)
    for k in np.unique(sizes):
        try:
            P = np.array([p for p, s in zip(polys, sizes) if s == k], dtype=np.int64)
        except OverflowError:          # unsigned 64-bit indices from a binary file
            raise SelfshapeError("a face index is beyond the int64 range") from None
        for j in range(1, k - 1):  # fan around the first corner, vectorised per polygon size
            tris.append(P[:, [0, j, j + 1]])
    if not tris:
        return np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(tris, axis=0)


def read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a surface mesh (OBJ with the own reader, anything else through meshio;
    quads and polygons are triangulated, STL vertices are merged)."""
    name = os.path.basename(str(path))
    if str(path).lower().endswith(".obj"):
        return read_obj(path)
    mesh = read_meshio(path, "mesh", name)
    V = np.asarray(mesh.points, dtype=float)
    if V.ndim != 2 or V.shape[1] not in (2, 3):
        raise SelfshapeError(f"{name}: vertices are not 2D or 3D points")
    if V.shape[1] == 2:
        V = np.column_stack([V, np.zeros(len(V))])
    polys = []
    for block in mesh.cells:
        if block.type in ("triangle", "quad") or block.type.startswith("polygon"):
            polys.extend(np.asarray(block.data).tolist())
    try:
        F = _fan_triangulate(polys)
    except SelfshapeError as e:
        raise SelfshapeError(f"{name}: {e}") from None
    if str(path).lower().endswith(".stl") and len(F):
        V, F = weld_coincident(V, F)      # STL stores every triangle with its own corners
    return V, F


# ----------------------------------------------------------------------------- topology
def check_disk(V: np.ndarray, F: np.ndarray, where: str = "mesh", repairs: list | None = None, holes: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
    """Validate a disk-topology triangle mesh (with ``holes``: a disk with any number of holes,
    i.e. genus 0 with one boundary loop per hole besides the outer one); return it without
    unreferenced vertices, with its faces consistently oriented.

    Two defects of exported meshes are repaired, since each has one right answer: faces stored
    apart (a polygon soup, or an exporter's seams) are welded at identical positions when that
    makes the mesh one piece with one boundary (:func:`weld_coincident`); and faces whose
    orientation disagrees with their neighbours' are flipped to agree, keeping the orientation
    of the majority (which side is the front). Each repair appends a sentence to ``repairs``.
    Raises SelfshapeError (one line starting with ``where``) on: no faces, non-finite
    coordinates, bad indices, degenerate or zero-area faces, non-manifold edges or
    vertices, a non-orientable surface, several components, no or several boundary loops,
    or a non-disk Euler characteristic.
    """
    V = np.asarray(V, dtype=float)
    try:
        F = np.asarray(F)
    except OverflowError:
        raise SelfshapeError(f"{where}: a face index is beyond the int64 range") from None
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise SelfshapeError(f"{where}: no triangle faces")
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 3:
        raise SelfshapeError(f"{where}: vertices must be an (n, 3) array with n >= 3")
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise SelfshapeError(f"{where}: vertex {int(np.flatnonzero(bad)[0])} has a non-finite coordinate")
    far = np.abs(V).max(axis=1) > MAX_COORD
    if far.any():
        raise SelfshapeError(f"{where}: vertex {int(np.flatnonzero(far)[0])} has a coordinate beyond "
                             f"+-{MAX_COORD:g} (squared lengths would overflow)")
    if F.dtype.kind not in "iu" and F.dtype != object:
        raise SelfshapeError(f"{where}: face indices must be integers, got {F.dtype}")
    if F.dtype.kind == "u" and F.size and int(F.max()) > MAX_INDEX:
        raise SelfshapeError(f"{where}: a face index is beyond the int64 range")
    try:
        F = F.astype(np.int64)
    except (OverflowError, TypeError, ValueError):
        raise SelfshapeError(f"{where}: face indices must be integers within the int64 range") from None
    out = (F < 0) | (F >= len(V))
    if out.any():
        f = int(np.flatnonzero(out.any(axis=1))[0])
        raise SelfshapeError(f"{where}: face {f} references a vertex index outside 0..{len(V) - 1}")
    V, F = _welded_if_disk(V, F, repairs)
    rep = _repeated_vertex(F)
    if rep.any():
        f = int(np.flatnonzero(rep)[0])
        raise SelfshapeError(f"{where}: face {f} is degenerate (repeated vertex), {int(rep.sum())} such faces")
    V, F, _ = remove_unreferenced(V, F)
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    area = face_areas(V, F)
    zero = area <= ZERO_AREA_REL * max(diag, np.finfo(float).tiny) ** 2
    if zero.any():
        f = int(np.flatnonzero(zero)[0])
        raise SelfshapeError(f"{where}: face {f} has zero area, {int(zero.sum())} such faces")
    E, he2e, counts = unique_edges(F)
    if (counts > 2).any():
        a, b = E[np.flatnonzero(counts > 2)[0]]
        raise SelfshapeError(f"{where}: non-manifold edge ({a}, {b}) shared by {int(counts.max())} faces")
    if _clashing_edge(F, len(V)) is not None:
        F = _oriented(F, repairs)
        clash = _clashing_edge(F, len(V))
        if clash is not None:
            raise SelfshapeError(f"{where}: the surface is not orientable (a Moebius band: no orientation of "
                                 f"the faces agrees along edge ({clash[0]}, {clash[1]}))")
    n = len(V)
    ncomp, loops = _components_and_loops(F, n)
    if ncomp > 1:
        raise SelfshapeError(f"{where}: {ncomp} connected components (need one)")
    manifold = _vertex_manifold(F, n)
    if not manifold.all():
        v = int(np.flatnonzero(~manifold)[0])
        raise SelfshapeError(f"{where}: non-manifold vertex {v} (its faces form several fans)")
    if loops == 0:
        raise SelfshapeError(f"{where}: closed surface (no boundary); a disk-like surface is required")
    if loops > 1 and not holes:
        raise SelfshapeError(f"{where}: {loops} boundary loops ({loops - 1} hole{'s' if loops > 2 else ''}); a disk "
                             f"has one: fill the hole{'s' if loops > 2 else ''} or cut the surface open to its "
                             f"outer edge")
    chi = n - len(E) + len(F)
    if chi != 2 - loops:
        genus = (2 - loops - chi) // 2
        raise SelfshapeError(f"{where}: Euler characteristic {chi} with {loops} boundary loop{'s' if loops > 1 else ''} "
                             f"(genus {genus}: {genus} handle{'s' if genus > 1 else ''}); a disk"
                             f"{' with holes' if loops > 1 else ''} has {2 - loops}: cut each handle open")
    return V, F


def _clashing_edge(F: np.ndarray, n: int):
    """An edge (a, b) that two faces run the same way (their orientations disagree), or None."""
    H = halfedges(F)
    _, first, dc = np.unique(H[:, 0] * n + H[:, 1], return_index=True, return_counts=True)
    if not (dc > 1).any():
        return None
    he = int(first[np.flatnonzero(dc > 1)[0]])
    return int(H[he, 0]), int(H[he, 1])


def _oriented(F: np.ndarray, repairs: list | None) -> np.ndarray:
    """F with every face oriented as its neighbours (libigl's breadth-first orientation of a
    manifold mesh), then all flipped if that turned more faces than it kept: the majority's
    orientation (the side the user called the front) stays."""
    import igl

    G = np.asarray(igl.bfs_orient(np.ascontiguousarray(F, dtype=np.int64))[0], dtype=np.int64)
    same = _same_cycle(F, G)
    if same.sum() < len(F) - same.sum():
        G = G[:, ::-1].copy()
        same = ~same
    if repairs is not None:
        repairs.append(f"{int(len(F) - same.sum())} of {len(F)} faces turned to agree with their neighbours' orientation")
    return G


def _same_cycle(F: np.ndarray, G: np.ndarray) -> np.ndarray:
    """True for faces whose vertex cycles agree (G[i] is a rotation of F[i])."""
    return np.any([np.all(np.roll(G, k, axis=1) == F, axis=1) for k in range(3)], axis=0)


def weld_coincident(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices at identical positions (after rounding to 1e-9 of the bounding-box
    diagonal, so that values printed and read back alike merge); returns (V, F) with the
    first vertex of each position kept."""
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    key = np.round(V / max(1e-9 * diag, np.finfo(float).tiny)).astype(np.int64) if diag > 0 else np.zeros_like(V, int)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                     # keep the input order of the kept vertices
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return V[first[order]], rank[inverse.reshape(-1)][F]


def _repeated_vertex(F: np.ndarray) -> np.ndarray:
    """True for faces that name one vertex twice (degenerate)."""
    return (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])


def _components_and_loops(F: np.ndarray, n: int) -> tuple[int, int]:
    """Connected pieces (counting referenced vertices only) and boundary loops of (F, n vertices)."""
    E, _, _ = unique_edges(F)
    _, labels = connected_components(
        sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)), directed=False)
    used = np.unique(F)
    return len(np.unique(labels[used])), boundary_loop_count(F, n)


def _welded_if_disk(V: np.ndarray, F: np.ndarray, repairs: list | None):
    """(V, F) welded (:func:`weld_coincident`) when it is in several pieces or has several
    boundaries and welding joins some (the welded mesh manifold and without a degenerate face);
    else (V, F) unchanged. The checks then name what is still wrong (two patches stored as a
    soup are "2 connected components", not one per face)."""
    pieces, loops = _components_and_loops(F, len(V))
    if pieces == 1 and loops == 1:
        return V, F
    W, G = weld_coincident(V, F)
    if len(W) == len(V):
        return V, F
    if _repeated_vertex(G).any():
        return V, F
    _, _, counts = unique_edges(G)
    if (counts > 2).any():
        return V, F
    pieces_w, loops_w = _components_and_loops(G, len(W))
    if (pieces_w, loops_w) == (pieces, loops):
        return V, F
    if repairs is not None:
        repairs.append(f"{len(V) - len(W)} vertices at the positions of others welded: the faces were stored "
                       f"apart ({pieces} pieces and {loops} boundaries before, {pieces_w} and {loops_w} after)")
    return W, G


def _vertex_manifold(F: np.ndarray, n: int) -> np.ndarray:
    """True where the faces around a vertex form a single fan (libigl's check)."""
    import igl

    return np.asarray(igl.is_vertex_manifold(np.ascontiguousarray(F, dtype=np.int64)), dtype=bool)[:n]


# ----------------------------------------------------------------------------- scaling
def normalize(V: np.ndarray, diagonal_mm: float | None = 110.0) -> np.ndarray:
    """Centre the bounding box at the origin and scale uniformly to a bounding-box
    diagonal of ``diagonal_mm`` (None keeps the units), which must be in the range of
    geometry.schema.DESIGN_NUMBERS["diagonal_mm"] (10-5000 mm; one-line error otherwise)."""
    if diagonal_mm is not None:
        diagonal_mm = number(diagonal_mm, "target diagonal (--diagonal, diagonal_mm)", DESIGN_NUMBERS["diagonal_mm"])
    lo, hi = V.min(axis=0), V.max(axis=0)
    V = V - 0.5 * (lo + hi)
    if diagonal_mm is None:
        return V
    return V * (float(diagonal_mm) / float(np.linalg.norm(hi - lo)))


def load_target(path, diagonal_mm: float | None = 110.0) -> tuple[np.ndarray, np.ndarray]:
    """Read a target surface (OBJ/PLY/STL/... ; a disk, possibly with holes), validate it, drop
    unreferenced vertices, centre it and scale it to a bounding-box diagonal of ``diagonal_mm`` mm."""
    name = os.path.basename(str(path))
    V, F = read_mesh(path)
    V, F = check_disk(V, F, where=name, holes=True)
    return normalize(V, diagonal_mm), F


# ----------------------------------------------------------------------------- refinement
def refine(V: np.ndarray, F: np.ndarray, levels: int = 1, method: str = "loop"):
    """Subdivide ``levels`` times (each level x4 faces): "loop" (smooth, libigl) or
    "midpoint" (keeps the piecewise-flat shape)."""
    import igl

    if levels < 0:
        raise SelfshapeError(f"refine: levels must be >= 0, got {levels}")
    if levels == 0:
        return np.asarray(V, float), np.asarray(F, np.int64)
    V = np.ascontiguousarray(V, dtype=float)
    F = np.ascontiguousarray(F, dtype=np.int64)
    if method == "loop":
        return igl.loop(V, F, int(levels))
    if method == "midpoint":
        return igl.upsample(V, F, int(levels))
    raise SelfshapeError(f"refine: unknown method {method!r} (use 'loop' or 'midpoint')")


def levels_for_faces(n_faces: int, target_faces: int = 100_000) -> int:
    """Subdivision levels (x4 faces each) bringing ``n_faces`` closest in log scale to
    ``target_faces``, preferring counts within [0.4, 1.6] x target (the seed's 40k-160k)."""
    levels = np.arange(9)
    counts = n_faces * 4.0 ** levels
    dist = np.abs(np.log(counts / target_faces))
    inside = (counts >= 0.4 * target_faces) & (counts <= 1.6 * target_faces)
    return int(levels[inside][np.argmin(dist[inside])] if inside.any() else levels[np.argmin(dist)])


# ----------------------------------------------------------------------------- synthetic targets
def disk_points(n_radial: int) -> np.ndarray:
    """Well-spaced points on the unit disk: concentric rings of 6k points (k = 0..n_radial)."""
    pts = [np.zeros((1, 2))]
    for k in range(1, n_radial + 1):
        t = 2 * np.pi * np.arange(6 * k) / (6 * k) + (np.pi / (6 * k) if k % 2 else 0.0)
        pts.append((k / n_radial) * np.column_stack([np.cos(t), np.sin(t)]))
    return np.concatenate(pts)


def triangulate_disk(n_radial: int) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay triangulation of `disk_points`, counter-clockwise faces."""
    from scipy.spatial import Delaunay

    P = disk_points(n_radial)
    F = Delaunay(P).simplices.astype(np.int64)
    d = P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]]
    cw = d[0][:, 0] * d[1][:, 1] - d[0][:, 1] * d[1][:, 0] < 0
    F[cw] = F[cw][:, [0, 2, 1]]
    return P, F


def sphere_cap(radius: float = 40.0, half_angle_deg: float = 45.0, n_radial: int = 20):
    """Spherical cap of given radius (mm) and opening half-angle; apex at the origin, the
    sphere centre at (0, 0, radius), normals pointing away from the centre (-z at the apex)."""
    P, F = triangulate_disk(n_radial)
    r = np.linalg.norm(P, axis=1)
    phi = r * np.deg2rad(half_angle_deg)
    t = np.arctan2(P[:, 1], P[:, 0])
    V = radius * np.column_stack([np.sin(phi) * np.cos(t), np.sin(phi) * np.sin(t), 1.0 - np.cos(phi)])
    return V, F[:, [0, 2, 1]]  # CW in the xy-projection: normal -z, i.e. away from the centre


def cylinder_patch(radius: float = 30.0, arc_mm: float = 60.0, length_mm: float = 50.0,
                   n_arc: int = 24, n_len: int = 20):
    """Cylinder patch (axis along y, radius mm) of arc length ``arc_mm`` and length ``length_mm``,
    structured alternating-diagonal triangles; normals point away from the axis."""
    s = np.linspace(-arc_mm / 2, arc_mm / 2, n_arc + 1)
    y = np.linspace(-length_mm / 2, length_mm / 2, n_len + 1)
    S, Y = np.meshgrid(s, y, indexing="ij")
    P = np.column_stack([S.ravel(), Y.ravel()])
    F = grid_triangles(n_arc, n_len)
    a = P[:, 0] / radius
    V = np.column_stack([radius * np.sin(a), P[:, 1], radius * (1.0 - np.cos(a))])
    return V, F[:, [0, 2, 1]]  # axis at z = +radius: outward normal is -z at s = 0


def plane_patch(width: float = 60.0, height: float = 40.0, nx: int = 24, ny: int = 16):
    """Flat rectangle in the xy-plane (mm), normals +z."""
    x = np.linspace(-width / 2, width / 2, nx + 1)
    y = np.linspace(-height / 2, height / 2, ny + 1)
    X, Y = np.meshgrid(x, y, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    return V, grid_triangles(nx, ny)


def grid_triangles(nx: int, ny: int) -> np.ndarray:
    """Counter-clockwise triangles of an (nx+1) x (ny+1) vertex grid (index i*(ny+1)+j),
    diagonals alternating so the mesh has no preferred direction."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v00 = i * (ny + 1) + j
    v10, v01, v11 = v00 + ny + 1, v00 + 1, v00 + ny + 2
    alt = (i + j) % 2 == 0
    t1 = np.where(alt[:, None], np.column_stack([v00, v10, v11]), np.column_stack([v00, v10, v01]))
    t2 = np.where(alt[:, None], np.column_stack([v00, v11, v01]), np.column_stack([v10, v11, v01]))
    return np.concatenate([t1, t2]).astype(np.int64)
