"""The demo's cooled-CCD section: the real 2017 STL-1001E series against issue 28's independent figures where the
shared data are, a synthetic FITS series against its truth where they are not (the demo runs anywhere)."""
from __future__ import annotations

import pytest

from forensics._shared.progress import no_progress
from forensics.demo import ccd
from tests.conftest import shared_or_skip


def test_figures_agree_when_the_intervals_overlap():
    measured = [{"kind": "rate", "set_point": -5.0, "quantity": "r", "value": 0.352, "ci": [0.350, 0.354]},
                {"kind": "rate", "set_point": -10.0, "quantity": "r10", "value": 0.19, "ci": [0.18, 0.20]},
                {"kind": "gain", "set_point": None, "quantity": "g1", "value": 1.93, "ci": [1.93, 1.94]},
                {"kind": "gain", "set_point": None, "quantity": "g2", "value": 1.90, "ci": [1.86, 1.94]}]
    refs = [ccd.Reference("rate", -5.0, 0.35, 0.345, 0.355, "x"), ccd.Reference("rate", -10.0, 0.17, 0.165, 0.175, "x"),
            ccd.Reference("gain", None, 2.06, 2.06, 2.06, "EGAIN")]
    rows = ccd.compare(measured, refs)
    assert [(r["quantity"], r["agree"]) for r in rows] == [("r", True), ("r10", False), ("g1", False), ("g2", False)]


def test_without_the_shared_data_the_section_runs_on_a_synthetic_series(tmp_path, monkeypatch):
    monkeypatch.setenv("FORENSICS_SHARED_DATA", str(tmp_path / "absent"))
    work = tmp_path / "work"
    work.mkdir()
    section = ccd.run(work, 0, no_progress)
    data = section.data
    assert data["real"] is False and "synthetic" in section.summary[0]
    kinds = sorted(r["kind"] for r in data["figures"])
    assert kinds == ["bias_all", "gain", "gain", "hot_pixels", "rate", "rate", "read_noise", "read_noise"]
    # every figure against the truth the series was made from: 95 % intervals whose calibration
    # tests/defects/test_darkseries.py checks (read noise: the range of the group's and each bias frame's estimate,
    # about ±0.1 ADU on ten 96×64 biases); the seed is fixed
    disagree = [r["quantity"] for r in data["figures"] if not r["agree"]]
    assert not disagree, disagree
    assert {r["source"].split(" ")[0] for r in data["figures"]} == {"truth"}
    assert "not on this machine" in section.report.html()


def test_the_real_2017_series_against_the_independent_figures(tmp_path, monkeypatch):
    shared = shared_or_skip(ccd.REAL_SERIES).parent
    monkeypatch.setenv("FORENSICS_SHARED_DATA", str(shared))
    section = ccd.run(tmp_path, 0, no_progress)
    data = section.data
    assert data["real"] is True
    agree = {r["quantity"]: r["agree"] for r in data["figures"]}
    # the median dark rates at the effective temperatures, the bias over all biases, both groups' read noise and
    # both gains: inside (or overlapping) the independent figures' stated precision
    assert all(agree.values()), agree
    assert sorted(r["kind"] for r in data["figures"]) == ["bias_all", "gain", "gain", "rate", "rate", "read_noise",
                                                          "read_noise"]
    assert data["hot_pixels"] > 0 and data["hot_pixels_ci"][0] < data["hot_pixels"] < data["hot_pixels_ci"][1]
