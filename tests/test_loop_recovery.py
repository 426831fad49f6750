"""The loop on strip sets with two and three simultaneous undeclared effects (issue 19):
every effect found (added, or reported indistinguishable from an added one), nothing
added to clean sets, held-out error at the noise floor. The sets come from
validation.strip_sets (effects written independently of validation.effects, seeded
relative noise of 1.5 %). The full sweep over seeds is studies/loop_recovery.py."""
import numpy as np
import pytest

from validation import loop, strip_sets
from validation.strips import MEASURED


def found(sel, effect):
    """Added, or reported indistinguishable from an added effect."""
    if effect in sel["added"]:
        return True
    return any(effect in d["effects"] and set(d["effects"]) & set(sel["added"]) for d in sel["indistinguishable"])


@pytest.mark.parametrize("case,seed", [
    ("side_deposition+orthotropy", 1),                     # lost a whole outer fold before (issue 19)
    ("stretch_modulus+plastic_prestrain", 2),              # partly confounded: both act through the stretch
    ("thickness_bias+stretch_modulus+gravity", 1),         # a wrong first greedy step before
    ("side_fabric_stiffness+plastic_prestrain+width_transition", 0),
    # the greedy path took side_deposition_factor for side_fabric_stiffness (and the reverse):
    # the truth fits better by 5.6 and 10.2 noise variances; the swap search takes it (issue 19)
    ("side_fabric_stiffness+plastic_set_thickness", 7),
    ("side_deposition_factor+plastic_set_constant+orthotropy", 4),
])
def test_every_effect_of_a_multi_effect_set_is_found(case, seed):
    rows = strip_sets.strip_set(case, seed)
    truth = strip_sets.CASES[case]
    sel = loop.select_effects(rows, seed=seed, report=False)
    assert sorted(sel["added"]) == sorted(truth)  # these effects are identifiable: each one itself
    # the final model leaves no structure beyond the replicate scatter
    assert sel["lack_of_fit_after"]["p"] > 0.01, sel["lack_of_fit_after"]
    assert sel["lack_of_fit_before"]["p"] < 1e-6


def test_heldout_error_reaches_the_noise_floor_over_seeds():
    """Outer 5-fold held-out error over the loop's own noise-floor estimate, a two-effect
    set and a three-effect set at two seeds (the baseline loop was 40, 14 and 1.1 x the
    floor on these); the floor estimate itself within 20 % of the truth."""
    ratios = []
    for case, seed in (("side_deposition+orthotropy", 1), ("thickness_bias+stretch_modulus+gravity", 1),
                       ("thickness_bias+stretch_modulus+gravity", 2)):
        rows = strip_sets.strip_set(case, seed)
        rep = loop.validate(rows, seed=seed)
        assert sorted(rep["effects_added"]) == sorted(strip_sets.CASES[case]), rep["effects_added"]
        assert all(sorted(f) == sorted(strip_sets.CASES[case]) for f in rep["effects_added_per_outer_fold"])
        true_rel = strip_sets.NOISE * np.sqrt(np.mean(rows["_truth"]["noise_free"] ** 2)) / np.sqrt(
            np.mean(rows[MEASURED] ** 2))
        assert abs(rep["noise_relative"] / true_rel - 1) < 0.2
        assert rep["error_before"] > 5 * rep["noise_relative"]
        ratios.append(rep["error_after"] / rep["noise_relative"])
    assert np.mean(ratios) <= 1.1, ratios
    assert max(ratios) <= 1.25, ratios


def test_clean_sets_add_nothing():
    """validate on one clean set (outer folds too), then the selection alone on ten more,
    with replicates and without (the same number of single strips)."""
    rows = strip_sets.strip_set("clean", 0)
    rep = loop.validate(rows, seed=0)
    assert rep["effects_added"] == []
    assert all(not f for f in rep["effects_added_per_outer_fold"])
    assert rep["error_after"] == rep["error_before"]
    for seed in range(100, 110):
        for n_points, reps in ((24, 3), (72, 1)):
            rows = strip_sets.strip_set("clean", seed, n_points=n_points, reps=reps)
            assert loop.select_effects(rows, seed=seed, report=False)["added"] == [], (seed, reps)


def test_variance_function_recovers_relative_and_additive_noise():
    """60 groups of 4 replicates at curvatures 0.002-0.1 1/mm, noise 1e-4 1/mm additive
    plus 2 % relative: both parts within 25 %, and the pooled estimate they give within
    10 % of the true RMS noise."""
    rng = np.random.default_rng(3)
    level = np.repeat(np.exp(rng.uniform(np.log(0.002), np.log(0.1), 60)), 4)
    groups = np.repeat(np.arange(60), 4)
    sd = np.sqrt(1e-4 ** 2 + (0.02 * level) ** 2)
    resid = sd * rng.standard_normal(level.size)
    a, b, dof = loop.variance_function(groups, resid, level)
    assert dof == 180
    assert abs(np.sqrt(a) / 1e-4 - 1) < 0.25 and abs(np.sqrt(b) / 0.02 - 1) < 0.25
    est = np.sqrt(np.mean(a + b * level ** 2))
    assert abs(est / np.sqrt(np.mean(sd ** 2)) - 1) < 0.1


def test_indistinguishable_effects_are_reported_not_picked_silently():
    """Only back-face strips of one fabric thickness: a back-face extra thickness and a
    printer thickness bias change every strip the same way, the data cannot separate
    them."""
    levels = {"side": ("back",), "fabric_thickness_mm": (0.8,), "stretch": (1.35,), "orientation_deg": (0.0,),
              "width_mm": (10.0,), "length_mm": (40.0,)}
    rows = strip_sets.measure(strip_sets.design(4, n_points=16, reps=3, levels=levels), ("thickness_bias",),
                              seed=5)
    sel = loop.select_effects(rows, seed=0)
    assert len(sel["added"]) == 1
    assert found(sel, "thickness_bias")
    pairs = [set(d["effects"]) for d in sel["indistinguishable"]]
    assert {"thickness_bias", "side_deposition"} in pairs


def test_without_replicates_the_partial_f_test_decides():
    """No two strips share a design point (no pure error): the loop falls back on the
    classical partial F test and says its noise estimate is not an independent floor;
    it still finds a two-effect set and adds nothing to a clean one."""
    rows = strip_sets.strip_set("side_deposition+orthotropy", 5, n_points=60, reps=1)
    sel = loop.select_effects(rows, seed=0, report=False)
    assert sel["noise"]["dof"] is None and "not an independent" in sel["noise"]["method"]
    assert sorted(sel["added"]) == ["orthotropy", "side_deposition"]
    clean = strip_sets.strip_set("clean", 6, n_points=60, reps=1)
    assert loop.select_effects(clean, seed=0, report=False)["added"] == []
