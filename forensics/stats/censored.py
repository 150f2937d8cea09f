"""Moments of a normal variable clipped to an interval, continuous and as a quantised readout.

:func:`clipped_normal_moments` — y = clip(x, lo, hi), x ~ N(μ, σ²): mean and variance in closed form
(the censored normal: atoms at the bounds carry the tails' mass).

:func:`readout_moments` — the quantised readout of a sensor, y = rint(clip(x, lo, hi)) with integer bounds,
computed exactly from the probabilities of the integer levels (no Sheppard approximation, which fails near a
bound and for σ below ~1 DN).  Far from the bounds it equals μ and σ² + 1/12 (the rounding variance); at a
bound the rounding variance vanishes with the mass that sits on the atom.  With ``truncate=True`` it gives
the moments conditional on lo < y < hi (what remains when pixels that touched a bound are set aside).  With
``dither=d`` the converter adds a uniform draw of width d DN before rounding (EMVA 1288's reference simulator:
d = 1): y = rint(clip(x + u, lo, hi)), u ~ U(−d/2, d/2), whose level probabilities are those of the Gaussian
smoothed by the box (:func:`_edge_probabilities`).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.special import erfcx, ndtr

_SQRT2PI = math.sqrt(2.0 * math.pi)
_SQRT2 = math.sqrt(2.0)
_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)


def _phi(z: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return np.where(np.isfinite(z), np.exp(-0.5 * z * z) / _SQRT2PI, 0.0)


def _mass_between(za: np.ndarray, zb: np.ndarray) -> np.ndarray:
    """Φ(zb) − Φ(za) without cancellation in either tail."""
    return np.where(za > 0, ndtr(-za) - ndtr(-zb), ndtr(zb) - ndtr(za))


def _partial_tail(a: np.ndarray) -> np.ndarray:
    """L(a) = G(−a) for a ≥ 0, where G(t) = ∫₋∞ᵗ Φ(s) ds = t·Φ(t) + φ(t): φ(a)·(1 − a·R(a)) with Mills' ratio
    R(a) = √(π/2)·erfcx(a/√2), accurate where both terms of G nearly cancel.  G(t) = L(|t|) + max(t, 0)."""
    return _phi(a) * (1.0 - a * _SQRT_HALF_PI * erfcx(a / _SQRT2))


def _edge_probabilities(edges: np.ndarray, mu: np.ndarray, sigma: np.ndarray,
                        dither: float) -> tuple[np.ndarray, np.ndarray]:
    """P(w < e) and P(w > e) at ``edges`` e for w = x + u, x ~ N(μ, σ²), u ~ U(−d/2, d/2) (d = ``dither``;
    d = 0: Φ(z) and Φ(−z)).  ∫ Φ((e − u − μ)/σ) du/d over the box is (σ/d)·[G(t₊) − G(t₋)] with
    t± = (e ± d/2 − μ)/σ; the upper tail the same mirrored, (σ/d)·[G(−t₋) − G(−t₊)].  Both come from L at |t±|
    (:func:`_partial_tail`), so that neither tail is a difference from 1; with d = 1 DN and edges a whole DN apart
    (a row of levels' edges) an edge's t₊ is the next one's t₋, and each L is computed once."""
    if dither <= 0:
        z = (edges - mu) / sigma
        return ndtr(z), ndtr(-z)
    t_hi = (edges + 0.5 * dither - mu) / sigma
    t_lo = (edges - 0.5 * dither - mu) / sigma
    l_hi = _partial_tail(np.abs(t_hi))
    if dither == 1.0 and edges.ndim == 2 and edges.shape[1] > 1 and np.all(np.diff(edges[:1], axis=1) == 1.0):
        l_lo = np.empty_like(l_hi)
        l_lo[:, 1:] = l_hi[:, :-1]  # (edges + ½) of one column is (edges − ½) of the next, bit for bit
        l_lo[:, :1] = _partial_tail(np.abs(t_lo[:, :1]))
    else:
        l_lo = _partial_tail(np.abs(t_lo))
    scale = sigma / dither
    lower = scale * (l_hi + np.maximum(t_hi, 0.0) - l_lo - np.maximum(t_lo, 0.0))
    upper = scale * (l_lo + np.maximum(-t_lo, 0.0) - l_hi - np.maximum(-t_hi, 0.0))
    return lower, upper


def clipped_normal_moments(mu, sigma, lo=-np.inf, hi=np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of y = clip(x, lo, hi) with x ~ N(mu, sigma²) (broadcast, vectorised).

    Exact in the limits: bounds far away give (μ, σ²); a variable clipped entirely gives (bound, 0); σ = 0
    gives (clip(μ), 0).  The moments are taken about c = clip(μ, lo, hi), so that no large numbers cancel.
    """
    mu, sigma, lo, hi = np.broadcast_arrays(*(np.asarray(v, float) for v in (mu, sigma, lo, hi)))
    if np.any(lo > hi):
        raise ValueError("lo must not exceed hi")
    c = np.clip(mu, lo, hi)
    s = np.where(sigma > 0, sigma, 1.0)
    with np.errstate(invalid="ignore"):
        a = (lo - mu) / s
        b = (hi - mu) / s
    p_lo = ndtr(a)  # P(x < lo)
    p_hi = ndtr(-b)  # P(x > hi)
    p_in = _mass_between(a, b)
    fa, fb = _phi(a), _phi(b)
    with np.errstate(invalid="ignore"):
        afa = np.where(np.isfinite(a), a * fa, 0.0)
        bfb = np.where(np.isfinite(b), b * fb, 0.0)
    dlo = np.where(np.isfinite(lo), lo - c, 0.0)
    dhi = np.where(np.isfinite(hi), hi - c, 0.0)
    m0 = mu - c
    # E[(x − c) 1{lo<x<hi}] and E[(x − c)² 1{lo<x<hi}] for the truncated part
    e1 = m0 * p_in + s * (fa - fb)
    e2 = (m0 * m0 + s * s) * p_in + 2.0 * m0 * s * (fa - fb) + s * s * (afa - bfb)
    m1 = dlo * p_lo + dhi * p_hi + e1
    m2 = dlo * dlo * p_lo + dhi * dhi * p_hi + e2
    mean = c + m1
    var = np.maximum(m2 - m1 * m1, 0.0)
    degenerate = ~(sigma > 0)
    return np.where(degenerate, c, mean), np.where(degenerate, 0.0, var)


#: Above this σ (DN) the readout's moments come from the continuous normal's (see :func:`readout_moments`).
SMOOTH_SIGMA = 2.0
#: How far into a tail beyond a bound the closed form holds: while the log density falls by at most this much per
#: level (z/σ ≤ TAIL_SLOPE); the next Euler–Maclaurin term is then ≲ TAIL_SLOPE³/720 of the density.
TAIL_SLOPE = 0.25
#: The closed form is used only where the levels between the bounds hold at least this much of the mass.
MIN_INNER_MASS = 1e-12


def readout_moments(mu, sigma, lo: int, hi: int, truncate: bool = False,
                    reach: float = 10.0, closed_form: bool = True,
                    dither: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the readout y = rint(clip(x, lo, hi)), x ~ N(mu, sigma²), integer lo < hi.

    P(y = k) = Φ((k+½−μ)/σ) − Φ((k−½−μ)/σ) for lo < k < hi; the bounds take the tails.  Only the levels
    within ``reach`` σ of clip(μ) are summed (the mass beyond is below Φ(−reach)).  ``truncate``: conditional
    on lo < y < hi.  (Ties of rint at half-integers have probability 0.)  ``dither``: the width d of a uniform
    dither added before rounding (the module's docstring); the closed form below then takes the smoothed variable
    as normal of variance σ² + d²/12 (the box's fourth cumulant, −d⁴/120, changes its tail masses by ≲ 10⁻⁴ of
    themselves at σ ≥ :data:`SMOOTH_SIGMA`).

    Examples
    --------
    At an integer mean rounding leaves far less than σ² + 1/12 = 0.173 (its average over μ), and a dither of
    1 DN adds about its own 1/12 on top (0.257 on average):

    >>> round(float(readout_moments(2.0, 0.3, 0, 4095)[1][()]), 4)
    0.0956
    >>> round(float(readout_moments(2.0, 0.3, 0, 4095, dither=1.0)[1][()]), 4)
    0.2395

    For σ ≥ :data:`SMOOTH_SIGMA`, with μ no more than max(1, :data:`TAIL_SLOPE`·σ) σ beyond a bound, the sum is replaced by the
    continuous normal's moments on (lo+½, hi−½) plus the rounding's by Euler–Maclaurin (per period the rounding
    error integrates to −g′/12, which sums to boundary terms because the interval holds whole periods; its
    square adds 1/12).  The neglected terms are O(g‴): against the sum, ≤ 2·10⁻⁴ DN in the mean and ≤ 10⁻³·σ²
    in the variance (tests/stats/test_censored.py), far below what any variance bin resolves.  It costs O(1)
    per value where the sum costs O(σ) — the sum dominated the model check on data with a black level a few σ
    of noise above 0 (every dark-frame pixel is then near a bound).  ``closed_form=False``: the sum everywhere
    (what a table of the exact values is made of and checked against).
    """
    mu, sigma = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float))
    shape = mu.shape
    mu, sigma = mu.ravel(), np.maximum(sigma.ravel(), 1e-9)
    lo, hi = int(lo), int(hi)
    if hi <= lo + (2 if truncate else 0):
        raise ValueError("empty range of levels")
    if mu.size == 0:
        return np.zeros(shape), np.zeros(shape)
    mean, var = np.empty(mu.shape), np.empty(mu.shape)
    smooth = (_smooth_readout(mu, _smoothed_sigma(sigma, dither), lo, hi, truncate, mean, var) if closed_form
              else np.zeros(mu.shape, bool))
    rest = np.flatnonzero(~smooth)
    rest = rest[~_single_level(mu, sigma, rest, lo, hi, truncate, reach, mean, var, dither)]
    # the sum's window is set by the widest row summed together: sum rows of like width together (within a
    # factor of 2), so a few wide ones do not widen every row's window
    octave = np.floor(np.log2(_window(mu[rest], sigma[rest], lo, hi, reach, truncate, dither))).astype(int)
    for o in np.unique(octave):
        at = rest[octave == o]
        mean[at], var[at] = _summed_readout(mu[at], sigma[at], lo, hi, truncate, reach, dither)
    return mean.reshape(shape), var.reshape(shape)


def _smoothed_sigma(sigma: np.ndarray, dither: float) -> np.ndarray:
    """The standard deviation of x + u (the dither's variance d²/12 added)."""
    return sigma if dither <= 0 else np.sqrt(sigma * sigma + dither * dither / 12.0)


def truncated_readout_mean(mu, sigma, lo: int, hi: int, reach: float = 10.0, dither: float = 0.0,
                           sigma_of: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """:func:`readout_moments`' truncated mean (conditional on lo < y < hi) for many values at once, as cheaply as
    it holds: the closed form where σ ≥ :data:`SMOOTH_SIGMA` allows it, a level's own value where one level holds
    the mass, and for the rest (σ below :data:`SMOOTH_SIGMA`, or means deep beyond a bound) a checked table
    (:func:`tabulated_truncated_mean`) where there are many values, else the sum once per distinct (μ, σ).

    Why: the sum costs O(σ) normal tail probabilities per value, and the model check evaluates this mean for
    every pixel of every dark frame near 0 DN at every prediction.  On 16-bit frames with a 48 DN black level,
    20 DN of read noise and a DSNU of 48 DN, a fifth of the dark pixels sit 5–10 σ below 0, beyond the closed
    form's reach: summed, they were a sixth of the check's time; the table (one σ per frame) costs a few hundred
    sums.  Without patterns of their own, pixels share their (μ, σ) and one sum serves them all.  ``sigma_of``:
    σ as a function of μ where it is one (the noise law at a common electronic offset), for a table in μ alone."""
    mu, sigma = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float))
    shape = mu.shape
    mu, sigma = mu.ravel(), np.maximum(sigma.ravel(), 1e-9)
    if hi <= lo + 2:
        raise ValueError("empty range of levels")
    mean, var = np.empty(mu.shape), np.empty(mu.shape)
    rest = np.flatnonzero(~_smooth_readout(mu, _smoothed_sigma(sigma, dither), lo, hi, True, mean, var))
    rest = rest[~_single_level(mu, sigma, rest, lo, hi, True, reach, mean, var, dither)]
    if rest.size:
        m, s = mu[rest], sigma[rest]
        table = tabulated_truncated_mean(m, s, lo, hi, dither=dither, sigma_of=sigma_of)
        if table is not None:
            mean[rest] = table
        else:
            distinct, inverse = np.unique(m + 1j * s, return_inverse=True)  # complex numbers sort by (real, imag)
            if len(distinct) > 0.5 * len(m):
                mean[rest] = readout_moments(m, s, lo, hi, truncate=True, reach=reach, dither=dither)[0]
            else:
                mean[rest] = readout_moments(distinct.real, distinct.imag, lo, hi, truncate=True,
                                             reach=reach, dither=dither)[0][inverse.ravel()]
    return mean.reshape(shape)


def _single_level(mu: np.ndarray, sigma: np.ndarray, at: np.ndarray, lo: int, hi: int, truncate: bool, reach: float,
                  mean: np.ndarray, var: np.ndarray, dither: float = 0.0) -> np.ndarray:
    """Fill ``mean``/``var`` at the values ``at`` whose nearest level holds all but Φ(−``reach``) of their mass
    (σ under 1/``reach`` of μ's distance to that level's edges; a bound's level takes its whole tail); returns
    which of ``at`` it filled.

    Why: what the sum gives them (the level, variance 0; truncated at a bound, the inner level next to it, as
    :func:`_summed_readout` makes it) without summing — the model check's first look at the noise can leave dark
    pixels at σ ≪ 0.1 DN (read noise 0 while the black level is at its start; RESULTS_check.md), and the sum over
    the window of their group was most of its time on the EMVA 1288 standard series with shot noise in the model."""
    m, s = mu[at], sigma[at]
    c = np.rint(np.clip(m, lo, hi))
    # distance to the level's lower and upper edges (none at a bound), less the dither's half-width
    below = np.where(c <= lo, np.inf, m - (c - 0.5) - 0.5 * dither)
    above = np.where(c >= hi, np.inf, (c + 0.5) - m - 0.5 * dither)
    single = np.minimum(below, above) >= reach * s
    if truncate:
        # at a bound, what counts is the inner level next to it against the one after: their densities differ by
        # exp(−(2d + 1)/2σ²), d = μ's distance to the bound's edge (a mean 10 σ beyond the bound at σ = 20 DN
        # leaves its inner mass spread over ≈ 2 DN, not on one level)
        d = np.where(c <= lo, lo + 0.5 - m, m - (hi - 0.5)) - 0.5 * dither
        single = np.where((c <= lo) | (c >= hi), 2.0 * d + 1.0 >= (reach * s) ** 2, single)
    level = np.clip(c, lo + 1, hi - 1) if truncate else c
    mean[at[single]] = level[single]
    var[at[single]] = 0.0
    return single


def _smooth_readout(mu: np.ndarray, sigma: np.ndarray, lo: int, hi: int, truncate: bool, mean: np.ndarray,
                    var: np.ndarray) -> np.ndarray:
    """Fill ``mean``/``var`` where the closed form holds (see :func:`readout_moments`); returns where it did."""
    ok = sigma >= SMOOTH_SIGMA
    if not ok.any():  # (the usual case of dark frames near 0 DN: nothing of the below is needed)
        return ok
    a = (lo + 0.5 - mu) / sigma
    b = (hi - 0.5 - mu) / sigma
    # the expansion needs a density smooth over a period at the bounds: in a tail z beyond a bound the log density
    # falls by z/σ per level, so up to max(1, TAIL_SLOPE·σ) standard deviations (a wide noise: 5σ at σ = 20 DN,
    # where the sum would cost O(σ) per value over every dark-frame pixel predicted below 0 during a fit)
    tail = np.maximum(1.0, TAIL_SLOPE * sigma)
    ok &= (a <= tail) & (b >= -tail)
    # a mean many σ beyond a bound leaves (nearly) no mass between them: the closed form's ratios need some
    # (a 6-σ reach of a hot pixel's wide noise put p_in at 0 and the ratios at 0/0); those values are summed
    p_all = np.zeros(mu.shape)
    p_all[ok] = _mass_between(a[ok], b[ok])
    ok &= p_all > MIN_INNER_MASS
    a, b, m, s = a[ok], b[ok], mu[ok], sigma[ok]
    p_in = p_all[ok]
    fa, fb = _phi(a), _phi(b)
    r1 = (fa - fb) / p_in
    r2 = (np.where(np.isfinite(a), a * fa, 0.0) - np.where(np.isfinite(b), b * fb, 0.0)) / p_in
    d = m - np.clip(np.rint(m), lo + 1, hi - 1)  # moments about an inner level: no cancellation
    c = m - d
    # the continuous truncated normal's first two moments about c ...
    e1 = d + s * r1
    e2 = s * s * (1.0 + r2) + d * (d + 2.0 * s * r1)
    # ... and the rounding's: per period the integral of (k - x)·g is -g'(k)/12 + O(g'''(k)); summed over the
    # interval (whole periods) -[g]/12, for g = f and g = 2(x - c)·f; the rounding error's square adds 1/12
    fa_x, fb_x = fa / (s * p_in), fb / (s * p_in)
    xa, xb = lo + 0.5 - c, hi - 0.5 - c
    t_mean = e1 - (fb_x - fa_x) / 12.0
    t_m2 = e2 + 1.0 / 12.0 - 2.0 * (xb * fb_x - xa * fa_x) / 12.0
    t_var = np.maximum(t_m2 - t_mean * t_mean, 0.0)
    if truncate:
        mean[ok], var[ok] = c + t_mean, t_var
        return ok
    p_lo, p_hi = ndtr(a), ndtr(-b)
    dlo, dhi = lo - c, hi - c
    m1 = dlo * p_lo + dhi * p_hi + p_in * t_mean
    m2 = dlo * dlo * p_lo + dhi * dhi * p_hi + p_in * (t_var + t_mean * t_mean)
    mean[ok], var[ok] = c + m1, np.maximum(m2 - m1 * m1, 0.0)
    return ok


def _window(mu: np.ndarray, sigma: np.ndarray, lo: int, hi: int, reach: float, truncate: bool = False,
            dither: float = 0.0) -> np.ndarray:
    """Per value, how many levels either side of clip(μ) carry mass above Φ(−``reach``), plus two: ``reach``·σ,
    less the distance of μ beyond a bound (the levels past the bound do not exist).  ``truncate``: the mass that
    matters is relative to what lies inside the bounds — for μ a distance z·σ beyond a bound, the density inside
    falls by z·n/σ + n²/2σ² over n levels, which reaches ``reach``²/2 at n = σ·(√(z² + reach²) − z) (the same
    as ``reach``·σ at z = 0; the untruncated window stopped short of it at z ≳ ``reach``·0.9 and cut the
    conditional mean: 0.67 DN at σ = 19.9 DN, z = 10)."""
    # (a dither of width d reaches d/2 further either way: the window is taken from the nearer end of its box)
    beyond = np.maximum(np.maximum(lo - mu, mu - hi) - 0.5 * dither, 0.0)
    if truncate:
        z = beyond / sigma
        return np.ceil(sigma * (np.sqrt(z * z + reach * reach) - z) + 0.5 * dither) + 2.0
    return np.ceil(np.maximum(reach * sigma - beyond, 0.0) + 0.5 * dither) + 2.0


def _summed_readout(mu: np.ndarray, sigma: np.ndarray, lo: int, hi: int, truncate: bool,
                    reach: float, dither: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The readout's moments summed over its integer levels within ``reach`` σ (and the dither's reach)."""
    half = int(_window(mu, sigma, lo, hi, reach, truncate, dither).max())
    c = np.rint(np.clip(mu, lo, hi))
    offsets = np.arange(-half, half + 1, dtype=float)
    if 2 * half + 1 >= hi - lo + 1:  # the window covers the whole range: sum over every level
        c = np.full_like(mu, float(lo))
        offsets = np.arange(0, hi - lo + 1, dtype=float)
    k = c[:, None] + offsets[None, :]
    valid = (k >= lo) & (k <= hi)
    # each level's mass between its two half-integer edges, every edge's tail probabilities computed once (a
    # level's upper edge is the next one's lower edge, bit for bit: k + ½ = (k + 1) − ½ exactly) — the same
    # numbers as _mass_between level by level, with half its ndtr calls
    edges = np.concatenate([k - 0.5, k[:, -1:] + 0.5], axis=1)
    lower, upper = _edge_probabilities(edges, mu[:, None], sigma[:, None], dither)
    first, last = np.zeros(edges.shape, bool), np.zeros(edges.shape, bool)
    first[:, :-1], last[:, 1:] = k <= lo, k >= hi  # the bounds take the tails
    lower, upper = np.where(first, 0.0, np.where(last, 1.0, lower)), np.where(first, 1.0, np.where(last, 0.0, upper))
    above = edges[:, :-1] > mu[:, None]  # difference whichever tail is the smaller
    p = np.where(valid, np.where(above, upper[:, :-1] - upper[:, 1:], lower[:, 1:] - lower[:, :-1]), 0.0)
    if truncate:
        p = np.where((k > lo) & (k < hi), p, 0.0)
    tot = p.sum(axis=1)
    if truncate:  # no mass left inside (μ far beyond a bound): the limit is the inner level next to it
        c = np.where(tot > 0, c, np.clip(c, lo + 1, hi - 1))
    tot = np.where(tot > 0, tot, 1.0)
    d = k - c[:, None]  # moments about c: no cancellation
    m1 = (p * d).sum(axis=1) / tot
    m2 = (p * d * d).sum(axis=1) / tot
    return c + m1, np.maximum(m2 - m1 * m1, 0.0)


#: Harmonics summed by :func:`readout_variance_harmonics` (exp(−2π²k²σ²) at k = 64 is below 10⁻¹⁶ for σ ≥ 0.035 DN).
HARMONIC_TERMS = 64


def readout_variance_harmonics(sigma, dither: float = 0.0, n: int = 15) -> np.ndarray:
    """The cosine coefficients ``a_0 … a_n`` of the readout's variance as a function of the level, away from the
    bounds: Var(rint(x + u)) = Σ a_k cos(2πkμ) for x ~ N(μ, σ²), u ~ U(−d/2, d/2) (d = ``dither``), harmonics
    above ``n`` left out.  ``(..., n + 1)`` for ``sigma`` of any shape.

    In closed form from the rounding error's Fourier series (Widrow's quantisation theory): with the sawtooth
    s(w) = w − rint(w) = Σ (−1)^{k+1} sin(2πkw)/(πk), its square 1/12 + Σ (−1)^k cos(2πkw)/(π²k²), the
    characteristic functions g_k = exp(−2π²k²σ²) of the noise and sinc(kd) of the dither at 2πk, and Stein's lemma
    for the covariance of w and s(w):

        Var y = σ² + d²/12 + E s² − (E s)² − 2 Cov(w, s),   E s = Σ B_k sin(2πkμ),  B_k = (−1)^{k+1} g_k sinc(kd)/(πk),
        Cov(w, s) = Σ (−1)^{k+1} g_k (2πkσ² sinc(kd) − t_k) cos(2πkμ)/(πk),  t_k = (d/2)(a cos a − sin a)/a², a = πkd.

    Why: the model check's variance channel predicts a low-noise bin from its pixels' mean cos(2πkμ) (see
    :func:`~forensics.check.prediction.phase_averaged`); these coefficients were the discrete cosine transform of
    the exact sum at 32 levels per bin and per prediction — a tenth of the check of a small series.  They agree
    with the exact readout's variance to 10⁻¹³ DN² for σ ≥ 0.1 DN (``tests/stats/test_censored.py``).

    Examples
    --------
    With a dither of 1 DN the variance is σ² + 1/6 − Σ exp(−2π²k²σ²) cos(2πkμ)/(π²k²): at a whole level and
    σ = 0.3 DN (the exact sum: 0.2395, :func:`readout_moments`)

    >>> a = readout_variance_harmonics(0.3, dither=1.0)
    >>> round(float(a.sum()), 4)
    0.2395
    """
    sigma = np.asarray(sigma, float)[..., None]
    k = np.arange(1, HARMONIC_TERMS + 1, dtype=float)
    g = np.exp(-2.0 * np.pi**2 * k * k * sigma * sigma)                     # (..., K)
    a = np.pi * k * dither
    sinc = np.sinc(k * dither)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(a > 0, 0.5 * dither * (a * np.cos(a) - np.sin(a)) / (a * a), 0.0)
    sign = np.where(k % 2 == 1, 1.0, -1.0)                                   # (−1)^{k+1}
    b = sign * g * sinc / (np.pi * k)                                        # E s = Σ b_k sin(2πkμ)
    # E s² − 2 Cov(w, s), harmonic k
    direct = -sign * g * sinc / (np.pi * k) ** 2 - 2.0 * sign * g * (2.0 * np.pi * k * sigma**2 * sinc - t) / (np.pi * k)
    out = np.zeros(sigma.shape[:-1] + (n + 1,))
    out[..., 0] = sigma[..., 0] ** 2 + (1.0 + dither * dither) / 12.0 - 0.5 * np.sum(b * b, axis=-1)
    for m in range(1, n + 1):
        # −(E s)²: ½ Σ b_j b_k [cos 2π(j − k)μ − cos 2π(j + k)μ] at harmonic m
        cross = np.sum(b[..., m:] * b[..., :HARMONIC_TERMS - m], axis=-1)
        inner = np.sum(b[..., :m - 1] * b[..., m - 2::-1], axis=-1) if m > 1 else 0.0
        out[..., m] = direct[..., m - 1] - cross + 0.5 * inner
    return out


#: Spacing of :func:`tabulated_truncated_mean`'s grid, in units of the smallest σ tabulated: a cubic spline's
#: error is ≈ (5/384)·h⁴·|f⁗|, with |f⁗| ≲ 1/σ³ DN near a bound ≈ 4·10⁻⁸ DN here (measured: below 10⁻⁷ DN
#: on dark frames at σ = 0.2–1.8 DN, tests/stats/test_censored_table.py).
TABLE_STEP = 0.025
#: The largest error of the table accepted on its check sample (DN); above it the caller sums exactly.
TABLE_TOLERANCE = 1e-6
#: Values checked against the exact sum: every n-th (and the extremes of μ and σ).
TABLE_CHECKS = 512
#: A table along μ serves calls of at least twice this many values (its validation costs two sums a node).
MIN_ALONG_MU = 64
#: Below this σ (DN) no table: the readout's mean becomes a staircase in μ that no spline follows.
TABLE_SIGMA_MIN = 0.1


def _lagrange_weights(u: np.ndarray, n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """For positions ``u`` in grid units on a grid of ``n`` nodes: the index ``i`` of each one's interval, clipped
    to [1, n − 3], and the weights of nodes i − 1 … i + 2 of the cubic through them (Lagrange)."""
    i = np.clip(np.floor(u).astype(np.intp), 1, n - 3)
    t = u - i
    tm, tp, t2 = t - 1.0, t + 1.0, t - 2.0
    return i, [(t * tm * t2) / -6.0, (tp * tm * t2) / 2.0, (tp * t * t2) / -2.0, (tp * t * tm) / 6.0]


def uniform_cubic(start: float, step: float, table: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The cubic through the four table values around each ``x`` (Lagrange, nodes ``start + k·step``), for ``x``
    at least one step inside the table's ends.  Error ≤ (3/128)·step⁴·|f⁗| between the middle nodes.

    Why by hand: on a uniform grid the interval is an index, not a search — a third of the time of scipy's
    B-spline evaluation for the model check's dark frames (76,800 values, once per condition and prediction).

    Examples
    --------
    >>> import numpy as np
    >>> grid = np.arange(0.0, 2.01, 0.25)
    >>> round(float(uniform_cubic(0.0, 0.25, grid**3, np.array([1.1]))[0]), 12)  # exact for cubics
    1.331
    """
    i, w = _lagrange_weights((np.asarray(x, float) - start) / step, len(table))
    out = w[0] * table[i - 1]
    for k in range(1, 4):
        out += w[k] * table[i + k - 1]
    return out


def uniform_bicubic(starts: tuple[float, float], steps: tuple[float, float], table: np.ndarray, x: np.ndarray,
                    y: np.ndarray) -> np.ndarray:
    """:func:`uniform_cubic` in two variables: the tensor-product cubic through the 4 × 4 table values around each
    (``x``, ``y``) on a uniform grid (``table[j, k]`` at ``starts + (j, k)·steps``; at least 4 nodes along each).
    Exact for polynomials of degree 3 in each variable.

    Examples
    --------
    >>> import numpy as np
    >>> gx, gy = np.arange(0.0, 2.01, 0.25), np.arange(1.0, 2.01, 0.25)
    >>> table = gx[:, None] ** 3 * gy[None, :] ** 2
    >>> round(float(uniform_bicubic((0.0, 1.0), (0.25, 0.25), table, np.array([1.1]), np.array([1.3]))[0]), 12)
    2.24939
    """
    i, wx = _lagrange_weights((np.asarray(x, float) - starts[0]) / steps[0], table.shape[0])
    j, wy = _lagrange_weights((np.asarray(y, float) - starts[1]) / steps[1], table.shape[1])
    flat = table.ravel()
    base = (i - 1) * table.shape[1] + (j - 1)
    out = np.zeros(np.shape(i))
    for a in range(4):
        row = wy[0] * flat[base + a * table.shape[1]]
        for b in range(1, 4):
            row += wy[b] * flat[base + a * table.shape[1] + b]
        out += wx[a] * row
    return out


def _composite_table(mu: np.ndarray, grid_mu: np.ndarray, sigma_of: Callable[[np.ndarray], np.ndarray], lo: int,
                     hi: int, tolerance: float, dither: float) -> np.ndarray:
    """The truncated mean at ``mu`` from a cubic along ``grid_mu`` whose nodes sit at their own σ = ``sigma_of(μ)``.

    σ(μ) need not be smooth (a shot-noise law clipped at zero charge has a kink), so the cubic is checked at the
    midpoint of every interval against the exact sum; values whose four nodes reach an interval that misses by
    more than ``tolerance`` (or its neighbours) are summed exactly — the table holds where it is smooth."""
    h = float(grid_mu[1] - grid_mu[0])
    start = float(grid_mu[0])

    def exact(m: np.ndarray) -> np.ndarray:
        return readout_moments(m, np.maximum(np.asarray(sigma_of(m), float), 1e-9), lo, hi, truncate=True,
                               closed_form=False, dither=dither)[0]

    table = exact(grid_mu)
    mid = grid_mu[:-1] + 0.5 * h
    bad = np.abs(uniform_cubic(start, h, table, mid) - exact(mid)) > tolerance
    if bad.any():  # an interval's neighbours share its nodes: they are summed too
        bad = np.convolve(bad, np.ones(5), mode="same") > 0
    out = uniform_cubic(start, h, table, mu)
    interval = np.clip(np.floor((mu - start) / h).astype(np.intp), 0, bad.size - 1)
    rough = bad[interval]
    if rough.any():
        out[rough] = exact(mu[rough])
    return out


def tabulated_truncated_mean(mu: np.ndarray, sigma: np.ndarray, lo: int, hi: int,
                             tolerance: float = TABLE_TOLERANCE, dither: float = 0.0,
                             sigma_of: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray | None:
    """:func:`readout_moments`' truncated mean (conditional on lo < y < hi) by local cubics over a uniform grid of
    (μ, σ), checked against the exact sum; None where a table does not pay or does not hold (the caller sums).

    Why: the exact sum costs O(σ) normal tail probabilities per value (≈ 2 µs), and the model check evaluates it
    for every pixel of every dark frame near 0 DN at every prediction — most of its time on the EMVA 1288
    standard series (σ ≈ 0.5 DN, black level 1 DN).  The mean is smooth in μ and σ for σ ≳ 0.1 DN, so a table
    over the values' range (spacing :data:`TABLE_STEP`·σ_min, a few thousand exact sums) interpolated by local
    cubics (:func:`uniform_cubic`, :func:`uniform_bicubic`) costs ≈ 0.02–0.05 µs per value (scipy's splines took
    three to six times that).

    Where every value's σ is one number, or ``sigma_of(μ)`` (σ as a function of μ: the noise law at one
    electronic offset — shot noise makes σ grow with the dark signal), the table runs along μ alone, its nodes at
    their own σ (:func:`_composite_table`: four nodes a value instead of sixteen), and it is checked against the
    exact sum at the midpoint of *every* interval, where a cubic's error peaks; values next to an interval that
    misses (a kink of the noise law) are summed.  It serves calls of :data:`MIN_ALONG_MU` × 2 values and more.
    Otherwise a (μ, σ) grid is trusted only after :data:`TABLE_CHECKS` of the values (every n-th, plus the
    extremes) agree with the exact sum within ``tolerance``.  Either is refused when it would not be much smaller
    than the values themselves, and the values' σ must be the function's (:data:`TABLE_CHECKS` of them compared).
    """
    mu, sigma = np.asarray(mu, float).ravel(), np.asarray(sigma, float).ravel()
    if mu.size < 2 * MIN_ALONG_MU or not np.all(np.isfinite(mu)) or not np.all(np.isfinite(sigma)):
        return None
    s_lo, s_hi = float(sigma.min()), float(sigma.max())
    if not TABLE_SIGMA_MIN <= s_lo:
        return None
    h = TABLE_STEP * s_lo
    grid_mu = np.arange(float(mu.min()) - 2 * h, float(mu.max()) + 3 * h, h)
    step = max(1, mu.size // TABLE_CHECKS)
    check = np.unique(np.concatenate([np.arange(0, mu.size, step),
                                      [np.argmin(mu), np.argmax(mu), np.argmin(sigma), np.argmax(sigma)]]))
    if s_hi - s_lo <= 1e-9 * s_lo:  # one σ: a cubic in μ alone
        sigma_of = lambda m: np.full(np.shape(m), s_lo)  # noqa: E731
    if sigma_of is not None:
        # a cubic along μ, its nodes at their own σ, checked at every interval's midpoint (a node and a midpoint
        # per step: half the values at most, else the sums are as cheap); the values' σ must be the function's, to
        # the 10⁻⁹ that makes σ "one number" above (a mean moves by far less than the tolerance for it)
        if 4 * grid_mu.size > mu.size or not np.allclose(sigma_of(mu[check]), sigma[check], rtol=1e-9, atol=0.0):
            return None
        return _composite_table(mu, grid_mu, sigma_of, lo, hi, tolerance, dither)
    if mu.size < 2 * TABLE_CHECKS:
        return None
    n_sigma = max(int(np.ceil((s_hi - s_lo) / h)) + 1, 4)
    if grid_mu.size * n_sigma + TABLE_CHECKS > mu.size // 2:
        return None  # the table and its check would cost a good part of the exact sums they replace
    # σ's grid reaches a step beyond both ends, as μ's does, so that every value has its 4 × 4 nodes around it
    # (its step is at most TABLE_STEP·σ_min: the node below σ_min is still above 0)
    h_sigma = (s_hi - s_lo) / (n_sigma - 1)
    grid_sigma = s_lo + h_sigma * np.arange(-1, n_sigma + 1)
    table = readout_moments(grid_mu[:, None], grid_sigma[None, :], lo, hi, truncate=True, closed_form=False,
                            dither=dither)[0]
    out = uniform_bicubic((float(grid_mu[0]), float(grid_sigma[0])),
                          (float(grid_mu[1] - grid_mu[0]), h_sigma), table, mu, sigma)
    exact = readout_moments(mu[check], sigma[check], lo, hi, truncate=True, closed_form=False, dither=dither)[0]
    if not np.max(np.abs(out[check] - exact)) <= tolerance:
        return None
    return out
