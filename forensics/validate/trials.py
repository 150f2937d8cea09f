"""Validation on simulated ground truth: how far the defect estimators can be trusted.

Every trial realises a new device from a preset of the reference paper
(:func:`forensics.sensor.presets.preset`, 16-bit by default, plus read noise), with
its rates multiplied so that a small frame collects enough defects, images it
through the sensor model (:meth:`~forensics.sensor.model.Device.expose`) at each
epoch with K scenes drawn from a pool of scenes, and runs the real pipeline
on the frames: streaming stack statistics → :func:`forensics.defects.detection.detect`
→ :func:`forensics.defects.growth.estimate_growth` → :mod:`forensics.defects.dating`.  Nothing
is shortcut; only the scenes are shared between trials (a pool generated once
per run), which is why trials are cheap enough for a ≥ 400-trial sweep.

``defects`` trials (two epochs each) measure detection recall (true defects
with amplitude ≥ ``amp_sigma``·σ of d̂ found), precision (detections that are
true defects, of any amplitude), and the bias, RMSE and coverage of the
partially-stuck rate interval.  The truth for the rate is the rate of
defects above the threshold used: λ·P(amplitude > τ − centre) = λ·(1 −
(τ − centre)/a_ps) for the uniform amplitudes of the model — a rate only means
something with its threshold.  The paper's eq. 17 is scored against the same
truth.

``dating`` trials measure (a) the coverage, bias and RMSE of set dating: three
reference epochs and a query set at a random date up to one reference span
after the last epoch (or, with ``within`` queries, inside the span); (b)
single-image dating: references every year over 12 years with the model's
*deterministic* counting (one new defect per year, onset uniform within the
year), a query image at a random date, and whether the maximum-likelihood
interval is the true one; accuracy is reported for the trials whose catalogue
knows ≥ 10 defects with distinct onset intervals (the acceptance condition),
and for all trials.

Randomness: ``validate_defects`` and ``validate_dating`` take ``rng`` (a Generator or an int seed).  The
scene pool and every trial draw from their own stream, keyed by the run's seed and the trial's index
(:func:`forensics._shared.rng.keyed_generator`: ``default_rng([seed, 2, i])`` for trial ``i`` of an
integer seed), so a trial can be re-run alone and trials can run in any order or process.

Execution: every trial is one work item of the execution layer (:mod:`forensics._shared.parallel`): a
:class:`Trial` (its index and the run's seed) run by :func:`run_defects_trial` or :func:`run_dating_trial`,
with the settings and the scene pool as the items' shared data (made once, in this process).  Trials keep
their frames in memory and write nothing.  Records come back in trial order, so the summaries are identical
on every backend.  The figures and the report of a run are in :mod:`forensics.report.validate`.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from forensics._shared.errors import InputError, UsageError
from forensics._shared.limits import require_memory
from forensics._shared.parallel import Executor, resolve
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator, keyed_generator, seed_record
from forensics.defects.detection import DEFAULT_Q, DEFAULT_SIGMA, DetectionResult, MaskSpec, detect
from forensics.defects.growth import Epoch, estimate_growth
from forensics.io.stack import StackAccumulator
from forensics.sensor.effects import ReadNoise
from forensics.sensor.catalogue import PARTIAL, STUCK
from forensics.sensor.model import Device, SensorModel
from forensics.sensor.presets import PRESETS, preset
from forensics.sensor.scenes import scene
from forensics.validate.truth import match_truth

NOMINAL = 0.95
ACCEPT_COVERAGE = (0.92, 0.98)


@dataclass
class ValidationSettings:
    """What every trial simulates."""

    sensor: str = "F"
    shape: tuple[int, int] = (128, 128)
    bit_depth: int = 16
    read_noise: float = 40.0
    images: int = 50
    q: int = DEFAULT_Q
    sigma: float = DEFAULT_SIGMA
    mask: str = "all"
    amp_sigma: float = 6.0
    target_new: float = 40.0
    span: float = 8.0
    t0: float = 2000.0
    pool: int = 256
    dating_years: int = 15
    dating_images: int = 20
    scenes: str = "smooth"
    stuck_tolerance_noise: float = 12.0

    @property
    def stuck_tolerance(self) -> float:
        """Tolerance of the stuck test: the model adds read noise after the stuck override, so a stuck pixel
        varies by ~4.5σ over 50 frames; 12σ leaves a wide margin while scene-lit pixels vary by thousands of DN."""
        return self.stuck_tolerance_noise * self.read_noise

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "shape": list(self.shape), "stuck_tolerance": self.stuck_tolerance}

    def rate_scale(self) -> float:
        """Rate multiplier giving about ``target_new`` partially-stuck (or stuck) arrivals per span."""
        lam_ps, lam_s, _ = PRESETS[self.sensor.upper()]
        lam = lam_ps or lam_s
        mp = self.shape[0] * self.shape[1] / 1e6
        return self.target_new / (lam * mp * self.span)


#: Working memory of one trial per pixel beyond the scene pool: peak RSS measured at 1024² (defects 71 bytes,
#: dating 136 bytes).
TRIAL_BYTES_PER_PIXEL = 150
#: Pixels left on a side inside the median window's border, at the least, for a threshold to be fitted.
MIN_ANALYSED_SIDE = 8


def check_request(settings: ValidationSettings, workers: int = 1) -> None:
    """Refuse (:class:`~forensics._shared.errors.UsageError`) a validation whose frames are too small for the
    detection window, or that would not fit in memory: the scene pool (``settings.pool`` float32 frames) is
    held here and by each of ``workers`` worker processes, and every worker runs one trial at a time."""
    h, w = settings.shape
    least = 2 * (settings.q // 2) + MIN_ANALYSED_SIDE
    if min(h, w) < least:
        raise UsageError(f"--size {w}x{h}: too small for the {settings.q}×{settings.q} median window, whose border "
                         f"is left out of the analysis; give at least {least}x{least}")
    pixels = h * w
    nbytes = pixels * (4 * settings.pool * (1 + workers) + TRIAL_BYTES_PER_PIXEL * workers)
    require_memory(nbytes, f"validation at {settings.shape[1]}×{settings.shape[0]} with {workers} worker(s) "
                           f"(a pool of {settings.pool} scenes)")


def scene_pool(settings: ValidationSettings, rng: RngLike) -> list[np.ndarray]:
    """The scenes (incident light in DN) the trials draw their frames from.

    ``settings.scenes``: ``'smooth'`` (pink textures low-passed by a Gaussian of
    4 px: the uniformly lit, low-texture regions the paper relies on, e.g. skin),
    or a kind of :func:`forensics.sensor.scenes.scene` (``'mixed'``, ``'photo'``, ``'texture'``).
    """
    from scipy import ndimage

    rng = as_generator(rng)
    full = np.float32(2.0**settings.bit_depth - 1)
    out = []
    for _ in range(settings.pool):
        if settings.scenes == "smooth":
            img = ndimage.gaussian_filter(scene(settings.shape, rng, 1, "texture"), 4.0, mode="reflect")
        else:
            img = scene(settings.shape, rng, 1, settings.scenes)
        out.append(np.asarray(img, np.float32) * full)
    return out


def pool_scene(pool: list[np.ndarray], index: int, rng: RngLike) -> np.ndarray:
    """Scene ``index`` of the pool, randomly flipped (so epochs rarely repeat a scene exactly)."""
    rng = as_generator(rng)
    img = pool[index]
    if rng.random() < 0.5:
        img = img[::-1]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    return img


def simulated_model(settings: ValidationSettings, counting: str = "poisson", rate_scale: float | None = None) -> SensorModel:
    """The preset at the settings' size and bit depth, rates scaled, plus read noise."""
    model = preset(settings.sensor, settings.shape, bit_depth=settings.bit_depth, t0=settings.t0, counting=counting,
                   rate_scale=settings.rate_scale() if rate_scale is None else rate_scale)
    return model.with_effects(ReadNoise(settings.read_noise))


def image_epoch(device: Device, time: float, k: int, pool: list[np.ndarray], rng: RngLike,
                settings: ValidationSettings) -> DetectionResult:
    """K frames of the device at ``time`` (scenes from the pool), streamed into a detection."""
    rng = as_generator(rng)
    acc = StackAccumulator()
    ctx = device.context(time)
    for i in rng.choice(len(pool), size=k, replace=k > len(pool)):
        acc.add(device.expose(pool_scene(pool, int(i), rng), ctx, rng))
    mask = MaskSpec("all") if settings.mask == "all" else MaskSpec(settings.mask)
    return detect(acc.result(), q=settings.q, sigma=settings.sigma, mask=mask, threads=1,
                  full_scale=2.0**settings.bit_depth - 1, stuck_tolerance=settings.stuck_tolerance)


# =========================================================================== work items
@dataclass(frozen=True)
class Trial:
    """One trial as a work item: its index and the run's seed — all it draws from (its keyed streams)."""

    index: int
    seed: int | np.random.SeedSequence  #: the run's ``rng`` as :func:`stream_root` gives it


@dataclass
class TrialSetup:
    """What every trial of a run shares (the work items' shared data, shipped once per worker)."""

    settings: ValidationSettings
    pool: list[np.ndarray]
    within_fraction: float = 0.25  #: dating: share of set-dating queries inside the reference span


def stream_root(rng: RngLike) -> int | np.random.SeedSequence:
    """``rng`` in a form a work item carries: an integer seed as it is, a Generator as its seed sequence.

    :func:`~forensics._shared.rng.keyed_generator` gives the same sub-streams from either, and neither uses
    the generator's state, so a trial's streams do not depend on what ran before it or where."""
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, (bool, np.bool_)):
        return int(rng)
    if isinstance(rng, np.random.SeedSequence):
        return rng
    return as_generator(rng).bit_generator.seed_seq


def run_defects_trial(setup: TrialSetup, trial: Trial) -> dict[str, Any]:
    """Work item of :func:`defects_records`: defects trial ``trial.index``, from its stream ``(2, index)``."""
    return defects_trial(setup.settings, setup.pool, keyed_generator(trial.seed, 2, trial.index))


def run_dating_trial(setup: TrialSetup, trial: Trial) -> tuple[dict[str, Any], dict[str, Any]]:
    """Work item of :func:`dating_records`: the set-dating trial (stream ``(4, index)``) and the single-image
    trial (stream ``(5, index)``) of ``trial.index``."""
    i = trial.index
    set_rng = keyed_generator(trial.seed, 4, i)
    within = set_rng.random() < setup.within_fraction
    return (set_dating_trial(setup.settings, setup.pool, set_rng, within=within),
            image_dating_trial(setup.settings, setup.pool, keyed_generator(trial.seed, 5, i)))


# =========================================================================== summaries
@dataclass
class Metric:
    """One validated quantity over the trials."""

    name: str
    n: int
    value: float
    ci: tuple[float, float] | None = None
    target: str = ""
    passed: bool | None = None
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "n": self.n, "value": self.value, "ci": list(self.ci) if self.ci else None,
                "target": self.target, "passed": self.passed, "note": self.note}


def proportion(name: str, hits: int, n: int, lo: float | None = None, hi: float | None = None, note: str = "") -> Metric:
    """A proportion with its exact 95 % interval, checked against [lo, hi] when given."""
    from forensics.stats.counts import clopper_pearson

    value = hits / n if n else float("nan")
    passed = None
    target = ""
    if n and (lo is not None or hi is not None):
        passed = (lo is None or value >= lo) and (hi is None or value <= hi)
        target = f"[{lo:g}, {hi:g}]" if lo is not None and hi is not None else (f"≥ {lo:g}" if lo is not None else f"≤ {hi:g}")
    return Metric(name, n, value, clopper_pearson(hits, n) if n else None, target, passed, note)


def error_metrics(name: str, estimates: np.ndarray, truths: np.ndarray, unit: str) -> list[Metric]:
    """Bias (mean error) with its 95 % interval and RMSE, for finite estimates."""
    est, tru = np.asarray(estimates, float), np.asarray(truths, float)
    ok = np.isfinite(est) & np.isfinite(tru)
    err = est[ok] - tru[ok]
    if not len(err):
        return []
    se = err.std(ddof=1) / math.sqrt(len(err)) if len(err) > 1 else float("nan")
    bias = float(err.mean())
    return [Metric(f"{name}: bias ({unit})", len(err), bias, (bias - 1.96 * se, bias + 1.96 * se)),
            Metric(f"{name}: RMSE ({unit})", len(err), float(np.sqrt(np.mean(err**2))))]


@dataclass
class ValidationResult:
    """Per-trial records and the summary metrics."""

    what: str
    settings: ValidationSettings
    trials: int
    seed: Any
    metrics: list[Metric]
    records: list[dict[str, Any]] = field(default_factory=list)
    curves: dict[str, Any] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(m.passed for m in self.metrics if m.passed is not None)

    def to_dict(self) -> dict[str, Any]:
        return {"what": self.what, "settings": self.settings.to_dict(), "trials": self.trials, "seed": self.seed,
                "rate_scale": self.settings.rate_scale(), "metrics": [m.to_dict() for m in self.metrics],
                "passed": self.passed, "curves": self.curves}

    def table(self) -> list[list[Any]]:
        rows = []
        for m in self.metrics:
            ci = f"[{m.ci[0]:.4g}, {m.ci[1]:.4g}]" if m.ci else ""
            rows.append([m.name, m.n, f"{m.value:.4g}", ci, m.target,
                         "" if m.passed is None else ("pass" if m.passed else "FAIL")])
        return rows


# =========================================================================== defects
def defects_trial(settings: ValidationSettings, pool: list[np.ndarray], rng: RngLike) -> dict[str, Any]:
    """One device, two epochs: detection scores and the growth estimates against the truth."""
    rng = as_generator(rng)
    model = simulated_model(settings)
    growth = model.effect("growth")
    t1, t2 = settings.t0 + settings.span, settings.t0 + 2 * settings.span
    device = model.realize(rng, [t1, t2])
    epochs = []
    rec: dict[str, Any] = {"tp_big": 0, "n_big": 0, "tp": 0, "fp": 0, "stuck_tp": 0, "stuck_n": 0,
                           "amp_sigma": [], "found": []}
    for t in (t1, t2):
        det = image_epoch(device, t, settings.images, pool, rng, settings)
        epochs.append(Epoch(t, det, f"{t:g}"))
        truth = match_truth(det, device.catalogue, t)
        part = truth.kind == PARTIAL
        rel = truth.amplitude_sigma[part]
        hit = truth.found[part]
        big = rel >= settings.amp_sigma
        rec["n_big"] += int(big.sum())
        rec["tp_big"] += int(hit[big].sum())
        rec["amp_sigma"] += rel.tolist()
        rec["found"] += hit.tolist()
        rec["tp"] += truth.true_positives
        rec["fp"] += truth.false_positives
        st = truth.kind == STUCK
        rec["stuck_n"] += int(st.sum())
        rec["stuck_tp"] += int(truth.found_same_kind[st].sum())
    result = estimate_growth(epochs)
    area = epochs[0].detection.megapixels
    thr = np.mean([ep.detection.fits[0].tau - ep.detection.fits[0].center for ep in epochs])
    frac = max(0.0, 1.0 - thr / growth.amp_partial) if growth.amp_partial > 0 else 0.0
    rec.update({"rate_true": growth.rate_partial * frac, "rate": result.partial.rate.rate,
                "rate_lo": result.partial.rate.ci[0], "rate_hi": result.partial.rate.ci[1],
                "rate_paper": result.paper.lambda_ps * (result.shape[0] * result.shape[1] / 1e6) / area,
                "stuck_true": growth.rate_stuck, "stuck_rate": result.stuck.rate.rate,
                "stuck_lo": result.stuck.rate.ci[0], "stuck_hi": result.stuck.rate.ci[1],
                "new": result.partial.rate.count, "scale": float(epochs[0].detection.fits[0].scale),
                "threshold_dn": float(thr)})
    return rec


def validate_defects(settings: ValidationSettings, trials: int, rng: RngLike = 0,
                     progress: Progress = no_progress, executor: Executor | None = None) -> ValidationResult:
    """Run ``trials`` detection-and-growth trials (see the module docstring).

    ``rng`` (Generator or int seed) keys the streams: the scene pool draws from sub-stream ``(1,)``, trial
    ``i`` from ``(2, i)`` (:func:`~forensics._shared.rng.keyed_generator`); the result records
    :func:`~forensics._shared.rng.seed_record` of it.  ``executor`` runs the trials (None: in this process);
    the result is the same on every backend.
    """
    records = defects_records(settings, rng, range(trials), executor=executor, progress=progress)
    return summarise_defects(settings, records, seed_record(rng))


def defects_records(settings: ValidationSettings, rng: RngLike, indices: Iterable[int],
                    executor: Executor | None = None, progress: Progress = no_progress) -> list[dict[str, Any]]:
    """The records of the defects trials ``indices`` of the run ``rng`` (any subset), in the order given; one
    work item per trial on ``executor`` (None: in this process)."""
    setup = TrialSetup(settings, scene_pool(settings, keyed_generator(rng, 1)))
    items = [Trial(int(i), stream_root(rng)) for i in indices]
    return list(resolve(executor).map(run_defects_trial, items, shared=setup, progress=progress,
                                      desc="validate defects"))


def summarise_defects(settings: ValidationSettings, records: list[dict[str, Any]], seed: Any = 0) -> ValidationResult:
    """Metrics (with acceptance checks) from per-trial records; ``seed`` is recorded as given."""
    n = len(records)
    tp_big = sum(r["tp_big"] for r in records)
    n_big = sum(r["n_big"] for r in records)
    tp = sum(r["tp"] for r in records)
    fp = sum(r["fp"] for r in records)
    cover = sum(r["rate_lo"] <= r["rate_true"] <= r["rate_hi"] for r in records)
    metrics = [
        proportion(f"detection recall, amplitude ≥ {settings.amp_sigma:g}σ", tp_big, n_big, 0.95,
                   note=f"{settings.images} images per epoch, {settings.bit_depth}-bit"),
        proportion("detection precision", tp, tp + fp, 0.95),
        proportion("partially-stuck rate: coverage of the 95 % interval", cover, n, *ACCEPT_COVERAGE),
    ]
    truth = np.array([r["rate_true"] for r in records])
    metrics += error_metrics("rate (Garwood/first appearances)", np.array([r["rate"] for r in records]), truth,
                             "defects/MP/yr")
    metrics += error_metrics("rate (paper eq. 17)", np.array([r["rate_paper"] for r in records]), truth,
                             "defects/MP/yr")
    st = [r for r in records if r["stuck_true"] > 0]
    if st:
        metrics.append(proportion("stuck recall", sum(r["stuck_tp"] for r in st), sum(r["stuck_n"] for r in st), 0.95))
        metrics.append(proportion("stuck rate: coverage of the 95 % interval",
                                  sum(r["stuck_lo"] <= r["stuck_true"] <= r["stuck_hi"] for r in st), len(st),
                                  *ACCEPT_COVERAGE))
    amp = np.concatenate([np.asarray(r["amp_sigma"], float) for r in records]) if records else np.zeros(0)
    found = np.concatenate([np.asarray(r["found"], bool) for r in records]) if records else np.zeros(0, bool)
    edges = np.arange(0.0, 16.01, 1.0)
    curve = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (amp >= a) & (amp < b)
        curve.append([float((a + b) / 2), int(sel.sum()), float(found[sel].mean()) if sel.any() else None])
    slim = [{k: v for k, v in r.items() if k not in ("amp_sigma", "found")} for r in records]
    return ValidationResult("defects", settings, n, seed, metrics, slim,
                            {"recall_vs_amplitude_sigma": curve,
                             "coverage": [[r["rate_true"], r["rate_lo"], r["rate_hi"]] for r in records]})


# =========================================================================== dating
def set_dating_trial(settings: ValidationSettings, pool: list[np.ndarray], rng: RngLike,
                     within: bool = False) -> dict[str, Any]:
    """Three reference epochs over one span, then a query set at a random date; is the date in the interval?"""
    from forensics.defects.dating import date_set

    rng = as_generator(rng)
    t0 = settings.t0
    refs = [t0 + settings.span * f for f in (1.0, 1.5, 2.0)]
    tq = float(rng.uniform(refs[0], refs[-1]) if within else rng.uniform(refs[-1], refs[-1] + settings.span))
    model = simulated_model(settings)
    device = model.realize(rng, refs + [tq])
    epochs = [Epoch(t, image_epoch(device, t, settings.images, pool, rng, settings), f"{t:g}") for t in refs]
    gm = estimate_growth(epochs).model()
    query = image_epoch(device, tq, settings.images, pool, rng, settings)
    try:
        res = date_set(gm, query)
    except InputError as exc:  # e.g. no growth over the references: no interval at all, counts as a miss
        return {"t_true": tq, "estimate": math.nan, "lo": math.nan, "hi": math.nan, "covered": False,
                "position": str(exc), "within": within}
    lo = -math.inf if res.interval[0] is None else res.interval[0]
    hi = math.inf if res.interval[1] is None else res.interval[1]
    return {"t_true": tq, "estimate": res.estimate, "lo": lo, "hi": hi, "covered": bool(lo <= tq <= hi),
            "position": res.position, "within": within}


def image_dating_trial(settings: ValidationSettings, pool: list[np.ndarray], rng: RngLike) -> dict[str, Any]:
    """Yearly references with one new defect per year; a single query image at a random date."""
    from forensics.defects.dating import date_image

    rng = as_generator(rng)
    years = settings.dating_years
    t0 = settings.t0
    refs = [t0 + k for k in range(1, years + 1)]
    mp = settings.shape[0] * settings.shape[1] / 1e6
    lam_ps, lam_s, _ = PRESETS[settings.sensor.upper()]
    model = simulated_model(settings, counting="deterministic", rate_scale=1.0 / (mp * (lam_ps + lam_s)))
    device = model.realize(rng, [t0] + refs)
    epochs = [Epoch(t, image_epoch(device, t, settings.dating_images, pool, rng, settings), f"{t:g}") for t in refs]
    gm = estimate_growth(epochs).model()
    tq = float(rng.uniform(t0, refs[-1]))
    image = device.expose(pool_scene(pool, int(rng.integers(len(pool))), rng), device.context(tq), rng)
    truth = device.catalogue
    onset = {(int(x), int(y)): float(o) for x, y, o in zip(truth.x, truth.y, truth.onset)}
    groups: dict[int, list[float]] = {}
    for c in gm.catalogue:  # a catalogue entry that is no true defect never appears: onset +inf
        groups.setdefault(c.first_epoch, []).append(onset.get((c.x, c.y), math.inf))
    if not gm.catalogue:
        return {"t_true": tq, "groups": 0, "correct": False, "distinct": 0, "best": -1, "true": -1}
    res = date_image(gm, image)
    ordered = [groups[g] for g in res.groups]
    # the true interval: how many leading onset groups have all their defects present at the query date
    true_j = 0
    while true_j < len(ordered) and all(o <= tq for o in ordered[true_j]):
        true_j += 1
    distinct = sum(1 for g in ordered if len(g) == 1 and math.isfinite(g[0]))
    return {"t_true": tq, "groups": len(res.groups), "distinct": distinct, "best": res.best, "true": true_j,
            "correct": res.best == true_j, "estimate": res.estimate}


def validate_dating(settings: ValidationSettings, trials: int, rng: RngLike = 0, progress: Progress = no_progress,
                    within_fraction: float = 0.25, executor: Executor | None = None) -> ValidationResult:
    """Run ``trials`` set-dating trials and ``trials`` single-image trials.

    ``rng`` (Generator or int seed) keys the streams: the scene pool draws from sub-stream ``(3,)``, set
    trial ``i`` from ``(4, i)`` and image trial ``i`` from ``(5, i)``
    (:func:`~forensics._shared.rng.keyed_generator`).  ``executor`` runs the trials (None: in this process);
    the result is the same on every backend.
    """
    sets, images = dating_records(settings, rng, range(trials), within_fraction, executor=executor,
                                  progress=progress)
    return summarise_dating(settings, sets, images, seed_record(rng))


def dating_records(settings: ValidationSettings, rng: RngLike, indices: Iterable[int],
                   within_fraction: float = 0.25, executor: Executor | None = None,
                   progress: Progress = no_progress) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The set- and image-dating records of the trials ``indices`` of the run ``rng`` (any subset), in the
    order given; one work item per trial on ``executor`` (None: in this process)."""
    setup = TrialSetup(settings, scene_pool(settings, keyed_generator(rng, 3)), within_fraction)
    items = [Trial(int(i), stream_root(rng)) for i in indices]
    pairs = list(resolve(executor).map(run_dating_trial, items, shared=setup, progress=progress,
                                       desc="validate dating"))
    return [p[0] for p in pairs], [p[1] for p in pairs]


def summarise_dating(settings: ValidationSettings, sets: list[dict[str, Any]], images: list[dict[str, Any]],
                     seed: Any = 0) -> ValidationResult:
    """Metrics (with acceptance checks) from per-trial records; ``seed`` is recorded as given."""
    n = len(sets)
    metrics = [proportion("set dating: coverage of the 95 % interval", sum(r["covered"] for r in sets), n,
                          *ACCEPT_COVERAGE)]
    after = [r for r in sets if not r["within"]]
    within = [r for r in sets if r["within"]]
    if after and within:
        metrics.append(proportion("  … queries after the last reference", sum(r["covered"] for r in after), len(after)))
        metrics.append(proportion("  … queries inside the reference span", sum(r["covered"] for r in within),
                                  len(within)))
    metrics += error_metrics("set dating", np.array([r["estimate"] for r in sets]),
                             np.array([r["t_true"] for r in sets]), "years")
    qualified = [r for r in images if r["distinct"] >= 10]
    metrics.append(proportion("single-image dating: true interval, ≥ 10 distinct onsets",
                              sum(r["correct"] for r in qualified), len(qualified), 0.80,
                              note=f"{len(qualified)} of {len(images)} trials qualify"))
    metrics.append(proportion("single-image dating: true interval, all trials", sum(r["correct"] for r in images),
                              len(images)))
    err = np.array([r["best"] - r["true"] for r in images if r["groups"]])
    return ValidationResult("dating", settings, n, seed, metrics, sets + images,
                            {"interval_error_histogram": np.bincount(np.abs(err)).tolist() if len(err) else [],
                             "set_coverage": [[r["t_true"], r["lo"], r["hi"]] for r in sets]})
