"""Generators of synthetic fabric test folders, written exactly to the schema of the
measurement data README (meta.json, tensile_<deg>deg_<pct>pct.csv, shear_<deg>deg.csv,
cantilever.csv), from known parameters through the project's own fabric model forward:

- tensile: the engine's orthotropic log-barrier law (shellfem.materials.orthotropic) in
  uniaxial stress at the specimen's angle (validation.fabric_law.uniaxial_response), the
  unloading branch exact + load-cell noise, the loading branch above it (a hysteresis loop),
  cycle 1 off the stabilised curve (preconditioning), Eq. 4.4 inverted for the load;
- shear: simple shear F = [[1, gamma], [0, 1]] of the clamped square, the lateral force
  (S12 + gamma S22) side h of the same law (strain rotated into the course frame);
- cantilever: the heavy-elastica master curve (validation.elastica) at Gamma = w L^3 / k_B.

Everything a lab may vary within the schema is a field of FabricSpec: thickness, sample
geometry, Poisson's ratio in meta.json or not, moduli, barriers, max stretches, orientations,
number of cycles, crosshead speed and sampling rate (so the number of rows per branch and per
file), noise levels, rounding. ``random_spec(seed)`` draws one; ``write_folder`` writes it.
Units: mm, N, MPa; strains are Green strains. All randomness is seeded.
"""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from shellfem.materials.orthotropic import orthotropic_stress
from validation import elastica
from validation.fabric_law import strain_rotation, uniaxial_response


@dataclasses.dataclass
class FabricSpec:
    """Known parameters of one synthetic fabric and of its tests (mm, N, MPa, s)."""
    params: dict                       # a1, a2, a3, b1, b2 (MPa), g1, g2 (Green strain)
    k_b: dict                          # "<orientation>/<face>" -> bending stiffness, N mm
    thickness_mm: float = 0.8
    width_mm: float = 20.0             # tensile strip width
    gauge_mm: float = 60.0             # tensile gauge length
    shear_side_mm: float = 40.0
    poisson: float | None = None       # written to meta.json when given; the reader's default is 0.3
    pcts: tuple = (45, 70)             # max stretch of the tensile files, percent of the gauge length
    orientations: tuple = (0, 15, 30, 45, 60, 75, 90)
    shear_orientations: tuple = (0, 90)
    cycles: int = 3
    precondition: float = 1.08         # cycle-1 unloading stress / stabilised stress
    unload_drop: float = 0.0           # steep start of unloading (stress relaxation at the turn), fraction
    unload_drop_width: float = 0.004   # ... of the top stress, decaying over this Green strain
    speed_mm_s: float = 0.45           # crosshead speed
    rate_hz: float = 2.0               # sampling rate
    load_noise_n: float = 0.0013       # load-cell noise, N (standard deviation)
    shear_points: int = 60
    shear_max_mm: float = 14.0
    shear_noise_n: float = 0.001
    cantilever_lengths: tuple = (20, 30, 40, 50, 60, 80, 100)
    areal_weight: float = 1.9e-6       # N/mm^2
    cantilever_noise_rel: float = 0.02
    load_decimals: int = 5
    extension_decimals: int = 4
    seed: int = 0

    @property
    def nu(self) -> float:
        return 0.3 if self.poisson is None else float(self.poisson)

    def green_max(self, pct: float) -> float:
        r = pct / 100.0
        return r + 0.5 * r * r


def _fmt(x, d):
    return f"{x:.{d}f}"


def _write(path, header, rows):
    with open(path, "w", newline="") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join(str(v) for v in r) + "\n")


def _load_of_stress(S, d, spec):
    """Eq. 4.4 inverted: f = S w h (d + L) / L (N)."""
    return S * spec.width_mm * spec.thickness_mm * (d + spec.gauge_mm) / spec.gauge_mm


def tensile_rows(spec: FabricSpec, deg: float, pct: float, rng) -> list:
    """Rows (time_s, cycle, branch, extension_mm, load_N) of one tensile file: ``cycles``
    load/unload cycles to pct % of the gauge length, sampled at rate_hz while the crosshead
    moves at speed_mm_s (the sample count per branch follows; its first sample is at a random
    phase, so branches and files differ in length)."""
    L = spec.gauge_mm
    d_max = L * pct / 100.0
    step = spec.speed_mm_s / spec.rate_hz
    rows, t = [], 0.0
    for c in range(1, spec.cycles + 1):
        for branch in ("load", "unload"):
            phase = rng.uniform(0.0, step)
            s = np.arange(phase, d_max, step)
            d = s if branch == "load" else d_max - s
            if branch == "unload":
                d = np.concatenate([[d_max], d[d < d_max]])
            e = d / L + 0.5 * (d / L) ** 2
            S, _ = uniaxial_response(e, deg, spec.params, spec.nu)
            if not np.all(np.isfinite(S)):
                raise ValueError(f"spec beyond the barrier at {deg} deg, {pct} %")
            if branch == "load":
                S = S + 0.25 * S.max() * np.sin(np.pi * d / d_max) ** 0.7
            else:
                if spec.unload_drop:
                    e_top = d_max / L + 0.5 * (d_max / L) ** 2
                    S = S + spec.unload_drop * S.max() * np.exp(-(e_top - e) / spec.unload_drop_width)
                if c == 1 and spec.cycles > 1:
                    S = S * spec.precondition
            f = _load_of_stress(S, d, spec) + spec.load_noise_n * rng.standard_normal(d.size)
            for di, fi in zip(d, f):
                rows.append((f"{t:.2f}", c, branch, _fmt(di, spec.extension_decimals), _fmt(fi, spec.load_decimals)))
                t += 1.0 / spec.rate_hz
    return rows


def shear_lateral_stress(gamma, deg: float, params: dict, nu: float) -> np.ndarray:
    """tau = F / (side h) = S12 + gamma S22 (MPa) of simple shear gamma of a square cut at deg
    from the course direction (Green strain (0, gamma^2/2, gamma) in the specimen frame)."""
    g = np.asarray(gamma, float)
    eps_s = np.column_stack([np.zeros_like(g), 0.5 * g * g, g])
    T = strain_rotation(deg)
    sig, _ = orthotropic_stress(eps_s @ T.T, params, nu)
    ss = sig @ T                                   # stress back in the specimen frame
    return ss[:, 2] + g * ss[:, 1]


def shear_rows(spec: FabricSpec, deg: float, rng) -> list:
    u = np.linspace(0.0, spec.shear_max_mm, spec.shear_points)
    tau = shear_lateral_stress(u / spec.shear_side_mm, deg, spec.params, spec.nu)
    f = tau * spec.shear_side_mm * spec.thickness_mm + spec.shear_noise_n * rng.standard_normal(u.size)
    return [(_fmt(a, 4), _fmt(b, spec.load_decimals)) for a, b in zip(u, f)]


def cantilever_rows(spec: FabricSpec, rng) -> list:
    rows = []
    for key, k in spec.k_b.items():
        o, face = key.split("/")
        for L in spec.cantilever_lengths:
            hw = elastica.master_curve(spec.areal_weight * L ** 3 / k) * np.exp(spec.cantilever_noise_rel
                                                                            * rng.standard_normal())
            rows.append((o, face, L, f"{spec.areal_weight:.3e}", f"{hw:.5f}"))
    return rows


def write_folder(spec: FabricSpec, folder) -> str:
    """Write the test folder of spec (seeded by spec.seed) and return its path."""
    rng = np.random.default_rng(spec.seed)
    os.makedirs(folder, exist_ok=True)
    meta = {"fabric_thickness_mm": spec.thickness_mm, "tensile_width_mm": spec.width_mm,
            "tensile_gauge_length_mm": spec.gauge_mm, "shear_sample_side_mm": spec.shear_side_mm,
            "orientation_reference": "course direction (x)"}
    if spec.poisson is not None:
        meta["poisson"] = spec.poisson
    with open(os.path.join(folder, "meta.json"), "w") as f:
        json.dump(meta, f)
    for pct in spec.pcts:
        for deg in spec.orientations:
            _write(os.path.join(folder, f"tensile_{deg:02d}deg_{pct}pct.csv"),
                   ("time_s", "cycle", "branch", "extension_mm", "load_N"), tensile_rows(spec, deg, pct, rng))
    for deg in spec.shear_orientations:
        _write(os.path.join(folder, f"shear_{deg:02d}deg.csv"), ("lateral_displacement_mm", "lateral_load_N"),
               shear_rows(spec, deg, rng))
    _write(os.path.join(folder, "cantilever.csv"),
           ("orientation_deg", "face_up", "free_length_mm", "areal_weight_N_per_mm2", "height_over_width"),
           cantilever_rows(spec, rng))
    return str(folder)


def random_spec(seed: int, **override) -> FabricSpec:
    """A fabric and its tests drawn from seed: thickness 0.3-1.2 mm, moduli over a decade,
    barriers 1-8 % above the largest tested Green strain, 1-5 cycles, 0.5-8 Hz sampling,
    noise 0.02-0.3 % of the largest load, with or without meta.json's poisson, a random subset
    of the off-axis orientations, one to three max stretches. ``override``: fields to fix."""
    rng = np.random.default_rng(seed)
    pcts = tuple(sorted(rng.choice([30, 45, 55, 70, 80], size=int(rng.integers(1, 4)), replace=False).tolist()))
    e_top = pcts[-1] / 100 + 0.5 * (pcts[-1] / 100) ** 2
    h = float(rng.uniform(0.3, 1.2))
    params = {"a1": float(np.exp(rng.uniform(np.log(0.01), np.log(0.12)))),
              "a2": float(np.exp(rng.uniform(np.log(0.01), np.log(0.12)))),
              "a3": float(np.exp(rng.uniform(np.log(0.02), np.log(0.1)))),
              "b1": float(np.exp(rng.uniform(np.log(0.01), np.log(0.05)))),
              "b2": float(np.exp(rng.uniform(np.log(0.01), np.log(0.05)))),
              "g1": float(e_top * rng.uniform(1.01, 1.08)),
              "g2": float(e_top * rng.uniform(1.01, 1.08))}
    off = [d for d in (15, 30, 45, 60, 75) if rng.random() < 0.6]
    k_b = {f"{o}/{f}": float(np.exp(rng.uniform(np.log(0.005), np.log(0.05))))
           for o in (0, 90) for f in ("front", "back")}
    spec = FabricSpec(params=params, k_b=k_b, thickness_mm=h,
                      width_mm=float(rng.choice([15.0, 20.0, 25.0])), gauge_mm=float(rng.choice([50.0, 60.0, 80.0])),
                      shear_side_mm=float(rng.choice([30.0, 40.0, 50.0])),
                      poisson=(None if rng.random() < 0.5 else float(rng.uniform(0.2, 0.4))),
                      pcts=pcts, orientations=tuple([0] + off + [90]),
                      cycles=int(rng.integers(1, 6)), precondition=float(rng.uniform(1.03, 1.15)),
                      rate_hz=float(rng.uniform(0.5, 8.0)), speed_mm_s=float(rng.uniform(0.2, 1.0)),
                      seed=int(seed))
    # noise relative to the largest load of the top test
    s_top = max(uniaxial_response([e_top], d, params, spec.nu)[0][0] for d in (0.0, 90.0))
    f_top = s_top * spec.width_mm * h * (1 + pcts[-1] / 100)
    spec.load_noise_n = float(f_top * rng.uniform(2e-4, 3e-3))
    spec.shear_noise_n = float(spec.load_noise_n * 0.5)
    spec.load_decimals = 6
    for k, v in override.items():
        setattr(spec, k, v)
    return spec


def recovery_errors(spec: FabricSpec, result: dict) -> dict:
    """Relative errors of a1, a2, a3, b1, b2 and of each k_B, absolute errors of g1, g2, of
    a calibrate_fabric result against the spec's known parameters."""
    o = result["orthotropic"]
    out = {k: abs(o[k][0] / spec.params[k] - 1) for k in ("a1", "a2", "a3", "b1", "b2")}
    out.update({k: abs(o[k][0] - spec.params[k]) for k in ("g1", "g2")})
    out.update({f"k_B {k}": abs(result["bending_stiffness_nmm"][k][0] / v - 1) for k, v in spec.k_b.items()})
    return out
