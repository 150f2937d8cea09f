"""The generator of data with a hidden effect (fixtures/hidden.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from forensics.fixtures.hidden import CANDIDATES, HIDDEN, Design, hidden_model, make_hidden
from forensics.io.dataset import open_dataset
from forensics._shared.errors import UsageError


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    out = tmp_path_factory.mktemp("hidden") / "gain"
    return make_hidden("gain", out, seed=4)


def test_dataset_in_the_documented_format(lab):
    ds = open_dataset(lab.out)
    assert len(ds) == lab.n_frames == 72 + 9 * 4
    frame = ds[0]
    assert frame.captured is not None and frame.exposure_s is not None and frame.iso is not None
    assert frame.temperature_c is not None
    assert ds.shape() == (128, 128)
    img = frame.load()
    assert img.dtype == np.uint16 and img.max() <= 4095


def test_design_meets_the_issue_minimum(lab):
    ds = open_dataset(lab.out)
    epochs = ds.epochs(0.25)
    assert len(epochs) >= 5
    last = epochs[-1]
    assert len({f.subject for f in last}) >= 3
    assert len({f.exposure_s for f in last}) >= 3
    assert len({f.temperature_c for f in last}) >= 2
    assert len({f.iso for f in last}) >= 2
    sizes = [len(g) for g in ds.conditions().values()]
    # conditions repeat within an epoch: group by epoch too
    per = {}
    for f in ds:
        key = (round(f.captured), f.exposure_s, f.iso, f.temperature_c, f.subject)
        per[key] = per.get(key, 0) + 1
    assert min(per.values()) >= 2 and max(sizes) >= 2


def test_truth_names_the_hidden_effect(lab):
    truth = json.loads((lab.out / "truth.json").read_text())
    assert truth["hidden"] == "gain" and truth["params"]["exponent"] == HIDDEN["gain"]["exponent"]
    assert truth["seed"] == 4 and len(truth["epochs"]) == 10
    assert truth["defect_counts"]["partial"][-1] > 100
    names = [e["effect"] for e in truth["model"]["effects"]]
    assert "gain" in names and "growth" in names


def test_flat_fields_are_vignetted_and_scale_with_exposure(lab):
    ds = open_dataset(lab.out)
    flats = [f for f in ds if f.subject == "flat_high" and f.iso == 100 and f.temperature_c == 20
             and f.captured > 2019]
    by_t = {}
    for f in flats:
        by_t.setdefault(f.exposure_s, []).append(f.load().astype(float))
    mean = {t: np.mean(v, axis=0) for t, v in by_t.items()}
    centre = {t: np.median(m[56:72, 56:72]) for t, m in mean.items()}
    corner = np.median(mean[1.0][:12, :12])
    assert corner / centre[1.0] == pytest.approx(0.72, abs=0.04)  # ≈ 0.7 in the very corner
    # light ∝ exposure above the 64-DN pedestal
    assert (centre[1.0] - 64) / (centre[0.5] - 64) == pytest.approx(2.0, rel=0.01)


def test_none_and_user_effects(tmp_path):
    none = make_hidden("none", tmp_path / "none", seed=1)
    assert none.truth["hidden"] is None
    source = tmp_path / "col.py"
    source.write_text("from dataclasses import dataclass\nfrom forensics.sensor.model import Effect, Stage, param\n\n"
                      "@dataclass\nclass Flat(Effect):\n    name = 'flat_offset'\n    stage = Stage.DARK\n"
                      "    d: float = param(5.0, null=0.0)\n\n"
                      "    def apply(self, signal, ctx, rng):\n        signal += self.d\n        return signal\n")
    user = make_hidden(f"{source}:Flat", tmp_path / "user", seed=1)
    assert user.truth["hidden"] == "flat_offset"
    with pytest.raises(UsageError):
        make_hidden("offset", tmp_path / "base", seed=1)
    with pytest.raises(UsageError):
        make_hidden("none", tmp_path / "none", seed=1)  # exists, no force


def test_same_seed_same_data(tmp_path):
    a = make_hidden("prnu", tmp_path / "a", seed=9, design=Design(ages=(0, 1, 2), shape=(32, 32)))
    b = make_hidden("prnu", tmp_path / "b", seed=9, design=Design(ages=(0, 1, 2), shape=(32, 32)))
    fa = sorted(p.name for p in a.out.glob("*.png"))
    assert fa == sorted(p.name for p in b.out.glob("*.png"))
    from forensics.io.images import read_image

    for name in fa[:5]:
        np.testing.assert_array_equal(read_image(a.out / name), read_image(b.out / name))


def test_every_candidate_has_a_strength():
    assert set(CANDIDATES) | {"dsnu"} == set(HIDDEN)
    for name in CANDIDATES:
        model = hidden_model(name)
        assert model.effect(name) is not None
