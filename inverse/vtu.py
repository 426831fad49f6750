"""The VTU files of a design (ParaView): flat.vtu, the flattened target with its stretches and
curvature, and deployed.vtu, the registered simulated deployment with its distance to the
target (mm, 1/mm, % of the bounding-box diagonal). A NaN or infinite value is never written
(shellfem.outfiles.NonFiniteOutput)."""
from __future__ import annotations

import numpy as np

from inverse.record import Design
from shellfem.outfiles import check_finite_arrays


def write_flat_vtu(d: Design, path: str):
    """flat.vtu: flattened mesh (z = 0), cell data sigma1, sigma2, kappa1_per_mm; point data
    target (3D position on the target) and, for a design made for a proxy surface, proxy (3D
    position on it: the surface flattened)."""
    import meshio

    pts = np.column_stack([d.flat.uv, np.zeros(len(d.flat.uv))])
    point_data = {"target": d.goal} if d.V_goal is None else {"target": d.goal, "proxy": d.V}
    check_finite_arrays("flat.vtu", {"flat positions": pts, **point_data, "sigma1": d.flat.sigma1,
                                     "sigma2": d.flat.sigma2, "kappa1_per_mm": d.kappa1})
    meshio.write(path, meshio.Mesh(pts, [("triangle", d.F)], point_data=point_data,
                                   cell_data={"sigma1": [d.flat.sigma1], "sigma2": [d.flat.sigma2],
                                              "kappa1_per_mm": [d.kappa1]}))


def write_deployed_vtu(path: str, X: np.ndarray, sheet, pct: np.ndarray):
    """deployed.vtu: the registered deployed surface X (n, 3) on the simulated sheet's triangles,
    point data reference (printed-state position, z = 0) and distance_pct_bbox (distance to the
    target, % of its bounding-box diagonal), cell data side."""
    import meshio

    check_finite_arrays("deployed.vtu", {"deployed positions": X, "distance_pct_bbox": pct})
    meshio.write(path, meshio.Mesh(X, [("triangle", sheet.triangles)],
                                   point_data={"reference": np.column_stack([sheet.points, np.zeros(len(X))]),
                                               "distance_pct_bbox": pct},
                                   cell_data={"side": [np.asarray(sheet.side)]}))
