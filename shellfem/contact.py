"""Contact of the sheet with itself and with the ground: barrier energies on the positions (N mm),
their exact gradients and (PSD-projected) Hessians, and a step filter so that no step passes through.

Self-contact is built on ipctk (the IPC Toolkit's Python bindings: collision mesh, broad phase,
the smoothly clamped log barrier of Li et al. 2020 with its derivatives, continuous collision
detection by Additive CCD). Two surfaces of the sheet may not come closer than the sum of their
half-thicknesses; this is implemented as one global offset ``offset`` = the sheet's largest total
thickness (fabric + plastic front + back, mm), so two printed layers keep their full thickness apart
and bare fabric is kept a little farther than it needs (conservative). The barrier is active in a
band of width ``dhat`` above the offset (distances in (offset, offset + dhat)) and is +inf at the
offset: ipctk's barrier in the squared distance, kappa b(d^2 - offset^2, 2 offset dhat + dhat^2).

Neighbour exclusion: a sheet with a thickness offset is "in contact" with its own neighbours
everywhere, so vertex pairs close in the printed (flat, rest) state cannot collide: those in the
same cell of any of four printed-state grids of size g = ``exclusion_mm`` shifted by g/2 (ipctk's
vertex-patch filters, intersected; a pair of primitives is excluded when all its vertex pairs
are). Every pair closer than g/2 (max-norm) is excluded, every pair farther than g sqrt(2) can
collide. g/2 = (K + 1) L + 4 L / 3 (L the longest printed edge, K the skip test's patch reach
below) covers every pair of primitives closer than 1.3 s_max (offset + dhat) + 2 L: all pairs
that touch in a released, moderately curved state (a released sheet is the printed one
contracted by up to s_max). Two parts of the sheet farther apart than that in the printed state
can only meet after the sheet has rolled or folded back onto itself (a roll of radius r brings
layers 2 pi r s together), which is what self-contact is for. (ipctk's sparse vertex-pair map
was tried first: with the 2.9M pairs of the 10k-vertex benchmark it took 37 s to build and 7 s
per broad phase.)

Skip: before building collisions at a state (or running CCD on a move), a cheap test proves that
no pair of non-excluded primitives is within offset + dhat (:meth:`Contact.maybe_close`: bounding
boxes of printed-grid patches of vertices, inflated by the longest edge, compared only between
patches that are not printed neighbours, and where two patches come close, the same test on their
triangles' bounding spheres against the printed distance the exclusion covers, then the exact
distances of the triangle pairs left); then the barrier is 0 with zero derivatives and nothing
is built, so a sheet that never touches itself pays only that test. A sheet in contact fails the
test at every call: the closest pairs found within reach are kept and measured first at the next
call, which then fails at once instead of going through the stages.

Ground: the plane z = height (mm) under the sheet's mid-surface: a barrier on each free vertex's
height above it, kappa_g b(z - height, dhat) (hand-written, vectorised, exact first and second
derivatives: the Hessian is diagonal). A vertex resting on the ground sits in the band (0, dhat);
supports that stand the sheet on the table hold it at the band's top, height + dhat, where the
barrier exerts no force (forward.simulate.support_plane: a held vertex on the plane itself, where
the barrier is infinite, pushed its free neighbours up by most of the band within one edge).
Vertices whose z is held are not in the barrier, and a held vertex below the plane is a support
that forces penetration (an error, see :meth:`Contact.check_start`).

Barrier stiffness (scale-free): kappa = 0.01 median(diag H_x) / (offset + dhat)^2, with diag H_x
the position diagonal of the elastic Hessian at the start of a solve: the barrier's curvature
(kappa b'' (2 d)^2 ~ kappa (offset + dhat)^2 in the band) is then ~1/100 of a typical elastic
diagonal, stiff enough to stop a layer within the band and soft enough not to dominate Newton.
"""
from __future__ import annotations

from collections import deque

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from shellfem.errors import SelfshapeError
from shellfem.triangle_distance import triangle_pair_distances

#: the barrier's activation band above the offset, as a fraction of the offset
BAND_FRACTION = 0.25
#: kappa = KAPPA_SCALE median(diag H_x) / (offset + dhat)^2 (see the module docstring)
KAPPA_SCALE = 0.01


#: the skip test's triangle stage runs only when at most this many patch pairs per patch came
#: close (a patch has 8 neighbours at the reach): the calls it settled had under 0.03 per patch on
#: the gallery tube's coarse level (1.13 at the most, on a move), those it could not up to 110 (a
#: large line-search move or a sheet in contact), at 10-60 ms a call against 0.2 ms; there
#: ipctk's own broad phase is cheaper
TRIANGLE_STAGE_PAIRS = 8.0
#: Most triangle pairs the skip test measures exactly (shellfem.triangle_distance) after their
#: bounding spheres came within reach; beyond it the collisions are built.
EXACT_STAGE_PAIRS = 20_000
#: Triangle pairs the skip test keeps as witnesses: the closest pairs its exact stage found within
#: reach, measured first at the next call (a sheet in contact stays in contact from one trial
#: point to the next, and proving that again through the patch and triangle stages cost more
#: than the collision build it leads to)
WITNESS_PAIRS = 64

#: The step filter's continuous collision detection runs on pieces of the move in which no vertex
#: travels farther than half the exclusion (g/2, mm), at most this many per call (see
#: :meth:`Contact.step_fraction`). ipctk's broad phase puts each primitive's whole swept box in
#: its candidate list: on the 10k-vertex 50 x 35 mm analogue of examples/stars_tube.toml a 5 mm
#: move took 0.6 s and 0.2 GB, a 20 mm one 7.3 s and 0.56 GB (every broad phase it has: hash
#: grid, LBVH, sweep and prune), and one 69 mm trial step on the tube itself (38,798 vertices)
#: took the process past the machine's 23 GB.
MAX_CCD_PIECES = 4

#: States whose distance bound (the closest non-excluded pair, capped at offset + dhat) is kept
#: for the step filter: a move in which no vertex travels farther than half of (bound - offset)
#: cannot bring any pair to the offset, so it needs no CCD (:meth:`Contact.step_fraction`). The
#: solver's iterate and its line search's last trials are enough.
CERTIFIED_STATES = 4

_IPCTK = None


def _ipctk():
    """ipctk on one thread: its parallel reductions (gradient, Hessian, minimum distance) sum in
    a thread-dependent order, and two runs of a sweep case in contact differed at round-off
    (energy 6.193908571679513 vs ...515 N mm); one thread keeps runs bitwise repeatable."""
    global _IPCTK
    if _IPCTK is None:
        try:
            import ipctk
        except ImportError as e:  # pragma: no cover - ipctk is a dependency
            raise SelfshapeError("contact needs ipctk (pip install ipctk); or set [contact] enabled = false") from e
        ipctk.set_num_threads(1)
        _IPCTK = ipctk
    return _IPCTK


def ground_barrier(h, dhat):
    """IPC's clamped log barrier b(h) = -(h - dhat)^2 log(h / dhat) for 0 < h < dhat (0 above,
    +inf at h <= 0) with b' and b'' (h in mm; b in mm^2): values, first, second derivatives."""
    h = np.asarray(h, float)
    act = h < dhat
    pos = h > 0
    b = np.zeros_like(h)
    b1 = np.zeros_like(h)
    b2 = np.zeros_like(h)
    a = act & pos
    ha = h[a]
    r = ha - dhat
    lg = np.log(ha / dhat)
    b[a] = -r * r * lg
    b1[a] = -2 * r * lg - r * r / ha
    b2[a] = -2 * lg - 4 * r / ha + r * r / (ha * ha)
    b[~pos] = np.inf
    return b, b1, b2


class Contact:
    """Self-contact and/or ground contact of a sheet (printed-state points, triangles).

    points: (n, 2) printed positions (mm); triangles: (m, 3); offset: minimum surface distance
    (mm, the largest total thickness); stretch_max: largest pre-stretch of the fabric;
    self_contact: build the self-contact barrier; ground: None or the plane's height z (mm);
    held_z: (n,) bool, vertices whose z is held (kept out of the ground barrier);
    exclusion_mm: another printed-state exclusion than this mesh's own (mm; see __init__; a smaller
    one is raised to the neighbours' minimum), or None.
    kappa is set by :meth:`set_stiffness` (N/mm^3 for self-contact, N/mm for the ground).
    """

    def __init__(self, points, triangles, offset: float, stretch_max: float = 1.0, self_contact: bool = True,
                 ground: float | None = None, held_z=None, band_fraction: float = BAND_FRACTION,
                 exclusion_mm: float | None = None):
        self.n = len(points)
        self.rest = np.column_stack([points, np.zeros(self.n)]).astype(float)
        self.faces = np.ascontiguousarray(triangles, dtype=np.int32)
        self.offset = float(offset)
        self.dhat = band_fraction * self.offset
        self.self_contact = bool(self_contact)
        self.ground = None if ground is None else float(ground)
        self.held_z = np.zeros(self.n, bool) if held_z is None else np.asarray(held_z, bool)
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        e.sort(axis=1)
        self.edges = np.ascontiguousarray(np.unique(e, axis=0), dtype=np.int32)
        P = self.rest[:, :2]
        L = float(np.linalg.norm(P[self.edges[:, 1]] - P[self.edges[:, 0]], axis=1).max())
        delta = self.offset + self.dhat
        # skip-test patches: triangles grouped by their centroid's printed-grid cell (size h = L);
        # patch pairs within K cells of each other hold only excluded pairs (below), the others
        # are tested. K: in a released, moderately curved state (contracted by up to s_max, 1.3
        # for curvature) two patches K + 1 cells apart keep their bounding spheres delta apart
        h = L
        K = int(np.ceil((1.3 * (stretch_max * delta + 4.0 / 3.0 * L) + 0.41 * h) / h))
        self.patch_reach = K
        # exclusion: vertex pairs in the same cell of any of four grids of size g shifted by g/2
        # cannot collide (ipctk vertex-patch filters, intersected): every pair closer than g/2 in
        # the printed state (max-norm) is excluded, every pair farther than g sqrt(2) is not;
        # g/2 = (K + 1) h + 4 L / 3 covers every vertex pair of two patches within K cells
        self.exclusion_mm = 2.0 * ((K + 1) * h + 4.0 / 3.0 * L)
        if exclusion_mm is not None and exclusion_mm < self.exclusion_mm:
            # a smaller exclusion asked for (a coarse level of nested iteration takes the finest
            # level's, so that both resolve the same contacts): at least the neighbours' minimum
            # g/2 = 1.3 s_max delta + 2 L (a non-excluded pair of primitives then keeps
            # (g/2 - 2 L) / (1.3 s_max) > delta apart in a released, moderately curved state);
            # the skip test's reach shrinks to the patches that still hold only excluded pairs
            # (none: every evaluation builds its collisions)
            self.exclusion_mm = max(float(exclusion_mm), 2.0 * (1.3 * stretch_max * delta + 2.0 * L))
            self.patch_reach = int(np.floor((self.exclusion_mm / 2.0 - 4.0 / 3.0 * L) / h)) - 1
        elif exclusion_mm is not None:
            # a larger one (a pattern's [contact] exclusion_mm): more pairs excluded, the skip
            # test's reach kept (its patches then hold only excluded pairs a fortiori)
            self.exclusion_mm = float(exclusion_mm)
        self._edge_printed = L
        self._tri_printed = P[self.faces].mean(1)          # printed triangle centroids (the second stage)
        origin = P.min(0)
        cells = np.floor((self._tri_printed - origin) / h).astype(np.int64)
        ncol = int(cells[:, 1].max()) + 1
        key = cells[:, 0] * ncol + cells[:, 1]
        uniq, tri_patch = np.unique(key, return_inverse=True)
        # the triangles of each patch, padded with -1: (n_patches, most triangles in a patch)
        order = np.argsort(tri_patch, kind="stable")
        count = np.bincount(tri_patch, minlength=len(uniq))
        slot = np.arange(len(order)) - np.repeat(np.cumsum(count) - count, count)
        self._patch_tris = np.full((len(uniq), int(count.max())), -1, np.int64)
        self._patch_tris[tri_patch[order], slot] = order
        self._cells = np.stack([uniq // ncol, uniq % ncol], 1)
        pv = np.unique(np.stack([np.repeat(tri_patch, 3), self.faces.ravel().astype(np.int64)], 1), axis=0)
        self._pv_patch, self._pv_vertex = pv[:, 0], pv[:, 1]          # sorted by patch
        self._pv_start = np.searchsorted(self._pv_patch, np.arange(len(uniq)))
        self._pv_count = np.bincount(self._pv_patch, minlength=len(uniq)).astype(float)
        self._grid_origin = origin
        self.kappa = 0.0
        self.kappa_ground = 0.0
        self._mesh = None          # ipctk CollisionMesh, built the first time the skip test fails
        self.builds = 0            # collision builds (skip test failed)
        self.skips = 0             # evaluations the skip test settled
        self.witness_hits = 0      # skip tests decided by the last close pairs alone
        self.reuses = 0            # evaluations at the last state's positions (its collisions reused)
        self._last_state = None    # (positions (n, 3), their collisions or None, closest pair's squared distance)
        self._witness = None       # (k, 2) triangle pairs found within reach by the last exact stage
        self._certificates = deque(maxlen=CERTIFIED_STATES)   # (positions, distance bound) of the last states
        self.certified_moves = 0   # step-filter calls settled by a state's distance bound

    def __getstate__(self):
        """Pickled without its ipctk objects (the collision mesh and the last state's collisions):
        caches, rebuilt when next needed (a simulation sent back from a worker process)."""
        state = self.__dict__.copy()
        state["_mesh"] = None
        state["_last_state"] = None
        return state

    # --- set-up ----------------------------------------------------------------------------
    def set_stiffness(self, diag_positions: np.ndarray):
        """kappa from the position diagonal of the elastic Hessian (N/mm): see the module docstring."""
        med = float(np.median(np.abs(diag_positions))) if len(diag_positions) else 1.0
        med = med if med > 0 and np.isfinite(med) else 1.0
        self.kappa = KAPPA_SCALE * med / (self.offset + self.dhat) ** 2
        self.kappa_ground = KAPPA_SCALE * med / self.dhat ** 2

    def _collision_mesh(self):
        if self._mesh is None:
            ipctk = _ipctk()
            mesh = ipctk.CollisionMesh(self.rest, self.edges, self.faces)
            g = self.exclusion_mm
            P = self.rest[:, :2] - self._grid_origin
            filt = None
            for shift in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
                ij = np.floor(P / g + shift).astype(np.int64)
                ids = (ij[:, 0] * (int(ij[:, 1].max()) + 2) + ij[:, 1]).astype(np.int32)
                f = ipctk.make_vertex_patches_filter(ids)
                filt = f if filt is None else (filt & f)
            mesh.can_collide = filt
            self._mesh = mesh
        return self._mesh

    def _edge_max(self, x):
        d = x[self.edges[:, 1]] - x[self.edges[:, 0]]
        return float(np.sqrt(np.einsum("ij,ij->i", d, d).max()))

    def maybe_close(self, x, x1=None) -> bool:
        """False when no two non-excluded primitives can come within offset + dhat of each other
        at x (n, 3) (mm), or anywhere on the straight move x -> x1: the skip test. Each patch's
        bounding sphere (centre: the mean of its triangles' vertices, over both states; radius: the
        farthest of them) holds its triangles all along the move (each point of a moving triangle
        is a convex combination of its corners' start and end positions); patches within
        patch_reach printed cells hold only excluded pairs, so if no two other patches' spheres
        come within offset + dhat, no pair of non-excluded primitives does. Where two do, the same
        test on their triangle pairs (:meth:`_triangles_close`) decides, where few enough came close
        (TRIANGLE_STAGE_PAIRS). O(n) plus a KD-tree over the patch centres. First of all, the
        closest pairs the last exact stage found within reach (the witnesses, WITNESS_PAIRS) are
        measured: if one still is, the answer is True at once (a sheet in contact stays so from
        one trial point to the next)."""
        if not self.self_contact:
            return False
        x = np.asarray(x, float).reshape(self.n, 3)
        states = [x] if x1 is None else [x, np.asarray(x1, float).reshape(self.n, 3)]
        delta = self.offset + self.dhat
        if self.patch_reach < 0:
            return True          # a patch's own triangles may hold pairs that are not excluded
        if self._witness is not None:
            if (self._pair_distances(states, self._witness[:, 0], self._witness[:, 1]) < delta).any():
                self.witness_hits += 1
                return True
            self._witness = None
        cnt = self._pv_count * len(states)
        centre = sum(np.stack([np.bincount(self._pv_patch, weights=y[self._pv_vertex, k], minlength=len(cnt))
                               for k in range(3)], 1) for y in states) / cnt[:, None]
        radius = np.zeros(len(cnt))
        for y in states:
            d = y[self._pv_vertex] - centre[self._pv_patch]
            radius = np.maximum(radius, np.sqrt(np.maximum.reduceat(np.einsum("ij,ij->i", d, d), self._pv_start)))
        pairs = cKDTree(centre).query_pairs(2.0 * float(radius.max()) + delta, output_type="ndarray")
        if len(pairs) == 0:
            return False
        a, b = pairs[:, 0], pairs[:, 1]
        far = np.abs(self._cells[a] - self._cells[b]).max(1) > self.patch_reach
        a, b = a[far], b[far]
        close = np.linalg.norm(centre[a] - centre[b], axis=1) - radius[a] - radius[b] < delta
        if not close.any():
            return False
        if close.sum() > TRIANGLE_STAGE_PAIRS * len(cnt):
            return True
        return self._triangles_close(states, a[close], b[close], delta)

    def _triangles_close(self, states, a, b, delta) -> bool:
        """The skip test's second stage, on the triangle pairs of the patch pairs (a, b) whose
        spheres came within delta: True if a pair that the exclusion may not cover (printed
        centroids at least g/2 - 4 L / 3 apart: closer ones have all nine vertex pairs within
        g/2, so excluded) has bounding spheres (over the move) within delta. The patches' spheres
        are about a cell plus an edge wide, so next to the exclusion's minimum (the coarse levels
        take the finest level's) patches near the reach never proved apart and every evaluation
        built its collisions; triangle spheres are an edge wide."""
        ta, tb = self._patch_tris[a][:, :, None], self._patch_tris[b][:, None, :]
        ok = (ta >= 0) & (tb >= 0)
        i, j = np.broadcast_to(ta, ok.shape)[ok], np.broadcast_to(tb, ok.shape)[ok]
        apart = self.exclusion_mm / 2.0 - 4.0 / 3.0 * self._edge_printed
        dp = self._tri_printed[i] - self._tri_printed[j]
        may = np.einsum("ij,ij->i", dp, dp) >= apart * apart
        i, j = i[may], j[may]
        if len(i) == 0:
            return False
        tri = np.unique(np.concatenate([i, j]))
        f = self.faces[tri]
        centre = sum(y[f].sum(1) for y in states) / (3.0 * len(states))
        radius = np.zeros(len(tri))
        for y in states:
            d = y[f] - centre[:, None]
            radius = np.maximum(radius, np.sqrt(np.einsum("ijk,ijk->ij", d, d).max(1)))
        i, j = np.searchsorted(tri, i), np.searchsorted(tri, j)
        dc = centre[i] - centre[j]
        gap = np.sqrt(np.einsum("ij,ij->i", dc, dc)) - radius[i] - radius[j]
        near = gap < delta
        if not near.any():
            return False
        many = near.sum() > EXACT_STAGE_PAIRS
        if many:             # the collisions are built anyway; the closest pairs give witnesses
            near = np.flatnonzero(near)
            near = near[np.argpartition(gap[near], EXACT_STAGE_PAIRS // 10)[:EXACT_STAGE_PAIRS // 10]]
        # third stage: the exact distance of the pairs left (see _pair_distances); the closest
        # pairs within reach are kept as the next call's witnesses
        i, j = tri[i[near]], tri[j[near]]
        d = self._pair_distances(states, i, j)
        hit = d < delta
        if not hit.any():
            return many
        keep = np.argsort(d)[:WITNESS_PAIRS]
        keep = keep[hit[keep]]
        self._witness = np.stack([i[keep], j[keep]], 1)
        return True

    def _pair_distances(self, states, i, j):
        """A lower bound (mm) on the distance of the triangle pairs (i, j) (global indices) at
        states[0] and along the straight move to states[1]: their exact distance at the start of
        the move less the two triangles' largest corner moves (along a straight move no point of
        a triangle travels farther than its farthest corner)."""
        x0 = states[0]
        fi, fj = self.faces[i], self.faces[j]
        d = triangle_pair_distances(x0[fi], x0[fj])
        if len(states) > 1:
            x1 = states[1]
            d = d - np.linalg.norm(x1[fi] - x0[fi], axis=2).max(1) - np.linalg.norm(x1[fj] - x0[fj], axis=2).max(1)
        return d

    def _collisions(self, x):
        """ipctk NormalCollisions at x, or None when the skip test settles it. The last state's
        answer is kept: the solver evaluates the state it accepts again (gradient, Hessian), and
        the edge-angle relaxation evaluates many states that share their positions."""
        if self._last_state is not None and np.array_equal(self._last_state[0], x):
            self.reuses += 1
            return self._last_state[1]
        if not self.maybe_close(x):
            self.skips += 1
            c = None
        else:
            ipctk = _ipctk()
            mesh = self._collision_mesh()
            self.builds += 1
            c = ipctk.NormalCollisions()
            c.build(mesh, np.asfortranarray(x), self.dhat, dmin=self.offset)
        # the closest pair's squared distance (mm^2; inf: none in the band), measured once per
        # state for the barrier's admissibility, the reports and the step filter's certificate
        d2 = (float(c.compute_minimum_distance(self._collision_mesh(), np.asfortranarray(x)))
              if c is not None and len(c) > 0 else np.inf)
        self._last_state = (np.array(x, float, copy=True), c, d2)
        # a lower bound on the distance (mm) between any two non-excluded primitives at x, for the
        # step filter's skip (:meth:`step_fraction`): offset + dhat when no pair is within it (the
        # skip test, or no collision built), else the closest collision's
        self._certificates.append((self._last_state[0], min(self.offset + self.dhat, float(np.sqrt(max(d2, 0.0))))))
        return c

    def _closest2(self) -> float:
        """Squared distance (mm^2) of the closest pair at the state of the last :meth:`_collisions`."""
        return self._last_state[2]

    def _certified_gap(self, x) -> float | None:
        """The distance bound kept by :meth:`_collisions` minus the offset (mm) at positions x, if x is
        one of the last CERTIFIED_STATES states evaluated, else None."""
        for y, bound in reversed(self._certificates):
            if y.shape == x.shape and np.array_equal(y, x):
                return bound - self.offset
        return None

    def _potential(self):
        return _ipctk().BarrierPotential(self.dhat, self.kappa)

    # --- energy -----------------------------------------------------------------------------
    def evaluate(self, x, order: int = 0, project: bool = False):
        """(E, gradient (3n,), Hessian (3n, 3n) CSR or None) of the contact energy at positions
        x (n, 3) mm: N mm, N, N/mm. order 0: E only; 1: + gradient; 2: + the exact Hessian, or
        with ``project`` the barrier's per-collision blocks projected to PSD (ipctk's CLAMP) and
        the ground's diagonal clamped at 0. E = inf if a pair is at or below the offset or a
        vertex at or below the ground. After order 2, :meth:`projected_hessian` gives the
        projected Hessian of the same state without rebuilding its collisions."""
        x = np.asarray(x, float).reshape(self.n, 3)
        E = 0.0
        g = np.zeros(3 * self.n) if order >= 1 else None
        H = None
        if order >= 2:
            self._last = None
            self._last_ground = None
        if self.self_contact and self.kappa > 0:
            c = self._collisions(x)
            if c is not None and len(c) > 0:
                ipctk = _ipctk()
                mesh, pot = self._collision_mesh(), self._potential()
                X = np.asfortranarray(x)
                if self._closest2() <= self.offset ** 2:
                    return np.inf, g, None          # at or through the offset: inadmissible
                E += float(pot(c, mesh, X))
                if order >= 1:
                    g += pot.gradient(c, mesh, X)
                if order >= 2:
                    H = sp.csr_matrix(pot.hessian(c, mesh, X, ipctk.PSDProjectionMethod.CLAMP if project
                                                  else ipctk.PSDProjectionMethod.NONE))
                    self._last = (c, X)
        if self.ground is not None and self.kappa_ground > 0:
            free = ~self.held_z
            h = x[free, 2] - self.ground
            b, b1, b2 = ground_barrier(h, self.dhat)
            if not np.all(np.isfinite(b)):
                return np.inf, g, None
            E += self.kappa_ground * float(b.sum())
            if order >= 1:
                g[3 * np.flatnonzero(free) + 2] += self.kappa_ground * b1
            if order >= 2:
                idx = 3 * np.flatnonzero(free) + 2
                self._last_ground = (idx, self.kappa_ground * b2)
                w = self.kappa_ground * (np.maximum(b2, 0.0) if project else b2)
                keep = w != 0
                Hg = sp.csr_matrix((w[keep], (idx[keep], idx[keep])), shape=(3 * self.n, 3 * self.n))
                H = Hg if H is None else H + Hg
        return E, g, H

    @property
    def indefinite_part(self) -> bool:
        """True when the contact Hessian of the last order-2 :meth:`evaluate` has a self-contact
        part, the only one PSD projection can change: the ground's diagonal kappa_g b''(h) is
        positive in the whole band (each of its three terms is >= 0 for 0 < h < dhat). The
        solver tries the projected contact Hessian only then; with the ground alone each try was
        a second failed factorisation of an indefinite step (51 of 204 on the 2.5k-vertex dome)."""
        return getattr(self, "_last", None) is not None

    def projected_hessian(self):
        """The PSD-projected contact Hessian (3n, 3n) of the state of the last order-2
        :meth:`evaluate` (ipctk's per-collision CLAMP; the ground's diagonal clamped at 0), or None."""
        H = None
        if getattr(self, "_last", None) is not None:
            ipctk = _ipctk()
            c, X = self._last
            H = sp.csr_matrix(self._potential().hessian(c, self._collision_mesh(), X, ipctk.PSDProjectionMethod.CLAMP))
        if getattr(self, "_last_ground", None) is not None:
            idx, w = self._last_ground
            w = np.maximum(w, 0.0)
            keep = w != 0
            Hg = sp.csr_matrix((w[keep], (idx[keep], idx[keep])), shape=(3 * self.n, 3 * self.n))
            H = Hg if H is None else H + Hg
        return H

    # --- step filter ----------------------------------------------------------------------
    def step_fraction(self, x0, x1) -> float:
        """Largest t in [0, 1] such that the straight motion x0 -> x0 + t (x1 - x0) keeps every
        non-excluded pair farther apart than the offset (ipctk's conservative Additive CCD) and
        every free vertex above the ground, or a smaller t (conservative) on a long move; 1.0 when
        the skip test (inflated by the largest vertex move) shows no pair can come within reach.
        A state reached through an accepted step is therefore intersection-free whatever path
        produced it (the straight segment from the previous state is collision-free).

        The CCD runs piece by piece along the move, each piece at most g/2 (half the exclusion,
        mm) of vertex travel, each first put to the skip test: the broad phase's memory and time
        grow with the square of the travel (MAX_CCD_PIECES). After MAX_CCD_PIECES pieces
        without a contact the answer is the fraction checked so far: the line search shortens
        such a step at once, as it would one cut by a contact."""
        x0 = np.asarray(x0, float).reshape(self.n, 3)
        x1 = np.asarray(x1, float).reshape(self.n, 3)
        t = 1.0
        if self.ground is not None:
            free = ~self.held_z
            z0, z1 = x0[free, 2] - self.ground, x1[free, 2] - self.ground
            down = z1 < 0.05 * z0
            if down.any():        # stop at 5 % of the start height: the barrier is +inf at 0
                t = min(t, float(np.min(0.95 * z0[down] / (z0[down] - z1[down]))))
        if self.self_contact and not self._certified_move(x0, x1) and self.maybe_close(x0, x1):
            t = min(t, self._ccd_pieces(x0, x1))
        return max(t, 0.0)

    def _certified_move(self, x0, x1) -> bool:
        """True when x0 is a recently evaluated state (its bound kept by :meth:`_collisions`) and no vertex travels
        farther than half of its distance bound less the offset: two points of different
        primitives approach each other by at most the sum of their travels, so no non-excluded
        pair reaches the offset along the straight move (no CCD needed)."""
        gap = self._certified_gap(x0)
        if gap is None or gap <= 0.0:
            return False
        dx = x1 - x0
        if 2.0 * float(np.sqrt(np.einsum("ij,ij->i", dx, dx).max())) < gap:
            self.certified_moves += 1
            return True
        return False

    def _ccd_pieces(self, x0, x1) -> float:
        """The self-contact part of :meth:`step_fraction`: the CCD on pieces of the move."""
        ipctk = _ipctk()
        dx = x1 - x0
        travel = float(np.sqrt(np.einsum("ij,ij->i", dx, dx).max()))
        pieces = max(1, int(np.ceil(travel / (0.5 * self.exclusion_mm))))
        for k in range(min(pieces, MAX_CCD_PIECES)):
            a = x0 + (k / pieces) * dx
            b = x0 + ((k + 1) / pieces) * dx if k + 1 < pieces else x1
            if pieces > 1 and not self.maybe_close(a, b):
                continue
            # Additive CCD (Li et al. 2021, made for thickness offsets): the Euclidean minimum
            # separation; Tight Inclusion's is an L-infinity box (a 1.1 mm offset stopped moves
            # of 1e-5 mm between layers 1.75 mm apart: the solve stalled)
            tc = float(ipctk.compute_collision_free_stepsize(self._collision_mesh(), np.asfortranarray(a),
                                                             np.asfortranarray(b), min_distance=self.offset,
                                                             narrow_phase_ccd=ipctk.AdditiveCCD()))
            if tc < 1.0:
                return (k + tc) / pieces
        return min(pieces, MAX_CCD_PIECES) / pieces

    # --- checks and reports ---------------------------------------------------------------------
    def intersects(self, x) -> bool:
        """True if the surface at x (n, 3) intersects itself (non-excluded primitives; ipctk)."""
        x = np.asarray(x, float).reshape(self.n, 3)
        if not self.self_contact or not self.maybe_close(x):
            return False
        return bool(_ipctk().has_intersections(self._collision_mesh(), np.asfortranarray(x)))

    def check_start(self, x, where: str = "contact") -> str | None:
        """None if x is an admissible start; else the reason (one line): a held vertex below the
        ground, a free vertex at or below it, a self-intersection, or two layers closer than the offset."""
        x = np.asarray(x, float).reshape(self.n, 3)
        if self.ground is not None:
            below = x[:, 2] < self.ground - 1e-9
            if np.any(below & self.held_z):
                return (f"{where}: a support holds the sheet {self.ground - x[below & self.held_z, 2].max():.3g} mm "
                        f"below the ground (z = {self.ground:g} mm): it forces penetration")
            if np.any(x[~self.held_z, 2] <= self.ground):
                return f"{where}: the start state reaches below the ground (z = {self.ground:g} mm)"
        if self.self_contact and self.maybe_close(x):
            if self.intersects(x):
                return f"{where}: the start state intersects itself"
            d = self.minimum_distance(x)
            if d <= self.offset:
                return (f"{where}: two layers of the start state are {d:.3g} mm apart, closer than the "
                        f"thickness offset {self.offset:.3g} mm")
        return None

    def minimum_distance(self, x) -> float:
        """Smallest distance (mm) between non-excluded primitives within offset + dhat of each
        other at x; inf when none is (the skip test or no collision in the band)."""
        c = self._collisions(np.asarray(x, float).reshape(self.n, 3)) if self.self_contact else None
        if c is None or len(c) == 0:
            return float("inf")
        return float(np.sqrt(max(self._closest2(), 0.0)))

    def report(self, x) -> dict:
        """{"min_distance_mm", "active_pairs", "ground_min_height_mm", "in_contact" (m,) bool}:
        the self-contact pairs within the barrier's band at x, the smallest distance among them
        (None: no pair in the band), the lowest free vertex's height above the ground, and the
        triangles touching an active pair or the ground band."""
        x = np.asarray(x, float).reshape(self.n, 3)
        in_contact_v = np.zeros(self.n, bool)
        active = 0
        dmin = None
        if self.self_contact:
            c = self._collisions(x)
            if c is not None and len(c) > 0:
                active = len(c)
                dmin = float(np.sqrt(max(self._closest2(), 0.0)))
                for k in range(len(c)):          # output only: one pass over the active pairs
                    ids = np.asarray(c[k].vertex_ids(self.edges, self.faces))
                    in_contact_v[ids[ids >= 0]] = True
        ground_min = None
        if self.ground is not None:
            free = ~self.held_z
            ground_min = float((x[free, 2] - self.ground).min()) if free.any() else None
            in_contact_v[free] |= (x[free, 2] - self.ground) < self.dhat
        in_contact = in_contact_v[self.faces].any(axis=1)
        return dict(min_distance_mm=dmin, active_pairs=int(active), ground_min_height_mm=ground_min,
                    in_contact=in_contact)
