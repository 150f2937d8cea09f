"""Cosmic-ray rejection and the diagnostic pass of a dark-series fit (work items of the execution layer).

Each **round** streams a temperature group's frames against the current per-pixel lines and keeps, per pixel,
its most discrepant sample: z = e/√Var(e), with e the least-squares residual and Var(e) its exact variance
under the read + shot noise model (:func:`residual_variance`).  Where that z exceeds ``k`` the sample is a
cosmic-ray hit; the hit's 8 neighbours whose own most discrepant sample lies in the same frame are hits too
from ``k_grow`` (a track spreads its charge).  Only one sample per pixel goes per round: a hit pulls the whole
line, so that every other sample of the pixel looks off too, and only the worst one is the hit.  A second
round catches a pixel hit twice.

The **diagnostic pass** then streams the frames once more against the final lines: per frame its common-mode
residual (the median over pixels of y − a − r·t), its median dark signal (of y − a), its noise against the model, its read noise for biases; per
pixel the residual sum of squares.  A pixel whose residuals are far beyond the noise model (χ² p below
½/pixels) does not follow a line — a hot pixel whose dark signal is not linear in the exposure, a random
telegraph pixel — and is reported as a *misfit* (its rate is still the slope of its samples, at most ``rounds``
of its most discrepant ones left out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from forensics._shared.progress import Progress
from forensics.defects.darkseries import (
    GroupSums,
    LineFit,
    SeriesPlan,
    _check_shape,
    chunk_items,
    load_frame,
    solve_lines,
)

Drops = tuple[np.ndarray, np.ndarray, np.ndarray]  # (pixel, frame within group, value) of samples left out
_NO_DROPS: Drops = (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0))


@dataclass(frozen=True)
class NoiseModel:
    """Each group's median bias B and read noise σ_r, the gain g and the outlier test's thresholds."""

    bias_level: list[float]
    read_noise: list[float]
    gain: float
    k: float
    k_grow: float


@dataclass
class RoundState:
    """What every work item of a pass needs (shipped once per worker): each group's lines and the noise model.

    28 bytes per pixel per group (seven float32 maps).
    """

    shape: tuple[int, int]
    lines: list[dict[str, np.ndarray]]
    noise: NoiseModel
    dropped: list[dict[int, np.ndarray]]


@dataclass
class FrameStats:
    """One frame's measurements in the diagnostic pass."""

    local: int
    common_residual: float
    residual_sigma: float
    dark_level: float
    noise_ratio: float
    frame_read_noise: float | None
    tested: int


def residual_variance(t: float, offset: np.ndarray, rate: np.ndarray, n: np.ndarray, mean_t: np.ndarray,
                      sxx: np.ndarray, sx: np.ndarray, t3: np.ndarray, bias: float, read_noise: float,
                      gain: float) -> np.ndarray:
    """Variance of the least-squares residual of the sample at exposure ``t`` under the noise model.

    With σ_f² = A + B·t_f (A = σ_r² + max(a − B₀, 0)/g, B = max(r, 0)/g) and leverages h_fj = 1/n + u_f·u_j/Sxx
    (u = t − t̄): Var e_f = σ_f²(1 − 2h_ff) + Σ_j h_fj²σ_j² = A(1 − h_ff) + B·[t_f(1 − 2h_ff) + Σt/n² + 2u_f/n +
    u_f²·Σu²t/Sxx²].  Exact where the noise grows with the exposure (shot noise), where the homoscedastic
    σ_f²(1 − h_ff) would overstate a long exposure's residual variance and hide hits in it.
    """
    t32 = np.float32(t)
    inv_gain = np.float32(1.0 / gain)
    a_term = np.float32(read_noise ** 2) + np.maximum(offset - np.float32(bias), 0) * inv_gain
    b_term = np.maximum(rate, 0) * inv_gain
    u = t32 - mean_t
    h = 1 / n + u * u / sxx
    shot = t32 * (1 - 2 * h) + sx / (n * n) + 2 * u / n + u * u * t3 / (sxx * sxx)
    return a_term * (1 - h) + b_term * shot


def _frame_z(state: RoundState, group: int, local: int, path: str, t: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's values, residuals, z and validity (samples already left out are invalid)."""
    fit = state.lines[group]
    nm = state.noise
    data = load_frame(path)
    _check_shape(data, state.shape, path)
    y = data.astype(np.float32).ravel()
    e = y - fit["offset"] - fit["rate"] * np.float32(t)
    with np.errstate(divide="ignore", invalid="ignore"):
        var = residual_variance(t, fit["offset"], fit["rate"], fit["n"], fit["mean_t"], fit["sxx"], fit["sx"],
                                fit["t3"], nm.bias_level[group], nm.read_noise[group], nm.gain)
        z = e / np.sqrt(var)
    valid = np.isfinite(z) & (var > 0)
    gone = state.dropped[group].get(local)
    if gone is not None and gone.size:
        valid[gone] = False
    return y, e, z, valid


def test_item(state: RoundState, item: tuple[int, tuple[tuple[int, str, float, bool], ...]]
              ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Work item of a round: per pixel, the largest z over a chunk's frames, its frame and its value."""
    group, frames = item
    size = state.shape[0] * state.shape[1]
    zmax = np.full(size, -np.inf, np.float32)
    where = np.full(size, -1, np.int32)
    value = np.zeros(size, np.float32)
    for local, path, t, _bias in frames:
        y, _, z, valid = _frame_z(state, group, local, path, t)
        better = valid & (z > zmax)
        zmax[better], where[better], value[better] = z[better], local, y[better]
    return group, zmax, where, value


def diagnose_item(state: RoundState, item: tuple[int, tuple[tuple[int, str, float, bool], ...]]
                  ) -> tuple[int, list[FrameStats], np.ndarray]:
    """Work item of the diagnostic pass: each frame's statistics and the chunk's per-pixel residual sum of squares."""
    group, frames = item
    fit = state.lines[group]
    esq = np.zeros(state.shape[0] * state.shape[1], np.float64)
    out = []
    for local, path, t, bias in frames:
        y, e, z, valid = _frame_z(state, group, local, path, t)
        kept = valid & (z <= state.noise.k)
        level = float(np.median(y[kept] - fit["offset"][kept])) if kept.any() else math.nan
        ek = e[kept]
        centre = float(np.median(ek)) if ek.size else math.nan
        sigma = 1.4826 * float(np.median(np.abs(ek - centre))) if ek.size else math.nan
        zk = z[kept]
        med_z = float(np.median(zk)) if zk.size else math.nan
        ratio = 1.4826 * float(np.median(np.abs(zk - med_z))) if zk.size else math.nan
        frame_rn = None
        if bias and kept.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                q = 1 - 1 / fit["n"][kept] - fit["mean_t"][kept] ** 2 / fit["sxx"][kept]
                scaled = e[kept] / np.sqrt(q)
            scaled = scaled[np.isfinite(scaled)]
            frame_rn = 1.4826 * float(np.median(np.abs(scaled - np.median(scaled)))) if scaled.size else None
        out.append(FrameStats(local, centre, sigma, level, ratio, frame_rn, int(kept.sum())))
        ev = np.where(valid, e, 0).astype(np.float64)
        esq += ev * ev
    return group, out, esq


def mark_hits(zmax: np.ndarray, where: np.ndarray, value: np.ndarray, shape: tuple[int, int], k: float,
              k_grow: float) -> Drops:
    """The samples a round takes out: z above ``k``, and their neighbours' samples of the same frame above ``k_grow``."""
    hit = (zmax > k).reshape(shape)
    if k_grow < k and hit.any():
        z2, w2 = zmax.reshape(shape), where.reshape(shape)
        grown = np.zeros(shape, bool)
        h, w = shape
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if not (dy or dx):
                    continue
                ys, yd = slice(max(0, -dy), h - max(0, dy)), slice(max(0, dy), h - max(0, -dy))
                xs, xd = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w - max(0, -dx))
                # a neighbour at (y+dy, x+dx) of a hit at (y, x), whose worst sample is in the hit's frame
                grown[yd, xd] |= hit[ys, xs] & (w2[yd, xd] == w2[ys, xs]) & (z2[yd, xd] > k_grow)
        hit |= grown
    idx = np.flatnonzero(hit.ravel())
    return idx.astype(np.int64), where[idx].astype(np.int32), value[idx].astype(np.float64)


@dataclass
class RobustFit:
    """The lines after the rounds, the samples taken out, the diagnostics and the misfit pixels of every group."""

    lines: list[LineFit]
    drops: list[Drops]
    stats: dict[tuple[int, int], FrameStats]
    residual_sq: list[np.ndarray]
    jitter: list[float]
    misfit: list[np.ndarray]


def robust_fit(plan: SeriesPlan, sums: list[GroupSums], exposures: list[np.ndarray], noise: NoiseModel, rounds: int,
               ex: Any, progress: Progress) -> RobustFit:
    """The rounds, the diagnostic pass and the misfit test (see the module notes): ``rounds + 1`` passes."""
    shape = sums[0].shape
    drops: list[Drops] = [_NO_DROPS for _ in sums]
    lines = [solve_lines(s, t) for s, t in zip(sums, exposures)]
    items = chunk_items(plan, exposures)
    for round_index in range(rounds):
        state = _state(shape, sums, lines, drops, noise)
        best: list[list[np.ndarray] | None] = [None] * len(sums)
        for g, zmax, where, value in ex.map(test_item, items, shared=state, progress=progress,
                                            desc=f"dark series: cosmic rays {round_index + 1}"):
            if best[g] is None:
                best[g] = [zmax, where, value]
            else:
                cur = best[g]
                better = zmax > cur[0]
                for arr, new in zip(cur, (zmax, where, value)):
                    arr[better] = new[better]
        for g in range(len(sums)):
            zmax, where, value = best[g]  # type: ignore[misc]
            new = mark_hits(zmax, where, value, shape, noise.k, noise.k_grow)
            drops[g] = tuple(np.concatenate([a, b]) for a, b in zip(drops[g], new))  # type: ignore[assignment]
        lines = [solve_lines(s, t, *d) for s, t, d in zip(sums, exposures, drops)]
    state = _state(shape, sums, lines, drops, noise)
    stats: dict[tuple[int, int], FrameStats] = {}
    esq: list[np.ndarray | None] = [None] * len(sums)
    for g, frame_stats, part in ex.map(diagnose_item, items, shared=state, progress=progress,
                                       desc="dark series: diagnostics"):
        stats.update({(g, fs.local): fs for fs in frame_stats})
        esq[g] = part if esq[g] is None else esq[g] + part
    jitter = [offset_jitter(g, plan.biases(g), stats) for g in range(len(plan.groups))]
    misfit = [misfits(lines[g], esq[g], jitter[g], noise, g) for g in range(len(sums))]  # type: ignore[arg-type]
    return RobustFit(lines, drops, stats, esq, jitter, misfit)  # type: ignore[arg-type]


def _state(shape: tuple[int, int], sums: list[GroupSums], lines: list[LineFit], drops: list[Drops],
           noise: NoiseModel) -> RoundState:
    dropped = []
    for s, d in zip(sums, drops):
        pix = np.concatenate([s.drop_pixel, d[0]])
        fr = np.concatenate([s.drop_frame, d[1]])
        order = np.argsort(fr, kind="stable")
        pix, fr = pix[order], fr[order]
        bounds = np.flatnonzero(np.diff(fr)) + 1
        dropped.append({int(fr[p[0]]): pix[p] for p in np.split(np.arange(fr.size), bounds) if p.size})
    maps = [{name: np.asarray(getattr(li, name), np.float32)
             for name in ("offset", "rate", "n", "mean_t", "sxx", "sx", "t3")} for li in lines]
    return RoundState(shape, maps, noise, dropped)


def offset_jitter(g: int, biases: np.ndarray, stats: dict[tuple[int, int], FrameStats]) -> float:
    """σ_o: the scatter of the biases' common-mode residuals (the frame-to-frame offset jitter), 0 if unknown.

    ``biases``: which of the group's frames are biases (:meth:`SeriesPlan.biases`)."""
    values = [stats[(g, local)].common_residual for local in range(biases.size)
              if biases[local] and (g, local) in stats and math.isfinite(stats[(g, local)].common_residual)]
    return float(np.std(values, ddof=1)) if len(values) >= 3 else 0.0


def expected_residual_sq(line: LineFit, bias: float, read_noise: float, jitter: float, gain: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """E[Σe²] under the noise model, Σ_f (1 − h_f)σ_f², and its dark-charge part times g (the shot term)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        charge0 = np.maximum(line.offset - bias, 0)
        shot = charge0 * (line.n - 2) + np.maximum(line.rate, 0) * (line.sx - line.sx / line.n - line.t3 / line.sxx)
        return (read_noise ** 2 + jitter ** 2) * (line.n - 2) + shot / gain, shot


def misfits(line: LineFit, esq: np.ndarray, jitter: float, noise: NoiseModel, g: int) -> np.ndarray:
    """Pixels whose residual sum of squares is beyond the noise model at p < ½/pixels (χ² with n − 2 d.o.f.)."""
    expected, _ = expected_residual_sq(line, noise.bias_level[g], noise.read_noise[g], jitter, noise.gain)
    nu = line.n - 2
    with np.errstate(invalid="ignore", divide="ignore"):
        statistic = esq / expected * nu
        ok = np.isfinite(statistic) & (nu >= 1)
    out = np.zeros(esq.size, bool)
    if ok.any():
        out[ok] = stats.chi2.sf(statistic[ok], nu[ok]) < 0.5 / esq.size
    return out
