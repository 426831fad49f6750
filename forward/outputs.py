"""The files of a simulation: deployed.vtu (ParaView: deployed surface, printed-state reference,
regions, thickness, side, curvatures; mm, 1/mm); deployed.obj/.stl/.ply (the deployed surface
for Rhino and slicers, mm) and pattern.dxf/.svg (the flat pattern: fabric outline and printed
polygons per side and thickness, printed-state mm), all by geometry.cad; summary.json is the
Simulation.summary() dict written by shellfem.outfiles.write_json.

Neither takes a non-finite number (shellfem.outfiles.NonFiniteOutput, naming the array or key):
a NaN or infinity in a result file is never written. ``simulate_pattern_file`` writes them
through shellfem.outfiles.OutputDir (checked before the work, atomic, summary.json last)."""
from __future__ import annotations

import numpy as np

from shellfem.outfiles import check_finite_arrays

#: The files `selfshape simulate` writes (an earlier run's are removed before a new run).
OUTPUTS = ("deployed.vtu", "deployed.obj", "deployed.stl", "deployed.ply", "pattern.dxf", "pattern.svg",
           "deployed.png", "index.html", "summary.json")
#: The deployed surface's CAD copies (geometry.cad.write_surface)
SURFACES = ("deployed.obj", "deployed.stl", "deployed.ply")


def write_vtu(sim, path: str):
    """deployed.vtu: deployed surface with point data `reference` and cell data `region`,
    `thickness_mm`, `side` (+1 front, -1 back, 0 fabric, 2 both), curvatures (1/mm), `in_contact`
    (1 on the triangles touching an active self-contact pair or the ground's band, else 0).
    NonFiniteOutput (nothing written) if a position or field is NaN or infinite."""
    import meshio
    sheet = sim.sheet
    k, H, K = sim.model.curvatures(sim.result.q)
    ref = np.column_stack([sheet.points, np.zeros(sheet.n_vertices)])
    cells = {"region": sheet.region, "thickness_mm": sheet.thickness, "side": sheet.side,
             "thickness_front_mm": sheet.thickness_front, "thickness_back_mm": sheet.thickness_back,
             "k1_per_mm": k[:, 0], "k2_per_mm": k[:, 1], "mean_curvature_per_mm": H,
             "gaussian_curvature_per_mm2": K,
             "in_contact": sim.contact_report()["in_contact"].astype(np.int64)}
    check_finite_arrays("deployed.vtu", {"deployed positions": sim.positions, "reference": ref, **cells})
    meshio.write(path, meshio.Mesh(sim.positions, [("triangle", sheet.triangles)],
                                   point_data={"reference": ref},
                                   cell_data={name: [np.asarray(v)] for name, v in cells.items()}))


def write_cad(out, sim, pattern):
    """deployed.obj/.stl/.ply and pattern.dxf/.svg of a simulation into the OutputDir ``out``,
    each atomically (geometry.cad; mm)."""
    from geometry import cad
    for name in SURFACES:
        out.write(name, lambda tmp: cad.write_surface(tmp, sim.positions, sim.sheet.triangles))
    drawing = cad.pattern_drawing(pattern)
    for name in ("pattern.dxf", "pattern.svg"):
        out.write(name, lambda tmp: cad.write_drawing(tmp, drawing))
