"""Were two image sets taken with one device?  The reference paper's protocol (section 4, tables 1–2).

The test, as the paper runs it (Höller & Uhl's sensor-identification methodology):

1. **Selection.**  From each set, disjoint random images: ``fingerprint_images``
   (50) for a PRNU fingerprint and ``score_images`` (800) for scoring.  A small set
   gives at most half of its images to the fingerprint and the rest to scoring, and
   the result carries a warning about the loss of statistical power.
2. **Scores.**  Every scoring image is correlated (NCC of its σ = 2 residual with
   ``I·K``, :func:`forensics.prnu.match.score_pair`) with its *own* set's fingerprint — a
   *matching* score — and with the *other* set's fingerprint — a *non-matching*
   score.  Its residual is computed once and used for both.
3. **EER.**  The equal error rate of matching against non-matching scores, with a
   95 % percentile bootstrap interval (the two bags resampled separately, 1,000
   replicates: :func:`forensics.stats.scores.bootstrap_eer`).
4. **Verdict.**  The paper argues by contradiction: *if* the sets came from two
   devices, each image would match its own set's fingerprint better than the
   other's, and the EER would be low.  An interval containing 50 % means the
   two fingerprints cannot be told apart by the images: consistent with one device.
   An interval below ``different_below`` (10 %) means different devices.  Anything
   in between is reported as what it is: the sets are partly distinguishable —
   one device whose fingerprint changed (ageing, a processing change) or two
   devices with weak fingerprints — which this test alone cannot decide.
5. **Fingerprint ageing (table 2).**  Up to 16 median-residual fingerprints per set,
   each from 50 disjoint random images; intra- and inter-set mean NCC and their
   consistency, with bootstrap intervals over fingerprints
   (:mod:`forensics.prnu.ageing`, which also explains why ageing lowers the
   inter-set NCC).  The figures and tables of a result are drawn by
   :func:`forensics.report.prnu.add_same_device`.

Streaming: images are decoded one at a time (per worker).  An image is decoded once for the
EER part (it is either a fingerprint image or a scoring image) and once more if it
also falls in an ageing group; each kind of residual is computed once per image.
Memory: one frame's work, the two EER fingerprints, and the finished ageing
fingerprints (``n_fingerprints × region pixels × 4`` bytes: 32 MB for 32
fingerprints of the paper's corner patches).

Execution (:mod:`forensics._shared.parallel`): each set's fingerprint is built from
chunks of its images (:func:`forensics.prnu.fingerprint.build_fingerprints`), each
scoring image is one work item, and a set's ageing fingerprints are built together as
(group, chunk) items; workers read the images by index from the set (the items' shared
data).  Every random draw is made here, from ``rng``, before or after the work, so the
result is the same on every backend.
"""
from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from forensics._shared.errors import InputError, UsageError
from forensics._shared.parallel import Executor, resolve
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator
from forensics.prnu.ageing import (
    AGEING_FINGERPRINTS,
    AGEING_IMAGES,
    AGEING_RESIDUALS,
    MIN_AGEING_FINGERPRINTS,
    AgeingTable,
    ageing_table,
    build_ageing_fingerprints,
)
from forensics.prnu.fingerprint import (
    Fingerprint,
    FingerprintBuilder,
    FingerprintJob,
    ImageSet,
    Region,
    build_fingerprints,
    parse_region,
    region_content_problem,
)
from forensics.prnu.match import QUERY_SIGMA, prepare_query, score_pair
from forensics.stats.scores import DetCurve, auc, bootstrap_eer, det_curve, eer, eer_convex_hull

__all__ = [
    "FINGERPRINT_IMAGES",
    "SCORE_IMAGES",
    "DIFFERENT_BELOW",
    "ImageSet",
    "SetPlan",
    "plan_set",
    "expected_eer_ci_width",
    "EerVerdict",
    "eer_verdict",
    "SetSummary",
    "SameDeviceResult",
    "same_device",
]

#: The paper's counts: 50 images per fingerprint, 800 scoring images per set.
FINGERPRINT_IMAGES = 50
SCORE_IMAGES = 800
#: An EER interval entirely below this says "different devices".
DIFFERENT_BELOW = 0.10
#: An EER interval wider than this is flagged as weak evidence.
WIDE_INTERVAL = 0.20


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


# ----------------------------------------------------------------------------- selection


def expected_eer_ci_width(n_genuine: int, n_impostor: int, level: float = 0.95, eer_value: float = 0.5) -> float:
    """Expected width of the bootstrap EER interval (binomial approximation).

    ``width ≈ 2 z √(p(1 − p)(1/n_g + 1/n_i)) / 2`` with ``p`` the EER and ``z`` the
    normal quantile of the level: the EER is about the mean of a FAR and an FRR at
    one threshold, each a binomial proportion.  At ``p = 0.5`` and 95 % this is
    ``0.98 √(1/n_g + 1/n_i)``; against a Monte-Carlo of the bootstrap with
    identical score distributions (n_g = n_i = n from 4 to 1,600, 200 runs each)
    the measured mean width is ``1.39/√n`` to ``1.47/√n``, the formula gives
    ``1.39/√n``.

    Parameters
    ----------
    n_genuine, n_impostor : int
        Numbers of matching and non-matching scores.
    level : float
        Interval coverage.
    eer_value : float
        EER at which to evaluate (0.5: the one-device case, the widest).

    Returns
    -------
    float
        Full width (high − low), as a fraction.
    """
    if n_genuine < 1 or n_impostor < 1:
        return 1.0
    z = float(stats.norm.ppf(0.5 + level / 2))
    p = min(max(eer_value, 0.0), 1.0)
    return float(min(1.0, z * math.sqrt(p * (1 - p) * (1 / n_genuine + 1 / n_impostor))))


@dataclass(frozen=True)
class SetPlan:
    """Which images of one set play which role (indices into the set).

    Attributes
    ----------
    name : str
    n_available : int
    fingerprint : tuple of int
        Images of the set's PRNU fingerprint.
    score : tuple of int
        Scoring images (disjoint from ``fingerprint``).
    ageing_groups : tuple of tuple of int
        Disjoint groups, one ageing fingerprint each (drawn independently of the
        EER roles, so they may share images with them).
    warnings : tuple of str
        What was reduced and what it costs.
    """

    name: str
    n_available: int
    fingerprint: tuple[int, ...]
    score: tuple[int, ...]
    ageing_groups: tuple[tuple[int, ...], ...] = ()
    warnings: tuple[str, ...] = ()

    @property
    def ageing_images(self) -> int:
        """Images per ageing fingerprint (0 without ageing)."""
        return len(self.ageing_groups[0]) if self.ageing_groups else 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (indices included)."""
        return {
            "name": self.name,
            "n_available": self.n_available,
            "n_fingerprint": len(self.fingerprint),
            "n_score": len(self.score),
            "n_ageing_fingerprints": len(self.ageing_groups),
            "ageing_images_per_fingerprint": self.ageing_images,
            "fingerprint_indices": list(self.fingerprint),
            "score_indices": list(self.score),
            "ageing_groups": [list(g) for g in self.ageing_groups],
            "warnings": list(self.warnings),
        }


def plan_set(
    n_available: int,
    rng: RngLike,
    *,
    name: str = "set",
    fingerprint_images: int = FINGERPRINT_IMAGES,
    score_images: int = SCORE_IMAGES,
    ageing_fingerprints: int = AGEING_FINGERPRINTS,
    ageing_images: int = AGEING_IMAGES,
) -> SetPlan:
    """Draw the images of one set for the fingerprint, for scoring and for the ageing groups.

    Rules: the fingerprint takes ``min(fingerprint_images, n // 2)`` random images
    (at most half the set, so a small set keeps images to score); scoring takes
    ``min(score_images, rest)`` others.  Ageing: ``min(ageing_fingerprints,
    n // ageing_images)`` groups of ``ageing_images``; if that gives fewer than
    ``min(4, ageing_fingerprints)`` groups, the groups shrink to ``n // 4`` images so
    that there are at least four (bootstrap over fewer fingerprints is meaningless).
    Every reduction adds a warning.

    Parameters
    ----------
    n_available : int
        Number of images in the set.
    rng : numpy.random.Generator or int
        Source of the random draws.
    name : str
        For the warnings.
    fingerprint_images, score_images, ageing_fingerprints, ageing_images : int
        Requested counts (``ageing_fingerprints = 0`` disables the ageing groups).

    Raises
    ------
    InputError
        If the set has fewer than 2 images.
    UsageError
        If a requested count is not positive.
    """
    rng = as_generator(rng)
    for label, value in (("fingerprint_images", fingerprint_images), ("score_images", score_images),
                         ("ageing_images", ageing_images)):
        if int(value) != value or value < 1:
            raise UsageError(f"{label}={value!r}: give a positive whole number")
    if int(ageing_fingerprints) != ageing_fingerprints or ageing_fingerprints < 0:
        raise UsageError(f"ageing_fingerprints={ageing_fingerprints!r}: give a whole number ≥ 0 (0 disables the table)")
    n = int(n_available)
    if n < 2:
        raise InputError(f"{name}: {n} image(s); the protocol needs at least 2 per set (one for the fingerprint, "
                         "one to score) and hundreds for a useful interval")
    warnings: list[str] = []
    n_fp = min(int(fingerprint_images), n // 2)
    n_score = min(int(score_images), n - n_fp)
    order = rng.permutation(n)
    fp = tuple(int(i) for i in np.sort(order[:n_fp]))
    score = tuple(int(i) for i in np.sort(order[n_fp:n_fp + n_score]))
    if n_fp < fingerprint_images or n_score < score_images:
        text = f"{name}: {n} images, so the fingerprint uses {n_fp}"
        text += f" (not {fingerprint_images})" if n_fp < fingerprint_images else ""
        text += f" and {n_score} are scored" + (f" (not {score_images})" if n_score < score_images else "")
        if n_fp < fingerprint_images:
            text += ("; a fingerprint from fewer images is noisier, which lowers the matching scores and pushes "
                     "the EER towards 50 % even for two different devices")
        warnings.append(text)
    groups: tuple[tuple[int, ...], ...] = ()
    if ageing_fingerprints > 0:
        size = int(ageing_images)
        count = min(int(ageing_fingerprints), n // size)
        wanted = min(MIN_AGEING_FINGERPRINTS, int(ageing_fingerprints))
        if count < wanted:
            size = max(1, n // wanted)
            count = min(int(ageing_fingerprints), n // size)
        perm = rng.permutation(n)[: count * size].reshape(count, size)
        groups = tuple(tuple(int(i) for i in np.sort(row)) for row in perm)
        if count < ageing_fingerprints or size < ageing_images:
            warnings.append(
                f"{name}: the ageing table uses {count} fingerprints of {size} images (asked for "
                f"{ageing_fingerprints} of {ageing_images}); fewer or smaller fingerprints give wider intervals"
            )
    return SetPlan(name, n, fp, score, groups, tuple(warnings))


# ----------------------------------------------------------------------------- EER and verdict


@dataclass(frozen=True)
class EerVerdict:
    """EER of matching against non-matching scores, its interval, and what it means.

    Attributes
    ----------
    eer : float
        Interpolated EER (:func:`forensics.stats.scores.eer`), a fraction.
    ci : (float, float)
        Bootstrap percentile interval.
    level : float
        Coverage of ``ci``.
    n_boot : int
        Bootstrap replicates.
    threshold : float
        NCC threshold at the EER.
    eer_convex_hull : float
        ROC-convex-hull EER (≤ ``eer``).
    auc : float
        P(matching > non-matching).
    n_genuine, n_impostor : int
        Numbers of matching and non-matching scores.
    expected_width : float
        Width the interval would be expected to have at EER = 50 % with these
        counts (:func:`expected_eer_ci_width`): the resolution of the test.
    decision : str
        ``'indistinguishable'`` (interval contains 50 %), ``'different'`` (interval
        below ``different_below``), ``'partly_distinguishable'`` (in between) or
        ``'anomalous'`` (interval above 50 %: images match the other set's
        fingerprint better than their own).
    verdict : str
        The decision in words.
    """

    eer: float
    ci: tuple[float, float]
    level: float
    n_boot: int
    threshold: float
    eer_convex_hull: float
    auc: float
    n_genuine: int
    n_impostor: int
    expected_width: float
    decision: str
    verdict: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "eer": self.eer,
            "eer_ci": [self.ci[0], self.ci[1]],
            "level": self.level,
            "n_boot": self.n_boot,
            "threshold": self.threshold if math.isfinite(self.threshold) else None,
            "eer_convex_hull": self.eer_convex_hull,
            "auc": self.auc,
            "n_genuine": self.n_genuine,
            "n_impostor": self.n_impostor,
            "expected_width_at_50": self.expected_width,
            "decision": self.decision,
            "verdict": self.verdict,
        }


def eer_verdict(
    genuine: Any,
    impostor: Any,
    rng: RngLike,
    *,
    n_boot: int = 1000,
    level: float = 0.95,
    different_below: float = DIFFERENT_BELOW,
) -> EerVerdict:
    """EER with its bootstrap interval, and the paper's reading of it.

    Parameters
    ----------
    genuine, impostor : array_like
        Matching (own fingerprint) and non-matching (other set's fingerprint) scores.
    rng : numpy.random.Generator or int
        For the bootstrap.
    n_boot, level : int, float
        Bootstrap replicates and interval coverage.
    different_below : float
        An interval entirely below this EER means different devices.

    Returns
    -------
    EerVerdict
    """
    rng = as_generator(rng)
    g = np.asarray(genuine, np.float64).ravel()
    i = np.asarray(impostor, np.float64).ravel()
    boot = bootstrap_eer(g, i, rng, n_boot=n_boot, level=level)
    point = eer(g, i)
    lo, hi = boot.ci
    width = expected_eer_ci_width(g.size, i.size, level)
    interval = f"EER {_pct(point.eer)} (95 % interval {_pct(lo)} – {_pct(hi)})" if level == 0.95 else \
        f"EER {_pct(point.eer)} ({100 * level:g} % interval {_pct(lo)} – {_pct(hi)})"
    if lo <= 0.5 <= hi:
        decision = "indistinguishable"
        verdict = (f"{interval}: the interval contains 50 %, so the images do not match their own set's "
                   "fingerprint better than the other set's; the two sets cannot be told apart, which is "
                   "consistent with one device.")
        if hi - lo > WIDE_INTERVAL:
            verdict += (f" The interval is wide ({g.size} matching and {i.size} non-matching scores): weak "
                        "evidence; a partly changed fingerprint would not be ruled out.")
    elif hi < different_below:
        decision = "different"
        verdict = (f"{interval}: the images match their own set's fingerprint far better than the other's; "
                   "the sets come from different devices.")
    elif hi < 0.5:
        decision = "partly_distinguishable"
        verdict = (f"{interval}: the interval excludes 50 % but the EER is not low. The sets are partly "
                   "distinguishable: one device whose fingerprint changed between them (ageing defects, a "
                   "processing change) or two devices whose fingerprints are weak at this sample size (few, "
                   "dark or textured images, a small region). This test alone cannot decide; more or flatter "
                   "images, or a larger region, would.")
    else:
        decision = "anomalous"
        verdict = (f"{interval}: above 50 % — images match the other set's fingerprint better than their own. "
                   "No device explanation gives this; look for shared scene content or mislabelled sets.")
    return EerVerdict(
        eer=float(point.eer), ci=(float(lo), float(hi)), level=float(level), n_boot=int(n_boot),
        threshold=float(point.threshold), eer_convex_hull=float(eer_convex_hull(g, i).eer), auc=float(auc(g, i)),
        n_genuine=int(g.size), n_impostor=int(i.size), expected_width=width, decision=decision, verdict=verdict,
    )


# ----------------------------------------------------------------------------- the protocol


@dataclass(frozen=True)
class SetSummary:
    """What one set contributed: counts, files, and its scores.

    ``excluded`` lists the content-free images (:mod:`forensics.io.content`) left out of its fingerprint and
    of its scores, ``(file, why)``; ``own`` and ``other`` hold the scores of the others only.
    """

    plan: SetPlan
    fingerprint_files: list[str]
    own: np.ndarray
    other: np.ndarray
    eer: float
    excluded: tuple[tuple[str, str], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        out = self.plan.to_dict()
        out.update({
            "fingerprint_files": list(self.fingerprint_files),
            "own_fingerprint_scores": self.own.tolist(),
            "other_fingerprint_scores": self.other.tolist(),
            "eer_own_vs_other": self.eer,
            "excluded": [{"file": f, "reason": why} for f, why in self.excluded],
        })
        return out


@dataclass
class SameDeviceResult:
    """Outcome of :func:`same_device`.

    Attributes
    ----------
    set_a, set_b : SetSummary
        Per set: the plan, the files of its fingerprint, its images' NCC with
        their own (matching) and the other set's (non-matching) fingerprint, and
        the EER of those two alone.
    eer : EerVerdict
        Pooled over both sets (the paper's table 1).
    ageing : AgeingTable or None
        The paper's table 2 (None when disabled or a set is too small).
    region : str
    parameters : dict
    warnings : list of str
    """

    set_a: SetSummary
    set_b: SetSummary
    eer: EerVerdict
    ageing: AgeingTable | None
    region: str
    parameters: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def genuine(self) -> np.ndarray:
        """Matching scores: each set's scoring images against their own set's fingerprint."""
        return np.concatenate([self.set_a.own, self.set_b.own])

    @property
    def impostor(self) -> np.ndarray:
        """Non-matching scores: each set's scoring images against the other set's fingerprint."""
        return np.concatenate([self.set_a.other, self.set_b.other])

    @property
    def verdict(self) -> str:
        """The verdict in words."""
        return self.eer.verdict

    @property
    def median_scores(self) -> tuple[float, float]:
        """Median matching and median non-matching NCC."""
        return float(np.median(self.genuine)), float(np.median(self.impostor))

    def det_curve(self) -> DetCurve:
        """DET curve of the matching against the non-matching scores."""
        return det_curve(self.genuine, self.impostor)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form: ``eer``, ``eer_ci``, ``verdict`` at the top, details below."""
        return {
            "eer": self.eer.eer,
            "eer_ci": [self.eer.ci[0], self.eer.ci[1]],
            "verdict": self.eer.verdict,
            "decision": self.eer.decision,
            "statistics": self.eer.to_dict(),
            "region": self.region,
            "sets": {"a": self.set_a.to_dict(), "b": self.set_b.to_dict()},
            "ageing": self.ageing.to_dict() if self.ageing is not None else None,
            "warnings": list(self.warnings),
            "parameters": dict(self.parameters),
        }


def _default_name(source: Any, fallback: str) -> str | None:
    """None (keep the set's own name) for folders, Datasets and ImageSets; ``fallback`` for bare sequences."""
    from forensics.io.dataset import Dataset

    return None if isinstance(source, (str, os.PathLike, Dataset, ImageSet)) else fallback


def _build_fingerprint(images: ImageSet, indices: Sequence[int], region: Region, sigma: float, executor: Executor,
                       progress: Progress, desc: str, options: dict[str, Any]) -> Fingerprint:
    job = FingerprintJob(FingerprintBuilder(region, sigma, **options), images, tuple(indices))
    return build_fingerprints([job], executor=executor, progress=progress, desc=desc)[0]


def same_device(
    set_a: Any,
    set_b: Any,
    rng: RngLike,
    *,
    fingerprint_images: int = FINGERPRINT_IMAGES,
    score_images: int = SCORE_IMAGES,
    region: str | Region = "corners",
    fingerprint_sigma: float = 3.0,
    query_sigma: float = QUERY_SIGMA,
    n_boot: int = 1000,
    level: float = 0.95,
    different_below: float = DIFFERENT_BELOW,
    ageing: bool = True,
    ageing_fingerprints: int = AGEING_FINGERPRINTS,
    ageing_images: int = AGEING_IMAGES,
    ageing_residual: str = "median",
    median_size: int = 3,
    names: tuple[str, str] | None = None,
    progress: Progress = no_progress,
    executor: Executor | None = None,
    dark: Any = None,
    **options: Any,
) -> SameDeviceResult:
    """The paper's same-device test on two image sets, with the fingerprint-ageing table.

    Parameters
    ----------
    set_a, set_b
        Anything :meth:`ImageSet.of` accepts: dataset folders, Datasets, sequences of
        arrays/paths/frames/callables, or ImageSets.  All images of both sets must
        have one frame size (rotate portrait frames first).
    rng : numpy.random.Generator or int
        Every random draw (image selection, bootstraps).
    fingerprint_images, score_images : int
        Per set (50 and 800 in the paper); reduced for small sets, with a warning.
    region : str or Region
        'corners' (the paper's four 128×128 patches), 'center:N' or 'full'.
    fingerprint_sigma, query_sigma : float
        Wavelet residual noise levels (8-bit scale) of fingerprint and scoring images.
    n_boot, level : int, float
        Bootstrap replicates and interval coverage (EER and ageing table).
    different_below : float
        EER interval below this → "different devices".
    ageing : bool
        Compute the ageing table.
    ageing_fingerprints, ageing_images : int
        Fingerprints per set and images per fingerprint for the table (16 and 50).
    ageing_residual : {'median', 'wavelet'}
        Residual of the ageing fingerprints (the paper: median).
    median_size : int
        Median window of the median residual (3).
    names : (str, str), optional
        Set names (default: the folders, or 'A' and 'B').
    progress : callable
        ``progress(iterable, total=None, desc=None)``: one bar per stage and set, counting work items.
    executor : Executor, optional
        Where the fingerprints are built (chunks of images) and the images scored (one item per
        image); default in this process.  On worker processes or a cluster the sets' loaders must
        be picklable (dataset folders and frames are).  The result does not depend on it: the
        random draws (selection, bootstraps) are made here, from ``rng`` only.
    dark : DarkCalibration or (DarkCalibration or None, DarkCalibration or None), optional
        Calibrate the raw CCD frames of both sets (one calibration), or of each set with its own (a pair), as
        ``frame − offset − rate·exposure`` before their residuals (:mod:`forensics.prnu.calibration`); a set
        calibrated must be a dataset (folder or Dataset).  A camera's darks belong to its own frames: give a pair
        when the sets may come from two cameras with darks of each.
    **options
        white_level, black_level, saturation_level, saturation_dilate, rolloff,
        workers — as :class:`forensics.prnu.fingerprint.FingerprintBuilder`.

    Returns
    -------
    SameDeviceResult

    Raises
    ------
    InputError
        A set has fewer than 2 images, frames differ in size, or a set's fingerprint images or scoring images
        are all content-free (constant, black or saturated: :mod:`forensics.io.content`; some such images
        are left out, with a warning).
    UsageError
        Bad counts or options, or both sets are the same images (sets sharing some images get a warning).
    """
    rng = as_generator(rng)
    _check_options(ageing_residual, options)
    ex = resolve(executor)
    region = parse_region(region)
    set_a, set_b, options = _calibrated(set_a, set_b, dark, names, options)
    images_a, images_b = _open_sets(set_a, set_b, names)
    overlap = _shared_images(images_a, images_b)
    plans = [plan_set(len(s), rng, name=s.name, fingerprint_images=fingerprint_images, score_images=score_images,
                      ageing_fingerprints=ageing_fingerprints if ageing else 0, ageing_images=ageing_images)
             for s in (images_a, images_b)]
    warnings = [w for p in plans for w in p.warnings] + ([overlap] if overlap else [])

    # 1. the two fingerprints
    fps = [_build_fingerprint(s, p.fingerprint, region, fingerprint_sigma, ex, progress, f"fingerprint {s.name}",
                              options)
           for s, p in zip((images_a, images_b), plans)]
    shape_a, shape_b = fps[0].frame_shape, fps[1].frame_shape
    if shape_a != shape_b:
        raise InputError(f"{images_a.name} has {shape_a[0]}×{shape_a[1]} frames, {images_b.name} "
                         f"{shape_b[0]}×{shape_b[1]}; both sets must come at one frame size and orientation")
    # 2. scores: each scoring image's residual once, against both fingerprints
    scored = [_score_set(s, p.score, fps[k], fps[1 - k], region, query_sigma, ex, progress, options)
              for k, (s, p) in enumerate(zip((images_a, images_b), plans))]
    excluded = [tuple((d["file"], d["reason"]) for d in fp.parameters.get("excluded_frames", [])) + left_out
                for fp, (_, _, left_out) in zip(fps, scored)]
    warnings += [f"{s.name}: {len(x)} content-free image(s) left out of its fingerprint and scores (first, {x[0][0]}: "
                 f"{x[0][1]})" for s, x in zip((images_a, images_b), excluded) if x]
    (a_own, a_other, _), (b_own, b_other, _) = scored
    verdict = eer_verdict(np.concatenate([a_own, b_own]), np.concatenate([a_other, b_other]), rng,
                          n_boot=n_boot, level=level, different_below=different_below)
    if len(plans[0].score) < score_images or len(plans[1].score) < score_images or any(excluded):
        warnings.append(_power_warning(verdict, score_images, level))
    summaries = [
        SetSummary(p, list(fp.files), own, other, float(eer(own, other).eer), x)
        for p, fp, (own, other, _), x in zip(plans, fps, scored, excluded)
    ]
    del fps

    # 3. ageing table
    table = None
    if ageing and plans[0].ageing_groups and plans[1].ageing_groups:
        groups = [build_ageing_fingerprints(s, p.ageing_groups, region, ageing_residual, fingerprint_sigma,
                                            median_size, progress, f"ageing {s.name}", options, executor=ex)
                  for s, p in zip((images_a, images_b), plans)]
        table = ageing_table(groups[0], groups[1], rng, names=(images_a.name, images_b.name),
                             residual=ageing_residual,
                             images_per_fingerprint=(plans[0].ageing_images, plans[1].ageing_images),
                             n_boot=n_boot, level=level)
        if table.consistency.ci is None and min(table.n_fingerprints) < 3:
            warnings.append("ageing table: fewer than 3 fingerprints in a set, so no intervals")
    parameters = {
        "fingerprint_images": fingerprint_images, "score_images": score_images, "region": region.spec,
        "fingerprint_sigma": fingerprint_sigma, "query_sigma": query_sigma, "metric": "ncc",
        "n_boot": n_boot, "level": level, "different_below": different_below,
        "ageing": ageing, "ageing_fingerprints": ageing_fingerprints, "ageing_images": ageing_images,
        "ageing_residual": ageing_residual, "median_size": median_size,
        "frame_shape": list(shape_a),
        **{k: v for k, v in options.items() if k != "workers"},
        "dark_calibration": _dark_dicts(dark),
    }
    return SameDeviceResult(summaries[0], summaries[1], verdict, table, region.spec, parameters, warnings)


_OPTIONS = {"white_level", "black_level", "saturation_level", "saturation_dilate", "rolloff", "workers"}


def _check_options(ageing_residual: str, options: dict[str, Any]) -> None:
    if ageing_residual not in AGEING_RESIDUALS:
        raise UsageError(f"ageing_residual={ageing_residual!r}: choose one of {', '.join(AGEING_RESIDUALS)}")
    unknown = set(options) - _OPTIONS
    if unknown:
        raise UsageError(f"unknown option(s) {', '.join(sorted(unknown))}; allowed: {', '.join(sorted(_OPTIONS))}")


def _calibrated(set_a: Any, set_b: Any, dark: Any, names: tuple[str, str] | None, options: dict[str, Any]
                ) -> tuple[Any, Any, dict[str, Any]]:
    """The sets loaded dark-calibrated where a calibration is given (see :func:`same_device`), and the options with the
    raw frames' full scale as the white level."""
    if dark is None:
        return set_a, set_b, options
    pair = tuple(dark) if isinstance(dark, (tuple, list)) else (dark, dark)
    if len(pair) != 2:
        raise UsageError("dark: give one calibration for both sets or a pair (set A's, set B's)")
    label = names if names is not None else (None, None)
    sets = [s if cal is None else cal.calibrated_set(s, n) for s, cal, n in zip((set_a, set_b), pair, label)]
    levels = {cal.white_level for cal in pair if cal is not None}
    if len(levels) > 1:
        raise InputError("the two dark sets have different full scales; the frames of both sets must have one type")
    return sets[0], sets[1], ({"white_level": levels.pop(), **options} if levels else options)


def _dark_dicts(dark: Any) -> Any:
    if dark is None:
        return None
    pair = tuple(dark) if isinstance(dark, (tuple, list)) else (dark, dark)
    return [None if cal is None else cal.to_dict() for cal in pair]


def _open_sets(set_a: Any, set_b: Any, names: tuple[str, str] | None) -> tuple[ImageSet, ImageSet]:
    """The two sets as ImageSets with distinct names."""
    name_a, name_b = names if names is not None else (None, None)
    images_a = ImageSet.of(set_a, name_a or _default_name(set_a, "A"))
    images_b = ImageSet.of(set_b, name_b or _default_name(set_b, "B"))
    if images_a.name == images_b.name:
        images_a = ImageSet.of(images_a, f"{images_a.name} (A)")
        images_b = ImageSet.of(images_b, f"{images_b.name} (B)")
    return images_a, images_b


@dataclass(frozen=True)
class _Scoring:
    """What every scoring item of one set needs (the items' shared data): the set and the two fingerprints."""

    images: ImageSet
    own: Fingerprint
    other: Fingerprint
    region: Region
    sigma: float
    options: dict[str, Any]


def _score_image(task: _Scoring, index: int) -> tuple[float, float, str | None]:
    """Work item: NCC of scoring image ``index`` with its own set's and the other set's fingerprint (one residual);
    a content-free image is not scored (NaN, NaN and why)."""
    images = task.images
    shape = tuple(task.own.frame_shape)
    image = images.load(index)
    if tuple(image.shape[:2]) != shape:
        raise InputError(f"{images.sources[index]}: frame is {image.shape[0]}×{image.shape[1]}, the others are "
                         f"{shape[0]}×{shape[1]}")
    problem = region_content_problem(image, task.region, **task.options)
    if problem is not None:
        return math.nan, math.nan, problem
    query = prepare_query(image, task.region, sigma=task.sigma, source=images.sources[index], **task.options)
    del image
    return score_pair(task.own, query, "ncc").value, score_pair(task.other, query, "ncc").value, None


def _score_set(images: ImageSet, indices: Sequence[int], own_fp: Fingerprint, other_fp: Fingerprint, region: Region,
               query_sigma: float, executor: Executor, progress: Progress,
               options: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, tuple[tuple[str, str], ...]]:
    """NCC of each scoring image with its own set's and the other set's fingerprint, in index order, and the
    content-free images left out ``(file, why)``.

    Raises
    ------
    InputError
        Every scoring image of the set is content-free.
    """
    task = _Scoring(images, own_fp, other_fp, region, query_sigma, dict(options))
    results = list(executor.map(_score_image, list(indices), shared=task, progress=progress,
                                desc=f"scoring {images.name}"))
    left_out = tuple((images.sources[i], why) for i, (_, _, why) in zip(indices, results) if why is not None)
    if results and len(left_out) == len(results):
        raise InputError(f"{images.name}: every one of its {len(results)} scoring image(s) is content-free (first, "
                         f"{left_out[0][0]}: {left_out[0][1]}); give exposed images")
    kept = [(a, b) for a, b, why in results if why is None]
    scores = np.array(kept, dtype=np.float64).reshape(len(kept), 2)
    return scores[:, 0].copy(), scores[:, 1].copy(), left_out


def _shared_images(a: ImageSet, b: ImageSet) -> str | None:
    """The protocol compares two sets: refuse one set given twice; a warning when they share some image files.

    Raises
    ------
    UsageError
        Both sets are the same files (by their resolved paths).
    """
    files_a = {os.path.realpath(src) for src in a.sources if os.path.isfile(src)}
    shared = [src for src in b.sources if os.path.isfile(src) and os.path.realpath(src) in files_a]
    if not shared:
        return None
    if len(shared) == len(b) == len(a) == len(files_a):
        raise UsageError(f"{a.name} and {b.name} are the same {len(a)} images: the same-device test compares two "
                         "different sets; give two sets")
    return (f"{len(shared)} image(s) are in both {a.name} and {b.name} (first: {shared[0]}): a shared image is "
            "scored against a fingerprint it may have helped build, which pushes the EER towards 50 %")


def _power_warning(verdict: EerVerdict, score_images: int, level: float) -> str:
    full = expected_eer_ci_width(2 * score_images, 2 * score_images, level)
    return (f"statistical power: {verdict.n_genuine} matching and {verdict.n_impostor} non-matching scores; when the "
            f"sets cannot be told apart the {100 * level:g} % EER interval is expected to be about "
            f"{100 * verdict.expected_width:.0f} points wide (±{50 * verdict.expected_width:.0f} around 50 %), "
            f"against {100 * full:.1f} points with {score_images} scoring images per set")
