"""The block-phase PCE of identification (:mod:`forensics.prnu.identify`) and its weighted search over positions.

The statistic: block-phase PCE
------------------------------
The PCE of :mod:`forensics.prnu.match` divides the squared peak by one energy, the mean squared
correlation over all shifts.  JPEG's 8×8 blocks break that: residuals and fingerprints of JPEG images
are noisier on block boundaries, so the correlation's null variance is periodic in the shift, and at
the shifts that align the query's block grid with the fingerprint's — zero shift for a full frame, the
true offset for a crop — it is 1.6–1.85 times the mean (Dresden Nikons).  The plain PCE then exceeds its
χ²₁ null there: non-matching Dresden pairs reached PCE 21 at zero shift (p ≈ 4·10⁻⁶) and 48 in crop
searches whose Šidák bound was 40.  Here each shift's energy is the mean over the shifts of its own
phase ``(dy mod 8, dx mod 8)`` (the 11×11 window around the peak left out; shrunk towards the
all-shift energy by :data:`PHASE_PRIOR` shifts for small canvases), so ``z = peak/√energy`` is standard
normal under the null at every shift.  On images without blocks (simulations, PNG, resized images) all
phases agree and the value is the plain PCE; on JPEG frames and crops it is about half the plain PCE
(reported beside it as ``pce_global``, for comparison with ``forensics fingerprint match``).

The grid first: a weighted search
---------------------------------
The same energies show where the query's JPEG grid meets the fingerprint's: the aligning phase is the
one with the largest null energy (:func:`_grid_phase`; found only when clearly above the others, so not
on images without blocks).  A crop cut from a decoded JPEG lies on the camera's grid, so its true offset
is one of the ``n_A = n/64`` offsets of that phase.  Those offsets share half of the false-alarm budget
and the others the other half: position weights ``w_A = n/(2·n_A)`` and ``w_R = n/(2·(n − n_A))``, which
sum to ``n`` (weighted Bonferroni), and a peak's tail is ``Q(z)/w``.  On the Dresden 1024² crops the
threshold falls from PCE 40 to 33 on the grid (to 41.5 off it): 83 % of crops attributed instead of
76 %, with no false attribution.  A crop written again as JPEG after cropping carries its own grid and is
found off the camera's, at ``w_R``.  The choice of phase uses the energies only, never the normalised
peaks, so the bound holds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from forensics._shared.errors import InputError
from forensics.prnu.correlation import _log_tail

__all__ = ["BLOCK", "GRID_MIN_EXCESS", "GRID_SHARE", "GRID_SIGMAS", "PHASE_PRIOR"]

#: Period of the block grid whose phase the correlation's null variance depends on (JPEG's 8×8 blocks).
BLOCK = 8
#: Weight, in shifts, of the all-shift energy in each phase's energy (shrinks small canvases' noisy estimates).
PHASE_PRIOR = 256
#: Share of a search's false-alarm budget given to the offsets on the query's detected JPEG grid.
GRID_SHARE = 0.5
#: A block phase is the grid when its null energy exceeds the mean by this fraction (Dresden: 0.6–0.85) …
GRID_MIN_EXCESS = 0.1
#: … and by this many standard errors of its estimate.
GRID_SIGMAS = 8.0


@dataclass(frozen=True)
class _Peak:
    """The block-phase PCE of one correlation surface (see :func:`_block_pce`)."""

    pce: float
    pce_global: float
    shift: tuple[int, int]
    sign: int
    ncc: float
    weight: float = 1.0          # the peak's share of the weighted search (see _grid_phase)



def _phases(n: int) -> np.ndarray:
    """Block phase ``shift mod BLOCK`` of every circular shift index, shifts taken in ``(−n/2, n/2]``."""
    idx = np.arange(n)
    return np.where(idx > n // 2, idx - n, idx) % BLOCK


def _block_pce(corr: np.ndarray, rows: np.ndarray, cols: np.ndarray, exclusion: int, norms: float) -> _Peak:
    """Peak of ``corr`` over ``rows × cols`` normalised by the energy of the shifts in its block phase.

    JPEG's 8×8 blocks make the null variance of the correlation periodic in the shift: on the Dresden
    JPEGs, the shifts that align the query's block grid with the fingerprint's have 1.6–1.85 times the
    mean energy (others 0.8), and the plain PCE, with one energy for all shifts, then exceeds its χ²₁
    tail there (non-matching Dresden pairs: PCE 21 at zero shift, many crop searches above the Šidák
    bound).  Each shift's ``z`` is therefore the correlation over the root-mean-square of the shifts with
    the same phase ``(dy mod 8, dx mod 8)`` (the ``exclusion`` window around the peak left out, as in the
    PCE), shrunk towards the all-shift energy by :data:`PHASE_PRIOR` shifts so that a small canvas's noisy
    phase energies do not themselves inflate ``z``.  On images without blocks all phases agree and the
    statistic is the PCE.
    """
    h, w = corr.shape
    half = exclusion // 2
    if h < 2 * exclusion or w < 2 * exclusion:
        raise InputError(f"a correlation of shape {corr.shape} is too small for PCE with a {exclusion}×{exclusion} "
                         "exclusion window")
    ry, rx = _phases(h), _phases(w)
    one_y = (ry[None, :] == np.arange(BLOCK)[:, None]).astype(np.float64)   # (BLOCK, h)
    one_x = (rx[:, None] == np.arange(BLOCK)[None, :]).astype(np.float64)   # (w, BLOCK)
    sq = np.square(corr, dtype=np.float64)
    sums = one_y @ sq @ one_x
    del sq
    counts = np.outer(one_y.sum(axis=1), one_x.sum(axis=0))

    def energies(s: np.ndarray, c: np.ndarray) -> np.ndarray:
        overall = s.sum() / c.sum()
        return (s + PHASE_PRIOR * overall) / (c + PHASE_PRIOR)

    energy = energies(sums, counts)
    sub = corr[np.ix_(rows, cols)] / np.sqrt(energy[np.ix_(ry[rows], rx[cols])])
    (iy, ix), weight = _weighted_argmax(sub, ry[rows], rx[cols], _grid_phase(sums, counts))
    py, px = int(rows[iy]), int(cols[ix])
    # leave the window around the peak out of the energies
    wr = np.unique((py + np.arange(-half, half + 1)) % h)
    wc = np.unique((px + np.arange(-half, half + 1)) % w)
    window = np.square(corr[np.ix_(wr, wc)], dtype=np.float64)
    win_y = (ry[wr][None, :] == np.arange(BLOCK)[:, None]).astype(np.float64)
    win_x = (rx[wc][:, None] == np.arange(BLOCK)[None, :]).astype(np.float64)
    sums -= win_y @ window @ win_x
    counts -= np.outer(win_y.sum(axis=1), win_x.sum(axis=0))
    np.maximum(sums, 0.0, out=sums)
    energy = energies(sums, counts)
    peak = float(corr[py, px])
    dy = py - h if py > h // 2 else py
    dx = px - w if px > w // 2 else px
    e_phase = float(energy[ry[py], rx[px]])
    e_all = float(sums.sum() / counts.sum())
    if e_phase <= 0.0 or e_all <= 0.0 or norms == 0.0:
        return _Peak(0.0, 0.0, (dy, dx), 0, 0.0)
    sign = 1 if peak > 0 else (-1 if peak < 0 else 0)
    return _Peak(sign * peak * peak / e_phase, sign * peak * peak / e_all, (int(dy), int(dx)), sign,
                 float(np.clip(peak / norms, -1.0, 1.0)), weight)


def _grid_phase(sums: np.ndarray, counts: np.ndarray) -> tuple[int, int] | None:
    """The block phase of the shifts that align the query's JPEG grid with the fingerprint's, if any.

    Under the null the correlation's variance at shift ``s`` is ``Σ_p v_q(p)·v_K(p + s)`` over the
    block phases ``p`` of the two arrays' variances; when both are periodic alike (JPEG: noisier
    block boundaries) it is largest at the aligning phase (rearrangement inequality).  A phase counts
    as the grid when its energy exceeds the mean by :data:`GRID_MIN_EXCESS` and by :data:`GRID_SIGMAS`
    standard errors of an energy estimated from that many shifts (``√(2/m)`` for a white surface), so
    images without blocks (PNG, simulations, resampled fingerprints) have none.  The choice depends
    on the energies only, not on the normalised peaks, so it leaves the null of ``z`` unchanged.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_phase = sums / counts
    overall = float(sums.sum() / counts.sum())
    if not overall > 0.0:
        return None
    a = np.unravel_index(int(np.nanargmax(mean_phase)), mean_phase.shape)
    excess = float(mean_phase[a]) / overall - 1.0
    if excess < max(GRID_MIN_EXCESS, GRID_SIGMAS * math.sqrt(2.0 / float(counts[a]))):
        return None
    return int(a[0]), int(a[1])


def _weighted_argmax(z: np.ndarray, phase_rows: np.ndarray, phase_cols: np.ndarray,
                     grid: tuple[int, int] | None) -> tuple[tuple[int, int], float]:
    """The position of ``z`` with the smallest weighted tail ``Q(z)/w``, and its weight ``w``.

    Weighted Bonferroni over one test's ``n`` positions: the grid-aligned ones (``n_A``, the phase
    :func:`_grid_phase` found) share :data:`GRID_SHARE` of the false-alarm budget (``w_A = share·n/n_A``),
    the others the rest (``w_R = (1 − share)·n/n_R``); the weights sum to ``n``, so the Šidák count is
    unchanged and the bound holds whichever class the true offset is in.  A crop cut from a decoded
    JPEG sits on the grid (threshold of ``n/w_A`` positions: PCE 33 instead of 40 for 1024² crops of a
    3008×2000 frame at p_FA 10⁻³); one re-encoded after cropping has its own grid and is searched at
    ``n/w_R`` (PCE 41.5).  Without a grid every weight is 1 and this is the plain argmax.
    """
    flat = int(np.argmax(z))
    best = np.unravel_index(flat, z.shape)
    if grid is None:
        return (int(best[0]), int(best[1])), 1.0
    on_rows, on_cols = phase_rows == grid[0], phase_cols == grid[1]
    n = z.size
    n_a = int(on_rows.sum()) * int(on_cols.sum())
    if n_a == 0 or n_a == n:
        return (int(best[0]), int(best[1])), 1.0
    w_a, w_r = GRID_SHARE * n / n_a, (1.0 - GRID_SHARE) * n / (n - n_a)
    ra, ca = np.flatnonzero(on_rows), np.flatnonzero(on_cols)
    za = z[np.ix_(ra, ca)]
    ia = np.unravel_index(int(np.argmax(za)), za.shape)
    pos_a = (int(ra[ia[0]]), int(ca[ia[1]]))
    masked = z.copy()
    masked[np.ix_(ra, ca)] = -np.inf
    ib = np.unravel_index(int(np.argmax(masked)), masked.shape)
    pos_r = (int(ib[0]), int(ib[1]))
    return (pos_a, w_a) if _log_tail(z[pos_a], w_a) <= _log_tail(z[pos_r], w_r) else (pos_r, w_r)

