"""The refit after re-detection starts from the first fit's patterns, not from their cold start."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.check import fit as fit_module
from forensics.check.fit import fit_model
from forensics.check.pipeline import base_model, prepare
from forensics.fixtures.hidden import make_hidden


def _fits(monkeypatch, folder, carry: bool) -> tuple[list[list[float]], object]:
    """Fit base + dark_current; the χ² traces of the pixel fits it made, and the fitted model."""
    traces: list[list[float]] = []
    real = fit_module.fit_pixels

    def recording(*args, **kwargs):
        out = real(*args, **kwargs)
        traces.append(list(out.chi_trace))
        return out

    monkeypatch.setattr(fit_module, "fit_pixels", recording)
    if not carry:
        monkeypatch.setattr(fit_module, "carry_patterns", lambda *args: None)
    ev, extra = prepare(folder, ["dark_current"], np.random.default_rng(0), 19)
    fitted = fit_model(ev, [*base_model(ev.black_level), *extra])
    monkeypatch.undo()
    return traces, fitted


def test_the_refit_starts_where_the_first_fit_ended(tmp_path, monkeypatch):
    # the hidden-effect dataset of the benchmark (128 × 128 × 108 frames), on which re-detection against the
    # fitted dark-rate pattern changes the defect catalogue, so the model is fitted twice (not so at 64² or 96²)
    make_hidden("dark_current", tmp_path / "d", rng=1)
    warm, fitted = _fits(monkeypatch, tmp_path / "d", carry=True)
    cold, reference = _fits(monkeypatch, tmp_path / "d", carry=False)
    assert len(warm) == len(cold) == 2, "re-detection did not change the catalogue: no refit to test"
    # χ² of the refit's first cycle: from the carried patterns it is already at the cold refit's optimum (within
    # its convergence tolerance, 10⁻⁶ of χ², a few times over: the first cycle still moves the globals) — the
    # cold start's first cycle is far above it (it re-learns every pixel's dark rate)
    optimum = cold[1][-1]
    assert warm[1][0] <= optimum * (1 + 1e-5)
    assert cold[1][0] > optimum * (1 + 1e-4)
    # so it stops after the fewest cycles a fit can (χ² compared across two), where the cold start needs more
    assert len(warm[1]) == 2 < len(cold[1])
    # the same optimum: every global parameter within a fifth of its standard error of the cold refit's
    for p, q in zip(fitted.params, reference.params):
        assert p.label == q.label
        if q.se is not None and np.isfinite(q.se) and q.se > 0:
            assert abs(p.value - q.value) <= 0.2 * q.se, p.label
        else:
            assert p.value == pytest.approx(q.value, rel=1e-6, abs=1e-9), p.label
