"""Calibration of the fabric model from its tensile, shear and cantilever tests (seed 4.3-4.4).

Units: mm, N, MPa; strains are Green strains (dimensionless).

Model (the engine's convention): Voigt Green strain eps = (e11, e22, 2 e12) in the course
frame, Psi = 1/2 eps^T C eps / (1 - nu^2) - phi1(e11) - phi2(e22),
C = [[a1, sqrt(a1 a2) nu, 0], [sqrt(a1 a2) nu, a2, 0], [0, 0, a3 (1 - nu^2)]], with the
symmetric log barrier phi_i of Eq. 4.3, whose derivative is phi_i'(e) = sign(e) b_i log(1 - |e|/g_i).
So the stress is sigma = C eps / (1 - nu^2) + (-sign(e_i) b_i log(1 - |e_i| / g_i)), Eq. 4.5.

Pipeline (``calibrate_fabric``):
- tensile files -> unloading branch of the stabilised cycles -> Green strain / 2nd Piola-Kirchhoff
  stress (Eq. 4.4) -> the seed's route: fit sigma = A e - b log(1 - e/g) (Eq. 4.6-4.7) on 0 and
  90 deg -> b1, g1, b2, g2 and a1, a2 from A1 = (a1 - sqrt(a1 a2) nu^2)/(1 - nu^2), A2 likewise
  ("orthotropic_seed_eq46"); then, from there, the model-consistent fit in which the model's own
  uniaxial-stress response matches the 0 and 90 deg curves ("orthotropic", what the engine uses);
- release (pseudo-Young) modulus: slope of each orientation's unloading curve at release,
  averaged over orientations, per max stretch;
- a3: initial slope of shear stress vs shear strain, averaged over 0 and 90 deg;
- k_B per orientation/face: least squares on the heavy-elastica master curve;
- validation: the fitted model's uniaxial-stress response at every orientation (strain
  rotated into the course frame, transverse strain and shear solved so that the lateral
  and shear stresses vanish) against the measured unloading curves.
"""
from __future__ import annotations

import csv
import json
import math
import os
import re

import numpy as np
from scipy.optimize import least_squares

from shellfem.errors import SelfshapeError
from shellfem.materials.orthotropic import orthotropic_stress
from validation import elastica
from validation.plots import Series, plot_series

DEFAULT_POISSON = 0.3  # seed 4.3: measured from videos of a uniaxial test
PARAM_NAMES = ("a1", "a2", "a3", "b1", "b2", "g1", "g2")

TENSILE_COLUMNS = {"time_s": "float", "cycle": "int", "branch": ("load", "unload"),
                   "extension_mm": "float", "load_N": "float"}
SHEAR_COLUMNS = {"lateral_displacement_mm": "float", "lateral_load_N": "float"}
CANTILEVER_COLUMNS = {"orientation_deg": "float", "face_up": ("front", "back"), "free_length_mm": "float",
                      "areal_weight_N_per_mm2": "float", "height_over_width": "float"}
META_KEYS = ("fabric_thickness_mm", "tensile_width_mm", "tensile_gauge_length_mm", "shear_sample_side_mm")

_TENSILE_RE = re.compile(r"^tensile_(\d+(?:\.\d+)?)deg_(\d+(?:\.\d+)?)pct\.csv$")
_SHEAR_RE = re.compile(r"^shear_(\d+(?:\.\d+)?)deg\.csv$")


# ----------------------------------------------------------------------------- reading

def _number_key(x: float) -> str:
    """'0', '15', '45', '37.5': the key of an orientation or stretch percent."""
    return f"{float(x):g}"


def read_table(path: str, columns: dict) -> dict:
    """Read a CSV whose header must be exactly the keys of columns.

    columns maps name -> "float" | "int" | tuple of allowed strings. Returns name -> array.
    Raises SelfshapeError (file, row, column) on a missing/extra/duplicate column, a short
    or long row, an empty or non-numeric cell, a non-finite number, an unknown label, or no rows.
    """
    name = os.path.basename(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = [r for r in csv.reader(f)]
    except OSError as e:
        raise SelfshapeError(f"{path}: cannot read ({e.strerror or e})") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise SelfshapeError(f"{name}: not a readable CSV text file ({e})") from None
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise SelfshapeError(f"{name}: empty file (expected header {','.join(columns)})")
    header = [c.strip() for c in rows[0]]
    dup = sorted({c for c in header if header.count(c) > 1})
    if dup:
        raise SelfshapeError(f"{name}: duplicate column(s) {', '.join(dup)}")
    missing = [c for c in columns if c not in header]
    if missing:
        raise SelfshapeError(f"{name}: missing column(s) {', '.join(missing)}")
    extra = [c for c in header if c not in columns]
    if extra:
        raise SelfshapeError(f"{name}: unexpected column(s) {', '.join(extra)}")
    body = rows[1:]
    if not body:
        raise SelfshapeError(f"{name}: no data rows after the header")
    out = {}
    for j, col in enumerate(header):
        kind = columns[col]
        vals = []
        for i, r in enumerate(body, start=1):
            if len(r) != len(header):
                raise SelfshapeError(f"{name}: row {i}: expected {len(header)} fields, got {len(r)}")
            cell = r[j].strip()
            where = f"{name}: row {i}, column {col}"
            if cell == "":
                raise SelfshapeError(f"{where}: empty cell")
            if isinstance(kind, tuple):
                if cell not in kind:
                    raise SelfshapeError(f"{where}: unknown value {cell!r} (expected one of {', '.join(kind)})")
                vals.append(cell)
                continue
            try:
                v = float(cell)
            except ValueError:
                raise SelfshapeError(f"{where}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise SelfshapeError(f"{where}: {cell!r} is not finite")
            if kind == "int":
                if v != int(v):
                    raise SelfshapeError(f"{where}: {cell!r} is not an integer")
                v = int(v)
            vals.append(v)
        out[col] = np.array(vals, dtype=object if isinstance(kind, tuple) else
                            (np.int64 if kind == "int" else float))
        if isinstance(kind, tuple):
            out[col] = out[col].astype(str)
    return out


def read_meta(folder: str) -> dict:
    """meta.json of a fabric test folder: thickness and sample geometry (mm), all > 0.

    Optional "poisson" overrides the default Poisson's ratio 0.3.
    """
    path = os.path.join(folder, "meta.json")
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except FileNotFoundError:
        raise SelfshapeError(f"{path}: missing (thickness and sample geometry are read from it)") from None
    except json.JSONDecodeError as e:
        raise SelfshapeError(f"{path}: invalid JSON at line {e.lineno}: {e.msg}") from None
    if not isinstance(meta, dict):
        raise SelfshapeError(f"{path}: expected a JSON object")
    out = dict(meta)
    for k in META_KEYS:
        if k not in meta:
            raise SelfshapeError(f"{path}: missing key {k!r}")
        v = meta[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise SelfshapeError(f"{path}: {k} must be a positive number, got {v!r}")
        out[k] = float(v)
    nu = meta.get("poisson", DEFAULT_POISSON)
    if isinstance(nu, bool) or not isinstance(nu, (int, float)) or not (-1.0 < nu < 1.0):
        raise SelfshapeError(f"{path}: poisson must be a number in (-1, 1), got {nu!r}")
    out["poisson"] = float(nu)
    return out


def read_tensile(path: str) -> dict:
    """A tensile_<deg>deg_<pct>pct.csv table (cycles integers >= 1, branch load/unload)."""
    t = read_table(path, TENSILE_COLUMNS)
    bad = np.flatnonzero(t["cycle"] < 1)
    if bad.size:
        raise SelfshapeError(f"{os.path.basename(path)}: row {bad[0] + 1}, column cycle: must be >= 1")
    return t


def read_shear(path: str) -> dict:
    return read_table(path, SHEAR_COLUMNS)


def read_cantilever(path: str) -> dict:
    t = read_table(path, CANTILEVER_COLUMNS)
    name = os.path.basename(path)
    for col in ("free_length_mm", "areal_weight_N_per_mm2", "height_over_width"):
        bad = np.flatnonzero(t[col] <= 0)
        if bad.size:
            raise SelfshapeError(f"{name}: row {bad[0] + 1}, column {col}: must be > 0")
    return t


def find_test_files(folder: str) -> dict:
    """Locate the tests in folder: {"tensile": {pct: {deg: path}}, "shear": {deg: path},
    "cantilever": path}. Other files are ignored; missing kinds raise SelfshapeError."""
    if not os.path.isdir(folder):
        raise SelfshapeError(f"{folder}: not a directory (expected a fabric test folder)")
    tensile, shear = {}, {}
    for fn in sorted(os.listdir(folder)):
        m = _TENSILE_RE.match(fn)
        if m:
            tensile.setdefault(_number_key(m.group(2)), {})[_number_key(m.group(1))] = os.path.join(folder, fn)
            continue
        m = _SHEAR_RE.match(fn)
        if m:
            shear[_number_key(m.group(1))] = os.path.join(folder, fn)
    if not tensile:
        raise SelfshapeError(f"{folder}: no tensile_<deg>deg_<pct>pct.csv files")
    for pct, files in tensile.items():
        for need in ("0", "90"):
            if need not in files:
                raise SelfshapeError(f"{folder}: missing tensile_{int(float(need)):02d}deg_{pct}pct.csv "
                                     f"(the 0 and 90 deg tests define the model at {pct} %)")
    if not shear:
        raise SelfshapeError(f"{folder}: no shear_<deg>deg.csv file")
    cant = os.path.join(folder, "cantilever.csv")
    if not os.path.isfile(cant):
        raise SelfshapeError(f"{folder}: missing cantilever.csv")
    return {"tensile": tensile, "shear": shear, "cantilever": cant}


# ----------------------------------------------------------------------------- tensile

def green_strain(extension_mm, gauge_mm: float) -> np.ndarray:
    """Uniaxial Green strain e = d/L + d^2/(2 L^2) (Eq. 4.4)."""
    r = np.asarray(extension_mm, dtype=float) / gauge_mm
    return r + 0.5 * r * r


def second_pk_stress(load_n, extension_mm, width_mm: float, gauge_mm: float, thickness_mm: float) -> np.ndarray:
    """Uniaxial 2nd Piola-Kirchhoff stress S = f L / (w (d + L)) / thickness, MPa (Eq. 4.4)."""
    d = np.asarray(extension_mm, dtype=float)
    return np.asarray(load_n, dtype=float) * gauge_mm / (width_mm * (d + gauge_mm)) / thickness_mm


def barrier_curve(e, A: float, b: float, g: float) -> np.ndarray:
    """sigma(e) = A e - b log(1 - e/g) for 0 <= e < g (Eq. 4.6-4.7)."""
    return A * e - b * np.log1p(-np.asarray(e, dtype=float) / g)


def _barrier_jacobian(e, A, b, g):
    return np.column_stack([e, -np.log1p(-e / g), -b * e / (g * (g - e))])


def fit_barrier_curve(e, S) -> dict:
    """Least-squares fit of S = A e - b log(1 - e/g) with g > max(e) and b >= 0.

    For fixed g the model is linear in (A, b): g is found on a profile grid first (robust
    to the flat barrier of low stretches), then all three are refined together.
    Returns A, b, g, cov (3x3 from the Jacobian, s^2 = SSR/(n-3)), se, rms, n.
    """
    e = np.asarray(e, dtype=float)
    S = np.asarray(S, dtype=float)
    if e.size < 6:
        raise SelfshapeError(f"fit_barrier_curve: needs at least 6 points, got {e.size}")
    em = float(e.max())
    if em <= 0:
        raise SelfshapeError("fit_barrier_curve: strains must reach above 0")

    def linear_ab(g):
        X = np.column_stack([e, -np.log1p(-e / g)])
        coef, *_ = np.linalg.lstsq(X, S, rcond=None)
        coef[1] = max(coef[1], 0.0)
        r = X @ coef - S
        return coef, float(r @ r)

    gaps = em * np.geomspace(1e-4, 1e2, 121)
    ssr = [linear_ab(em + d)[1] for d in gaps]
    d0 = gaps[int(np.argmin(ssr))]
    (A0, b0), _ = linear_ab(em + d0)
    # unknowns: A, log b, log(g - em): keeps b > 0 and g above the data
    x0 = [A0, np.log(max(b0, 1e-12 * max(abs(S).max(), 1e-12))), np.log(d0)]

    def resid(x):
        return barrier_curve(e, x[0], np.exp(x[1]), em + np.exp(x[2])) - S

    def jac(x):
        b, d = np.exp(x[1]), np.exp(x[2])
        J = _barrier_jacobian(e, x[0], b, em + d)
        return np.column_stack([J[:, 0], J[:, 1] * b, J[:, 2] * d])

    sol = least_squares(resid, x0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    A, b, g = sol.x[0], float(np.exp(sol.x[1])), em + float(np.exp(sol.x[2]))
    r = barrier_curve(e, A, b, g) - S
    J = _barrier_jacobian(e, A, b, g)
    dof = max(e.size - 3, 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    return {"A": float(A), "b": b, "g": g, "cov": cov, "se": np.sqrt(np.clip(np.diag(cov), 0, None)),
            "rms": float(np.sqrt(np.mean(r * r))), "n": int(e.size), "e_max": em}


def release_tangent(fit: dict, e_release: float | None = None) -> tuple[float, float]:
    """Slope dS/de of a fitted unloading curve at release (default: its largest strain), with SE."""
    e = fit["e_max"] if e_release is None else float(e_release)
    A, b, g = fit["A"], fit["b"], fit["g"]
    grad = np.array([1.0, 1.0 / (g - e), -b / (g - e) ** 2])
    return float(A + b / (g - e)), float(np.sqrt(max(grad @ fit["cov"] @ grad, 0.0)))


def tensile_curve(table: dict, meta: dict, cycles, branch: str = "unload") -> tuple[np.ndarray, np.ndarray]:
    """(Green strain, 2nd PK stress MPa) of the given cycles' branch, in file order."""
    m = np.isin(table["cycle"], list(cycles)) & (table["branch"] == branch)
    d, f = table["extension_mm"][m], table["load_N"][m]
    L = meta["tensile_gauge_length_mm"]
    return green_strain(d, L), second_pk_stress(f, d, meta["tensile_width_mm"], L, meta["fabric_thickness_mm"])


def stabilised_cycles(table: dict, meta: dict, name: str = "tensile") -> tuple[list, str]:
    """Cycles whose unloading branch represents the stabilised material, and why.

    The first cycle (preconditioning: fibres rearrange, the textile is not yet
    stabilised) is always dropped when there are several. Of the rest, the last cycle is
    the reference; going backwards, a cycle is kept while its unloading branch agrees
    with the reference fit within noise (RMS <= 1.5 x the reference's residual RMS and
    mean offset <= 4 standard errors of a difference of two noisy curves); the first disagreeing cycle and all before it are dropped.
    """
    cycles = sorted(int(c) for c in np.unique(table["cycle"]))
    for c in cycles:
        n = int(np.sum((table["cycle"] == c) & (table["branch"] == "unload")))
        if n < 6:
            raise SelfshapeError(f"{name}: cycle {c} has {n} unload rows (need >= 6)")
    if len(cycles) == 1:
        return cycles, "single cycle in the file: used as is (stabilisation cannot be checked)"
    ref = cycles[-1]
    ref_fit = fit_barrier_curve(*tensile_curve(table, meta, [ref]))
    sigma = max(ref_fit["rms"], 1e-15)
    kept = [ref]
    for c in reversed(cycles[1:-1]):
        e, S = tensile_curve(table, meta, [c])
        if e.max() >= ref_fit["g"]:
            break
        r = S - barrier_curve(e, ref_fit["A"], ref_fit["b"], ref_fit["g"])
        # the mean offset compares two noisy curves: its SE is ~ sqrt(2) sigma / sqrt(n)
        if np.sqrt(np.mean(r * r)) > 1.5 * sigma or abs(r.mean()) > 4.0 * np.sqrt(2.0) * sigma / np.sqrt(r.size):
            break
        kept.append(c)
    kept.sort()
    dropped = [c for c in cycles if c not in kept]
    why = (f"cycle {cycles[0]} dropped as preconditioning" +
           (f"; cycle(s) {dropped[1:]} differ from the last cycle beyond noise" if len(dropped) > 1 else "") +
           f"; cycles {kept} agree with the last cycle within noise and are pooled")
    return kept, why


def stiffness_from_uniaxial(A1: float, A2: float, nu: float) -> tuple[float, float]:
    """a1, a2 from the uniaxial slopes A1 = (a1 - sqrt(a1 a2) nu^2)/(1-nu^2), A2 likewise.

    With r = sqrt(a2/a1), P = A1 (1-nu^2), Q = A2 (1-nu^2): P r^2 - nu^2 (P - Q) r - Q = 0,
    positive root, then a1 = P / (1 - nu^2 r), a2 = r^2 a1.
    """
    P, Q = A1 * (1 - nu * nu), A2 * (1 - nu * nu)
    if P <= 0 or Q <= 0:
        raise SelfshapeError(f"uniaxial slopes must be positive to define a1, a2 (got A1 = {A1:.4g}, A2 = {A2:.4g} MPa)")
    n2 = nu * nu
    r = (n2 * (P - Q) + np.sqrt(n2 * n2 * (P - Q) ** 2 + 4 * P * Q)) / (2 * P)
    if 1 - n2 * r <= 0 or 1 - n2 / r <= 0:
        raise SelfshapeError(f"uniaxial slopes A1 = {A1:.4g}, A2 = {A2:.4g} MPa admit no a1, a2 with nu = {nu:g}")
    a1 = P / (1 - n2 * r)
    return float(a1), float(r * r * a1)


def _stiffness_with_se(A1, se1, A2, se2, nu):
    a = np.array(stiffness_from_uniaxial(A1, A2, nu))
    J = np.empty((2, 2))
    for k, (h, base) in enumerate(((1e-6 * abs(A1), (A1, A2)), (1e-6 * abs(A2), (A1, A2)))):
        up, dn = list(base), list(base)
        up[k] += h
        dn[k] -= h
        J[:, k] = (np.array(stiffness_from_uniaxial(*up, nu)) - np.array(stiffness_from_uniaxial(*dn, nu))) / (2 * h)
    cov = J @ np.diag([se1 ** 2, se2 ** 2]) @ J.T
    return a, np.sqrt(np.diag(cov))


# ----------------------------------------------------------------------------- the model

def strain_rotation(angle_deg: float) -> np.ndarray:
    """T with eps_course = T @ eps_specimen (Voigt, engineering shear) for a specimen
    axis at angle_deg from the course direction; stresses map back with T^T."""
    t = np.radians(angle_deg)
    c, s = np.cos(t), np.sin(t)
    return np.array([[c * c, s * s, -c * s], [s * s, c * c, c * s], [2 * c * s, -2 * c * s, c * c - s * s]])


def uniaxial_response(e_axial, angle_deg: float, params: dict, nu: float):
    """Model stress along a strip cut at angle_deg, stretched to axial Green strain(s) e_axial,
    in uniaxial stress (lateral and shear stress zero, solved by damped Newton; the problem
    is the minimisation of a convex energy over the two free strains).

    Returns (axial stress MPa (n,), free strains (n,2) = transverse Green strain and 2 e12).
    NaN where the axial strain is beyond the model's barrier.
    """
    e = np.atleast_1d(np.asarray(e_axial, dtype=float))
    T = strain_rotation(angle_deg)
    g = np.array([params["g1"], params["g2"]])
    x = np.zeros((e.size, 2))
    x[:, 0] = -nu * e

    def course(xx):
        return np.column_stack([e, xx]) @ T.T

    def feasible(xx):
        return np.all(np.abs(course(xx)[:, :2]) < g, axis=1)

    ok = feasible(x)
    x[~ok, 0] = 0.0
    ok = feasible(x)
    for _ in range(100):
        sig, K = orthotropic_stress(course(x[ok]), params, nu)
        ss = sig @ T
        Ks = np.einsum("ji,njk,kl->nil", T, K, T)
        R = ss[:, 1:]
        if np.abs(R).max(initial=0.0) < 1e-13 * max(1.0, np.abs(ss[:, 0]).max(initial=0.0)):
            break
        dx = np.linalg.solve(Ks[:, 1:, 1:], -R[..., None])[..., 0]
        step = np.ones(dx.shape[0])
        xo = x[ok]
        for _ in range(60):
            trial = xo + step[:, None] * dx
            bad = ~np.all(np.abs((np.column_stack([e[ok], trial]) @ T.T)[:, :2]) < g, axis=1)
            if not bad.any():
                break
            step[bad] *= 0.5
        x[ok] = xo + step[:, None] * dx
    out = np.full(e.size, np.nan)
    sig, _ = orthotropic_stress(course(x[ok]), params, nu)
    out[ok] = (sig @ T)[:, 0]
    x[~ok] = np.nan
    return out, x


def fit_orthotropic_uniaxial(e0, S0, e90, S90, nu: float, a3: float, start: dict | None = None) -> dict:
    """Model-consistent fit of a1, a2, b1, b2, g1, g2 on the 0 and 90 deg unloading curves.

    Residuals are the model's own uniaxial-stress response (uniaxial_response: the lateral
    stress vanishes, the transverse strain and barrier included) minus the measured stress,
    so the engine reproduces the two tests it is fitted on. (The seed's Eq. 4.6-4.7 instead
    impose e22 = -nu e11, which is not the model's uniaxial state.) a3 does not enter at
    0/90 deg (no shear strain by symmetry). Start: the Eq. 4.6 fits (a1 ~ A1, a2 ~ A2, the
    small-strain uniaxial slopes of the model). SE from the Jacobian, s^2 = SSR/(n-6).
    """
    e0, S0, e90, S90 = (np.asarray(v, dtype=float) for v in (e0, S0, e90, S90))
    em0, em9 = float(e0.max()), float(e90.max())
    if start is None:
        f0, f9 = fit_barrier_curve(e0, S0), fit_barrier_curve(e90, S90)
        start = {"a1": f0["A"], "a2": f9["A"], "b1": f0["b"], "b2": f9["b"], "g1": f0["g"], "g2": f9["g"]}
    tiny = 1e-9 * max(float(np.abs(S0).max()), float(np.abs(S90).max()), 1e-12)

    def unpack(x):
        return {"a1": np.exp(x[0]), "a2": np.exp(x[1]), "a3": a3, "b1": np.exp(x[2]), "b2": np.exp(x[3]),
                "g1": em0 + np.exp(x[4]), "g2": em9 + np.exp(x[5])}

    def resid(x):
        p = unpack(x)
        r0 = uniaxial_response(e0, 0.0, p, nu)[0] - S0
        r9 = uniaxial_response(e90, 90.0, p, nu)[0] - S90
        r = np.concatenate([r0, r9])
        return np.where(np.isfinite(r), r, 1e3 * float(np.abs(S0).max() + np.abs(S90).max()))

    x0 = [np.log(max(start["a1"], tiny)), np.log(max(start["a2"], tiny)), np.log(max(start["b1"], tiny)),
          np.log(max(start["b2"], tiny)), np.log(max(start["g1"] - em0, 1e-6)), np.log(max(start["g2"] - em9, 1e-6))]
    sol = least_squares(resid, x0, x_scale="jac", xtol=1e-12, ftol=1e-12, max_nfev=400)
    p = unpack(sol.x)
    r = sol.fun
    s2 = float(r @ r) / max(r.size - 6, 1)
    cov_x = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    scale = np.array([p["a1"], p["a2"], p["b1"], p["b2"], p["g1"] - em0, p["g2"] - em9])
    se = np.sqrt(np.clip(np.diag(cov_x), 0, None)) * scale
    names = ("a1", "a2", "b1", "b2", "g1", "g2")
    return {"params": {k: float(v) for k, v in p.items()}, "se": dict(zip(names, map(float, se))),
            "rms": float(np.sqrt(np.mean(r * r))), "converged": bool(sol.success)}


# ----------------------------------------------------------------------------- shear

def shear_stress_strain(displacement_mm, load_n, side_mm: float, thickness_mm: float):
    """Kinematics of the square clamped on two parallel edges: gamma = u / side (the clamp
    separation equals the side), tau = F / (side * thickness) MPa. For simple shear
    F = [[1, gamma], [0, 1]] the Green strain has 2 e12 = gamma exactly (and e22 = gamma^2/2)."""
    u = np.asarray(displacement_mm, dtype=float)
    return u / side_mm, np.asarray(load_n, dtype=float) / (side_mm * thickness_mm)


def fit_shear_modulus(gamma, tau) -> dict:
    """Initial shear slope a3 of tau(gamma), two linear least-squares fits.

    main ("odd-cubic"): tau = c0 + a3 gamma + c gamma^3. The model's sigma12 is linear in 2 e12,
    so a3 is the slope at zero; the measured lateral force also carries the stretching term
    gamma * S22 (e22 = gamma^2/2), odd and cubic in gamma, which the cubic absorbs (a quadratic
    term would break the symmetry gamma -> -gamma).
    seed ("linear"): tau = c0 + a gamma over the whole range (the seed's straight line).
    Each with SE from (X^T X)^-1 s^2.
    """
    g = np.asarray(gamma, dtype=float)
    t = np.asarray(tau, dtype=float)
    if g.size < 5 or np.ptp(g) <= 0:
        raise SelfshapeError(f"shear fit needs >= 5 points over a range of displacement, got {g.size}")
    out = {}
    for key, X in (("odd_cubic", np.column_stack([np.ones_like(g), g, g ** 3])),
                   ("linear", np.column_stack([np.ones_like(g), g]))):
        coef, *_ = np.linalg.lstsq(X, t, rcond=None)
        r = t - X @ coef
        s2 = float(r @ r) / max(g.size - X.shape[1], 1)
        cov = s2 * np.linalg.pinv(X.T @ X)
        out[key] = {"slope": float(coef[1]), "se": float(np.sqrt(cov[1, 1])), "coef": coef,
                    "rms": float(np.sqrt(np.mean(r * r)))}
    return out


# ----------------------------------------------------------------------------- calibration

def _pair(v, se):
    v, se = float(v), float(se)
    return [v if math.isfinite(v) else None, se if math.isfinite(se) else None]


def _mean_with_se(values, ses):
    values, ses = np.asarray(values, float), np.asarray(ses, float)
    return float(values.mean()), float(np.sqrt(np.sum(ses ** 2)) / values.size)


def interpolate_by_stretch(values_by_pct: dict, stretch_pct: float):
    """Seed rule: linear interpolation in the max stretch (percent) between measured values
    (dict pct-string -> number or dict of numbers); clamped to the nearest measured stretch
    outside the measured range."""
    keys = sorted(values_by_pct, key=float)
    xs = np.array([float(k) for k in keys])
    p = float(np.clip(stretch_pct, xs[0], xs[-1]))
    i = int(np.clip(np.searchsorted(xs, p) - 1, 0, max(len(xs) - 2, 0)))
    if len(xs) == 1:
        return values_by_pct[keys[0]]
    t = (p - xs[i]) / (xs[i + 1] - xs[i])
    lo, hi = values_by_pct[keys[i]], values_by_pct[keys[i + 1]]
    if isinstance(lo, dict):
        return {k: (1 - t) * lo[k] + t * hi[k] for k in lo}
    return (1 - t) * lo + t * hi


def _load_tensile(files: dict, meta: dict) -> dict:
    """pct -> deg -> {e, S, cycles, why, load_e, load_S, name}."""
    out = {}
    L = meta["tensile_gauge_length_mm"]
    for pct, by_deg in files.items():
        for deg, path in by_deg.items():
            name = os.path.basename(path)
            t = read_tensile(path)
            bad = np.flatnonzero(t["extension_mm"] <= -L)
            if bad.size:
                raise SelfshapeError(f"{name}: row {bad[0] + 1}, column extension_mm: below minus the gauge length")
            if not np.any(t["branch"] == "unload"):
                raise SelfshapeError(f"{name}: no unload rows (the calibration uses the unloading branch)")
            cycles, why = stabilised_cycles(t, meta, name)
            e, S = tensile_curve(t, meta, cycles)
            le, lS = tensile_curve(t, meta, cycles, "load")
            out.setdefault(pct, {})[deg] = {"e": e, "S": S, "cycles": cycles, "why": why,
                                           "load_e": le, "load_S": lS, "name": name}
    return out


def _shear_results(files: dict, meta: dict) -> dict:
    side, h = meta["shear_sample_side_mm"], meta["fabric_thickness_mm"]
    per = {}
    for deg, path in sorted(files.items(), key=lambda kv: float(kv[0])):
        t = read_shear(path)
        g, tau = shear_stress_strain(t["lateral_displacement_mm"], t["lateral_load_N"], side, h)
        per[deg] = {"gamma": g, "tau": tau, "fit": fit_shear_modulus(g, tau)}
    res = {"per": per}
    for key in ("odd_cubic", "linear"):
        vals = [p["fit"][key]["slope"] for p in per.values()]
        ses = [p["fit"][key]["se"] for p in per.values()]
        res[key] = _mean_with_se(vals, ses)
        if "0" in per and "90" in per:
            f0, f9 = per["0"]["fit"][key], per["90"]["fit"][key]
            res[key + "_diff"] = (f0["slope"] - f9["slope"], float(np.hypot(f0["se"], f9["se"])))
    return res


def _cantilever_results(path: str) -> dict:
    t = read_cantilever(path)
    name = os.path.basename(path)
    groups = {}
    for o, f in sorted({(float(o), str(f)) for o, f in zip(t["orientation_deg"], t["face_up"])}):
        m = (t["orientation_deg"] == o) & (t["face_up"] == f)
        key = f"{_number_key(o)}/{f}"
        if np.sum(m) < 2:
            raise SelfshapeError(f"{name}: {key} has one free length; need >= 2 to fit k_B with an error")
        fit = elastica.fit_bending_stiffness(t["free_length_mm"][m], t["areal_weight_N_per_mm2"][m],
                                             t["height_over_width"][m])
        fit["L"], fit["w"], fit["h"] = t["free_length_mm"][m], t["areal_weight_N_per_mm2"][m], t["height_over_width"][m]
        groups[key] = fit
    return groups


def _model_params(by_pct_fits: dict, a3: float, nu: float) -> dict:
    f1, f2 = by_pct_fits["0"], by_pct_fits["90"]
    a1, a2 = stiffness_from_uniaxial(f1["A"], f2["A"], nu)
    return {"a1": a1, "a2": a2, "a3": a3, "b1": f1["b"], "b2": f2["b"], "g1": f1["g"], "g2": f2["g"]}


def _validation(curves: dict, params: dict, nu: float) -> dict:
    out = {}
    for deg, c in sorted(curves.items(), key=lambda kv: float(kv[0])):
        pred, _ = uniaxial_response(c["e"], float(deg), params, nu)
        ok = np.isfinite(pred)
        if not ok.any():
            out[deg] = {"rel_rms": None, "release_rel_error": None}
            continue
        err = pred[ok] - c["S"][ok]
        k = int(np.argmax(c["e"]))
        rel_rel = (pred[k] - c["S"][k]) / c["S"][k] if np.isfinite(pred[k]) and c["S"][k] != 0 else float("nan")
        out[deg] = {"rel_rms": float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(c["S"][ok] ** 2))),
                    "release_rel_error": float(rel_rel) if math.isfinite(rel_rel) else None,
                    "fraction_predicted": float(ok.mean())}
    return out


def _plots(out_dir, tensile, fits, params_by_pct, nu, shear, cant) -> list:
    paths = []
    degs = sorted({d for by in tensile.values() for d in by}, key=float)
    for deg in degs:
        pts, lines = [], []
        for pct in sorted(tensile, key=float):
            c = tensile[pct].get(deg)
            if c is None:
                continue
            pts.append(Series(c["load_e"], c["load_S"], f"{pct} %: loading", style=".", alpha=0.25))
            pts.append(Series(c["e"], c["S"], f"{pct} %: unloading (cycles {c['cycles']})", style=".", alpha=0.6))
            eg = np.linspace(0.0, c["e"].max(), 200)
            f = fits[pct][deg]
            lines.append(Series(eg, barrier_curve(eg, f["A"], f["b"], f["g"]), f"{pct} %: Eq. 4.6 fit", style="-"))
            pred, _ = uniaxial_response(eg, float(deg), params_by_pct[pct], nu)
            lines.append(Series(eg, pred, f"{pct} %: model (uniaxial stress)", style="--"))
        paths.append(plot_series(os.path.join(out_dir, f"tensile_{deg}deg.png"),
                                 title=f"Tensile, {deg} deg from the course direction",
                                 xlabel="Green strain", ylabel="2nd Piola-Kirchhoff stress (MPa)",
                                 points=pts, lines=lines))
    pts, lines = [], []
    for deg, p in shear["per"].items():
        pts.append(Series(p["gamma"], p["tau"], f"{deg} deg", style="."))
        gg = np.linspace(0, p["gamma"].max(), 100)
        c = p["fit"]["odd_cubic"]["coef"]
        lines.append(Series(gg, c[0] + c[1] * gg + c[2] * gg ** 3, f"{deg} deg: c0 + a3 g + c g^3"))
        lines.append(Series(gg, c[0] + c[1] * gg, f"{deg} deg: initial slope {c[1]:.4f} MPa", style=":"))
    paths.append(plot_series(os.path.join(out_dir, "shear.png"), title="Shear test",
                             xlabel="shear strain gamma = u / side = 2 e12", ylabel="tau = F / (side h) (MPa)",
                             points=pts, lines=lines))
    g_tab, r_tab = elastica.master_curve_table()
    gmin = min(f["gamma"].min() for f in cant.values()) / 3
    gmax = max(f["gamma"].max() for f in cant.values()) * 3
    m = (g_tab >= gmin) & (g_tab <= gmax)
    pts = [Series(f["gamma"], f["h"], f"{k}: k_B = {f['k_b']:.4g} N mm") for k, f in cant.items()]
    paths.append(plot_series(os.path.join(out_dir, "master_curve.png"), title="Cantilever: heavy-elastica master curve",
                             xlabel="Gamma = w L^3 / k_B", ylabel="height / width", points=pts,
                             lines=[Series(g_tab[m], r_tab[m], "master curve")], logx=True, logy=True))
    return paths


def calibrate_fabric(folder: str, out_dir: str) -> dict:
    """Fit the fabric model on a test folder (meta.json, tensile_*, shear_*, cantilever.csv).

    Writes out_dir/parameters.json (every parameter as [value, standard error]; mm, N, MPa)
    and PNG plots; returns the same dict. Bad input raises SelfshapeError before anything
    is written.
    """
    if not os.path.isdir(folder):
        raise SelfshapeError(f"{folder}: not a directory (expected a fabric test folder)")
    meta = read_meta(folder)
    nu = meta["poisson"]
    files = find_test_files(folder)
    tensile = _load_tensile(files["tensile"], meta)
    shear = _shear_results(files["shear"], meta)
    cant = _cantilever_results(files["cantilever"])
    a3, a3_se = shear["odd_cubic"]

    fits, ortho_by, seed_by, params_by, seed_params_by = {}, {}, {}, {}, {}
    release, release_by, validation, seed_validation, rms, rms_model = {}, {}, {}, {}, {}, {}
    for pct in sorted(tensile, key=float):
        fits[pct] = {deg: fit_barrier_curve(c["e"], c["S"]) for deg, c in tensile[pct].items()}
        f1, f2 = fits[pct]["0"], fits[pct]["90"]
        # the seed's route: Eq. 4.6-4.7 with e22 = -nu e11, then the small system for a1, a2
        (a1, a2), (se_a1, se_a2) = _stiffness_with_se(f1["A"], f1["se"][0], f2["A"], f2["se"][0], nu)
        seed_by[pct] = {"a1": _pair(a1, se_a1), "a2": _pair(a2, se_a2), "a3": _pair(a3, a3_se),
                        "b1": _pair(f1["b"], f1["se"][1]), "b2": _pair(f2["b"], f2["se"][1]),
                        "g1": _pair(f1["g"], f1["se"][2]), "g2": _pair(f2["g"], f2["se"][2])}
        seed_params_by[pct] = _model_params(fits[pct], a3, nu)
        # model-consistent refinement: the engine's own uniaxial response fits 0 and 90 deg
        c0, c9 = tensile[pct]["0"], tensile[pct]["90"]
        cons = fit_orthotropic_uniaxial(c0["e"], c0["S"], c9["e"], c9["S"], nu, a3)
        params_by[pct] = cons["params"]
        ortho_by[pct] = {k: (_pair(a3, a3_se) if k == "a3" else _pair(cons["params"][k], cons["se"][k]))
                         for k in PARAM_NAMES}
        rms_model[pct] = cons["rms"]
        tangents = {deg: release_tangent(f) for deg, f in sorted(fits[pct].items(), key=lambda kv: float(kv[0]))}
        release_by[pct] = {deg: _pair(*v) for deg, v in tangents.items()}
        release[pct] = _pair(*_mean_with_se([v[0] for v in tangents.values()], [v[1] for v in tangents.values()]))
        validation[pct] = _validation(tensile[pct], params_by[pct], nu)
        seed_validation[pct] = _validation(tensile[pct], seed_params_by[pct], nu)
        rms[pct] = {deg: f["rms"] for deg, f in fits[pct].items()}
    top = max(tensile, key=float)
    kb = {k: _pair(f["k_b"], f["se"]) for k, f in cant.items()}
    kb_mean = _pair(*_mean_with_se([f["k_b"] for f in cant.values()], [f["se"] for f in cant.values()]))

    result = {
        "units": {"a1 a2 a3 b1 b2": "MPa", "g1 g2": "Green strain", "release_modulus_mpa": "MPa",
                  "bending_stiffness_nmm": "N mm (moment per unit width per unit curvature)"},
        "orthotropic": ortho_by[top],
        "orthotropic_max_stretch_pct": float(top),
        "orthotropic_by_stretch": ortho_by,
        "orthotropic_seed_eq46": seed_by[top],
        "orthotropic_seed_eq46_by_stretch": seed_by,
        "release_modulus_mpa": release,
        "release_modulus_by_orientation_mpa": release_by,
        "bending_stiffness_nmm": kb,
        "bending_stiffness_mean_nmm": kb_mean,
        "poisson": [nu, 0.0],
        "shear": {
            "a3_by_orientation_mpa": {d: _pair(p["fit"]["odd_cubic"]["slope"], p["fit"]["odd_cubic"]["se"])
                                      for d, p in shear["per"].items()},
            "a3_0_minus_90_mpa": _pair(*shear["odd_cubic_diff"]) if "odd_cubic_diff" in shear else None,
            "seed_straight_line_mpa": _pair(*shear["linear"]),
            "seed_straight_line_by_orientation_mpa": {d: _pair(p["fit"]["linear"]["slope"], p["fit"]["linear"]["se"])
                                                      for d, p in shear["per"].items()},
            "seed_straight_line_0_minus_90_mpa": _pair(*shear["linear_diff"]) if "linear_diff" in shear else None,
        },
        "fit_quality": {
            "tensile_eq46_rms_mpa": rms,
            "tensile_model_rms_mpa": rms_model,
            "validation": validation,
            "validation_seed_eq46": seed_validation,
            "shear_rms_mpa": {d: p["fit"]["odd_cubic"]["rms"] for d, p in shear["per"].items()},
            "cantilever_rms_log": {k: f["rms_log"] for k, f in cant.items()},
        },
        "cycles_used": {c["name"]: {"cycles": c["cycles"], "why": c["why"]}
                        for by in tensile.values() for c in by.values()},
        "method": {
            "tensile": "unloading branch of the stabilised cycles, Eq. 4.4 (Green strain, 2nd PK stress). "
                       "orthotropic: a1, a2, b1, b2, g1, g2 fitted so that the model's own uniaxial-stress response "
                       "(lateral stress zero) matches the 0 and 90 deg curves, started from the seed's route. "
                       "orthotropic_seed_eq46: the seed's route, sigma = A e - b log(1 - e/g) on 0 deg (A1, b1, g1) and "
                       "90 deg (A2, b2, g2), a1, a2 from A1, A2 with e22 = -nu e11 (Eq. 4.6-4.7)",
            "validation": "every orientation's unloading curve against the model in uniaxial stress (strain rotated "
                          "into the course frame, transverse strain and shear solved); rel_rms = RMS error / RMS stress",
            "release_modulus": "slope of each orientation's fitted unloading curve at its largest strain, "
                               "mean over orientations; SE = sqrt(sum SE_i^2) / n",
            "shear": "gamma = u/side = 2 e12, tau = F/(side h); a3 = initial slope of tau = c0 + a3 gamma + c gamma^3, "
                     "mean of the orientations",
            "bending": "least squares in log(height/width) against the heavy-elastica master curve, Gamma = w L^3 / k_B",
            "poisson": "from meta.json 'poisson' if given, else the seed's 0.3 (not measured here; SE 0)",
            "interpolation": "parameters at other max stretches: linear in the percent between measured ones "
                             "(validation.fabric.interpolate_by_stretch)",
        },
        "meta": {k: meta[k] for k in META_KEYS},
    }
    os.makedirs(out_dir, exist_ok=True)
    result["plots"] = [os.path.basename(p) for p in _plots(out_dir, tensile, fits, params_by, nu, shear, cant)]
    path = os.path.join(out_dir, "parameters.json")
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(result, f, indent=1, allow_nan=False)
    os.replace(tmp, path)
    return result


def model_parameters(parameters: dict, stretch_pct: float | None = None) -> dict:
    """Plain {a1..g2} floats from a parameters.json dict, at the largest measured stretch or
    linearly interpolated at stretch_pct (seed rule, clamped outside the measured range)."""
    if stretch_pct is None:
        return {k: parameters["orthotropic"][k][0] for k in PARAM_NAMES}
    by = {p: {k: v[k][0] for k in PARAM_NAMES} for p, v in parameters["orthotropic_by_stretch"].items()}
    return interpolate_by_stretch(by, stretch_pct)
