import numpy as np
import pytest
import shapely
from scipy.spatial import Delaunay

from inverse.layout import _Paths, _trim_angle, ribbon_layout
from inverse.spacing import ribbon_spacing
from shellfem.errors import SelfshapeError

LX, LY, H = 120.0, 60.0, 0.5
S_PRE, SIG1, SIG2, KAPPA = 1.6, 1.1, 1.4, 0.02
LR, WR = 15.0, 1.5


def rectangle(lx=LX, ly=LY, h=H, seed=0):
    x, y = np.meshgrid(np.linspace(0, lx, int(round(lx / h)) + 1), np.linspace(0, ly, int(round(ly / h)) + 1))
    P = np.column_stack([x.ravel(), y.ravel()])
    inner = (P[:, 0] > 0) & (P[:, 0] < lx) & (P[:, 1] > 0) & (P[:, 1] < ly)
    P[inner] += np.random.default_rng(seed).uniform(-0.2 * h, 0.2 * h, (inner.sum(), 2))
    return P, Delaunay(P).simplices


def length(path):
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


@pytest.fixture(scope="module")
def rect():
    V, F = rectangle()
    m = len(F)
    c = V[F].mean(axis=1)
    args = dict(uv=V, F=F, dir1=np.tile([1.0, 0.0], (m, 1)), sigma1=np.full(m, SIG1), sigma2=np.full(m, SIG2),
                kappa1=np.where(c[:, 0] < LX / 2, KAPPA, -KAPPA), s=S_PRE)
    return args, ribbon_layout(**args)


def test_spacing_and_staggering(rect):
    _, ribbons = rect
    mu1, mu2 = ribbon_spacing(SIG1, SIG2, S_PRE, LR, WR)
    for r in ribbons:
        assert np.ptp(r.path[:, 1]) < 1e-6                      # straight rows along dir1 = x
        assert r.meta["mu2"] == pytest.approx(mu2, rel=1e-9)
        assert r.meta["mu1"] == pytest.approx(mu1, rel=1e-9)
        assert r.width_mm == WR and r.thickness_mm == 0.0
    rows = {}
    for r in ribbons:
        rows.setdefault(round(float(r.path[0, 1]), 6), []).append(r)
    ys = np.array(sorted(rows))
    np.testing.assert_allclose(np.diff(ys), mu2, rtol=1e-6)    # rows mu2 apart (Eq. 5.15)
    grids = [rows[y][0].meta["grid"] for y in ys]
    assert all(all(r.meta["grid"] == g for r in rows[y]) for y, g in zip(ys, grids))
    assert all(a != b for a, b in zip(grids[:-1], grids[1:]))   # A and B rows alternate
    phase = {"A": [], "B": []}
    for y in ys:
        full = [r for r in rows[y] if abs(length(r.path) - LR) < 1e-6]
        centres = np.sort([0.5 * (r.path[0, 0] + r.path[-1, 0]) for r in full])
        assert len(centres) >= 2
        k = np.diff(centres) / mu1                              # dash period mu1 (a dash
        np.testing.assert_allclose(k, np.rint(k), atol=1e-6)    # split at x = 60 is not full)
        assert (np.rint(k) >= 1).all() and (np.rint(k) == 1).sum() >= 1
        phase[rows[y][0].meta["grid"]].extend(centres % mu1)
    a, b = np.array(phase["A"]), np.array(phase["B"])
    circ = lambda d: (d + mu1 / 2) % mu1 - mu1 / 2             # noqa: E731  signed distance mod mu1
    assert np.abs(circ(a - a[0])).max() < 1e-6 and np.abs(circ(b - b[0])).max() < 1e-6
    assert abs(circ(b[0] - a[0])) == pytest.approx(mu1 / 2, abs=1e-6)  # brick-like half shift


def test_lengths_clipping_and_min_length(rect):
    args, ribbons = rect
    outline = shapely.box(0, 0, LX, LY)
    inner = outline.buffer(-WR / 2)
    n_full = 0
    for r in ribbons:
        L = length(r.path)
        assert 2.0 <= L <= LR + 1e-9
        printed = shapely.LineString(r.path).buffer(WR / 2)            # round caps
        assert outline.buffer(1e-9).covers(printed)
        ends = shapely.points(r.path[[0, -1]])
        clipped = np.any(shapely.distance(ends, inner.exterior) < 1e-6)
        split = np.any(np.abs(r.path[[0, -1], 0] - LX / 2) < 2 * H)
        if not (clipped or split):
            assert L == pytest.approx(LR, abs=1e-6)
            n_full += 1
    assert n_full >= 30
    # a larger min_length removes exactly the shorter pieces (the split at x = 60 always
    # leaves a piece no longer than l_r / 2 in some row)
    lengths = np.array([length(r.path) for r in ribbons])
    assert (lengths < 7.6).any()
    longer = ribbon_layout(**args, min_length=7.6)
    assert len(longer) == (lengths >= 7.6).sum()
    assert min(length(r.path) for r in longer) >= 7.6


def test_sides_follow_the_sign_of_kappa(rect):
    _, ribbons = rect
    front = [r for r in ribbons if r.side == "front"]
    back = [r for r in ribbons if r.side == "back"]
    assert front and back and len(front) + len(back) == len(ribbons)
    assert max(r.path[:, 0].max() for r in front) <= LX / 2 + 2 * H
    assert min(r.path[:, 0].min() for r in back) >= LX / 2 - 2 * H
    for r in front:
        assert (r.meta["kappa"] >= 0).all()
    for r in back:
        assert (r.meta["kappa"] <= 0).all()
    for r in ribbons:
        if np.all(np.abs(r.path[:, 0] - LX / 2) > 2 * H):
            assert r.meta["kappa_mean_abs"] == pytest.approx(KAPPA, rel=1e-9)
    # dashes spanning the sign change were split there: a front piece ends and a back piece
    # starts at the same point of the same row
    f_end = {(round(r.path[0, 1], 6), round(r.path[:, 0].max(), 6)) for r in front}
    b_start = {(round(r.path[0, 1], 6), round(r.path[:, 0].min(), 6)) for r in back}
    shared = f_end & b_start
    assert len(shared) >= 4
    assert all(abs(x - LX / 2) < 2 * H for _, x in shared)


def test_explicit_outline_contains_all_ribbons(rect):
    args, _ = rect
    circle = shapely.Point(LX / 2, LY / 2).buffer(25.0, quad_segs=64)
    ribbons = ribbon_layout(**{**args, "outline": np.asarray(circle.exterior.coords)[:-1]})
    assert len(ribbons) >= 10
    for r in ribbons:
        assert circle.buffer(1e-9).covers(shapely.LineString(r.path).buffer(WR / 2))


def test_closed_centre_lines_keep_full_dashes_across_the_seam():
    # annulus, ribbons along circles: every centre line is a closed loop
    P, F = rectangle(60.0, 60.0, 0.6, seed=1)
    P = P - 30.0
    c = P[F].mean(axis=1)
    rc = np.hypot(*c.T)
    keep = (rc > 10.0) & (rc < 28.0)
    F = F[keep]
    used = np.unique(F)
    remap = np.full(len(P), -1)
    remap[used] = np.arange(len(used))
    P, F = P[used], remap[F]
    c = P[F].mean(axis=1)
    m = len(F)
    dir1 = np.column_stack([-c[:, 1], c[:, 0]])
    ribbons = ribbon_layout(P, F, dir1, np.full(m, 1.05), np.full(m, 1.2), np.full(m, 0.01), S_PRE)
    on_loops = [r for r in ribbons if np.hypot(*r.path.T).min() > 11.5 and np.hypot(*r.path.T).max() < 26.5]
    assert len(on_loops) >= 15
    for r in on_loops:
        rad = np.hypot(*r.path.T)
        assert np.ptp(rad) < 0.05
        assert length(r.path) == pytest.approx(LR, abs=1e-6)
        assert r.side == "front"


def test_trim_where_the_centre_line_turns_away_from_dir1():
    a = np.deg2rad(40.0)
    pts = np.array([[0.0, 0.0], [5.0, 0.0], [5.0 + 5 * np.cos(a), 5 * np.sin(a)],
                    [15.0 + 5 * np.cos(a), 5 * np.sin(a)]])
    paths = _Paths(pts, np.zeros((4, 1)), np.array([0, 0, 0, -1]), np.array([0, 4]))
    out = _trim_angle(paths, np.array([[1.0, 0.0]]), 25.0)
    assert out.n == 2
    np.testing.assert_allclose(out.lengths(), [5.0, 10.0])
    assert _trim_angle(paths, np.array([[1.0, 0.0]]), 45.0).n == 1


def test_bad_input_is_an_error(rect):
    args, _ = rect
    s2 = args["sigma2"].copy()
    s2[7] = 1.6
    with pytest.raises(SelfshapeError, match=r"sigma2\[7\]"):
        ribbon_layout(**{**args, "sigma2": s2})
    with pytest.raises(SelfshapeError, match="dir1"):
        ribbon_layout(**{**args, "dir1": args["dir1"][:5]})
    k = args["kappa1"].copy()
    k[3] = np.nan
    with pytest.raises(SelfshapeError, match=r"kappa1\[3\]"):
        ribbon_layout(**{**args, "kappa1": k})
