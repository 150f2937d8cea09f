"""Robust fits shared by the domains."""
from __future__ import annotations

import math

import numpy as np


def origin_slope(predicted: np.ndarray, observed: np.ndarray) -> tuple[float, float]:
    """The least-squares slope of ``observed`` on ``predicted`` through the origin, and its standard error from
    the robust scatter about the line (1.4826·MAD of the residuals over √Σ predicted²).

    How much of a predicted pattern some data carry: 1 where they carry all of it, 0 where none (a frame already
    dark-subtracted against the dark pattern its darks predict).  The robust scatter keeps a few outliers (a
    cosmic-ray hit, a pixel the prediction misses) from widening the interval.  ``(nan, inf)`` without data or
    without a pattern.

    Examples
    --------
    >>> import numpy as np
    >>> slope, se = origin_slope(np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.5, 1.0, 1.5, 2.0]))
    >>> round(slope, 6), se
    (0.5, 0.0)
    """
    p = np.asarray(predicted, np.float64).ravel()
    o = np.asarray(observed, np.float64).ravel()
    ss = float(np.dot(p, p))
    if p.size == 0 or ss <= 0:
        return math.nan, math.inf
    slope = float(np.dot(p, o) / ss)
    resid = o - slope * p
    sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    return slope, sigma / math.sqrt(ss)
