"""Tests of forensics.prnu.match: NCC, PCE (zero shift vs search), queries and score matrices."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage, stats

from forensics._shared.errors import InputError, UsageError
from forensics.prnu.fingerprint import Fingerprint, FingerprintBuilder
from forensics.prnu.match import (
    PCE_THRESHOLD,
    MatchScore,
    Query,
    match_set,
    _false_alarm,
    ncc,
    orientations,
    pce,
    prepare_query,
    score_matrix,
    score_pair,
    score_query,
)

SHAPE = (256, 256)
N_QUERIES = 6


def flat_scene(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    field = ndimage.gaussian_filter(rng.normal(0, 1, shape), 24)
    return 120 + 25 * field / field.std()


def natural_scene(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Shading, edges and fine texture: a harder scene than a flat field."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    scene = 110 + 50 * np.sin(xx / 37 + rng.uniform(0, 6)) * np.cos(yy / 23)
    scene += 25 * ((xx // 40 + yy // 30) % 2)
    scene += ndimage.gaussian_filter(rng.normal(0, 25, shape), 1.5)
    return scene


def camera_image(rng: np.random.Generator, scene: np.ndarray, k: np.ndarray, noise: float = 3.0) -> np.ndarray:
    img = scene * (1 + k) + rng.normal(0, noise, scene.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def cameras() -> dict:
    """Two cameras (PRNU σ = 0.5 %), a 16-flat-field fingerprint of A, natural queries from both."""
    rng = np.random.default_rng(8675309)
    k_a = rng.normal(0, 0.005, SHAPE)
    k_b = rng.normal(0, 0.005, SHAPE)
    builder = FingerprintBuilder()
    for _ in range(16):
        builder.add(camera_image(rng, flat_scene(rng, SHAPE), k_a))
    return {
        "fp": builder.result(),
        "k_a": k_a,
        "from_a": [camera_image(rng, natural_scene(rng, SHAPE), k_a) for _ in range(N_QUERIES)],
        "from_b": [camera_image(rng, natural_scene(rng, SHAPE), k_b) for _ in range(N_QUERIES)],
    }


# ----------------------------------------------------------------------------- NCC


def test_ncc_basic_values():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 40))
    assert ncc(a, a) == pytest.approx(1.0)
    assert ncc(a, -3 * a + 7) == pytest.approx(-1.0)
    assert ncc(a, np.ones_like(a)) == 0.0
    with pytest.raises(InputError):
        ncc(a, a[:, :-1])


finite = st.floats(-1e3, 1e3, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, (6, 7), elements=finite), arrays(np.float32, (6, 7), elements=finite))
def test_ncc_symmetric_and_bounded(a, b):
    r = ncc(a, b)
    assert -1.0 <= r <= 1.0
    assert r == pytest.approx(ncc(b, a), abs=1e-12)


# ----------------------------------------------------------------------------- PCE


def brute_force_pce(a: np.ndarray, b: np.ndarray, exclusion: int = 11) -> float:
    """Signed PCE at zero shift from the circular correlation computed shift by shift."""
    a = a - a.mean()
    b = b - b.mean()
    h, w = a.shape
    c = np.array([[np.sum(a * np.roll(b, (dy, dx), axis=(0, 1))) for dx in range(w)] for dy in range(h)])
    r = exclusion // 2
    keep = np.ones_like(c, bool)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            keep[dy % h, dx % w] = False
    return float(np.sign(c[0, 0]) * c[0, 0] ** 2 / np.mean(c[keep] ** 2))


def test_pce_matches_brute_force():
    rng = np.random.default_rng(2)
    b = rng.normal(size=(24, 30))
    a = 0.3 * b + rng.normal(size=b.shape)
    result = pce(a, b)
    assert result.pce == pytest.approx(brute_force_pce(a, b), rel=1e-4)
    assert result.shift == (0, 0) and result.n_shifts == 1 and result.sign == 1
    anti = pce(-a, b)
    assert anti.pce == pytest.approx(-result.pce, rel=1e-4) and anti.sign == -1


def test_pce_finds_a_shift_only_when_asked():
    rng = np.random.default_rng(3)
    b = rng.normal(size=(128, 160)).astype(np.float32)
    a = np.roll(b, (3, -5), axis=(0, 1)) + rng.normal(0, 2, b.shape).astype(np.float32)
    searched = pce(a, b, shift_range=8)
    assert searched.shift == (3, -5)
    assert searched.pce > 1000 and searched.n_shifts == 17 * 17
    assert abs(pce(a, b).pce) < 20  # zero shift: nothing there (|z| < 4.5)
    assert pce(a, b, shift_range=None).shift == (3, -5)


def test_false_alarm_probability():
    # one shift: p = Q(z)
    p, log10 = _false_alarm(2.0, 1)
    assert p == pytest.approx(stats.norm.sf(2.0), rel=1e-9) and log10 == pytest.approx(math.log10(p))
    # n shifts: 1 − (1 − p)^n
    p100, _ = _false_alarm(2.0, 100)
    assert p100 == pytest.approx(1 - stats.norm.cdf(2.0) ** 100, rel=1e-9)
    # far tail: p underflows but log10 stays finite and ordered
    _, l1 = _false_alarm(60.0, 1)
    _, l2 = _false_alarm(80.0, 1)
    assert np.isfinite(l1) and np.isfinite(l2) and l2 < l1 < -700
    assert _false_alarm(-3.0, 10)[0] == pytest.approx(1.0)


def test_pce_rejects_bad_input():
    a = np.zeros((40, 40))
    with pytest.raises(InputError):
        pce(a, a[:, :30])
    with pytest.raises(InputError):
        pce(np.zeros((15, 15)), np.zeros((15, 15)))  # smaller than twice the exclusion window
    with pytest.raises(UsageError):
        pce(a, a, exclusion=10)
    with pytest.raises(UsageError):
        pce(a, a, shift_range=-1)
    assert pce(a, a).pce == 0.0  # degenerate: no evidence, no crash


# ----------------------------------------------------------------------------- the detector on synthetic cameras


def test_matching_and_non_matching_pairs(cameras):
    """Matching PCE ≫ 60; non-matching PCE is a χ²₁ draw (|PCE| < 15 has probability 1 − 1e-4).

    Genuine PCE measured over 4 seeds × 6 queries: 563–778 (spread ≈ 8 %); 300 is
    far below that and still 5× the decision threshold.
    """
    fp = cameras["fp"]
    genuine = [score_query(fp, img) for img in cameras["from_a"]]
    impostor = [score_query(fp, img) for img in cameras["from_b"]]
    assert min(s.value for s in genuine) > 5 * PCE_THRESHOLD
    assert max(abs(s.value) for s in impostor) < 15
    assert all(s.pce.log10_p_fa < -20 for s in genuine)
    assert all(s.pce.shift == (0, 0) and s.rotation == 0 for s in genuine)


def test_shift_search_inflates_impostor_pce(cameras):
    """Over 65 536 circular shifts the maximum of null values sits near 2·ln(65 536) ≈ 22.

    Each searched impostor PCE exceeds its zero-shift PCE and 9 (P(max of 65 536
    standard normals < 3) ≈ e^-88); the false-alarm probability accounts for the search.
    """
    fp = cameras["fp"]
    for img in cameras["from_b"]:
        zero = score_query(fp, img)
        searched = score_query(fp, img, shift_range=None)
        assert searched.value > max(zero.value, 9.0)
        assert searched.pce.n_shifts == SHAPE[0] * SHAPE[1]
        assert searched.pce.log10_p_fa > -2  # not significant once the search is accounted for
    genuine = score_query(fp, cameras["from_a"][0], shift_range=None)
    assert genuine.pce.shift == (0, 0)


def test_ncc_metric(cameras):
    fp = cameras["fp"]
    g = score_query(fp, cameras["from_a"][0], metric="ncc")
    i = score_query(fp, cameras["from_b"][0], metric="ncc")
    assert g.metric == "ncc" and g.pce is None
    assert g.value > 10 * abs(i.value)
    # the NCC reported with PCE is the same number
    assert score_query(fp, cameras["from_a"][0]).ncc == pytest.approx(g.value, rel=1e-4)
    with pytest.raises(UsageError):
        score_query(fp, cameras["from_a"][0], metric="psnr")


def test_portrait_queries_are_rotated():
    """A frame stored turned by 90° is matched after turning it back; either direction works."""
    rng = np.random.default_rng(31337)
    shape = (128, 192)
    k = rng.normal(0, 0.01, shape)
    builder = FingerprintBuilder()
    for _ in range(8):
        builder.add(camera_image(rng, flat_scene(rng, shape), k))
    fp = builder.result()
    image = camera_image(rng, natural_scene(rng, shape), k)
    straight = score_query(fp, image)
    assert straight.rotation == 0 and straight.value > PCE_THRESHOLD
    for turns, expected in ((1, 3), (3, 1)):
        portrait = np.ascontiguousarray(np.rot90(image, turns))
        score = score_query(fp, portrait)
        assert score.rotation == expected
        assert score.value == pytest.approx(straight.value, rel=1e-5)
        assert score.pce.n_shifts == 2  # two orientations tried: counted in p_FA
    with pytest.raises(InputError):
        score_query(fp, image[:100])


def test_orientations():
    # square frames cannot tell: 'auto' leaves them as they are (pass rotations=... to try turns)
    assert orientations((256, 256), (256, 256)) == (0,)
    assert orientations((300, 200), (200, 300)) == (1, 3)
    with pytest.raises(InputError):
        orientations((100, 200), (200, 300))


def test_explicit_rotations(cameras):
    fp = cameras["fp"]
    image = cameras["from_a"][1]
    turned = np.ascontiguousarray(np.rot90(image, 1))
    assert score_query(fp, turned).value < PCE_THRESHOLD  # square: 'auto' does not turn it
    score = score_query(fp, turned, rotations=(0, 1, 2, 3))
    assert score.rotation == 3 and score.value > 5 * PCE_THRESHOLD and score.pce.n_shifts == 4


def test_score_matrix(cameras):
    fp_a = cameras["fp"]
    fp_b = build_b_fingerprint()
    queries = cameras["from_a"][:2] + cameras["from_b"][:2]
    scores, details = score_matrix([fp_a, fp_b], queries, details=True)
    assert scores.shape == (2, 4)
    assert np.all(scores[0, :2] > PCE_THRESHOLD) and np.all(scores[1, 2:] > PCE_THRESHOLD)
    assert np.all(np.abs(scores[0, 2:]) < PCE_THRESHOLD) and np.all(np.abs(scores[1, :2]) < PCE_THRESHOLD)
    assert isinstance(details[0][0], MatchScore)
    for j, img in enumerate(queries):
        assert scores[0, j] == pytest.approx(score_query(fp_a, img).value, rel=1e-6)
    # prepared queries and (residual, intensity) pairs give the same numbers
    prepared = [prepare_query(img, fp_a.region) for img in queries]
    assert isinstance(prepared[0], Query)
    np.testing.assert_allclose(score_matrix([fp_a, fp_b], prepared), scores, rtol=1e-6)
    pairs = [(q.residual, q.intensity) for q in prepared]
    np.testing.assert_allclose(score_matrix([fp_a, fp_b], pairs), scores, rtol=1e-6)
    ncc_scores = score_matrix([fp_a], queries, metric="ncc")
    assert ncc_scores.shape == (1, 4) and np.all(np.abs(ncc_scores) <= 1)


def build_b_fingerprint() -> Fingerprint:
    rng = np.random.default_rng(8675309)
    rng.normal(0, 0.005, SHAPE)  # replay the fixture's draws: k_a, then k_b
    k_b = rng.normal(0, 0.005, SHAPE)
    other = np.random.default_rng(99)
    builder = FingerprintBuilder()
    for _ in range(16):
        builder.add(camera_image(other, flat_scene(other, SHAPE), k_b))
    return builder.result()


def test_region_mismatch_is_refused(cameras):
    fp = cameras["fp"]
    q = prepare_query(cameras["from_a"][0], "center:64")
    with pytest.raises(InputError):
        score_pair(fp, q)
    with pytest.raises(InputError):
        score_pair(fp, (q.residual, q.intensity))
    with pytest.raises(InputError):
        score_query(fp, cameras["from_a"][0][:100])


def test_queries_are_not_modified(cameras):
    image = cameras["from_a"][0].copy()
    image.flags.writeable = False
    score_query(cameras["fp"], image)
    score_matrix([cameras["fp"]], [image])
    np.testing.assert_array_equal(image, cameras["from_a"][0])


@pytest.mark.parametrize("region", ["corners:64", "center:128"])
def test_regions_end_to_end(region):
    """The paper's corner patches and a centre crop both identify the camera."""
    rng = np.random.default_rng(2718)
    k_a = rng.normal(0, 0.005, SHAPE)
    k_b = rng.normal(0, 0.005, SHAPE)
    builder = FingerprintBuilder(region=region)
    for _ in range(16):
        builder.add(camera_image(rng, flat_scene(rng, SHAPE), k_a))
    fp = builder.result()
    genuine = score_query(fp, camera_image(rng, natural_scene(rng, SHAPE), k_a))
    impostor = score_query(fp, camera_image(rng, natural_scene(rng, SHAPE), k_b))
    assert genuine.value > PCE_THRESHOLD and abs(impostor.value) < 15
    assert score_query(fp, camera_image(rng, natural_scene(rng, SHAPE), k_a), metric="ncc").value > 0


# ----------------------------------------------------------------------------- content-free queries (issue 26)


def _dataset(folder: Path, images: list[np.ndarray]) -> object:
    from forensics.io.dataset import open_dataset
    from forensics.io.images import write_image

    folder.mkdir()
    for i, image in enumerate(images):
        write_image(folder / f"q{i:02d}.png", image)
    return open_dataset(folder)


def test_content_free_queries_are_not_scored(cameras, tmp_path):
    """D06: a black frame with a few hot pixels, a saturated and a constant frame among real queries get no score
    (not a PCE taken at face value); a set of nothing but such frames is refused, naming the set and why."""
    black = np.zeros(SHAPE, np.uint8)
    black.flat[np.random.default_rng(1).choice(black.size, 30, replace=False)] = 45
    junk = [black, np.full(SHAPE, 255, np.uint8), np.full(SHAPE, 77, np.uint8)]
    ds = _dataset(tmp_path / "mixed", cameras["from_a"][:2] + junk)
    result = match_set(cameras["fp"], ds)
    rows = result.scores
    assert [r["excluded"] is None for r in rows] == [True, True, False, False, False]
    assert all(r["score"] > PCE_THRESHOLD and r["match"] for r in rows[:2])
    assert all(r["score"] is None and r["match"] is None and r["ncc"] is None for r in rows[2:])
    assert "mostly black" in rows[2]["excluded"] and "all saturated" in rows[3]["excluded"]
    assert result.to_dict()["n_excluded"] == 3 and result.n_match == 2
    scores, details = score_matrix([cameras["fp"]], junk, details=True)
    assert np.all(np.isnan(scores)) and all(d.excluded for d in details[0])
    with pytest.raises(InputError, match="content-free"):
        score_query(cameras["fp"], black)
    with pytest.raises(InputError, match=r"black: every one of its 2 frame\(s\) is content-free"):
        match_set(cameras["fp"], _dataset(tmp_path / "black", [black, np.zeros(SHAPE, np.uint8)]))


@pytest.mark.parametrize("bad", ["nan", "constant"])
def test_a_fingerprint_without_a_pattern_is_never_matched(cameras, bad):
    """D20: NaN or constant K is refused by every matching entry point (not scored as PCE 0 or NaN)."""
    fp = cameras["fp"]
    k = np.full(fp.K.shape, np.nan if bad == "nan" else 0.0, np.float32)
    broken = Fingerprint(k, fp.region, fp.sigma, fp.files, fp.n_images, fp.frame_shape, fp.parameters)
    image = cameras["from_a"][0]
    for call in (lambda: score_query(broken, image), lambda: score_matrix([broken], [image])):
        with pytest.raises(InputError, match="NaN or infinite|constant"):
            call()


def test_a_threshold_that_is_not_a_number_is_refused(cameras, tmp_path):
    with pytest.raises(UsageError, match="threshold=nan"):
        match_set(cameras["fp"], _dataset(tmp_path / "q", cameras["from_a"][:1]), threshold=float("nan"))
