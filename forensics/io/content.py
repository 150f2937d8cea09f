"""Whether a frame holds anything a sensor left in it: content-free (constant, black or saturated) frames.

Pure functions on arrays, used wherever frames become statistics (fingerprints, queries, the same-device
protocol, the model check) so that a frame without content is refused or left out *before* any statistic
is reported, instead of being taken at face value.

What a frame must have
----------------------
A pixel tells something about the sensor only when it is *exposed*: strictly between the black level and
the saturation level.  At either level the value is clipped: it carries neither the pixel's noise nor its
photo-response (PRNU multiplies the light above the black level, so a pixel at the black level has
``I·K = 0``, and a saturated one has lost ``K`` in the clip — the fingerprint estimator gives both zero
weight), nor the offsets and gains the model check fits.  A colour pixel is exposed when none of its
channels is saturated and not all of them are at the black level.

A frame is **content-free** when

* it is constant (every pixel one value: no noise, no pattern, whatever the value), or
* fewer than :data:`MIN_EXPOSED` (1 %) of its pixels are exposed.

Why 1 %: every statistic built on frames — the PCE and NCC of a residual with a fingerprint, the EER of
the same-device protocol, the model check's per-condition moments — is a sum over pixels whose null
distribution assumes many comparable contributions.  When the only exposed pixels of a black (or white)
frame are a few defects, the sum is theirs alone: 30 hot pixels in an otherwise black 256 × 256 frame
gave PCE 6·10⁴ between a "fingerprint" of such frames and others like them, a match of defects, not of
PRNU, and not calibrated by the PCE's Gaussian null.  Defects are rare (hot and stuck pixels are 10⁻⁵ to
10⁻³ of a sensor's pixels, even after decades in the paper's presets), so 1 % of the frame is far above
any defect population, while natural photographs with large clipped areas (a night sky, blown
highlights: tens of per cent) keep their remaining pixels — 10⁴ and more in a one-megapixel frame, which
carry a usable pattern.  The threshold is deliberately lenient: it refuses frames without content, it
does not grade how much content a frame has (that is what the PCE does).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from forensics._shared.arrays import full_scale

__all__ = ["MIN_EXPOSED", "FrameContent", "content_problem", "frame_content"]

#: Smallest share of a frame's pixels that must be exposed (strictly between black and saturation).
MIN_EXPOSED = 0.01


@dataclass(frozen=True)
class FrameContent:
    """How much of a frame is exposed, black or saturated (shares of its pixels), and whether it is constant.

    ``black`` and ``saturated`` may overlap only for colour pixels with a channel at each level (counted as
    saturated); ``exposed + black + saturated = 1`` for grey frames.
    """

    exposed: float
    black: float
    saturated: float
    constant: bool
    black_level: float
    saturation_level: float
    value: float | None = None  #: the value of a constant frame

    def problem(self, min_exposed: float = MIN_EXPOSED) -> str | None:
        """Why the frame is content-free (one phrase), or None when it has content."""
        if self.constant:
            what = (" (all black)" if self.black == 1.0 else " (all saturated)" if self.saturated == 1.0 else "")
            return f"constant: every pixel is {self.value:g}{what}, so it holds no noise and no pattern"
        if self.exposed < min_exposed:
            where = "black" if self.black >= self.saturated else "saturated"
            return (f"only {_share(self.exposed)} of its pixels lie strictly between the black level "
                    f"{self.black_level:g} and the saturation level {self.saturation_level:g} ({_share(self.black)} "
                    f"black, {_share(self.saturated)} saturated): mostly {where}, at least {_share(min_exposed)} "
                    "exposed is needed")
        return None


def _share(x: float) -> str:
    return f"{100 * x:.4g} %"


def frame_content(frame: np.ndarray | Sequence[np.ndarray], black_level: float | np.ndarray = 0.0,
                  saturation_level: float | None = None) -> FrameContent:
    """The exposed, black and saturated shares of a frame's pixels (module notes).

    Parameters
    ----------
    frame : ndarray, (H, W) or (H, W, C), or a sequence of them
        Any pixel type; not modified.  A sequence is the pieces of one frame (e.g. a fingerprint's four
        corner patches), counted together.
    black_level : float or ndarray
        A pixel at or below it is black (an array broadcastable to each piece's (H, W), e.g. a tiled 2×2 CFA
        pattern).
    saturation_level : float, optional
        A pixel at or above it is saturated; default the pixel type's full scale.

    Returns
    -------
    FrameContent
    """
    pieces = [np.asarray(frame)] if isinstance(frame, np.ndarray) else [np.asarray(p) for p in frame]
    sat = full_scale(pieces[0].dtype) if saturation_level is None else float(saturation_level)
    black = np.asarray(black_level, dtype=np.float64)
    floor = float(black) if black.ndim == 0 else black
    n = n_sat = n_dark = 0
    lo, hi = math.inf, -math.inf
    for a in pieces:
        if a.size == 0:
            continue
        n += a.shape[0] * a.shape[1]
        lo, hi = min(lo, float(a.min())), max(hi, float(a.max()))
        # a colour pixel is saturated if any channel is, black if every channel is: both from its largest channel
        top = a.max(axis=2) if a.ndim == 3 else a
        saturated = top >= sat
        dark = top <= floor
        dark &= ~saturated
        n_sat += int(np.count_nonzero(saturated))
        n_dark += int(np.count_nonzero(dark))
    if n == 0:
        return FrameContent(0.0, 0.0, 0.0, True, float(np.mean(black)), sat, None)
    return FrameContent((n - n_sat - n_dark) / n, n_dark / n, n_sat / n, lo == hi, float(np.mean(black)), sat,
                        lo if lo == hi else None)


def content_problem(frame: np.ndarray | Sequence[np.ndarray], black_level: float | np.ndarray = 0.0, saturation_level: float | None = None,
                    min_exposed: float = MIN_EXPOSED) -> str | None:
    """Why ``frame`` is content-free (one phrase), or None when it has content (:func:`frame_content`)."""
    return frame_content(frame, black_level, saturation_level).problem(min_exposed)
