"""Tests for forensics.stats.scores: ROC, EER (interpolated and convex hull), AUC, DET, bootstrap.

Tolerances are derived in the comments (binomial standard errors, Monte-Carlo
errors of means and standard deviations); the oracles are deliberately plain
re-implementations, not the code under test.
"""
from __future__ import annotations

import io
import json
import math
from fractions import Fraction

import numpy as np
import pytest
from scipy.stats import norm

from forensics.stats import scores as S
from forensics._shared.errors import InputError, UsageError
from forensics.stats.scores import (
    auc,
    bootstrap_ci,
    bootstrap_eer,
    decision_threshold_at_far,
    det_curve,
    eer,
    eer_convex_hull,
    roc,
)
from forensics.report.scores import plot_det, plot_score_histograms


# --------------------------------------------------------------------------- oracles


def brute_force_eer(genuine, impostor) -> tuple[Fraction, float]:
    """Loop over every threshold, count by hand, interpolate the sign change exactly."""
    g, i = list(map(float, genuine)), list(map(float, impostor))
    thresholds = sorted(set(g) | set(i)) + [math.inf]
    points = []
    for t in thresholds:
        far = Fraction(sum(1 for s in i if s >= t), len(i))
        frr = Fraction(sum(1 for s in g if s < t), len(g))
        points.append((t, far, frr))
    for (t0, x0, y0), (t1, x1, y1) in zip(points, points[1:]):
        if y0 - x0 <= 0 < y1 - x1:
            alpha = (x0 - y0) / ((y1 - y0) - (x1 - x0))
            e = x0 + alpha * (x1 - x0)
            thr = t0 if (alpha == 0 or t1 == math.inf) else t0 + float(alpha) * (t1 - t0)
            return e, thr
    raise AssertionError("no crossing")


def brute_force_auc(genuine, impostor) -> float:
    total = 0.0
    for a in genuine:
        for b in impostor:
            total += 1.0 if a > b else 0.5 if a == b else 0.0
    return total / (len(genuine) * len(impostor))


def loop_bootstrap_eer(g, i, rng, n_boot):
    """Per-replicate loop: resample each class with replacement, call eer()."""
    out = np.empty(n_boot)
    for b in range(n_boot):
        out[b] = eer(rng.choice(g, g.size, replace=True), rng.choice(i, i.size, replace=True)).eer
    return out


def random_case(rng, max_n=40, grid=8):
    """Small score sets on a coarse grid, so that ties within and across classes are common."""
    n_g, n_i = rng.integers(1, max_n, size=2)
    shift = rng.uniform(-1, 3)
    g = np.round(rng.normal(shift, 1.0, n_g) * grid / 4) / grid
    i = np.round(rng.normal(0.0, 1.0, n_i) * grid / 4) / grid
    return g, i


# --------------------------------------------------------------------------- EER


def test_eer_matches_theory_for_two_normals():
    # N(0,1) impostor vs N(d,1) genuine: FAR(t) = 1 - Phi(t), FRR(t) = Phi(t - d),
    # equal at t = d/2, EER = Phi(-d/2).  The empirical EER is, to first order,
    # p + w*eps_FAR + (1-w)*eps_FRR with binomial errors of variance p(1-p)/n and
    # a weight w in [0, 1], so its SD is at most sqrt(p(1-p)/min(n_g, n_i)).
    # 4 SD gives a false-failure rate < 1e-4.
    rng = np.random.default_rng(20240601)
    # The second case is large enough for the sort-free path.
    for d, n_g, n_i in [(2.0, 200_000, 200_000), (1.0, 20_000, 600_000)]:
        p = norm.cdf(-d / 2)
        res = eer(rng.normal(d, 1.0, n_g), rng.normal(0.0, 1.0, n_i))
        tol = 4 * math.sqrt(p * (1 - p) / min(n_g, n_i))
        assert abs(res.eer - p) < tol
        # The crossing threshold is d/2; its SD is that of the EER divided by the density phi(d/2).
        assert abs(res.threshold - d / 2) < tol / norm.pdf(d / 2)


def test_exact_crossing_hand_example():
    # genuine = [1, 2, 3], impostor = [0, 2]; accept score >= t.
    #   t = 0 : FAR = 2/2, FRR = 0/3          d = FRR - FAR = -1
    #   t = 1 : FAR = 1/2, FRR = 0/3          d = -1/2
    #   t = 2 : FAR = 1/2, FRR = 1/3          d = -1/6
    #   t = 3 : FAR = 0/2, FRR = 2/3          d = +2/3   (the tie at 2 gives a diagonal step)
    # alpha = (1/6) / (1/6 + 2/3) = 1/5;  EER = 1/2 + (0 - 1/2)/5 = 2/5 (= 1/3 + (2/3 - 1/3)/5);
    # threshold = 2 + (3 - 2)/5 = 2.2.
    res = eer([1.0, 2.0, 3.0], [0.0, 2.0])
    assert res.eer == pytest.approx(0.4, abs=1e-15)
    assert res.threshold == pytest.approx(2.2, abs=1e-15)
    # Convex hull of (FAR, FRR): (0, 2/3), (1/2, 0), (1, 0); (1/2, 1/3) lies above the chord.
    # Edge y = 2/3 - (4/3) x meets y = x at x = 2/7; from threshold 1 (x = 1/2) to 3 (x = 0)
    # the fraction is (1/2 - 2/7)/(1/2) = 3/7, so threshold = 1 + 2 * 3/7 = 13/7.
    hull = eer_convex_hull([1.0, 2.0, 3.0], [0.0, 2.0])
    assert hull.eer == pytest.approx(2 / 7, abs=1e-15)
    assert hull.threshold == pytest.approx(13 / 7, abs=1e-15)
    # genuine = [0.4, 0.9], impostor = [0.1, 0.5, 0.6]: at t = 0.5 FAR = 2/3, FRR = 1/2;
    # at t = 0.6 FAR = 1/3, FRR = 1/2: horizontal step, crossing halfway: EER 1/2 at 0.55.
    res = eer([0.4, 0.9], [0.1, 0.5, 0.6])
    assert res.eer == pytest.approx(0.5, abs=1e-15)
    assert res.threshold == pytest.approx(0.55, abs=1e-12)


def test_perfect_separation_gives_zero():
    g, i = [2.0, 3.0, 5.0], [-1.0, 0.0, 1.0, 1.5]
    res = eer(g, i)
    assert res.eer == 0.0
    # Any threshold in (1.5, 2] separates; the crossing sits on the point at t = 2.
    assert 1.5 < res.threshold <= 2.0
    assert eer_convex_hull(g, i).eer == 0.0
    assert auc(g, i) == 1.0


def test_identical_scores_give_one_half_exactly():
    # Every distinct value is a tie of both classes, so all operating points lie
    # on FAR + FRR = 1 and the crossing is exactly 1/2 (for both EER definitions).
    x = np.random.default_rng(3).normal(size=101)
    assert eer(x, x).eer == pytest.approx(0.5, abs=1e-15)
    assert eer_convex_hull(x, x).eer == pytest.approx(0.5, abs=1e-15)
    assert auc(x, x) == pytest.approx(0.5, abs=1e-15)


def test_same_distribution_eer_near_half_and_ci_covers_it():
    rng = np.random.default_rng(11)
    g, i = rng.normal(size=800), rng.normal(size=800)
    res = bootstrap_eer(g, i, rng, n_boot=1000)
    # SD bound as in the theory test: sqrt(0.25/800) = 0.0177; 4 SD.
    assert abs(res.estimate - 0.5) < 4 * math.sqrt(0.25 / 800)
    assert res.ci[0] <= 0.5 <= res.ci[1]


def test_eer_matches_brute_force_oracle():
    rng = np.random.default_rng(5)
    for _ in range(300):
        g, i = random_case(rng)
        exact, thr = brute_force_eer(g, i)
        res = eer(g, i)
        assert res.eer == pytest.approx(float(exact), rel=1e-12, abs=1e-15)
        assert res.threshold == pytest.approx(thr, rel=1e-12, abs=1e-12)


def test_eer_is_symmetric_and_rank_invariant():
    # Negating the scores and swapping the classes mirrors the polyline in the
    # diagonal; a strictly increasing transform keeps every operating point.
    rng = np.random.default_rng(9)
    for _ in range(100):
        g, i = random_case(rng)
        e = eer(g, i).eer
        assert eer(-i, -g).eer == pytest.approx(e, rel=1e-12, abs=1e-15)
        assert eer(np.exp(g), np.exp(i)).eer == e


def test_sort_free_path_is_identical_to_full_sort(monkeypatch):
    # _eer_windowed must return exactly what the full sort returns, including when
    # its subsample is misleading and it has to fall back.
    calls = {"full": 0}
    original = S._eer_sorted

    def spy(gs, is_):
        if gs.size == n_g and is_.size == n_i:
            calls["full"] += 1
        return original(gs, is_)

    rng = np.random.default_rng(17)
    monkeypatch.setattr(S, "_eer_sorted", spy)
    windowed = 0
    for case in range(120):
        # A 1,024-value subsample puts about a quarter of the impostors in the window.
        n_g, n_i = int(rng.integers(1, 3000)), int(rng.integers(3000, 30000))
        g = np.round(rng.normal(rng.uniform(0, 3), 1, n_g) * 10) / 10
        i = np.round(rng.normal(0, 1, n_i) * 10) / 10 if case % 2 else rng.normal(0, 1, n_i)
        before = calls["full"]
        got = S._eer_windowed(g, i, subsample=1024)
        windowed += calls["full"] == before
        assert got == original(np.sort(g), np.sort(i))
    assert windowed > 100  # the window normally suffices
    # Adversarial order: every 50th score (exactly what the stride picks) comes
    # from a separate cluster in [10, 11.2], so the window lands far from the
    # true crossing near 1 and the exact answer needs the fallback.
    n_g = n_i = 2048 * 50
    g, i = rng.normal(2, 1, n_g), rng.normal(0, 1, n_i)
    g[::50] = rng.uniform(10.2, 11.2, g[::50].size)
    i[::50] = rng.uniform(10.0, 11.0, i[::50].size)
    before = calls["full"]
    assert S._eer_windowed(g, i, subsample=2048) == original(np.sort(g), np.sort(i))
    assert calls["full"] == before + 1  # fell back
    # And through the public entry point on a large input (sort-free path).
    n_g, n_i = 9000, 400_000
    g, i = rng.normal(2, 1, n_g), rng.normal(0, 1, n_i)
    before = calls["full"]
    res = eer(g, i)
    assert calls["full"] == before
    assert (res.eer, res.threshold) == original(np.sort(g), np.sort(i))


# --------------------------------------------------------------------------- convex hull


def test_convex_hull_eer_never_exceeds_interpolated():
    rng = np.random.default_rng(23)
    for _ in range(300):
        g, i = random_case(rng)
        assert eer_convex_hull(g, i).eer <= eer(g, i).eer + 1e-12


def test_convex_hull_equals_interpolated_on_convex_roc():
    # genuine = [0, 1, 1, 2, 2, 2], impostor = [0, 0, 0, 1, 1, 2]: every value is a tie,
    # points (FAR, FRR): t=0 (1, 0), t=1 (1/2, 1/6), t=2 (1/6, 1/2), +inf (0, 1).
    # Slopes -3, -1, -1/3 (from the left) increase: the ROC is convex.  The crossing
    # is on the middle edge x + y = 2/3, at x = 1/3, halfway from t=1 to t=2 (1.5).
    g, i = [0, 1, 1, 2, 2, 2], [0, 0, 0, 1, 1, 2]
    a, b = eer(g, i), eer_convex_hull(g, i)
    assert a.eer == pytest.approx(1 / 3, abs=1e-15)
    assert b.eer == pytest.approx(1 / 3, abs=1e-15)
    assert a.threshold == pytest.approx(1.5) and b.threshold == pytest.approx(1.5)


def test_convex_hull_matches_lp_oracle():
    # ROCCH-EER = max_w min_t [w FAR(t) + (1-w) FRR(t)]; min over points of a linear
    # function, maximised over a fine w grid (piecewise linear, so the grid error is
    # at most (grid step) * max|FAR - FRR| <= 1e-4).
    rng = np.random.default_rng(29)
    w = np.linspace(0, 1, 10_001)[:, None]
    for _ in range(60):
        g, i = random_case(rng)
        r = roc(g, i)
        oracle = np.max(np.min(w * r.far + (1 - w) * r.frr, axis=1))
        got = eer_convex_hull(g, i).eer
        assert got >= oracle - 1e-12
        assert got <= oracle + 1e-4


# --------------------------------------------------------------------------- ROC, AUC, DET


def test_roc_hand_example_and_invariants():
    r = roc([1.0, 2.0, 3.0], [0.0, 2.0])
    np.testing.assert_array_equal(r.thresholds, [0, 1, 2, 3, np.inf])
    np.testing.assert_allclose(r.far, [1, 0.5, 0.5, 0, 0])
    np.testing.assert_allclose(r.frr, [0, 0, 1 / 3, 2 / 3, 1])
    rng = np.random.default_rng(31)
    for _ in range(50):
        g, i = random_case(rng)
        r = roc(g, i)
        assert np.all(np.diff(r.thresholds) > 0)
        assert np.all(np.diff(r.far) <= 0) and np.all(np.diff(r.frr) >= 0)
        assert (r.far[0], r.frr[0], r.far[-1], r.frr[-1]) == (1.0, 0.0, 0.0, 1.0)
        # Direct counts at a few thresholds.
        for k in rng.integers(0, r.thresholds.size, size=5):
            t = r.thresholds[k]
            assert r.far[k] == np.mean(i >= t) and r.frr[k] == np.mean(g < t)


def test_auc_matches_brute_force():
    rng = np.random.default_rng(37)
    for _ in range(200):
        g, i = random_case(rng)
        assert auc(g, i) == pytest.approx(brute_force_auc(g, i), abs=1e-14)


def test_det_curve_is_probit_of_roc():
    rng = np.random.default_rng(41)
    g, i = rng.normal(2, 1, 500), rng.normal(0, 1, 700)
    d = det_curve(g, i)
    assert np.all(np.isfinite(d.far_probit)) and np.all(np.isfinite(d.frr_probit))
    np.testing.assert_allclose(d.far_probit, norm.ppf(d.far))
    np.testing.assert_allclose(d.frr_probit, norm.ppf(d.frr))
    r = roc(g, i)
    inner = (r.far > 0) & (r.far < 1) & (r.frr > 0) & (r.frr < 1)
    assert d.far.size == np.count_nonzero(inner)


def test_plots_draw_on_given_axes():
    from matplotlib.figure import Figure

    rng = np.random.default_rng(43)
    g, i = rng.normal(2, 1, 300), rng.normal(0, 1, 3000)
    fig = Figure()
    ax1, ax2 = fig.subplots(1, 2)
    res = eer(g, i)
    line = plot_det(ax1, det_curve(g, i), label="test", eer_point=res)
    assert line.get_label() == "test" and len(ax1.lines) >= 2
    plot_score_histograms(ax2, g, i, threshold=res.threshold)
    assert len(ax2.patches) == 2 and len(ax2.lines) == 1
    fig.savefig(io.BytesIO(), format="png")  # renders without pyplot


# --------------------------------------------------------------------------- threshold at FAR


def test_decision_threshold_at_far_is_smallest_admissible():
    rng = np.random.default_rng(47)
    for _ in range(100):
        g, i = random_case(rng, max_n=60)
        target = float(rng.choice([0.0, 0.01, 0.1, 0.25, 0.5, 1.0]))
        op = decision_threshold_at_far(i, target, genuine=g)
        assert op.far == np.mean(i >= op.threshold) <= target + 1e-12
        assert op.frr == np.mean(g < op.threshold)
        if math.isfinite(op.threshold):
            # One float lower and the FAR target is broken.
            assert np.mean(i >= np.nextafter(op.threshold, -np.inf)) > target
        else:
            assert target * i.size >= i.size - 1e-9


# --------------------------------------------------------------------------- bootstrap


def test_vectorised_replicates_equal_eer_of_the_same_resamples():
    # White-box: one chunk draws the genuine indices, then the impostor indices, each
    # into the sorted arrays.  Reproduce those draws and compare replicate by replicate.
    rng = np.random.default_rng(53)
    g, i = np.round(rng.normal(1.5, 1, 120), 1), rng.normal(0, 1, 90)
    reps = S._bootstrap_eer_replicates(g, i, np.random.default_rng(7), 50)
    r2 = np.random.default_rng(7)
    gi = np.sort(g)[r2.integers(0, g.size, size=(50, g.size))]
    ii = np.sort(i)[r2.integers(0, i.size, size=(50, i.size))]
    expected = [eer(a, b).eer for a, b in zip(gi, ii)]
    np.testing.assert_allclose(reps, expected, rtol=0, atol=1e-15)


def test_vectorised_bootstrap_distribution_matches_plain_loop():
    rng = np.random.default_rng(59)
    g, i = rng.normal(1.5, 1, 300), rng.normal(0, 1, 300)
    n_boot = 2000
    fast = bootstrap_eer(g, i, np.random.default_rng(1), n_boot=n_boot).replicates
    slow = loop_bootstrap_eer(g, i, np.random.default_rng(2), n_boot)
    sd = np.std(slow, ddof=1)
    # Two independent means of B draws: SE of the difference sqrt(2/B) sd; 4 SE.
    assert abs(fast.mean() - slow.mean()) < 4 * math.sqrt(2 / n_boot) * sd
    # SE of a sample SD ~ sd / sqrt(2(B-1)); difference of two: sd / sqrt(B - 1); 4 SE.
    assert abs(np.std(fast, ddof=1) - sd) < 4 * sd / math.sqrt(n_boot - 1)


def test_bootstrap_interval_coverage():
    # 200 data sets of 200 vs 200 normal scores, d = 2 (EER = Phi(-1)), 500 replicates.
    # Nominal 95 %: the number of intervals covering the truth is Binomial(200, 0.95),
    # SD = sqrt(0.95 * 0.05 / 200) = 0.0154.  Accept 0.95 +/- 3 SD = [0.904, 0.996].
    # (Over 3,000 data sets this design covers 0.959 +/- 0.004, inside the band.)
    rng = np.random.default_rng(61)
    truth = norm.cdf(-1.0)
    reps = 200
    hits = 0
    for _ in range(reps):
        res = bootstrap_eer(rng.normal(2, 1, 200), rng.normal(0, 1, 200), rng, n_boot=500)
        hits += res.ci[0] <= truth <= res.ci[1]
    se = math.sqrt(0.95 * 0.05 / reps)
    assert 0.95 - 3 * se <= hits / reps <= 0.95 + 3 * se


def test_bootstrap_ci_mean_vectorised_and_loop_agree_with_theory():
    # Bootstrap SD of a mean of n values ~ s / sqrt(n) (times sqrt((n-1)/n));
    # the replicate SD estimate has relative SE 1/sqrt(2(B-1)); allow 4 of those.
    rng = np.random.default_rng(67)
    x = rng.normal(3.0, 2.0, 400)
    expected_sd = np.std(x, ddof=0) / math.sqrt(x.size)
    for vec in (True, False):
        res = bootstrap_ci(np.mean, x, rng=rng, n_boot=2000, vectorized=vec)
        assert res.estimate == pytest.approx(np.mean(x))
        assert abs(np.std(res.replicates, ddof=1) / expected_sd - 1) < 4 / math.sqrt(2 * 1999)
        assert res.ci[0] < res.estimate < res.ci[1]
    # Two samples: difference of means, vectorised.
    y = rng.normal(2.0, 1.0, 300)
    res = bootstrap_ci(lambda a, b, axis=-1: np.mean(a, axis=axis) - np.mean(b, axis=axis), x, y,
                       rng=rng, n_boot=1000, vectorized=True)
    assert res.estimate == pytest.approx(x.mean() - y.mean())
    assert res.replicates.shape == (1000,)


def test_results_serialise_to_json():
    rng = np.random.default_rng(71)
    g, i = rng.normal(2, 1, 50), rng.normal(0, 1, 50)
    for obj in (eer(g, i), eer_convex_hull(g, i), roc(g, i), det_curve(g, i),
                bootstrap_eer(g, i, rng, n_boot=50), decision_threshold_at_far(i, 0.1, genuine=g)):
        json.dumps(obj.to_dict())
    json.dumps(bootstrap_eer(g, i, rng, n_boot=20).to_dict(include_replicates=True))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("func", [roc, eer, eer_convex_hull, auc, det_curve])
def test_bad_scores_raise_input_error(func):
    with pytest.raises(InputError, match="genuine scores are empty"):
        func([], [1.0])
    with pytest.raises(InputError, match="impostor scores are empty"):
        func([1.0], np.array([]))
    with pytest.raises(InputError, match="NaN"):
        func([1.0, np.nan], [0.0])
    with pytest.raises(InputError, match="impostor.*NaN"):
        func([1.0], [0.0, float("nan")])
    with pytest.raises(InputError, match="real numbers"):
        func(["a", "b"], [0.0])


def test_bad_bootstrap_arguments():
    rng = np.random.default_rng(0)
    with pytest.raises(InputError):
        bootstrap_eer([np.nan], [1.0], rng)
    with pytest.raises(UsageError):
        bootstrap_eer([1.0], [0.0], rng, n_boot=0)
    with pytest.raises(UsageError):
        bootstrap_eer([1.0], [0.0], rng, level=1.0)
    with pytest.raises(TypeError):
        bootstrap_eer([1.0], [0.0], None)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        bootstrap_ci(np.mean, [], rng=rng)
    with pytest.raises(UsageError):
        decision_threshold_at_far([0.0], 1.5)


def test_infinite_and_nd_inputs_are_accepted():
    # +/-inf are legitimate scores (e.g. log-likelihood ratios); inputs are flattened.
    g = np.array([[1.0, np.inf], [2.0, 3.0]])
    i = np.array([-np.inf, 0.0, 2.0], dtype=np.float32)
    res = eer(g, i)
    exact, _ = brute_force_eer(g.ravel(), i)
    assert res.eer == pytest.approx(float(exact))
    assert math.isfinite(res.threshold)
    assert auc(g, i) == pytest.approx(brute_force_auc(g.ravel(), i))
