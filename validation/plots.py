"""Small plotting helpers shared by the calibration and validation tools.

matplotlib with the Agg backend (no display needed); one PNG per figure. A figure is
described by data series, so callers never touch matplotlib state:

    plot_series("fit.png", title="...", xlabel="...", ylabel="...",
                points=[Series(x, y, "data")], lines=[Series(x, y_fit, "fit")])
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


@dataclass
class Series:
    """One curve or point cloud: x, y (same length), legend label, optional y error bars."""
    x: np.ndarray
    y: np.ndarray
    label: str = ""
    yerr: np.ndarray | None = None
    style: str = ""          # matplotlib format string, e.g. "--" or "o"; "" = default
    alpha: float = 1.0


def new_axes(title: str = "", xlabel: str = "", ylabel: str = "", size=(6.0, 4.2)):
    """A new (figure, axes) pair with a grid and labels."""
    fig, ax = plt.subplots(figsize=size)
    fig.subplots_adjust(left=0.13, right=0.97, bottom=0.12, top=0.92)  # fixed: layout engines double the draw time
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    return fig, ax


def save_figure(fig, path: str, dpi: int = 120) -> str:
    """Write fig as PNG to path (directories created; atomically, shellfem.outfiles.write_atomic)
    and close it. Returns path."""
    from shellfem.outfiles import write_atomic
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    try:
        write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=dpi))
    finally:
        plt.close(fig)
    return path


def draw_series(ax, points=(), lines=()):
    """Scatter the points series (markers) and draw the lines series (curves) on ax."""
    for s in points:
        fmt = s.style or "o"
        if s.yerr is not None:
            ax.errorbar(s.x, s.y, yerr=s.yerr, fmt=fmt, ms=3, capsize=2, label=s.label or None, alpha=s.alpha)
        else:
            ax.plot(s.x, s.y, fmt, ms=2.5, label=s.label or None, alpha=s.alpha)
    for s in lines:
        ax.plot(s.x, s.y, s.style or "-", lw=1.6, label=s.label or None, alpha=s.alpha)
    if any(s.label for s in (*points, *lines)):
        ax.legend(fontsize=8, loc="upper left")  # "best" scans every point: slow


def plot_series(path: str, *, title: str = "", xlabel: str = "", ylabel: str = "",
                points=(), lines=(), logx: bool = False, logy: bool = False, note: str = "") -> str:
    """One PNG with scatter series and line series; optional log axes and a text note."""
    fig, ax = new_axes(title, xlabel, ylabel)
    draw_series(ax, points, lines)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    if note:
        ax.text(0.02, 0.98, note, transform=ax.transAxes, va="top", ha="left", fontsize=8,
                bbox=dict(boxstyle="round", fc="white", alpha=0.8))
    return save_figure(fig, path)
