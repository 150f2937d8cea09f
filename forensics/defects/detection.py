"""Defect detection from ordinary images (reference paper, section 3.2, eq. 11–15).

One streaming pass over K images of one device (:func:`forensics.io.stack.stack_stats`)
gives the per-pixel mean ȳ, minimum, maximum and variance.  Then

* **stuck** pixels (eq. 11): the same value in all K images, ``max − min ≤ tolerance``
  (tolerance 0 by default; raise it for compressed or noisy data), while the
  neighbourhood does vary (a constant patch — clipping, a black border — is not
  a defect);
* **partially stuck** pixels (eq. 15): d̂ = ȳ − median_q(ȳ) > τ, where τ comes
  from a robust normal fit of d̂ over the analysed region (median and
  1.4826·MAD; ``center + sigma·scale`` with sigma = 5 by default) or is given.

The region analysed is a mask (always without the q//2 border, where the
mirrored median is biased by any gradient): by default the centre of the frame (where the
subject usually is, so where the mean image is textured) is left out, as in the
paper's fig. 2; alternatively a user's mask image, every pixel, or an automatic
mask that leaves out pixels whose local texture (local mean |d̂|) is high.
Raw CFA mosaics are analysed per colour channel (each 2×2 sub-lattice has its
own median, fit and threshold); colour images are averaged over channels.

The q×q median is exact: :func:`median_filter` evaluates a comparator network
(sorted columns shared between rows, merged sorted column groups shared between
columns, pruned to the one rank needed) with NumPy on cache-sized tiles — about
ten times faster than :func:`scipy.ndimage.median_filter` at q = 9, identical
output (scipy's ``mode='reflect'`` boundary).
"""
from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from forensics._shared.arrays import full_scale, grey_mean
from forensics._shared.errors import InputError, UsageError
from forensics._shared.filters import NETWORK_MAX_Q, median_filter
from forensics._shared.limits import require_memory
from forensics.sensor.catalogue import KIND_NAMES, PARTIAL, STUCK
from forensics._shared.progress import Progress, no_progress
from forensics.io.stack import StackStats, prefetch, stack_sets  # noqa: F401  (prefetch: kept importable from here)
from forensics.stats.tails import norm_sf

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

DEFAULT_Q = 9
DEFAULT_SIGMA = 5.0
DEFAULT_CENTRE_FRACTION = 0.5
MIN_IMAGES = 10
MAD_TO_SIGMA = 1.4826
#: Above this fraction of constant pixels the stuck test is meaningless (static scenes) and is not applied.
MAX_CONSTANT_FRACTION = 0.01
#: Working memory of :func:`detect_datasets` per pixel: peak RSS measured on 16-bit sets of 2048×1024 and
#: 2048×2048 (grey 69–80 bytes, RGB 1024×1024 175 bytes; about 10 more per further set, whose results are kept).
BYTES_PER_PIXEL_CHANNEL = 56
BYTES_PER_PIXEL = 24
BYTES_PER_PIXEL_SET = 12
#: scipy's median for q > NETWORK_MAX_Q holds a boolean footprint and an int64 offset per window element.
BYTES_PER_WINDOW_ELEMENT = 9


# =========================================================================== masks
@dataclass(frozen=True)
class MaskSpec:
    """Which pixels are analysed.

    ``kind``: ``'centre'`` (leave out a centred rectangle whose sides are
    ``fraction`` of the frame's — where the subject usually is), ``'auto'``
    (leave out pixels whose local texture is high), ``'all'`` or ``'file'``
    (a mask image: non-zero = analysed).
    """

    kind: str = "centre"
    fraction: float = DEFAULT_CENTRE_FRACTION
    path: str | None = None
    window: int = 15
    factor: float = 3.0

    def describe(self) -> str:
        if self.kind == "centre":
            return f"centre left out ({self.fraction:g} of width and height)"
        if self.kind == "auto":
            return f"automatic: textured pixels left out (local mean |d̂| over {self.window}×{self.window} > {self.factor:g}× its median)"
        if self.kind == "file":
            return f"mask image {self.path}"
        return "every pixel"

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "fraction": self.fraction, "path": self.path, "window": self.window,
                "factor": self.factor}

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> "MaskSpec":
        return cls(**{k: obj[k] for k in ("kind", "fraction", "path", "window", "factor") if k in obj})


def parse_mask(text: str | None) -> MaskSpec:
    """``centre``, ``centre:0.6``, ``auto``, ``all`` or a path to a mask image."""
    if text is None or text == "":
        return MaskSpec()
    low = text.lower()
    if low in ("centre", "center") or low.startswith(("centre:", "center:")):
        if ":" not in low:
            return MaskSpec("centre")
        try:
            frac = float(low.split(":", 1)[1])
        except ValueError:
            raise UsageError(f"--mask '{text}': give centre:FRACTION with a number, e.g. centre:0.5") from None
        if not 0.0 <= frac < 1.0:
            raise UsageError(f"--mask '{text}': the centre fraction must be in [0, 1)")
        return MaskSpec("centre", frac)
    if low == "auto":
        return MaskSpec("auto")
    if low in ("all", "none"):
        return MaskSpec("all")
    if not Path(text).is_file():
        raise InputError(f"--mask '{text}': no such mask image; give centre[:FRACTION], auto, all or a mask file")
    return MaskSpec("file", path=str(text))


def centre_mask(shape: tuple[int, int], fraction: float) -> np.ndarray:
    """True outside a centred rectangle whose sides are ``fraction`` of the frame's."""
    h, w = shape
    mask = np.ones((h, w), bool)
    ch, cw = int(round(h * fraction)), int(round(w * fraction))
    if ch and cw:
        y0, x0 = (h - ch) // 2, (w - cw) // 2
        mask[y0:y0 + ch, x0:x0 + cw] = False
    return mask


def texture_mask(d_hat: np.ndarray, window: int = 15, factor: float = 3.0) -> np.ndarray:
    """True where the local mean of |d̂| is at most ``factor`` times its image-wide median.

    A single defect moves a window's mean by 1/window² of its amplitude, so
    isolated defects stay inside; edges and texture in the mean image leave.
    """
    local = ndimage.uniform_filter(np.abs(d_hat).astype(np.float32), window, mode="reflect")
    return local <= factor * max(float(np.median(local)), np.finfo(np.float32).tiny)


def load_mask(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """A mask image as booleans (non-zero = analysed); must match the frames' size."""
    from forensics.io.images import read_image

    img = read_image(path)
    if img.ndim == 3:
        img = img.max(axis=2)
    if img.shape != tuple(shape):
        raise InputError(f"{path}: mask is {img.shape[1]}×{img.shape[0]} but the images are {shape[1]}×{shape[0]}")
    return img > 0


# =========================================================================== detection
@dataclass
class ChannelFit:
    """Robust normal fit of d̂ on one channel and the threshold derived from it."""

    name: str
    center: float
    scale: float
    tau: float
    n_pixels: int

    def to_dict(self) -> dict[str, Any]:
        return {"channel": self.name, "center": self.center, "scale": self.scale, "tau": self.tau,
                "n_pixels": self.n_pixels}


@dataclass
class DetectionResult:
    """Defects found in one stack of images.

    Array attributes (x, y, kind, amplitude, z, channel) hold one entry per
    defect: kind is :data:`~forensics.sensor.model.PARTIAL` or
    :data:`~forensics.sensor.model.STUCK`; amplitude is d̂ (DN) for partially stuck
    pixels and the stuck value c for stuck ones; z is (d̂ − center)/scale.
    ``d_hat`` and ``mask`` are image-sized and not serialised.
    """

    shape: tuple[int, int]
    n_images: int
    q: int
    sigma: float | None
    tau_given: float | None
    stuck_tolerance: float
    mask_spec: MaskSpec
    n_analysed: int
    fits: list[ChannelFit]
    x: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    amplitude: np.ndarray
    z: np.ndarray
    channel: np.ndarray
    hist_thresholds: np.ndarray
    hist_counts: np.ndarray
    hist_expected: np.ndarray
    cfa: str | None = None
    warnings: list[str] = field(default_factory=list)
    d_hat: np.ndarray | None = field(default=None, repr=False)
    mask: np.ndarray | None = field(default=None, repr=False)
    full_scale: float | None = None
    _sites: dict[Any, set[tuple[int, int]]] = field(default_factory=dict, repr=False)

    @property
    def megapixels(self) -> float:
        """Area analysed (megapixels): the denominator of every rate."""
        return self.n_analysed / 1e6

    def count(self, kind: int | None = None) -> int:
        return int(len(self.x) if kind is None else np.sum(self.kind == kind))

    def sites(self, kind: int | None = None) -> set[tuple[int, int]]:
        """The (x, y) sites of the defects (of one kind)."""
        if kind not in self._sites:
            sel = np.ones(len(self.x), bool) if kind is None else self.kind == kind
            self._sites[kind] = set(zip(self.x[sel].tolist(), self.y[sel].tolist()))
        return self._sites[kind]

    def amplitudes(self) -> dict[tuple[int, int], float]:
        """Amplitude by site."""
        return dict(zip(zip(self.x.tolist(), self.y.tolist()), self.amplitude.tolist()))

    @property
    def tau(self) -> float:
        """The threshold (DN) of the first channel (grey images have one)."""
        return self.fits[0].tau

    def threshold_dict(self) -> dict[str, Any]:
        """How the threshold was set: sigma or a given τ, τ per channel, q, mask."""
        return {"sigma": self.sigma, "tau_given": self.tau_given, "tau": [f.tau for f in self.fits] if len(self.fits) > 1
                else self.fits[0].tau, "q": self.q, "mask": self.mask_spec.describe(),
                "stuck_tolerance": self.stuck_tolerance, "analysed_megapixels": self.megapixels}

    def detection_settings(self) -> dict[str, Any]:
        """The settings that repeat this detection on another set (kept in a growth model for dating)."""
        return {"q": self.q, "sigma": self.sigma, "tau": self.tau_given, "mask": self.mask_spec.to_dict(),
                "stuck_tolerance": self.stuck_tolerance}

    def defect_rows(self) -> list[dict[str, Any]]:
        names = [f.name for f in self.fits]
        rows = []
        for i in range(len(self.x)):
            row = {"x": int(self.x[i]), "y": int(self.y[i]), "kind": KIND_NAMES[int(self.kind[i])],
                   "amplitude": float(self.amplitude[i]), "z": float(self.z[i])}
            if self.cfa:
                row["channel"] = names[int(self.channel[i])]
            rows.append(row)
        return rows

    def to_dict(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "n_images": self.n_images, "threshold": self.threshold_dict(),
                "fits": [f.to_dict() for f in self.fits], "cfa": self.cfa,
                "counts": {"partial": self.count(PARTIAL), "stuck": self.count(STUCK)},
                "defects": self.defect_rows(),
                "accumulated_histogram": {"threshold": self.hist_thresholds.tolist(),
                                          "pixels_above": self.hist_counts.tolist(),
                                          "expected_normal": self.hist_expected.tolist()},
                "warnings": list(self.warnings)}


#: The robust fit uses at most this many values (an evenly strided subsample beyond).
FIT_MAX_VALUES = 4_000_000


def robust_normal(values: np.ndarray) -> tuple[float, float]:
    """Median and 1.4826·MAD: the centre and σ of a normal fitted to the bulk, ignoring outliers.

    Beyond :data:`FIT_MAX_VALUES` values an evenly strided subsample is used
    (its sampling error, ~1e-3 σ, is far below anything that matters here).
    """
    values = np.asarray(values, np.float32).ravel()
    if values.size == 0:
        raise InputError("no pixels left to fit the noise of d̂; use a smaller --mask or more of the frame")
    if values.size > FIT_MAX_VALUES:
        values = values[:: -(-values.size // FIT_MAX_VALUES)]
    center = float(np.median(values))
    scale = MAD_TO_SIGMA * float(np.median(np.abs(values - np.float32(center))))
    return center, scale


def accumulated_histogram(values: np.ndarray, center: float, scale: float, top: float | None = None,
                          points: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Number of values above each threshold x (x from the centre to the largest value), and the normal expectation.

    Returns ``(thresholds, counts, expected)`` where ``expected = N·P(Z > (x − center)/scale)``.
    """
    values = np.asarray(values, np.float32).ravel()
    hi = float(values.max()) if top is None else top
    hi = max(hi, center + 10 * max(scale, 1e-12))
    edges = np.linspace(center, hi, points)
    # uniform bins (NumPy's fast path); bin i holds (edges[i], edges[i+1]]; the last edge collects the rest
    hist, _ = np.histogram(values, bins=points - 1, range=(center, hi))
    above_top = int(np.count_nonzero(values > hi))
    counts = np.cumsum(np.concatenate([hist, [above_top]])[::-1])[::-1]
    counts[0] = np.count_nonzero(values > center)
    expected = values.size * norm_sf((edges - center) / max(scale, 1e-12))
    return edges, counts.astype(np.int64), expected


def _constant(stats_: StackStats, tolerance: float) -> np.ndarray:
    if tolerance <= 0:
        const = stats_.maximum == stats_.minimum
    else:
        const = (stats_.maximum.astype(np.float64) - stats_.minimum.astype(np.float64)) <= tolerance
    return const.all(axis=2) if const.ndim == 3 else const


def _constant_neighbours(const: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """For each True of ``candidates``, how many of its 8 neighbours are constant (image-sized int array)."""
    ys, xs = np.nonzero(candidates)
    out = np.zeros(const.shape, np.int16)
    if len(ys) > 200_000:
        full = ndimage.uniform_filter(const.astype(np.float32), 3, mode="nearest") * 9 - const
        out[ys, xs] = np.rint(full[ys, xs]).astype(np.int16)
        return out
    padded = np.pad(const, 1, mode="edge")
    count = np.zeros(len(ys), np.int16)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                count += padded[ys + 1 + dy, xs + 1 + dx]
    out[ys, xs] = count
    return out


def _lattices(shape: tuple[int, int], cfa: str | None) -> list[tuple[str, tuple[slice, slice]]]:
    if not cfa:
        return [("grey", (slice(None), slice(None)))]
    if len(cfa) != 4:
        raise InputError(f"CFA pattern '{cfa}' must name the 4 positions of the 2×2 cell, e.g. RGGB")
    names = []
    for i, c in enumerate(cfa):
        label = c + (str(cfa[:i].count(c) + 1) if cfa.count(c) > 1 else "")
        names.append((label, (slice(i // 2, None, 2), slice(i % 2, None, 2))))
    return names


def expected_false_alarms(n_pixels: int, sigma: float) -> float:
    """False partially-stuck alarms expected among ``n_pixels`` at a threshold of ``sigma`` under the normal model."""
    return float(n_pixels * norm_sf(sigma))


def detect(stack: StackStats, q: int = DEFAULT_Q, sigma: float | None = DEFAULT_SIGMA, tau: float | None = None,
           mask: MaskSpec | np.ndarray | None = None, stuck_tolerance: float = 0.0, cfa: str | None = None,
           full_scale: float | None = None, threads: int | None = None, keep_images: bool = True) -> DetectionResult:
    """Detect stuck (eq. 11) and partially stuck (eq. 15, d̂ > τ) pixels from stack statistics.

    Parameters
    ----------
    stack
        Statistics of K images of one device (:func:`forensics.io.stack.stack_stats`).
    q
        Median kernel size (odd).
    sigma, tau
        Threshold: ``center + sigma·scale`` of the robust normal fit of d̂, or the
        given τ in DN (``tau`` wins when both are given).
    mask
        A :class:`MaskSpec` (default: centre left out) or a boolean image (True = analysed).
    stuck_tolerance
        Largest ``max − min`` (DN) still counted as "the same value in all K images".
    cfa
        CFA pattern (e.g. ``"RGGB"``) when the images are raw mosaics: each 2×2
        sub-lattice is filtered, fitted and thresholded on its own.
    full_scale
        Saturation value of the data (for reports; optional).

    Returns
    -------
    DetectionResult
    """
    if tau is None and (sigma is None or sigma <= 0):
        raise UsageError("give a positive --sigma or a threshold --tau")
    mean = grey_mean(stack.mean)
    shape = mean.shape
    if cfa and (shape[0] % 2 or shape[1] % 2):
        shape_note = f"{shape[1]}×{shape[0]}"
        raise InputError(f"a raw mosaic of odd size ({shape_note}) cannot be split into 2×2 CFA cells")
    const = _constant(stack, stuck_tolerance)
    d_hat = np.empty(shape, np.float32)
    lattices = _lattices(shape, cfa)
    for _, (sy, sx) in lattices:
        sub = np.ascontiguousarray(mean[sy, sx])
        d_hat[sy, sx] = sub - median_filter(sub, q, threads=threads)
    if isinstance(mask, np.ndarray):
        if mask.shape != shape:
            raise InputError(f"mask of shape {mask.shape} does not match the images' {shape}")
        region, spec = mask.astype(bool), MaskSpec("file", path="(array)")
    else:
        spec = mask or MaskSpec()
        if spec.kind == "centre":
            region = centre_mask(shape, spec.fraction)
        elif spec.kind == "auto":
            region = texture_mask(d_hat, spec.window, spec.factor)
        elif spec.kind == "file":
            region = load_mask(spec.path, shape)  # type: ignore[arg-type]
        else:
            region = np.ones(shape, bool)
    # the median is ill-defined within q//2 of the edge (mirrored neighbourhoods bias d̂ on any gradient)
    edge = (q // 2) * (2 if cfa else 1)
    if edge:
        region = region.copy()
        region[:edge] = region[-edge:] = False
        region[:, :edge] = region[:, -edge:] = False
    # stuck: constant over K images while at most 2 of the 8 neighbours are (a clipped patch is no defect)
    candidates = const & region
    constant_fraction = float(candidates.sum()) / max(int(region.sum()), 1)
    if constant_fraction > MAX_CONSTANT_FRACTION:
        stuck = np.zeros(shape, bool)
    else:
        stuck = candidates & (_constant_neighbours(const, candidates) <= 2)
    fits = []
    above = np.zeros(shape, bool)
    all_values = []
    for index, (name, (sy, sx)) in enumerate(lattices):
        sub_region = region[sy, sx] & ~stuck[sy, sx]
        values = d_hat[sy, sx][sub_region]
        center, scale = robust_normal(values)
        if scale <= 0:
            scale = float(np.std(values)) or 1e-6
        threshold = float(tau) if tau is not None else center + float(sigma) * scale  # type: ignore[arg-type]
        fits.append(ChannelFit(name, center, scale, threshold, int(values.size)))
        above[sy, sx] = (d_hat[sy, sx] > threshold) & sub_region
        all_values.append(values if len(lattices) == 1 else
                          (values - np.float32(center)) / np.float32(scale) * np.float32(fits[0].scale)
                          + np.float32(fits[0].center))
    partial = above & ~stuck
    ys, xs = np.nonzero(partial | stuck)
    kind = np.where(stuck[ys, xs], STUCK, PARTIAL).astype(np.int8)
    amplitude = np.where(kind == STUCK, mean[ys, xs], d_hat[ys, xs]).astype(np.float64)
    channel = np.zeros(len(xs), np.int8)
    if cfa:
        channel = ((ys % 2) * 2 + (xs % 2)).astype(np.int8)
    centers = np.array([f.center for f in fits])[channel]
    scales = np.array([f.scale for f in fits])[channel]
    z_sites = (d_hat[ys, xs].astype(np.float64) - centers) / scales
    # accumulated histogram in DN of the first channel's scale (all channels pooled in σ units)
    pooled = np.concatenate(all_values) if len(all_values) > 1 else all_values[0]
    c0, s0 = fits[0].center, fits[0].scale
    hist_x, hist_n, hist_e = accumulated_histogram(pooled, c0, s0)
    n_analysed = int(region.sum())
    result = DetectionResult(shape=shape, n_images=stack.n, q=q, sigma=None if tau is not None else sigma,
                             tau_given=tau, stuck_tolerance=stuck_tolerance, mask_spec=spec, n_analysed=n_analysed,
                             fits=fits, x=xs.astype(np.int64), y=ys.astype(np.int64), kind=kind, amplitude=amplitude,
                             z=z_sites, channel=channel, hist_thresholds=hist_x,
                             hist_counts=hist_n, hist_expected=hist_e, cfa=cfa, full_scale=full_scale)
    if constant_fraction > MAX_CONSTANT_FRACTION:
        result.warnings.append(
            f"{constant_fraction:.1%} of the analysed pixels kept one value (within {stuck_tolerance:g} DN) over all "
            f"{stack.n} images: the scenes are too alike (flat fields, a static view) or the tolerance is too large, "
            "so the stuck test cannot tell stuck pixels from static content; no stuck pixels are reported")
    if stack.n < MIN_IMAGES:
        eff_sigma = sigma if tau is None else (tau - c0) / s0
        fa = expected_false_alarms(sum(f.n_pixels for f in fits), float(eff_sigma))  # type: ignore[arg-type]
        result.warnings.append(
            f"only {stack.n} images (fewer than {MIN_IMAGES}): the mean still shows the scenes, so d̂ is far from "
            f"normal; even under the normal model about {fa:.2g} false partially-stuck alarms are expected among "
            f"{sum(f.n_pixels for f in fits)} pixels at {eff_sigma:.3g}σ, and pixels that happen to repeat a value "
            f"{stack.n} times pass the stuck test; use at least {MIN_IMAGES} (better ≥ 50) images")
    if keep_images:
        result.d_hat, result.mask = d_hat, region
    return result


# =========================================================================== streaming from a dataset
def dataset_cfa(ds: Any) -> str | None:
    """The CFA pattern when the dataset's frames are raw mosaics, else None."""
    from forensics.io.images import is_raw, read_raw

    if ds.frames and is_raw(ds.frames[0].path):
        return read_raw(ds.frames[0].path).cfa_pattern
    return None


def stack_dataset(ds: Any, progress: Progress = no_progress, desc: str = "reading",
                  executor: Executor | None = None) -> StackStats:
    """Stream a dataset once into :class:`StackStats` (chunks of frames on ``executor``; in-process by default)."""
    (stack,) = stack_datasets([ds], progress, desc, executor)
    return stack


def stack_datasets(datasets: Sequence[Any], progress: Progress = no_progress, desc: str = "reading",
                   executor: Executor | None = None) -> Iterator[StackStats]:
    """Each dataset's :class:`StackStats`, yielded in order as soon as it is complete.

    Every (dataset, chunk of frames) pair is one work item of ``executor``
    (:func:`forensics.io.stack.stack_sets`), so several sets keep every worker busy.
    """
    for ds in datasets:
        if len(ds) == 0:
            raise InputError(f"{ds.root}: no images")
    return stack_sets([[frame.path for frame in ds.frames] for ds in datasets], executor, progress, desc)


def detect_dataset(ds: Any, q: int = DEFAULT_Q, sigma: float | None = DEFAULT_SIGMA, tau: float | None = None,
                   mask: MaskSpec | None = None, stuck_tolerance: float = 0.0, progress: Progress = no_progress,
                   threads: int | None = None, executor: Executor | None = None) -> DetectionResult:
    """:func:`detect` on a dataset folder's images (one streaming pass; raw mosaics per CFA channel)."""
    (result,) = detect_datasets([ds], q=q, sigma=sigma, tau=tau, mask=mask, stuck_tolerance=stuck_tolerance,
                                progress=progress, threads=threads, executor=executor)
    return result


def detect_datasets(datasets: Sequence[Any], q: int = DEFAULT_Q, sigma: float | None = DEFAULT_SIGMA,
                    tau: float | None = None, mask: MaskSpec | None = None, stuck_tolerance: float = 0.0,
                    progress: Progress = no_progress, threads: int | None = None,
                    executor: Executor | None = None) -> list[DetectionResult]:
    """:func:`detect_dataset` on several datasets with one setting, their frames read on ``executor``.

    The stack statistics of all sets are one list of work items (one progress bar); each set is detected
    here as soon as its statistics are complete, while the workers read the following sets.
    """
    for ds in datasets:
        if len(ds) == 0:
            raise InputError(f"{ds.root}: no images")
        ds.shape()  # one size, or a clear error naming the odd file
    cfas = [dataset_cfa(ds) for ds in datasets]
    check_request([ds.shape() for ds in datasets], q, cfa=any(cfas))  # before the pass over the images
    results = []
    for ds, cfa, stack in zip(datasets, cfas, stack_datasets(datasets, progress, executor=executor)):
        results.append(detect(stack, q=q, sigma=sigma, tau=tau, mask=mask, stuck_tolerance=stuck_tolerance,
                              cfa=cfa, full_scale=full_scale(stack.minimum.dtype), threads=threads))
    return results


def check_request(shapes: Sequence[tuple[int, ...]], q: int, cfa: bool = False) -> None:
    """Refuse, before any image is read, a detection that cannot work or would not fit in memory.

    ``shapes`` are the frame shapes of the sets (from their headers), ``q`` the median kernel size; ``cfa``
    true when the frames are raw mosaics (each 2×2 sub-lattice is filtered on its own).

    Raises
    ------
    UsageError
        ``q`` not odd and ≥ 1; a window whose border (left out of the analysis) covers the whole frame; or a
        memory estimate (:data:`BYTES_PER_PIXEL_CHANNEL` …) above :func:`~forensics._shared.limits.memory_limit`.
    """
    if q < 1 or q % 2 == 0:
        raise UsageError(f"--q {q}: the median kernel size must be odd and at least 1 (the paper's is 9)")
    h = min(s[0] for s in shapes)
    w = min(s[1] for s in shapes)
    edge = (q // 2) * (2 if cfa else 1)
    if 2 * edge >= min(h, w):
        raise UsageError(f"--q {q}: the median window's border ({edge} pixels on every side, left out of the "
                         f"analysis) covers the whole {w}×{h} frame; give a smaller odd q (the paper's is 9)")
    pixels = max(s[0] * s[1] for s in shapes)
    channels = max(s[2] if len(s) == 3 else 1 for s in shapes)
    nbytes = (BYTES_PER_PIXEL_CHANNEL * channels + BYTES_PER_PIXEL + BYTES_PER_PIXEL_SET * (len(shapes) - 1)) * pixels
    if q > NETWORK_MAX_Q:
        nbytes += BYTES_PER_WINDOW_ELEMENT * q * q
    require_memory(nbytes, f"defect detection on {len(shapes)} set(s) of {w}×{h} images with q = {q}")
