"""report.json of a design: mesh sizes, flattening quality, ribbon counts and lengths (mm),
thickness histogram and clamping, stretch bounds."""
from __future__ import annotations

import numpy as np

from inverse.coverage import printed_over_asked
from inverse.record import Design


def thickness_histogram(ribbons) -> dict:
    """{"front": {"0.4": count, ...}, "back": {...}} of the ribbon thicknesses (mm)."""
    out = {}
    for side in ("front", "back"):
        t = [round(r.thickness_mm, 3) for r in ribbons if r.side == side]
        vals, counts = np.unique(t, return_counts=True) if t else ([], [])
        out[side] = {f"{v:g}": int(c) for v, c in zip(vals, counts)}
    return out


def report_dict(d: Design) -> dict:
    f = d.flat
    lengths = [r.length_mm for r in d.ribbons]
    return {
        "n_faces": int(len(d.F)), "n_faces_input": int(len(d.F_input)), "refine_levels": d.refine_levels,
        "n_faces_layout": int(len(d.F_input) * 4 ** d.layout_levels),
        "lambda": d.lam, "k1_deviation_deg": float(f.k1_deviation_deg),
        "sigma_bound_violation": [float(x) for x in f.sigma_bound_violation],
        "sigma_out_of_bounds_pct": [float(x) for x in f.sigma_out_of_bounds_pct],
        "residual_energy": float(f.residual_energy),
        "stretch": d.stretch, "stretch_bounds": np.asarray(d.bounds).tolist(), "contraction": d.contraction,
        "flatten_iterations": int(f.iterations), "flatten_coarse_iterations": int(d.coarse_iterations),
        "flatten_converged": bool(f.converged), "flatten_stop": d.stop,
        "flatten_last_change": [float(x) for x in f.history[-1]] if f.history else None,
        "field_t": None if not np.isfinite(d.field.t) else float(d.field.t),
        "sigma1_range": [float(f.sigma1.min()), float(f.sigma1.max())],
        "sigma2_range": [float(f.sigma2.min()), float(f.sigma2.max())],
        "flat_area_mm2": float(d.fabric_polygon().area),
        "n_ribbons": len(d.ribbons),
        "ribbons_per_side": {s: sum(r.side == s for r in d.ribbons) for s in ("front", "back")},
        "ribbon_length_mm": {"total": float(np.sum(lengths)), "mean": float(np.mean(lengths))},
        "thickness_histogram": thickness_histogram(d.ribbons),
        "ribbons_separated": d.separation,
        "printed_over_asked_area": round(printed_over_asked(d), 4),
        "thickness_clamped": d.thickness_info, "thickness_law": d.law_source,
        "plastic_young_modulus_mpa": d.law_plastic_mpa,
        "curvature_reach": d.curvature_reach,
        "target_repairs": d.target_repairs,
        "proxy": d.proxy,
    }

