"""Light frames that reached the check already dark-subtracted.

Capture software often subtracts a dark frame from every light frame it saves (CCDSoft's and MaxIm DL's
auto-dark): the flats of the 2017 STL-1001E series read, at their hottest pixels, what their neighbours read,
while 60 s darks of the same session show those pixels thousands of ADU above.  The check's model is a raw
sensor's, so in such frames it predicts a dark signal and hot-pixel offsets that are not there: the hot pixels
misfit, and the fit bends the PRNU, the DSNU and the nonlinearity to make up for it.  Nothing in the files says
so; the frames themselves do.

Per repeated condition with light, the pixels' excess over their scene estimate (the neighbours' reading) at the
pixels of largest predicted dark pattern (the fitted device's deviation from a typical pixel at zero light:
dark rate × exposure, DSNU, partially stuck offsets) is regressed through the origin on that pattern
(:func:`~forensics.stats.robust.origin_slope`): a raw frame carries 1 of it, a dark-subtracted frame 0.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from forensics.check.classes import STK
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel
from forensics.check.prediction import context
from forensics.stats.robust import origin_slope

#: Pixels of largest predicted dark pattern used per condition (as the fingerprint's dark calibration does).
PROBES = 256
#: A condition is named when its share of the pattern lies below one half by this many standard errors.
SHARE_Z = 3.0
#: Pixels closer than this fraction of the clip level are left out (clipped, nonlinear).
NEAR_CLIP = 0.9


@dataclass(frozen=True)
class PatternShare:
    """How much of the predicted dark pattern one light condition's frames carry."""

    label: str  #: the condition
    share: float  #: 1 for raw frames, 0 for dark-subtracted ones
    se: float  #: its standard error
    pixels: int  #: pixels it was measured at


def dark_pattern_shares(ev: Evidence, fitted: FittedModel) -> list[PatternShare]:
    """Per repeated light condition of a data set with dark frames, the share of the fitted model's dark
    pattern its frames carry (first half of the repeats, as fitted).  Empty when the model predicts no
    per-pixel dark pattern."""
    pixels, device = fitted.pixels, fitted.device
    if not ev.predictor.dark.any():
        return []
    typical = device.typical()
    zero = np.zeros(ev.shape)
    clip = ev.meas.clip_level
    out = []
    for r, g in enumerate(ev.rgroups):
        if ev.predictor.dark[r]:
            continue
        # the whole device's reading without light less a typical pixel's: defects' offsets included
        d = device.mean_signal(zero, context(device, g)) - typical.mean_signal(zero, context(typical, g))
        y = ev.meas.mean_a[r]
        use = ev.usable[r] & (pixels.classes[r] != STK) & (y < NEAR_CLIP * clip) & (d > 0)
        if not use.any():
            continue
        idx = np.flatnonzero(use)
        idx = idx[np.argsort(d.ravel()[idx])[-PROBES:]]
        excess = y.ravel()[idx] - pixels.scene_a[r].ravel()[idx]
        share, se = origin_slope(d.ravel()[idx], excess)
        if np.isfinite(share):
            out.append(PatternShare(g.label(), share, se, int(idx.size)))
    return out


def reduced_frame_warnings(shares: list[PatternShare]) -> list[str]:
    """The light conditions (of :func:`dark_pattern_shares`) whose frames carry clearly less than half the dark
    pattern the dark frames predict: dark-subtracted already, which a raw sensor's model cannot follow."""
    return [f"the frames of condition '{s.label}' carry {s.share:.2f} ± {s.se:.2f} of the dark pattern the dark "
            f"frames predict at their {s.pixels} hottest pixels (raw frames: 1): they look dark-subtracted "
            "already (a capture program's auto-dark?), which the model of a raw sensor cannot follow — give raw "
            "frames, or leave these out"
            for s in shares if s.share + SHARE_Z * s.se < 0.5]
