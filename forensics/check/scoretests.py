"""The channels' tests of a candidate's signature against the fitted model's residuals.

pixel — Gaussian score (Lagrange-multiplier) test for global parameters, likelihood ratio of a per-block
random effect for fixed patterns; variance — score test on the log binned variances; growth — Poisson
score test with a quasi-Poisson dispersion; spatial — projection of Ripley's L on the candidate's
direction, calibrated by the null simulations.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats

from forensics.check.classes import STK
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel
from forensics.check.result import ChannelTest
from forensics.check.signatures import Signature


def random_effect_lr(zb: np.ndarray, ab: np.ndarray) -> tuple[float, float]:
    """Likelihood ratio for a per-block random effect: z_b ~ N(0, 1 + t·a_b), t ≥ 0. Returns (LR, t̂)."""
    keep = ab > 1e-12
    zb, ab = zb[keep], ab[keep]
    if zb.size == 0:
        return 0.0, 0.0
    score = 0.5 * float(np.sum(ab * (zb**2 - 1)))
    if score <= 0:
        return 0.0, 0.0

    def negll(u: float) -> float:
        t = math.exp(u)
        s = 1 + t * ab
        return float(np.sum(0.5 * np.log(s) - 0.5 * zb**2 * t * ab / s))

    lo = math.log(1e-8 / ab.max())
    hi = math.log(1e8 / ab.min())
    res = optimize.minimize_scalar(negll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return max(0.0, -2.0 * res.fun), math.exp(res.x)


def score_pixel(ev: Evidence, fitted: FittedModel, sigs: list[Signature], z: np.ndarray, n_obs: int) -> list[ChannelTest]:
    px = fitted.pixels
    tests = []
    sw = np.sqrt(px.weight)
    keep = ev.usable & (px.classes != STK)
    glob_cols = []
    glob_names = []
    for s in sigs:
        raw = np.where(keep, s.x * sw, 0.0)
        raw_norm = float(np.sum(raw**2))
        if raw_norm <= 0 or float(np.max(np.abs(raw))) < 1e-4:  # no signature (up to rounding) in these data
            continue
        xp = fitted.projector.project(raw) if s.pixel_local or s.blocks is None else raw
        xp = np.where(keep, xp, 0.0)
        if s.blocks is not None:
            blk = np.broadcast_to(s.blocks[None], xp.shape)
            m = (blk >= 0) & keep
            nblk = int(s.blocks.max()) + 1
            zb_num = np.bincount(blk[m], (xp * z)[m], minlength=nblk)
            ab = np.bincount(blk[m], (xp * xp)[m], minlength=nblk)
            used = ab > 1e-12 * max(ab.max(), 1e-300)
            zb = np.where(used, zb_num / np.sqrt(np.where(used, ab, 1)), 0.0)
            lr, t = random_effect_lr(zb[used], ab[used])
            frac = float(np.sum(ab)) / raw_norm
            tests.append(ChannelTest("pixel", lr, 1, n_obs,
                                     f"{s.name}: random-effect LR {lr:.4g} over {int(used.sum())} blocks "
                                     f"(typical size {math.sqrt(t):.3g}; {frac:.0%} of the signature survives the "
                                     "model's own parameters)", boundary=True, absorbed=frac < 0.05))
        else:
            frac = float(np.sum(xp**2)) / raw_norm
            if frac < 1e-6:
                tests.append(ChannelTest("pixel", 0.0, 0, n_obs, f"{s.name}: absorbed by the model's parameters",
                                         absorbed=True))
                continue
            glob_cols.append(xp)
            glob_names.append((s.name, frac))
    if glob_cols:
        H = np.array([[np.sum(a * b) for b in glob_cols] for a in glob_cols])
        g = np.array([np.sum(a * z) for a in glob_cols])
        lm = float(g @ np.linalg.pinv(H) @ g)
        names = ", ".join(n for n, _ in glob_names)
        frac = min(f for _, f in glob_names)
        tests.append(ChannelTest("pixel", lm, len(glob_cols), n_obs,
                                 f"{names}: score LM {lm:.4g} on {n_obs} pixel means ({frac:.0%} of the signature "
                                 "survives the model's own parameters)", absorbed=frac < 0.05))
    return tests


def score_variance(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    px = fitted.pixels
    if not sigs or not len(px.bins.observed):
        return []
    e = np.log(px.bins.observed) - np.log(fitted.variance_pred)
    w = px.bins.df / 2.0
    X = np.array([s.x for s in sigs])
    if fitted.variance_jac is not None:
        J = fitted.variance_jac
        coef = np.linalg.lstsq((J * w) @ J.T, (J * w) @ X.T, rcond=None)[0]
        X = X - coef.T @ J
    H = (X * w) @ X.T
    g = (X * w) @ e
    lm = float(g @ np.linalg.pinv(H) @ g)
    return [ChannelTest("variance", lm, len(sigs), len(e),
                        f"{', '.join(s.name for s in sigs)}: score LM {lm:.4g} on {len(e)} binned variances")]


def score_growth(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    out = []
    if len(ev.times) < 3:
        return out
    obs, mu = ev.defects.increments(fitted.expected)
    mu = np.maximum(mu, 1e-9)
    M = fitted.growth_jac
    for s in sigs:
        x = s.x.copy()
        if M is not None and len(M):
            coef = np.linalg.lstsq((M / mu) @ M.T, (M / mu) @ x, rcond=None)[0]
            x = x - coef @ M
        info = float(np.sum(x * x / mu))
        raw = float(np.sum(s.x * s.x / mu))
        if raw <= 0 or info <= 1e-9 * raw:
            continue
        u = float(np.sum(x * (obs - mu) / mu))
        mu_alt = np.maximum(mu + x * (u / info), 1e-9)  # one Fisher-scoring step towards the alternative
        pearson_alt = float(np.sum((obs - mu_alt) ** 2 / mu_alt))
        df_alt = max(len(obs) - (0 if M is None else M.shape[0]) - 1, 1)
        # quasi-Poisson dispersion, applied only when the counts are clearly over-dispersed (pre-test at 1 %)
        phi = pearson_alt / df_alt if pearson_alt > stats.chi2.ppf(0.99, df_alt) else 1.0
        lm = u * u / info / phi
        out.append(ChannelTest("growth", lm, 1, int(max(obs.sum(), 1)),
                               f"{s.name}: Poisson score z {u / math.sqrt(info * phi):+.3g} on {len(obs)} count "
                               f"increments (dispersion {phi:.2g})"))
    return out


def score_spatial(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    out = []
    null = fitted.spatial_null
    if null is None:
        return out
    l_obs = ev.defects.ripley_l(ev.defects.sites)
    u_obs = (l_obs - null["mean"]) / null["sd"]
    u_sim = (null["sims"] - null["mean"]) / null["sd"]
    for s in sigs:
        d = s.x / max(float(np.linalg.norm(s.x)), 1e-12)
        t_obs = float(d @ u_obs)
        t_sim = u_sim @ d
        zval = (t_obs - float(t_sim.mean())) / max(float(t_sim.std(ddof=1)), 1e-9)
        lm = zval * zval if zval > 0 else 0.0
        out.append(ChannelTest("spatial", lm, 1, len(ev.defects.sites),
                               f"{s.name}: Ripley L moves the way this effect predicts, z {zval:+.3g} against "
                               f"{len(t_sim)} simulations of the fitted model"))
    return out
