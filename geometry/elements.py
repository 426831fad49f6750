"""Records shared by pattern parsing, G-code reading and meshing (printed-state mm)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PrintedElement:
    """One printed element: a planar shape with a plastic thickness on one fabric face.

    geometry: shapely Polygon or MultiPolygon in printed-state mm.
    thickness_mm: plastic thickness (> 0). side: "front" (+z) or "back" (-z).
    kind: "region", "ribbon", "star" or "gcode". label: where it came from, for
    error messages and provenance (e.g. "region[2]", "stars (3, -1)", "print.gcode path 17").
    centrelines: for stars and ribbons, the centre lines ((k, 2) polylines, mm; a star's
    three arms from its centre, unclipped) and width_mm their printed width: what the rods
    model ([solver] model = "rods", geometry.centrelines) puts its rods on; None otherwise.
    """
    geometry: object
    thickness_mm: float
    side: str = "front"
    kind: str = "region"
    label: str = ""
    centrelines: list | None = None
    width_mm: float | None = None


@dataclass
class Support:
    """Boundary condition after release: nearest mesh vertices to ``points`` are held.

    fix: "z" (on the ground plane z = 0, free to slide) or "xyz" (held at
    ``position`` or, when None, at the relaxed-fabric position (x/sx, y/sy, 0)). With a ground
    ([ground]) "z" and relaxed "xyz" supports stand on it: at its height plus the barrier's band
    (forward.simulate.support_plane).
    boundary: hold every mesh vertex on the fabric's outline (``points`` empty), as the
    seed's Fig. 3.8 sheets "fixed at the boundary".
    """
    points: np.ndarray            # (k, 2) printed-state mm
    fix: str = "z"
    position: np.ndarray | None = None  # (k, 3) mm, deployed frame
    label: str = ""
    boundary: bool = False


@dataclass
class Ribbon:
    """A printed path of given width (inverse design output, G-code writer input).

    path: (k, 2) centre line in printed-state mm. width_mm, thickness_mm: plastic
    bead width and stacked thickness. side: "front" or "back".
    """
    path: np.ndarray
    width_mm: float = 1.5
    thickness_mm: float = 0.4
    side: str = "front"
    label: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def length_mm(self) -> float:
        """Length of the centre line (printed mm)."""
        return float(np.linalg.norm(np.diff(np.asarray(self.path, float), axis=0), axis=1).sum())
