"""Residual structure no catalogued effect explains (:mod:`forensics.check.structure`).

Unit tests of the profile and trend statistics on synthetic residuals (cheap), then hidden-effect datasets:
the user's column offsets of ``test_check.py`` (named, then gone once the user's class is added), null data
(nothing named; the false-alarm rate over 24 seeds is measured outside CI by
``benchmarks/structure_null.py``: 0/24 named), and a row pattern and a ring pattern written as small user
effects here.
"""
from __future__ import annotations

import numpy as np
import pytest
from forensics.fixtures.hidden import make_hidden
from scipy import ndimage, stats
from test_check import USER_EFFECT  # tests/check is on sys.path (pytest prepend mode)

from forensics.check import KERNEL, check
from forensics.check.structure import NAME_P, _labels, profile_test, trend_test
from forensics.stats.multiple import holm_adjusted as holm


def _residual(image: np.ndarray) -> np.ndarray:
    """What the check's scene estimate leaves: (I − K) applied to the frame."""
    return image - ndimage.correlate(image, KERNEL, mode="reflect")


def _profiles(res: np.ndarray, border: int = 3) -> dict:
    used = np.zeros(res.shape, bool)
    used[border:-border, border:-border] = True
    z = np.where(used, res, 0.0)
    return {kind: profile_test(kind, z, z, lab, full, c)[0] for kind, (lab, full, c) in _labels(res.shape, used).items()}


# ----------------------------------------------------------------------------------------- statistics
def test_profile_tests_hold_their_size_on_white_noise():
    """Neighbouring residuals are correlated through the scene kernel; the bin covariance accounts for it, so
    the whitened χ² is χ²(df): 30 frames × 3 profiles give p-values that are uniform (KS) and χ²/df whose
    mean is 1 within 4 standard errors (SE = √(2/df)/√30)."""
    rng = np.random.default_rng(7)
    ps, ratios = [], {"column": [], "row": [], "radial": []}
    for _ in range(30):
        tests = _profiles(_residual(2.0 * rng.standard_normal((64, 64))))
        for kind, t in tests.items():
            ps.append(t.p)
            ratios[kind].append(t.statistic / t.df)
            assert t.df > 20
    assert stats.kstest(ps, "uniform").pvalue > 1e-3
    for kind, r in ratios.items():
        df = tests[kind].df
        assert abs(np.mean(r) - 1.0) < 4 * np.sqrt(2 / df) / np.sqrt(30), kind


def test_dark_frames_residual_is_tested_against_its_own_white_null():
    """In frames known to be dark the prediction is the chain's output, not the scene estimate, so their
    residual is plain noise: summed with (I − K)-filtered residuals under the (I − K) null alone the whitened
    χ² explodes (smooth profile directions the kernel removes carry the white part's full power: χ²/df ≈ 5
    on the 14bit null data); tested apart, the sum of the two χ² holds its size (same criteria as above), and
    a row pattern present in the dark frames only is still found."""
    rng = np.random.default_rng(11)
    used = np.zeros((64, 64), bool)
    used[3:-3, 3:-3] = True
    ps, ratios, dfs = [], [], []
    for _ in range(30):
        scene = np.where(used, sum(_residual(rng.standard_normal((64, 64))) for _ in range(4)), 0.0)
        dark = np.where(used, rng.standard_normal((4, 64, 64)).sum(axis=0), 0.0)
        for kind, (lab, full, c) in _labels(used.shape, used).items():
            t = profile_test(kind, scene, scene / 4, lab, full, c, (dark, dark / 4, 0.5))[0]
            ps.append(t.p)
            ratios.append(t.statistic / t.df)
            dfs.append(t.df)
            assert t.df > 40
    assert stats.kstest(ps, "uniform").pvalue > 1e-3
    # χ²/df has SD √(2/df); 4 standard errors of the mean of the 90 ratios
    assert abs(np.mean(ratios) - 1.0) < 4 * np.sqrt(np.mean(2 / np.array(dfs))) / np.sqrt(len(dfs))
    rows = 0.3 * rng.standard_normal(64)
    dark = np.where(used, rng.standard_normal((4, 64, 64)).sum(axis=0) + 4 * rows[:, None], 0.0)
    lab, full, c = _labels(used.shape, used)["row"]
    assert profile_test("row", scene, scene / 4, lab, full, c, (dark, dark / 4, 0.5))[0].p < 1e-8


def test_column_pattern_is_found_only_by_the_column_profile_and_sized():
    """Column offsets of 0.5 DN under 2 DN noise (64 rows): the residual's column means carry 0.5·√0.78 DN
    against 2·√(0.78/58) = 0.23 DN of noise, so the column χ² is overwhelming; the row profile sees nothing
    (the pattern sums to the same along every row, and the common mean is removed).  The pattern's size is
    recovered within 25 % of the realised rms (noise adds ~0.23²/0.5² ≈ 20 % variance before subtraction, and
    the subtraction is exact only on average over 58 columns)."""
    rng = np.random.default_rng(8)
    cols = 0.5 * rng.standard_normal(64)
    tests = _profiles(_residual(2.0 * rng.standard_normal((64, 64)) + cols[None, :]))
    assert tests["column"].p < 1e-8
    assert tests["row"].p > 1e-3
    assert tests["column"].pattern_rms == pytest.approx(np.std(cols[3:-3]), rel=0.25)
    assert 0 < tests["column"].share < 1


def test_smooth_shading_is_invisible_by_construction():
    """A quadratic (vignetting-like) pattern is absorbed by the scene estimate: no profile sees it."""
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[0:64, 0:64]
    shading = 40.0 * ((yy - 31.5) ** 2 + (xx - 31.5) ** 2) / 31.5**2
    tests = _profiles(_residual(2.0 * rng.standard_normal((64, 64)) + shading))
    assert all(t.p > 1e-3 for t in tests.values())


def test_trend_test_and_holm():
    rng = np.random.default_rng(10)
    x = np.repeat([0.25, 0.5, 1.0], 6)
    y = 0.3 + 0.2 * x + 0.01 * rng.standard_normal(x.size)
    t, plot = trend_test("misfit trend", "exposure_s", x, y, "error²")
    assert t.p < 1e-8 and t.slope == pytest.approx(0.2, abs=5 * t.slope_se) and t.df == x.size - 2
    assert plot["slope"] == t.slope
    assert trend_test("trend", "iso", np.full(8, 100.0), y[:8], "DN") is None  # one value: nothing to regress on
    np.testing.assert_allclose(holm([0.01, 0.04, 0.03, 0.5]), [0.04, 0.09, 0.09, 0.5])


# ----------------------------------------------------------------------------------------- hidden effects
ROW_EFFECT = '''
from dataclasses import dataclass
from forensics.sensor.model import Effect, Stage, param


@dataclass
class RowOffset(Effect):
    name = "row_offset"
    description = "each row adds its own constant offset (row drivers)"
    stage = Stage.DARK
    sigma: float = param(1.5, "DN", "standard deviation of the row offsets", null=0.0)

    def realize(self, device, rng):
        device.state[self.key] = self.sigma * rng.standard_normal(device.model.shape[0])

    def apply(self, signal, ctx, rng):
        signal += ctx.device.state[self.key][:, None]
        return signal
'''

RING_EFFECT = '''
from dataclasses import dataclass
import numpy as np
from forensics.sensor.model import Effect, Stage, param


@dataclass
class RingGain(Effect):
    name = "ring_gain"
    description = "every 1-pixel ring around the optical centre has its own gain (lens or microlens rings)"
    stage = Stage.GAIN
    sigma: float = param(0.01, "", "standard deviation of the ring gains", null=0.0)

    def realize(self, device, rng):
        h, w = device.model.shape
        yy, xx = np.mgrid[0:h, 0:w]
        ring = np.floor(np.hypot(yy - (h - 1) / 2, xx - (w - 1) / 2)).astype(int)
        device.state[self.key] = (1.0 + self.sigma * rng.standard_normal(ring.max() + 1))[ring]

    def apply(self, signal, ctx, rng):
        signal *= ctx.device.state[self.key]
        return signal
'''


@pytest.fixture(scope="module")
def column_check(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("column")
    path = tmp / "column.py"
    path.write_text(USER_EFFECT)
    spec = f"{path}:ColumnOffset"
    data = make_hidden(spec, tmp / "data", rng=5)
    return check(data.out, add=[spec], rng=5)


def test_user_column_offsets_are_named_with_their_size(column_check):
    """σ = 3 DN column offsets: the named pattern's rms is within 20 % of σ — the realised rms of 122 interior
    columns spreads by σ/√(2·122) = 6.4 % (3 SD ≈ 19 %); the noise of a column mean (≈ 0.05 DN) is negligible.
    (Measured: 2.77 DN for seed 5.)"""
    st = column_check.baseline.structure
    assert st is not None and st.named is not None
    assert st.named.kind == "column" and st.named.p_holm < NAME_P
    assert 2.4 < st.named.pattern_rms < 3.6
    assert st.named.share > 0.5
    assert st.named.summary().startswith("column-wise pattern, ")
    d = column_check.baseline.to_dict()["structure"]
    assert d["named"]["kind"] == "column" and d["summary"] == st.named.summary()
    assert {t["kind"] for t in d["tests"]} >= {"column", "row", "radial", "trend", "misfit trend"}


def test_cli_summary_names_the_structure(column_check):
    from forensics.cli.model import format_check

    assert "Unexplained structure: column-wise pattern" in format_check(column_check.baseline)
    assert "Unexplained structure" not in format_check(column_check)


def test_adding_the_user_effect_removes_the_structure(column_check):
    st = column_check.structure
    assert st.named is None, st.named
    assert column_check.to_dict()["structure"]["named"] is None
    column = next(t for t in st.tests if t.kind == "column")
    assert column.p > NAME_P


@pytest.mark.parametrize("seed", [31, 32])
def test_null_data_names_nothing(tmp_path, seed):
    """The false-alarm rate over 24 seeds is measured by ``benchmarks/structure_null.py`` (outside CI)."""
    data = make_hidden("none", tmp_path / "none", rng=seed)
    st = check(data.out, rng=seed).structure
    assert st.named is None, st.named.summary()
    assert len(st.tests) >= 8


@pytest.mark.parametrize(("source", "cls", "kind"), [(ROW_EFFECT, "RowOffset", "row"),
                                                    (RING_EFFECT, "RingGain", "radial")])
def test_user_row_and_ring_patterns_are_named_as_such(tmp_path, source, cls, kind):
    path = tmp_path / "effect.py"
    path.write_text(source)
    data = make_hidden(f"{path}:{cls}", tmp_path / "data", rng=6)
    st = check(data.out, rng=6).structure
    assert st.named is not None and st.named.kind == kind, [(t.label, t.p_holm) for t in st.tests]
    assert st.named.p_holm < NAME_P
