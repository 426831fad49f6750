"""The reference domain: a flat triangulated sheet in its printed (pre-stretched) state.

Coordinates are millimetres in the printed state. Each triangle carries its printed
region id (0 = bare fabric, k > 0 = k-th printed element/region) and the plastic
thickness on each face of the fabric (``thickness_front`` on +z, ``thickness_back``
on -z; 0 where there is none). Both may be non-zero where the fabric was printed on
both sides.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from skfem import MeshTri

from shellfem.errors import SelfshapeError


@dataclass
class Sheet:
    points: np.ndarray            # (n, 2) printed-state positions, mm
    triangles: np.ndarray         # (m, 3) vertex indices
    region: np.ndarray = None     # (m,) int, 0 = bare fabric
    thickness_front: np.ndarray = None  # (m,) mm of plastic on the front (+z) face
    thickness_back: np.ndarray = None   # (m,) mm of plastic on the back (-z) face
    _mesh: MeshTri = field(default=None, repr=False)

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=float)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int64)
        m = len(self.triangles)
        if self.region is None:
            self.region = np.zeros(m, dtype=np.int64)
        if self.thickness_front is None:
            self.thickness_front = np.zeros(m)
        if self.thickness_back is None:
            self.thickness_back = np.zeros(m)
        self.region = np.asarray(self.region, dtype=np.int64)
        self.thickness_front = np.asarray(self.thickness_front, dtype=float)
        self.thickness_back = np.asarray(self.thickness_back, dtype=float)
        self.validate()
        # counter-clockwise orientation so that the face normals start along +z
        p = self.points[self.triangles]
        cross = ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                 - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
        flip = cross < 0
        if flip.any():
            self.triangles[flip] = self.triangles[flip][:, [0, 2, 1]]

    def validate(self):
        """Raise SelfshapeError (one line) on anything the engine cannot use."""
        p, t = self.points, self.triangles
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
            raise SelfshapeError(f"sheet: points must be an (n, 2) array with n >= 3, got shape {p.shape}")
        if t.ndim != 2 or t.shape[1] != 3 or len(t) < 1:
            raise SelfshapeError(f"sheet: triangles must be an (m, 3) array, got shape {t.shape}")
        if not np.all(np.isfinite(p)):
            bad = int(np.argwhere(~np.isfinite(p))[0, 0])
            raise SelfshapeError(f"sheet: point {bad} has a non-finite coordinate")
        if t.min() < 0 or t.max() >= len(p):
            raise SelfshapeError("sheet: a triangle refers to a point index out of range")
        m = len(t)
        for name in ("region", "thickness_front", "thickness_back"):
            a = getattr(self, name)
            if a.shape != (m,):
                raise SelfshapeError(f"sheet: {name} must have one value per triangle ({m}), got shape {a.shape}")
        for name in ("thickness_front", "thickness_back"):
            a = getattr(self, name)
            if not np.all(np.isfinite(a)) or (a < 0).any():
                bad = int(np.argwhere(~(np.isfinite(a) & (a >= 0)))[0, 0])
                raise SelfshapeError(f"sheet: {name} of triangle {bad} is {a[bad]!r}; thickness must be >= 0 mm")
        q = p[t]
        e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
        area2 = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        longest = np.max(np.stack([np.hypot(*e1.T), np.hypot(*e2.T), np.hypot(*(q[:, 2] - q[:, 1]).T)]), axis=0)
        degenerate = area2 <= 1e-10 * np.maximum(longest, 1e-300) ** 2
        if degenerate.any():
            i = int(np.argmax(degenerate))
            raise SelfshapeError(f"sheet: triangle {i} (vertices {t[i].tolist()}) is degenerate (zero area)")

    @property
    def mesh(self) -> MeshTri:
        """The scikit-fem mesh of the reference domain (edges = skfem facets)."""
        if self._mesh is None:
            self._mesh = MeshTri(self.points.T.copy(), self.triangles.T.copy())
        return self._mesh

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @property
    def printed(self) -> np.ndarray:
        """Boolean per triangle: carries plastic on either face."""
        return (self.thickness_front > 0) | (self.thickness_back > 0)

    @property
    def side(self) -> np.ndarray:
        """Per triangle: +1 plastic on the front only, -1 back only, 0 bare fabric, 2 both faces."""
        f, b = self.thickness_front > 0, self.thickness_back > 0
        s = np.zeros(self.n_triangles, dtype=np.int64)
        s[f & ~b], s[b & ~f], s[f & b] = 1, -1, 2
        return s

    @property
    def thickness(self) -> np.ndarray:
        """Total plastic thickness per triangle, mm."""
        return self.thickness_front + self.thickness_back

    @staticmethod
    def rectangle(width: float, height: float, nx: int, ny: int, diagonal: str = "alternate") -> "Sheet":
        """A structured triangulation of [0, width] x [0, height] (mm), for tests and studies."""
        x, y = np.meshgrid(np.linspace(0, width, nx + 1), np.linspace(0, height, ny + 1), indexing="ij")
        pts = np.column_stack([x.ravel(), y.ravel()])
        idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        if diagonal == "alternate":
            ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
            alt = ((ii + jj) % 2 == 1).ravel()
        else:
            alt = np.zeros(nx * ny, bool)
        t1 = np.where(alt[:, None], np.column_stack([a, b, d]), np.column_stack([a, b, c]))
        t2 = np.where(alt[:, None], np.column_stack([b, c, d]), np.column_stack([a, c, d]))
        return Sheet(pts, np.vstack([t1, t2]))
