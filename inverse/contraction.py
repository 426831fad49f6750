"""Contraction models: the row spacing (mu1 along, mu2 across, printed mm) of a staggered
dashed-ribbon pattern that deploys with the homogenised stretch (sigma1 along, sigma2 across
the ribbons; printed / deployed length), and the stretch bounds that spacing can realise.

Two models with one interface (``stretch_at``, ``spacing``, ``bounds``):

* :class:`SeedContraction`: the seed's Eq. 5.15 (inverse.spacing), each direction on its own:
  a motif contracts as one dash plus a bare gap in series. Simulated patches contract more
  than that across the ribbons (only l_r / mu1 of the lines across meet a dash) and along them
  depend on mu2 as much as on mu1, so a flattening within Eq. 5.15's bounds deploys with
  another metric than it asked for.
* :class:`TableContraction`: sigma1(mu1, mu2) and sigma2(mu1, mu2) measured on simulated
  patches (studies/ribbon_contraction.py: the intrinsic printed / deployed length over the
  patch's central quarter) at one pre-stretch and ribbon size, read from a CSV table. Each
  stretch is fitted by least squares as a quadratic in (ln mu1, ln mu2) of the logit of the
  fraction of the bare fabric's contraction it realises, f = (1 - 1/sigma) / (1 - 1/s) (the
  stretch saturates towards s at sparse spacings); the fit smooths the patches' scatter
  (multistable oblique modes) and is inverted by Gauss-Newton in (ln mu1, ln mu2) on the
  table's spacing box. The fit must increase in both spacings over the
  box (more bare fabric contracts more), else the table is refused.

Shipped tables (``inverse/data/contraction_s<s>.csv``, used by `design` by default at their
stretch) and measured ones kept for comparison (``contraction_measured_s<s>.csv``, given by
path). Table format (like the curvature law): ``#`` provenance
lines, of which ``# fabric_stretch = s``, ``# ribbon_length_mm = l``, ``# ribbon_width_mm = w``
and ``# thickness_mm = t`` are read, then the header ``mu1_mm, mu2_mm, sigma1, sigma2`` (extra
columns ignored) and at least 8 rows spanning at least 2 values of each spacing.

Bounds (`bounds`): Eq. 5.15's box (geometry.flattening.stretch_bounds) for both models, the
table only choosing the spacings; with ``polygon_bounds`` a table's are the admissible
(sigma1, sigma2) pairs as a polygon (`polygon`), the image of the spacing box's boundary under
the fit. Its stretches move together (a wider row spacing contracts more along
the ribbons too), so no box of useful size lies inside the set; the bounded flattening projects
each face's stretches onto the polygon (geometry.flattening.project_stretches).
"""
from __future__ import annotations

import csv
import io
import os
import re
from dataclasses import dataclass, field

import numpy as np

from geometry.schema import PATTERN_NUMBERS, Num, number
from shellfem.errors import SelfshapeError
from shellfem.infiles import csv_error_text, read_input_text

DATA_DIR = os.path.join(os.path.dirname(__file__), "data")
COLUMNS = ("mu1_mm", "mu2_mm", "sigma1", "sigma2")
_SHIPPED = re.compile(r"^contraction_s(\d+(?:\.\d+)?)\.csv$")
_KEYS = {"fabric_stretch": "stretch", "ribbon_length_mm": "ribbon_length", "ribbon_width_mm": "ribbon_width",
         "thickness_mm": "thickness"}
#: Ranges of the table's '# key = value' lines (geometry.schema): a table is data from anyone.
_META_NUMBERS = {
    "fabric_stretch": Num(1.0, PATTERN_NUMBERS["fabric"]["stretch"].hi, "", "a pre-stretch > 1 (the fabric's range)",
                          lo_open=True),
    "ribbon_length_mm": Num(1.0, 1000.0, "mm", "a dash of 1 mm to 1 m"),
    "ribbon_width_mm": PATTERN_NUMBERS["ribbon"]["width_mm"],
    "thickness_mm": PATTERN_NUMBERS["ribbon"]["thickness_mm"],
}
#: Largest dash period or row spacing of a table row (mm): 1 m.
MAX_SPACING_MM = 1000.0


def _basis(x, y):
    """Quadratic basis in (x, y) = (ln mu1, ln mu2): (..., 6) and its x / y derivatives."""
    one, zero = np.ones_like(x), np.zeros_like(x)
    B = np.stack([one, x, y, x * x, x * y, y * y], -1)
    Bx = np.stack([zero, one, zero, 2 * x, y, zero], -1)
    By = np.stack([zero, zero, one, zero, x, 2 * y], -1)
    return B, Bx, By


@dataclass
class SeedContraction:
    """The seed's Eq. 5.15 (inverse.spacing): mm, dimensionless stretches."""
    stretch: float
    ribbon_length: float = 15.0
    ribbon_width: float = 1.5
    name: str = "seed Eq. 5.15"

    def stretch_at(self, mu1, mu2):
        from inverse.spacing import stretch_from_spacing
        return stretch_from_spacing(mu1, mu2, self.stretch, self.ribbon_length, self.ribbon_width)

    def spacing(self, sigma1, sigma2):
        """(mu1, mu2, realised): Eq. 5.15 realises every 1 <= sigma < s."""
        from inverse.spacing import ribbon_spacing
        mu1, mu2 = ribbon_spacing(sigma1, sigma2, self.stretch, self.ribbon_length, self.ribbon_width)
        return mu1, mu2, np.ones(np.shape(mu1), bool)

    def bounds(self):
        from geometry.flattening import stretch_bounds
        return stretch_bounds(self.stretch, self.ribbon_length, self.ribbon_width)

    def describe(self) -> dict:
        return {"model": self.name, "stretch": self.stretch, "bounds": [round(b, 4) for b in self.bounds()]}


@dataclass
class TableContraction:
    """sigma1, sigma2 (mu1, mu2) fitted to simulated patches at one stretch (see the module).
    coef: (2, 6) quadratic coefficients in (ln mu1, ln mu2) of logit f (see the module); mu1_range, mu2_range: the table's
    spacing box (mm); rms: the fit's residual per output; source: the table file."""
    stretch: float
    ribbon_length: float
    ribbon_width: float
    thickness: float | None
    coef: np.ndarray
    mu1_range: tuple
    mu2_range: tuple
    rms: tuple
    source: str = "<table>"
    provenance: list = field(default_factory=list)
    name: str = "simulated patches"
    polygon_bounds: bool = False     # bounds(): the admissible polygon instead of Eq. 5.15's box

    def _eval(self, x, y):
        """Fitted (sigma1, sigma2) (..., 2) at (x, y) = (ln mu1, ln mu2) and d sigma / d(x, y)
        (..., 2, 2)."""
        B, Bx, By = _basis(x, y)
        g = B @ self.coef.T                                   # (..., 2) logit of the fraction f
        gx, gy = Bx @ self.coef.T, By @ self.coef.T
        f = 1.0 / (1.0 + np.exp(-g))
        c = 1.0 - 1.0 / self.stretch
        S = 1.0 / (1.0 - c * f)
        dS = c * S * S * f * (1.0 - f)                        # d sigma / d g
        return S, np.stack([dS * gx, dS * gy], -1)

    def stretch_at(self, mu1, mu2):
        """(sigma1, sigma2) of the fit at spacings (mm; clamped to the table's box)."""
        x = np.log(np.clip(np.asarray(mu1, float), *self.mu1_range))
        y = np.log(np.clip(np.asarray(mu2, float), *self.mu2_range))
        S = self._eval(x, y)[0]
        return S[..., 0], S[..., 1]

    def spacing(self, sigma1, sigma2, tol: float = 1e-4):
        """(mu1, mu2, realised) per entry: the spacing box point whose fitted stretch is nearest
        (sigma1, sigma2) (grid start, then projected Levenberg-Marquardt in ln mu); realised
        where it is within ``tol``."""
        s1 = np.asarray(sigma1, float)
        s2 = np.asarray(sigma2, float)
        shape = np.broadcast(s1, s2).shape
        s1, s2 = np.broadcast_to(s1, shape).ravel(), np.broadcast_to(s2, shape).ravel()
        if not (np.isfinite(s1).all() and np.isfinite(s2).all()):
            raise SelfshapeError(f"contraction {self.source}: the asked stretch is not finite")
        lo = np.log([self.mu1_range[0], self.mu2_range[0]])
        hi = np.log([self.mu1_range[1], self.mu2_range[1]])
        want = np.column_stack([s1, s2])
        # start: the best of a coarse grid of the box (the fit is smooth but its Jacobian nearly
        # singular along the band), then Levenberg-Marquardt steps kept only where they lower
        # the residual, projected onto the box
        g1, g2 = np.meshgrid(np.linspace(lo[0], hi[0], 9), np.linspace(lo[1], hi[1], 9), indexing="ij")
        grid = np.column_stack([g1.ravel(), g2.ravel()])
        Sg = self._eval(grid[:, 0], grid[:, 1])[0]
        best = np.empty(len(s1), dtype=int)
        for a in range(0, len(s1), 20000):                  # bounded memory: chunks of 20k x 81
            d2 = ((want[a:a + 20000, None, :] - Sg[None]) ** 2).sum(-1)
            best[a:a + 20000] = np.argmin(d2, axis=1)
        z = grid[best].copy()
        lam = np.full(len(s1), 1e-6)
        S, J = self._eval(z[:, 0], z[:, 1])
        cost = ((S - want) ** 2).sum(1)
        for _ in range(200):
            r = S - want
            JtJ = np.einsum("nki,nkj->nij", J, J)
            g = np.einsum("nki,nk->ni", J, r)
            D = JtJ + (lam * (np.trace(JtJ, axis1=1, axis2=2) + 1e-12))[:, None, None] * np.eye(2)
            dz = -np.linalg.solve(D, g[..., None])[..., 0]
            zt = np.clip(z + dz, lo, hi)
            St, Jt = self._eval(zt[:, 0], zt[:, 1])
            ct = ((St - want) ** 2).sum(1)
            ok = ct < cost
            z[ok], S[ok], J[ok], cost[ok] = zt[ok], St[ok], Jt[ok], ct[ok]
            lam = np.where(ok, lam * 0.3, lam * 10.0)
            if np.all((ok & (np.abs(dz).max(1) < 1e-12)) | (lam > 1e8) | (cost < 1e-24)):
                break
        mu = np.exp(z)
        return mu[:, 0].reshape(shape), mu[:, 1].reshape(shape), (np.sqrt(cost) <= tol).reshape(shape)

    def bounds(self, n: int = 8):
        """The flattening's bounds: Eq. 5.15's box (geometry.flattening.stretch_bounds), or with
        ``polygon_bounds`` the admissible stretches as a polygon ((4 n, 2); see the module)."""
        if not self.polygon_bounds:
            from geometry.flattening import stretch_bounds
            return stretch_bounds(self.stretch, self.ribbon_length, self.ribbon_width)
        return self.polygon(n)

    def polygon(self, n: int = 8):
        """The admissible (sigma1, sigma2): the fit on the spacing box's boundary, n samples per side."""
        return _image_polygon(self, n)

    def describe(self) -> dict:
        return {"model": self.name, "table": os.path.basename(self.source), "stretch": self.stretch,
                "thickness_mm": self.thickness, "mu1_range_mm": list(self.mu1_range),
                "mu2_range_mm": list(self.mu2_range), "fit_rms": [round(r, 5) for r in self.rms],
                "bounds": "admissible polygon" if self.polygon_bounds else "seed Eq. 5.15 box",
                "polygon": np.round(self.polygon(), 4).tolist()}


def _image_polygon(model: "TableContraction", n: int):
    """The fitted stretches on the spacing box's boundary, n samples per side, in order: the
    boundary of the admissible (sigma1, sigma2) set (the fit is smooth and one-to-one on the
    box, so the image of its boundary bounds the image of the box)."""
    g = np.linspace(0.0, 1.0, n, endpoint=False)
    l1, l2 = np.log(model.mu1_range), np.log(model.mu2_range)
    x = np.r_[l1[0] + g * (l1[1] - l1[0]), np.full(n, l1[1]), l1[1] - g * (l1[1] - l1[0]), np.full(n, l1[0])]
    y = np.r_[np.full(n, l2[0]), l2[0] + g * (l2[1] - l2[0]), np.full(n, l2[1]), l2[1] - g * (l2[1] - l2[0])]
    from geometry.flattening import polygon_area
    P = np.column_stack(model.stretch_at(np.exp(x), np.exp(y)))
    if not abs(polygon_area(P)) > 1e-12:
        raise SelfshapeError(f"contraction {model.source}: the table realises no range of stretches "
                             "(sigma1 and sigma2 move together over its whole spacing box)")
    return P


def parse_contraction(text: str, source: str = "<table>") -> TableContraction:
    """A TableContraction from the CSV text (format in the module docstring)."""
    prov, body, meta = [], [], {}
    for line in text.splitlines():
        if line.startswith("#"):
            c = line[1:].strip()
            prov.append(c)
            m = re.match(r"^(\w+)\s*=\s*(\S+)\s*$", c)
            if m and m.group(1) in _KEYS:
                try:
                    v = float(m.group(2))
                except ValueError:
                    raise SelfshapeError(f"{source}: '# {c}' is not a number") from None
                meta[_KEYS[m.group(1)]] = number(v, f"{source}: {m.group(1)}", _META_NUMBERS[m.group(1)])
        elif line.strip():
            body.append(line)
    for key in ("fabric_stretch", "ribbon_length_mm", "ribbon_width_mm"):
        if _KEYS[key] not in meta:
            raise SelfshapeError(f"{source}: a '# {key} = ...' line is required")
    if not meta["stretch"] > 1 or not np.isfinite(meta["stretch"]):
        raise SelfshapeError(f"{source}: fabric_stretch = {meta['stretch']} must be a finite number > 1")
    reader = csv.DictReader(io.StringIO("\n".join(body)))
    try:
        fieldnames = reader.fieldnames or []
        missing = [c for c in COLUMNS if c not in fieldnames]
        if missing:
            raise SelfshapeError(f"{source}: missing column(s) {', '.join(missing)} (need {', '.join(COLUMNS)})")
        records = list(reader)
    except csv.Error as e:               # a field over the csv module's limit, a NUL byte
        raise SelfshapeError(f"{source}: data row {reader.line_num}: {csv_error_text(e)}") from None
    rows = []
    for i, r in enumerate(records, start=2):
        try:
            v = [float(r[c]) for c in COLUMNS]
        except (TypeError, ValueError):
            raise SelfshapeError(f"{source}: data row {i}: {', '.join(COLUMNS)} must be numbers") from None
        if not all(np.isfinite(v)) or not meta["ribbon_length"] <= v[0] <= MAX_SPACING_MM \
                or not meta["ribbon_width"] <= v[1] <= MAX_SPACING_MM \
                or not (1.0 <= v[2] < meta["stretch"] * 1.1 and 1.0 <= v[3] < meta["stretch"] * 1.1):
            raise SelfshapeError(f"{source}: data row {i}: spacings must be >= the ribbon length / width and "
                                 f"<= {MAX_SPACING_MM:g} mm and stretches in [1, ~s), got {v}")
        rows.append(v)
    a = np.array(rows) if rows else np.zeros((0, 4))
    if len(a) < 8 or len(np.unique(a[:, 0])) < 2 or len(np.unique(a[:, 1])) < 2:
        raise SelfshapeError(f"{source}: needs at least 8 rows over at least 2 values of each spacing")
    x, y = np.log(a[:, 0]), np.log(a[:, 1])
    B = _basis(x, y)[0]
    # fitted in the logit of the fraction of the bare fabric's contraction realised,
    # f = (1 - 1 / sigma) / (1 - 1 / s): the stretch saturates towards s at sparse spacings
    c = 1.0 - 1.0 / meta["stretch"]
    f = np.clip((1.0 - 1.0 / a[:, 2:4]) / c, 1e-3, 1.0 - 1e-3)
    coef = np.linalg.lstsq(B, np.log(f / (1.0 - f)), rcond=None)[0].T
    model = TableContraction(stretch=meta["stretch"], ribbon_length=meta["ribbon_length"],
                             ribbon_width=meta["ribbon_width"], thickness=meta.get("thickness"),
                             coef=np.asarray(coef), mu1_range=(float(a[:, 0].min()), float(a[:, 0].max())),
                             mu2_range=(float(a[:, 1].min()), float(a[:, 1].max())), rms=(0.0, 0.0),
                             source=source, provenance=prov)
    S = model._eval(x, y)[0]
    model.rms = tuple(float(np.sqrt(np.mean((S[:, k] - a[:, 2 + k]) ** 2))) for k in (0, 1))
    # monotone over the box: more bare fabric (wider spacing) never contracts less
    g = np.linspace(0, 1, 25)
    x = np.log(model.mu1_range[0]) + g * np.log(model.mu1_range[1] / model.mu1_range[0])
    y = np.log(model.mu2_range[0]) + g * np.log(model.mu2_range[1] / model.mu2_range[0])
    X, Y = np.meshgrid(x, y, indexing="ij")
    J = model._eval(X, Y)[1]
    for k, name in ((0, "sigma1"), (1, "sigma2")):
        if J[..., k, 0].min() < -1e-9 or J[..., k, 1].min() < -1e-9:
            raise SelfshapeError(f"{source}: the fit of {name} decreases with a spacing somewhere in the table's "
                                 "box; add patches or narrow the box")
    return model


def load_contraction(path) -> TableContraction:
    """Read a contraction table CSV (one-line error naming the file)."""
    return parse_contraction(read_input_text(path, "contraction table (CSV)", str(path)), str(path))


def shipped_contractions() -> dict:
    """{stretch: path} of the tables in inverse/data (contraction_s<s>.csv)."""
    from inverse.thickness_law import files_by_stretch
    return files_by_stretch(DATA_DIR, _SHIPPED)


def shipped_table(stretch: float, ribbon_length: float = 15.0, ribbon_width: float = 1.5):
    """The shipped TableContraction made at this stretch and ribbon size, or None."""
    path = next((p for s, p in shipped_contractions().items() if abs(s - stretch) < 1e-9), None)
    if path is None:
        return None
    m = load_contraction(path)
    if abs(m.ribbon_length - ribbon_length) > 1e-9 or abs(m.ribbon_width - ribbon_width) > 1e-9:
        return None
    return m


def contraction_for(stretch: float, ribbon_length: float = 15.0, ribbon_width: float = 1.5, model="auto"):
    """The contraction model of a design: ``model`` "auto" (the shipped table at this stretch and
    ribbon size for the spacings, with Eq. 5.15's bounds; Eq. 5.15 where there is none), "seed"
    (Eq. 5.15), "table" (the shipped table; a one-line error if there is none), "table-polygon"
    (the same with the table's admissible polygon as the flattening's bounds), a table path (or
    "PATH:polygon"), or a model object."""
    if isinstance(model, (SeedContraction, TableContraction)):
        m = model
    elif model == "seed":
        return SeedContraction(stretch, ribbon_length, ribbon_width)
    elif model == "auto":
        m = shipped_table(stretch, ribbon_length, ribbon_width)
        return SeedContraction(stretch, ribbon_length, ribbon_width) if m is None else m
    elif model in ("table", "table-polygon"):
        m = shipped_table(stretch, ribbon_length, ribbon_width)
        if m is None:
            have = ", ".join(f"{s:g}" for s in shipped_contractions()) or "none"
            raise SelfshapeError(f"contraction: no shipped table at fabric stretch {stretch:g} for {ribbon_length:g} x "
                                 f"{ribbon_width:g} mm ribbons (tables at stretch {have}); give a table file or 'seed'")
        m.polygon_bounds = model == "table-polygon"
        return m
    else:
        path, polygon = str(model), False
        if path.endswith(":polygon"):
            path, polygon = path[: -len(":polygon")], True
        m = load_contraction(path)
        m.polygon_bounds = polygon
    if abs(m.stretch - stretch) > 1e-9:
        raise SelfshapeError(f"{m.source}: the contraction table is made at fabric stretch {m.stretch:g}, "
                             f"the design is at {stretch:g}")
    if abs(m.ribbon_length - ribbon_length) > 1e-9 or abs(m.ribbon_width - ribbon_width) > 1e-9:
        raise SelfshapeError(f"{m.source}: the contraction table is made for {m.ribbon_length:g} x "
                             f"{m.ribbon_width:g} mm ribbons, the design has {ribbon_length:g} x {ribbon_width:g}")
    return m


def realisation_check(table: TableContraction, sigma1, sigma2, area, mu1=None, mu2=None, tol: float = 0.01) -> dict:
    """How far the stretches a layout asks for (sigma1, sigma2 per face) are from what its
    spacings (mu1, mu2 per face, mm; None: the table's own nearest spacings) realise by the
    simulated table: area-weighted median and 90th percentile of |realised - asked| per
    direction, the area fraction (%) whose asked pair lies within ``tol`` of the table's
    realisable set, and the table's file."""
    from inverse.thickness_law import weighted_quantile
    w = np.asarray(area, float)
    w = w / w.sum()
    t1, t2, ok = table.spacing(sigma1, sigma2, tol=tol)
    r1, r2 = table.stretch_at(t1 if mu1 is None else mu1, t2 if mu2 is None else mu2)
    e1, e2 = np.abs(r1 - sigma1), np.abs(r2 - sigma2)
    wq = lambda x, q: weighted_quantile(x, w, q)  # noqa: E731
    return {"table": os.path.basename(table.source), "realisable_area_pct": round(100.0 * float(w[ok].sum()), 2),
            "sigma1_error_median_p90": [round(wq(e1, 0.5), 4), round(wq(e1, 0.9), 4)],
            "sigma2_error_median_p90": [round(wq(e2, 0.5), 4), round(wq(e2, 0.9), 4)],
            "realised_minus_asked_mean": [round(float(w @ (r1 - sigma1)), 4), round(float(w @ (r2 - sigma2)), 4)]}


def format_contraction(rows, provenance_lines) -> str:
    """CSV text of a table: rows of (mu1_mm, mu2_mm, sigma1, sigma2)."""
    out = [f"# {line}" for line in provenance_lines] + [",".join(COLUMNS)]
    out += [f"{r[0]:g},{r[1]:g},{r[2]:.5f},{r[3]:.5f}" for r in rows]
    return "\n".join(out) + "\n"
