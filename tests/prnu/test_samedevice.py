"""Tests of forensics.prnu.samedevice: the paper's same-device protocol on simulated cameras.

Cameras are the sensor model of :mod:`forensics.sensor.model` (preset + ``prnu`` +
``read_noise`` + ``shot_noise``) on 256×256 8-bit frames of smooth scenes, rendered
on demand by :func:`forensics.demo.prnu.simulated_set`.  Counts are far below the
paper's (50 + 800 images per set) to keep the file at about 15 s; the tolerances
follow from what those counts can resolve.
"""
from __future__ import annotations

import json
import re
from collections import Counter

import numpy as np
import pytest
from scipy import ndimage

from forensics.demo.prnu import sensor_model, simulated_set
from forensics._shared.errors import InputError, UsageError
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.prnu.ageing import MedianFingerprintBuilder, ageing_table
from forensics.prnu.samedevice import (
    ImageSet,
    eer_verdict,
    expected_eer_ci_width,
    plan_set,
    same_device,
)
from forensics.stats.scores import bootstrap_eer

YEARS = 50.0
SMALL = dict(fingerprint_images=20, score_images=60, region="full", n_boot=1000)
AGEING = dict(ageing_fingerprints=8, ageing_images=10)


# ----------------------------------------------------------------------------- simulated protocol runs


@pytest.fixture(scope="module")
def two_devices():
    """Two devices of one model (independent PRNU, σ_k = 1 %)."""
    rng = np.random.default_rng(20240601)
    model = sensor_model("A")
    d1, d2 = model.realize(rng, [0.0]), model.realize(rng, [0.0])
    a = simulated_set(d1, 80, 0.0, 11, "device 1")
    b = simulated_set(d2, 80, 0.0, 12, "device 2")
    return same_device(a, b, rng, ageing=False, **SMALL)


@pytest.fixture(scope="module")
def one_device():
    """One device, one epoch, its images split into two disjoint halves (even and odd)."""
    rng = np.random.default_rng(20240602)
    device = sensor_model("A").realize(rng, [0.0])
    images = simulated_set(device, 160, 0.0, 21, "all")
    halves = images.subset(range(0, 160, 2), "even"), images.subset(range(1, 160, 2), "odd")
    return same_device(*halves, rng, **SMALL, **AGEING)


@pytest.fixture(scope="module")
def aged():
    """One device as sensor H, new and after 50 years (8× the iris sensor's rate at 100 DN, plus stuck pixels)."""
    rng = np.random.default_rng(20240603)
    device = sensor_model("H").realize(rng, [0.0, YEARS])
    young = simulated_set(device, 80, 0.0, 31, "new")
    old = simulated_set(device, 80, YEARS, 32, "old")
    return device, same_device(young, old, rng, **SMALL, **AGEING)


def test_two_devices_are_told_apart(two_devices):
    r = two_devices
    assert r.eer.decision == "different"
    assert r.eer.eer <= 0.05 and r.eer.ci[1] < 0.10  # the interval excludes 50 % by far
    # matching NCC ~0.2 here; non-matching NCC of unrelated patterns is ~N(0, 1/√65536)
    assert np.median(r.genuine) > 0.1
    assert abs(np.median(r.impostor)) < 5 / 256
    assert r.ageing is None


def test_one_device_halves_cannot_be_told_apart(one_device):
    r = one_device
    assert r.eer.ci[0] <= 0.5 <= r.eer.ci[1]
    assert r.eer.decision == "indistinguishable"
    # 120 v 120 scores: the interval's width is about 0.98·√(2/120) ≈ 0.18 (±20 % spread across seeds)
    width = r.eer.ci[1] - r.eer.ci[0]
    assert 0.6 * r.eer.expected_width < width < 1.5 * r.eer.expected_width
    # and the ageing table sees one unchanged pattern: consistency interval contains 1
    t = r.ageing
    assert t.n_fingerprints == (8, 8) and t.images_per_fingerprint == (10, 10)
    assert t.consistency.ci[0] <= 1.0 <= t.consistency.ci[1]


def test_heavy_ageing_lowers_inter_set_ncc(aged):
    """Table 2: fingerprints of the two epochs agree less than fingerprints of one epoch.

    Physics: a partially stuck pixel adds a light-independent offset d (here up to
    100 DN).  The 3×3 median residual keeps it as a spike of height ≈ d, and the
    ML estimate Σ W·I / Σ I² as a spike ≈ d/Ī ≈ 0.4 in K — forty times the PRNU's
    σ_k = 0.01.  Every old fingerprint carries the ~30 defects born in 50 years,
    the new ones none.  The intra-set NCC of the old set rises (shared spikes), the
    inter-set NCC gets only what both share (the PRNU) in its numerator and the
    spikes' energy in its denominator: it falls below both intra-set values, and the
    consistency inter/√(intra·intra) — 1 for an unchanged pattern — falls well
    below 1, to √(P/(P + D)).
    """
    device, r = aged
    n_defects = len(device.catalogue.effective(YEARS))
    assert n_defects >= 15  # λ = 5.3 + 3.7 per MP per year × 0.066 MP × 50 years ≈ 30 expected
    t = r.ageing
    assert t.inter_below_intra
    assert t.inter.ci[1] < t.intra_a.ci[0] and t.inter.ci[1] < t.intra_b.ci[0]
    # 0.05–0.83 over 6 seeds (a few stuck pixels far from the scene level dominate); always ±0.01
    assert t.consistency.ci[1] < 0.95
    # the EER sees the change too: images match their own epoch's fingerprint better
    assert r.eer.ci[1] < 0.5
    assert r.eer.decision in ("partly_distinguishable", "different")


def test_median_fingerprint_carries_the_new_defects(aged):
    """The mechanism behind table 2: the old fingerprint has spikes of ≈ d/Ī at the defect sites, the new one not.

    Over 8 seeds the median |K| at partially stuck sites with d > 20 DN was 11–28
    standard deviations of K elsewhere in the old fingerprint, 0.4–1.2 in the new one.
    """
    device, _ = aged
    sites = device.catalogue.effective(YEARS)
    partial = sites.select((sites.kind == PARTIAL) & (sites.amplitude > 20))
    assert len(partial) >= 5
    elsewhere = np.ones(256 * 256, bool)
    elsewhere[sites.y * 256 + sites.x] = False
    ratios = []
    for time, seed in ((YEARS, 41), (0.0, 42)):
        images = simulated_set(device, 12, time, seed, "x")
        builder = MedianFingerprintBuilder("full")
        for i in range(len(images)):
            builder.add(images.load(i))
        k = builder.result().K.ravel()
        ratios.append(np.median(np.abs(k[partial.y * 256 + partial.x])) / k[elsewhere].std())
    assert ratios[0] > 5 and ratios[1] < 2
    assert len(sites.select(sites.kind == STUCK)) > 0  # stuck pixels add spikes too (not asserted: clipping)


# ----------------------------------------------------------------------------- selection


def test_plan_set_disjoint_and_reproducible():
    plan = plan_set(900, np.random.default_rng(5), name="s")
    assert len(plan.fingerprint) == 50 and len(plan.score) == 800
    assert not set(plan.fingerprint) & set(plan.score)
    assert len(plan.ageing_groups) == 16 and {len(g) for g in plan.ageing_groups} == {50}
    flat = [i for g in plan.ageing_groups for i in g]
    assert len(set(flat)) == len(flat) == 800
    assert plan.warnings == ()
    again = plan_set(900, np.random.default_rng(5), name="s")
    assert again == plan


def test_plan_set_small_sets_warn():
    plan = plan_set(60, np.random.default_rng(1), name="tiny")
    assert (len(plan.fingerprint), len(plan.score)) == (30, 30)  # at most half to the fingerprint
    assert len(plan.ageing_groups) == 4 and plan.ageing_images == 15  # shrunk to keep four fingerprints
    assert any("fingerprint uses 30 (not 50)" in w and "30 are scored (not 800)" in w for w in plan.warnings)
    assert any("ageing table uses 4 fingerprints of 15 images" in w for w in plan.warnings)
    plan = plan_set(130, np.random.default_rng(1), name="mid")
    assert (len(plan.fingerprint), len(plan.score)) == (50, 80)
    assert not any("fingerprint uses" in w and "not 50" in w for w in plan.warnings)
    assert len(plan_set(3, np.random.default_rng(1)).fingerprint) == 1
    with pytest.raises(InputError):
        plan_set(1, np.random.default_rng(1))
    with pytest.raises(UsageError):
        plan_set(100, np.random.default_rng(1), fingerprint_images=0)
    with pytest.raises(TypeError):
        plan_set(100, None)  # type: ignore[arg-type]


def test_expected_interval_width_matches_the_bootstrap():
    """0.98·√(1/n_g + 1/n_i) at EER 50 %; checked against the bootstrap itself on identical distributions."""
    assert expected_eer_ci_width(800, 800) == pytest.approx(1.96 * np.sqrt(0.25 * 2 / 800), rel=1e-3)
    rng = np.random.default_rng(77)
    widths = []
    for _ in range(30):
        b = bootstrap_eer(rng.normal(size=60), rng.normal(size=60), rng, n_boot=400)
        widths.append(b.ci[1] - b.ci[0])
    # measured mean width 1.39–1.47/√n over n = 4…1600 (200 runs each); 30 runs: ±4 % standard error
    assert np.mean(widths) == pytest.approx(expected_eer_ci_width(60, 60), rel=0.15)


# ----------------------------------------------------------------------------- verdicts


@pytest.mark.parametrize("shift, decision", [(6.0, "different"), (0.0, "indistinguishable"),
                                              (1.0, "partly_distinguishable"), (-1.0, "anomalous")])
def test_eer_verdict_decisions(shift, decision):
    rng = np.random.default_rng(3)
    g, i = rng.normal(shift, 1, 400), rng.normal(0, 1, 400)
    v = eer_verdict(g, i, rng, n_boot=500)
    assert v.decision == decision
    assert v.ci[0] <= v.eer <= v.ci[1]
    words = {"different": "different devices", "indistinguishable": "consistent with one device",
             "partly_distinguishable": "partly distinguishable", "anomalous": "better than their own"}
    assert words[decision] in v.verdict
    json.dumps(v.to_dict(), allow_nan=False)


def test_wide_interval_is_flagged():
    rng = np.random.default_rng(4)
    v = eer_verdict(rng.normal(size=6), rng.normal(size=6), rng, n_boot=500)
    assert v.decision == "indistinguishable" and "weak evidence" in v.verdict


# ----------------------------------------------------------------------------- ageing table


def _noisy(k: np.ndarray, sd: float, rng: np.random.Generator) -> np.ndarray:
    return (k + rng.normal(0, sd, k.shape)).astype(np.float32)


def test_ageing_table_consistency_is_one_for_one_pattern_whatever_the_noise():
    """intra = P/(P+N_set), inter = P/√((P+N_a)(P+N_b)): a noisier set alone lowers the inter mean, not the ratio."""
    rng = np.random.default_rng(8)
    k = rng.normal(0, 1, (96, 96))
    fa = [_noisy(k, 1.0, rng) for _ in range(8)]  # P/(P+N) = 0.5
    fb = [_noisy(k, 2.0, rng) for _ in range(8)]  # 0.2
    t = ageing_table(fa, fb, rng, names=("clean", "noisy"), n_boot=500)
    assert t.intra_a.mean == pytest.approx(0.5, abs=0.02)
    assert t.intra_b.mean == pytest.approx(0.2, abs=0.02)
    assert t.inter.mean == pytest.approx(np.sqrt(0.5 * 0.2), abs=0.02)
    assert t.intra_b.mean < t.inter.mean < t.intra_a.mean and not t.inter_below_intra  # geometric mean between
    assert t.consistency.ci[0] <= 1.0 <= t.consistency.ci[1]
    assert t.intra_a.n_pairs == 56 and t.inter.n_pairs == 64
    assert "contains 1" in t.verdict
    json.dumps(t.to_dict(), allow_nan=False)


def test_ageing_table_consistency_measures_a_changed_pattern():
    """Set B's pattern is k·cos θ + k'·sin θ: the consistency estimates cos θ."""
    rng = np.random.default_rng(9)
    k, k2 = rng.normal(0, 1, (2, 96, 96))
    theta = np.arccos(0.6)
    kb = np.cos(theta) * k + np.sin(theta) * k2
    t = ageing_table([_noisy(k, 1.0, rng) for _ in range(8)], [_noisy(kb, 1.0, rng) for _ in range(8)], rng,
                     n_boot=500)
    assert t.consistency.mean == pytest.approx(0.6, abs=0.03)
    assert t.consistency.ci[0] < 0.6 < t.consistency.ci[1] < 1.0
    assert t.inter_below_intra and "below 1" in t.verdict


def test_ageing_table_small_inputs():
    rng = np.random.default_rng(10)
    k = rng.normal(0, 1, (32, 32))
    t = ageing_table([_noisy(k, 1, rng) for _ in range(2)], [_noisy(k, 1, rng) for _ in range(2)], rng)
    assert t.consistency.ci is None and t.n_boot == 0 and "too few" in t.verdict
    with pytest.raises(InputError):
        ageing_table([k], [k, k], rng)
    with pytest.raises(InputError):
        ageing_table([k, k], [k[:16], k[:16]], rng)


# ----------------------------------------------------------------------------- estimator and streaming


def test_median_fingerprint_builder_matches_the_batch_formula():
    rng = np.random.default_rng(12)
    images = [rng.integers(40, 200, (64, 80), dtype=np.uint8) for _ in range(3)]
    images[0][5:9, 5:9] = 255  # saturated: excluded with its neighbours
    builder = MedianFingerprintBuilder("full", saturation_dilate=1)
    for img in images:
        builder.add(img)
    num = np.zeros((64, 80))
    den = np.zeros((64, 80))
    for img in images:
        y = img.astype(np.float64)
        w = y - ndimage.median_filter(y, size=3, mode="reflect")
        i = y.copy()
        sat = ndimage.maximum_filter(img == 255, size=3)
        i[sat] = 0
        num += w * i
        den += i * i
    k = np.where(den > 0, num / np.where(den > 0, den, 1), 0)
    k = k.astype(np.float32)
    from forensics.prnu.residual import zero_mean_cfa

    np.testing.assert_allclose(builder.result().K, zero_mean_cfa(k), atol=2e-6)
    assert builder.result().n_images == 3
    with pytest.raises(InputError):
        builder.add(np.zeros((32, 32), np.uint8))


def test_streaming_each_image_loaded_at_most_twice_and_scored_once():
    """Scoring images are read once and scored against both fingerprints; ageing reads an image once more."""
    rng = np.random.default_rng(13)
    device = sensor_model("A", (64, 64)).realize(rng, [0.0])
    base = simulated_set(device, 24, 0.0, 5, "x")
    loads: Counter = Counter()

    def counted(i: int) -> np.ndarray:
        loads[i] += 1
        return base.load(i)

    images = ImageSet.from_function(24, counted, "counted")
    calls = []

    def progress(iterable, total=None, desc=None):
        calls.append((desc, total))
        return iterable

    r = same_device(images.subset(range(12), "a"), images.subset(range(12, 24), "b"), rng, fingerprint_images=4,
                    score_images=8, region="full", ageing_fingerprints=3, ageing_images=4, n_boot=200,
                    progress=progress)
    plan_a = r.set_a.plan
    eer_roles = set(plan_a.fingerprint) | set(plan_a.score)
    ageing_members = {i for g in plan_a.ageing_groups for i in g}
    for i in range(12):
        assert loads[i] == (i in eer_roles) + (i in ageing_members)
    assert max(loads.values()) <= 2
    assert {d for d, _ in calls} >= {"fingerprint a", "scoring a", "scoring b", "ageing a", "ageing b"}
    assert r.set_a.own.size == r.set_a.other.size == 8


def test_result_to_dict_is_json_ready(one_device):
    d = one_device.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    assert set(back) >= {"eer", "eer_ci", "verdict", "ageing", "sets", "warnings"}
    assert back["eer_ci"][0] <= back["eer"] <= back["eer_ci"][1]
    assert len(back["sets"]["a"]["own_fingerprint_scores"]) == 60
    assert back["ageing"]["consistency"]["ci"] is not None


def test_bad_inputs():
    rng = np.random.default_rng(14)
    ok = [rng.integers(50, 200, (32, 32), dtype=np.uint8) for _ in range(4)]  # images with content
    with pytest.raises(InputError, match="at least 2"):
        same_device([ok[0]], ok, rng, region="full")
    with pytest.raises(InputError, match="32×40"):
        same_device(ok, [rng.integers(50, 200, (32, 40), dtype=np.uint8)] * 4, rng, region="full", ageing=False,
                    n_boot=50)
    with pytest.raises(UsageError):
        same_device(ok, ok, rng, region="full", ageing_residual="gaussian")
    with pytest.raises(UsageError):
        same_device(ok, ok, rng, region="full", colour=True)
    with pytest.raises(UsageError):
        same_device((img for img in ok), ok, rng, region="full")
    with pytest.raises(TypeError):
        same_device(ok, ok, None, region="full")  # type: ignore[arg-type]
    with pytest.raises(InputError):  # 4 corners of 128 do not fit a 32×32 frame
        same_device(ok, ok, rng, ageing=False)


def test_sequences_of_arrays_and_paths(tmp_path):
    from forensics.io.images import write_image

    rng = np.random.default_rng(15)
    images = [rng.integers(50, 200, (32, 32), dtype=np.uint8) for _ in range(4)]
    paths = []
    for n, img in enumerate(images):
        paths.append(tmp_path / f"{n}.png")
        write_image(paths[-1], img)
    s = ImageSet.of(paths, "p")
    assert len(s) == 4 and s.sources[0].endswith("0.png")
    np.testing.assert_array_equal(s.load(2), images[2])
    s = ImageSet.of(images)
    assert s.name == "set" and s.sources[1] == "set[1]"
    s = ImageSet.of(tmp_path)
    assert s.name == tmp_path.name and len(s) == 4


# ----------------------------------------------------------------------------- refused inputs (issue 26)


def _folder(path, images):
    from forensics.io.images import write_image

    path.mkdir()
    for i, image in enumerate(images):
        write_image(path / f"{i:02d}.png", image)
    return path


def test_one_set_given_twice_is_refused(tmp_path):
    """D20: ``same-device X X`` (under any spelling of the folder) is a usage error, not 'indistinguishable';
    sets sharing some image files (a link counts) get a warning."""
    rng = np.random.default_rng(16)
    images = [rng.integers(50, 200, (32, 32), dtype=np.uint8) for _ in range(6)]
    folder = _folder(tmp_path / "x", images)
    with pytest.raises(UsageError, match="are the same 6 images"):
        same_device(folder, tmp_path / "x" / ".." / "x", rng, region="full", ageing=False)
    other = _folder(tmp_path / "y", [rng.integers(50, 200, (32, 32), dtype=np.uint8) for _ in range(5)])
    (other / "link.png").symlink_to(folder / "03.png")  # the same file by another name: shared
    result = same_device(folder, other, rng, region="full", ageing=False, n_boot=50)
    assert any(re.match(r"1 image\(s\) are in both .* \(first: .*link.png\)", w) for w in result.warnings)


def test_content_free_sets_are_refused_and_frames_left_out(tmp_path):
    """D07: black against white frames is refused (it said 'different devices, EER 0 %'), naming the set and
    why; a few content-free frames among real ones are left out of the fingerprint and the scores, with a
    warning, and the verdict is the one of the real frames."""
    rng = np.random.default_rng(17)
    black = [np.zeros((64, 64), np.uint8)] * 8
    white = [np.full((64, 64), 255, np.uint8)] * 8
    with pytest.raises(InputError, match=r"black: all 4 frame\(s\) given for the fingerprint are content-free.*"
                                         r"all black"):
        same_device(ImageSet.of(black, "black"), ImageSet.of(white, "white"), rng, region="full", ageing=False)
    device = sensor_model("A", (64, 64)).realize(rng, [0.0])
    a = simulated_set(device, 24, 0.0, 41, "a")
    b = simulated_set(device, 24, 0.0, 42, "b")
    with_junk = ImageSet.of([a.load(i) for i in range(24)] + white[:4], "a+white")
    result = same_device(with_junk, b, np.random.default_rng(18), region="full", ageing=False, n_boot=200)
    left_out = result.set_a.excluded
    assert len(left_out) == 4 and all("all saturated" in why for _, why in left_out)
    plan = result.set_a.plan
    white_fp, white_score = (sum(1 for i in indices if i >= 24) for indices in (plan.fingerprint, plan.score))
    assert white_fp + white_score == 4  # 28 images: 14 for the fingerprint, 14 scored
    assert len(result.set_a.fingerprint_files) == len(plan.fingerprint) - white_fp
    assert len(result.set_a.own) == len(result.set_a.other) == len(plan.score) - white_score
    assert any("content-free" in w for w in result.warnings)
    assert result.eer.decision == "indistinguishable"
    json.dumps(result.to_dict())
