"""Misfit nobody's catalogue covers: where the residual's leftover structure lives.

After the fit, the residual of normal pixels is searched for structure of a few generic shapes, each tested
against what pure noise would leave:

``column`` / ``row``  the mean residual per column (row), averaged over rows (columns) and conditions
``radial``            the mean residual in 1-pixel rings of distance from the frame centre (the optical centre
                      is taken to be the centre of the frame: the check has no optics model)
``trend``             the per-condition mean residual regressed on each covariate (exposure, ISO, temperature,
                      signal level, epoch)
``misfit trend``      the per-condition held-out error² (mean squared standardised residual) regressed on the
                      same covariates

The strongest structure (smallest Holm-adjusted p over every test run, if below :data:`NAME_P`) is named in
words with its size, e.g. "column-wise pattern, 3.1 DN rms".

**The residual.**  Profiles use the sum of the two halves' residuals, ``(mean_a − mu_a) + (mean_b − mu_b)``,
standardised by each half's noise floor: for a least-squares fit on half a the sum has exactly the covariance
of pure noise (``I − 2P`` is a reflection), so a fitted pattern's estimation noise — which the held-out half
alone would show as a column pattern after a column effect is added — does not raise false alarms.

**The null.**  The scene of every pixel is estimated from its neighbours (a leave-one-out quadratic kernel
``K``), so the residual is ``(I − K)`` applied to noise and to any unexplained pattern.  Neighbouring residuals
are correlated; the exact covariance of every bin sum follows from the kernel's autocorrelation and the bins'
geometry (:func:`bin_covariance`), scaled by the residual's own measured variance — so any pixel-to-pixel
independent leftover (noise, or an uncatalogued per-pixel pattern) is the null, and only structure shared
along a row, a column, a ring or a covariate counts.  In frames known to be dark the prediction is the
chain's own output, not the scene estimate, so there the residual is the noise itself: those conditions are
summed and tested apart (independent bins), and the two χ² add.  The profile is tested by a whitened χ² (directions the
kernel removes — smooth profiles — dropped).  Trends use ordinary least squares with the standard error from
the scatter about the line (t with n − 2 df).

**What the tests cannot see.**  Anything the scene estimate absorbs: a per-frame offset or gain and any
pattern that is locally quadratic on the kernel's 7 × 7 scale (smooth vignetting, smooth shading) cancel in
the residual by construction, so only pixel-fixed patterns that change from one pixel (row, column, ring) to
the next are visible in the profiles.  For the same reason the per-condition *mean* residual is nearly blind
(``I − K`` removes the mean of any pattern); it sees what the model gets wrong non-linearly (clipping, fill
values).  The misfit trend sees a pixel-to-pixel pattern whose size changes with a covariate, but not its
shape.  Defective pixels (stuck, partially stuck) are left out; their channels are tested elsewhere.
"""
from __future__ import annotations

import hashlib
import math
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
from forensics.stats.tails import chi2_sf, t_sf

from forensics.stats.multiple import holm_adjusted

from forensics.check.classes import NORMAL, dark_groups
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel
from forensics.check.result import StructureResult, StructureTest
from forensics.check.pixels import uses_scene
from forensics.check.scene import KERNEL, KERNEL_VAR

#: A structure is named when its Holm-adjusted p is below this.
NAME_P = 1e-3
#: Pixels whose summed standardised residual is further than this many robust σ out are left out (undetected
#: defects would otherwise dominate a bin's sum).
OUTLIER_Z = 6.0
#: Eigenvalues of the bin covariance below this fraction of the largest are dropped (profiles the scene
#: estimate removes).
EIG_FLOOR = 1e-3

#: ``(I − K)``: the residual at p is Σ_u A1[u] · x[p + u].
A1 = -KERNEL.copy()
A1[KERNEL.shape[0] // 2, KERNEL.shape[1] // 2] += 1.0
#: Its autocorrelation: Cov(residual_p, residual_q) = σ² · A2[q − p] for white noise of variance σ².
A2 = np.zeros((2 * A1.shape[0] - 1, 2 * A1.shape[1] - 1))
# scipy.signal.correlate2d(A1, A1, "full") as a sum of shifted copies (A1 ⋆ A1 = A1 ∗ A1 reversed): the same values
# to 2·10⁻¹⁶, without importing scipy.signal (0.3–0.4 s, with the scipy.stats it imports) for one small product
for (_i, _j), _a in np.ndenumerate(A1):
    A2[_i:_i + A1.shape[0], _j:_j + A1.shape[1]] += _a * A1[::-1, ::-1]
del _i, _j, _a

SEES = {
    "column": "pixel-fixed patterns constant down each column (column amplifiers, column offsets); not smooth "
              "shading across columns, which the scene estimate absorbs",
    "row": "pixel-fixed patterns constant along each row (row drivers); not smooth shading, nor per-frame row "
           "noise (temporal, averaged into the noise)",
    "radial": "pixel-fixed patterns that depend on the distance from the frame centre and change within a few "
              "pixels (rings, sharp-edged shading); not smooth vignetting, which the scene estimate absorbs",
    "trend": "a mean residual that moves with the covariate (clipping, fill values); nearly blind to fixed "
             "patterns, whose mean the scene estimate removes",
    "misfit trend": "a pixel-to-pixel misfit whose size changes with the covariate (an uncatalogued pattern that "
                    "grows with exposure, temperature, level or age); not its shape",
}
LABELS = {"column": "column-wise pattern", "row": "row-wise pattern",
          "radial": "radial pattern (distance from the frame centre)"}


def _pair_sums(left: np.ndarray, right: np.ndarray, kernel: np.ndarray, n_left: int, n_right: int) -> np.ndarray:
    """``M[j, k] = Σ_d kernel[d] · #{p : left[p] = j, right[p + d] = k}`` (labels < 0 are left out)."""
    h, w = left.shape
    c = kernel.shape[0] // 2
    out = np.zeros(n_left * n_right)
    square = out.reshape(n_left, n_right)
    for dy in range(-c, c + 1):
        for dx in range(-c, c + 1):
            wt = kernel[dy + c, dx + c]
            if wt == 0.0:
                continue
            a = left[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
            b = right[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
            ok = (a >= 0) & (b >= 0)
            a, b = a[ok], b[ok]
            if not a.size:
                continue
            # neighbouring pixels' labels differ by little (column, row, radius): count (label, difference)
            # pairs, a band instead of the whole square (the same counts, added in the same order)
            diff = b - a
            lo = int(diff.min())
            span = int(diff.max()) - lo + 1
            if span < n_right:
                band = np.bincount(a * span + (diff - lo), minlength=n_left * span).reshape(n_left, span)
                j, d = np.nonzero(band)
                square[j, j + d + lo] += wt * band[j, d]
            else:
                out += wt * np.bincount(a * n_right + b, minlength=n_left * n_right)
    return square


#: The last few bin geometries (bin covariance, white gain, eigen-decomposition), keyed by the labels' digest:
#: they depend on the pixels used only, which are the same for every model fitted to one dataset unless the outliers change.
_GEOMETRY: OrderedDict[bytes, tuple[np.ndarray, ...]] = OrderedDict()
_GEOMETRY_SIZE = 3


def _geometry(labels: np.ndarray, pattern_labels: np.ndarray, n_bins: int) -> tuple[np.ndarray, ...]:
    """(:func:`bin_covariance`, :func:`white_gain`, eigenvalues and eigenvectors of the bin covariance over the
    bins that hold pixels) of the labels, from a small cache (read-only arrays).  The eigen-decomposition, cubic
    in the number of bins, is most of a profile test's time on large frames; the noise variance only scales the
    eigenvalues."""
    digest = hashlib.blake2b(digest_size=20)
    for a in (labels, pattern_labels):
        digest.update(repr((a.shape, a.dtype.str)).encode())
        digest.update(np.ascontiguousarray(a).data)
    key = digest.digest() + n_bins.to_bytes(8, "little")
    if key in _GEOMETRY:
        _GEOMETRY.move_to_end(key)
        return _GEOMETRY[key]
    geo = bin_covariance(labels, n_bins)
    have = np.bincount(labels[labels >= 0], minlength=n_bins) > 0
    evals, evecs = np.linalg.eigh(geo[np.ix_(have, have)])
    out = (geo, white_gain(labels, pattern_labels, n_bins), evals, evecs)
    for a in out:
        a.flags.writeable = False
    _GEOMETRY[key] = out
    while len(_GEOMETRY) > _GEOMETRY_SIZE:
        _GEOMETRY.popitem(last=False)
    return out


def bin_covariance(labels: np.ndarray, n_bins: int) -> np.ndarray:
    """Covariance of the bin sums of ``(I − K)`` applied to unit white noise (labels < 0: not summed).

    Exact for bins whose pixels' kernel neighbourhoods lie inside the frame (the check's border guarantees it).
    """
    return _pair_sums(labels, labels, A2, n_bins, n_bins)


def white_gain(labels: np.ndarray, pattern_labels: np.ndarray, n_bins: int) -> np.ndarray:
    """Per bin, the variance that ``(I − K)`` leaves of a pattern constant within bins and independent (unit
    variance) from bin to bin, in the bin's mean: Σ_k H[j, k]² / n_j² with H the bins' transfer matrix."""
    hmat = _pair_sums(labels, pattern_labels, A1, n_bins, int(pattern_labels.max()) + 1)
    n = np.bincount(labels[labels >= 0], minlength=n_bins).astype(float)
    return np.sum(hmat**2, axis=1) / np.maximum(n, 1.0) ** 2


def profile_test(kind: str, zsum: np.ndarray, rbar: np.ndarray, labels: np.ndarray, pattern_labels: np.ndarray,
                 centres: np.ndarray, white: tuple[np.ndarray, np.ndarray, float] | None = None,
                 ) -> tuple[StructureTest, dict[str, Any]]:
    """Test the bin means of a residual against the null of pixel-to-pixel independent leftovers.

    Parameters
    ----------
    kind
        ``column``, ``row`` or ``radial``.
    zsum
        Summed standardised residual per pixel (only where ``labels >= 0``) of the conditions whose prediction
        uses the scene estimate: ``(I − K)`` applied to the noise.
    rbar
        Their residual in DN (mean over halves and conditions), same pixels.
    labels
        Bin of each pixel used (−1: not used).
    pattern_labels
        Bin of every pixel of the frame (for the size of a bin-wise independent pattern).
    centres
        Position of each bin (column, row, radius in px).
    white
        ``(zsum, rbar, share)`` of the conditions whose prediction does not use the scene estimate (frames known
        to be dark: the chain's own output is predicted), where the residual is the noise itself and bins are
        independent; ``share`` is their fraction of all conditions.  The two parts are independent (different
        frames): the test is the sum of their χ² with the sum of their degrees of freedom.

    Returns
    -------
    (StructureTest, plot arrays: ``x``, ``profile`` (DN), ``null_sd`` (DN))
    """
    nb = int(labels.max()) + 1
    use = labels >= 0
    n = np.bincount(labels[use], minlength=nb).astype(float)
    have = n > 0
    geo, gains, geo_evals, evecs = _geometry(labels, pattern_labels, nb)
    ac0 = float(A2[A2.shape[0] // 2, A2.shape[1] // 2])  # 1 + Σw²
    share = 0.0 if white is None else float(white[2])
    chi, df = 0.0, 0
    noise = np.zeros(int(have.sum()))
    s2 = float(np.mean(zsum[use] ** 2)) / ac0
    if share < 1.0 and s2 > 0:
        sums = np.bincount(labels[use], weights=zsum[use], minlength=nb)
        evals = s2 * geo_evals  # of the bins' covariance s2 · geo (geo's eigenvectors)
        keep = evals > EIG_FLOOR * max(float(evals.max()), 1e-300)
        # whitened χ² of the bin sums, with a common mean per pixel fitted (GLS) and removed: only differences
        # between bins count
        u = evecs[:, keep] / np.sqrt(evals[keep])
        zs, zn = u.T @ sums[have], u.T @ n[have]
        chi += float(zs @ zs - (zs @ zn) ** 2 / max(float(zn @ zn), 1e-300))
        df += max(int(keep.sum()) - 1, 0)
        noise += (1.0 - share) ** 2 * float(np.mean(rbar[use] ** 2)) / ac0 * np.diag(geo)[have] / n[have] ** 2
    if white is not None and share > 0:
        wz, wr = white[0], white[1]
        s2w = float(np.mean(wz[use] ** 2))
        if s2w > 0:
            sums = np.bincount(labels[use], weights=wz[use], minlength=nb)[have]
            zs, zn = sums / np.sqrt(s2w * n[have]), np.sqrt(n[have] / s2w)
            chi += float(zs @ zs - (zs @ zn) ** 2 / float(zn @ zn))
            df += int(have.sum()) - 1
        noise += share**2 * float(np.mean(wr[use] ** 2)) / n[have]
        rbar = (1.0 - share) * rbar + share * wr
    p = float(chi2_sf(chi, df)) if df else 1.0
    prof = np.bincount(labels[use], weights=rbar[use], minlength=nb)[have] / n[have]
    prof = prof - float(np.sum(prof * n[have]) / np.sum(n[have]))
    ms = float(np.mean(prof**2 - noise))
    rms = math.sqrt(max(ms, 0.0))
    # a pattern's share of its variance that reaches the profile: (I − K)'s in the scene part, all in the white
    gain = float(((1.0 - share) * np.sqrt(np.mean(gains[have])) + share) ** 2)
    total = float(np.mean(rbar[use] ** 2))
    share_var = max(ms, 0.0) / total if total > 0 else 0.0
    test = StructureTest(kind=kind, label=LABELS[kind], statistic=chi, df=float(df), p=p, p_holm=p, size=rms,
                         unit="DN rms", pattern_rms=rms / math.sqrt(gain) if gain > 0 else None, share=share_var,
                         sees=SEES[kind])
    return test, {"x": centres[:nb][have], "profile": prof, "null_sd": np.sqrt(noise)}


def trend_test(kind: str, covariate: str, x: np.ndarray, y: np.ndarray,
               unit: str) -> tuple[StructureTest, dict[str, Any]] | None:
    """OLS slope of per-condition values ``y`` on ``x``: SE from the scatter about the line, t with n − 2 df.

    None when fewer than five conditions or two distinct values of the covariate are available."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 5 or np.unique(x).size < 2:
        return None
    xc = x - x.mean()
    sxx = float(np.sum(xc * xc))
    slope = float(np.sum(xc * (y - y.mean())) / sxx)
    intercept = float(y.mean() - slope * x.mean())
    res = y - intercept - slope * x
    dof = x.size - 2
    se = math.sqrt(max(float(np.sum(res * res)) / dof, 1e-300) / sxx)
    t = slope / se
    p = float(2 * t_sf(abs(t), dof))
    label = (f"residual trend with {covariate}" if kind == "trend" else f"misfit changing with {covariate}")
    test = StructureTest(kind=kind, label=label, statistic=t, df=float(dof), p=p, p_holm=p,
                         size=slope * float(np.ptp(x)), unit=f"{unit} over the range", covariate=covariate,
                         slope=slope, slope_se=se, sees=SEES[kind])
    return test, {"x": x, "y": y, "slope": slope, "intercept": intercept}


def _labels(shape: tuple[int, int], used: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(used-pixel labels, whole-frame labels, bin centres) of the column, row and radial profiles."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    rad = np.floor(np.hypot(yy - (h - 1) / 2, xx - (w - 1) / 2)).astype(np.int64)
    out = {}
    for kind, full, centres in (("column", xx.astype(np.int64), np.arange(w, dtype=float)),
                                ("row", yy.astype(np.int64), np.arange(h, dtype=float)),
                                ("radial", rad, np.arange(int(rad.max()) + 1, dtype=float))):
        out[kind] = (np.where(used, full, -1), full, centres)
    return out


def residual_structure(ev: Evidence, fitted: FittedModel) -> StructureResult:
    """Search the fitted model's residual for row, column, radial and covariate structure.

    Parameters
    ----------
    ev
        The evidence the model was fitted to.
    fitted
        The fitted model (its ``mu_a``, ``mu_b`` and pixel data are used; nothing is refitted).

    Returns
    -------
    StructureResult
        Every test run (Holm-adjusted over all of them) and the strongest structure named, or None.
    """
    meas, px = ev.meas, fitted.pixels
    nb = meas.n_b[:, None, None].astype(float)
    r_a = meas.mean_a - fitted.mu_a
    r_b = meas.mean_b - fitted.mu_b
    var_b = px.floor_b * (1.0 + np.where(uses_scene(px.classes, ev.rgroups), KERNEL_VAR, 0.0)) / nb
    z_a, z_b = r_a / np.sqrt(px.var_a), r_b / np.sqrt(var_b)
    # error² of a held-out mean exceeds 1 by the fitted patterns' estimation noise, which grows with the pattern's
    # signal (a dark-rate pattern's with the dark signal): the misfit trend is taken net of it
    excess = 0.0 if fitted.estimation_var is None else fitted.estimation_var / var_b
    normal = ev.usable & (px.classes == NORMAL)
    fixed = normal.all(axis=0)
    notes: list[str] = []
    # in frames known to be dark the prediction is the chain's own output, not the scene estimate: there the
    # residual is the noise itself (bins independent), elsewhere (I − K) applied to it — two nulls, kept apart
    dark = dark_groups(ev.rgroups)
    parts = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for name, sel in (("scene", ~dark), ("white", dark)):
            parts[name] = (np.where(fixed, np.sum(z_a[sel] + z_b[sel], axis=0), 0.0),
                           np.where(fixed, np.mean(r_a[sel] + r_b[sel], axis=0) / 2.0, 0.0) if sel.any()
                           else np.zeros(meas.shape))
    zsum = parts["scene"][0] + parts["white"][0]
    share = float(dark.mean())
    white = (*parts["white"], share) if dark.any() else None
    if fixed.sum() < 100:
        note = "fewer than 100 pixels are normal in every condition: no structure tests"
        return StructureResult(tests=[], named=None, notes=[note])
    robust = 1.4826 * float(np.median(np.abs(zsum[fixed])))
    outlier = fixed & (np.abs(zsum) > OUTLIER_Z * max(robust, 1e-12))
    used = fixed & ~outlier
    if outlier.any():
        notes.append(f"{int(outlier.sum())} pixels more than {OUTLIER_Z:g} robust σ out left out of the profiles")
    tests: list[StructureTest] = []
    plots: dict[str, Any] = {"profiles": {}, "trends": {}}
    for kind, (lab, full, centres) in _labels(meas.shape, used).items():
        t, pl = profile_test(kind, *parts["scene"], lab, full, centres, white)
        tests.append(t)
        plots["profiles"][kind] = pl
    for kind, per_cond, unit in (("trend", _masked_mean((r_a + r_b) / 2.0, normal), "DN"),
                                 ("misfit trend", _masked_mean(z_b * z_b - excess, normal), "error²")):
        for cov, x in _covariates(ev, meas, normal).items():
            out = trend_test(kind, cov, x, per_cond, unit)
            if out is not None:
                tests.append(out[0])
                plots["trends"][f"{kind}: {cov}"] = out[1]
    for t, q in zip(tests, holm_adjusted([t.p for t in tests])):
        t.p_holm = float(q)
    best = min(tests, key=lambda t: (t.p_holm, t.p)) if tests else None
    named = best if best is not None and best.p_holm < NAME_P else None
    return StructureResult(tests=tests, named=named, notes=notes, plots=plots)


def _masked_mean(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-condition mean of ``values`` over ``mask`` (NaN where empty)."""
    cnt = mask.sum(axis=(1, 2))
    tot = np.where(mask, values, 0.0).sum(axis=(1, 2))
    return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)


def _covariates(ev: Evidence, meas: Any, normal: np.ndarray) -> dict[str, np.ndarray]:
    def field(name: str) -> np.ndarray:
        return np.array([np.nan if getattr(g, name) is None else float(getattr(g, name)) for g in ev.rgroups])

    level = _masked_mean(meas.mean_all[ev.rep], normal)
    return {"exposure_s": field("exposure_s"), "iso": field("iso"), "temperature_c": field("temperature_c"),
            "signal level (DN)": level, "epoch (year)": np.array([g.time for g in ev.rgroups], float)}
