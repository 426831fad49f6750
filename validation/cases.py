"""Pattern dicts (the TOML tables of geometry.patterns, mm) of the studies' and tests' cases.

- The gallery (studies/gallery.py): the seed's qualitative results, GALLERY_CASES by name.
- The orthotropic ribbon sweep (studies/ortho_sweep.py): the gallery's parallel ribbons with a
  given thickness, pitch and course direction.
- The form-finding benchmark (studies/bench_solver.py): the ~10,000-vertex star sheet.
- The meshing benchmark (studies/bench_meshing.py): 800 staggered ribbons, a ~300-star tiling.
"""
from __future__ import annotations

import numpy as np

from shellfem.newton import DEFAULT_METRIC_FLOOR

# --------------------------------------------------------------------------- gallery

FABRIC = {"stretch": 1.35, "thickness_mm": 0.8}
PLASTIC = {"young_modulus_mpa": 72.3, "poisson": 0.5}
# the seed's chapter-3 star experiments: E_plastic / E_fabric = 3.2e3 from its strip calibration
# (section 3.3); with chapter 4's 72.3 MPa a 0.3 mm star curls to a ~3 mm radius and every
# star sheet rolls up tightly whatever the arm-length field
PLASTIC_CH3 = {"young_modulus_mpa": 3.2e3 * 1.05, "poisson": 0.5}


def stars_sheet(outline: dict, arm_length, spacing=10.0, across=1.0, size=2.5) -> dict:
    """Star tiling (spacing mm, arm length as a fraction of it or a field expression, 0.3 mm
    plastic of the seed's chapter 3 on the front) on the fabric ``outline`` table."""
    return {"fabric": {**outline, **FABRIC}, "plastic": PLASTIC_CH3,
            "stars": {"spacing_mm": spacing, "arm_length": arm_length, "thickness_mm": 0.3, "arm_width_mm": 0.8,
                      "side": "front"},
            "mesh": {"size_mm": size, "across": across}, "solver": {"seed": 0}}


def parallel_ribbons(width=60.0, height=40.0, pitch=4.0, model="neo-hookean", course=0.0) -> dict:
    """Ribbons 1.5 x 0.4 mm along x, ``pitch`` mm apart, on a width x height mm fabric of the given
    model (``course``: the orthotropic fabric's course direction, deg from x)."""
    rows = np.arange(pitch / 2, height, pitch)
    ribbons = [{"path": [[2.0, float(y)], [width - 2.0, float(y)]], "width_mm": 1.5, "thickness_mm": 0.4,
                "side": "front"} for y in rows]
    fab = {"rectangle": [width, height], **FABRIC, "model": model}
    if model == "orthotropic":
        fab["course_angle_deg"] = course
    return {"fabric": fab, "plastic": PLASTIC, "ribbon": ribbons, "mesh": {"size_mm": 2.0, "across": 1},
            "solver": {"seed": 0}}


def held_rim(raw: dict) -> dict:
    """Seed Fig. 3.8: "a hexagonal domain fixed at its boundary". The rim is held on the ground
    plane and slides (fix = "z"): held in place (xyz) a rim of long-armed stars cannot contract
    to where the bare fabric would, and a free hexagon rolls into a tube like Fig. 3.2."""
    return {**raw, "support": [{"boundary": True, "fix": "z"}]}


def half_annulus(r_in=25.0, r_out=50.0, n_arc=48) -> dict:
    """Half annulus (radii mm) with ribbons along circular arcs, denser towards the outer edge."""
    t = np.linspace(0.0, np.pi, n_arc + 1)
    outer = np.column_stack([r_out * np.cos(t), r_out * np.sin(t)])
    inner = np.column_stack([r_in * np.cos(t[::-1]), r_in * np.sin(t[::-1])])
    outline = np.vstack([outer, inner]) + [r_out, 0.0]
    # arcs, denser outside: gaps shrink linearly from 6 mm at the inner edge to 2 mm outside
    radii, r = [], r_in + 2.0
    while r < r_out - 1.5:
        radii.append(r)
        r += 6.0 - 4.0 * (r - r_in) / (r_out - r_in)
    ribbons = []
    for rr in radii:
        ta = np.linspace(0.05, np.pi - 0.05, 40)
        path = np.column_stack([rr * np.cos(ta) + r_out, rr * np.sin(ta)])
        ribbons.append({"path": path.round(4).tolist(), "width_mm": 1.5, "thickness_mm": 0.4, "side": "front"})
    return {"fabric": {"outline": outline.round(4).tolist(), **FABRIC}, "plastic": PLASTIC, "ribbon": ribbons,
            "mesh": {"size_mm": 2.5, "across": 1}, "solver": {"seed": 0}}


GALLERY_CASES = {
    "tube": lambda: stars_sheet({"rectangle": [50.0, 35.0]}, 0.7),
    "dome": lambda: held_rim(stars_sheet({"hexagon": 36.0}, "clip(0.75 - 0.45 * r / 36, 0.2, 0.75)",
                                         spacing=12.0)),
    "flat_centre": lambda: held_rim(stars_sheet({"hexagon": 36.0}, "clip(0.3 + 0.45 * r / 36, 0.2, 0.75)",
                                                spacing=12.0)),
    "ribbons": lambda: parallel_ribbons(),
    "ortho_0": lambda: parallel_ribbons(model="orthotropic", course=0.0),
    "ortho_90": lambda: parallel_ribbons(model="orthotropic", course=90.0),
    "half_annulus": lambda: half_annulus(),
}


# --------------------------------------------------------------------------- orthotropic ribbon sweep


def ortho_ribbons(thickness_mm: float, pitch_mm: float, course_deg: float, seed: int = 0) -> dict:
    """One case of the orthotropic sweep: the gallery's parallel ribbons with this thickness and
    pitch (mm) on the orthotropic fabric, course direction course_deg from the ribbons (seed: the
    solver's symmetry-breaking perturbation)."""
    raw = parallel_ribbons(pitch=pitch_mm, model="orthotropic", course=course_deg)
    for r in raw["ribbon"]:
        r["thickness_mm"] = float(thickness_mm)
    raw["solver"]["seed"] = int(seed)
    return raw


# --------------------------------------------------------------------------- benchmarks


def star_benchmark(width: float = 85.0, height: float = 60.0, across: float = 1.0,
                   fabric_bending_stiffness: float | None = None, seed: int = 0,
                   metric_floor: float = DEFAULT_METRIC_FLOOR) -> dict:
    """The form-finding benchmark: a uniform 3-pointed-star tiling (spacing 10 mm, arms 7 x 0.8 mm,
    0.3 mm plastic on the front, E_plastic / E_fabric = 3.2e3) on a width x height mm fabric at
    s = 1.35, ``across`` triangles across an arm; the default is the ~10,000-vertex sheet."""
    fabric = {"rectangle": [width, height], "stretch": 1.35, "thickness_mm": 0.8}
    if fabric_bending_stiffness is not None:       # N mm; default: the fabric's measured k_B
        fabric["bending_stiffness_nmm"] = float(fabric_bending_stiffness)
    return {"fabric": fabric,
            "plastic": {"young_modulus_mpa": 3.2e3 * 1.05, "poisson": 0.5},   # seed ch. 3: E1/E2 = 3.2e3
            "stars": {"spacing_mm": 10.0, "arm_length": 0.7, "thickness_mm": 0.3, "arm_width_mm": 0.8,
                      "side": "front"},
            "mesh": {"size_mm": 2.0, "across": across},
            "solver": {"seed": int(seed), "metric_floor": float(metric_floor)}}


def staggered_ribbons(rows: int = 80, per_row: int = 10, length: float = 15.0, width: float = 1.5,
                      side: float = 200.0, size_mm: float = 2.0) -> dict:
    """Meshing benchmark: rows x per_row ribbons (length x width mm) on a side x side mm fabric,
    odd rows shifted by half a pitch, clipped at the edge."""
    ribbons = []
    pitch_y, pitch_x = side / rows, side / per_row
    for i in range(rows):
        y = pitch_y * (i + 0.5)
        x0 = 0.5 * (pitch_x - length) + (0.5 * pitch_x if i % 2 else 0.0)
        for j in range(per_row):
            x = x0 + j * pitch_x
            ribbons.append({"path": [[x, y], [x + length, y]], "width_mm": width, "thickness_mm": 0.4})
    return {"fabric": {"rectangle": [side, side]}, "ribbon": ribbons, "mesh": {"size_mm": size_mm}}


def star_tiling(side: float = 160.0, size_mm: float = 2.0) -> dict:
    """Meshing benchmark: star tiling (spacing 10 mm, arms 7 x 0.8 mm) on a side x side mm fabric."""
    return {"fabric": {"rectangle": [side, side]},
            "stars": {"spacing_mm": 10.0, "arm_length": 0.7, "thickness_mm": 0.3, "arm_width_mm": 0.8},
            "mesh": {"size_mm": size_mm}}
