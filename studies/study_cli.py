"""What the verification studies share on the command line: the options --quick, --out (JSON
directory) and --figures (PNG directory), and writing a study's JSON record while printing its
one-line summary. Imported by the scripts beside it (studies/ is on sys.path when one of them
is run as ``python studies/<name>.py``)."""
from __future__ import annotations

import argparse
import json
import os


def study_arguments(doc: str, quick_help: str, argv=None) -> argparse.Namespace:
    """Parse --quick (``quick_help``), --out (default out/validation) and --figures (default
    docs/validation); the description is the first line of ``doc``."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--out", default="out/validation")
    ap.add_argument("--figures", default="docs/validation")
    return ap.parse_args(argv)


def write_result(out_dir: str, name: str, record: dict, summary: dict) -> None:
    """OUT/<name>.json = ``record`` (indented), and ``summary`` printed as one JSON line."""
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, f"{name}.json"), "w") as fh:
        json.dump(record, fh, indent=2)
    print(json.dumps(summary))


TARGETS = os.path.join("meshes", "targets", "*.obj")     # relative to the repository root


def target_paths(names=()) -> list:
    """The shipped target meshes (meshes/targets/*.obj), sorted, restricted to ``names`` (file
    stems) if given."""
    import glob
    paths = sorted(glob.glob(TARGETS))
    return [p for p in paths if not names or os.path.splitext(os.path.basename(p))[0] in names]


def _wave(length_mm: float = 110.0, width_mm: float = 70.0, amplitude_mm: float = 8.0, nx: int = 55, ny: int = 35):
    """A developable S-wave z = A sin(2 pi x / L) (mm): one full period, so its curvature along x
    changes sign (ribbons on both sides), and it is flat across."""
    import numpy as np

    from geometry.target import plane_patch
    V, F = plane_patch(length_mm, width_mm, nx, ny)
    V[:, 2] = amplitude_mm * np.sin(2 * np.pi * V[:, 0] / length_mm)
    return V, F


def _vault():
    """A barrel vault: a cylinder patch of radius 70 mm, 80 mm of arc by 100 mm along the axis."""
    from geometry.target import cylinder_patch
    return cylinder_patch(radius=70.0, arc_mm=80.0, length_mm=100.0, n_arc=32, n_len=40)


def _hypar(size_mm: float = 100.0, c_mm: float = 250.0, n: int = 40):
    """A gentle hyperbolic paraboloid z = x y / c over a size x size square (mm): negative
    Gaussian curvature everywhere, principal curvatures ~ 1 / c at the centre (0.004 1/mm)."""
    from geometry.target import plane_patch
    V, F = plane_patch(size_mm, size_mm, n, n)
    V[:, 2] = V[:, 0] * V[:, 1] / c_mm
    return V, F


def _ellipsoid_cap(length_mm: float = 120.0, width_mm: float = 70.0, height_mm: float = 15.0):
    """A shallow cap of the ellipsoid with semi-axes 90 x 60 x 15 mm over a 120 x 70 mm
    rectangle (mm): positive Gaussian curvature, curvatures 0.002-0.004 1/mm at the top."""
    import numpy as np

    from geometry.target import plane_patch
    V, F = plane_patch(length_mm, width_mm, 50, 30)
    V[:, 2] = height_mm * np.sqrt(np.clip(1 - (V[:, 0] / 90.0) ** 2 - (V[:, 1] / 60.0) ** 2, 0.0, None))
    return V, F


def _bump(size_mm: float = 110.0, height_mm: float = 14.0, width_mm: float = 30.0, n: int = 55):
    """A Gaussian bump z = h exp(-r^2 / w^2) over a size x size square (mm): a dome (K = 4 h^2 / w^4
    at the top) ringed by saddles where it meets the nearly flat rim, so K changes sign."""
    import numpy as np

    from geometry.target import plane_patch
    V, F = plane_patch(size_mm, size_mm, n, n)
    V[:, 2] = height_mm * np.exp(-(V[:, 0] ** 2 + V[:, 1] ** 2) / width_mm ** 2)
    return V, F


def _cone(half_angle_deg: float = 30.0, slant_mm: tuple = (40.0, 120.0), turn_rad: float = 1.4, n: int = 40):
    """A developable cone segment (mm): slant distance 40-120 mm from the apex, 1.4 rad around the
    axis, half angle 30 degrees; K = 0, and the curvature across the generators falls as 1/distance."""
    import numpy as np

    from geometry.target import plane_patch
    V, F = plane_patch(1.0, 1.0, n, n)
    s = slant_mm[0] + (V[:, 0] + 0.5) * (slant_mm[1] - slant_mm[0])
    th = V[:, 1] * turn_rad
    a = np.radians(half_angle_deg)
    return np.column_stack([s * np.sin(a) * np.cos(th), s * np.sin(a) * np.sin(th), -s * np.cos(a)]), F


#: analytic targets outside meshes/ (the classes the shipped scans do not cover), by name
ANALYTIC_TARGETS = {"vault": _vault, "wave": _wave, "hypar": _hypar, "ellipsoid": _ellipsoid_cap, "bump": _bump,
                    "cone": _cone}


def analytic_target(name: str, out_dir: str) -> str:
    """Write the analytic target ``name`` (a key of ANALYTIC_TARGETS) as OUT_DIR/<name>.obj and
    return its path."""
    import meshio
    V, F = ANALYTIC_TARGETS[name]()
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"{name}.obj")
    meshio.write(path, meshio.Mesh(V, [("triangle", F)]))
    return path
