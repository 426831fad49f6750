"""Calibrate the plastic/fabric modulus ratio on measured bilayer strips.

Reads the repository's copy of the strip measurements (validation/data/strips_S1.csv: 80
strips, each with its plastic and fabric thickness, pre-stretch and measured curvature),
fits E_plastic / E_fabric by nonlinear least squares on the engine's own narrow-strip model
(shellfem.strip, plastic flat at rest), and prints the ratio with its standard error and 95 %
profile-likelihood interval, the plastic modulus it implies for the default fabric
(1.05 MPa), and the model's curvature for one strip next to the measured mean (the base model
leaves a gap there that `selfshape validate` attributes to plastic set and side deposition).
This is what `selfshape calibrate strips` does; parameters.json and strips_fit.png are
written to a temporary folder.

Run from the repository root:  python examples/calibrate_strips.py
"""
import tempfile

import numpy as np

from shellfem.materials import Fabric
from validation.strips import calibrate_strips, read_strips, strip_model

DATA = "validation/data/strips_S1.csv"

with tempfile.TemporaryDirectory() as out:
    params = calibrate_strips(DATA, out)

ratio, se = params["modulus_ratio"]
lo, hi = params["confidence_intervals_95"]["modulus_ratio"]
print(f"strips {params['fit']['n_rows']}")
print(f"modulus_ratio {ratio:.1f} +- {se:.1f}")
print(f"ci95 {lo:.0f} {hi:.0f}")
print(f"plastic_modulus_mpa {ratio * Fabric().young_modulus:.0f}")

# the fitted model against the data, on the first strip's geometry
rows = read_strips(DATA)
tp, tf, s = rows["plastic_thickness_mm"][0], rows["fabric_thickness_mm"][0], rows["stretch"][0]
same = (rows["plastic_thickness_mm"] == tp) & (rows["stretch"] == s) & (rows["side"] == rows["side"][0])
model = float(strip_model(tp, tf, s, ratio))
measured = float(np.mean(rows["curvature_per_mm"][same]))
print(f"strip {rows['side'][0]} t_plastic {tp:.2f} mm, s {s:.2f}: model {model:.4f} 1/mm, measured mean {measured:.4f} 1/mm")
