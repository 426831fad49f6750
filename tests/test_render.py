"""forward.render's roll pictures: the roll axis of an analytic cylinder and spiral, and the
two-panel picture written as a PNG of the asked size."""
from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest

from forward.render import render_roll, roll_axis


def _grid(nu, nv):
    """(nu*nv, 2) grid indices and its (2 (nu-1)(nv-1), 3) triangles."""
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    idx = (i * nv + j)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return np.stack([i.ravel(), j.ravel()], 1).astype(float), tri


def _rolled(axis, turns=1.0, r0=5.0, pitch=0.0, length=30.0, nu=60, nv=12):
    """A sheet rolled about ``axis`` through the origin: angle theta over ``turns`` turns, radius
    r0 + pitch theta / (2 pi), length along the axis; positions (n, 3) and triangles."""
    uv, tri = _grid(nu, nv)
    theta = 2 * np.pi * turns * uv[:, 0] / (nu - 1)
    r = r0 + pitch * theta / (2 * np.pi)
    s = length * (uv[:, 1] / (nv - 1) - 0.5)
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    x = (r * np.cos(theta))[:, None] * e1 + (r * np.sin(theta))[:, None] * e2 + s[:, None] * a
    return x, tri


def _sim(x, tri, side=None):
    sheet = SimpleNamespace(triangles=tri, points=x[:, :2], n_triangles=len(tri),
                            side=np.zeros(len(tri), int) if side is None else side)
    return SimpleNamespace(positions=x, sheet=sheet)


@pytest.mark.parametrize("axis", [(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (1.0, 2.0, -0.5)])
@pytest.mark.parametrize("turns,pitch", [(1.0, 0.0), (0.6, 0.0), (2.5, 1.2)])
def test_roll_axis_of_a_cylinder_and_a_spiral_is_their_axis(axis, turns, pitch):
    x, tri = _rolled(axis, turns, pitch=pitch)
    a = np.asarray(axis) / np.linalg.norm(axis)
    got = roll_axis(_sim(x, tri))
    assert abs(np.linalg.norm(got) - 1.0) < 1e-12
    assert abs(abs(got @ a) - 1.0) < 1e-9          # the axis up to its sign


def test_roll_axis_of_a_flat_sheet_lies_in_its_plane():
    uv, tri = _grid(10, 8)
    x = np.column_stack([uv, np.zeros(len(uv))])
    got = roll_axis(_sim(x, tri))
    assert abs(got[2]) < 1e-12                     # perpendicular to the normal (0, 0, 1)


def test_render_roll_writes_a_two_panel_png(tmp_path):
    pytest.importorskip("pyvista")
    pytest.importorskip("PIL")
    from PIL import Image
    x, tri = _rolled((0, 0, 1), turns=2.0, pitch=1.5)
    side = np.where(np.arange(len(tri)) % 3 == 0, 1, 0)
    hl = np.zeros(len(tri), bool)
    hl[:10] = True
    path = os.path.join(tmp_path, "roll.png")
    render_roll(_sim(x, tri, side), path, title="spiral", size=(640, 300), highlight=hl)
    assert os.path.getsize(path) > 1000
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape[:2] == (300, 640)
    for half in (img[:, :320], img[:, 320:]):           # the isometric view and the section: both drawn
        background = half[0, -1]
        assert (np.abs(half.astype(int) - background).sum(axis=2) > 60).mean() > 0.002
