"""Staggered dashed-ribbon layout over a flattened surface (seed section 5.4.2).

Two stripe fields on the flat mesh form one grid of cell size mu1 x 2 mu2:
theta has isolines *along* the ribbon direction dir1, 2 mu2 apart (ribbon centre lines), psi
has isolines *across* it, mu1 apart. Grid A: centre lines arg(theta) = 0, cut into dashes of
length l_r centred where they cross arg(psi) = 0. Grid B (shifted half a cell, brick-like):
arg(theta) = pi lines, dashes centred on arg(psi) = pi. Rows of A and B alternate mu2 apart and
B's dashes are shifted by mu1 / 2. Dashes are clipped to the outline (eroded by half the ribbon
width so the printed ribbon stays on the fabric), trimmed where the centre line turns more than
max_angle away from dir1 (stripes merging or splitting near singularities), split where the
target curvature kappa1 changes sign (front for kappa1 > 0, back for < 0) and dropped when
shorter than min_length.

Units: mm (printed, pre-stretched flat state), curvature 1/mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from geometry.elements import Ribbon
from geometry.meshops import mesh_edges
from geometry.stripes import isoline_set, stripe_field
from shellfem.errors import SelfshapeError


# ----------------------------------------------------------------------------- ragged polylines

@dataclass
class _Paths:
    """Concatenated polylines. Piece j is rows off[j]:off[j+1] of pts (k, 2) and attr (k, q);
    face[i] is the mesh face holding the segment i -> i + 1 (-1 on each piece's last point)."""
    pts: np.ndarray
    attr: np.ndarray
    face: np.ndarray
    off: np.ndarray

    @property
    def n(self) -> int:
        return len(self.off) - 1

    def piece_of_point(self) -> np.ndarray:
        return np.repeat(np.arange(self.n), np.diff(self.off))

    def seg_len(self) -> np.ndarray:
        """Length of segment i -> i + 1 (0 on each piece's last point)."""
        d = np.zeros(len(self.pts))
        d[:-1] = np.linalg.norm(np.diff(self.pts, axis=0), axis=1)
        d[self.off[1:] - 1] = 0.0
        return d

    def arc(self) -> tuple[np.ndarray, np.ndarray]:
        """Arc length of each point from its piece start, and piece lengths."""
        if len(self.pts) == 0:
            return np.zeros(0), np.zeros(self.n)
        d = self.seg_len()
        c = np.concatenate([[0.0], np.cumsum(d)[:-1]])
        c -= np.repeat(c[self.off[:-1]], np.diff(self.off))
        return c, c[self.off[1:] - 1]

    def lengths(self) -> np.ndarray:
        return self.arc()[1]

    def select(self, keep: np.ndarray) -> "_Paths":
        cnt = np.diff(self.off)
        rows = np.repeat(keep, cnt)
        off = np.concatenate([[0], np.cumsum(cnt[keep])]).astype(np.int64)
        return _Paths(self.pts[rows], self.attr[rows], self.face[rows], off)


def _cut(paths: _Paths, piece: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> _Paths:
    """Sub-polylines [s0, s1] (arc length, 0 <= s0 < s1 <= piece length) of the given pieces,
    with attributes linearly interpolated at the new end points."""
    ok = s1 - s0 > 1e-9
    piece, s0, s1 = piece[ok], s0[ok], s1[ok]
    if len(piece) == 0:
        return _Paths(np.zeros((0, 2)), np.zeros((0, paths.attr.shape[1])), np.zeros(0, np.int64),
                      np.zeros(1, np.int64))
    c, L = paths.arc()
    base = np.concatenate([[0.0], np.cumsum(L + 1.0)[:-1]])
    g = c + np.repeat(base, np.diff(paths.off))
    G0 = base[piece] + np.clip(s0, 0.0, L[piece])
    G1 = base[piece] + np.clip(s1, 0.0, L[piece])
    i0 = np.searchsorted(g, G0, side="right")
    i1 = np.searchsorted(g, G1, side="left")
    last = paths.off[piece + 1] - 1
    i0 = np.clip(i0, paths.off[piece] + 1, last)
    i1 = np.clip(i1, paths.off[piece] + 1, last)
    i1 = np.maximum(i1, i0)

    def interp(G, j):
        den = g[j + 1] - g[j]
        u = np.clip((G - g[j]) / np.where(den > 0, den, 1.0), 0.0, 1.0)[:, None]
        return (1 - u) * paths.pts[j] + u * paths.pts[j + 1], (1 - u) * paths.attr[j] + u * paths.attr[j + 1]

    p0, a0 = interp(G0, i0 - 1)
    p1, a1 = interp(G1, i1 - 1)
    cnt = i1 - i0 + 2
    off = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
    r = np.repeat(np.arange(len(cnt)), cnt)
    pos = np.arange(off[-1]) - off[r]
    src = i0[r] + pos - 1                       # source point for interior rows
    first = pos == 0
    lastrow = pos == cnt[r] - 1
    mid = ~(first | lastrow)
    pts = np.empty((off[-1], 2))
    attr = np.empty((off[-1], paths.attr.shape[1]))
    pts[mid], attr[mid] = paths.pts[src[mid]], paths.attr[src[mid]]
    pts[first], attr[first] = p0, a0
    pts[lastrow], attr[lastrow] = p1, a1
    face = paths.face[np.clip(i0[r] - 1 + pos, 0, len(paths.face) - 1)]
    face[lastrow] = -1
    return _Paths(pts, attr, face, off)


def _runs_to_intervals(paths: _Paths, good: np.ndarray):
    """Maximal runs of consecutive segments with good == True, as (piece, s0, s1)."""
    c, _ = paths.arc()
    is_seg = paths.face >= 0
    good = good & is_seg
    prev = np.concatenate([[False], good[:-1]])
    nxt = np.concatenate([good[1:], [False]])
    starts = np.nonzero(good & ~prev)[0]
    ends = np.nonzero(good & ~nxt)[0]
    piece = paths.piece_of_point()[starts]
    return piece, c[starts], c[ends + 1]


# ----------------------------------------------------------------------------- mesh helpers

def _vertex_average(F, n, areas, values):
    """Area-weighted average of per-face values at the vertices."""
    w = np.bincount(F.ravel(), weights=np.repeat(areas, 3), minlength=n)
    s = np.bincount(F.ravel(), weights=np.repeat(areas * values, 3), minlength=n)
    return s / w


def mesh_outline(uv, F):
    """The flat mesh's region as a shapely (Multi)Polygon, from its boundary edges (mm)."""
    uv = np.asarray(uv, dtype=float)
    F = np.asarray(F, dtype=np.int64)
    E, face_edge, _ = mesh_edges(F, len(uv))
    once = np.bincount(face_edge.ravel(), minlength=len(E)) == 1
    lines = shapely.multilinestrings(uv[E[once]].reshape(-1, 2, 2))
    area = shapely.build_area(lines)
    if area.is_empty:
        raise SelfshapeError("ribbon_layout: the flat mesh has no closed boundary")
    return area


def _outline_polygon(outline, uv, F):
    if outline is None:
        return mesh_outline(uv, F)
    if isinstance(outline, shapely.Geometry):
        poly = outline
    else:
        pts = np.asarray(outline, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3 or not np.isfinite(pts).all():
            raise SelfshapeError("ribbon_layout: outline must be a (k, 2) array of at least 3 finite points")
        poly = shapely.Polygon(pts)
    if poly.geom_type not in ("Polygon", "MultiPolygon") or poly.is_empty or not poly.is_valid:
        raise SelfshapeError(f"ribbon_layout: outline is not a valid polygon ({shapely.is_valid_reason(poly)})")
    return poly


def _check_face_array(name, a, m, cols=None):
    a = np.asarray(a, dtype=float)
    shape = (m,) if cols is None else (m, cols)
    if a.shape != shape:
        raise SelfshapeError(f"ribbon_layout: {name} must have shape {shape}, got {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        raise SelfshapeError(f"ribbon_layout: {name}[{int(np.argwhere(bad)[0, 0])}] is not finite")
    return a


# ----------------------------------------------------------------------------- layout steps

def _level_crossings(p0, p1, value):
    """Levels value + 2 pi k in (min(p0, p1), max(p0, p1)] per row: (row, u) with the level
    at p0 + u (p1 - p0)."""
    lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
    k_lo = np.floor((lo - value) / (2 * np.pi)).astype(np.int64) + 1
    k_hi = np.floor((hi - value) / (2 * np.pi)).astype(np.int64)
    nk = np.maximum(k_hi - k_lo + 1, 0)
    rows = np.repeat(np.arange(len(p0)), nk)
    k = k_lo[rows] + np.arange(len(rows)) - np.repeat(np.cumsum(nk) - nk, nk)
    lev = value + 2 * np.pi * k
    return rows, (lev - p0[rows]) / (p1[rows] - p0[rows])


def _grid_lines(uv, F, theta, psi, value, fields_v, ribbon_length) -> tuple[_Paths, np.ndarray]:
    """Centre lines arg(theta) = value and the arc positions (piece, s) of their dash centres
    (crossings with arg(psi) = value). Closed loops are doubled so that dashes can straddle the
    seam. Point attributes: the per-vertex ``fields_v`` (n, q) interpolated along mesh edges,
    then the edge (a, b, t) each point lies on (valid on isoline points only)."""
    S = isoline_set(uv, F, theta, value)
    if len(S.closed) == 0:
        return _Paths(np.zeros((0, 2)), np.zeros((0, fields_v.shape[1] + 3)), np.zeros(0, np.int64),
                      np.zeros(1, np.int64)), np.zeros((0, 2))
    a, b = S.edge[:, 0], S.edge[:, 1]
    t = S.t
    q = fields_v.shape[1]
    attr = np.column_stack([(1 - t)[:, None] * fields_v[a] + t[:, None] * fields_v[b], a, b, t])
    # rows of each piece: its points, then (closed loops) the points again and the first point
    cnt = np.diff(S.offsets)
    ext = np.where(S.closed, 2 * cnt + 1, cnt)
    off = np.concatenate([[0], np.cumsum(ext)]).astype(np.int64)
    r = np.repeat(np.arange(len(cnt)), ext)
    pos = np.arange(off[-1]) - off[r]
    src = S.offsets[r] + pos % cnt[r]
    face = S.seg_face[src].copy()
    face[off[1:] - 1] = -1
    paths = _Paths(S.points[src], attr[src], face, off)

    # psi phase at both ends of each segment, in the segment's face (corner interpolation)
    j = np.nonzero(paths.face >= 0)[0]
    f = paths.face[j]
    live = ~psi.singular[f]
    j, f = j[live], f[live]

    def phase(row, f):
        ea, eb, tt = paths.attr[row, q].astype(np.int64), paths.attr[row, q + 1].astype(np.int64), \
            paths.attr[row, q + 2]
        ca = np.argmax(F[f] == ea[:, None], axis=1)
        cb = np.argmax(F[f] == eb[:, None], axis=1)
        return (1 - tt) * psi.alpha[f, ca] + tt * psi.alpha[f, cb]

    p0, p1 = phase(j, f), phase(j + 1, f)
    c, L = paths.arc()
    seg = paths.seg_len()
    rows, u = _level_crossings(p0, p1, value)
    jj = j[rows]
    centre = c[jj] + u * seg[jj]
    piece = paths.piece_of_point()[jj]
    # dashes centred just beyond an open end (outside the mesh or in a singular zone) still
    # reach into the piece: extrapolate psi's phase linearly over half a ribbon length
    half = 0.5 * ribbon_length
    pp = paths.piece_of_point()[j]
    is_first = j == paths.off[pp]
    is_last = j + 1 == paths.off[pp + 1] - 1
    opn = ~S.closed[pp]
    ext_centres, ext_piece = [], []
    for sel, anchor, other, sign in ((is_first & opn, p0, p1, -1.0), (is_last & opn, p1, p0, 1.0)):
        ks = np.nonzero(sel & (seg[j] > 0))[0]
        slope = (anchor[ks] - other[ks]) / seg[j[ks]]          # phase change per mm outwards
        r2, u2 = _level_crossings(anchor[ks], anchor[ks] + slope * half, value)
        start = np.where(sign < 0, 0.0, L[pp[ks]])
        ext_centres.append(start[r2] + sign * u2 * half)
        ext_piece.append(pp[ks][r2])
    centre = np.concatenate([centre] + ext_centres)
    piece = np.concatenate([piece] + ext_piece)
    closed_piece = S.closed[piece]
    loop_len = 0.5 * L[piece]
    keep = np.where(closed_piece, (centre >= half) & (centre < loop_len + half) & (loop_len > ribbon_length),
                    True)
    return paths, np.column_stack([piece[keep], centre[keep]])


def _dashes(paths: _Paths, centres: np.ndarray, ribbon_length: float) -> _Paths:
    piece = centres[:, 0].astype(np.int64)
    p = centres[:, 1]
    L = paths.lengths()[piece]
    half = 0.5 * ribbon_length
    return _cut(paths, piece, np.maximum(p - half, 0.0), np.minimum(p + half, L))


def _clip(paths: _Paths, region) -> _Paths:
    """Parts of the pieces inside ``region`` (shapely polygon)."""
    if paths.n == 0:
        return paths
    lines = shapely.linestrings(paths.pts, indices=paths.piece_of_point())
    shapely.prepare(region)
    inside = shapely.within(lines, region)
    out = np.nonzero(~inside)[0]
    _, L = paths.arc()
    piece = [np.nonzero(inside)[0]]
    s0 = [np.zeros(inside.sum())]
    s1 = [L[inside]]
    if len(out):
        parts, idx = shapely.get_parts(shapely.intersection(lines[out], region), return_index=True)
        is_line = shapely.get_type_id(parts) == 1
        parts, idx = parts[is_line], out[idx[is_line]]
        if len(parts):
            a = shapely.line_locate_point(lines[idx], shapely.get_point(parts, 0))
            b = shapely.line_locate_point(lines[idx], shapely.get_point(parts, -1))
            piece.append(idx)
            s0.append(np.minimum(a, b))
            s1.append(np.maximum(a, b))
    piece, s0, s1 = (np.concatenate(x) for x in (piece, s0, s1))
    order = np.lexsort((s0, piece))
    return _cut(paths, piece[order], s0[order], s1[order])


def _trim_angle(paths: _Paths, dir1: np.ndarray, max_angle_deg: float) -> _Paths:
    d = np.zeros_like(paths.pts)
    d[:-1] = np.diff(paths.pts, axis=0)
    ln = np.linalg.norm(d, axis=1)
    f = np.maximum(paths.face, 0)
    ref = dir1[f] / np.linalg.norm(dir1[f], axis=1)[:, None]
    cos = np.abs(np.sum(d * ref, axis=1)) / np.where(ln > 0, ln, 1.0)
    good = (cos >= np.cos(np.deg2rad(max_angle_deg)) - 1e-12) | (ln == 0)
    return _cut(paths, *_runs_to_intervals(paths, good))


def _split_sides(paths: _Paths) -> tuple[_Paths, np.ndarray]:
    """Split pieces where kappa (attr column 0) changes sign; side +1 (front) / -1 (back)."""
    k = paths.attr[:, 0]
    sgn = np.where(k < 0, -1, 1)
    c, L = paths.arc()
    seg = paths.seg_len()
    i = np.nonzero((paths.face >= 0) & (sgn != np.roll(sgn, -1)))[0]
    z = c[i] + seg[i] * k[i] / (k[i] - k[i + 1])
    pp = paths.piece_of_point()
    # breakpoints per piece: 0, zero crossings, L
    piece = np.concatenate([np.arange(paths.n), pp[i], np.arange(paths.n)])
    pos = np.concatenate([np.zeros(paths.n), z, L])
    order = np.lexsort((pos, piece))
    piece, pos = piece[order], pos[order]
    same = piece[1:] == piece[:-1]
    cut = _cut(paths, piece[:-1][same], pos[:-1][same], pos[1:][same])
    if cut.n == 0:
        return cut, np.zeros(0, np.int64)
    kk = cut.attr[:, 0]
    side = np.where(np.add.reduceat(kk, cut.off[:-1]) < 0, -1, 1)
    # end points at a sign change carry round-off of either sign: they are zeros
    cut.attr[:, 0] = np.where(kk * np.repeat(side, np.diff(cut.off)) < 0, 0.0, kk)
    return cut, side


# ----------------------------------------------------------------------------- public API

def ribbon_layout(uv, F, dir1, sigma1, sigma2, kappa1, s: float, outline=None,
                  ribbon_length: float = 15.0, ribbon_width: float = 1.5, min_length: float = 2.0,
                  max_angle_deg: float = 25.0, seed: int = 0, bound_tol: float = 0.05,
                  contraction=None) -> list[Ribbon]:
    """Staggered dashed ribbons over a flattened mesh (seed 5.4.2).

    uv: (n, 2) flat vertices (mm); F: (m, 3) faces. Per face: dir1 (m, 2) ribbon direction,
    sigma1 / sigma2 (m,) target stretch along / across it, kappa1 (m,) signed target normal
    curvature along dir1 (1/mm; > 0 is obtained by printing on the front). s: fabric
    pre-stretch. outline: (k, 2) polygon or shapely polygon, default the mesh boundary.
    Ribbon dimensions l_r = ribbon_length, w_r = ribbon_width (mm). sigma values within
    bound_tol below 1 (the flattening's bound residual) are treated as 1.

    Returns Ribbon records (path (k, 2) mm, width_mm = w_r, thickness_mm = 0 until the thickness
    law assigns it, side "front"/"back") with meta: "kappa" (k,) samples along the path,
    "kappa_mean_abs" (length-weighted mean |kappa1|), "mu2" (local transverse spacing, mm),
    "mu1" (local dash period, mm), "grid" ("A" or "B").
    ``contraction``: the model that maps the stretches to the spacings (inverse.contraction;
    None: the seed's Eq. 5.15, inverse.contraction.SeedContraction).
    """
    uv = np.asarray(uv, dtype=float)
    F = np.asarray(F)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise SelfshapeError(f"ribbon_layout: uv must be an (n, 2) array, got shape {uv.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise SelfshapeError(f"ribbon_layout: F must be an (m, 3) integer array, got shape {F.shape}")
    F = F.astype(np.int64)
    m, n = len(F), len(uv)
    dir1 = _check_face_array("dir1", dir1, m, 2)
    sigma1 = _check_face_array("sigma1", sigma1, m)
    sigma2 = _check_face_array("sigma2", sigma2, m)
    kappa1 = _check_face_array("kappa1", kappa1, m)
    for name, val, lo in (("min_length", min_length, 0.0), ("max_angle_deg", max_angle_deg, 0.0),
                          ("bound_tol", bound_tol, 0.0)):
        if not np.isfinite(val) or val < lo:
            raise SelfshapeError(f"ribbon_layout: {name} = {val} must be a finite number >= {lo}")
    if not 0.0 < max_angle_deg <= 90.0:
        raise SelfshapeError(f"ribbon_layout: max_angle_deg = {max_angle_deg} must be in (0, 90]")
    bad = np.linalg.norm(dir1, axis=1) == 0
    if bad.any():
        raise SelfshapeError(f"ribbon_layout: dir1[{int(np.argmax(bad))}] is zero")
    sigma1 = np.where((sigma1 < 1.0) & (sigma1 >= 1.0 - bound_tol), 1.0, sigma1)
    sigma2 = np.where((sigma2 < 1.0) & (sigma2 >= 1.0 - bound_tol), 1.0, sigma2)
    if contraction is None:
        from inverse.contraction import SeedContraction
        contraction = SeedContraction(s, ribbon_length, ribbon_width)
    mu1, mu2, _ = contraction.spacing(sigma1, sigma2)
    region = _outline_polygon(outline, uv, F)

    e1, e2 = uv[F[:, 1]] - uv[F[:, 0]], uv[F[:, 2]] - uv[F[:, 0]]
    areas = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    mu1_v = _vertex_average(F, n, areas, mu1)
    mu2_v = _vertex_average(F, n, areas, mu2)
    kappa_v = _vertex_average(F, n, areas, kappa1)
    fields_v = np.column_stack([kappa_v, mu2_v, mu1_v])
    perp = np.column_stack([-dir1[:, 1], dir1[:, 0]])
    theta = stripe_field(uv, F, dir1, 2.0 * mu2_v, seed=seed, direction_on="face")
    psi = stripe_field(uv, F, perp, mu1_v, seed=seed + 1, direction_on="face")

    eroded = region.buffer(-0.5 * ribbon_width)
    ribbons: list[Ribbon] = []
    for grid, value in (("A", 0.0), ("B", np.pi)):
        lines, centres = _grid_lines(uv, F, theta, psi, value, fields_v, ribbon_length)
        if len(centres) == 0:
            continue
        dash = _dashes(lines, centres, ribbon_length)
        for step in (lambda p: _clip(p, eroded), lambda p: _trim_angle(p, dir1, max_angle_deg)):
            if dash.n:
                dash = step(dash)
        if dash.n == 0:
            continue
        dash, side = _split_sides(dash)
        keep = dash.lengths() >= min_length
        dash, side = dash.select(keep), side[keep]
        ribbons.extend(_records(dash, side, grid, ribbon_width))
    for i, r in enumerate(ribbons):
        r.label = f"ribbon[{i}]"
    return ribbons


def _records(paths: _Paths, side, grid, width) -> list[Ribbon]:
    """Ribbon records; attr columns 0, 1, 2 are kappa1, mu2, mu1 along the path."""
    seg = paths.seg_len()
    out = []
    for j in range(paths.n):
        sl = slice(paths.off[j], paths.off[j + 1])
        w = seg[sl][:-1]
        L = max(w.sum(), 1e-300)
        k, mu2, mu1 = paths.attr[sl, 0], paths.attr[sl, 1], paths.attr[sl, 2]
        trap = lambda v: float(np.sum(w * 0.5 * (v[:-1] + v[1:])) / L)  # noqa: E731
        out.append(Ribbon(path=paths.pts[sl].copy(), width_mm=float(width), thickness_mm=0.0,
                          side="front" if side[j] > 0 else "back",
                          meta={"kappa": k.copy(), "kappa_mean_abs": trap(np.abs(k)),
                                "mu2": trap(mu2), "mu1": trap(mu1), "grid": grid}))
    return out
