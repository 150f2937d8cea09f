"""Validation: a fast subset of the simulated-truth trials (the full ≥ 400-trial sweep is benchmarks/sweep_validate.py)."""
from __future__ import annotations

import numpy as np

from forensics.validate.trials import (
    ValidationSettings,
    proportion,
    summarise_dating,
    summarise_defects,
    validate_dating,
    validate_defects,
)
from forensics.report.validate import validation_report

FAST = ValidationSettings(shape=(96, 96), pool=48, images=50, dating_years=12, dating_images=15)


def test_defects_fast_subset():
    res = validate_defects(FAST, trials=20, rng=11)
    m = {x.name: x for x in res.metrics}
    recall = m["detection recall, amplitude ≥ 6σ"]
    precision = m["detection precision"]
    # acceptance figures; ~1,000 defects ≥ 6σ in 20 trials make these tight (exact 95 % CIs above 0.95)
    assert recall.n > 500 and recall.value >= 0.95
    assert precision.value >= 0.95
    cover = m["partially-stuck rate: coverage of the 95 % interval"]
    assert cover.n == 20 and cover.value >= 0.8  # 20 trials: P(≤ 16 of 20 | p = 0.95) < 2 %
    d = res.to_dict()
    assert d["what"] == "defects" and len(d["metrics"]) >= 6
    curve = res.curves["recall_vs_amplitude_sigma"]
    low = [c[2] for c in curve if c[0] < 3 and c[2] is not None]
    high = [c[2] for c in curve if c[0] > 8 and c[2] is not None]
    assert max(low) < 0.2 and min(high) > 0.95  # recall switches on around τ = 5σ


def test_dating_fast_subset(tmp_path):
    res = validate_dating(FAST, trials=8, rng=12)
    m = {x.name: x for x in res.metrics}
    assert m["set dating: coverage of the 95 % interval"].n == 8
    assert m["set dating: coverage of the 95 % interval"].value >= 0.75
    assert m["single-image dating: true interval, all trials"].value >= 0.6
    path = validation_report(res).write(tmp_path / "rep")
    assert path.exists() and (tmp_path / "rep" / "coverage.png").exists()


def test_summaries_check_acceptance():
    settings = ValidationSettings()
    recs = [{"tp_big": 99, "n_big": 100, "tp": 100, "fp": 1, "stuck_tp": 0, "stuck_n": 0, "amp_sigma": [7.0],
             "found": [True], "rate_true": 1.0, "rate": 1.0, "rate_lo": 0.5 if i < 95 else 1.5, "rate_hi": 2.0,
             "rate_paper": 0.9, "stuck_true": 0.0, "stuck_rate": 0.0, "stuck_lo": 0.0, "stuck_hi": 1.0, "new": 10,
             "scale": 1.0, "threshold_dn": 5.0} for i in range(100)]
    res = summarise_defects(settings, recs)
    assert res.passed
    recs[0]["tp_big"] = 0  # recall falls to 0.98, still ≥ 0.95
    assert summarise_defects(settings, recs).passed
    for r in recs[:10]:
        r["rate_lo"] = 1.5  # coverage 0.85 < 0.92
    assert not summarise_defects(settings, recs).passed
    sets = [{"t_true": 1.0, "estimate": 1.0, "lo": 0.0, "hi": 2.0, "covered": True, "position": "", "within": False}]
    images = [{"t_true": 1.0, "groups": 12, "distinct": 12, "best": 3, "true": 3, "correct": True}]
    out = summarise_dating(settings, sets * 10, images * 10)
    assert out.metrics[0].passed is False  # coverage 1.0 > 0.98: over-wide intervals fail too
    p = proportion("x", 95, 100, 0.92, 0.98)
    assert p.passed and p.ci[0] < 0.95 < p.ci[1]
    assert np.isnan(proportion("y", 0, 0).value)


def test_int_seed_and_its_generator_give_one_run():
    small = ValidationSettings(shape=(48, 48), pool=6, images=10)
    a = validate_defects(small, trials=2, rng=3)
    b = validate_defects(small, trials=2, rng=np.random.default_rng(3))
    assert a.records == b.records and a.seed == 3
