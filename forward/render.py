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


def roll_axis(sim) -> np.ndarray:
    """Unit axis (3,) of a rolled sheet: the direction most nearly perpendicular to every
    triangle normal (the smallest eigenvector of the area-weighted sum of n n^T); for a tube or a
    spiral, its axis."""
    x, t = sim.positions, sim.sheet.triangles
    n = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])     # |n| = 2 x area
    a = np.linalg.norm(n, axis=1)
    u = n / np.maximum(a, 1e-300)[:, None]
    w, v = np.linalg.eigh((u * a[:, None]).T @ u)
    return v[:, 0]


def render_roll(sim, path: str, title: str = "", size=(1300, 600), highlight=None):
    """A two-panel PNG of a rolled sheet: left the isometric view of :func:`render_deployed`,
    right the section of the sheet by the plane through its centre across :func:`roll_axis`, seen
    along the axis in parallel projection, so that the turns of the roll show as a spiral of
    lines: layers that pass through each other cross there, layers in contact run side by side.
    ``highlight``: (m,) bool, triangles drawn in black (e.g. those that intersect another, or those
    in contact), in both panels. Falls back to :func:`render_deployed` when pyvista cannot render."""
    try:
        _render_roll_pyvista(sim, path, title, size, highlight)
    except Exception:
        render_deployed(sim, path, title, size)


def _render_roll_pyvista(sim, path, title, size, highlight):
    import pyvista as pv
    pv.OFF_SCREEN = True
    x, t = sim.positions, sim.sheet.triangles
    colours = _cell_colours(sim.sheet)
    if highlight is not None:
        colours = np.where(np.asarray(highlight, bool), np.nan, colours)
    mesh = pv.PolyData(x, np.hstack([np.full((len(t), 1), 3), t]).ravel())
    mesh.cell_data["plastic"] = colours
    axis = roll_axis(sim)
    centre = x.mean(0)
    section = mesh.slice(normal=axis, origin=centre)       # lines; each keeps its triangle's colour
    p = pv.Plotter(off_screen=True, window_size=size, shape=(1, 2))
    style = dict(scalars="plastic", cmap="coolwarm", clim=[-1, 1], nan_color="black", show_scalar_bar=False)
    p.subplot(0, 0)
    p.add_mesh(mesh, **style)
    p.add_text(title, font_size=10)
    p.view_isometric()
    p.subplot(0, 1)
    if section.n_points:
        p.add_mesh(section, line_width=2, **style)
    p.add_text("section across the roll axis, through the centre", font_size=9)
    p.enable_parallel_projection()
    p.camera.focal_point = tuple(centre)
    p.camera.position = tuple(centre - 10.0 * float(np.ptp(x, axis=0).max()) * axis)
    up = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    p.camera.up = tuple(up / np.linalg.norm(up))
    y = (np.asarray(section.points) if section.n_points else x) - centre
    p.camera.parallel_scale = 1.1 * float(np.linalg.norm(y - np.outer(y @ axis, axis), axis=1).max())
    p.screenshot(path)
    p.close()


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
