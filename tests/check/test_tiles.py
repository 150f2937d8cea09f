"""The whole frame checked in tiles (``forensics.check.tiles``): the grid, the combination's statistics, and
the tiles against the whole-frame check on a synthetic cooled-CCD series — with a dark rate that is the same
everywhere, and with amplifier glow raising it near one corner."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from forensics.check import check
from forensics.check.result import ParamEstimate
from forensics.check.tiles import HALO, Tile, TileResult, check_tiles, combine_params, tile_grid
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series

from forensics.cli.main import main

# the design of tests/check/test_single_frames.py, on a frame of six 48 × ~43 tiles
DESIGN = DarkSeriesDesign(shape=(96, 128), temperature_wander=0.0, offset_jitter=0.0, readout_s=0.0,
                          column_pattern=0.0, doubling_hot=5.0, hot_fraction=0.01, hot_min=3.0, hot_max=10.0,
                          n_repeat_dark=6, cosmic_rate=1e-5)
ADD = ["shot_noise", "dark_current"]


@pytest.mark.parametrize("shape,size", [((96, 128), 48), ((1000, 37), 256), ((17, 300), 64), ((40, 40), 16)])
def test_tile_cores_partition_the_frame_and_regions_add_the_halo(shape, size):
    tiles = tile_grid(shape, size)
    cover = np.zeros(shape, int)
    for t in tiles:
        top, left, h, w = t.core
        assert h <= size and w <= size and h >= size // 2 or h == shape[0] or w == shape[1]
        cover[top:top + h, left:left + w] += 1
        r0, c0, rh, rw = t.region
        assert (r0, c0) == (max(top - HALO, 0), max(left - HALO, 0))
        assert (r0 + rh, c0 + rw) == (min(top + h + HALO, shape[0]), min(left + w + HALO, shape[1]))
    assert np.all(cover == 1)  # every pixel in exactly one core


def _tile(values: dict[str, tuple[float, float]], cov: dict[tuple[str, str], float] | None = None) -> TileResult:
    params = []
    for label, (v, se) in values.items():
        effect, name = label.split(".")
        c = {b: x for (a, b), x in (cov or {}).items() if a == label}
        c.update({a: x for (a, b), x in (cov or {}).items() if b == label})
        params.append(ParamEstimate(effect, name, v, se, cov=c))
    return TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], params, {}, {}, None, {}, [], [], [])


def test_combination_is_generalised_least_squares_with_calibrated_intervals_and_heterogeneity_test():
    """Eight tiles, each an unbiased estimate of (a, b) with its own correlated covariance (correlation −0.8, as a
    dark offset and rate): over 2,000 simulated frames the combined 95 % intervals cover the truth and the joint
    and per-parameter heterogeneity p-values are uniform.  Tolerances: 3 binomial standard errors at n = 2,000
    (coverage 0.95 ± 0.015, rejection 0.05 ± 0.015)."""
    rng = np.random.default_rng(7)
    truth = np.array([3.0, -1.0])
    n_rep, n_tiles = 2000, 8
    cover = np.zeros(2, int)
    reject_joint = reject_a = 0
    for _ in range(n_rep):
        tiles = []
        for _ in range(n_tiles):
            se = rng.uniform(0.5, 2.0, 2)
            cov = np.array([[se[0] ** 2, -0.8 * se[0] * se[1]], [-0.8 * se[0] * se[1], se[1] ** 2]])
            est = rng.multivariate_normal(truth, cov)
            tiles.append(_tile({"x.a": (est[0], se[0]), "x.b": (est[1], se[1])}, {("x.a", "x.b"): cov[0, 1]}))
        params, q, df, p = combine_params(tiles)
        assert df == 2 * n_tiles - 2
        for i, par in enumerate(params):
            cover[i] += abs(par.estimate.value - truth[i]) <= 1.96 * par.estimate.se
        reject_joint += p < 0.05
        reject_a += params[0].p_same < 0.05
    assert np.all(np.abs(cover / n_rep - 0.95) <= 0.015), cover / n_rep
    assert abs(reject_joint / n_rep - 0.05) <= 0.015 and abs(reject_a / n_rep - 0.05) <= 0.015


def test_a_parameter_missing_in_a_tile_and_a_failed_tile_are_left_out():
    tiles = [_tile({"x.a": (1.0, 1.0), "x.b": (5.0, 1.0)}), _tile({"x.a": (3.0, 1.0)}),
             TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], [ParamEstimate("x", "a", 100.0, 1.0)], {}, {}, None,
                        {}, [], ["x.a"], [])]
    params, q, df, p = combine_params(tiles)
    by = {par.estimate.label: par for par in params}
    assert by["x.a"].estimate.value == pytest.approx(2.0) and by["x.a"].tiles == 2
    assert by["x.b"].estimate.value == pytest.approx(5.0) and by["x.b"].tiles == 1 and by["x.b"].p_same is None
    assert df == 1 and q == pytest.approx(2.0)


@pytest.fixture(scope="module")
def flat_rate(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiles-flat")
    make_dark_series(folder, 1, DESIGN)
    return folder, check_tiles(folder, add=ADD, size=48), check(folder, add=ADD, baseline=False)


def test_tiles_agree_with_the_whole_frame_check(flat_rate):
    """The combined estimates and standard errors against one fit of the whole frame, on the same pixels.  The
    two are different estimators of the same quantities (per-tile patterns and scene estimates at the tiles'
    edges), so they differ by noise of a fraction of a standard error (measured: ≤ 1.0 SE, SE ratios 0.97–1.01):
    within 2 SE, and standard errors within 20 %."""
    _, tiled, whole = flat_rate
    own = {p.label: p for p in whole.params if p.se is not None}
    assert len(tiled.params) >= 4
    for p in tiled.params:
        w = own[p.estimate.label]
        assert abs(p.estimate.value - w.value) <= 2.0 * w.se, p.estimate.label
        assert 0.8 <= p.estimate.se / w.se <= 1.25, p.estimate.label
    assert tiled.error["pixel"] == pytest.approx(whole.error["pixel"], rel=0.2)
    assert not tiled.flagged and not whole.flagged
    # where the model holds, no tile's covariance is distrusted (the guard of untrusted_estimates stays silent)
    assert tiled.untrusted == []


def test_every_parameter_is_reported_combined_or_with_the_reason_it_is_not(flat_rate):
    """A tiled check states what a whole-frame check states: every global parameter is either combined over the
    tiles or listed as not combined, with the whole-frame check's own reason (held, not separable, the largest of
    several values) and the tiles' values — in the summary and in standard JSON."""
    import json

    from cli.model import format_tiles

    _, tiled, whole = flat_rate
    combined = {p.estimate.label for p in tiled.params}
    listed = {u.label: u for u in tiled.uncombined}
    assert not combined & set(listed)
    assert combined | set(listed) == {p.label for p in whole.params}
    for p in whole.params:
        if p.label in listed:
            reason = listed[p.label].reason
            assert reason.startswith("not identifiable") == (not p.identifiable), p.label
            assert reason.startswith("the largest") == (p.identifiable and not p.quadratic), p.label
            assert listed[p.label].low <= listed[p.label].median <= listed[p.label].high
    text = format_tiles(tiled)
    assert "not combined" in text and all(label in text for label in listed)
    out = json.loads(json.dumps(tiled.to_dict(), allow_nan=False))
    assert {u["label"] for u in out["uncombined"]} == set(listed)


def test_tiles_agree_with_each_other_when_the_rate_is_the_same_everywhere(flat_rate):
    _, tiled, _ = flat_rate
    assert len(tiled.tiles) == 6 and not tiled.failed
    assert all(p.p_same is None or p.p_same > 1e-3 for p in tiled.params)
    assert tiled.joint_p_same > 1e-3


def test_amplifier_glow_is_found_as_a_dark_rate_that_differs_between_tiles(tmp_path):
    """Glow tripling the dark rate at the corner (falling off over 0.3 widths): the rate's heterogeneity test
    rejects (measured p 1e-14 and 7e-7 on seeds 1 and 2), the read noise and the conversion gain, which the
    glow does not touch, pass."""
    make_dark_series(tmp_path, 1, DarkSeriesDesign(**{**DESIGN.__dict__, "glow": 2.0}))
    tiled = check_tiles(tmp_path, add=ADD, size=48)
    by = {p.estimate.label: p for p in tiled.params}
    assert by["dark_current.rate"].p_same < 1e-4
    assert by["dark_current.rate"].spread > 0.05 * by["dark_current.rate"].estimate.value
    assert by["read_noise.sigma"].p_same > 1e-3 and by["shot_noise.g"].p_same > 1e-3
    corner = next(t for t in tiled.tiles if t.tile.core[:2] == (0, 0))
    far = next(t for t in tiled.tiles if t.tile.core[0] > 0 and t.tile.core[1] > 64)
    rate = {id(t): next(q.value for q in t.params if q.label == "dark_current.rate") for t in (corner, far)}
    assert rate[id(corner)] > 1.3 * rate[id(far)]


def test_tiles_from_the_command_line(flat_rate, tmp_path, capsys):
    """Two worker processes give the in-process result (each tile draws from its own spawned stream)."""
    folder, tiled, _ = flat_rate
    code = main(["model", "check", str(folder), "--tiles", "48", "--add", "shot_noise", "--add", "dark_current",
                 "--json", "--workers", "2", "--quiet", "--report", str(tmp_path / "rep")])
    text = capsys.readouterr().out
    assert code == 0
    out = json.loads(text)  # json.loads accepts NaN tokens, so the text is checked for them too
    assert "NaN" not in text and "Infinity" not in text
    assert [p["value"] for p in out["params"]] == [p.estimate.value for p in tiled.params]
    assert len(out["tiles"]) == 6 and out["heterogeneity"]["df"] == tiled.joint_df
    assert (tmp_path / "rep" / "tile_maps.png").stat().st_size > 0
    assert main(["model", "check", str(folder), "--tiles", "48", "--region", "64", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--tiles" in err and len(err.strip().splitlines()) == 1


def test_auto_chooses_on_the_central_tile_and_checks_every_tile_with_that_model(flat_rate, capsys):
    folder, tiled, _ = flat_rate
    assert main(["model", "check", str(folder), "--tiles", "48", "--auto", "--json", "--workers", "1",
                 "--quiet"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["selection"]["path"][0]["step"] == "base"
    assert {"dark_current", "shot_noise"} <= set(out["effects"])  # what the series has, found on one tile
    assert len(out["tiles"]) == 6 and not any(c["flagged"] for c in out["candidates"])


def test_a_dead_corner_is_named_and_left_out(flat_rate, tmp_path):
    """Every frame reads 0 in one tile's core (a dead part of the sensor): that tile gives nothing, is named, and
    the other five still give the combined figures (within 2 SE of the whole series' tiles)."""
    from astropy.io import fits

    folder, tiled, _ = flat_rate
    for f in sorted(folder.glob("*.fits")):
        with fits.open(f) as hdul:
            data, header = hdul[0].data.copy(), hdul[0].header.copy()
        data[:48, :43] = 0
        fits.PrimaryHDU(data, header).writeto(tmp_path / f.name)
    dead = check_tiles(tmp_path, add=ADD, size=48)
    assert any("rows 0–47, columns 0–42" in w for w in dead.warnings)
    whole = {p.estimate.label: p.estimate for p in tiled.params}
    for p in dead.params:
        assert p.tiles == 5
        assert abs(p.estimate.value - whole[p.estimate.label].value) <= 2 * p.estimate.se, p.estimate.label


def _located(i: int, label_values: dict[str, tuple[float, float]], error: float = 1.5) -> TileResult:
    t = _tile(label_values)
    return replace(t, tile=Tile((8 * i, 0, 8, 8), (8 * i, 0, 8, 8)), classes={"normal": error},
                   held_out={"normal": 50})


def test_a_tile_claiming_a_hundredfold_information_or_misfitting_tenfold_is_left_out_of_the_combination():
    """The STL-1001E's whole frame: a tile settled on a cusp reported β ± 9·10⁻⁸ against the others' ± 5·10⁻³ and
    set the combined β.  Such an estimate, and every estimate of a tile whose held-out error is ten times the
    tiles' median, are left out (named in the warnings and the JSON); the tile's other estimates still count."""
    from forensics.check.tiles import combine

    rng = np.random.default_rng(3)
    tiles = [_located(i, {"x.a": (10.0 + rng.normal(), 1.0), "x.b": (2.0 + 0.1 * rng.normal(), 0.1)})
             for i in range(7)]
    honest, _, _, _ = combine_params(tiles)
    cusp = _located(7, {"x.a": (25.0, 1e-7), "x.b": (2.05, 0.1)})
    misfit = _located(8, {"x.a": (-40.0, 0.5), "x.b": (9.0, 0.05)}, error=30.0)
    whole = combine((72, 8), 8, [*tiles, cusp, misfit])
    by = {p.estimate.label: p for p in whole.params}
    base = {p.estimate.label: p for p in honest}
    assert by["x.a"].tiles == 7 and by["x.a"].estimate.value == pytest.approx(base["x.a"].estimate.value)
    # the cusp tile's b (an ordinary estimate) still enters, the misfitting tile's does not
    assert by["x.b"].tiles == 8
    assert abs(by["x.b"].estimate.value - base["x.b"].estimate.value) <= 0.05
    assert sorted((u.tile, u.label) for u in whole.untrusted) == [(7, "x.a"), (8, "x.a"), (8, "x.b")]
    assert any("rows 56–63" in w and "x.a" in w for w in whole.warnings)
    listed = json.loads(json.dumps(whole.to_dict()))["untrusted"]
    assert {(u["core"][0], u["label"]) for u in listed} == {(56, "x.a"), (64, "x.a"), (64, "x.b")}


def test_a_tile_that_misfits_weighs_less_in_the_heterogeneity_test_not_in_the_estimate():
    """Two tiles 10 ± 1 and 14 ± 1: Q = 8 on 1 df.  Where both tiles' held-out errors are 2 (the model misfits
    there, φ = 4), Q = 2 — the estimate and its standard error are unchanged."""
    def tile(v, e):
        return TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), [], [ParamEstimate("x", "a", v, 1.0)],
                          {"normal": e}, {"normal": 100}, None, {}, [], [], [])

    fit, _, _, _ = combine_params([tile(10.0, 1.0), tile(14.0, 1.0)])
    misfit, _, _, _ = combine_params([tile(10.0, 2.0), tile(14.0, 2.0)])
    assert fit[0].q == pytest.approx(8.0) and misfit[0].q == pytest.approx(2.0)
    assert misfit[0].estimate.value == fit[0].estimate.value and misfit[0].estimate.se == fit[0].estimate.se


def test_a_tile_that_could_not_be_checked_is_named_and_all_of_them_is_an_error():
    from forensics._shared.errors import InputError
    from forensics.check.tiles import combine

    good = TileResult(Tile((0, 0, 8, 8), (0, 0, 8, 8)), ["offset"], [ParamEstimate("x", "a", 1.0, 0.1)],
                      {"normal": 1.0}, {"normal": 10}, None, {}, [], [], [])
    bad = TileResult(Tile((8, 0, 8, 8), (5, 0, 11, 8)), [], [], {}, {}, None, {}, [], [], [],
                     unchecked="f.fits: content-free there")
    whole = combine((16, 8), 8, [good, bad])
    assert whole.failed == [bad] and whole.params[0].tiles == 1
    assert any("rows 8–15" in w and "content-free there" in w for w in whole.warnings)
    with pytest.raises(InputError, match="content-free there"):
        combine((16, 8), 8, [bad])


def test_frames_decoded_once_give_the_same_tiles_and_leave_nothing_behind(flat_rate, tmp_path, monkeypatch):
    """The tiles read the frames decoded once into scratch space (``forensics.io.framecache``): the results are
    those of decoding the files in every tile, value for value, and the scratch directory is empty afterwards.
    Where the decoded frames would not fit, the tiles decode the files themselves and the warnings say so."""
    from forensics.io import framecache

    folder, _, _ = flat_rate
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    cached = check_tiles(folder, add=ADD, size=48, scratch=scratch)
    assert list(scratch.iterdir()) == []
    monkeypatch.setattr(framecache, "FREE_MARGIN", 1e30)  # no disk has room: each tile decodes the files
    direct = check_tiles(folder, add=ADD, size=48, scratch=scratch)
    assert any("do not fit" in w for w in direct.warnings)
    assert not any("do not fit" in w for w in cached.warnings)
    assert [(p.estimate.value, p.estimate.se) for p in cached.params] == \
        [(p.estimate.value, p.estimate.se) for p in direct.params]
    assert [t.held_out for t in cached.tiles] == [t.held_out for t in direct.tiles]


def test_workers_that_may_not_see_this_machine_decode_the_files_themselves(flat_rate):
    """A Dask scheduler given by address may have its workers on other machines: without scratch space named,
    nothing is decoded into this machine's temporary directory, and the warnings say how to get it."""
    from forensics._shared.parallel import Executor

    class Remote(Executor):
        local_disk = False  # as for ``--scheduler tcp://…``

    folder, tiled, _ = flat_rate
    assert Executor("in-process").local_disk and Executor("processes", 2).local_disk
    remote = check_tiles(folder, add=ADD, size=48, executor=Remote("in-process"))
    assert any("--scratch" in w for w in remote.warnings)
    assert [p.estimate.value for p in remote.params] == [p.estimate.value for p in tiled.params]


def test_a_cached_frame_is_the_decoded_file(tmp_path):
    """The cache holds the decoder's values and dtype; a sub-dataset finds its frames' files (named by path)."""
    from forensics.io.dataset import open_dataset
    from forensics.io.framecache import frame_cache, open_cached
    from forensics.io.images import read_image

    make_dark_series(tmp_path / "d", 2, DarkSeriesDesign(shape=(20, 24), n_repeat_dark=2))
    ds = open_dataset(tmp_path / "d")
    with frame_cache(ds.subset([3, 1]), tmp_path) as (sub, why):
        assert why is None and sub.frame_cache is not None
        for f in sub.frames:
            got, want = open_cached(sub.frame_cache, f.path), read_image(f.path)
            assert got.dtype == want.dtype and np.array_equal(got, want)
    assert [p.name for p in tmp_path.iterdir()] == ["d"]


def test_scratch_must_be_a_writable_directory_and_needs_tiles(flat_rate, tmp_path, capsys):
    folder, _, _ = flat_rate
    for argv in (["--tiles", "48", "--scratch", str(tmp_path / "missing")], ["--scratch", str(tmp_path)]):
        assert main(["model", "check", str(folder), "--add", "shot_noise", "--quiet", *argv]) == 2
        err = capsys.readouterr().err
        assert "--scratch" in err and len(err.strip().splitlines()) == 1


def test_a_disk_that_fills_up_while_decoding_leaves_the_files_to_the_tiles(tmp_path, monkeypatch):
    """A write that fails (the disk full after all) removes what was written and hands back the dataset as it
    was, with the reason; the tiles then decode the files themselves."""
    import errno

    from forensics.io import framecache
    from forensics.io.dataset import open_dataset

    def full(item):
        raise OSError(errno.ENOSPC, "No space left on device")

    make_dark_series(tmp_path / "d", 2, DarkSeriesDesign(shape=(20, 24), n_repeat_dark=2))
    ds = open_dataset(tmp_path / "d")
    monkeypatch.setattr(framecache, "decode_to", full)
    with framecache.frame_cache(ds, tmp_path) as (same, why):
        assert same is ds and "No space left" in why
    assert [p.name for p in tmp_path.iterdir()] == ["d"]


def test_whole_frame_advice_points_to_tiles_above_its_limit():
    from forensics.check.tiles import whole_frame_advice

    # the hidden-effect datasets (128², 108 frames) fit in well under a GB: no advice
    assert whole_frame_advice(128 * 128, 108) is None
    # the EMVA simulator's 216-frame series, whose whole-frame --auto peaked at 5.2–5.3 GB (RESULTS_check.md)
    text = whole_frame_advice(320 * 240, 210)
    assert "about 5 GB" in text and "--tiles 128" in text and "210 frames of 76,800 pixels" in text
    assert whole_frame_advice(320 * 240, 210, limit=6 * 2**30) is None
