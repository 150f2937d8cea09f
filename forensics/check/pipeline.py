"""Entry points: the base model, the candidates, and :func:`check` — measurements → evidence → fit →
goodness of fit → diagnosis → result.

On the execution layer (:mod:`forensics._shared.parallel`): the frames are read condition by condition on the
workers (:func:`~forensics.check.measurements.load_measurements`), and :func:`check`'s model and its baseline
— two fits of one evidence that are both needed — are independent work items (:func:`fit_models`) sharing the
evidence.  A fit draws only from the check's keyed streams (:mod:`forensics.check.streams`, fresh generators
for every fit), so every model's result is the same on every backend.
"""
from __future__ import annotations

import dataclasses
import math
import pickle
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.errors import UsageError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike
from forensics.check.classes import CLASSES
from forensics.check.frame_advice import design_warnings, light_levels
from forensics.check.reduced import PatternShare, dark_pattern_shares, reduced_frame_warnings
from forensics.check.diagnosis import diagnose
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel, fit_model
from forensics.check.identifiability import with_held
from forensics.check.gof import (
    class_errors,
    covariate_checks,
    growth_gof,
    heldout_terms,
    pixel_gof,
    spatial_gof,
    variance_gof,
)
from forensics.check.measurements import Measurements, Region, load_measurements
from forensics.check.result import CheckResult, CheckRow, HeldOut, PlotData
from forensics.check.pixels import uses_scene
from forensics.check.scene import KERNEL_VAR
from forensics.check.darkfigures import dark_figures
from forensics.check.singles import single_frame_warnings
from forensics.check.singles import summary as singles_summary
from forensics.check.structure import residual_structure
from forensics._shared.errors import InputError
from forensics.io.dataset import Dataset, open_dataset
from forensics.io.images import is_raw, read_raw
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.sensor.effects import BlackLevel
from forensics.sensor.model import EFFECTS, Effect, make_effect

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor


def base_model(black_level: float | None = None) -> list[Effect]:
    """The base model: every registered effect whose role is ``base``, at its defaults; with ``black_level``
    (from metadata) the black level is known rather than fitted."""
    effects = [cls() for cls in EFFECTS.values() if cls.role == "base"]
    if black_level is not None:
        effects = [BlackLevel(level=float(black_level), known=True) if isinstance(e, BlackLevel) else e
                   for e in effects]
    return effects


def metadata_black_level(data: Dataset | str | Path) -> float | None:
    """The black level the files or the manifest state, if any: the manifest's ``black_level`` column (one
    value for every frame) or a raw file's black level (mean over the CFA channels).

    Raises
    ------
    InputError
        The manifest gives different black levels for different frames.
    """
    ds = data if isinstance(data, Dataset) else open_dataset(data)
    values = {f.extra.get("black_level") for f in ds.frames} - {None, ""}
    if values:
        try:
            levels = {float(v) for v in values}
        except ValueError as exc:
            raise InputError(f"{ds.root}: manifest column 'black_level' must be a number in DN ({exc})") from exc
        if len(levels) > 1:
            raise InputError(f"{ds.root}: manifest column 'black_level' differs between frames "
                             f"({', '.join(f'{v:g}' for v in sorted(levels))}); give one value or leave it empty")
        return levels.pop()
    first = ds.frames[0].path if len(ds) else None
    if first is not None and is_raw(first):
        return float(np.mean(read_raw(first).black_level))
    return None


def candidate_names(model_effects: Sequence[Effect]) -> list[str]:
    """Registered candidate effects not in the model."""
    have = {e.key for e in model_effects}
    return [n for n, c in EFFECTS.items() if c.role == "candidate" and n not in have]


def resolve_effects(add: Sequence[str | Effect]) -> list[Effect]:
    """Effects from names, ``module:Class``, ``file.py:Class`` or instances."""
    return [spec if isinstance(spec, Effect) else make_effect(spec) for spec in add]


def run_check(ev: Evidence, effects: Sequence[Effect], start: Mapping[str, float] | None = None,
              dither: float | None = None) -> CheckResult:
    """Fit ``effects`` to prepared evidence, score, and diagnose (``effects`` are left unchanged); ``start``:
    global pixel parameters to start the fit from (``effect.name`` → value, :func:`~forensics.check.fit.warm_start`);
    ``dither``: the converter the fit assumes until its noise fit picks one (a previous model's choice)."""
    fitted = fit_model(ev, effects, start=start, dither=dither)
    px = fitted.pixels
    r2, floor = heldout_terms(ev, fitted)
    classes = class_errors(ev, fitted, r2, floor)
    vals = [v for v in classes.values() if v is not None]
    gof_pixel, consistency, pixel_rows = pixel_gof(ev, fitted)
    covariates, covariate_rows = covariate_checks(ev, fitted)
    err_var, gof_var, variance_rows = variance_gof(ev, fitted)
    err_growth, gof_growth, growth_rows = growth_gof(ev, fitted)
    gof_spatial, ripley, spatial_rows = spatial_gof(ev, fitted)
    error_rows = []
    for name, value in reversed(classes.items()):  # the table lists the classes last to first
        if value is not None:
            n = int(np.sum(ev.usable & (px.classes == CLASSES.index(name))))
            error_rows.append(CheckRow(f"pixel: held-out error² ({name}, {n} pixel means)", value**2, 1.0,
                                       (value**2 - 1) / math.sqrt(2 / max(n, 1))))
    checks = [*error_rows, *pixel_rows, *covariate_rows, *variance_rows, *growth_rows, *spatial_rows]
    candidates, notes = diagnose(ev, fitted, candidate_names(fitted.effects))
    unsettled = fitted.not_converged
    shares = [] if unsettled else dark_pattern_shares(ev, fitted)
    warn = (list(ev.meas.notes) + ev.notes + notes + design_warnings(ev, px, candidates, fitted.effects)
            + single_frame_warnings(ev, fitted) + reduced_frame_warnings(shares))
    if unsettled:
        # not a result: no error or gof is reported for a fit that did not settle
        warn.insert(0, f"the fit did not converge ({', '.join(unsettled)} still moving): no error or goodness of "
                       "fit is reported for this model")
        classes = {k: None for k in classes}
        vals, err_var, err_growth = [], None, None
        gof_pixel = gof_var = gof_growth = gof_spatial = None
    scored = ev.usable & np.isfinite(r2)
    heldout = None if unsettled else HeldOut(np.where(scored, r2, np.nan).astype(np.float32),
                                             floor.astype(np.float32), px.classes)
    return CheckResult(
        heldout=heldout,
        effects=[e.key for e in fitted.effects],
        params=with_held(fitted.params, fitted.effects),
        patterns=fitted.patterns,
        error={"pixel": max(vals) if vals else None, "classes": classes, "variance": err_var, "growth": err_growth},
        gof={"pixel": gof_pixel, "variance": gof_var, "growth": gof_growth, "spatial": gof_spatial},
        checks=checks,
        candidates=candidates,
        warnings=warn,
        data=_data_summary(ev, fitted, shares),
        plots=_plot_data(ev, fitted, consistency, covariates, ripley),
        structure=residual_structure(ev, fitted),
        quantiser=None if fitted.quantiser is None else fitted.quantiser.to_dict(),
    )


def _plot_data(ev: Evidence, fitted: FittedModel, consistency: np.ndarray, covariates: dict[str, Any],
               ripley: dict[str, Any]) -> PlotData:
    """The arrays the report draws: residual maps, counts with the model's band, the variance channel."""
    meas, px, counts = ev.meas, fitted.pixels, ev.defects.counts
    r = meas.mean_b - fitted.mu_b
    nb = meas.n_b[:, None, None].astype(float)
    zb = r / np.sqrt(px.floor_b * (1.0 + np.where(uses_scene(px.classes, ev.rgroups), KERNEL_VAR, 0.0)) / nb)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        residual_map = np.nanmean(np.where(ev.usable, r, np.nan), axis=0)
        rms_map = np.sqrt(np.nanmean(np.where(ev.usable, zb * zb, np.nan), axis=0))
    counts_plot = {"times": ev.times, "observed": {k: counts[k] for k in (PARTIAL, STUCK)},
                   "expected": {k: fitted.expected[k] + counts[k][0] for k in (PARTIAL, STUCK)}}
    if fitted.sims:
        counts_plot["band"] = {k: (np.quantile(v, 0.025, axis=0), np.quantile(v, 0.975, axis=0))
                               for k, v in fitted.sims["counts"].items()}
    variance_plot = {"level": px.bins.level, "observed": px.bins.observed, "predicted": fitted.variance_pred,
                     "df": px.bins.df}
    return PlotData(residual_map, rms_map, consistency, px.classes[-1], covariates, counts_plot, ripley, variance_plot)


def _data_summary(ev: Evidence, fitted: FittedModel, shares: list[PatternShare]) -> dict[str, Any]:
    meas, px, defects = ev.meas, fitted.pixels, ev.defects
    return {"folder": str(meas.root), "frames": meas.n_frames, "conditions": len(meas.groups),
            "dark_pattern_share": [dataclasses.asdict(s) for s in shares],
            "repeated_conditions": len(meas.repeated), "single_frames": singles_summary(meas, ev.singles),
            "dark_series": None if fitted.not_converged else dark_figures(ev, fitted),
            "epochs": [float(t) for t in ev.times],
            "size": [meas.shape[1], meas.shape[0]], "full_scale": meas.full_scale, "border": meas.border,
            "light_levels": light_levels(ev, px),
            "defects": {"partial": int(defects.counts[PARTIAL][-1]), "stuck": int(defects.counts[STUCK][-1]),
                        "threshold_dn": float(defects.threshold[PARTIAL])},
            "classes": {name: int(np.sum(px.classes[-1][meas.interior] == k)) for k, name in enumerate(CLASSES)},
            "held_out_means": {name: int(np.sum(ev.usable & (px.classes == k))) for k, name in enumerate(CLASSES)}}


def fit_executor(executor: Executor | None, models: Sequence[Sequence[Effect]]) -> Executor:
    """The executor that fits ``models``: ``executor`` (None: in-process), or in-process when an effect cannot be
    sent to a worker — an instance of a class a worker cannot import (one defined inside a function or in an
    interactive session) does not pickle.  (A class loaded from a user's ``file.py:Class`` travels by its spec:
    :mod:`forensics._shared.plugins`.)"""
    from forensics._shared.parallel import in_process, resolve

    ex = resolve(executor)
    if ex.backend == "in-process":
        return ex
    try:
        pickle.dumps([list(m) for m in models])
    except (pickle.PicklingError, AttributeError, TypeError):
        return in_process()
    return ex


def _check_model(ev: Evidence, effects: list[Effect]) -> CheckResult:
    """Work item of :func:`fit_models` (module-level, so that workers import it by reference)."""
    return run_check(ev, effects)


def fit_models(ev: Evidence, models: Sequence[Sequence[Effect]], executor: Executor | None = None) -> Iterator[CheckResult]:
    """:func:`run_check` of every model on one evidence, in the order of ``models``; each model is one work item.

    The evidence is the items' shared data: shipped once to every worker that fits a model, so a worker holds a
    copy of it (the per-condition arrays of :class:`Measurements`) — with two models, two workers do.  A single
    model is fitted in this process.
    """
    models = [list(m) for m in models]
    yield from fit_executor(executor, models).map(_check_model, models, shared=ev, desc="fits")


def prepare(data: Dataset | str | Path | Measurements, add: Sequence[str | Effect], rng: RngLike, n_sim: int,
            progress: Progress = no_progress, region: Region | None = None,
            executor: Executor | None = None) -> tuple[Evidence, list[Effect]]:
    """The evidence of a dataset and the effects to add to the base model (refusing one already in it);
    ``region`` as in :func:`~forensics.check.measurements.load_measurements` (whole frames by default), which
    reads the conditions on ``executor``."""
    extra = resolve_effects(add)
    names = [e.key for e in base_model()]
    for e in extra:
        if e.key in names:
            raise UsageError(f"the effect '{e.key}' is already in the model")
        names.append(e.key)
    if isinstance(data, Measurements):
        if region is not None:
            raise UsageError("a region is chosen when the frames are read (load_measurements), not afterwards")
        # the frames were accepted when the measurements were read; only their metadata is read again here
        meas, source = data, open_dataset(data.root, allow_outside=True)
    else:
        # opened once, as given (a Dataset keeps how it was opened, e.g. with files outside its folder)
        source = data if isinstance(data, Dataset) else open_dataset(data)
        meas = load_measurements(source, region=region, progress=progress, executor=executor)
    require_fit_memory(meas)
    return Evidence(meas, rng=rng, n_sim=n_sim, black_level=metadata_black_level(source)), extra


#: Peak memory of a check (the fit, the diagnosis and ``--auto``'s steps) per pixel and fitted condition, in
#: bytes: measured 2.1 KB on the real STL-1001E dark series (19 fitted conditions, ``--auto``: 226 MB at 64²,
#: 729 MB at 128², 1,530 MB at 192²), 1.2 KB on the EMVA 1288 standard series (42 conditions, 3.8 GB at
#: 320 × 240) and 1.3–1.8 KB with 2 conditions (RESULTS_check.md, 24 MP section).  The fit holds whole-frame
#: (conditions, H, W) arrays; the row-block fit of issue 27 is what would bound it.
FIT_BYTES_PER_PIXEL_CONDITION = 2200


def require_fit_memory(meas: Measurements) -> None:
    """Refuse, before the fit, a check whose memory estimate (:data:`FIT_BYTES_PER_PIXEL_CONDITION` per pixel
    and fitted condition) exceeds :func:`~forensics._shared.limits.memory_limit`, naming ``--tiles`` and
    ``--region``: without
    it a whole 1 MP dark series (43 GB) ran for many minutes and then died out of memory.

    Raises
    ------
    UsageError
        The estimate exceeds the limit.
    """
    from forensics._shared.limits import require_memory

    h, w = meas.shape
    n = max(len(meas.fitted), 1)
    require_memory(FIT_BYTES_PER_PIXEL_CONDITION * h * w * n,
                   f"the model check of {w}×{h} pixels × {n} fitted conditions (--tiles 256 checks the whole "
                   f"frame tile by tile in the memory of one tile per worker; --region checks a part of it, e.g. "
                   f"--region {min(h, w, 512)})")


def check(data: Dataset | str | Path | Measurements, add: Sequence[str | Effect] = (), rng: RngLike = 0,
          baseline: bool = True, n_sim: int = 199, progress: Progress = no_progress,
          region: Region | None = None, executor: Executor | None = None) -> CheckResult:
    """Fit the base model plus ``add`` to a dataset, score it and diagnose what is missing.

    Parameters
    ----------
    data
        Dataset (or its folder, or prepared :class:`Measurements`).
    add
        Effects to add to the base model: registry names, ``module:Class``, ``file.py:Class`` or instances
        (instances are not changed).
    rng
        Generator or integer seed of the Monte-Carlo simulations (fixed patterns, arrival counts, placement);
        see :mod:`forensics.check.streams`.
    baseline
        With ``add``, also check the base model alone and keep it as :attr:`CheckResult.baseline`
        (for before/after comparisons).
    n_sim
        Monte-Carlo simulations of the fitted arrival model.
    progress
        Progress callable for reading the frames (one bar counting the conditions).
    region
        ``(top, left, height, width)``: check only this part of every frame (the warnings say so); default the
        whole frame (:func:`~forensics.check.measurements.load_measurements`).
    executor
        The execution layer (None: in this process): the conditions are read on it, and the model and its
        baseline are fitted side by side (:func:`fit_models`).

    Returns
    -------
    CheckResult
    """
    ev, extra = prepare(data, add, rng, n_sim, progress, region, executor)
    models = [[*base_model(ev.black_level), *extra]]
    if extra and baseline:
        models.append(base_model(ev.black_level))
    result, *before = fit_models(ev, models, executor)
    if before:
        result.baseline = before[0]
    return result
