"""Simulate a pattern file from Python: the narrow bilayer strip of examples/strip_narrow.toml.

A 30 x 3 mm strip covered by 0.3 mm of plastic, printed on fabric pre-stretched by 1.35,
rolls up when the fabric is released. This loads the pattern, meshes it, solves for the released equilibrium and prints
whether the solver converged, how many Newton iterations it took, the energy (N mm) and the
median principal curvatures of the printed triangles (1/mm; negative: the centre of
curvature is on the fabric side, below the front plastic).

Run from the repository root:  python examples/simulate_strip.py
"""
import numpy as np

from forward.simulate import simulate
from geometry.patterns import load_pattern

pattern = load_pattern("examples/strip_narrow.toml")
sim = simulate(pattern)
result = sim.result

k, H, K = sim.model.curvatures(result.q)        # per triangle: principal (k1, k2), mean, Gaussian
printed = sim.sheet.thickness > 0
k_along = np.median(k[printed, 0])
k_across = np.median(k[printed, 1])

print(f"converged {result.converged}")
print(f"iterations {result.iterations}")
print(f"energy_nmm {result.energy:.6g}")
print(f"vertices {sim.sheet.n_vertices}")
print(f"curvature_k1_per_mm {k_along:.5f}")
print(f"curvature_k2_per_mm {k_across:.5f}")
print(f"bbox_mm {' '.join(f'{v:.2f}' for v in sim.positions.max(0) - sim.positions.min(0))}")
