"""Forward selection (``forensics model check --auto``): the path base → +A → +B … and why it stops.

The stopping rules are tested on stand-in checks (no fitting); the end-to-end behaviour on one dataset with
two hidden effects and one with none.  The multi-seed figures are ``benchmarks/sweep_check.py --combo``.
"""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from forensics.fixtures.hidden import (
    HIDDEN,
    hidden_effect,
    hidden_effects,
    hidden_model,
    make_hidden,
)

import forensics.check.select as sel_mod
from forensics.check import SelectionResult, check_auto, forward_select
from forensics.check.result import Candidate, CheckResult
from forensics.check.pipeline import base_model

#: Two hidden effects the base check flags, and a seed where forward selection finds exactly them
#: (measured: 10/10 seeds 1–10 for this combination, see benchmarks/sweep_check.py --combo).
PAIR = ["prnu", "dark_current"]
SEED = 1


# ------------------------------------------------------------------------------------ stopping rules (stand-ins)
def _result(effects, pixel, flagged, gof_pixel=0.5):
    cands = [Candidate(f, 100.0, 1e-9, True, 120.0, 1, 1e-10, 1, [], "") for f in flagged]
    return CheckResult(effects=list(effects), params=[], patterns=[],
                       error={"pixel": pixel, "classes": {}, "variance": 0.02, "growth": 1.0},
                       gof={"pixel": gof_pixel, "variance": 0.5, "growth": 0.5, "spatial": 0.5},
                       checks=[], candidates=cands, warnings=[], data={})


def _fake(monkeypatch, table):
    """run_check stand-in: the result for a model is looked up by its added effects; returns the added effects of
    each call and the converter each was told to assume."""
    calls, told = [], []

    def run_check(ev, effects, dither=None):
        added = tuple(e.key for e in effects if e.key not in {b.key for b in base_model()})
        calls.append(added)
        pixel, flagged = table[added]
        result = _result([e.key for e in effects], pixel, flagged)
        # each model finds the converter 0.5 DN wider than the one it was told to assume (a marker, not physics)
        result.quantiser = {"dither": (dither or 0.0) + 0.5, "compared": True, "variance_chi2": {}}
        told.append(dither)
        return result

    monkeypatch.setattr(sel_mod, "run_check", run_check)
    return calls, told


def test_adds_flagged_candidates_until_nothing_is_flagged(monkeypatch):
    _, told = _fake(monkeypatch, {(): (8.0, ["prnu", "dark_current"]), ("prnu",): (4.0, ["dark_current"]),
                                  ("prnu", "dark_current"): (1.02, [])})
    sel = forward_select(None, base_model())
    assert [s.label for s in sel.steps] == ["base", "+prnu", "+dark_current"]
    assert sel.added == ["prnu", "dark_current"] and sel.reason == sel_mod.NOTHING_FLAGGED
    # each added model's fit starts from the converter the model before it found
    assert told == [None, 0.5, 1.0]
    assert sel.stopped == "nothing flagged"
    assert [s.error["pixel"] for s in sel.steps] == [8.0, 4.0, 1.02]
    assert sel.result.baseline is sel.steps[0].result
    out = sel.to_dict()
    assert [p["step"] for p in out["path"]] == ["base", "+prnu", "+dark_current"]
    assert out["stopped"] == "nothing flagged" and out["effects"][-2:] == ["prnu", "dark_current"]
    assert out["path"][0]["top"]["effect"] == "prnu" and "before" in out
    json.dumps(out, default=float)


def test_a_candidate_that_does_not_improve_is_skipped_once_then_the_next_is_tried(monkeypatch):
    calls, _ = _fake(monkeypatch, {(): (8.0, ["gain", "prnu"]), ("gain",): (7.99, ["prnu"]),
                                ("prnu",): (1.03, ["gain"]), ("prnu", "gain"): (1.03, ["gain"])})
    sel = forward_select(None, base_model())
    assert sel.added == ["prnu"]
    assert [a.effect for a in sel.steps[1].rejected] == ["gain"]
    assert "did not lower the error" in sel.steps[1].rejected[0].reason
    # gain is flagged again after +prnu: tried once more on the new model, not kept, stop and say why
    assert sel.reason == sel_mod.NO_IMPROVEMENT and "adding gain did not" in sel.stopped
    assert calls == [(), ("gain",), ("prnu",), ("prnu", "gain")]


def test_stops_when_neither_of_the_top_two_improves(monkeypatch):
    _fake(monkeypatch, {(): (8.0, ["gain", "prnu", "dsnu"]), ("gain",): (8.0, ["prnu"]), ("prnu",): (8.1, [])})
    sel = forward_select(None, base_model())
    assert [s.label for s in sel.steps] == ["base"] and sel.reason == sel_mod.NO_IMPROVEMENT
    assert "adding gain did not" in sel.stopped and "adding prnu did not" in sel.stopped
    assert [a.effect for a in sel.rejected] == ["gain", "prnu"]


def test_max_steps_and_a_failing_fit(monkeypatch):
    _fake(monkeypatch, {(): (8.0, ["prnu", "dark_current"]), ("prnu",): (4.0, ["dark_current"])})
    sel = forward_select(None, base_model(), max_steps=1)
    assert sel.added == ["prnu"] and sel.reason == sel_mod.MAX_STEPS and "dark_current" in sel.stopped

    def broken(ev, effects, dither=None):
        if len(effects) > len(base_model()):
            raise ValueError("singular")
        return _result([e.key for e in effects], 8.0, ["prnu"])

    monkeypatch.setattr(sel_mod, "run_check", broken)
    sel = forward_select(None, base_model())
    assert sel.reason == sel_mod.NO_IMPROVEMENT and "adding prnu failed: singular" in sel.stopped


def test_unsettled_fits_and_lost_pixel_classes_are_refused(monkeypatch):
    """A step whose fit did not settle, or that left no normal pixel to score (detection against a diverged
    model took every pixel for a defect: error only for 'stuck', gof 1), is not kept however its numbers look."""
    from forensics.check.result import ParamEstimate

    before = _result([], 1.04, ["shot_noise"], gof_pixel=1e-300)
    before.error["classes"] = {"normal": 1.04, "partial": None, "stuck": None}
    lost = _result([], 22.0, [], gof_pixel=1.0)
    lost.error["classes"] = {"normal": None, "partial": None, "stuck": 22.0}
    assert sel_mod._problem(before, lost) == "no normal pixels are left to score"
    moving = _result([], 1.0, [], gof_pixel=0.5)
    moving.params = [ParamEstimate("dark_current", "offset", -1187.0, None, "DN", converged=False)]
    assert "did not converge (dark_current.offset)" in sel_mod._problem(before, moving)
    fine = _result([], 1.0, [], gof_pixel=0.5)
    fine.error["classes"] = {"normal": 1.0, "partial": None, "stuck": None}
    assert sel_mod._problem(before, fine) is None

    def run_check(ev, effects, dither=None):
        return before if len(effects) == len(base_model()) else lost

    monkeypatch.setattr(sel_mod, "run_check", run_check)
    sel = forward_select(None, base_model())
    assert sel.added == [] and "no normal pixels are left" in sel.stopped


def test_a_recovering_gof_counts_as_improvement():
    before = _result([], 1.0, ["clusters"], gof_pixel=1e-6)
    assert sel_mod.improvement(before, _result([], 1.0, [], gof_pixel=0.3)) == "gof.pixel 1e-06 → 0.3"
    assert sel_mod.improvement(before, _result([], 0.995, [], gof_pixel=2e-6)) is None


def test_the_pixel_errors_tolerance_is_its_sampling_noise():
    """3 SE of an error over n pixel means (relative SD 1/√(2n)): 1 % at n = 45,000; a fall of 0.7 % is kept at
    n = 110,000 (EMVA-sized data) and not at n = 10,000."""
    assert sel_mod.pixel_error_tolerance(45_000) == pytest.approx(0.01, rel=1e-3)
    assert sel_mod.pixel_error_tolerance(None) == sel_mod.ERROR_TOL["pixel"]
    before = _result([], 1.017, ["prnu"])
    after = _result([], 1.010, [])
    before.error["classes"] = {"normal": 1.017}
    after.error["classes"] = {"normal": 1.010}
    after.data = {"held_out_means": {"normal": 110_000}}
    assert sel_mod.improvement(before, after) == "error.pixel 1.02 → 1.01"
    after.data = {"held_out_means": {"normal": 10_000}}
    assert sel_mod.improvement(before, after) is None


def test_a_paired_fall_counts_where_the_unpaired_tolerance_cannot_see_it():
    """Two models scored on the same 10,000 held-out means: the noise (χ²₁ per mean) is common to both, the
    second model removes a small misfit (0.1 σ per mean, 1 % of error²).  Unpaired, a 0.5 % fall of the error is
    inside 3 SE (1/√(2n) = 0.7 % each); paired, the difference's own spread is that of 2·0.1·z·σ (SD 0.2), so
    the fall of 0.01 in error² has SE 0.2/√n = 0.002: z ≈ 5.  With the misfit removed from nothing (the same
    residuals) the paired test must not fire."""
    from forensics.check.result import HeldOut

    rng = np.random.default_rng(12)
    n = 10_000
    noise = rng.standard_normal(n)
    classes = np.zeros(n, np.int8)  # all normal
    floor = np.ones(n, np.float32)
    before = _result([], 1.005, ["prnu"])
    after = _result([], 1.0, [])
    before.error["classes"], after.error["classes"] = {"normal": 1.005}, {"normal": 1.0}
    after.data = {"held_out_means": {"normal": n}}
    before.heldout = HeldOut(((noise + 0.1) ** 2).astype(np.float32), floor, classes)
    after.heldout = HeldOut((noise**2).astype(np.float32), floor, classes)
    fall, se = sel_mod.paired_fall(before, after, "normal")
    assert fall == pytest.approx(0.01 + 0.2 * noise.mean(), abs=1e-6)
    assert se == pytest.approx(0.2 / np.sqrt(n), rel=0.03)  # SD of 0.2·z + 0.01 over √n; the SD's own error 0.7 %
    assert sel_mod.improvement(before, after).startswith("error.classes.normal")
    after.heldout = before.heldout
    assert sel_mod.paired_fall(before, after, "normal")[0] == 0.0
    assert sel_mod.improvement(before, after) is None


def test_one_class_falling_does_not_make_up_for_all_classes_rising():
    """A few hot pixels' error² falls clearly (paired z ≈ 10) while the many normal pixels' rises more (a
    nonlinearity on a dark series: normal error 2.5 → 4.4): together the error² rose beyond its noise, so nothing
    counts as an improvement.  The same hot pixels' fall with the normal pixels unchanged still counts."""
    from forensics.check.classes import CLASSES
    from forensics.check.result import HeldOut

    rng = np.random.default_rng(5)
    n_normal, n_hot = 10_000, 200
    z = rng.standard_normal(n_normal + n_hot)
    classes = np.r_[np.zeros(n_normal), np.full(n_hot, CLASSES.index("partial"))].astype(np.int8)
    floor = np.ones(n_normal + n_hot, np.float32)
    misfit = np.r_[np.zeros(n_normal), np.full(n_hot, 3.0)]  # the hot pixels' misfit before
    before = _result([], 3.0, [])
    before.error["classes"] = {"normal": 1.0, "partial": 3.2}
    before.heldout = HeldOut(((z + misfit) ** 2).astype(np.float32), floor, classes)
    worse_normal = np.r_[np.full(n_normal, 1.5), np.zeros(n_hot)]  # the normal pixels' new misfit after
    after = _result([], 1.9, [])
    after.error["classes"] = {"normal": 1.8, "partial": 1.0}
    after.data = {"held_out_means": {"normal": n_normal, "partial": n_hot}}
    after.heldout = HeldOut(((z + worse_normal) ** 2).astype(np.float32), floor, classes)
    fall, se = sel_mod.paired_fall(before, after, "partial")
    assert fall > 3 * se  # the hot pixels alone: a clear fall
    total, total_se = sel_mod.paired_fall(before, after, None)
    assert -total > 3 * total_se
    assert sel_mod.improvement(before, after) is None
    after.heldout = HeldOut((z**2).astype(np.float32), floor, classes)  # the normal pixels as they were
    assert sel_mod.improvement(before, after).startswith("error.classes.partial")


# ------------------------------------------------------------------------------------ several hidden effects
def test_the_generator_hides_several_effects():
    assert [e.key for e in hidden_effects(PAIR)] == PAIR and hidden_effects("none") == []
    assert hidden_effect("prnu").key == "prnu" and [e.key for e in hidden_effect(PAIR)] == PAIR
    names = [e.key for e in hidden_model(PAIR).effects]
    assert set(PAIR) <= set(names) and "growth" in names
    with pytest.raises(Exception, match="twice"):
        hidden_effects(["prnu", "prnu"])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("select") / "pair"
    made = make_hidden(PAIR, out, rng=SEED)
    return made, check_auto(out, rng=SEED)


def test_truth_lists_every_hidden_effect(pair):
    made, _ = pair
    truth = json.loads((made.out / "truth.json").read_text())
    assert truth["hidden_effects"] == PAIR and truth["hidden"] == "prnu+dark_current"
    assert truth["hidden_params"]["prnu"]["sigma_k"] == HIDDEN["prnu"]["sigma_k"]
    assert made.hidden_effects == PAIR


def test_auto_adds_exactly_the_hidden_effects(pair):
    _, sel = pair
    assert isinstance(sel, SelectionResult)
    assert sel.steps[0].label == "base" and set(PAIR) <= set(sel.steps[0].flagged)
    assert sorted(sel.added) == sorted(PAIR), [(s.label, s.flagged) for s in sel.steps]
    assert sel.reason == sel_mod.NOTHING_FLAGGED and sel.result.flagged == []
    assert sel.result.error["pixel"] <= 1.1
    pixel = [s.error["pixel"] for s in sel.steps]
    assert all(b > a for b, a in itertools.pairwise(pixel)), pixel


def test_auto_on_data_with_nothing_hidden_is_just_the_base(tmp_path):
    made = make_hidden("none", tmp_path / "none", rng=3)
    sel = check_auto(made.out, rng=3)
    assert [s.label for s in sel.steps] == ["base"] and sel.stopped == "nothing flagged"
    assert sel.result.baseline is None and sel.to_dict()["path"][0]["flagged"] == []
