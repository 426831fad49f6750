"""Pictures of a design (PNG, off-screen matplotlib): pattern.png (the printed pattern to scale)
and verify.png (the simulated deployment against the target)."""
from __future__ import annotations

import numpy as np

from inverse.record import Design


def plot_pattern(d: Design, path: str, title: str = ""):
    """pattern.png: outline and ribbons to scale (front red, back blue, darker = thicker)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import to_rgb

    ext = d.outline.max(0) - d.outline.min(0)
    fig, ax = plt.subplots(figsize=(8, 8 * max(ext[1], 1) / max(ext[0], 1) + 0.6))
    ax.fill(*d.outline.T, facecolor="0.94", edgecolor="0.3", lw=0.8)
    for h in d.holes:
        ax.fill(*np.asarray(h).T, facecolor="white", edgecolor="0.3", lw=0.8)
    th = np.array([r.thickness_mm for r in d.ribbons])
    lo = th.min()
    polys, cols = [], []
    for r, t in zip(d.ribbons, th):
        g = shapely.LineString(r.path).buffer(r.width_mm / 2, cap_style="flat", join_style="mitre")
        for part in getattr(g, "geoms", [g]):
            if part.geom_type == "Polygon" and not part.is_empty:
                polys.append(np.asarray(part.exterior.coords))
                base = np.array(to_rgb("tab:red" if r.side == "front" else "tab:blue"))
                shade = 0.3 + 0.7 * t / th.max()
                cols.append(1 - shade * (1 - base))
    ax.add_collection(PolyCollection(polys, facecolors=cols, edgecolors="none"))
    ax.set_aspect("equal")
    ax.autoscale_view()
    n_f = sum(r.side == "front" for r in d.ribbons)
    ax.set_title(f"{title}  {n_f} front (red), {len(d.ribbons) - n_f} back (blue); "
                 f"thickness {lo:.1f}-{th.max():.1f} mm (darker = thicker)", fontsize=9)
    ax.set_xlabel("x (printed mm)")
    ax.set_ylabel("y (printed mm)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _draw_state(fig, row, rows, d: Design, X, T, pct, vmax):
    """One row of two views: the registered sheet X (n, 3) mm coloured by its distance to the
    target pct (n,) % (colour scale 0..vmax), the target as a grey wireframe."""
    col = pct[T].mean(axis=1)
    for k, (elev, azim) in enumerate(((25, -60), (70, 30))):
        ax = fig.add_subplot(rows, 2, 2 * row + k + 1, projection="3d")
        surf = ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=T, cmap="viridis", linewidth=0)
        surf.set_array(col)
        surf.set_clim(0, max(float(vmax), 1e-9))
        ax.plot_trisurf(d.V_input[:, 0], d.V_input[:, 1], d.V_input[:, 2], triangles=d.F_input,
                        color=(0.5, 0.5, 0.5, 0.08), edgecolor=(0.3, 0.3, 0.3, 0.15), linewidth=0.2)
        ax.view_init(elev, azim)
        ax.set_box_aspect(np.ptp(np.vstack([X, d.V_input]), axis=0))
        ax.set_axis_off()
    return surf


def plot_verify(d: Design, X, T, pct, path: str):
    """verify.png: the registered simulated surface coloured by distance to the target (%),
    the target as a grey wireframe, two views."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, 5))
    surf = _draw_state(fig, 0, 1, d, X, T, pct, pct.max())
    fig.colorbar(surf, ax=fig.axes, shrink=0.6, label="distance to target (% of bbox diagonal)")
    fig.suptitle(f"simulated (colour) vs target (grey): mean {pct.mean():.2f} %, max {pct.max():.2f} %")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_before_after(d: Design, states, path: str, title: str = ""):
    """refine.png: the open-loop and the refined deployment one above the other, each coloured by
    its distance to the target (% of the bounding-box diagonal, one colour scale for both) with
    the target as a grey wireframe, two views each. ``states``: [(label, X registered (n, 3) mm,
    triangles (m, 3), deployed -> target % (n,), target -> deployed % (k,))] in drawing order."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vmax = max(float(pct.max()) for _, _, _, pct, _ in states)
    top, row_h = 0.4, 4.6                                   # inches: title band, one state's row
    height = top + row_h * len(states)
    fig = plt.figure(figsize=(11, height))
    surf = None
    for i, (label, X, T, pct, back) in enumerate(states):
        surf = _draw_state(fig, i, len(states), d, X, T, pct, vmax)
        fig.text(0.02, 1 - (top + row_h * i + 0.1) / height,          # the label at the top of its row
                 f"{label}\ndeployed -> target mean {pct.mean():.2f} %, max {pct.max():.2f} %; "
                 f"target -> deployed mean {back.mean():.2f} %, max {back.max():.2f} %", fontsize=9, va="top")
    fig.colorbar(surf, ax=fig.axes, shrink=0.5, label="distance to target (% of bbox diagonal)")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
