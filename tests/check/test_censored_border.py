"""Dark frames censored at 0 DN: the never-scored border no longer keeps the pixel fit moving (sweep_check's 8bit
dsnu), the random effects' zero sum runs over the scored pixels only, and the variance near the bound is predicted
at the pixels' fitted latent levels."""
import dataclasses

import numpy as np
import pytest

from forensics.check.local_solve import common_mode
from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.check.pixels import VarianceBins, with_latent_spread
from forensics.fixtures.hidden import convention, make_hidden


def test_common_mode_over_members_leaves_the_others_free():
    rng = np.random.default_rng(0)
    shape, k = (6, 7), 2
    a = rng.standard_normal((*shape, k, k + 3))
    inv = np.linalg.inv(np.einsum("...ij,...kj->...ik", a, a))        # per-pixel SPD pseudo-inverses
    coef = rng.standard_normal((*shape, k))
    centred = np.array([True, False])
    members = np.zeros(shape, bool)
    members[1:-1, 1:-1] = True
    moved = coef + common_mode(inv, coef, centred, members=members)
    assert abs(moved[members][:, 0].sum()) < 1e-12 * np.abs(coef).sum()  # the zero sum, over the members
    assert np.array_equal(moved[~members], coef[~members])                  # the others keep their values
    # the constrained least-squares change: each member's shift is A⁺[:, C]·λ with one λ for all
    lam = (moved - coef)[members] @ np.array([1.0, 0.0]) / inv[members][:, 0, 0]
    assert np.allclose(lam, lam[0])
    whole = coef + common_mode(inv, coef, centred)                           # default: all pixels
    assert abs(whole[..., 0].sum()) < 1e-12 * np.abs(coef).sum()


def test_latent_spread_replaces_only_the_near_bound_bins():
    rng = np.random.default_rng(1)
    latent = rng.normal(0.3, 0.2, (2, 8, 8))
    labels = np.full((2, 8, 8), -1)
    labels[0, 1:7, 1:7] = 0                      # bin 0: condition 0, near a bound
    labels[1, :, :4], labels[1, :, 4:] = 1, 2     # bins 1, 2: condition 1, binned by level
    spread = np.full((3, 4), np.nan)
    spread[0] = [0.1, 0.2, 0.3, 0.4]
    bins = VarianceBins(np.array([0, 1, 1]), np.zeros(3), np.ones(3), np.ones(3), spread, 255.0, labels)
    out = with_latent_spread(bins, latent)
    assert out.spread_latent and not bins.spread_latent
    assert np.allclose(out.spread[0], np.quantile(latent[0, 1:7, 1:7], (np.arange(4) + 0.5) / 4))
    assert np.all(np.isnan(out.spread[1:]))
    assert with_latent_spread(VarianceBins(np.array([1]), np.zeros(1), np.ones(1), np.ones(1), spread[1:2], 255.0,
                                           labels), latent).spread_latent is False   # nothing near a bound


@pytest.mark.slow
def test_eight_bit_dsnu_at_black_level_zero_settles(tmp_path):
    # 8-bit frames at a black level of 0 DN: half the dark readings are censored at 0.  The border's DSNU values
    # used to be set by the neighbours' light frames (−21 DN at σ_o = 0.19 DN) and to crawl back for good: the
    # fit ran out of its 24 cycles with the DSNU's mean still drifting (40 × 40: −0.077 DN, not converged)
    design = dataclasses.replace(convention("8bit"), shape=(40, 40))
    make_hidden("dsnu", tmp_path / "data", rng=1, design=design)
    ev, _ = prepare(tmp_path / "data", [], 1, 199)
    res = run_check(ev, [*base_model(ev.black_level), *resolve_effects(["dsnu"])])
    assert not [p.label for p in res.params if not p.converged]
    assert res.error["pixel"] is not None and res.error["pixel"] <= 1.1
    # the model is the camera's: nothing is flagged.  Before the latent spread the variance channel read the
    # DSNU's spread near 0 DN as input noise (gof.variance 0.053, flagged; 128 × 128: shot noise and input noise)
    assert not res.flagged
    # the dark level (black level + the DSNU's mean; only their sum is determined without an ISO gain) is
    # 0 DN in truth.  Its precision: 0.7 DN of noise over 1,600 pixels × 20 dark readings, about half of them
    # censored, ≈ 0.01 DN; 0.1 DN is 10 of those and a seventh of the read noise
    level = {p.label: p.value for p in res.params}
    assert abs(level["dsnu.offset"] + level["black_level.level"]) < 0.1
    # the DSNU's size as the frames show it (split halves) covers the truth: the dark frames, half of whose means
    # are censored, are left out of it (with them: 0.37 ± 0.03 DN against the truth's 0.19; 128 × 128: 0.370 ±
    # 0.005, the dark frames alone 0.85, the flats alone 0.195)
    size = next(p for p in res.patterns if p.effect == "dsnu")
    truth = 3.0 * convention("8bit").level_scale
    assert size.size is not None and abs(size.size - truth) < 3.0 * size.size_se, (size.size, size.size_se, truth)
    # and σ_o reports that size, not the fitted values' rms less their noise (which misses the noise of the modes
    # only the censored dark frames determine: 0.31 DN on 128 × 128, seed 4)
    assert size.hyper == "sigma_o" and size.hyper_value == size.size


@pytest.mark.slow
def test_eight_bit_dsnu_held_out_values_predict_the_offsets(tmp_path):
    # The held-out half is predicted with the DSNU values shrunk to the mixed-model solution.  On 8-bit frames at a
    # black level of 0 DN most dark means are censored, the kept ones (truncated at 1 DN) move by a fraction of the
    # offset, and the light frames' scene estimates absorb the smooth modes: shrunk as if every kept dark mean
    # moved 1:1 and pixel by pixel, the values' error exceeded the offsets' own spread (0.26 DN against 0.19 DN on
    # 128 × 128, seed 4: worse than predicting 0), and the smooth part of it, shared by both halves' light-frame
    # predictions, flagged prnu.  A mixed-model predictor's error is below its prior's spread; 0.85 leaves room
    # for the spread of a standard deviation over ≈ 1,700 pixels (≈ 2 %) and the small sensor's edges.
    from forensics._shared.rng import keyed_generator
    from forensics.check.fit import fit_model
    from forensics.fixtures.hidden import apply_convention, hidden_effects, hidden_model

    design = dataclasses.replace(convention("8bit"), shape=(48, 48))
    model, _ = apply_convention(hidden_model("dsnu", design), hidden_effects("dsnu"), design)
    truth = model.realize(keyed_generator(2), [design.start_year + a for a in design.ages]).state["dsnu"]
    make_hidden("dsnu", tmp_path / "data", rng=2, design=design)
    ev, _ = prepare(tmp_path / "data", [], 2, 199)
    fitted = fit_model(ev, [*base_model(ev.black_level), *resolve_effects(["dsnu"])])
    values = fitted.device.state["dsnu"]
    classes = fitted.pixels.classes
    normal = np.all(classes == 0, axis=0) if classes.ndim == 3 else classes == 0
    scored = np.any(fitted.pixels.weight > 0, axis=0) & normal
    error = np.std((values - truth)[scored])
    assert error < 0.85 * np.std(truth[scored])

    # the variance channel's forward model takes the bins' electronic offsets (here the DSNU's, which differ from
    # bin to bin) averaged once per device (``bin_offsets``, as the noise fit does): the numbers averaged anew
    from forensics.check.prediction import bin_offsets, predicted_variance

    bins, noise = fitted.pixels.bins, fitted.noise_effects()
    offsets = bin_offsets(bins, ev.rgroups, fitted.device)
    assert np.ptp(np.concatenate(list(offsets.values()))) > 0.1
    assert np.array_equal(predicted_variance(bins, ev.rgroups, noise, fitted.device, offsets),
                          predicted_variance(bins, ev.rgroups, noise, fitted.device))
