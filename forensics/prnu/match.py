"""Matching noise residuals against camera fingerprints: NCC and PCE.

The detector of the reference design asks whether a query image ``I`` carries the
fingerprint ``K``: its residual ``W`` (σ = 2, with zero-mean and DFT Wiener steps)
is correlated with the expected signal ``I·K``.

**NCC** (:func:`ncc`) is the normalised correlation of the two arrays at zero shift.

**PCE** (:func:`pce`, peak-to-correlation energy) is the squared correlation peak
over the mean squared circular cross-correlation outside an ``exclusion × exclusion``
window (11×11) around the peak.  Under the null hypothesis (other camera) the
normalised peak ``peak/√energy`` is about standard normal, so ``PCE ≈ χ²₁`` and
``PCE ≥ 60`` is the customary decision threshold.  The value is *signed*
(``sign(peak)·peak²/energy``): an anti-correlation is no match.

The peak is looked for **at zero shift only** by default.  Searching every circular
shift (what the public NumPy port does) takes the maximum of ``H·W`` null values and
lifts impostor PCE to 20–40; pass ``shift_range`` only when the query may be a
shifted crop of the frame.  The false-alarm probability reported accounts for the
number of shifts searched: ``p_FA = 1 − (1 − Q(peak/√energy))^n_shifts``.

Shift convention: ``shift = (dy, dx)`` means ``residual ≈ np.roll(reference, (dy, dx),
axis=(0, 1))``; shifts are reported in ``(−H/2, H/2] × (−W/2, W/2]``.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from forensics._shared.errors import InputError, UsageError
from forensics._shared.parallel import Executor, resolve
from forensics.prnu.correlation import _centred, _false_alarm, _shift_indices, _Spectrum, _sum_sq, surface
from forensics.prnu.fingerprint import (
    Fingerprint,
    Region,
    check_fingerprint,
    parse_region,
    region_content_problem,
    region_residual_and_intensity,
)
from forensics._shared.progress import Progress, no_progress
from forensics.prnu.residual import default_workers

__all__ = [
    "QUERY_SIGMA",
    "PCE_THRESHOLD",
    "PceResult",
    "MatchScore",
    "Query",
    "ncc",
    "pce",
    "prepare_query",
    "orientations",
    "score_pair",
    "score_query",
    "score_matrix",
    "SetMatch",
    "match_set",
]

#: Residual noise level of queries in the reference design (8-bit scale).
QUERY_SIGMA = 2.0
#: Customary PCE decision threshold.
PCE_THRESHOLD = 60.0
METRICS = ("pce", "ncc")


@dataclass(frozen=True)
class PceResult:
    """Outcome of a PCE test.

    Attributes
    ----------
    pce : float
        Signed peak-to-correlation energy ``sign(peak)·peak²/energy``.
    shift : (int, int)
        Position of the peak, ``(dy, dx)`` (``(0, 0)`` without a search).
    sign : int
        Sign of the peak (+1, −1, or 0 for a degenerate input).
    ncc : float
        Normalised correlation at the peak (``peak / (‖a‖·‖b‖)``).
    p_fa : float
        Probability that an unrelated pair gives a peak at least this high over the
        searched shifts (Gaussian tail of ``peak/√energy``, times the search).
    log10_p_fa : float
        ``log10(p_fa)``, finite even where ``p_fa`` underflows to 0 (for ranking).
    n_shifts : int
        Number of shifts searched.
    """

    pce: float
    shift: tuple[int, int]
    sign: int
    ncc: float
    p_fa: float
    log10_p_fa: float
    n_shifts: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "pce": self.pce,
            "shift": list(self.shift),
            "sign": self.sign,
            "ncc": self.ncc,
            "p_fa": self.p_fa,
            "log10_p_fa": self.log10_p_fa,
            "n_shifts": self.n_shifts,
        }


@dataclass(frozen=True)
class MatchScore:
    """Score of one query against one fingerprint.

    ``value`` is the PCE (signed) or the NCC, per ``metric``; ``rotation`` the number
    of 90° counter-clockwise turns (``np.rot90``) applied to the query image.  A content-free
    query (constant, black or saturated over the fingerprint's region, :mod:`forensics.io.content`)
    is not scored: ``value`` and ``ncc`` are NaN and ``excluded`` says why.
    """

    metric: str
    value: float
    rotation: int
    ncc: float
    pce: PceResult | None = None
    excluded: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "metric": self.metric,
            "value": self.value,
            "rotation": self.rotation,
            "ncc": self.ncc,
            "pce": self.pce.to_dict() if self.pce is not None else None,
            "excluded": self.excluded,
        }


@dataclass(frozen=True)
class Query:
    """A query prepared for matching: residual ``W`` and intensity ``I`` over a region.

    ``rotation`` records the ``np.rot90`` turns applied to the image before extraction.
    """

    residual: np.ndarray
    intensity: np.ndarray
    region: str
    rotation: int = 0
    source: str | None = None


# ----------------------------------------------------------------------------- correlation measures


def _check_pair(a: np.ndarray, b: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a)
    b = np.asarray(b)
    if a.ndim != 2 or a.shape != b.shape:
        raise InputError(f"{what}: need two 2-D arrays of the same shape, got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InputError(f"{what}: arrays contain NaN or infinite values")
    return a, b


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation at zero shift, in [−1, 1] (0 if either array is constant).

    ``Σ(a − ā)(b − b̄) / √(Σ(a − ā)² Σ(b − b̄)²)``; products in float32, sums
    accumulated in float64.  Symmetric in ``a`` and ``b``.
    """
    a, b = _check_pair(a, b, "ncc")
    a0 = _centred(a)
    b0 = _centred(b)
    den = math.sqrt(_sum_sq(a0) * _sum_sq(b0))
    if den == 0.0:
        return 0.0
    num = float(np.multiply(a0, b0).sum(dtype=np.float64))
    return float(np.clip(num / den, -1.0, 1.0))


def _parse_shift_range(shift_range: int | tuple[int, int] | None) -> tuple[int | None, int | None]:
    if shift_range is None:
        return None, None
    if np.ndim(shift_range) == 0:
        r = int(shift_range)  # type: ignore[arg-type]
        ry = rx = r
    else:
        ry, rx = (int(v) for v in shift_range)  # type: ignore[union-attr]
    if ry < 0 or rx < 0:
        raise UsageError(f"shift_range={shift_range}: must be non-negative (0 = zero shift only)")
    return ry, rx


def _pce_with(sa: _Spectrum, reference: np.ndarray, shift_range: Any, exclusion: int) -> tuple[PceResult, float]:
    """PCE of the spectrum's array against ``reference``, and the NCC at zero shift."""
    h, w = sa.shape
    if exclusion < 1 or exclusion % 2 == 0:
        raise UsageError(f"exclusion={exclusion}: the window around the peak must be a positive odd size")
    if h < 2 * exclusion or w < 2 * exclusion:
        raise InputError(f"arrays of shape {sa.shape} are too small for PCE with a {exclusion}×{exclusion} exclusion window")
    ry, rx = _parse_shift_range(shift_range)
    corr, norm_b = surface(sa, reference)
    rows = _shift_indices(ry, h)
    cols = _shift_indices(rx, w)
    n_shifts = rows.size * cols.size
    if n_shifts == 1:
        py, px = 0, 0
    else:
        sub = corr[np.ix_(rows, cols)]
        iy, ix = np.unravel_index(int(np.argmax(sub)), sub.shape)
        py, px = int(rows[iy]), int(cols[ix])
    peak = float(corr[py, px])
    half = exclusion // 2
    wr = np.unique((py + np.arange(-half, half + 1)) % h)
    wc = np.unique((px + np.arange(-half, half + 1)) % w)
    energy_all = float(np.square(corr, dtype=np.float32).sum(dtype=np.float64))
    energy_win = float(np.square(corr[np.ix_(wr, wc)].astype(np.float64)).sum())
    n_out = h * w - wr.size * wc.size
    energy = max(energy_all - energy_win, 0.0) / n_out
    dy = py - h if py > h // 2 else py
    dx = px - w if px > w // 2 else px
    if energy <= 0.0 or sa.norm == 0.0 or norm_b == 0.0:
        return PceResult(0.0, (dy, dx), 0, 0.0, 1.0, 0.0, n_shifts), 0.0
    ncc0 = float(np.clip(corr[0, 0] / (sa.norm * norm_b), -1.0, 1.0))
    sign = 1 if peak > 0 else (-1 if peak < 0 else 0)
    value = sign * peak * peak / energy
    z = peak / math.sqrt(energy)
    p_fa, log10_p_fa = _false_alarm(z, n_shifts)
    result = PceResult(
        pce=float(value),
        shift=(int(dy), int(dx)),
        sign=sign,
        ncc=float(np.clip(peak / (sa.norm * norm_b), -1.0, 1.0)),
        p_fa=p_fa,
        log10_p_fa=log10_p_fa,
        n_shifts=int(n_shifts),
    )
    return result, ncc0


def pce(
    residual: np.ndarray,
    reference: np.ndarray,
    shift_range: int | tuple[int, int] | None = 0,
    exclusion: int = 11,
    workers: int | None = None,
) -> PceResult:
    """Peak-to-correlation energy of the circular cross-correlation of two arrays.

    Parameters
    ----------
    residual, reference : ndarray, (H, W)
        E.g. a query's residual ``W`` and ``I·K``; both are made zero-mean.
    shift_range : int, (int, int) or None
        Largest |dy|, |dx| searched for the peak: 0 (default) = zero shift only;
        None = every circular shift (the public port's behaviour: inflates
        impostor PCE; for comparison or for crops at unknown positions).
    exclusion : int
        Odd size of the square around the peak left out of the energy (11).
    workers : int, optional
        FFT threads (default :func:`forensics.prnu.residual.default_workers`).

    Returns
    -------
    PceResult
    """
    residual, reference = _check_pair(residual, reference, "pce")
    sa = _Spectrum(residual, default_workers() if workers is None else workers)
    return _pce_with(sa, reference, shift_range, exclusion)[0]


# ----------------------------------------------------------------------------- queries


def orientations(image_shape: Sequence[int], frame_shape: Sequence[int]) -> tuple[int, ...]:
    """The ``np.rot90`` turns to try so that an image lies like the sensor's frame.

    ``(0,)`` if the image already has the frame's (H, W); ``(1, 3)`` (both quarter
    turns, the better one is kept) if it has (W, H), as portrait pictures written
    rotated do.

    Raises
    ------
    InputError
        If the image has neither shape.
    """
    ih, iw = int(image_shape[0]), int(image_shape[1])
    fh, fw = int(frame_shape[0]), int(frame_shape[1])
    if (ih, iw) == (fh, fw):
        return (0,)
    if (ih, iw) == (fw, fh):
        return (1, 3)
    raise InputError(
        f"image is {ih}×{iw} but the fingerprint's frames are {fh}×{fw}; "
        "PRNU matching needs the full, unscaled frame (crops and resized images need a shift/scale search)"
    )


def prepare_query(
    image: np.ndarray,
    region: str | Region = "full",
    *,
    sigma: float = QUERY_SIGMA,
    rotation: int = 0,
    source: str | None = None,
    white_level: float | None = None,
    black_level: float | Sequence[float] = 0.0,
    saturation_level: float | None = None,
    saturation_dilate: int = 1,
    rolloff: bool = True,
    workers: int | None = None,
    cfa: bool = False,
) -> Query:
    """Residual (σ = 2, zero-mean, DFT Wiener) and intensity of a query image over a region.

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        Not modified.
    region : str or Region
        Must be the fingerprint's region.
    sigma : float
        Residual noise level, 8-bit scale.
    rotation : int
        ``np.rot90`` turns applied to the image first.
    source : str, optional
        Name kept in the result.
    white_level, black_level, saturation_level, saturation_dilate, rolloff, workers, cfa
        As :class:`forensics.prnu.fingerprint.FingerprintBuilder`.
    """
    region = parse_region(region)
    image = np.asarray(image)
    if rotation % 4:
        image = np.ascontiguousarray(np.rot90(image, rotation % 4, axes=(0, 1)))
    res, inten = region_residual_and_intensity(
        image, region, sigma,
        white_level=white_level, black_level=black_level, saturation_level=saturation_level,
        saturation_dilate=saturation_dilate, rolloff=rolloff, postprocess=True, workers=workers, cfa=cfa,
    )
    return Query(residual=res, intensity=inten, region=region.spec, rotation=rotation % 4, source=source)


def _check_metric(metric: str) -> str:
    if metric not in METRICS:
        raise UsageError(f"metric {metric!r}: choose one of {', '.join(METRICS)}")
    return metric


def _score(
    fingerprint: Fingerprint,
    residual: np.ndarray,
    intensity: np.ndarray,
    metric: str,
    shift_range: Any,
    exclusion: int,
    rotation: int,
    workers: int,
    spectrum: _Spectrum | None = None,
) -> MatchScore:
    if residual.shape != fingerprint.K.shape or intensity.shape != fingerprint.K.shape:
        raise InputError(
            f"query of shape {residual.shape} does not match the fingerprint's {fingerprint.K.shape} "
            f"(region {fingerprint.region}); prepare the query with the same region"
        )
    expected = intensity * fingerprint.K
    if metric == "ncc":
        corr = ncc(residual, expected)
        return MatchScore("ncc", corr, rotation, corr, None)
    sa = spectrum if spectrum is not None else _Spectrum(residual, workers)
    result, corr = _pce_with(sa, expected, shift_range, exclusion)
    return MatchScore("pce", result.pce, rotation, corr, result)


def score_pair(
    fingerprint: Fingerprint,
    query: Query | tuple[np.ndarray, np.ndarray],
    metric: str = "pce",
    *,
    shift_range: int | tuple[int, int] | None = 0,
    exclusion: int = 11,
    workers: int | None = None,
) -> MatchScore:
    """Score a prepared query (or a ``(residual, intensity)`` pair) against a fingerprint.

    The detector correlates the query residual ``W`` with ``I·K``.
    """
    _check_metric(metric)
    workers = default_workers() if workers is None else workers
    if isinstance(query, Query):
        if query.region != fingerprint.region:
            raise InputError(f"query region {query.region} differs from the fingerprint's {fingerprint.region}")
        res, inten, rot = query.residual, query.intensity, query.rotation
    else:
        res, inten = (np.asarray(v) for v in query)
        rot = 0
    return _score(fingerprint, res, inten, metric, shift_range, exclusion, rot, workers)


def _rotations_for(rotations: str | int | Sequence[int], image_shape: Sequence[int], fp: Fingerprint) -> tuple[int, ...]:
    if isinstance(rotations, str):
        if rotations != "auto":
            raise UsageError(f"rotations={rotations!r}: use 'auto', an int or a sequence of ints")
        return orientations(image_shape, fp.frame_shape)
    if np.ndim(rotations) == 0:
        return (int(rotations) % 4,)  # type: ignore[arg-type]
    return tuple(int(r) % 4 for r in rotations)  # type: ignore[union-attr]


def score_query(
    fingerprint: Fingerprint,
    image: np.ndarray,
    metric: str = "pce",
    *,
    sigma: float = QUERY_SIGMA,
    shift_range: int | tuple[int, int] | None = 0,
    exclusion: int = 11,
    rotations: str | int | Sequence[int] = "auto",
    workers: int | None = None,
    **query_options: Any,
) -> MatchScore:
    """Score a query image against a fingerprint.

    Parameters
    ----------
    fingerprint : Fingerprint
    image : ndarray, (H, W) or (H, W, 3)
        The full frame (not modified); the fingerprint's region is cut out of it.
    metric : {'pce', 'ncc'}
    sigma : float
        Query residual noise level (2 in the reference).
    shift_range, exclusion
        See :func:`pce`.
    rotations : 'auto', int or sequence of int
        ``np.rot90`` turns to try; the best score is kept.  'auto' tries none for an
        image shaped like the frames and both quarter turns for a transposed one
        (:func:`orientations`).  Trying two orientations doubles ``n_shifts`` in
        the false-alarm probability.
    **query_options
        Passed to :func:`prepare_query` (white_level, black_level, ...).
    """
    _check_metric(metric)
    check_fingerprint(fingerprint)
    workers = default_workers() if workers is None else workers
    region = parse_region(fingerprint.region)
    best: MatchScore | None = None
    rots = _rotations_for(rotations, np.shape(image), fingerprint)
    problem = _content_problem(np.asarray(image), region.spec, rots[0], query_options)
    if problem is not None:
        raise InputError(f"the query image is content-free over the fingerprint's region ({problem}); it holds no "
                         "pattern to match")
    for rot in rots:
        q = prepare_query(image, region, sigma=sigma, rotation=rot, workers=workers, **query_options)
        score = _score(fingerprint, q.residual, q.intensity, metric, shift_range, exclusion, rot, workers)
        if best is None or score.value > best.value:
            best = score
    assert best is not None
    return _account_rotations(best, len(rots))


def _account_rotations(score: MatchScore, n_rot: int) -> MatchScore:
    """Fold the number of orientations tried into the false-alarm probability."""
    if score.pce is None or n_rot <= 1:
        return score
    p = score.pce
    n = p.n_shifts * n_rot
    z = math.copysign(math.sqrt(abs(p.pce)), p.pce)
    p_fa, log10 = _false_alarm(z, n) if p.sign != 0 else (1.0, 0.0)
    pce_result = PceResult(p.pce, p.shift, p.sign, p.ncc, p_fa, log10, n)
    return MatchScore(score.metric, score.value, score.rotation, score.ncc, pce_result)


def _content_problem(image: np.ndarray, region: str, rotation: int, options: dict[str, Any]) -> str | None:
    """Why ``image`` turned by ``rotation`` holds no pattern over ``region``, or None (also when the region does not
    fit: the scoring then says so, with the shapes)."""
    try:
        return region_content_problem(np.rot90(image, rotation % 4, axes=(0, 1)), region, **options)
    except InputError:
        return None


class _PreparedImage:
    """A query image whose region residuals and spectra are computed once, on demand."""

    def __init__(self, image: np.ndarray, source: str | None, sigma: float, workers: int, options: dict[str, Any]):
        self.image = image
        self.source = source
        self.sigma = sigma
        self.workers = workers
        self.options = options
        self._cache: dict[tuple[str, int], tuple[Query, _Spectrum | None]] = {}
        self._content: dict[tuple[str, int], str | None] = {}

    def content_problem(self, region: str, rotation: int = 0) -> str | None:
        """Why the image, turned by ``rotation``, holds no pattern over ``region`` (None if it has some;
        :func:`~forensics.prnu.fingerprint.region_content_problem`), computed once per region and rotation."""
        key = (region, rotation % 4)
        if key not in self._content:
            self._content[key] = _content_problem(self.image, region, rotation, self.options)
        return self._content[key]

    def get(self, region: str, rotation: int, need_spectrum: bool) -> tuple[Query, _Spectrum | None]:
        key = (region, rotation)
        q, s = self._cache.get(key, (None, None))
        if q is None:
            q = prepare_query(self.image, region, sigma=self.sigma, rotation=rotation, source=self.source,
                              workers=self.workers, **self.options)
        if need_spectrum and s is None:
            s = _Spectrum(q.residual, self.workers)
        self._cache[key] = (q, s)
        return q, s


@dataclass(frozen=True)
class _MatchSettings:
    """What every query of a score matrix is scored with (the work items' shared data)."""

    fingerprints: tuple[Fingerprint, ...]
    metric: str
    sigma: float
    shift_range: Any
    exclusion: int
    rotations: Any
    workers: int | None
    query_options: dict[str, Any] = field(default_factory=dict)


def _is_reference(item: Any) -> bool:
    """A query that a worker can read itself: an image path or an object with ``load()`` (a dataset frame)."""
    return isinstance(item, (str, os.PathLike)) or (hasattr(item, "load") and not isinstance(item, np.ndarray))


def _score_column(settings: _MatchSettings, item: Any) -> list[MatchScore]:
    """Work item of a score matrix: one query against every fingerprint (read here if it is a path or frame)."""
    workers = default_workers() if settings.workers is None else settings.workers
    metric, fingerprints = settings.metric, settings.fingerprints
    if isinstance(item, Query) or (isinstance(item, tuple) and len(item) == 2):
        return [score_pair(fp, item, metric, shift_range=settings.shift_range, exclusion=settings.exclusion,
                           workers=workers) for fp in fingerprints]
    source = None
    if isinstance(item, (str, os.PathLike)):
        from forensics.io.images import read_image

        source, item = str(item), read_image(item)
    elif hasattr(item, "load"):
        source = str(getattr(item, "path", "")) or None
        item = item.load()
    prepared = _PreparedImage(np.asarray(item), source, settings.sigma, workers, settings.query_options)
    column: list[MatchScore] = []
    for fp in fingerprints:
        rots = _rotations_for(settings.rotations, prepared.image.shape, fp)
        problem = prepared.content_problem(fp.region, rots[0])
        if problem is not None:  # no score at all: a number would be taken at face value
            column.append(MatchScore(metric, math.nan, 0, math.nan, None, problem))
            continue
        best: MatchScore | None = None
        for rot in rots:
            q, spec = prepared.get(fp.region, rot, metric == "pce")
            s = _score(fp, q.residual, q.intensity, metric, settings.shift_range, settings.exclusion, rot, workers,
                       spec)
            if best is None or s.value > best.value:
                best = s
        assert best is not None
        column.append(_account_rotations(best, len(rots)))
    return column


def score_matrix(
    fingerprints: Sequence[Fingerprint],
    queries: Iterable[Any],
    metric: str = "pce",
    *,
    sigma: float = QUERY_SIGMA,
    shift_range: int | tuple[int, int] | None = 0,
    exclusion: int = 11,
    rotations: str | int | Sequence[int] = "auto",
    progress: Progress = no_progress,
    total: int | None = None,
    details: bool = False,
    workers: int | None = None,
    executor: Executor | None = None,
    **query_options: Any,
) -> np.ndarray | tuple[np.ndarray, list[list[MatchScore]]]:
    """Score every query against every fingerprint.

    Parameters
    ----------
    fingerprints : sequence of Fingerprint
        May differ in region; each query is prepared once per (region, rotation).
    queries : iterable
        Each item is an image array, a :class:`Query`, a ``(residual, intensity)``
        pair already cut to the fingerprints' region, an image path, or an object with
        ``load()`` (and ``path``), e.g. :class:`forensics.io.dataset.Frame`.  They are
        consumed one at a time, so only one query's data is in memory (per worker).
    metric, sigma, shift_range, exclusion, rotations, **query_options
        As :func:`score_query`.
    progress : callable
        Progress wrapper, counting queries.
    total : int, optional
        Number of queries of an iterator, for the progress bar.
    details : bool
        Also return the :class:`MatchScore` of every pair.
    workers : int, optional
        Threads per query (default: the process's share, :func:`forensics.prnu.residual.default_workers`).
    executor : Executor, optional
        Where the queries are scored, one work item per query, the fingerprints shipped once per
        worker (default: this process).  Workers read the queries themselves, so on worker
        processes or a cluster give paths or dataset frames (a sequence); the scores are the
        same on every backend, in query order.

    Returns
    -------
    scores : ndarray, float64, (n_fingerprints, n_queries)
    details : list (per fingerprint) of lists of MatchScore, if ``details``

    Raises
    ------
    UsageError
        No fingerprints, an unknown metric, or arrays (or an iterator) given to an executor that
        is not in-process.
    """
    _check_metric(metric)
    fingerprints = list(fingerprints)
    if not fingerprints:
        raise UsageError("no fingerprints to score against")
    for i, fp in enumerate(fingerprints):
        check_fingerprint(fp, f"fingerprint {i}")
    settings = _MatchSettings(tuple(fingerprints), metric, sigma, shift_range, exclusion, rotations, workers,
                              dict(query_options))
    ex = resolve(executor)
    sized = hasattr(queries, "__len__") and not isinstance(queries, np.ndarray)
    if ex.backend == "in-process" and not sized:  # an iterator: stream it, never hold it as a list
        columns = [_score_column(settings, item) for item in progress(queries, total=total, desc="matching")]
    else:
        items = list(queries)
        if ex.backend != "in-process" and not all(_is_reference(item) for item in items):
            raise UsageError("scoring on worker processes or a cluster reads every query from its file: give image "
                             "paths or dataset frames, not arrays (or use the in-process executor)")
        columns = list(ex.map(_score_column, items, shared=settings, progress=progress, desc="matching"))
    n_fp = len(fingerprints)
    scores = np.array([[column[i].value for column in columns] for i in range(n_fp)],
                      dtype=np.float64).reshape(n_fp, len(columns))
    if details:
        return scores, [[column[i] for column in columns] for i in range(n_fp)]
    return scores


@dataclass
class SetMatch:
    """Every image of a set scored against one fingerprint, with a decision at a threshold (:func:`match_set`).

    ``scores`` holds one row per image: ``file``, ``score`` (the metric's value), ``ncc``, ``rotation``
    (quarter turns), ``pce`` (:meth:`PceResult.to_dict` or None), ``match`` (None without a threshold) and
    ``excluded`` (why a content-free image was not scored: then ``score``, ``ncc`` and ``match`` are None).
    """

    fingerprint: str
    set: str
    region: str
    metric: str
    threshold: float | None
    shift_search: str | None
    scores: list[dict[str, Any]]

    @property
    def n_match(self) -> int | None:
        """Images reaching the threshold (None without one)."""
        return sum(1 for r in self.scores if r["match"]) if self.threshold is not None else None

    @property
    def excluded(self) -> list[dict[str, Any]]:
        """The rows of content-free images (not scored)."""
        return [r for r in self.scores if r.get("excluded") is not None]

    def to_dict(self) -> dict[str, Any]:
        return {"fingerprint": self.fingerprint, "set": self.set, "region": self.region, "metric": self.metric,
                "threshold": self.threshold, "shift_search": self.shift_search, "n_images": len(self.scores),
                "n_match": self.n_match, "n_excluded": len(self.excluded), "scores": self.scores}


def match_set(fingerprint: Fingerprint, dataset: Any, metric: str = "pce", *, threshold: float | None = None,
              shift_range: int | None = 0, sigma: float = QUERY_SIGMA, progress: Progress = no_progress,
              name: str | None = None, executor: Executor | None = None, dark: Any = None) -> SetMatch:
    """Score each frame of ``dataset`` against ``fingerprint`` and decide at ``threshold``.

    Parameters
    ----------
    fingerprint : Fingerprint
    dataset : forensics.io.dataset.Dataset
        Its frames are scored (streamed) with :func:`score_matrix`.
    metric : {'pce', 'ncc'}
    threshold : float, optional
        Default :data:`PCE_THRESHOLD` for PCE, none (no decisions) for NCC.
    shift_range : int or None
        PCE only: 0 (zero shift), R (up to ±R pixels) or None (every circular shift).
    sigma : float
        Query residual noise level (8-bit scale).
    name : str, optional
        How the fingerprint is named in the result (e.g. its file).
    executor : Executor, optional
        Where the frames are scored, one work item each (:func:`score_matrix`); default in this process.
    dark : DarkCalibration, optional
        Calibrate every raw CCD frame as ``frame − offset − rate·exposure`` before its residual
        (:mod:`forensics.prnu.calibration`).

    Raises
    ------
    UsageError
        A shift search with NCC.
    InputError
        Every image is content-free over the fingerprint's region (:mod:`forensics.io.content`); images that
        are so among others are not scored (their rows say why).
    """
    _check_metric(metric)
    if metric == "ncc" and shift_range != 0:
        raise UsageError("--shift-range applies to PCE only; drop it or use --metric pce")
    if threshold is not None and not math.isfinite(threshold):
        raise UsageError(f"threshold={threshold}: give a finite number (e.g. 60 for PCE)")
    if threshold is None and metric == "pce":
        threshold = PCE_THRESHOLD
    check_fingerprint(fingerprint, name or "fingerprint")
    from forensics.prnu.fingerprint import query_options

    queries, options = dataset.frames, query_options(fingerprint)
    if dark is not None:
        queries, options = dark.calibrated_frames(dataset), {**options, "white_level": dark.white_level}
    scores, details = score_matrix([fingerprint], queries, metric, sigma=sigma, shift_range=shift_range,
                                   progress=progress, total=len(dataset), details=True, executor=executor,
                                   **options)
    rows = []
    for frame, value, d in zip(dataset.frames, scores[0], details[0]):
        decision = None if threshold is None or d.excluded is not None else bool(value >= threshold)
        rows.append({"file": frame.file, "score": None if d.excluded is not None else float(value),
                     "ncc": None if d.excluded is not None else d.ncc, "rotation": d.rotation,
                     "pce": d.pce.to_dict() if d.pce is not None else None, "match": decision,
                     "excluded": d.excluded})
    excluded = [r for r in rows if r["excluded"] is not None]
    if rows and len(excluded) == len(rows):
        raise InputError(f"{dataset.root}: every one of its {len(rows)} frame(s) is content-free over the fingerprint's "
                         f"region, so none can be scored (first, {rows[0]['file']}: {rows[0]['excluded']}); give "
                         "exposed images")
    search = ("zero shift" if shift_range == 0 else
              "all circular shifts" if shift_range is None else f"shifts up to ±{shift_range}")
    return SetMatch(name or "fingerprint", str(dataset.root), fingerprint.region, metric, threshold,
                    search if metric == "pce" else None, rows)
