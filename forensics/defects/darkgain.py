"""The conversion gain g (e⁻/ADU) of a sensor, two ways, from the frames of a dark series.

* **Flat pairs** (the photon-transfer method, EMVA 1288): two flat fields of one exposure differ only by noise.
  With F' = F − O (O the pixel's offset plus its dark signal for the flat's exposure, from the dark series'
  lines) and k = mean(F'₁)/mean(F'₂) removing the pair's illumination difference, D = F'₁ − k·F'₂ has
  variance (μ₁ + k²μ₂)/g + (1 + k²)·σ_r² over the frame (the pixel pattern cancels), so
  g = (μ₁ + k²μ₂) / (Var D − (1 + k²)σ_r²).  Var D is the variance of D within 5 robust σ (hot pixels and
  cosmic rays left out).  Disjoint consecutive pairs give independent estimates; their spread is the interval.
* **The dark signal's shot noise** (a photon-transfer curve of dark charge): every pixel's scatter about its
  fitted line is read noise plus the shot noise of its own dark charge, so pixels of many different dark
  rates (the hot ones above all) give the gain without any light.  For pixels whose expected scatter is at
  least half shot noise (misfits left out), E[Σe²] = read part + shot part / g summed over the pixels gives g;
  ten interleaved subsets of those pixels give the interval.

Neither depends on the maker's figure (EGAIN in the header), which is reported beside them.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from forensics._shared.progress import Progress, no_progress

if TYPE_CHECKING:
    from forensics.defects.darkseries import GroupFit, LineFit, SeriesPlan

#: Points of D beyond this many robust σ are left out of Var D (hot pixels, cosmic-ray hits).
CLIP_SIGMA = 5.0
#: Pixels enter the dark-shot estimate when their expected shot variance is at least this multiple of the read
#: variance (at least half their scatter is shot noise: below that, the read noise's own uncertainty takes over).
SHOT_DOMINANCE = 1.0
#: Fewest pixels per subset for the dark-shot estimate.
MIN_PER_SUBSET = 10
#: Interleaved pixel subsets of the dark-shot estimate (their spread gives its interval).
SUBSETS = 10
LEVEL = 0.95


@dataclass
class GainEstimate:
    """A conversion gain (e⁻/ADU) with its interval and what it rests on."""

    method: str
    gain: float
    ci: tuple[float, float]
    parts: list[float] = field(default_factory=list)
    signal_adu: float | None = None
    n: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "gain_e_per_adu": self.gain, "ci": list(self.ci), "level": LEVEL,
                "parts": self.parts, "mean_signal_adu": self.signal_adu, "n": self.n, "notes": self.notes}


def _t_interval(values: Sequence[float]) -> tuple[float, tuple[float, float]]:
    v = np.asarray(values, float)
    mean = float(v.mean())
    if v.size < 2:
        return mean, (float("nan"), float("nan"))
    half = float(stats.t.ppf(0.5 + LEVEL / 2, v.size - 1)) * float(v.std(ddof=1)) / math.sqrt(v.size)
    return mean, (mean - half, mean + half)


# =========================================================================== flat pairs
@dataclass
class PairShared:
    """The offset map (offset + dark signal) of each flat condition, shipped once per worker."""

    offsets: dict[int, np.ndarray]
    read_noise: dict[int, float]
    saturation: float | None


def pair_item(shared: PairShared, item: tuple[int, str, str]) -> tuple[float, float, float, int]:
    """Work item: one flat pair → (g, mean signal, Var D, pixels used)."""
    from forensics.defects.darkseries import load_frame

    key, first, second = item
    offset = shared.offsets[key]
    f1 = load_frame(first).astype(np.float32).ravel()
    f2 = load_frame(second).astype(np.float32).ravel()
    valid = np.isfinite(offset)
    if shared.saturation is not None:
        valid &= (f1 < shared.saturation) & (f2 < shared.saturation)
    a = f1[valid] - offset[valid]
    b = f2[valid] - offset[valid]
    k = float(a.mean(dtype=np.float64) / b.mean(dtype=np.float64))
    d = a - np.float32(k) * b
    med = float(np.median(d))
    sigma = 1.4826 * float(np.median(np.abs(d - med)))
    keep = np.abs(d - med) < CLIP_SIGMA * sigma
    var = float(d[keep].var(dtype=np.float64, ddof=1))
    mu1, mu2 = float(a[keep].mean(dtype=np.float64)), float(b[keep].mean(dtype=np.float64))
    rn2 = shared.read_noise[key] ** 2
    gain = (mu1 + k * k * mu2) / (var - (1 + k * k) * rn2)
    return gain, 0.5 * (mu1 + mu2), var, int(keep.sum())


def flat_pair_gain(plan: "SeriesPlan", lines: Sequence["LineFit"], exposures: Sequence[np.ndarray],
                   read_noise: Sequence[float], bias_level: Sequence[float], executor: Any = None,
                   progress: Progress = no_progress) -> GainEstimate | None:
    """The gain from disjoint consecutive pairs of flat (or light) frames of one exposure and temperature group.

    A pair is matched to the temperature group of its set point (else its measured temperature), whose lines
    give each pixel's offset plus dark signal at the flat's exposure.  None without a usable pair.
    """
    from forensics._shared.parallel import resolve

    frames = plan.frames
    conditions: dict[tuple[float, int], list[int]] = {}
    notes = []
    for i in plan.flats:
        g = _matching_group(plan, i)
        if g is None:
            notes.append(f"{frames[i].name}: no dark group at its temperature; not used for the gain")
            continue
        conditions.setdefault((frames[i].exposure_s, g), []).append(i)
    items, offsets, rn = [], {}, {}
    for (t, g), members in conditions.items():
        members = sorted(members, key=lambda i: (frames[i].captured or 0.0, frames[i].path))
        key = len(offsets)
        line = lines[g]
        offsets[key] = (line.offset + line.rate * t).astype(np.float32)
        rn[key] = read_noise[g]
        items += [(key, frames[members[j]].path, frames[members[j + 1]].path) for j in range(0, len(members) - 1, 2)]
    if not items:
        return None
    from forensics.defects.darkseries import _default_saturation, _frame_dtype

    shared = PairShared(offsets, rn, _default_saturation(_frame_dtype(items[0][1])))
    results = list(resolve(executor).map(pair_item, items, shared=shared, progress=progress,
                                         desc="dark series: flat pairs"))
    gains = [r[0] for r in results]
    mean, ci = _t_interval(gains)
    if len(gains) == 1:
        # one pair: only the sampling error of Var D, √(2/N) relative (the pixels are independent)
        rel = math.sqrt(2.0 / results[0][3])
        z = float(stats.norm.ppf(0.5 + LEVEL / 2))
        ci = (mean * (1 - z * rel), mean * (1 + z * rel))
        notes.append("one pair: the interval holds the variance's sampling error only")
    return GainEstimate("flat pairs (photon transfer)", mean, ci, gains, float(np.mean([r[1] for r in results])),
                        len(gains), notes)


def _matching_group(plan: "SeriesPlan", index: int) -> int | None:
    fr = plan.frames[index]
    for g, sp in enumerate(plan.setpoints):
        if sp is not None and fr.set_temperature_c is not None and round(fr.set_temperature_c, 1) == sp:
            return g
    if fr.temperature_c is None:
        return 0 if len(plan.groups) == 1 else None
    best, gap = None, math.inf
    for g, members in enumerate(plan.groups):
        temps = [plan.frames[i].temperature_c for i in members if plan.frames[i].temperature_c is not None]
        if temps and abs(float(np.median(temps)) - fr.temperature_c) < gap:
            best, gap = g, abs(float(np.median(temps)) - fr.temperature_c)
    from forensics.defects.darkseries import SETPOINT_TOLERANCE_C

    return best if gap <= SETPOINT_TOLERANCE_C else None


# =========================================================================== the dark signal's shot noise
def dark_shot_gain(groups: Sequence["GroupFit"], gain_prior: float) -> GainEstimate | None:
    """The gain from every pixel's scatter about its line (see the module notes); None with too few pixels.

    ``gain_prior`` only selects the shot-noise-dominated pixels (expected shot variance ≥
    :data:`SHOT_DOMINANCE` × read variance); the estimate does not depend on it otherwise.
    """
    esq, read_part, shot, dof = [], [], [], []
    for grp in groups:
        if grp.residual_sq is None or grp.shot_charge is None:
            continue
        nu = grp.used.astype(np.float64) - 2
        read = (grp.read_noise ** 2 + grp.offset_jitter ** 2) * nu
        with np.errstate(invalid="ignore"):
            sel = (nu >= 3) & np.isfinite(grp.shot_charge) & (grp.shot_charge / gain_prior >= SHOT_DOMINANCE * read)
        sel &= np.isfinite(grp.residual_sq) & ~grp.misfit  # a pixel off its line scatters for another reason
        if not sel.any():
            continue
        esq.append(grp.residual_sq[sel])
        read_part.append(read[sel])
        shot.append(grp.shot_charge[sel])
        dof.append(nu[sel])
    if not esq:
        return None
    e, rp, sh, nu_all = (np.concatenate(x) for x in (esq, read_part, shot, dof))
    if e.size < MIN_PER_SUBSET * SUBSETS:
        return None
    whole = _solve_gain(e, rp, sh)
    parts = [_solve_gain(e[s::SUBSETS], rp[s::SUBSETS], sh[s::SUBSETS]) for s in range(SUBSETS)]
    parts = [p for p in parts if math.isfinite(p)]
    _, ci = _t_interval(parts)
    return GainEstimate("dark signal's shot noise (pixels' scatter about their lines)", whole, ci, parts,
                        float(np.median(sh / nu_all)), int(e.size),
                        [f"{e.size} pixels whose expected scatter is at least half shot noise; interval from "
                         f"{SUBSETS} interleaved subsets"])


def _solve_gain(esq: np.ndarray, read: np.ndarray, shot: np.ndarray) -> float:
    """g from E[Σe²] = read + shot/g summed over pixels: g = Σ shot / (Σ Σe² − Σ read).

    Sums, not medians: under shot noise a pixel's residual sum of squares is a weighted sum of χ²₁ variables
    dominated by its long exposures, whose median falls below the χ²_ν median — the mean is exact.
    """
    excess = float(esq.sum() - read.sum())
    return float(shot.sum()) / excess if excess > 0 else float("nan")
