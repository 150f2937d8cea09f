"""The ageing-impact experiment: EER against virtual sensor age, for any matcher (the reference paper's section 5).

For every virtual sensor, one device (one defect history) ages every image of the source set to every age —
exactly the ageing simulation of :func:`~forensics.sensor.simulate.age_dataset` — and every matcher encodes
each aged image once.  At every age all genuine and all impostor comparisons (pairs ``i < j`` of the set, or a
documented sample of the impostor pairs) are scored under two protocols:

``same-age``
    enrolment and probe both aged to the same age (the reference paper's protocol);
``enrol-0``
    enrolment image at age 0, probe aged to age T (what an operator whose sensor ages after enrolment
    faces).  Pair ``i < j`` enrols image ``i`` and probes with image ``j``.

Statistics.  The EER's interval resamples *classes* (:mod:`forensics.stats.clustered`), because comparisons
sharing an image are not independent.  Every sensor, age, matcher and protocol uses the same class resamples,
so replicate ``r`` of the EER at two ages is the same resample of subjects: the trend against age (the OLS
slope of the EER on age) and the change from the first to the last age get paired intervals, and a change is
called significant only when its interval excludes zero.  Across sensors (the paper's figure 6) the mean EER
at each age gets a paired interval too, with the spread (standard deviation, range) beside it.

Execution.  Every (sensor, age) is computed by a task of the execution layer (:mod:`forensics._shared.parallel`):
a worker realises the sensor's device from its keyed stream, reads the source images from their paths, ages
and encodes them, scores the pairs and runs the class bootstrap, and hands back the EERs.  Tasks at age 0 come
first when the ``enrol-0`` protocol is asked for, because their templates are every later task's enrolment
gallery (shipped to the workers once).  Nothing a task computes depends on which process runs it, so the
result is identical in-process, in local processes and on a Dask cluster.

Reuse.  Aged images change only when a defect appears or grows: sensor A's 13 ages give 3 distinct sets of
aged images of the IITD eyes, and at age 0 every noiseless sensor records the source image.  A cheap first
pass ages every (sensor, age) and digests its images; of the tasks with byte-identical inputs only the first
is computed and the others take its results (exactly: everything after the ageing is a deterministic function
of the aged images).  Sensors with frame noise give distinct images at every age and are computed in full.
Inside a computed task most *templates* are still byte-identical to those of the sensor's previous distinct
age (a new defect lands in the sampled iris of only some images): the score of a pair whose two templates are
byte-identical to those of a pair already scored is copied (:mod:`forensics.impact.reuse`; exact, the
templates' complete content is hashed).  For that, every sensor's first age runs first, one task each, and then
each sensor's later distinct ages run in age order in one work item holding only the previous age's scores;
``computed_pairs`` and ``copied_pairs`` count the comparisons.  Parallelism is then across sensors.  The
chain also carries the previous age's templates with the digests of their rubber-sheet bands: a built-in
matcher's template whose band is byte-identical to that age's is that template (its encoding is a deterministic
function of the band; :func:`~forensics.impact.reuse.encode_reusing`), so only the segmentation and the unwrapping
are recomputed for it; ``reused_templates`` counts them.  And each image's segmentation reuses the costly steps
(Hough transforms, limbus fits) whose inputs are byte-identical to those of the same eye's previous segmentation
(:class:`~forensics.impact.segment.memo.StepMemo`, exact by construction); ``reused_steps`` counts them.

Memory of the score reuse: a work item holds the scores of the previous and the current age, n (n − 1) / 2
float64 per matcher and protocol (2,240 images: 20 MB each, 480 MB at most for six matchers and both
protocols), and every worker holds the first ages' scores its chains start from (240 MB per distinct first
age), whatever the number of ages or sensors; the chains also hold the previous age's templates (about 30 kB
per image for the six built-ins), and a cross-correlation comparison (``cr``, ``qsw``, Masek) works in up to
≈ 0.6 GB while it compares a band of rows (:func:`~forensics.impact.spectral.shift_counts`).

Resuming.  With a checkpoint folder (:class:`~forensics._shared.parallel.Checkpoint`), every finished work item
— a (sensor, age), or with reuse a sensor's chain of later ages — writes its results (and at the first age the
enrolment templates and the scores the chains start from) atomically; a rerun with the same settings skips
them and gives the identical result.
"""
from __future__ import annotations

import dataclasses
import hashlib
import pickle
import time
import warnings
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics import __version__
from forensics._shared.errors import InputError, UsageError
from forensics._shared.parallel import Checkpoint, Executor, in_process, resolve
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator, keyed_generator, seed_record
from forensics.impact.matchers import Matcher, compare_all, template_failure
from forensics.impact.reuse import (
    ScoredPairs,
    best_base,
    encode_reusing,
    fill_pairs,
    fill_upper,
    score_digest,
    segment_reusing,
    step_segmenters,
)
from forensics.io.dataset import Dataset
from forensics.sensor.model import SensorModel, load_model
from forensics.sensor.presets import PRESETS, preset
from forensics.sensor.simulate import aged_exposures, source_bit_depth
from forensics.stats.clustered import (
    ClassBootstrap,
    PairedScores,
    class_bootstrap_eer,
    class_weights,
)
from forensics.stats.scores import percentile_ci

__all__ = [
    "PROTOCOLS",
    "ImpactResult",
    "SensorSpec",
    "Spread",
    "Trend",
    "UnitResult",
    "parse_sensors",
    "run_impact",
]

PROTOCOLS: dict[str, str] = {
    "same-age": "enrolment and probe both aged to the same age (the reference paper's protocol)",
    "enrol-0": "enrolment at age 0, probe aged to age T (the operator's protocol)",
}
# Sub-streams of the run's seed (keyed_generator keys): one device per sensor, the class resamples, the
# impostor sample.  Keyed by the sensor's name, so adding a sensor changes no other sensor's history.
_DEVICE_STREAM, _BOOT_STREAM, _SAMPLE_STREAM = 1, 2, 3
_HIST_BINS = 60


@dataclass(frozen=True)
class SensorSpec:
    """A virtual sensor: its name in outputs and its model."""

    name: str
    model: SensorModel

    def stream_key(self) -> int:
        return zlib.crc32(self.name.encode())


def parse_sensors(spec: str, shape: tuple[int, int], bit_depth: int) -> list[SensorSpec]:
    """Sensors from a comma list: presets ``A``–``H``, ``H*100`` (a preset with its rates × 100), or the path of
    a ``sensor.json`` written by ``forensics simulate age`` (its name is the file's folder)."""
    out: list[SensorSpec] = []
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        name, _, scale = item.partition("*")
        if name.upper() in PRESETS:
            try:
                rate_scale = float(scale) if scale else 1.0
            except ValueError:
                raise UsageError(f"--sensors '{item}': write a preset and a rate factor as H*100") from None
            if not (np.isfinite(rate_scale) and rate_scale > 0):
                raise UsageError(f"--sensors '{item}': the rate factor must be a finite number > 0")
            label = name.upper() + (f"×{rate_scale:g}" if scale else "")
            out.append(SensorSpec(label, preset(name, shape, bit_depth=bit_depth, rate_scale=rate_scale)))
        elif item.endswith(".json"):
            model = load_model(item)
            if tuple(model.shape) != tuple(shape) or model.bit_depth != bit_depth:
                raise InputError(f"{item}: the sensor is {model.shape[1]}×{model.shape[0]} at {model.bit_depth} bits "
                                 f"but the images are {shape[1]}×{shape[0]} at {bit_depth} bits")
            out.append(SensorSpec(Path(item).resolve().parent.name or Path(item).stem, model))
        else:
            raise UsageError(f"--sensors '{item}': use presets A–H, a preset with a rate factor (H*100) or a "
                             "sensor.json")
    if not out:
        raise UsageError("--sensors: name at least one sensor (e.g. A,B,H)")
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise UsageError(f"--sensors: a sensor is named twice ({', '.join(names)})")
    return out


@dataclass
class UnitResult:
    """One EER: a sensor at an age, one matcher, one protocol.

    ``failed_images`` are the images (file names) whose template at this age carries a failed segmentation
    (:func:`~forensics.impact.matchers.template_failure`); ``failed_pairs`` the comparisons in which one of
    the two templates failed (for ``enrol-0`` the enrolment template at age 0 counts too).  A failed image is
    not scored as if its circles were an eye: its comparisons count as non-matches at every threshold (a
    genuine pair falsely rejected, an impostor pair correctly rejected; ISO/IEC 19795-1's generalised rates).
    """

    sensor: str
    age: float
    matcher: str
    protocol: str
    eer: ClassBootstrap
    histogram: dict[str, Any]
    failed_images: tuple[str, ...] = ()
    failed_pairs: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"sensor": self.sensor, "age": self.age, "matcher": self.matcher, "protocol": self.protocol,
                **self.eer.to_dict(),
                "segmentation_failures": {"images": list(self.failed_images), "n": len(self.failed_images),
                                          "failed_pairs": self.failed_pairs}}


@dataclass(frozen=True)
class Trend:
    """The EER's trend against age for one sensor, matcher and protocol (paired over class resamples)."""

    sensor: str
    matcher: str
    protocol: str
    slope: float
    slope_ci: tuple[float, float]
    p_value: float
    change: float
    change_ci: tuple[float, float]
    level: float

    @property
    def significant(self) -> bool:
        return not (self.slope_ci[0] <= 0.0 <= self.slope_ci[1])

    def describe(self) -> str:
        per_decade = [10 * v * 100 for v in (self.slope, *self.slope_ci)]
        verdict = "significant" if self.significant else "no significant trend"
        return (f"{verdict}: slope {per_decade[0]:+.3f} points per decade "
                f"[{per_decade[1]:+.3f}, {per_decade[2]:+.3f}], p = {self.p_value:.3g}")

    def to_dict(self) -> dict[str, Any]:
        return {"sensor": self.sensor, "matcher": self.matcher, "protocol": self.protocol,
                "slope_per_year": self.slope, "slope_ci": list(self.slope_ci), "p_value": self.p_value,
                "significant": self.significant, "change": self.change, "change_ci": list(self.change_ci),
                "level": self.level}


@dataclass(frozen=True)
class Spread:
    """The EER across sensors at one age (the paper's figure 6): mean with a paired interval, SD, range."""

    matcher: str
    protocol: str
    age: float
    mean: float
    mean_ci: tuple[float, float]
    sd: float
    minimum: float
    maximum: float
    n_sensors: int

    def to_dict(self) -> dict[str, Any]:
        return {"matcher": self.matcher, "protocol": self.protocol, "age": self.age, "mean": self.mean,
                "mean_ci": list(self.mean_ci), "sd": self.sd, "min": self.minimum, "max": self.maximum,
                "n_sensors": self.n_sensors}


@dataclass
class ImpactResult:
    """Everything :func:`run_impact` measured."""

    source: str
    n_images: int
    n_classes: int
    n_genuine: int
    n_impostor: int
    impostors_sampled: bool
    sensors: list[str]
    ages: list[float]
    matchers: list[str]
    protocols: list[str]
    n_boot: int
    level: float
    seed: Any
    units: list[UnitResult]
    trends: list[Trend] = field(default_factory=list)
    spreads: list[Spread] = field(default_factory=list)
    elapsed_s: float = 0.0
    resumed_units: int = 0
    #: Units copied from a (sensor, age) whose aged images are byte for byte the same (see :func:`run_impact`).
    reused_units: int = 0
    #: Comparisons scored, and comparisons whose score was copied because both templates are byte-identical to
    #: those of a pair already scored (:mod:`forensics.impact.reuse`), over the computed (sensor, age) tasks.
    computed_pairs: int = 0
    copied_pairs: int = 0
    #: Templates taken from the sensor's previous computed age because their band (texture, mask and
    #: segmentation) was byte-identical (:func:`~forensics.impact.reuse.encode_reusing`): encodings skipped.
    reused_templates: int = 0
    #: Costly segmentation steps whose result was taken from the same eye's previous age because their inputs
    #: were byte-identical (:class:`~forensics.impact.segment.memo.StepMemo`): Hough transforms and limbus fits.
    reused_steps: int = 0
    #: Segmentation method of each matcher that segments (``matcher.segmenter.method``), None for the others.
    segmentations: dict[str, str | None] = field(default_factory=dict)

    def unit(self, sensor: str, age: float, matcher: str, protocol: str) -> UnitResult:
        for u in self.units:
            if (u.sensor, u.age, u.matcher, u.protocol) == (sensor, age, matcher, protocol):
                return u
        raise KeyError((sensor, age, matcher, protocol))

    def trajectory(self, sensor: str, matcher: str, protocol: str) -> list[UnitResult]:
        return [self.unit(sensor, a, matcher, protocol) for a in self.ages]

    def trend(self, sensor: str, matcher: str, protocol: str) -> Trend:
        return next(t for t in self.trends if (t.sensor, t.matcher, t.protocol) == (sensor, matcher, protocol))

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "n_images": self.n_images, "n_classes": self.n_classes,
                "n_genuine": self.n_genuine, "n_impostor": self.n_impostor,
                "impostors": "sample" if self.impostors_sampled else "all", "sensors": self.sensors,
                "ages": self.ages, "matchers": self.matchers,
                "protocols": {p: PROTOCOLS[p] for p in self.protocols}, "n_boot": self.n_boot,
                "level": self.level, "bootstrap": "classes resampled with replacement; same resamples for "
                                                  "every sensor, age, matcher and protocol (paired)",
                "seed": self.seed, "units": [u.to_dict() for u in self.units],
                "trends": [t.to_dict() for t in self.trends], "spreads": [s.to_dict() for s in self.spreads],
                "elapsed_s": self.elapsed_s, "resumed_units": self.resumed_units, "reused_units": self.reused_units,
                "computed_pairs": self.computed_pairs, "copied_pairs": self.copied_pairs,
                "reused_templates": self.reused_templates, "reused_steps": self.reused_steps,
                "segmentations": dict(self.segmentations), "forensics_version": __version__}


def _classes(source: Dataset) -> tuple[np.ndarray, list[str]]:
    subjects = []
    for frame in source.frames:
        subject = frame.subject
        if subject is None or str(subject).strip() == "":
            raise InputError(f"{source.root / 'manifest.csv'}: {frame.file} has no subject; the impact experiment "
                             "needs the class of every image in the manifest's 'subject' column")
        subjects.append(str(subject))
    names = sorted(set(subjects))
    index = {n: k for k, n in enumerate(names)}
    return np.array([index[s] for s in subjects], dtype=np.intp), names


def _pairs(labels: np.ndarray, impostors: int | None, rng: RngLike) -> tuple[np.ndarray, np.ndarray, bool]:
    """All pairs ``i < j``, or all genuine pairs and a uniform sample of ``impostors`` impostor pairs."""
    i, j = np.triu_indices(labels.size, 1)
    genuine = labels[i] == labels[j]
    if impostors is None or impostors >= int((~genuine).sum()):
        return i, j, False
    pick = keyed_generator(rng, _SAMPLE_STREAM).choice(np.flatnonzero(~genuine), size=int(impostors), replace=False)
    keep = np.sort(np.concatenate([np.flatnonzero(genuine), pick]))
    return i[keep], j[keep], True


def _scores(matcher: Matcher, enrol: Sequence[Any], probe: Sequence[Any], i: np.ndarray, j: np.ndarray,
            sampled: bool) -> np.ndarray:
    """Scores of pairs (enrol[i], probe[j]): the vectorised matrix when all pairs are wanted, else pair by pair
    for matchers without their own ``compare_all``."""
    if sampled and not hasattr(matcher, "compare_all"):
        return np.array([matcher.compare(enrol[a], probe[b]) for a, b in zip(i, j)], dtype=np.float64)
    if not sampled:
        return _upper_scores(matcher, enrol, probe)
    matrix = np.asarray(compare_all(matcher, enrol, probe), dtype=np.float64)
    return matrix[i, j]


def _upper_scores(matcher: Matcher, enrol: Sequence[Any], probe: Sequence[Any], band: int | None = None) -> np.ndarray:
    """Scores of every pair ``i < j`` (enrol[i], probe[j]), in :func:`numpy.triu_indices` order.

    Only the upper triangle is computed, in bands of ``band`` rows (:func:`upper_band`) against the columns
    right of the band's first row: :func:`upper_entries` of the ``n²`` entries of the whole matrix.  Every
    score is a function of its two templates only, so each equals the full matrix's (tested).
    """
    n = len(enrol)
    band = band or upper_band(n)
    parts = []
    for k in range(0, n - 1, band):
        rows = list(enrol[k:min(k + band, n - 1)])
        block = np.asarray(compare_all(matcher, rows, list(probe[k + 1:])), dtype=np.float64)
        parts.extend(block[r, r:] for r in range(len(rows)))
    return np.concatenate(parts) if parts else np.empty(0, dtype=np.float64)


def upper_band(n: int) -> int:
    """Rows per band of :func:`_upper_scores`: at least 256, at most 8 bands.

    A matcher's ``compare_all`` prepares every column template once per call (the rotated codes: for ``dct``
    75 shifted copies per template), so narrow bands repeat that preparation; 8 bands of ``n / 8`` rows
    compute ``n² / 2 + n² / 16`` entries (56 % of the full matrix) and prepare each column at most 8 times.
    """
    return max(256, -(-n // 8))


def upper_entries(n: int, band: int | None = None) -> int:
    """Matrix entries :func:`_upper_scores` computes for ``n`` templates (``n (n − 1) / 2`` plus the bands'
    slivers below the diagonal)."""
    band = band or upper_band(n)
    return sum(min(band, n - 1 - k) * (n - 1 - k) for k in range(0, n - 1, band))


def _histogram(pairs: PairedScores, higher_is_similar: bool) -> dict[str, Any]:
    """A coarse histogram of the genuine and impostor scores in the matcher's own orientation (for reports)."""
    g, imp = pairs.split()
    sign = 1.0 if higher_is_similar else -1.0
    g, imp = sign * g, sign * imp
    lo, hi = float(min(g.min(), imp.min())), float(max(g.max(), imp.max()))
    edges = np.linspace(lo, hi if hi > lo else lo + 1.0, _HIST_BINS + 1)
    return {"edges": edges.tolist(), "genuine": np.histogram(g, edges)[0].tolist(),
            "impostor": np.histogram(imp, edges)[0].tolist()}


def _stream_root(rng: RngLike) -> int | np.random.SeedSequence:
    """What workers derive the run's keyed sub-streams from: the integer seed, or the generator's seed sequence.

    ``keyed_generator`` of either gives exactly the sub-streams of ``rng`` itself, and neither carries the
    generator's state, so a task's streams depend on the seed and its key only, wherever it runs.
    """
    if isinstance(rng, (int, np.integer, np.random.SeedSequence)) and not isinstance(rng, (bool, np.bool_)):
        return rng
    return as_generator(rng).bit_generator.seed_seq


@dataclass(frozen=True)
class _Encoded:
    """The templates of one (sensor, age) and the digests of their bands, per matcher name, one per image; and
    per image the segmentation steps of each of the matchers' segmenters
    (:func:`~forensics.impact.reuse.step_segmenters`), which the next age's segmentations start from (None
    without reuse)."""

    templates: dict[str, list[Any]]
    bands: dict[str, list[bytes | None]]
    steps: list[tuple[dict[bytes, Any], ...]] | None = None
    #: The age index these templates were made at (their images are re-aged to compare pixels with the next age's).
    age: int | None = None


@dataclass(frozen=True)
class _ImpactJob:
    """What every (sensor, age) task needs: shipped once per worker (the executor's ``shared``), never per task."""

    sensors: list[SensorSpec]
    ages: list[float]
    matchers: list[Matcher]
    protocols: list[str]
    paths: list[str]
    dtype: str
    shape: tuple[int, ...]
    labels: np.ndarray
    n_classes: int
    impostors: int | None
    root: int | np.random.SeedSequence
    weights: np.ndarray
    level: float
    keep_enrol: bool
    reuse: bool = True
    #: Age-0 templates of every sensor (sensor index → matcher name → templates), the enrol-0 gallery.
    enrol: dict[int, dict[str, list[Any]]] | None = None
    #: With reuse: the age indices each sensor's chain computes (:func:`_chain_task`), in order, and the scores
    #: its chain starts from (sensor index → matcher name → :class:`~forensics.impact.reuse.ScoredPairs`).
    chains: dict[int, list[int]] | None = None
    starts: dict[int, dict[str, list[ScoredPairs]]] | None = None
    #: With reuse: each chained sensor's first-age templates and band digests (matcher name → one per image),
    #: from which its chain's first age reuses the templates of unchanged bands.
    firsts: dict[int, _Encoded] | None = None


def _impact_task(job: _ImpactJob, item: tuple[int, int]) -> dict[str, Any]:
    """One (sensor, age) scored in full: age and encode every image, score every matcher and protocol, bootstrap.

    Returns ``{"units": [UnitResult, …], "enrol": templates or None, "bases": scores or None, "computed": n,
    "copied": n}``; the templates are kept only at age 0 and only when a later task needs them as its enrolment
    gallery, the scores (:class:`~forensics.impact.reuse.ScoredPairs` per matcher) only with ``job.reuse``, as
    the start of the sensors' chains (:func:`_chain_task`), and so are the templates with their band digests
    (``"first"``, an :class:`_Encoded`).
    """
    s_index, a_index = item
    pairs = _pairs(job.labels, job.impostors, job.root)
    units, encoded, bases, computed, copied, _ = _score_cell(job, s_index, a_index, pairs, {}, None)
    return {"units": units, "enrol": encoded.templates if job.ages[a_index] == 0.0 and job.keep_enrol else None,
            "bases": bases if job.chains else None, "first": encoded if job.chains else None,
            "computed": computed, "copied": copied}


def _chain_task(job: _ImpactJob, s_index: int) -> dict[str, Any]:
    """Every distinct later (sensor, age) of one sensor, in age order, each reusing the scores of the one before.

    A sensor's ages run one after the other in one work item so that each can copy the scores of pairs whose
    templates did not change since the previous computed age (:mod:`forensics.impact.reuse`); the chain starts
    from the scores of the sensor's first age (``job.starts``, computed first by :func:`_impact_task`).  Only
    the previous age's scores are held, so memory does not grow with the number of ages.

    The templates are reused the same way: each age starts from the previous one's (:class:`_Encoded`; the
    first from ``job.firsts``), and a template whose band is unchanged is not encoded again.

    The segmentations too: each image's starts from the steps of the same image's previous segmentation
    (:func:`~forensics.impact.reuse.segment_reusing`).

    Returns ``{"cells": [[age index, [UnitResult, …]], …], "computed": n, "copied": n, "templates_reused": n,
    "steps_reused": n}``.
    """
    pairs = _pairs(job.labels, job.impostors, job.root)
    bases = (job.starts or {}).get(s_index, {})
    before = (job.firsts or {}).get(s_index)
    cells, computed, copied, reused, steps = [], 0, 0, 0, 0
    for a_index in (job.chains or {}).get(s_index, []):
        units, before, bases, done, same, (kept, recalled) = _score_cell(job, s_index, a_index, pairs, bases,
                                                                         before)
        cells.append([a_index, units])
        computed, copied, reused, steps = computed + done, copied + same, reused + kept, steps + recalled
    return {"cells": cells, "computed": computed, "copied": copied, "templates_reused": reused,
            "steps_reused": steps}


def _score_cell(job: _ImpactJob, s_index: int, a_index: int, pairs: tuple[np.ndarray, np.ndarray, bool],
                bases: dict[str, list[ScoredPairs]], before: _Encoded | None
                ) -> tuple[list[UnitResult], _Encoded, dict[str, list[ScoredPairs]], int, int, tuple[int, int]]:
    """Units of one (sensor, age), its templates, its scores (with ``job.reuse``), the pairs computed / copied and
    the templates and segmentation steps reused from ``before`` (:func:`_aged_templates`).

    With ``job.reuse`` every (matcher, protocol) starts from the stored scores (``bases``: the previous age's of
    this sensor, and for ``enrol-0`` this age's ``same-age`` scores) that leave the fewest pairs to compute, and
    copies the score of every pair whose two templates are byte-identical to the stored pair's.
    """
    i, j, sampled = pairs
    spec, age = job.sensors[s_index], job.ages[a_index]
    encoded, reused, steps_reused = _aged_templates(job, s_index, a_index, before)
    templates = encoded.templates
    enrol = templates if age == 0.0 else (job.enrol or {}).get(s_index)
    units, made_all, computed = [], {}, 0
    for matcher in job.matchers:
        probe = templates[matcher.name]
        probe_failed = _failed(probe)
        names = tuple(Path(job.paths[k]).name for k in np.flatnonzero(probe_failed))
        probe_digests = [score_digest(matcher, t) for t in probe] if job.reuse else None
        made: list[ScoredPairs] = []
        for protocol in job.protocols:
            gallery = probe if protocol == "same-age" else enrol[matcher.name]
            keep = ~(_failed(gallery)[i] | probe_failed[j])
            if job.reuse:
                gallery_digests = probe_digests if gallery is probe else [score_digest(matcher, t) for t in gallery]
                scores, done = _reused_scores(matcher, gallery, probe, gallery_digests, probe_digests, pairs,
                                              [*bases.get(matcher.name, ()), *made])
                scores.flags.writeable = False   # kept for later ages (and maybe shared): nothing may alter it
                made.append(ScoredPairs(tuple(gallery_digests), tuple(probe_digests), scores))
            else:
                scores, done = _scores(matcher, gallery, probe, i, j, sampled), i.size
            computed += done
            if not np.all(np.isfinite(scores[keep])):
                raise InputError(f"matcher {matcher.name} returned a score that is not a finite number")
            scores = _reject_failed(scores, keep, matcher.higher_is_similar)
            scored = PairedScores.of(scores, job.labels[i], job.labels[j], job.n_classes,
                                     higher_is_similar=matcher.higher_is_similar)
            shown = scored if keep.all() or not keep.any() else PairedScores.of(
                scores[keep], job.labels[i[keep]], job.labels[j[keep]], job.n_classes,
                higher_is_similar=matcher.higher_is_similar)
            # The bootstrap's matrix products are BLAS calls; OpenBLAS gives the same bits whatever its thread
            # count (it never splits a dot product), so a worker's EERs equal the in-process ones.
            units.append(UnitResult(spec.name, age, matcher.name, protocol,
                                    class_bootstrap_eer(scored, job.weights, job.level),
                                    _histogram(shown, matcher.higher_is_similar), names,
                                    int((~keep).sum())))
        made_all[matcher.name] = made
    total = i.size * len(job.matchers) * len(job.protocols)
    return units, encoded, made_all, computed, total - computed, (reused, steps_reused)


def _reused_scores(matcher: Matcher, gallery: Sequence[Any], probe: Sequence[Any],
                   gallery_digests: list[bytes | None], probe_digests: list[bytes | None],
                   pairs: tuple[np.ndarray, np.ndarray, bool], bases: list[ScoredPairs]) -> tuple[np.ndarray, int]:
    """Scores of the run's pairs, copied from the best of ``bases`` where both templates are byte-identical to the
    stored pair's, computed otherwise; and how many were computed."""
    i, j, sampled = pairs
    base, rows, cols = best_base(bases, gallery_digests, probe_digests, i, j)
    stored = base.scores if base is not None else None
    if sampled:
        return fill_pairs(matcher, gallery, probe, i, j, rows, cols, stored)
    return fill_upper(matcher, gallery, probe, rows, cols, stored, upper_band(len(gallery)))


def _reject_failed(scores: np.ndarray, keep: np.ndarray, higher_is_similar: bool) -> np.ndarray:
    """Scores with the pairs not in ``keep`` set one step beyond the least similar real score.

    A comparison involving a failed segmentation is a non-match at every threshold that matters (ISO/IEC
    19795-1's generalised false-reject and false-accept rates count a failure to acquire so): a genuine pair
    is falsely rejected, an impostor pair correctly rejected.  When every pair failed, all are tied and the EER
    is 50 %: chance.
    """
    if keep.all():
        return scores
    if not keep.any():
        return np.zeros_like(scores)
    real = scores[keep]
    worst = float(real.min()) - 1.0 if higher_is_similar else float(real.max()) + 1.0
    return np.where(keep, scores, worst)


def _failed(templates: Sequence[Any]) -> np.ndarray:
    """Which templates carry a failed segmentation (:func:`~forensics.impact.matchers.template_failure`)."""
    return np.array([template_failure(t) is not None for t in templates], dtype=bool)


def _aged_images(job: _ImpactJob, s_index: int, a_index: int, previous: int | None = None
                 ) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """Every source image aged by sensor ``s_index`` to age ``a_index``, one at a time, in the set's order, with
    the same image aged to age index ``previous`` (None without one).

    The device comes from the sensor's keyed stream and image ``k``'s frame noise from its sub-stream
    ``(k, a_index)`` (:func:`~forensics.sensor.simulate.aged_exposures`): the images ``forensics simulate age``
    writes with that stream, whichever process ages them.
    """
    from forensics.io.images import read_image

    spec, age = job.sensors[s_index], job.ages[a_index]
    sensor_rng = keyed_generator(job.root, _DEVICE_STREAM, spec.stream_key())
    device = spec.model.realize(sensor_rng, [spec.model.t0 + a for a in job.ages])
    ctx = device.context(spec.model.t0 + age)
    for index, path in enumerate(job.paths):
        image = read_image(path)
        if image.dtype.str != job.dtype or image.shape != job.shape:
            raise InputError(f"{path}: {image.dtype} {image.shape} differs from the first image "
                             f"({np.dtype(job.dtype)} {job.shape}); a source set must be uniform")
        earlier = None if previous is None else aged_exposures(
            device, image, [device.context(spec.model.t0 + job.ages[previous])], sensor_rng, index,
            first_step=previous)[0]
        yield aged_exposures(device, image, [ctx], sensor_rng, index, first_step=a_index)[0], earlier


def _aged_templates(job: _ImpactJob, s_index: int, a_index: int, before: _Encoded | None
                    ) -> tuple[_Encoded, int, int]:
    """Every aged image (:func:`_aged_images`) encoded by every matcher, and how many templates and segmentation
    steps were reused.

    With ``job.reuse`` a built-in matcher's template is ``before``'s (the sensor's previous computed age) where
    the image's band is byte-identical to that age's (:func:`~forensics.impact.reuse.encode_reusing`; not even
    unwrapped where the pixels it reads and the segmentation are unchanged: the image is aged to ``before``'s age
    too to compare), and each segmentation reuses the costly steps whose inputs are byte-identical to
    ``before``'s (:func:`~forensics.impact.reuse.segment_reusing`).
    """
    templates: dict[str, list[Any]] = {m.name: [] for m in job.matchers}
    bands: dict[str, list[bytes | None]] = {m.name: [] for m in job.matchers}
    segmenters = step_segmenters(job.matchers) if job.reuse else []
    prior_steps = getattr(before, "steps", None) if before is not None else None
    steps: list[tuple[dict[bytes, Any], ...]] = []
    reused = steps_reused = 0
    previous = getattr(before, "age", None) if job.reuse and before is not None else None
    for k, (aged, earlier) in enumerate(_aged_images(job, s_index, a_index, previous)):
        if segmenters:
            recorded = prior_steps[k] if prior_steps is not None else (None,) * len(segmenters)
            memos = [segment_reusing(seg, aged, old) for seg, old in zip(segmenters, recorded)]
            steps.append(tuple(memo.entries for memo in memos))
            steps_reused += sum(memo.hits for memo in memos)
        for matcher in job.matchers:
            if job.reuse:
                prior = (before.bands[matcher.name][k], before.templates[matcher.name][k]) if before else None
                band, template, same = encode_reusing(matcher, aged, prior, earlier)
            else:
                band, template, same = None, matcher.encode(aged), False
            templates[matcher.name].append(template)
            bands[matcher.name].append(band)
            reused += same
    return _Encoded(templates, bands, steps if segmenters else None, a_index), reused, steps_reused


def _digest_task(job: _ImpactJob, item: tuple[int, int]) -> bytes:
    """BLAKE2b digest of every aged image of one (sensor, age), in order (pixels, dtype and shape).

    Two (sensor, age) tasks with the same digest age every image to the same array; the matchers and
    everything after them are deterministic functions of those arrays, so their results are the same.
    """
    digest = hashlib.blake2b(digest_size=20)
    for aged, _ in _aged_images(job, *item):
        digest.update(f"{aged.dtype.str}{aged.shape}".encode())
        digest.update(np.ascontiguousarray(aged).tobytes())
    return digest.digest()


class _OneBar:
    """One progress bar over the tasks of several maps: a ``Progress`` whose every tick advances the same bar."""

    def __init__(self, progress: Progress, total: int, desc: str) -> None:
        self._ticks = iter(progress(range(total), total=total, desc=desc))

    def __call__(self, iterable: Iterable[Any], total: int | None = None, desc: str | None = None) -> Iterator[Any]:
        for value in iterable:
            next(self._ticks, None)
            yield value

    def close(self) -> None:
        for _ in self._ticks:
            pass


def _pickling_problem(objects: Sequence[Any], backend: str) -> str | None:
    """Why one of ``objects`` (matchers, sensors) cannot be sent to a worker, or None."""
    for obj in objects:
        try:
            pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # noqa: BLE001 — whatever a user's object raises when pickled
            if backend == "dask":  # Dask falls back on cloudpickle, which ships more (classes by value)
                try:
                    import cloudpickle

                    cloudpickle.dumps(obj)
                    continue
                except Exception:  # noqa: BLE001
                    pass
            kind = "sensor" if isinstance(obj, SensorSpec) else "matcher"
            name = getattr(obj, "name", type(obj).__name__)
            return f"{kind} {name!r} cannot be sent to worker processes ({type(exc).__name__}: {exc})"
    return None


def _usable_executor(ex: Executor, job: _ImpactJob) -> Executor:
    """``ex``, or the in-process executor (with a warning) when a matcher or sensor cannot be pickled."""
    if ex.backend == "in-process":
        return ex
    problem = _pickling_problem([*job.matchers, *job.sensors], ex.backend)
    if problem is None:
        return ex
    warnings.warn(f"{problem}; the impact experiment runs in this process instead (a matcher class defined in a "
                  "module or a file.py travels to workers; one holding open files, locks or lambdas does not)",
                  RuntimeWarning, stacklevel=3)
    return in_process()


def run_impact(
    source: Dataset,
    sensors: Sequence[SensorSpec],
    ages: Sequence[float],
    matchers: Sequence[Matcher],
    rng: RngLike,
    protocols: Sequence[str] = tuple(PROTOCOLS),
    n_boot: int = 1000,
    level: float = 0.95,
    impostors: int | None = None,
    checkpoint: str | Path | None = None,
    progress: Progress = no_progress,
    executor: Executor | None = None,
    reuse: bool = True,
) -> ImpactResult:
    """Age ``source`` with every sensor to every age, score it with every matcher, and measure the EER.

    Parameters
    ----------
    source
        A dataset whose manifest names each image's class in ``subject`` (left and right eye are two classes).
    sensors
        Virtual sensors (:func:`parse_sensors`).
    ages
        Ages in years after T0 (taken in ascending order); must include 0 for the ``enrol-0`` protocol.
    matchers
        Objects with ``encode``/``compare`` (see :mod:`forensics.impact.matchers`).  On worker processes they
        must be picklable (the built-ins, ``cmd:`` programs and classes loaded as ``module:Class`` or
        ``file.py:Class`` are); if one is not, the run stays in this process with a ``RuntimeWarning``.
    rng
        Integer seed or generator of everything random: sensor ``s``'s device and frame noise come from
        ``keyed_generator(rng, 1, crc32(name))`` exactly as :func:`~forensics.sensor.simulate.age_dataset`
        would draw them from that generator; the class resamples from ``keyed_generator(rng, 2)``; the
        impostor sample from ``keyed_generator(rng, 3)``.
    protocols
        Any of :data:`PROTOCOLS`.
    n_boot, level
        Class-bootstrap replicates and interval coverage.
    impostors
        Score only this many impostor pairs, drawn uniformly without replacement (the same pairs at every age
        and sensor); all genuine pairs are always scored.
    checkpoint
        Folder for resumable partial results (one file per finished sensor and age).  A folder made with
        other settings is refused (:class:`~forensics._shared.errors.UsageError`).
    progress
        Progress wrapper; one bar counts the finished work items ((sensor, age) tasks, or with ``reuse`` the
        sensors' first ages and then each sensor's later ages).
    executor
        Where the (sensor, age) tasks run (default: in this process); the result is the same on every backend.
    reuse
        Compute each distinct set of aged images once: a (sensor, age) whose aged images are byte for byte
        those of an earlier one (and, for ``enrol-0``, whose age-0 images are too) takes its results, under its
        own sensor and age (``reused_units`` counts them); and copy the score of every pair whose two templates
        are byte-identical to those of a pair scored at the sensor's previous computed age or, for ``enrol-0``,
        at the same age (``copied_pairs``; ``computed_pairs`` are scored).  A sensor's later ages then run in age
        order in one work item (a progress tick each), so the parallelism is across sensors.  The result is
        identical either way; False recomputes everything (for checking that).
    """
    started = time.perf_counter()
    ages = sorted(float(a) for a in ages)  # trends read ages in order
    _check_design(ages, matchers, protocols)
    names = [m.name for m in matchers]
    labels, class_names = _classes(source)
    if len(class_names) < 2:
        raise InputError(f"{source.root}: the impact experiment needs at least two classes (subjects)")
    i, j, sampled = _pairs(labels, impostors, rng)
    n_genuine = int((labels[i] == labels[j]).sum())
    if n_genuine == 0:
        raise InputError(f"{source.root}: no class has two images, so there is no genuine comparison")
    info = source.frames[0].info()
    shape = tuple(source.shape())
    bits = source_bit_depth(info.dtype)
    for spec in sensors:
        if tuple(spec.model.shape) != shape[:2] or spec.model.bit_depth != bits:
            raise InputError(f"{source.root}: images are {shape[1]}×{shape[0]} at {bits} bits but sensor {spec.name} "
                             f"is {spec.model.shape[1]}×{spec.model.shape[0]} at {spec.model.bit_depth} bits")
    job = _ImpactJob(list(sensors), ages, list(matchers), list(protocols),
                     [str(Path(f.path).absolute()) for f in source.frames], np.dtype(info.dtype).str, shape, labels,
                     len(class_names), impostors, _stream_root(rng),
                     class_weights(len(class_names), n_boot, keyed_generator(rng, _BOOT_STREAM)), float(level),
                     keep_enrol="enrol-0" in protocols, reuse=bool(reuse))
    segmentations = {m.name: _segmentation_of(m) for m in matchers}
    config = {"source": str(source.root), "files": [f.file for f in source.frames], "sensors": [s.name for s in sensors],
              "models": [s.model.to_dict() for s in sensors], "ages": ages, "matchers": names,
              "segmentations": segmentations,
              "protocols": list(protocols), "n_boot": int(n_boot), "level": float(level), "impostors": impostors,
              "seed": seed_record(rng), "forensics_version": __version__}
    store = Checkpoint(checkpoint, config, inputs=job.paths) if checkpoint is not None else None
    found, counts = _run_tasks(_usable_executor(resolve(executor), job), job, store, progress)
    units = [u for s in range(len(sensors)) for a in range(len(ages)) for u in found[s, a]]
    result = ImpactResult(str(source.root), len(source), len(class_names), n_genuine, int(i.size) - n_genuine,
                          sampled, [s.name for s in sensors], ages, names, list(protocols), int(n_boot),
                          float(level), seed_record(rng), units, resumed_units=counts["resumed"],
                          reused_units=counts["reused"], computed_pairs=counts["computed"],
                          copied_pairs=counts["copied"], reused_templates=counts["templates"],
                          reused_steps=counts["steps"], segmentations=segmentations)
    result.trends = trends(result)
    result.spreads = spreads(result)
    result.elapsed_s = time.perf_counter() - started
    return result


def _segmentation_of(matcher: Matcher) -> str | None:
    """The segmentation method a matcher uses (its ``segmenter.method``), or None if it has no segmenter."""
    method = getattr(getattr(matcher, "segmenter", None), "method", None)
    return str(method) if method is not None else None


def _check_design(ages: list[float], matchers: Sequence[Matcher], protocols: Sequence[str]) -> None:
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad:
        raise UsageError(f"unknown protocol {bad[0]!r}; choose from {', '.join(PROTOCOLS)}")
    if "enrol-0" in protocols and 0.0 not in ages:
        raise UsageError("the enrol-0 protocol enrols at age 0: include 0 in the ages")
    if len(ages) != len(set(ages)):
        raise UsageError("an age is given twice")
    names = [m.name for m in matchers]
    if len(set(names)) != len(names):
        raise UsageError(f"a matcher is named twice ({', '.join(names)})")


def _run_tasks(ex: Executor, job: _ImpactJob, store: Checkpoint | None,
               progress: Progress) -> tuple[dict[tuple[int, int], list[UnitResult]], dict[str, int]]:
    """Run every (sensor, age) on ``ex``: the units of each, and counts of how they were obtained.

    The counts: ``resumed`` units read from ``store``, ``reused`` units copied from a (sensor, age) with the same
    aged images, ``computed`` and ``copied`` comparisons (pairs scored, pairs whose score was copied from
    byte-identical templates), ``templates`` reused from the previous age of a chain.

    With ``job.reuse`` the aged images of every task are digested first (:func:`_digest_task`, cheap: ageing
    only), and of the tasks whose probe images — and, for ``enrol-0``, whose sensor's age-0 images — have the
    same digest only the first is computed; the others get its units under their own sensor and age.  Aged
    images change only when a defect appears or grows (sensor A: 3 distinct sets in 13 ages, and age 0 is the
    source image for every noiseless sensor), so most of the work repeats byte-identical inputs.  The computed
    tasks then run in two stages: every sensor's first age (age 0 with ``enrol-0``: its templates are the
    enrolment gallery), one task each (:func:`_impact_task`); then one work item per sensor running its later
    distinct ages in age order (:func:`_chain_task`), each copying the scores of unchanged templates from the age
    before.  Without reuse every (sensor, age) is one task.  Either way a task's result does not depend on the
    order or the process.
    """
    everything = [(s, a) for s in range(len(job.sensors)) for a in range(len(job.ages))]
    rep = _representatives(ex, job, everything, progress) if job.reuse else {t: t for t in everything}
    computed = [t for t in everything if rep[t] == t]
    lead = job.ages.index(0.0) if job.keep_enrol else 0
    if job.reuse:
        first = [(s, a) for s, a in computed if a == lead]
        chains = {s: [a for t, a in computed if t == s and a != lead] for s in range(len(job.sensors))}
        chains = {s: ages for s, ages in chains.items() if ages}
        # Longest chains first: with a few workers the last item to finish is then a short one.
        stages: list[list[Any]] = [first, sorted(chains, key=lambda s: (-len(chains[s]), s))]
        job = dataclasses.replace(job, chains=chains)
    else:
        first = [(s, a) for s, a in computed if job.keep_enrol and a == lead]
        stages = [first, [t for t in computed if t not in first]]
    def key(item: Any) -> str:
        return f"sensor{item:02d}-chain" if isinstance(item, int) else f"sensor{item[0]:02d}-age{item[1]:03d}"

    bar = _OneBar(progress, sum(len(t) for t in stages), "impact: sensor × age")
    found: dict[tuple[int, int], list[UnitResult]] = {}
    counts = dict.fromkeys(("resumed", "reused", "computed", "copied", "templates", "steps"), 0)
    for items in stages:
        if not items:
            continue
        keys = [key(t) for t in items]
        done = {k for k in keys if store is not None and store.has(k)}
        task = _chain_task if isinstance(items[0], int) else _impact_task
        outputs = ex.map(task, items, shared=job, progress=bar, desc="impact: sensor × age",
                         checkpoint=store, keys=keys)
        enrol_of, bases_of, firsts_of = {}, {}, {}
        for item, k, out in zip(items, keys, outputs):
            cells = out["cells"] if "cells" in out else [[item[1], out["units"]]]
            for a_index, units in cells:
                found[item if isinstance(item, tuple) else (item, a_index)] = units
                counts["resumed"] += len(units) if k in done else 0
            counts["computed"] += out.get("computed", 0)   # absent from items of earlier versions' checkpoints
            counts["copied"] += out.get("copied", 0)
            counts["templates"] += out.get("templates_reused", 0)
            counts["steps"] += out.get("steps_reused", 0)
            if out.get("enrol") is not None:
                enrol_of[item] = out["enrol"]
            if out.get("bases") is not None:
                bases_of[item] = out["bases"]
            if out.get("first") is not None:
                firsts_of[item] = out["first"]
        if enrol_of:
            job = dataclasses.replace(job, enrol={s: enrol_of[rep[s, lead]] for s in range(len(job.sensors))})
        if bases_of:
            job = dataclasses.replace(job, starts={s: bases_of[rep[s, lead]] for s in job.chains or {}
                                                   if rep[s, lead] in bases_of})
        if firsts_of:
            job = dataclasses.replace(job, firsts={s: firsts_of[rep[s, lead]] for s in job.chains or {}
                                                   if rep[s, lead] in firsts_of})
    bar.close()
    for task in everything:
        if rep[task] != task:
            spec, age = job.sensors[task[0]], job.ages[task[1]]
            found[task] = [dataclasses.replace(u, sensor=spec.name, age=age) for u in found[rep[task]]]
            counts["reused"] += len(found[task])
    return found, counts


def _representatives(ex: Executor, job: _ImpactJob, tasks: list[tuple[int, int]],
                     progress: Progress) -> dict[tuple[int, int], tuple[int, int]]:
    """For every task, the first task whose results must equal its own (itself when there is none).

    Results are equal when the probe images are (same digest) and, for the enrol-0 protocol, the enrolment
    images too (the sensor's age-0 digest).  Tasks are ordered sensor by sensor, ages ascending, so a group
    holding an age-0 task is represented by an age-0 task (whose templates are the enrolment gallery).
    """
    digests = dict(zip(tasks, ex.map(_digest_task, tasks, shared=job, progress=progress,
                                     desc="impact: ageing digests")))
    zero = job.ages.index(0.0) if job.keep_enrol else None
    first: dict[tuple[bytes, bytes | None], tuple[int, int]] = {}
    rep = {}
    for s, a in tasks:
        group = (digests[s, a], digests[s, zero] if zero is not None else None)
        rep[s, a] = first.setdefault(group, (s, a))
    return rep


def _ols_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """OLS slope of each column of ``y`` (ages along axis 0) on ``x``."""
    xc = x - x.mean()
    return (xc @ (y - y.mean(axis=0))) / (xc @ xc)


def trends(result: ImpactResult) -> list[Trend]:
    """The paired trend of every (sensor, matcher, protocol) trajectory with two or more ages."""
    out = []
    if len(result.ages) < 2:
        return out
    x = np.asarray(result.ages)
    for sensor in result.sensors:
        for matcher in result.matchers:
            for protocol in result.protocols:
                units = result.trajectory(sensor, matcher, protocol)
                y = np.array([u.eer.estimate for u in units])
                reps = np.stack([u.eer.replicates for u in units])  # (ages, replicates), paired by column
                slope = float(_ols_slopes(x, y[:, None])[0])
                rep_slopes = _ols_slopes(x, reps)
                rep_slopes = rep_slopes[np.isfinite(rep_slopes)]
                # Two-sided bootstrap p-value of "no trend": how often the resampled slope falls on the other
                # side of zero (at least one replicate's worth, so never 0).
                below, above = np.mean(rep_slopes <= 0), np.mean(rep_slopes >= 0)
                p = float(min(1.0, max(2 * min(below, above), 1.0 / max(rep_slopes.size, 1))))
                change = float(y[-1] - y[0])
                out.append(Trend(sensor, matcher, protocol, slope, percentile_ci(rep_slopes, result.level), p, change,
                                 percentile_ci(reps[-1] - reps[0], result.level), result.level))
    return out


def spreads(result: ImpactResult) -> list[Spread]:
    """Mean EER across sensors at every age (paired interval), with the standard deviation and range."""
    out = []
    for matcher in result.matchers:
        for protocol in result.protocols:
            for age in result.ages:
                units = [result.unit(s, age, matcher, protocol) for s in result.sensors]
                values = np.array([u.eer.estimate for u in units])
                mean_reps = np.mean(np.stack([u.eer.replicates for u in units]), axis=0)
                out.append(Spread(matcher, protocol, age, float(values.mean()), percentile_ci(mean_reps, result.level),
                                  float(values.std(ddof=1)) if values.size > 1 else 0.0, float(values.min()),
                                  float(values.max()), int(values.size)))
    return out
