"""Pictures of deployed shapes (PNG), off-screen.

pyvista renders through EGL when ``libegl1`` is installed (no X server); if VTK cannot open
an off-screen context the picture falls back to matplotlib's 3D triangle plot.
"""
from __future__ import annotations

import os

import numpy as np

# must be set before vtk is imported: EGL off-screen rendering, no X server needed
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _cell_colours(sheet):
    side = sheet.side
    return np.where(side == 1, 1.0, np.where(side == -1, -1.0, np.where(side == 2, 0.5, 0.0)))


def render_deployed(sim, path: str, title: str = "", size=(900, 700), lines=None):
    """Write a PNG of the deployed surface, printed regions coloured by side; ``lines``: (k, 2)
    vertex pairs drawn as red lines on it (the rods model's rods, on its bare fabric)."""
    try:
        _render_pyvista(sim, path, title, size, lines)
    except Exception:
        _render_matplotlib(sim, path, title, size, lines)


def _render_pyvista(sim, path, title, size, lines=None):
    import pyvista as pv
    pv.OFF_SCREEN = True
    x = sim.positions
    t = sim.sheet.triangles
    faces = np.hstack([np.full((len(t), 1), 3), t]).ravel()
    mesh = pv.PolyData(x, faces)
    mesh.cell_data["plastic"] = _cell_colours(sim.sheet)
    p = pv.Plotter(off_screen=True, window_size=size)
    p.add_mesh(mesh, scalars="plastic", cmap="coolwarm", clim=[-1, 1], show_edges=False, smooth_shading=False,
               show_scalar_bar=False)
    if lines is not None and len(lines):
        e = np.asarray(lines, dtype=np.int64)
        p.add_mesh(pv.PolyData(x, lines=np.hstack([np.full((len(e), 1), 2), e]).ravel()), color="#b40426",
                   line_width=4, render_lines_as_tubes=True)
    p.add_text(title, font_size=10)
    p.view_isometric()
    p.screenshot(path)
    p.close()


def _render_matplotlib(sim, path, title, size, lines=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    x = sim.positions
    fig = plt.figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    ax = fig.add_subplot(111, projection="3d")
    c = _cell_colours(sim.sheet)
    surf = ax.plot_trisurf(x[:, 0], x[:, 1], x[:, 2], triangles=sim.sheet.triangles, cmap="coolwarm",
                           linewidth=0, antialiased=False)
    surf.set_array(c)
    surf.set_clim(-1, 1)
    if lines is not None and len(lines):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection
        ax.add_collection3d(Line3DCollection(x[np.asarray(lines, dtype=np.int64)], colors="#b40426", linewidths=2))
    span = (x.max(0) - x.min(0)).max() / 2
    mid = (x.max(0) + x.min(0)) / 2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[1] - span, mid[1] + span)
    ax.set_zlim(mid[2] - span, mid[2] + span)
    ax.set_title(title)
    fig.savefig(path)
    plt.close(fig)
