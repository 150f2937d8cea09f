"""Which parameters the data determine (forensics.check.identifiability), and the black level the check fits."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check.identifiability import identify
from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.fixtures.hidden import Design, make_hidden


def test_a_parameter_without_information_is_not_identifiable():
    H = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    ident = identify(H, ["a", "b", "c"])
    assert list(ident.identifiable) == [True, True, False]
    assert "no information" in ident.why[2]
    assert ident.se(2) is None
    # the others' covariance is the inverse of their own block (c held fixed)
    np.testing.assert_allclose(ident.cov[:2, :2], np.linalg.inv(H[:2, :2]))


def test_parameters_that_trade_off_exactly_name_each_other():
    J = np.array([[1.0, 2.0, 0.5], [2.0, 4.0, 0.1], [0.5, 1.0, 3.0], [1.0, 2.0, 1.0]])  # b = 2·a
    ident = identify(J.T @ J, ["a", "b", "c"])
    assert not ident.identifiable[0] and not ident.identifiable[1] and ident.identifiable[2]
    assert "b" in ident.why[0] and "a" in ident.why[1]
    # c's standard error is its marginal one with what the data do determine of a and b (their common column)
    # free, not held fixed: 1/‖J_c off span(J_a)‖
    ja, jc = J[:, 0], J[:, 2]
    off = jc - ja * (ja @ jc) / (ja @ ja)
    assert ident.se(2) == pytest.approx(np.sqrt(1 / (off @ off)))


@pytest.fixture(scope="module")
def dark_framed(tmp_path_factory):
    """A small 14-bit dataset whose dark frames have no light (black level 256 DN in the readout, ISO gain)."""
    design = Design(convention="test", shape=(64, 64), bit_depth=14, ages=(0, 1, 2), pedestal=0.0,
                    black_level=256.0, read_noise=3.0, vignetting=0.6, stuck_fraction=0.1,
                    iso_gain="uncompensated")
    out = tmp_path_factory.mktemp("black") / "data"
    make_hidden("none", out, rng=5, design=design)
    return out


def test_black_level_from_dark_frames_covers_the_truth(dark_framed):
    ev, _ = prepare(dark_framed, ["gain"], 5, 19)
    result = run_check(ev, [*base_model(ev.black_level), *resolve_effects(["gain"])])
    p = next(p for p in result.params if p.label == "black_level.level")
    assert p.identifiable and p.converged and p.se is not None
    # 4 standard errors: the interval is the fit's own; a failure here is a bias, not bad luck (p < 1e-4)
    assert abs(p.value - 256.0) < 4 * p.se + 1e-3, p
    g = next(p for p in result.params if p.label == "gain.exponent")
    assert abs(g.value - 1.0) < 4 * g.se + 1e-4, g


def test_a_known_black_level_is_not_fitted(dark_framed):
    ev, _ = prepare(dark_framed, ["gain"], 5, 19)
    ev.black_level = 256.0
    result = run_check(ev, [*base_model(ev.black_level), *resolve_effects(["gain"])])
    assert not any(p.label == "black_level.level" for p in result.params)


def test_black_level_from_the_manifest(tmp_path):
    from forensics._shared.errors import InputError
    from forensics.check.pipeline import metadata_black_level
    from forensics.io.dataset import write_manifest
    from forensics.io.images import write_image

    for name in ("a.png", "b.png"):
        write_image(tmp_path / name, np.full((8, 8), 70, np.uint16))
    write_manifest(tmp_path / "manifest.csv", [{"file": "a.png", "black_level": 64}, {"file": "b.png", "black_level": 64}])
    assert metadata_black_level(tmp_path) == 64.0
    write_manifest(tmp_path / "manifest.csv", [{"file": "a.png", "black_level": 64}, {"file": "b.png", "black_level": 60}],
                   force=True)
    with pytest.raises(InputError, match="black_level"):
        metadata_black_level(tmp_path)


def test_bounded_step_holds_a_parameter_at_its_bound_and_solves_the_others():
    from forensics.check.identifiability import bounded_step

    H = np.array([[2.0, 0.5], [0.5, 1.0]])
    g = np.array([-3.0, 1.0])  # the unconstrained step takes the first below its bound 0
    step = bounded_step(H, g, np.zeros(2), np.array([0.0, -np.inf]), np.array([np.inf, np.inf]))
    assert step[0] == 0.0
    assert step[1] == pytest.approx(g[1] / H[1, 1])  # the other solved with the first held


def test_bounded_step_does_not_move_along_a_direction_the_data_do_not_determine():
    """Two collinear columns (b = 2a) and one the data carry no information on: the step reproduces the
    least-squares fit without the ±10³ split an unscaled solve of the near-singular system makes."""
    from forensics.check.identifiability import bounded_step

    rng = np.random.default_rng(0)
    a = rng.standard_normal(50)
    J = np.stack([a, 2 * a * (1 + 1e-13 * rng.standard_normal(50)), rng.standard_normal(50), 1e-9 * a], axis=1)
    r = rng.standard_normal(50)
    step = bounded_step(J.T @ J, J.T @ r, np.zeros(4), np.full(4, -np.inf), np.full(4, np.inf))
    assert step[3] == 0.0 and np.all(np.abs(step) < 10)
    # the fit in the span the data determine: a and the third column (b's 1e-13 departure from 2a is rounding)
    ls = np.linalg.lstsq(J[:, [0, 2]], r, rcond=None)[0]
    np.testing.assert_allclose(J @ step, J[:, [0, 2]] @ ls, atol=1e-8)


def test_a_parameter_on_its_bound_reports_a_one_sided_limit():
    """A noise σ fitted to 0 (its lower bound) is not "0 ± s": its 95 % limit is one-sided, 0 + 1.645·SE (the
    boundary likelihood ratio is ½χ²₀ + ½χ²₁); a parameter inside its range keeps its symmetric SE."""
    from forensics.check.identifiability import ONE_SIDED_95, estimates
    from forensics.sensor.effects import ReadNoise

    H = np.array([[4.0]])
    at_zero = estimates([ReadNoise(sigma=0.0)], [(0, "sigma")], H, True)[0]
    assert at_zero.bound == "lower" and at_zero.se == pytest.approx(0.5)
    assert at_zero.limit == pytest.approx(ONE_SIDED_95 * 0.5)
    assert "at its lower bound" in at_zero.summary() and "< 0.822" in at_zero.summary()
    inside = estimates([ReadNoise(sigma=2.0)], [(0, "sigma")], H, True)[0]
    assert inside.bound == "" and inside.limit is None and inside.summary() == "2 ± 0.5 DN"
