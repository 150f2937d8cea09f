"""1:N identification: which fingerprint of a database, if any, left its pattern in each query image?

For every query image and every candidate fingerprint ``K`` the PCE of :mod:`forensics.prnu.match` is
computed over every geometry searched, and the best device is the one with the highest PCE.

The search is described where it is computed: the geometry (orientations, crops, scales) in
:mod:`forensics.prnu.geometry`, the statistic (block-phase PCE, the weighted search on a JPEG grid) in
:mod:`forensics.prnu.blockpce`, the compressed pre-screen of large databases in
:mod:`forensics.prnu.prescreen`; the correlation and its tail statistics, shared with
:mod:`forensics.prnu.cluster`, in :mod:`forensics.prnu.correlation`.

Decision (Šidák over everything searched)
-----------------------------------------
Under the null hypothesis (no candidate took the image) the normalised peak ``z = sign·√|PCE|`` at
each position searched is about standard normal (:mod:`forensics.prnu.match`).  With ``n_j``
positions searched for fingerprint ``j`` (offsets × scales × orientations) and ``n = Σ_j n_j`` over
the ``N`` fingerprints the image is compatible with, the best device's corrected false-alarm
probability is

    p_FA = 1 − (1 − Q(z_best)/w_best)^n,     n = Σ_j positions_j · scales_j · rotations_j   (Šidák)

with position weights ``w`` that sum to ``n`` (a weighted Šidák/Bonferroni split of the budget; candidates
are ranked by ``Q(z)/w``), and the image is *attributed* when ``p_FA ≤ pfa``, else *unknown*.  Neighbouring
positions and scales are positively correlated, which makes Šidák conservative for Gaussian ``z``, so
searching more never inflates false alarms; measured on simulated devices outside the set the corrected
``p_FA`` is close to uniform (crop searches over ~10⁴ offsets: 5, 13 and 36 of 60 at 0.05, 0.2 and 0.5;
aligned images: 9 and 39 of 200 at 0.05 and 0.2).  The equivalent PCE threshold,
``Q⁻¹(1 − (1 − pfa)^(w/n))²`` for the best peak's weight, is reported with each image.

**Two hypotheses, two shares.**  An image of a fingerprint's frame size is most likely the camera's own
picture, aligned (one position per fingerprint and orientation); but in a database of many sensor sizes
it is also a possible crop of every larger sensor, at ~10⁶ offsets each.  With one count for both, the
crop searches set the threshold of the aligned test too: a natural Dresden D70 image scores PCE 27
(p ≈ 10⁻⁷) at zero shift against its own camera, but with two D200 fingerprints in the database its
``n`` is 1,025,894 and the threshold PCE 36, so it came out unknown.  The aligned positions (``n_al``:
same-size, scale 1, zero shift, over all fingerprints and orientations) therefore get their own share
:data:`ALIGNED_SHARE` of the budget and the searched positions (``n_se``: crops and scales) the rest:
``w_al = share·n/n_al`` and ``w_se = (1 − share)·n/n_se`` (times the JPEG-grid weight of
:mod:`forensics.prnu.blockpce` inside a search), which sum to ``n``, so the bound holds whichever
hypothesis is true.  For the D70 image (4 aligned tests, 1,025,890 crop positions) the aligned threshold
falls to PCE 13.4 and it is attributed, while the crop positions' threshold rises from 36.0 to 37.4.  With only
one kind of position every weight is 1, as before.  Both shares, their counts
and their thresholds are reported with each image (``budget``).

**Ambiguity.**  When more than one device reaches the decision (each one's ``p_FA`` at most ``pfa``) the
image is *ambiguous* and no device is named: the candidates are listed instead (``matches``).  This is
what two entries of one sensor (or a false alarm) give; picking one, for instance the first by name
among identical fingerprints, would state a certainty the data do not have.

**Content-free images** (constant, black or saturated: :mod:`forensics.io.content`) are not scored:
their decision is *excluded*, with the reason; a set of nothing but such images is refused.

Execution: one work item per query (a path or a dataset frame, read by the worker), the fingerprints
(and their sketches) shipped once per worker (``shared``); results in query order on every backend.
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
from forensics._shared.progress import Progress, no_progress
from forensics.prnu.blockpce import _block_pce, _Peak
from forensics.prnu.correlation import (
    _centred,
    _false_alarm,
    _log_tail,
    _shift_indices,
    _Spectrum,
    _z,
    pce_threshold,
    surface,
)
from forensics.prnu.fingerprint import Fingerprint, check_fingerprint, parse_region, region_content_problem
from forensics.prnu.geometry import (
    _ROTATION_MODES,
    ScaleSearch,
    _plan,
    _Reference,
    _scale_info,
    _Test,
    parse_scales,
    resample,
)
from forensics.prnu.match import QUERY_SIGMA, _is_reference, _PreparedImage
from forensics.prnu.prescreen import (
    PRESCREEN_AUTO_MIN,
    Prescreen,
    PrescreenMissRate,
    _prescreen,
    _prescreen_config,
    _screen,
    _with_sketches,
    sketch,
)
from forensics.prnu.residual import default_workers

__all__ = [
    "ALIGNED_SHARE",
    "CORRECTION",
    "DEFAULT_PFA",
    "PRESCREEN_AUTO_MIN",
    "Candidate",
    "IdentificationResult",
    "Prescreen",
    "PrescreenMissRate",
    "QueryIdentification",
    "ScaleSearch",
    "identify",
    "parse_scales",
    "pce_threshold",
    "prescreen_miss_rate",
    "resample",
]

#: Default false-alarm probability of an attribution, over all fingerprints and positions searched.
DEFAULT_PFA = 1e-3
#: Share of the false-alarm budget given to the aligned positions when crops or scales are searched too.
ALIGNED_SHARE = 0.5
#: The decision rule, as reported.
CORRECTION = ("weighted Šidák: p_FA = 1 − (1 − Q(z_best)/w_best)^n, n = Σ over compatible fingerprints of "
              "positions × scales × rotations searched; z = √PCE; weights sum to n: when both are searched, the "
              "aligned positions (same size, zero shift) share half the budget and the crop/scale positions the "
              "other half, and on a JPEG crop the offsets on its detected block grid share half of the search's; "
              "attributed when p_FA ≤ pfa for one device, ambiguous when for several")


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Candidate:
    """One fingerprint's best score against one query.

    Attributes
    ----------
    device_id : str
    pce : float
        Signed PCE at the best position (``z = sign·√|PCE|``).
    p_fa : float
        False-alarm probability of this fingerprint alone over its own search
        (``1 − (1 − Q(z)/w_grid)^n_positions``); the decision uses the query's corrected value instead.
    log10_p_fa : float
    ncc : float
        Normalised correlation at the peak.
    rotation : int
        Quarter turns (``np.rot90``) applied to the query.
    scale : float
        Query pixels per sensor pixel (1 for no resize).
    offset : (int, int)
        Top-left corner of the (rotated) query in the frame resampled by ``scale``, (row, column).
    n_positions : int
        Positions searched for this fingerprint (offsets × scales × rotations).
    method : str
        ``'aligned'`` (zero shift), ``'crop'`` (offset search) or ``'scale'`` (scale and offset search).
    sketch_score : float, optional
        The pre-screen's z-score ``√d·corr`` (None when not pre-screened).
    pce_global : float
        The plain PCE at the same peak (one energy over all shifts, as ``forensics fingerprint match``
        reports), for comparison; the decision uses ``pce`` (block-phase energy, module notes).
    search_weight : float
        The peak's weight in the query's weighted search (module notes): its hypothesis' share (aligned or
        searched, 1 when only one kind is searched) times its JPEG-grid weight (above 1 on the query's
        detected grid, below 1 off it, 1 without a grid).  Its tail is ``Q(z)/search_weight``.
    """

    device_id: str
    pce: float
    p_fa: float
    log10_p_fa: float
    ncc: float
    rotation: int
    scale: float
    offset: tuple[int, int]
    n_positions: int
    method: str
    sketch_score: float | None = None
    pce_global: float | None = None
    search_weight: float = 1.0

    @property
    def z(self) -> float:
        """The normalised peak ``sign·√|PCE|``."""
        return math.copysign(math.sqrt(abs(self.pce)), self.pce)

    @property
    def log_tail(self) -> float:
        """``log(Q(z)/search_weight)``: candidates rank by it, smallest (strongest) first."""
        return _log_tail(self.z, self.search_weight)

    def geometry(self) -> str:
        """Where the query matched, for tables: ``'aligned'`` or e.g. ``'rot 90°, scale 0.7, at (12, 40)'``."""
        parts = []
        if self.rotation:
            parts.append(f"rot {90 * self.rotation}°")
        if self.method == "scale":
            parts.append(f"scale {self.scale:.4g}")
        if self.method != "aligned":
            parts.append(f"at ({self.offset[0]}, {self.offset[1]})")
        if self.search_weight > 1.0:
            parts.append("on the JPEG grid")
        return ", ".join(parts) or "aligned"

    def to_dict(self) -> dict[str, Any]:
        return {"device_id": self.device_id, "pce": self.pce, "p_fa": self.p_fa, "log10_p_fa": self.log10_p_fa,
                "ncc": self.ncc, "rotation": self.rotation, "scale": self.scale, "offset": list(self.offset),
                "n_positions": self.n_positions, "method": self.method, "sketch_score": self.sketch_score,
                "pce_global": self.pce_global, "search_weight": self.search_weight}


@dataclass(frozen=True)
class QueryIdentification:
    """The identification of one image.

    Attributes
    ----------
    source : str
    shape : (int, int)
        Image height and width as stored.
    decision : str
        ``'attributed'`` (one device reaches the decision), ``'ambiguous'`` (several do: see ``matches``),
        ``'unknown'`` (none does) or ``'excluded'`` (a content-free image, not scored: see ``note``).
    device_id : str or None
        The attributed device.
    best, runner_up : Candidate or None
        Highest and second-highest PCE.
    top : tuple of Candidate
        The ``top_k`` highest, best first.
    p_fa, log10_p_fa : float
        The best device's false-alarm probability corrected for everything searched (module notes).
    pce_threshold : float
        The PCE the best device needed for an attribution at the run's ``pfa``.
    n_tests : int
        ``n`` of the correction: positions × scales × rotations summed over compatible fingerprints.
    n_fingerprints : int
        Fingerprints the image is compatible with (size, orientation, scale).
    n_scored : int
        Fingerprints that got the full PCE (fewer than ``n_fingerprints`` after a pre-screen).
    prescreen : dict or None
        The pre-screen's figures (sketch length, kept, dropped), None when it did not run.
    scales : dict or None
        The scale grid used (number, range, grid error in pixels), None without a scale search.
    note : str or None
        Why an image could not be scored, if so.
    matches : tuple of str
        Every device that reaches the decision (one when attributed, several when ambiguous).
    budget : dict or None
        The split of the false-alarm budget between the aligned and the searched positions (module notes):
        for each, its positions, share, weight and the PCE a peak of weight 1 within it needs.
    """

    source: str
    shape: tuple[int, int]
    decision: str
    device_id: str | None
    best: Candidate | None
    runner_up: Candidate | None
    top: tuple[Candidate, ...]
    p_fa: float
    log10_p_fa: float
    pce_threshold: float
    n_tests: int
    n_fingerprints: int
    n_scored: int
    prescreen: dict[str, Any] | None = None
    scales: dict[str, Any] | None = None
    note: str | None = None
    matches: tuple[str, ...] = ()
    budget: dict[str, Any] | None = None

    @property
    def attributed(self) -> bool:
        return self.decision == "attributed"

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "shape": list(self.shape), "decision": self.decision,
                "device_id": self.device_id, "best": self.best.to_dict() if self.best else None,
                "runner_up": self.runner_up.to_dict() if self.runner_up else None,
                "top": [c.to_dict() for c in self.top], "p_fa": self.p_fa, "log10_p_fa": self.log10_p_fa,
                "pce_threshold": self.pce_threshold, "n_tests": self.n_tests,
                "n_fingerprints": self.n_fingerprints, "n_scored": self.n_scored, "prescreen": self.prescreen,
                "scales": self.scales, "note": self.note, "matches": list(self.matches), "budget": self.budget}


@dataclass
class IdentificationResult:
    """Every query's identification against one set of fingerprints (:func:`identify`)."""

    queries: list[QueryIdentification]
    devices: list[dict[str, Any]]
    pfa: float
    settings: dict[str, Any]
    correction: str = CORRECTION
    name: str | None = None

    @property
    def n_attributed(self) -> int:
        return sum(1 for q in self.queries if q.attributed)

    def n_decided(self, decision: str) -> int:
        """Images with this decision ('attributed', 'ambiguous', 'unknown' or 'excluded')."""
        return sum(1 for q in self.queries if q.decision == decision)

    def counts(self) -> dict[str, int]:
        """Images attributed to each device (devices with none omitted)."""
        out: dict[str, int] = {}
        for q in self.queries:
            if q.attributed and q.device_id is not None:
                out[q.device_id] = out.get(q.device_id, 0) + 1
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"set": self.name, "n_images": len(self.queries), "n_fingerprints": len(self.devices),
                "n_attributed": self.n_attributed, "n_ambiguous": self.n_decided("ambiguous"),
                "n_unknown": self.n_decided("unknown"), "n_excluded": self.n_decided("excluded"),
                "pfa": self.pfa, "correction": self.correction, "settings": self.settings,
                "counts": self.counts(), "devices": self.devices, "queries": [q.to_dict() for q in self.queries]}



# ----------------------------------------------------------------------------- work items


@dataclass(frozen=True)
class _Settings:
    """What every query is identified with (the work items' shared data)."""

    refs: tuple[_Reference, ...]
    top_k: int
    pfa: float
    rotations: Any
    scales: ScaleSearch | None
    crop_search: bool
    prescreen: Prescreen | None
    sigma: float
    exclusion: int
    workers: int | None
    query_options: dict[str, Any] = field(default_factory=dict)


class _QueryImage:
    """One query: its residuals and spectra, each computed once and reused for every fingerprint."""

    def __init__(self, image: np.ndarray, source: str, settings: _Settings) -> None:
        if image.ndim not in (2, 3):
            raise InputError(f"{source}: array of shape {image.shape} is not an image")
        self.shape = (int(image.shape[0]), int(image.shape[1]))
        self.source = source
        self.workers = default_workers() if settings.workers is None else settings.workers
        self.prepared = _PreparedImage(image, source, settings.sigma, self.workers, settings.query_options)
        self._products: dict[tuple[str, int], np.ndarray] = {}
        self._spectra: dict[tuple[Any, ...], _Spectrum] = {}
        self._sketches: dict[tuple[str, int, int, int], np.ndarray] = {}

    def product(self, region: str, rot: int) -> np.ndarray:
        """Zero-mean ``W·I`` (residual times intensity), float32.

        ``region='full'`` with a rotation: the whole image's residual turned (one residual per image
        for the crop and scale searches); another region: the residual of that region of the turned image.
        """
        key = (region, rot)
        if key not in self._products:
            if region == "full":
                q, _ = self.prepared.get("full", 0, False)
                p = np.rot90(q.residual * q.intensity, rot)
            else:
                q, _ = self.prepared.get(region, rot, False)
                p = q.residual * q.intensity
            self._products[key] = _centred(np.ascontiguousarray(p))
        return self._products[key]

    def canvas_spectrum(self, test: _Test) -> _Spectrum:
        """Spectrum of the query's ``W·I`` zero-padded to the test's canvas, its origin at the canvas' centre offset."""
        key = (test.rotation, test.canvas, test.centre)
        if key not in self._spectra:
            p = self.product("full", test.rotation)
            canvas = np.zeros(test.canvas, np.float32)
            canvas[: p.shape[0], : p.shape[1]] = p
            canvas = np.roll(canvas, test.centre, axis=(0, 1))
            self._spectra[key] = _Spectrum(canvas, self.workers)
        return self._spectra[key]

    def sketch(self, region: str, rot: int, dim: int, seed: int) -> np.ndarray:
        key = (region, rot, dim, seed)
        if key not in self._sketches:
            self._sketches[key] = sketch(self.product(region, rot), dim, seed)
        return self._sketches[key]



def _run_test(query: _QueryImage, ref: _Reference, test: _Test, exclusion: int) -> tuple[_Peak, tuple[int, int]]:
    """Block-phase PCE of one test, and the query's top-left in the (resampled) frame at the peak."""
    k = ref.fingerprint.K
    if test.aligned:
        q, spectrum = query.prepared.get(ref.region.spec, test.rotation, True)
        assert spectrum is not None
        corr, norm_b = surface(spectrum, q.intensity * k)
        zero = np.zeros(1, np.int64)
        return _block_pce(corr, zero, zero, exclusion, spectrum.norm * norm_b), (0, 0)
    if test.scale_yx != (1.0, 1.0):
        assert ref.origin is not None
        k = resample(k, test.scale_yx, test.k_shape, out_origin=test.k_origin, in_origin=ref.origin)
    reference = np.zeros(test.canvas, np.float32)
    reference[: test.k_shape[0], : test.k_shape[1]] = _centred(k)
    spectrum = query.canvas_spectrum(test)
    corr, norm_b = surface(spectrum, reference)
    del reference
    rows = _shift_indices(test.radius[0], test.canvas[0])
    cols = _shift_indices(test.radius[1], test.canvas[1])
    peak = _block_pce(corr, rows, cols, exclusion, spectrum.norm * norm_b)
    # the query sits at δ = centre − shift in K's coordinates (shift convention of forensics.prnu.match.pce)
    dy, dx = peak.shift
    offset = (test.k_origin[0] + test.centre[0] - dy, test.k_origin[1] + test.centre[1] - dx)
    return peak, offset


def _score_reference(query: _QueryImage, ref: _Reference, tests: list[_Test], exclusion: int,
                     sketch_score: float | None, shares: _Budget) -> Candidate:
    """The best of a fingerprint's tests (smallest tail weighted by its hypothesis' share and its grid weight),
    with its own search-corrected p_FA."""
    best: tuple[float, _Peak, _Test, tuple[int, int], float] | None = None
    for test in tests:
        peak, offset = _run_test(query, ref, test, exclusion)
        weight = peak.weight * shares.weight(test.aligned)
        tail = _log_tail(_z(peak.pce), weight)
        if best is None or tail < best[0]:
            best = (tail, peak, test, offset, weight)
    assert best is not None
    _, peak, test, offset, weight = best
    n = sum(t.n_positions for t in tests)
    p_fa, log10 = _false_alarm(_z(peak.pce), n, peak.weight) if peak.sign != 0 else (1.0, 0.0)
    method = "aligned" if test.aligned else ("crop" if test.scale_yx == (1.0, 1.0) else "scale")
    return Candidate(ref.device_id, float(peak.pce), p_fa, log10, peak.ncc, test.rotation, float(test.scale),
                     (int(offset[0]), int(offset[1])), int(n), method, sketch_score, float(peak.pce_global),
                     float(weight))


@dataclass(frozen=True)
class _Budget:
    """How a query's false-alarm budget is split between aligned and searched positions (module notes)."""

    n_aligned: int
    n_searched: int
    share: float = ALIGNED_SHARE

    @property
    def n(self) -> int:
        return self.n_aligned + self.n_searched

    def weight(self, aligned: bool) -> float:
        """``w_al = share·n/n_al`` or ``w_se = (1 − share)·n/n_se``; 1 when only one kind is searched."""
        if self.n_aligned == 0 or self.n_searched == 0:
            return 1.0
        return self.share * self.n / self.n_aligned if aligned else (1.0 - self.share) * self.n / self.n_searched

    def to_dict(self, pfa: float) -> dict[str, Any]:
        both = self.n_aligned > 0 and self.n_searched > 0
        out = {}
        for key, aligned, count in (("aligned", True, self.n_aligned), ("searched", False, self.n_searched)):
            share = (self.share if aligned else 1.0 - self.share) if both else float(count > 0)
            w = self.weight(aligned)
            out[key] = {"n_tests": count, "share": share, "weight": w if count else None,
                        "pce_threshold": pce_threshold(pfa, self.n / w) if count else None}
        return out



def _load_query(payload: Any, index: int) -> tuple[np.ndarray, str]:
    if isinstance(payload, (str, os.PathLike)):
        from forensics.io.images import read_image

        return read_image(payload), str(payload)
    if hasattr(payload, "load") and not isinstance(payload, np.ndarray):
        name = getattr(payload, "file", None) or str(getattr(payload, "path", "")) or f"query[{index}]"
        return np.asarray(payload.load()), str(name)
    return np.asarray(payload), f"query[{index}]"


def _identify_item(settings: _Settings, item: tuple[int, Any]) -> QueryIdentification:
    """Work item: one query against every compatible fingerprint."""
    index, payload = item
    image, source = _load_query(payload, index)
    shape = (int(image.shape[0]), int(image.shape[1])) if image.ndim in (2, 3) else (0, 0)
    problem = region_content_problem(image, "full", **settings.query_options) if image.ndim in (2, 3) else None
    if problem is not None:  # nothing to score: any number would be taken at face value
        return QueryIdentification(source, shape, "excluded", None, None, None, (), 1.0, 0.0, math.inf, 0, 0, 0,
                                   note=f"content-free: {problem}")
    query = _QueryImage(image, source, settings)
    del image
    plans = [_plan(query.shape, ref, settings.rotations, settings.scales, settings.crop_search)
             for ref in settings.refs]
    compatible = [j for j, tests in enumerate(plans) if tests]
    n_aligned = sum(t.n_positions for tests in plans for t in tests if t.aligned)
    shares = _Budget(n_aligned, sum(t.n_positions for tests in plans for t in tests) - n_aligned)
    n_tests = shares.n
    scale_info = _scale_info(settings.scales, query.shape)
    if not compatible:
        note = (f"no fingerprint is compatible with this {query.shape[1]}×{query.shape[0]} image (size, orientation"
                + (", scales searched" if settings.scales is not None else "; a resized image needs a scale search")
                + ")")
        return QueryIdentification(source, query.shape, "unknown", None, None, None, (), 1.0, 0.0, math.inf, 0, 0, 0,
                                   None, scale_info, note)
    chosen, sketch_scores, pre_info = _prescreen(query, settings.refs, settings.prescreen, plans, compatible)
    candidates = [_score_reference(query, settings.refs[j], plans[j], settings.exclusion, sketch_scores.get(j),
                                   shares) for j in chosen]
    candidates.sort(key=lambda c: (c.log_tail, c.device_id))
    best = candidates[0]
    p_fa, log10 = _false_alarm(best.z, n_tests, best.search_weight) if best.pce != 0 else (1.0, 0.0)
    # every device that reaches the decision on its own: one is an attribution, several an ambiguity
    matches = tuple(c.device_id for c in candidates
                    if c.z > 0 and _false_alarm(c.z, n_tests, c.search_weight)[0] <= settings.pfa)
    decision = "unknown" if not matches else ("attributed" if len(matches) == 1 else "ambiguous")
    note = (f"{len(matches)} devices reach the decision ({', '.join(matches[:4])}): the image matches each of them "
            "(one sensor in the database twice, or a false alarm), so none is named") if len(matches) > 1 else None
    return QueryIdentification(
        source, query.shape, decision, best.device_id if decision == "attributed" else None,
        best, candidates[1] if len(candidates) > 1 else None, tuple(candidates[: settings.top_k]), p_fa, log10,
        pce_threshold(settings.pfa, n_tests / best.search_weight), int(n_tests), len(compatible), len(candidates),
        pre_info, scale_info, note, matches, shares.to_dict(settings.pfa))



# ----------------------------------------------------------------------------- the drivers


def _references(fingerprints: Any) -> tuple[tuple[_Reference, ...], list[dict[str, Any]]]:
    """The candidates (loaded once, here) from a database or from ``(id, Fingerprint)`` pairs."""
    pairs: list[tuple[Any, Fingerprint]]
    if hasattr(fingerprints, "entries") and hasattr(fingerprints, "load"):
        pairs = [(entry, fingerprints.load(entry.device_id)) for entry in fingerprints.entries()]
    else:
        pairs = []
        for item in fingerprints:
            try:
                ident, fp = item
            except (TypeError, ValueError):
                raise UsageError("fingerprints: give a FingerprintDatabase or (device id, Fingerprint) pairs") from None
            pairs.append((ident, fp))
    if not pairs:
        raise UsageError("no fingerprints to identify against; add some to the database first")
    refs, devices, seen = [], [], set()
    for ident, fp in pairs:
        device_id = str(getattr(ident, "device_id", ident))
        if device_id in seen:
            raise UsageError(f"device id {device_id!r} appears twice among the fingerprints")
        seen.add(device_id)
        if not isinstance(fp, Fingerprint):
            raise UsageError(f"{device_id}: {type(fp).__name__} is not a Fingerprint")
        check_fingerprint(fp, f"the fingerprint of device {device_id!r}")
        region = parse_region(fp.region)
        origin = None
        if region.kind != "corners":
            rows, cols = region.pieces(fp.frame_shape)[0]
            origin = (int(rows.start), int(cols.start))
        refs.append(_Reference(device_id, fp, region, origin))
        info = ident.to_dict() if hasattr(ident, "to_dict") else {"device_id": device_id}
        info = {k: v for k, v in info.items() if k != "provenance"}
        devices.append(info)
    return tuple(refs), devices



def _scale_search(scales: Any) -> ScaleSearch | None:
    if scales is None:
        return None
    if isinstance(scales, ScaleSearch):
        return scales
    if isinstance(scales, str):
        return ScaleSearch() if scales == "auto" else parse_scales(scales)
    if np.ndim(scales) == 0:
        return ScaleSearch(values=(float(scales),))
    return ScaleSearch(values=tuple(float(s) for s in scales))



def _query_items(queries: Any, executor: Executor) -> tuple[list[tuple[int, Any]], str | None]:
    name = None
    if hasattr(queries, "frames") and hasattr(queries, "root"):  # a Dataset
        name = str(queries.root)
        queries = queries.frames
    if isinstance(queries, (np.ndarray, str, os.PathLike)):
        raise UsageError("queries: give a sequence of images, paths or frames (or a Dataset), not a single one")
    items = list(enumerate(queries))
    if executor.backend != "in-process" and not all(_is_reference(p) for _, p in items):
        raise UsageError("identification on worker processes or a cluster reads every query from its file: give "
                         "image paths or dataset frames, not arrays (or use the in-process executor)")
    return items, name


def _check_options(top_k: int, pfa: float, rotations: Any, sigma: float) -> None:
    try:
        value = float(sigma)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"sigma={sigma!r}: the query residual's noise level must be a positive number (2 is usual)")
    if top_k < 1:
        raise UsageError(f"top_k={top_k}: list at least one candidate")
    if not (0.0 < pfa < 1.0):
        raise UsageError(f"pfa={pfa}: the false-alarm probability must be in (0, 1)")
    if isinstance(rotations, str) and rotations not in _ROTATION_MODES:
        raise UsageError(f"rotations={rotations!r}: choose one of {', '.join(_ROTATION_MODES)}, or give quarter turns")


def identify(
    queries: Iterable[Any],
    fingerprints: Any,
    *,
    top_k: int = 3,
    pfa: float = DEFAULT_PFA,
    rotations: str | int | Sequence[int] = "auto",
    scales: ScaleSearch | str | float | Sequence[float] | None = None,
    crop_search: bool = True,
    prescreen: Prescreen | str | bool | None = None,
    sigma: float = QUERY_SIGMA,
    exclusion: int = 11,
    workers: int | None = None,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    **query_options: Any,
) -> IdentificationResult:
    """Identify the device of each query image among a set of fingerprints (module notes).

    Parameters
    ----------
    queries : sequence or Dataset
        Image arrays, image paths or dataset frames (objects with ``load()``); on worker processes or a
        cluster, paths or frames (each worker reads its query).
    fingerprints : FingerprintDatabase or sequence of (id, Fingerprint)
        ``id`` a device id or a :class:`~forensics.prnu.database.DeviceEntry`; all are loaded once here.
    top_k : int
        Candidates listed per image.
    pfa : float
        False-alarm probability of an attribution, corrected for every fingerprint, position, scale and
        rotation searched (Šidák, module notes).
    rotations : {'auto', 'none', 'all'} or quarter turns
    scales : None, 'auto', 'LO:HI[:STEP]', ScaleSearch or scales
        None: scale 1 only; 'auto': :class:`ScaleSearch` over 0.5–1.0 with a grid error ≤ 0.5 pixel.
    crop_search : bool
        Search the offset of images smaller than the (resampled) frame.
    prescreen : None/'off', 'auto', 'on' or Prescreen
        'auto': on for more than :data:`PRESCREEN_AUTO_MIN` fingerprints.
    sigma, exclusion
        Query residual noise level (8-bit scale) and the PCE's exclusion window.
    workers : int, optional
        FFT and wavelet threads per query.
    executor : Executor, optional
        One work item per query; default in this process.
    progress : callable
        Counts queries.
    **query_options
        Passed to :func:`forensics.prnu.match.prepare_query` (white_level, black_level, ...).

    Returns
    -------
    IdentificationResult

    Raises
    ------
    UsageError
        Options out of range (``sigma`` not a positive number, ``pfa`` outside (0, 1), …).
    InputError
        A fingerprint holds no usable pattern (NaN, constant), a query cannot be read, or every query is
        content-free.
    """
    _check_options(top_k, pfa, rotations, sigma)
    search = _scale_search(scales)
    ex = resolve(executor)
    refs, devices = _references(fingerprints)
    pre = _prescreen_config(prescreen, len(refs))
    refs = _with_sketches(refs, pre)
    settings = _Settings(refs, int(top_k), float(pfa), rotations, search, bool(crop_search), pre, float(sigma),
                         int(exclusion), workers, dict(query_options))
    name = str(queries.root) if hasattr(queries, "frames") and hasattr(queries, "root") else None
    if ex.backend == "in-process" and not hasattr(queries, "__len__") and not hasattr(queries, "frames"):
        # an iterator of images: identified as it is consumed, never held as a list
        results = [_identify_item(settings, item) for item in progress(enumerate(queries), desc="identifying")]
    else:
        items, name = _query_items(queries, ex)
        results = list(ex.map(_identify_item, items, shared=settings, progress=progress, desc="identifying"))
    if results and all(q.decision == "excluded" for q in results):
        raise InputError(f"{name or 'the queries'}: every one of its {len(results)} image(s) is content-free, so none "
                         f"can be identified (first, {results[0].source}: {results[0].note}); give exposed images")
    return IdentificationResult(results, devices, float(pfa), _settings_dict(settings, prescreen), CORRECTION, name)


def _settings_dict(settings: _Settings, requested: Any) -> dict[str, Any]:
    return {"top_k": settings.top_k, "rotations": settings.rotations if isinstance(settings.rotations, str)
            else list(np.atleast_1d(settings.rotations).tolist()),
            "scales": settings.scales.to_dict() if settings.scales is not None else None,
            "crop_search": settings.crop_search,
            "prescreen": settings.prescreen.to_dict() if settings.prescreen is not None else None,
            "prescreen_requested": requested if isinstance(requested, (str, bool)) or requested is None else "custom",
            "prescreen_auto_min": PRESCREEN_AUTO_MIN, "sigma": settings.sigma, "exclusion": settings.exclusion}


# ----------------------------------------------------------------------------- measuring the pre-screen


def _rank_item(settings: _Settings, item: tuple[int, Any]) -> tuple[dict[str, float], bool]:
    """Work item of :func:`prescreen_miss_rate`: every aligned fingerprint's sketch score for one query."""
    index, payload = item
    image, source = _load_query(payload, index)
    query = _QueryImage(image, source, settings)
    plans = [_plan(query.shape, ref, settings.rotations, settings.scales, settings.crop_search)
             for ref in settings.refs]
    assert settings.prescreen is not None
    scores = _screen(query, settings.refs, plans, settings.prescreen.seed)
    return {settings.refs[j].device_id: s for j, s in scores.items()}, bool(scores)


def prescreen_miss_rate(
    queries: Iterable[Any],
    truth: Sequence[str | None],
    fingerprints: Any,
    prescreen: Prescreen | None = None,
    *,
    rotations: str | int | Sequence[int] = "auto",
    sigma: float = QUERY_SIGMA,
    executor: Executor | None = None,
    progress: Progress = no_progress,
    **query_options: Any,
) -> PrescreenMissRate:
    """How often the pre-screen drops the true device, on queries of known devices.

    Only the sketch stage runs (no full PCE).  Queries whose device is not among the fingerprints
    (``truth`` None or unknown) or that are not aligned (crops, other sizes) are skipped and counted.

    Parameters
    ----------
    queries : sequence or Dataset
        As :func:`identify`.
    truth : sequence of str or None
        The true device id of each query.
    fingerprints : FingerprintDatabase or sequence of (id, Fingerprint)
    prescreen : Prescreen, optional
        Default :class:`Prescreen` ``()``.

    Returns
    -------
    PrescreenMissRate
    """
    from forensics.stats.counts import clopper_pearson

    pre = prescreen or Prescreen()
    ex = resolve(executor)
    items, _ = _query_items(queries, ex)
    if len(truth) != len(items):
        raise UsageError(f"{len(truth)} true devices for {len(items)} queries; give one per query")
    refs, _ = _references(fingerprints)
    refs = _with_sketches(refs, pre)
    settings = _Settings(refs, 1, DEFAULT_PFA, rotations, None, False, pre, float(sigma), 11, None,
                         dict(query_options))
    keep = pre.keep_for(len(refs))
    ranks, scores, skipped = [], [], 0
    for (scored, aligned), device in zip(ex.map(_rank_item, items, shared=settings, progress=progress,
                                                desc="pre-screen"), truth):
        if not aligned or device is None or str(device) not in scored:
            skipped += 1
            continue
        own = scored[str(device)]
        ranks.append(sum(1 for v in scored.values() if v > own))
        scores.append(own)
    n = len(ranks)
    missed = sum(1 for r in ranks if r >= keep)
    ci = clopper_pearson(missed, n) if n else (0.0, 1.0)
    dims = {r.sketch.size for r in refs if r.sketch is not None}
    return PrescreenMissRate(n, missed, missed / n if n else math.nan, (float(ci[0]), float(ci[1])), keep,
                             min(dims) if dims else 0, len(refs), tuple(ranks), tuple(float(s) for s in scores),
                             skipped)
