"""A design as a pattern: the raw dict of the pattern TOML that `selfshape simulate` reads
(geometry.patterns), so that the designed print can be simulated and printed (mm, MPa)."""
from __future__ import annotations

import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:        # numpy and the design record load with pattern_dict: the CLI's parser
    from inverse.record import Design   # reads the defaults below without them

#: The verification's discretisation written to a designed pattern.toml's [mesh] (mm, rows
#: across a ribbon): the one every verified design figure of the README was computed on. The
#: shipped thickness laws' patches used 2 rows across; on the refined saddle, 2 rows move the
#: deployed surface by 0.22 % mean / 0.74 % max of the diagonal (deviation 0.77 / 3.22 % ->
#: 0.79 / 3.57 %) for 2.4x the vertices and 3x the time (docs/notes.md, session 37), so one row
#: is the default and ``--mesh-across 2`` the check.
VERIFY_MESH_SIZE_MM = 3.0
VERIFY_MESH_ACROSS = 1.0
#: The verification's Newton cap, written to the designed pattern.toml's [solver]: a soft
#: designed sheet released from flat takes 100-1,300 iterations to settle (saddle 210, beetle
#: 1,265), so the simulator's general default of 300 would leave many verifications unconverged.
VERIFY_ITERATIONS = 3000


def pattern_dict(d: Design, *, fabric=None, plastic=None, mesh_size_mm: float = VERIFY_MESH_SIZE_MM,
                 mesh_across: float | None = VERIFY_MESH_ACROSS, seed: int = 0, target_name: str = "",
                 max_iterations: int | None = VERIFY_ITERATIONS, metric_floor: float | None = None) -> dict:
    """The pattern TOML (geometry.patterns) of a design as a dict: [fabric] outline = flat boundary,
    [[ribbon]] per ribbon, [plastic] (default: the modulus the thickness law states), [mesh],
    [solver] (seed, and max_iterations when given: the Newton cap `selfshape simulate` uses for
    this pattern; metric_floor when given: shellfem.newton.lm_metric), [meta] provenance.
    [fabric] and [plastic] carry every field of the materials (geometry.patterns.fabric_table,
    plastic_table), so an orthotropic or other model's fabric reloads as it was designed."""
    import numpy as np

    from geometry.patterns import fabric_table, plastic_table
    from shellfem.materials import Fabric, Plastic

    fab = fabric or Fabric()
    # the plastic the thickness law was computed for, so the pattern simulates what was designed
    pla = plastic or (Plastic(young_modulus=d.law_plastic_mpa) if d.law_plastic_mpa else Plastic())
    r4 = lambda a: np.round(np.asarray(a, float), 4).tolist()  # noqa: E731
    return {
        "meta": {"generator": "selfshape design (inverse.design)", "target": target_name,
                 "stretch_bounds": np.asarray(d.bounds).tolist(), "thickness_law": os.path.basename(d.law_source)},
        "fabric": {"outline": r4(d.outline), **({"holes": [r4(h) for h in d.holes]} if d.holes else {}),
                   **fabric_table(fab), "stretch": d.stretch},
        "plastic": plastic_table(pla),
        "ribbon": [{"path": r4(r.path), "width_mm": float(r.width_mm), "thickness_mm": float(r.thickness_mm),
                    "side": r.side} for r in d.ribbons],
        "mesh": {"size_mm": float(mesh_size_mm), **({} if mesh_across is None else {"across": float(mesh_across)})},
        "solver": {"seed": int(seed), **({} if max_iterations is None else {"max_iterations": int(max_iterations)}),
                   **({} if metric_floor is None else {"metric_floor": float(metric_floor)})},
    }
