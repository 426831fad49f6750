"""The record of a design: everything the inverse pipeline computed for one target (mm),
read by the writers (pattern, report, VTU, pictures) and the verification."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Design:
    """Everything the pipeline computed (mm). V, F: scaled and refined target; V_input, F_input:
    the scaled input before refinement (the target, always); V_goal: the target refined like V
    when V is a proxy surface (a surface within the stretch bounds designed for instead); curvature, field: geometry.curvature / fields records;
    flat: geometry.flattening.FlatResult; kappa1 (m,): signed target normal curvature along the
    ribbon direction (> 0: front); outline (k, 2): flattened outer boundary polygon; holes: the
    flattened hole rims (a list of (k, 2) polygons; empty for a disk target); ribbons:
    geometry.elements.Ribbon list with thickness_mm and side; thickness_info: clamp counts per
    side; times: seconds per stage."""
    V: np.ndarray
    F: np.ndarray
    V_input: np.ndarray
    F_input: np.ndarray
    curvature: object
    field: object
    flat: object
    kappa1: np.ndarray
    outline: np.ndarray
    ribbons: list
    stretch: float
    bounds: tuple
    refine_levels: int
    layout_levels: int = 0
    lam: float = 0.0
    stop: str = "mean"
    thickness_info: dict = field(default_factory=dict)
    law_source: str = ""
    law_plastic_mpa: float | None = None     # the plastic modulus the law holds for (MPa), if it says
    times: dict = field(default_factory=dict)
    cpu_times: dict = field(default_factory=dict)
    coarse_iterations: int = 0
    contraction: dict | None = None      # the contraction model (inverse.contraction describe())
    separation: dict = field(default_factory=dict)
    curvature_reach: dict = field(default_factory=dict)   # inverse.thickness_law.curvature_reach
    target_repairs: list = field(default_factory=list)    # what geometry.target.check_disk repaired, sentences
    holes: list = field(default_factory=list)             # (k, 2) polygons cut out of the outline
    V_goal: np.ndarray | None = None    # the target on the mesh F when V is a proxy surface (inverse.design proxy)
    proxy: dict | None = None           # how the proxy was found (geometry.reachable), None: designed for the target

    @property
    def goal(self) -> np.ndarray:
        """The target's positions on the design's mesh F (mm): V, or V_goal when the design was made
        for a proxy surface; what verification and refinement measure against."""
        return self.V if self.V_goal is None else self.V_goal

    def fabric_polygon(self):
        """The flat fabric as a shapely Polygon: the outline with its holes (mm)."""
        from shapely.geometry import Polygon
        return Polygon(self.outline, [np.asarray(h) for h in self.holes])
