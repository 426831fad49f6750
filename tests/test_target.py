import os
import pathlib

import numpy as np
import pytest

from geometry.target import (check_disk, cylinder_patch, levels_for_faces, load_target, plane_patch,
                             read_mesh, refine, sphere_cap)
from geometry.meshops import face_areas
from shellfem.errors import SelfshapeError

TARGETS = sorted((pathlib.Path(__file__).resolve().parents[1] / "meshes" / "targets").glob("*.obj"))
assert len(TARGETS) == 4, "meshes/targets must hold the four shipped targets"


def write_obj(path, V, F, extra=""):
    with open(path, "w") as fh:
        fh.write(extra)
        for v in V:
            fh.write("v %.17g %.17g %.17g\n" % tuple(v))
        for f in F:
            fh.write("f " + " ".join(str(i + 1) for i in f) + "\n")
    return str(path)


@pytest.mark.parametrize("path", TARGETS, ids=lambda p: p.stem)
def test_shipped_targets_load_scaled_and_centred(path):
    V, F = load_target(path, diagonal_mm=110.0)
    lo, hi = V.min(axis=0), V.max(axis=0)
    assert np.linalg.norm(hi - lo) == pytest.approx(110.0, rel=1e-12)
    np.testing.assert_allclose(0.5 * (lo + hi), 0.0, atol=1e-9)
    assert len(np.unique(F)) == len(V)          # no unreferenced vertices


def test_keep_units_when_diagonal_none(tmp_path):
    V, F = plane_patch(6.0, 8.0, 3, 4)
    V = V + [100.0, 0, 0]
    W, G = load_target(write_obj(tmp_path / "p.obj", V, F), diagonal_mm=None)
    assert np.linalg.norm(W.max(0) - W.min(0)) == pytest.approx(10.0)
    np.testing.assert_allclose(0.5 * (W.max(0) + W.min(0)), 0.0, atol=1e-12)


def test_obj_reader_polygons_slashes_negative_indices_unreferenced(tmp_path):
    text = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nv 9 9 9\nvt 0 0\nvn 0 0 1\n"
            "f 1/1/1 2/1/1 3/1/1 4/1/1\n"      # quad with texture/normal indices
            "f -6//1 -3//1 -2//1 -5//1\n")      # negative indices: 2 5 6 3
    p = tmp_path / "quads.obj"
    p.write_text(text)
    V, F = read_mesh(str(p))
    assert F.shape == (4, 3)
    W, G = load_target(str(p), diagonal_mm=None)
    assert len(W) == 6                             # vertex 7 dropped
    assert np.isclose(np.abs(np.cross(W[G[:, 1]] - W[G[:, 0]], W[G[:, 2]] - W[G[:, 0]])).sum() / 2, 2.0)


def test_ply_and_stl_through_meshio(tmp_path):
    import meshio

    V, F = plane_patch(10.0, 10.0, 4, 4)
    meshio.write(str(tmp_path / "p.ply"), meshio.Mesh(V, [("triangle", F)]))
    W, G = load_target(str(tmp_path / "p.ply"), diagonal_mm=None)
    assert len(G) == len(F) and len(W) == len(V)
    # STL: every triangle stored with its own corners, must be welded into one disk
    meshio.write(str(tmp_path / "p.stl"), meshio.Mesh(V[F].reshape(-1, 3), [("triangle", np.arange(3 * len(F)).reshape(-1, 3))]))
    W, G = load_target(str(tmp_path / "p.stl"), diagonal_mm=None)
    assert len(G) == len(F) and len(W) == len(V)


def test_synthetic_targets_are_disks():
    for V, F in (sphere_cap(), cylinder_patch(), plane_patch()):
        W, G = check_disk(V, F)
        assert len(W) - len({tuple(e) for e in np.sort(np.r_[G[:, :2], G[:, 1:], G[:, ::2]], 1)}) + len(G) == 1


def _moebius(n: int = 24):
    """A Moebius band of n quads (two triangles each): one piece, one boundary, not orientable."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    V = []
    for s in (-1.0, 1.0):
        V.append(np.c_[(10 + s * np.cos(t / 2)) * np.cos(t), (10 + s * np.cos(t / 2)) * np.sin(t), s * np.sin(t / 2)])
    V = np.r_[V[0], V[1]]                          # vertex i: side -1 at station i; n + i: side +1
    F = []
    for i in range(n):
        a, b = i, n + i
        if i < n - 1:
            c, d = i + 1, n + i + 1
        else:                                      # the half twist: side -1 meets side +1
            c, d = n, 0
        F += [[a, c, b], [b, c, d]]
    return V, np.array(F)


def test_orientation_is_repaired_keeping_the_majority():
    """Faces oriented against their neighbours (an exporter's flips) are turned to agree with
    the majority, so the front stays the front; the repair is named."""
    V, F = plane_patch(4.0, 4.0, 3, 3)
    Fo = F.copy()
    Fo[[0, 5]] = Fo[[0, 5], ::-1]
    repairs = []
    W, G = check_disk(V, Fo, "x.obj", repairs)
    np.testing.assert_array_equal(np.sort(G, axis=1), np.sort(F, axis=1))
    assert np.all(np.any([np.all(np.roll(G, k, axis=1) == F, axis=1) for k in range(3)], axis=0))
    assert repairs == ["2 of 18 faces turned to agree with their neighbours' orientation"]
    repairs = []
    W, G = check_disk(V, Fo[:, ::-1], "x.obj", repairs)        # the majority flipped: the other front
    assert np.all(np.any([np.all(np.roll(G, k, axis=1) == F[:, ::-1], axis=1) for k in range(3)], axis=0))
    repairs = []
    check_disk(V, F, "x.obj", repairs)
    assert repairs == []


def test_a_polygon_soup_is_welded_into_one_disk(tmp_path):
    """An OBJ whose faces each carry their own corners (as some exporters write) is welded at
    identical positions; two separate patches stay two pieces (welding never joins them)."""
    V, F = plane_patch(4.0, 4.0, 3, 3)
    V[:, 2] = 0.1 * V[:, 0] ** 2
    soup = write_obj(tmp_path / "soup.obj", V[F].reshape(-1, 3), np.arange(3 * len(F)).reshape(-1, 3))
    repairs = []
    W, G = check_disk(*read_mesh(soup), "soup.obj", repairs)
    assert len(W) == len(V) and len(G) == len(F)
    np.testing.assert_allclose(np.sort(face_areas(W, G)), np.sort(face_areas(V, F)))
    assert repairs[0].startswith(f"{3 * len(F) - len(V)} vertices at the positions of others welded")
    two = np.r_[V, V + [10, 0, 0]]
    with pytest.raises(SelfshapeError, match="2 connected components"):
        check_disk(two[np.r_[F, F + len(V)]].reshape(-1, 3), np.arange(6 * len(F)).reshape(-1, 3), "two.obj")


def _bad_cases():
    V, F = plane_patch(4.0, 4.0, 2, 2)           # 9 vertices, 8 faces
    cases = {}
    # a third face on an interior edge
    E = (F[0, 1], F[0, 2])                          # an interior edge of face 0
    cases["non-manifold edge"] = (np.r_[V, [[0, 0, 5.0]]], np.r_[F, [[E[1], E[0], len(V)]]])
    # closed tetrahedron
    cases["closed surface"] = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                               np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]))
    # two separate patches
    cases["2 connected components"] = (np.r_[V, V + [10, 0, 0]], np.r_[F, F + len(V)])
    cases["degenerate"] = (V, np.r_[F, [[0, 0, 1]]])
    Vz = np.r_[V, [0.5 * (V[0] + V[3])]]          # collinear with vertices 0 and 3
    cases["zero area"] = (Vz, np.r_[F[:1], [[0, len(V), 3]]])
    cases["not orientable"] = _moebius()
    # two fans sharing one vertex (bow tie)
    bow = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0.0]])
    cases["non-manifold vertex"] = (bow, np.array([[0, 1, 2], [0, 3, 4]]))
    # a handle: a torus with one face cut out (one boundary loop, genus 1)
    cases["genus 1"] = _torus_with_a_hole()
    return cases


def _square_ring():
    """A square ring: a 3 x 3 cell grid without its middle cell (2 boundary loops)."""
    A, G = plane_patch(6.0, 6.0, 3, 3)
    centre = {5, 6, 9, 10}.__contains__            # the middle cell of the 4 x 4 vertex grid
    return A, G[~np.array([all(centre(i) for i in f[:2]) and centre(f[2]) for f in G])]


def _torus_with_a_hole(n=12, m=8):
    u, v = np.meshgrid(2 * np.pi * np.arange(n) / n, 2 * np.pi * np.arange(m) / m, indexing="ij")
    V = np.column_stack([((20 + 6 * np.cos(v)) * np.cos(u)).ravel(), ((20 + 6 * np.cos(v)) * np.sin(u)).ravel(),
                         (6 * np.sin(v)).ravel()])
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % n) * m + j
    c, d = ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    F = np.r_[np.column_stack([a.ravel(), b.ravel(), c.ravel()]), np.column_stack([a.ravel(), c.ravel(), d.ravel()])]
    return V, F[1:]


@pytest.mark.parametrize("problem", list(_bad_cases()))
def test_bad_input_one_line_naming_file_and_problem(tmp_path, problem):
    V, F = _bad_cases()[problem]
    path = write_obj(tmp_path / "bad.obj", V, F)
    with pytest.raises(SelfshapeError) as err:
        load_target(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("bad.obj:")
    key = {"closed surface": "closed", "degenerate": "degenerate", "zero area": "zero area",
           "non-manifold edge": "non-manifold edge", "non-manifold vertex": "non-manifold vertex",
           "not orientable": "not orientable",
           "2 connected components": "2 connected components",
           "genus 1": "Euler characteristic -1 with 1 boundary loop (genus 1: 1 handle); a disk has 1"}[problem]
    assert key in msg


def test_a_disk_with_holes_is_a_target_and_a_handle_is_not(tmp_path):
    V, F = _square_ring()
    V[:, 2] = 0.02 * V[:, 0] ** 2
    W, G = load_target(write_obj(tmp_path / "ring.obj", V, F), diagonal_mm=None)
    assert len(G) == len(F) and np.allclose(W, V - 0.5 * (V.min(0) + V.max(0)))
    with pytest.raises(SelfshapeError, match="ring.obj: 2 boundary loops .1 hole.; a disk has one: fill the hole or"):
        check_disk(V, F, "ring.obj")
    # a ring with a handle: genus 1 and 2 boundary loops
    T, H = _torus_with_a_hole()
    with pytest.raises(SelfshapeError, match=r"Euler characteristic -2 with 2 boundary loops \(genus 1: 1 handle\); "
                                             r"a disk with holes has 0: cut each handle open"):
        check_disk(T, np.r_[H[:40], H[41:]], "t.obj", holes=True)


def test_missing_file_and_nan(tmp_path):
    with pytest.raises(SelfshapeError, match="nope.obj: file not found"):
        load_target(str(tmp_path / "nope.obj"))
    V, F = plane_patch(2.0, 2.0, 1, 1)
    V[1, 2] = np.nan
    with pytest.raises(SelfshapeError, match="non-finite"):
        check_disk(V, F, "x.obj")


@pytest.mark.parametrize("diagonal", [1e300, 1e6, 5000.5, 9.99, 1e-6, 0.0, -1.0, float("nan"), float("inf")])
def test_the_diagonal_is_in_its_range(diagonal):
    """--diagonal / diagonal_mm scales the target before anything runs: 1e300 overflowed to
    "zero total area", 1e-6 to "no ribbons", 1e5 flattened for minutes (issue 19)."""
    with pytest.raises(SelfshapeError, match=r"target diagonal \(--diagonal, diagonal_mm\) must be"):
        load_target(TARGETS[0], diagonal_mm=diagonal)
    V, _ = load_target(TARGETS[0], diagonal_mm=5000.0)
    assert np.linalg.norm(np.ptp(V, axis=0)) == pytest.approx(5000.0)


def test_obj_byte_order_mark_tabs_and_devices(tmp_path):
    """A BOM before the first record, tab-separated records (both valid OBJ from Windows
    tools) read as without; a path that is a pipe is refused unread (issue 19)."""
    V, F = plane_patch(4.0, 4.0, 2, 2)
    V[:, 2] = 0.1 * V[:, 0] ** 2
    plain = write_obj(tmp_path / "plain.obj", V, F)
    text = open(plain).read()
    (tmp_path / "bom.obj").write_bytes(b"\xef\xbb\xbf" + text.replace("v ", "v\t").encode())
    for a, b in zip(read_mesh(plain), read_mesh(str(tmp_path / "bom.obj"))):
        np.testing.assert_array_equal(a, b)
    os.mkfifo(tmp_path / "pipe.obj")
    with pytest.raises(SelfshapeError, match="pipe.obj: is a named pipe"):
        read_mesh(str(tmp_path / "pipe.obj"))


def test_refine_counts_and_midpoint_keeps_shape():
    V, F = cylinder_patch(n_arc=6, n_len=5)
    for method in ("loop", "midpoint"):
        W, G = refine(V, F, 2, method)
        assert len(G) == 16 * len(F)
        check_disk(W, G)
    W, G = refine(V, F, 1, "midpoint")
    np.testing.assert_allclose(W[: len(V)], V)    # original vertices kept, new ones at midpoints
    assert levels_for_faces(2112, 100_000) == 3 and levels_for_faces(812, 100_000) == 3
    assert levels_for_faces(2752, 100_000) == 2
    with pytest.raises(SelfshapeError):
        refine(V, F, 1, "cubic")
