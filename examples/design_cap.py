"""Inverse design from Python: ribbons and G-code for a small spherical cap.

Builds a spherical cap (sphere radius 40 mm, opening half-angle 30 degrees), writes it as an
OBJ target, and runs the whole design pipeline on it at a 40 mm bounding-box diagonal and a
pre-stretch of 1.6: principal curvatures -> line field -> bounded flattening -> ribbon
layout -> thickness from the curvature law -> G-code. Prints the ribbon count per side, the
ribbon thicknesses, the flattening's Table 5.1 figures, and checks that the written
pattern.toml loads as a pattern (it runs with `selfshape simulate` like any other; that
simulation is left out here to keep the example fast).
This is what `selfshape design cap.obj -o DIR` does; the files go to a temporary folder.

Run from the repository root:  python examples/design_cap.py
"""
import os
import tempfile

from geometry.patterns import load_pattern
from geometry.target import sphere_cap
from inverse.design import design_file

V, F = sphere_cap(radius=40.0, half_angle_deg=30.0, n_radial=8)

with tempfile.TemporaryDirectory() as out:
    target = os.path.join(out, "cap.obj")
    with open(target, "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F)
    report = design_file(target, os.path.join(out, "design"), diagonal_mm=40.0, stretch=1.6)
    pattern = load_pattern(os.path.join(out, "design", "pattern.toml"))
    written = sorted(os.listdir(os.path.join(out, "design")))

sides = report["ribbons_per_side"]
print(f"ribbons {report['n_ribbons']} front {sides['front']} back {sides['back']}")
thick = sorted({t for side in report["thickness_histogram"].values() for t in side}, key=float)
print(f"thickness_mm {' '.join(thick)}")
print(f"k1_deviation_deg {report['k1_deviation_deg']:.3f}")
print(f"sigma_out_of_bounds_pct {report['sigma_out_of_bounds_pct'][0]:.2f} {report['sigma_out_of_bounds_pct'][1]:.2f}")
print(f"pattern_elements {len(pattern.elements)}")
print(f"files {' '.join(written)}")
print(f"time_s {report['time_s']:.1f}")
