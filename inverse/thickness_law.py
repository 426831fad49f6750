"""The curvature law kappa(thickness, transverse spacing, side) and its monotone inverse
(seed section 5.3.5, Fig. 5.6-5.7).

A law is a CSV table: lines starting with ``#`` are provenance comments (free text, kept in
``ThicknessLaw.provenance``), then a header with the columns

    thickness_mm, spacing_mm, side, kappa_per_mm

thickness_mm: printed plastic thickness of a ribbon (mm); spacing_mm: transverse
centre-to-centre spacing mu2 of neighbouring ribbon rows in the printed state (mm, Eq. 5.15);
side: "front" or "back"; kappa_per_mm: magnitude of the deployed normal curvature along the
ribbons (1/mm, per unit deployed length). Extra columns are allowed and ignored. Each side is
a full grid (every thickness with every spacing, at least 2 x 2), and for every spacing kappa
is strictly monotone in thickness, in the same direction for all spacings of a side (so the
bilinear interpolant is monotone in thickness at any spacing and can be inverted).
One comment line may state the plastic the law holds for, ``# plastic_young_modulus_mpa = E``
(MPa): `selfshape design` then writes that modulus into pattern.toml's [plastic], so that the
pattern simulates with the material its thicknesses were chosen for. Another may state the
fabric pre-stretch it was made at, ``# fabric_stretch = s``: a law's curvatures hold only at
that stretch (the misfit scales the curvature), so `design` refuses a law made at another
stretch than the one it designs for. The shipped laws are ``inverse/data/thickness_law_s<s>.csv``
(`shipped_laws`); `law_for_stretch` picks the one for a stretch.

Interpolation is bilinear in (thickness, spacing); spacings outside the table are clamped to
its range (counted). The inverse returns thicknesses rounded to multiples of the printer's
layer height within the printable part of the table's range; targets outside the achievable
curvature range are clamped (counted).
"""
from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field

import numpy as np

from geometry.schema import MIN_FEATURE_MM, PATTERN_NUMBERS, Num, number
from shellfem.errors import SelfshapeError, check_number
from shellfem.infiles import csv_error_text, read_input_text

COLUMNS = ("thickness_mm", "spacing_mm", "side", "kappa_per_mm")
SIDES = ("front", "back")
PLASTIC_KEY = "plastic_young_modulus_mpa"
STRETCH_KEY = "fabric_stretch"
DATA_DIR = os.path.join(os.path.dirname(__file__), "data")
#: The law shipped with the project for the default stretch 1.6 (see the file's provenance header).
DEFAULT_LAW = os.path.join(DATA_DIR, "thickness_law_s1.6.csv")
_SHIPPED = re.compile(r"^thickness_law_s(\d+(?:\.\d+)?)\.csv$")


@dataclass
class SideTable:
    """One side's grid: kappa[i, j] at thickness[i], spacing[j] (both strictly increasing)."""
    thickness: np.ndarray
    spacing: np.ndarray
    kappa: np.ndarray
    increasing: bool          # kappa increases with thickness


@dataclass
class ThicknessLaw:
    """A loaded law: per side a SideTable; provenance = the comment lines; source = file;
    plastic_young_modulus_mpa: the plastic the law holds for (MPa), None if not stated;
    stretch: the fabric pre-stretch it was made at, None if not stated."""
    sides: dict
    provenance: list = field(default_factory=list)
    source: str = "<table>"
    plastic_young_modulus_mpa: float | None = None
    stretch: float | None = None

    def table(self, side: str) -> SideTable:
        if side not in self.sides:
            raise SelfshapeError(f"{self.source}: no rows for side {side!r} (has {', '.join(self.sides)})")
        return self.sides[side]


# ----------------------------------------------------------------------------- reading
#: The law's numbers and their physical ranges (geometry.schema): a law is data from anyone,
#: and a kappa_per_mm of 1e300 1/mm was accepted and designed with (exit 0).
LAW_NUMBERS = {
    "thickness_mm": PATTERN_NUMBERS["ribbon"]["thickness_mm"],
    "spacing_mm": Num(MIN_FEATURE_MM, 1000.0, "mm", "a row spacing of a bead's width to 1 m"),
    "kappa_per_mm": Num(0.0, 10.0, "1/mm", "a magnitude; a curl radius below 0.1 mm is no ribbon"),
    PLASTIC_KEY: PATTERN_NUMBERS["plastic"]["young_modulus_mpa"],
    STRETCH_KEY: Num(1.0, PATTERN_NUMBERS["fabric"]["stretch"].hi, "", "a pre-stretch > 1 (the fabric's range)",
                     lo_open=True),
}


def _float(value, where):
    return check_number(where, value)


def _law_number(text, where, spec):
    """A number of the law CSV (text) inside its LAW_NUMBERS range, else one line naming it."""
    return number(_float(text, where), where, spec)


def parse_thickness_law(text: str, source: str = "<table>") -> ThicknessLaw:
    """Parse the CSV text of a law (see the module doc); one-line SelfshapeError on a bad table."""
    lines = text.splitlines()
    provenance = [ln[1:].strip() for ln in lines if ln.lstrip().startswith("#")]
    body = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise SelfshapeError(f"{source}: no header line (expected columns {', '.join(COLUMNS)})")
    reader = csv.reader(io.StringIO("\n".join(ln for _, ln in body)))
    try:
        rows = list(reader)
    except csv.Error as e:              # a field over the csv module's limit, a NUL byte
        raise SelfshapeError(f"{source}: line {body[min(reader.line_num, len(body)) - 1][0]}: "
                             f"{csv_error_text(e)}") from None
    header = [h.strip() for h in rows[0]]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise SelfshapeError(f"{source}: line {body[0][0]}: missing column {missing[0]!r} "
                             f"(need {', '.join(COLUMNS)})")
    col = {c: header.index(c) for c in COLUMNS}
    data = {s: [] for s in SIDES}
    for (lineno, _), row in zip(body[1:], rows[1:]):
        where = f"{source}: line {lineno}"
        if len(row) < len(header):
            raise SelfshapeError(f"{where}: {len(row)} fields, the header has {len(header)}")
        side = row[col["side"]].strip()
        if side not in SIDES:
            raise SelfshapeError(f"{where}: side must be \"front\" or \"back\", got {side!r}")
        t, mu, k = (_law_number(row[col[c]], f"{where}: {c}", LAW_NUMBERS[c])
                    for c in ("thickness_mm", "spacing_mm", "kappa_per_mm"))
        data[side].append((t, mu, k, lineno))
    sides = {s: _grid(rows_, s, source) for s, rows_ in data.items() if rows_}
    if not sides:
        raise SelfshapeError(f"{source}: no data rows")
    modulus = stretch = None
    for ln in provenance:
        key, eq, value = ln.partition("=")
        if eq and key.strip() == PLASTIC_KEY:
            modulus = _law_number(value.strip(), f"{source}: {PLASTIC_KEY}", LAW_NUMBERS[PLASTIC_KEY])
        if eq and key.strip() == STRETCH_KEY:
            stretch = _law_number(value.strip(), f"{source}: {STRETCH_KEY}", LAW_NUMBERS[STRETCH_KEY])
    return ThicknessLaw(sides, provenance, source, modulus, stretch)


def _grid(rows, side, source) -> SideTable:
    a = np.array(rows, dtype=float)
    T, S = np.unique(a[:, 0]), np.unique(a[:, 1])
    where = f"{source}: side {side}"
    if len(T) < 2 or len(S) < 2:
        raise SelfshapeError(f"{where}: need at least 2 thicknesses and 2 spacings, got {len(T)} x {len(S)}")
    K = np.full((len(T), len(S)), np.nan)
    i, j = np.searchsorted(T, a[:, 0]), np.searchsorted(S, a[:, 1])
    seen = np.zeros_like(K, dtype=bool)
    for r, (ii, jj) in enumerate(zip(i, j)):
        if seen[ii, jj]:
            raise SelfshapeError(f"{source}: line {int(a[r, 3])}: duplicate row for side {side}, "
                                 f"thickness {a[r, 0]:g} mm, spacing {a[r, 1]:g} mm")
        seen[ii, jj] = True
    K[i, j] = a[:, 2]
    if not seen.all():
        ii, jj = np.argwhere(~seen)[0]
        raise SelfshapeError(f"{where}: missing row for thickness {T[ii]:g} mm, spacing {S[jj]:g} mm "
                             f"(the table must be a full grid)")
    d = np.diff(K, axis=0)
    inc, dec = (d > 0).all(), (d < 0).all()
    if not (inc or dec):
        # name the first spacing column that is not strictly monotone (or disagrees in direction)
        up = (d > 0).all(axis=0)
        down = (d < 0).all(axis=0)
        bad = ~(up | down)
        j = int(np.argmax(bad)) if bad.any() else int(np.argmax(up != up[0]))
        raise SelfshapeError(f"{where}: kappa_per_mm is not strictly monotone in thickness_mm "
                             f"(same direction for every spacing) at spacing {S[j]:g} mm")
    return SideTable(T, S, K, bool(inc))


def load_thickness_law(path=None) -> ThicknessLaw:
    """Read a law CSV (default: the shipped ``inverse/data/thickness_law_s1.6.csv``)."""
    path = DEFAULT_LAW if path is None else os.fspath(path)
    return parse_thickness_law(read_input_text(path, "curvature-law CSV", path), path)


def files_by_stretch(folder: str, pattern) -> dict:
    """{fabric stretch: path} of the files in ``folder`` whose name matches ``pattern`` (a
    compiled regex whose group 1 is the stretch), e.g. the shipped laws and contraction tables."""
    out = {}
    for name in sorted(os.listdir(folder)):
        m = pattern.match(name)
        if m:
            out[float(m.group(1))] = os.path.join(folder, name)
    return out


def weighted_quantile(x, w, q: float) -> float:
    """The ``q`` quantile of the values x (n,) weighted by w (n,): the smallest x whose
    cumulative weight fraction reaches q."""
    x, w = np.asarray(x, float), np.asarray(w, float)
    order = np.argsort(x)
    cw = np.cumsum(w[order]) / w.sum()
    return float(x[order][min(np.searchsorted(cw, q), len(x) - 1)])


def shipped_laws() -> dict:
    """{fabric stretch: path} of the laws shipped in ``inverse/data`` (thickness_law_s<s>.csv)."""
    return files_by_stretch(DATA_DIR, _SHIPPED)


def law_for_stretch(stretch: float) -> ThicknessLaw:
    """The shipped law made at fabric stretch ``stretch`` (to 1e-6); a one-line error naming the
    stretches that are shipped otherwise."""
    laws = shipped_laws()
    for s, path in laws.items():
        if abs(s - float(stretch)) <= 1e-6:
            return load_thickness_law(path)
    have = ", ".join(f"{s:g}" for s in laws)
    raise SelfshapeError(f"no shipped thickness law for fabric stretch {float(stretch):g} (shipped: {have}); "
                         f"pass --law FILE made at that stretch (studies/thickness_law_sim.py --stretch "
                         f"{float(stretch):g}) or use a shipped stretch")


def check_law_stretch(law: ThicknessLaw, stretch: float) -> None:
    """Refuse a law that states a fabric stretch other than ``stretch`` (one line naming both)."""
    if law.stretch is not None and abs(law.stretch - float(stretch)) > 1e-6:
        raise SelfshapeError(f"{law.source}: the law was made at fabric stretch {law.stretch:g}, the design asks "
                             f"for {float(stretch):g}: its curvatures do not hold there (pass a law made at "
                             f"{float(stretch):g}, or --stretch {law.stretch:g})")


def format_thickness_law(rows, provenance_lines) -> str:
    """CSV text of a law: ``provenance_lines`` as ``#`` comments, then the header and
    ``rows`` (thickness_mm, spacing_mm, side, kappa_per_mm[, extra...])."""
    out = [f"# {ln}" for ln in provenance_lines]
    out.append(",".join(COLUMNS))
    for r in rows:
        out.append(f"{r[0]:.4g},{r[1]:.6g},{r[2]},{r[3]:.6g}")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- evaluation
def _spacing_weights(tab: SideTable, spacing):
    """Cell index j and weight w in [0, 1] along the spacing axis, clamped; and a clamped mask."""
    mu = np.asarray(spacing, dtype=float)
    clamped = (mu < tab.spacing[0]) | (mu > tab.spacing[-1])
    muc = np.clip(mu, tab.spacing[0], tab.spacing[-1])
    j = np.clip(np.searchsorted(tab.spacing, muc, side="right") - 1, 0, len(tab.spacing) - 2)
    w = (muc - tab.spacing[j]) / (tab.spacing[j + 1] - tab.spacing[j])
    return j, w, clamped


def _columns(tab: SideTable, spacing):
    """kappa at every grid thickness for each query spacing: (q, nt), plus the clamp mask."""
    j, w, clamped = _spacing_weights(tab, spacing)
    return (1 - w)[..., None] * tab.kappa[:, j].T + w[..., None] * tab.kappa[:, j + 1].T, clamped


def curvature(law: ThicknessLaw, thickness_mm, spacing_mm, side: str) -> np.ndarray:
    """kappa (1/mm) by bilinear interpolation in (thickness, spacing); thickness must lie in the
    table's range, spacing is clamped to it. Arrays broadcast."""
    tab = law.table(side)
    t, mu = np.broadcast_arrays(np.asarray(thickness_mm, float), np.asarray(spacing_mm, float))
    if ((t < tab.thickness[0] - 1e-12) | (t > tab.thickness[-1] + 1e-12)).any():
        raise SelfshapeError(f"{law.source}: thickness outside the table's range "
                             f"[{tab.thickness[0]:g}, {tab.thickness[-1]:g}] mm")
    cols, _ = _columns(tab, mu.ravel())
    tt = np.clip(t.ravel(), tab.thickness[0], tab.thickness[-1])
    i = np.clip(np.searchsorted(tab.thickness, tt, side="right") - 1, 0, len(tab.thickness) - 2)
    u = (tt - tab.thickness[i]) / (tab.thickness[i + 1] - tab.thickness[i])
    r = np.arange(len(tt))
    return ((1 - u) * cols[r, i] + u * cols[r, i + 1]).reshape(t.shape)


def printable_range(tab: SideTable, layer_height_mm: float) -> tuple[float, float]:
    """The table's thickness range shrunk to layer-height multiples (mm)."""
    h = float(layer_height_mm)
    lo = max(np.ceil(tab.thickness[0] / h - 1e-9), 1.0) * h
    hi = np.floor(tab.thickness[-1] / h + 1e-9) * h
    return float(lo), float(hi)


def thickness_for_curvature(law: ThicknessLaw, kappa, spacing_mm, side: str, layer_height_mm: float = 0.2,
                            quantize: bool = True):
    """Thickness (mm) whose interpolated curvature at ``spacing_mm`` is |kappa| (1/mm).

    The inverse is exact on the bilinear interpolant (piecewise linear in thickness at a fixed
    spacing). Targets outside the achievable range at that spacing get the end thickness
    (clamped); with ``quantize`` the result is rounded to the nearest multiple of
    ``layer_height_mm`` inside the printable range (`printable_range`). Returns (thickness
    array, info) with info counts: n, clamped_low (wanted less curvature than the law gives),
    clamped_high (wanted more), spacing_clamped, and the printable range."""
    tab = law.table(side)
    k = np.abs(np.asarray(kappa, dtype=float))
    mu = np.broadcast_to(np.asarray(spacing_mm, dtype=float), k.shape)
    if not np.isfinite(k).all() or not np.isfinite(mu).all():
        raise SelfshapeError("thickness_for_curvature: kappa and spacing must be finite")
    if layer_height_mm is None or not layer_height_mm > 0:
        raise SelfshapeError(f"thickness_for_curvature: layer height must be > 0, got {layer_height_mm}")
    cols, sclamp = _columns(tab, mu.ravel())       # (q, nt), monotone along axis 1
    kq = k.ravel()
    if not tab.increasing:
        cols, T = cols[:, ::-1], tab.thickness[::-1]
    else:
        T = tab.thickness
    low = kq < cols[:, 0]
    high = kq > cols[:, -1]
    kc = np.clip(kq, cols[:, 0], cols[:, -1])
    # first grid interval whose upper value reaches the target
    i = np.clip((cols < kc[:, None]).sum(axis=1) - 1, 0, cols.shape[1] - 2)
    r = np.arange(len(kq))
    a, b = cols[r, i], cols[r, i + 1]
    u = np.where(b > a, (kc - a) / np.where(b > a, b - a, 1.0), 0.0)
    t = T[i] + u * (T[i + 1] - T[i])
    lo, hi = printable_range(tab, layer_height_mm)
    if quantize:
        if hi < lo:
            raise SelfshapeError(f"{law.source}: side {side}: no multiple of the layer height "
                                 f"{layer_height_mm:g} mm within the table's thickness range")
        t = np.clip(np.round(t / layer_height_mm) * layer_height_mm, lo, hi)
    info = {"n": int(len(kq)), "clamped_low": int(low.sum()), "clamped_high": int(high.sum()),
            "spacing_clamped": int(sclamp.sum()), "printable_range_mm": [lo, hi],
            "layer_height_mm": float(layer_height_mm)}
    return t.reshape(k.shape), info


def curvature_reach(law: ThicknessLaw, kappa, spacing_mm, side, length_mm, layer_height_mm: float,
                    diagonal_mm: float | None = None, min_diagonal_mm: float = 0.0) -> dict:
    """How much of the curvature a design asks for the law can give, per side (1/mm, mm).

    kappa, spacing_mm, side, length_mm: per ribbon, the asked |curvature| along it, its spacing
    mu2, its side and its length (the weight). For each side: the length-weighted 10/50/90 %
    quantiles of the asked curvature, the law's printable range [kappa at the thickest, at the
    thinnest printable layer multiple] at the side's median spacing, and the fractions of ribbon
    length asking for less than the law's lowest (curls too much) or more than its highest
    curvature, and ``log_excess``, the length-weighted mean of |ln(asked / nearest reachable)|
    (0 when all is in range; 0.69 = a factor 2 off on average), which ranks laws for a target. The asked curvature of a target scales as 1 / size, so with ``diagonal_mm`` (the
    target's bounding-box diagonal) ``diagonal_in_range_mm`` is the range of diagonals at which
    the median asked curvature of every side lies inside the law's range, cut below at
    ``min_diagonal_mm`` (a pattern needs room for several ribbon periods for the law's
    parallel-ribbon behaviour to hold); None if no such size."""
    kappa, spacing_mm, length_mm = (np.asarray(v, float) for v in (kappa, spacing_mm, length_mm))
    side = np.asarray(side)
    out, lo_d, hi_d = {}, 0.0, np.inf
    for s in SIDES:
        m = side == s
        if not m.any() or s not in law.sides:
            continue
        k, w = np.abs(kappa[m]), length_mm[m]
        q = {f"p{int(p * 100)}": weighted_quantile(k, w, p) for p in (0.1, 0.5, 0.9)}
        mu_med = float(np.median(spacing_mm[m]))
        tab = law.table(s)
        t_lo, t_hi = printable_range(tab, layer_height_mm)
        k_ends = curvature(law, [t_lo, t_hi], [mu_med, mu_med], s)
        k_min, k_max = float(k_ends.min()), float(k_ends.max())
        kk = np.maximum(k, 1e-6)
        excess = float(np.sum(w * np.abs(np.log(kk / np.clip(kk, k_min, k_max)))) / w.sum())
        below = float(w[k < k_min].sum() / w.sum())
        above = float(w[k > k_max].sum() / w.sum())
        out[s] = {"asked_per_mm": q, "law_range_per_mm": [k_min, k_max], "at_spacing_mm": mu_med,
                  "printable_thickness_mm": [t_lo, t_hi], "length_below_range": round(below, 4),
                  "length_above_range": round(above, 4), "log_excess": round(excess, 4),
                  "law_thickness_mm": [float(tab.thickness.min()), float(tab.thickness.max())]}
        if diagonal_mm is not None and q["p50"] > 0:
            lo_d = max(lo_d, diagonal_mm * q["p50"] / k_max)
            hi_d = min(hi_d, diagonal_mm * q["p50"] / k_min) if k_min > 0 else hi_d
    if diagonal_mm is not None and out:
        out["diagonal_mm"] = float(diagonal_mm)
        lo_d = max(lo_d, float(min_diagonal_mm))
        out["diagonal_in_range_mm"] = [float(lo_d), float(hi_d)] if lo_d <= hi_d and np.isfinite(hi_d) else None
    return out


TWIST_SHARE = 0.25     # bend_share below which the ribbons are taken to follow twist directions


def along_twist(bend_share: float | None) -> bool:
    """The ribbons follow directions the target hardly bends along: a design's ``bend_share``
    (inverse.design.bend_share) below TWIST_SHARE (False when it was not measured)."""
    return bend_share is not None and bend_share < TWIST_SHARE


def reach_warning(reach: dict, threshold: float = 0.5) -> str | None:
    """One sentence when more than ``threshold`` of a side's ribbon length asks for curvature
    outside the law's range (the deployed shape then curls more, or less, than the target), with
    the size at which it would not; None otherwise. Where the ribbons follow directions along
    which the target hardly bends (``reach["bend_share"]``, :func:`along_twist`: the asymptotic
    directions of a minimal surface, where it twists instead) the asked curvature is near zero
    by construction and says nothing about the deployment; the sentence says so instead of
    predicting a curl."""
    share = reach.get("bend_share")
    if along_twist(share):
        return (f"the ribbons run where the target hardly bends ({100 * share:.0f} % of its largest principal "
                f"curvature, e.g. the asymptotic directions of a minimal surface, where it twists instead): "
                f"the thickness law's bending range does not predict this deployment; check it with --verify")
    parts = []
    for s in SIDES:
        r = reach.get(s)
        if not r:
            continue
        lo, hi = r["law_range_per_mm"]
        if r["length_below_range"] > threshold:
            parts.append(f"{s}: {100 * r['length_below_range']:.0f} % of the ribbon length asks for less curvature "
                         f"(median {r['asked_per_mm']['p50']:.3g} 1/mm) than the law's lowest {lo:.3g} 1/mm, "
                         f"so it will curl more than the target")
        elif r["length_above_range"] > threshold:
            parts.append(f"{s}: {100 * r['length_above_range']:.0f} % of the ribbon length asks for more curvature "
                         f"(median {r['asked_per_mm']['p50']:.3g} 1/mm) than the law's highest {hi:.3g} 1/mm")
    if not parts:
        return None
    # the law has a thicker row than the printer's layers can print (e.g. 0.5 mm with 0.2 mm layers)
    thicker = [r for s in SIDES if (r := reach.get(s)) and r["length_below_range"] > threshold
               and r.get("law_thickness_mm") and r["law_thickness_mm"][1] > r["printable_thickness_mm"][1] + 1e-9]
    if thicker:
        t = max(r["law_thickness_mm"][1] for r in thicker)
        parts.append(f"the law's {t:g} mm row is not a multiple of the printer's layers: a printer file with finer "
                     f"layers (--printer, e.g. inverse/data/printers/layer_0.1mm.toml) reaches lower curvature")
    rng = reach.get("diagonal_in_range_mm")
    if rng:
        hint = f"; at a diagonal of {rng[0]:.0f}-{rng[1]:.0f} mm (--diagonal) it would be in range"
    else:
        hint = ("; no size of this target is in range with these ribbons: a law that reaches it is needed "
                "(another --stretch, or --law for a softer plastic)")
    return "; ".join(parts) + hint
