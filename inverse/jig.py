"""Jig posts that select one equilibrium of a multistable printed sheet (mm, N).

A released sheet can settle in several stable states (a saddle or a rolled tube from the same
print). When release from flat reaches another state than the one a design was refined for,
the intended state can be selected by holding a few points of the sheet at their positions in
that state while it is released: pattern ``[[support]]`` tables with ``fix = "xyz"`` and a
``position``. The intended state is an equilibrium of the free sheet, so posts placed exactly
on it carry no load there; a release that reaches it on the posts reaches a state that stays
when the posts are removed (if it is stable), which the reactions measured at the posts show.
"""
from __future__ import annotations

import numpy as np


def farthest_points(points, k: int) -> np.ndarray:
    """Indices (k,) of k well-spread points of ``points`` (n, d): the point nearest the centroid,
    then greedily the point farthest from those chosen (farthest-point sampling; deterministic,
    ties to the lowest index)."""
    P = np.asarray(points, float)
    k = int(min(max(k, 1), len(P)))
    first = int(np.argmin(np.sum((P - P.mean(0)) ** 2, 1)))
    chosen = [first]
    d = np.sum((P - P[first]) ** 2, 1)
    for _ in range(k - 1):
        nxt = int(np.argmax(d))
        chosen.append(nxt)
        d = np.minimum(d, np.sum((P - P[nxt]) ** 2, 1))
    return np.array(chosen, np.int64)


def jig_supports(printed_points, positions, k: int, *, align: bool = True, triangles=None) -> list[dict]:
    """Pattern ``[[support]]`` tables (a list of dicts) of k jig posts: vertices chosen by
    :func:`farthest_points` on the printed (flat) sheet ``printed_points`` (n, 2|3, mm), each held
    (``fix = "xyz"``) at its position in the intended state ``positions`` (n, 3, mm).
    ``triangles`` (m, 3), the sheet's mesh: the posts are chosen among the vertices off its
    boundary (a rim vertex written to 1e-4 mm can land outside a curved outline, which the
    pattern then rejects; and a post is fixed under the sheet, not on its edge). ``align``:
    the state is first moved rigidly onto the printed sheet (least squares), so that the posts
    travel from the flat start by the shape change only: a state given in another frame (a
    target's) would drag the sheet through a large rigid motion, which the release's harmonic
    carrying of the posts' motion turns into a self-intersecting start."""
    from inverse.registration import kabsch

    flat = np.asarray(printed_points, float)[:, :2]
    X = np.asarray(positions, float)
    if align:
        R, c = kabsch(X, np.column_stack([flat, np.zeros(len(flat))]))
        X = X @ R.T + c
    cand = np.arange(len(flat))
    if triangles is not None:
        from geometry.meshops import unique_edges
        E, _, counts = unique_edges(np.asarray(triangles, np.int64))
        inner = np.setdiff1d(cand, E[counts == 1].ravel())
        cand = inner if len(inner) else cand
    idx = cand[farthest_points(flat[cand], k)]
    r4 = lambda a: np.round(a, 4).tolist()  # noqa: E731
    return [{"points": r4(flat[idx]), "fix": "xyz", "position": r4(X[idx])}]


def support_reactions(sim) -> np.ndarray:
    """Reaction force (N) at each held vertex of a converged forward.simulate.Simulation: the
    norm of the energy gradient's held components per vertex ((k,) for the k held vertices;
    empty when nothing is held)."""
    fixed = np.asarray(sim.fixed, np.int64)
    if len(fixed) == 0:
        return np.zeros(0)
    g = np.asarray(sim.model.gradient(sim.result.q))[fixed]
    v = fixed // 3
    uniq, inv = np.unique(v, return_inverse=True)
    return np.sqrt(np.bincount(inv, weights=g ** 2, minlength=len(uniq)))
