"""The gallery's shape measures (validation.measures) on exact surfaces, and its committed patterns."""
import numpy as np

from shellfem.sheet import Sheet
from validation.measures import centre_quadric


def test_centre_quadric_on_a_sphere_and_a_cylinder():
    sh = Sheet.rectangle(40, 40, 40, 40)
    P = sh.points - 20.0
    R = 50.0
    z = R - np.sqrt(R * R - (P ** 2).sum(1))
    m = centre_quadric(sh, np.column_stack([P, z]))
    assert abs(m["gauss_centre_fit"] * R * R - 1) < 0.02
    assert abs(m["mean_curv_centre_fit"] * R - 1) < 0.01
    zc = R - np.sqrt(R * R - P[:, 0] ** 2)        # cylinder: K = 0, |H| = 1/(2R)
    m = centre_quadric(sh, np.column_stack([P, zc]))
    assert abs(m["gauss_centre_fit"]) < 1e-3 / R ** 2
    assert abs(m["mean_curv_centre_fit"] * 2 * R - 1) < 0.01


def test_committed_gallery_patterns_are_what_the_script_simulates():
    """examples/gallery/*.toml are written by studies/gallery.py from validation.cases; a stale
    copy (a pattern that is not the one the study simulates) would mislead readers."""
    import os
    import tomllib

    import tomli_w

    from validation.cases import GALLERY_CASES
    root = os.path.join(os.path.dirname(__file__), "..", "examples", "gallery")
    for name, make in GALLERY_CASES.items():
        with open(os.path.join(root, f"{name}.toml"), "rb") as f:
            committed = tomllib.load(f)
        assert committed == tomllib.loads(tomli_w.dumps(make())), name
