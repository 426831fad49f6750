"""The files of a simulation: deployed.vtu (ParaView: deployed surface, printed-state reference,
regions, thickness, side, curvatures; mm, 1/mm) and summary.json."""
from __future__ import annotations

import json

import numpy as np


def write_vtu(sim: Simulation, path: str):
    """deployed.vtu: deployed surface with point data `reference` and cell data `region`,
    `thickness_mm`, `side` (+1 front, -1 back, 0 fabric, 2 both), curvatures (1/mm)."""
    import meshio
    sheet = sim.sheet
    k, H, K = sim.model.curvatures(sim.result.q)
    ref = np.column_stack([sheet.points, np.zeros(sheet.n_vertices)])
    cells = {"region": sheet.region, "thickness_mm": sheet.thickness, "side": sheet.side,
             "thickness_front_mm": sheet.thickness_front, "thickness_back_mm": sheet.thickness_back,
             "k1_per_mm": k[:, 0], "k2_per_mm": k[:, 1], "mean_curvature_per_mm": H,
             "gaussian_curvature_per_mm2": K}
    meshio.write(path, meshio.Mesh(sim.positions, [("triangle", sheet.triangles)],
                                   point_data={"reference": ref},
                                   cell_data={name: [np.asarray(v)] for name, v in cells.items()}))


def write_summary(summary: dict, path: str):
    """summary.json: the Simulation.summary() dict (with the pattern and seed), indented."""
    with open(path, "w") as f:
        json.dump(summary, f, indent=2)
