"""The channels' tests of a candidate's signature against the fitted model's residuals.

pixel — Gaussian score (Lagrange-multiplier) test for global parameters; for fixed patterns, the likelihood
ratio of a per-block random effect calibrated by the split-half cross-product (:func:`split_half_test`: a
pattern is what the two halves of the repeats share, so neither its presence nor the noise scale depends on the
noise floor, and the statistic's variance is measured over tiles, so spatially correlated noise does not
inflate it); variance — score test on the log binned variances; growth — Poisson
score test with a quasi-Poisson dispersion; spatial — projection of Ripley's L on the candidate's
direction, calibrated by the null simulations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from forensics.stats.tails import chi2_ppf

from forensics.check.streams import PATTERN_SIZE_STREAM
from forensics.check.classes import NORMAL, STK
from forensics.check.evidence import Evidence
from forensics.check.fit import FittedModel
from forensics.check.pixels import log_variance, pattern_size
from forensics.check.result import ChannelTest
from forensics.check.signatures import Signature

#: Side of the square tiles over which the split-half statistic's variance is measured: much larger than the
#: correlation length of demosaiced, JPEG-compressed noise (a few pixels), small enough for ~1000 tiles at 512².
TILE = 16


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
    from scipy import optimize  # here, not at import: scipy.optimize takes 0.2–0.3 s to import

    res = optimize.minimize_scalar(negll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return max(0.0, -2.0 * res.fun), math.exp(res.x)


@dataclass(frozen=True)
class SplitHalf:
    """The split-half cross-product test of a fixed pattern.

    ``t`` = Σ_b u_a·u_b / Σ_b a_b² estimates the pattern's variance per block (in the signature's units, as
    the residuals show it), with u_a, u_b the signature-weighted sums of the two halves' residuals over block b
    and a_b the signature's weight there.  Its null mean is 0 whatever the noise floor, because the halves'
    noises are independent.  ``z`` = t / se(t), with se(t) from the spread of the statistic over
    ``tiles`` tiles of ``TILE`` × ``TILE`` pixels.  ``noise`` = Σ_b (u_a² − u_a·u_b) / Σ_b a_b is the noise
    variance of the first half's residuals relative to the floor (1 when the floor is right), also free of the
    floor; ``inflation`` is the tiles' variance of the statistic over the variance it would have if blocks were
    independent (≈ 1 for white noise; more when the noise is spatially correlated).
    """

    z: float
    t: float
    se: float
    tiles: int
    noise: float = 1.0
    inflation: float = 1.0


def tile_index(shape: tuple[int, int], size: int = TILE) -> np.ndarray:
    """Index of each pixel's ``size × size`` tile (row-major)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    return (yy // size) * (-(-w // size)) + xx // size


def block_tiles(blocks: np.ndarray, tiles: np.ndarray, n_blocks: int) -> np.ndarray:
    """The tile of every block: that of its first pixel (a block spanning tiles — a column — goes whole to one
    tile, so blocks never straddle the statistic's units)."""
    m = blocks >= 0
    first = np.full(n_blocks, np.iinfo(np.int64).max, np.int64)
    flat = np.flatnonzero(m.ravel())
    np.minimum.at(first, blocks.ravel()[flat], flat)
    out = np.zeros(n_blocks, np.int64)
    used = first < np.iinfo(np.int64).max
    out[used] = tiles.ravel()[first[used]]
    return out


def split_half_test(ua: np.ndarray, ub: np.ndarray, ab: np.ndarray, tile: np.ndarray) -> SplitHalf:
    """The split-half cross-product test over blocks (``ua``, ``ub``: each half's signature-weighted residual
    sum per block; ``ab``: the signature's weight per block; ``tile``: each block's tile).

    The variance of Σ u_a·u_b is measured, not assumed: the sum over each tile less its expected share of the
    total (t·Σ_tile a_b², so that a present pattern does not count as noise), squared and summed over tiles.
    Tiles are far larger than the noise's correlation length, so their sums are nearly independent.
    """
    c = ua * ub
    a2 = ab * ab
    _, tile = np.unique(tile, return_inverse=True)
    n_tiles = int(tile.max()) + 1 if tile.size else 0
    total_a2 = float(a2.sum())
    if n_tiles < 2 or total_a2 <= 0:
        return SplitHalf(0.0, 0.0, math.inf, n_tiles)
    s_g = np.bincount(tile, c, minlength=n_tiles)
    a_g = np.bincount(tile, a2, minlength=n_tiles)
    t = float(s_g.sum()) / total_a2
    var = n_tiles / (n_tiles - 1) * float(np.sum((s_g - t * a_g) ** 2))
    se = math.sqrt(var) / total_a2 if var > 0 else math.inf
    independent = float(np.sum((c - t * a2) ** 2))
    inflation = var / independent if independent > 0 else 1.0
    noise = float(np.sum(ua * ua - c)) / float(ab.sum()) if ab.sum() > 0 else 1.0
    return SplitHalf(t / se if se > 0 else 0.0, t, se, n_tiles, noise, inflation)


def score_pixel(ev: Evidence, fitted: FittedModel, sigs: list[Signature], z: np.ndarray, n_obs: int) -> list[ChannelTest]:
    """The pixel channel's tests of the candidates' signatures against the fitted model's residuals ``z``
    (first half, weighted, projected off the model's own pixel-local patterns).

    A fixed pattern (a signature with blocks) is tested as a random effect calibrated by the split halves
    (:func:`_pattern_test`); global parameters by one joint score test on the *second* half's residuals
    (:func:`second_half_z`), the signatures projected off the model's own global parameters too
    (:func:`held_out_score`).
    """
    px = fitted.pixels
    tests = []
    sw = np.sqrt(px.weight)
    keep = ev.usable & (px.classes != STK)
    glob_cols = []
    glob_names = []
    zb = None
    tiles = tile_index(ev.meas.shape)
    for s in sigs:
        raw = np.where(keep, s.x * sw, 0.0)
        raw_norm = float(np.sum(raw**2))
        if raw_norm <= 0 or float(np.max(np.abs(raw))) < 1e-4:  # no signature (up to rounding) in these data
            continue
        xp = (fitted.projector.project(raw, keep_common=not s.random_effect) if s.pixel_local or s.blocks is None
              else raw)
        xp = np.where(keep, xp, 0.0)
        if s.blocks is not None:
            if zb is None:
                zb = second_half_z(ev, fitted, keep)
            tests.append(_pattern_test(ev, fitted, s, xp, z, zb, tiles, keep, raw_norm, n_obs))
        else:
            frac = float(np.sum(xp**2)) / raw_norm
            if frac < 1e-6:
                tests.append(ChannelTest("pixel", 0.0, 0, n_obs, f"{s.name}: absorbed by the model's parameters",
                                         absorbed=True))
                continue
            glob_cols.append(xp)
            glob_names.append((s.name, frac))
    if glob_cols:
        if zb is None:
            zb = second_half_z(ev, fitted, keep)
        cols = glob_cols
        model_cols = [np.where(keep, c, 0.0) for c in fitted.global_columns]
        lm, fracs = held_out_score(cols, zb, model_cols)
        shares = [f * s for (_, f), s in zip(glob_names, fracs)]
        # a signature (almost) in the span of the model's own parameters is theirs: what survives the projection
        # is a sliver that the held-out half reads with the first half's parameter errors and the model's misfit
        # (a dark series' DSNU offset, under 0.5 % left: LM 75; in-sample such a sliver is orthogonal to the residuals)
        live = [k for k, share in enumerate(shares) if share >= ABSORBED_SHARE]
        if len(live) < len(cols):
            lm = held_out_score([cols[k] for k in live], zb, model_cols)[0] if live else 0.0
        names = ", ".join(n for n, _ in glob_names)
        frac = min(shares)
        tests.append(ChannelTest("pixel", lm, len(live), n_obs,
                                 f"{names}: score LM {lm:.4g} on {n_obs} held-out pixel means ({frac:.0%} of the "
                                 "signature survives the model's own parameters)", absorbed=not live))
    return tests


#: A global signature with less than this share of its norm left after the projection off the model's own
#: parameters is absorbed by them (not tested: :func:`score_pixel`, :func:`score_variance`).
ABSORBED_SHARE = 0.05


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Σ a·b in float64 by numpy's own pairwise summation — not BLAS, whose threads (more in the main process than
    in a worker) change the order of the sums and so the last bits (a check in processes then differed from the
    same check in one)."""
    return float(np.sum(np.multiply(a, b, dtype=np.float64)))


def held_out_score(columns: list[np.ndarray], zb: np.ndarray,
                   model_columns: list[np.ndarray]) -> tuple[float, list[float]]:
    """The joint score statistic of the signature ``columns`` against the second half's residuals ``zb`` — the
    columns projected off the model's own global parameters (``model_columns``, all weighted alike) — and the
    share of each column's norm that survives that projection.

    Why the held-out half: the model's pixel-local values (a DSNU per pixel) are fitted to the first half, and
    where the prediction bends with them (near 0 DN, where only the frames that never read 0 are kept and the
    truncated mean's slope is well under 1) the first half's residuals keep a trace of each value's own noise
    that no projection removes; a global signature that contrasts dark with light frames reads it.  8-bit DSNU
    seed 1: nonlinearity's score LM 50.7 on the first half, 2.1 on the second; a hidden nonlinearity 498 → 372
    (8bit), 24,357 → 24,131 (project).  Why the projection: the global parameters fitted to the first half are
    off by their estimation error, which the second half's residuals show along their columns (an in-sample
    residual is orthogonal to them by the fit's own equations).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> m = rng.standard_normal(500)
    >>> x = m + rng.standard_normal(500)
    >>> lm, frac = held_out_score([x], 3.0 * m, [m])   # residuals along the model's own column: no evidence
    >>> round(lm, 6), 0.4 < frac[0] < 0.6
    (0.0, True)
    """
    # sums column by column (a (pixels × k) matrix of a 320 × 240 series with 100 conditions is 0.4 GB)
    G = [np.asarray(c) for c in model_columns if float(_dot(c, c)) > 0]
    gram = np.array([[float(_dot(a, b)) for b in G] for a in G]) if G else np.zeros((0, 0))
    pinv = np.linalg.pinv(gram) if G else gram
    projected = []
    for x in columns:
        x = np.asarray(x, float)
        coef = pinv @ np.array([float(_dot(c, x)) for c in G]) if G else []
        for c, k in zip(G, coef):
            x = x - k * c
        projected.append(x)
    fracs = [float(_dot(p, p) / max(float(_dot(x, x)), 1e-300)) for p, x in zip(projected, columns)]
    H = np.array([[float(_dot(a, b)) for b in projected] for a in projected])
    g = np.array([float(_dot(a, zb)) for a in projected])
    return float(g @ np.linalg.pinv(H) @ g), fracs


def second_half_z(ev: Evidence, fitted: FittedModel, keep: np.ndarray) -> np.ndarray:
    """The second half's residuals in the first half's units (√weight), projected off the model's own
    pixel-local patterns like the first half's: what a pattern missing from the model leaves in both halves."""
    px = fitted.pixels
    r = ev.meas.mean_b - fitted.mu_b
    return np.where(keep, fitted.projector.project(np.where(keep, r, 0.0) * np.sqrt(px.weight)), 0.0)


@dataclass(frozen=True)
class PatternStatistic:
    """A fixed pattern's test statistic over blocks (:func:`pattern_statistic`).

    ``lm`` is the first half's random-effect likelihood ratio made free of the floor and of the noise's spatial
    correlation: residuals rescaled by the noise the halves' difference shows, the ratio divided by its measured
    inflation (a quasi-likelihood ratio), 0 when the halves share no pattern (split-half z ≤ 0).  ``confirmed``
    is the split-half z² (0 when z ≤ 0): the evidence that *both* halves show the pattern, which is what a fixed
    pattern missing from the model leaves.  The ratio alone also grows with anything that raises one half's
    residual variance unevenly over the blocks (noise the floor misses there, a misfit of other parameters), so
    a candidate is flagged only when both clear the bar (:func:`~forensics.check.diagnosis.flag_rule`); the
    ratio, the stronger statistic when the pattern is real, ranks the candidates.
    """

    lm: float
    confirmed: float
    half: SplitHalf
    size: float  #: the random effect's typical size per block, in the signature's units
    scale: float  #: the first half's noise relative to the floor
    inflation: float  #: the ratio's inflation by spatially correlated noise (≥ 1)
    blocks: int  #: blocks that carry the signature


def pattern_statistic(ua: np.ndarray, ub: np.ndarray, ab: np.ndarray, tile: np.ndarray) -> PatternStatistic:
    """A fixed pattern's statistics from each half's signature-weighted residual sums per block (``ua``, ``ub``),
    the signature's weight per block (``ab``) and each block's tile.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> n = 64 * 64
    >>> tile = tile_index((64, 64)).ravel()
    >>> ones = np.ones(n)
    >>> pattern = 0.5 * rng.standard_normal(n)
    >>> shared = pattern_statistic(pattern + rng.standard_normal(n), pattern + rng.standard_normal(n), ones, tile)
    >>> bool(shared.lm > 100 and shared.confirmed > 100)
    True
    """
    used = ab > 1e-12 * max(float(ab.max()) if ab.size else 0.0, 1e-300)
    half = split_half_test(ua[used], ub[used], ab[used], tile[used])
    scale = half.noise if math.isfinite(half.noise) and half.noise > 0 else 1.0
    zs = ua[used] / np.sqrt(ab[used] * scale)
    lr, t_lr = random_effect_lr(zs, ab[used])
    inflation = max(half.inflation, 1.0)
    shared = half.z > 0
    return PatternStatistic(lr / inflation if shared else 0.0, half.z**2 if shared else 0.0, half,
                            math.sqrt(t_lr * scale), scale, inflation, int(used.sum()))


def _pattern_test(ev: Evidence, fitted: FittedModel, s: Signature, xp: np.ndarray, z: np.ndarray, zb: np.ndarray,
                  tiles: np.ndarray, keep: np.ndarray, raw_norm: float, n_obs: int) -> ChannelTest:
    """A fixed pattern's test (:func:`pattern_statistic`) from the two halves' residuals; for a pixel-local
    pattern, its size as the frames show it with an interval (:func:`pattern_size`)."""
    blk = np.broadcast_to(s.blocks[None], xp.shape)
    m = (blk >= 0) & keep
    nblk = int(s.blocks.max()) + 1
    ua = np.bincount(blk[m], (xp * z)[m], minlength=nblk)
    ub = np.bincount(blk[m], (xp * zb)[m], minlength=nblk)
    ab = np.bincount(blk[m], (xp * xp)[m], minlength=nblk)
    stat = pattern_statistic(ua, ub, ab, block_tiles(s.blocks, tiles, nblk))
    half = stat.half
    frac = float(np.sum(ab)) / raw_norm
    size = ""
    if s.pixel_local:
        est = pattern_size(ev.meas, fitted.pixels, s.x, keep & (fitted.pixels.classes == NORMAL),
                           ev.streams.stream(PATTERN_SIZE_STREAM))
        if est is not None and half.z > 0:
            kept = half.t / est.sigma**2 if est.sigma > 0 else math.nan
            size = (f"; pattern σ {est.sigma:.3g} ± {est.se:.2g} as the frames show it "
                    f"({min(kept, 9.99):.0%} of its variance left by the scene estimate)")
    detail = (f"{s.name}: random-effect LR {stat.lm:.4g} over {stat.blocks} blocks (typical size "
              f"{stat.size:.3g}; noise {stat.scale:.3g}× the floor, LR ÷ {stat.inflation:.3g} for its spatial "
              f"correlation); split-half z {half.z:+.3g} over {half.tiles} tiles of {TILE}×{TILE}{size}; "
              f"{frac:.0%} of the signature survives the model's own parameters")
    return ChannelTest("pixel", stat.lm, 1, n_obs, detail, boundary=True, absorbed=frac < 0.05,
                       confirmed=stat.confirmed)


def score_variance(ev: Evidence, fitted: FittedModel, sigs: list[Signature]) -> list[ChannelTest]:
    """The variance channel's score test of the candidates' signatures on the log binned variances, projected off
    the fitted noise parameters' own columns.

    A signature with less than :data:`ABSORBED_SHARE` of its (weighted) norm left by that projection is absorbed
    by those parameters, as in the pixel channel (:func:`score_pixel`), and not tested: what survives is the
    finite differences' rounding, and an LM statistic, which does not depend on the signature's scale, would test
    the residuals along that rounding.  (``input_noise`` without an analog gain is ``read_noise``: 2.6 × 10⁻⁹ of its
    signature survived on the 8-bit DSNU series of seed 2, and its LM 19.5 along it flagged it.)
    """
    px = fitted.pixels
    w = px.bins.df / 2.0
    sigs = [s for s in sigs if float((s.x * w) @ s.x) > 0]  # no signature in these data
    if not sigs or not len(px.bins.observed):
        return []
    e = log_variance(px.bins.observed, px.bins.df) - np.log(fitted.variance_pred)
    X = np.array([s.x for s in sigs])
    P = X
    if fitted.variance_jac is not None:
        J = fitted.variance_jac
        coef = np.linalg.lstsq((J * w) @ J.T, (J * w) @ X.T, rcond=None)[0]
        P = X - coef.T @ J
    shares = np.einsum("kb,b,kb->k", P, w, P) / np.einsum("kb,b,kb->k", X, w, X)
    names = ", ".join(s.name for s in sigs)
    live = shares >= ABSORBED_SHARE
    if not live.any():
        return [ChannelTest("variance", 0.0, 0, len(e), f"{names}: absorbed by the fitted noise parameters "
                            f"({shares.max():.2g} of the signature survives them)", absorbed=True)]
    P = P[live]
    H = (P * w) @ P.T
    g = (P * w) @ e
    lm = float(g @ np.linalg.pinv(H) @ g)
    return [ChannelTest("variance", lm, int(live.sum()), len(e),
                        f"{names}: score LM {lm:.4g} on {len(e)} binned variances")]


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
        phi = pearson_alt / df_alt if pearson_alt > chi2_ppf(0.99, df_alt) else 1.0
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
    u_obs = (ev.defects.observed_spatial() - null["mean"]) / null["sd"]
    u_sim = (null["sims"] - null["mean"]) / null["sd"]
    for s in sigs:
        d = s.x / max(float(np.linalg.norm(s.x)), 1e-12)
        t_obs = float(d @ u_obs)
        t_sim = u_sim @ d
        zval = (t_obs - float(t_sim.mean())) / max(float(t_sim.std(ddof=1)), 1e-9)
        lm = zval * zval if zval > 0 else 0.0
        out.append(ChannelTest("spatial", lm, 1, len(ev.defects.sites),
                               f"{s.name}: Ripley L and co-arrival pairs move the way this effect predicts, "
                               f"z {zval:+.3g} against {len(t_sim)} simulations of the fitted model"))
    return out
