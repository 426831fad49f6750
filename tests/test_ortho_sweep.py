"""The orthotropic ribbon sweep (studies/ortho_sweep.py): the seed's section 4.1 cases
(validation.cases.ortho_ribbons) and the mode comparison (validation.ribbon_modes)."""
from validation.cases import ortho_ribbons as case
from validation.ribbon_modes import markdown_table, summarise


def test_case_is_the_gallery_ribbons_with_thickness_pitch_and_course():
    raw = case(0.8, 6.0, 90.0)
    assert raw["fabric"]["model"] == "orthotropic" and raw["fabric"]["course_angle_deg"] == 90.0
    ys = sorted(r["path"][0][1] for r in raw["ribbon"])
    assert all(abs(b - a - 6.0) < 1e-12 for a, b in zip(ys, ys[1:]))
    assert {r["thickness_mm"] for r in raw["ribbon"]} == {0.8}


def _row(t, p, c, along, across, converged=True):
    return dict(thickness_mm=t, pitch_mm=p, course_deg=c, converged=converged, kappa_along_per_mm=along,
                kappa_across_per_mm=across, mode="along" if abs(along) > abs(across) else "across")


def test_modes_differ_only_where_both_orientations_converged_and_disagree():
    rows = [_row(0.4, 3, 0.0, 0.3, 0.1), _row(0.4, 3, 90.0, 0.1, -0.2),      # along vs across: differ
            _row(0.8, 3, 0.0, 0.3, 0.1), _row(0.8, 3, 90.0, 0.5, 0.1),       # both along
            _row(1.2, 3, 0.0, 0.3, 0.1), _row(1.2, 3, 90.0, 0.1, 0.5, converged=False)]
    s = summarise(rows)
    assert [(r["thickness_mm"], r["modes_differ"]) for r in s] == [(0.4, True), (0.8, False)]
    assert s[0]["ratio_90"] == 0.5
    table = markdown_table(rows)
    assert "| 0.4 | 3 | 3.00, along | 0.50, across | yes |" in table and "1.2" not in table


def test_other_seeds_are_listed_next_to_seed_0():
    rows = [_row(0.6, 3, 0.0, 0.1, 0.2), _row(0.6, 3, 90.0, 0.3, 0.2)]
    rows += [dict(r, seed=1, mode="along") for r in rows]
    assert [s["modes_differ"] for s in summarise(rows, 1)] == [False]
    assert "| yes | seed 1: along / along |" in markdown_table(rows)
