"""Spatial statistics of defect sites: Ripley's K and L, Clark–Evans, Thomas-process minimum contrast.

Sites are pixel positions; a site ``(x, y)`` is placed at the pixel centre
``(x + 0.5, y + 0.5)`` inside a rectangular observation window
``(x0, y0, x1, y1)`` (pixel edges).  Edge effects are corrected:

* Ripley's K uses the translation correction: a pair at offset ``(dx, dy)``
  is weighted by ``|W| / ((a − |dx|)(b − |dy|))`` for a window of sides a × b;
* Clark–Evans uses Donnelly's (1978) correction of the expected mean
  nearest-neighbour distance and its standard error for a rectangle.

Because sites live on a pixel lattice, the exact null distribution of these
statistics differs slightly from the continuous one at radii of a pixel or
two; tests in :mod:`forensics.check` therefore take their null distribution
from Monte-Carlo simulations of the fitted model on the same lattice.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import spatial

Window = tuple[float, float, float, float]

#: Radii (pixels) at which K and L are evaluated by default.
DEFAULT_RADII = np.array([1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0])


def _centres(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.column_stack([np.asarray(x, float) + 0.5, np.asarray(y, float) + 0.5])


def window_area(window: Window) -> float:
    x0, y0, x1, y1 = window
    return float((x1 - x0) * (y1 - y0))


def ripley_k(x: np.ndarray, y: np.ndarray, window: Window, radii: np.ndarray = DEFAULT_RADII) -> np.ndarray:
    """Ripley's K at ``radii`` with the translation edge correction (NaN with fewer than 2 sites).

    Parameters
    ----------
    x, y
        Pixel columns and rows of the sites (all inside ``window``).
    window
        ``(x0, y0, x1, y1)`` in pixel-edge coordinates.
    radii
        Increasing radii in pixels.
    """
    radii = np.asarray(radii, float)
    n = len(x)
    if n < 2:
        return np.full(len(radii), np.nan)
    x0, y0, x1, y1 = window
    a, b = x1 - x0, y1 - y0
    pts = _centres(x, y)
    pairs = spatial.cKDTree(pts).query_pairs(float(radii.max()), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(len(radii))
    d = pts[pairs[:, 0]] - pts[pairs[:, 1]]
    dist = np.hypot(d[:, 0], d[:, 1])
    weight = (a * b) / ((a - np.abs(d[:, 0])) * (b - np.abs(d[:, 1])))
    order = np.argsort(dist)
    cum = np.concatenate([[0.0], np.cumsum(weight[order])])
    counts = cum[np.searchsorted(dist[order], radii, side="right")]
    return a * b / (n * (n - 1)) * 2.0 * counts


def ripley_l(x: np.ndarray, y: np.ndarray, window: Window, radii: np.ndarray = DEFAULT_RADII) -> np.ndarray:
    """Besag's L(r) = √(K(r)/π); L(r) = r for complete spatial randomness."""
    return np.sqrt(np.maximum(ripley_k(x, y, window, radii), 0.0) / np.pi)


def co_arrival_pairs(x: np.ndarray, y: np.ndarray, group: np.ndarray,
                     radii: np.ndarray = DEFAULT_RADII) -> np.ndarray:
    """Number of site pairs within each radius that share a ``group`` label (cumulative in r).

    With the group the epoch a defect first appeared at, this counts the pairs that arrived together
    close to each other: the space–time signature of defects that arrive as events (a cluster's members
    appear at once).  Independent arrivals spread such pairs over every pair of epochs, so the count is
    far quieter than Ripley's K of all sites, whose pairs of different epochs add only noise.  No edge
    correction: callers compare it with simulations on the same window.

    Examples
    --------
    >>> co_arrival_pairs(np.array([0, 1, 5, 5]), np.array([0, 0, 0, 1]), np.array([1, 1, 1, 2]), np.array([1.0, 5.0]))
    array([1., 3.])
    """
    radii = np.asarray(radii, float)
    group = np.asarray(group)
    if len(x) < 2:
        return np.zeros(len(radii))
    pts = _centres(x, y)
    pairs = spatial.cKDTree(pts).query_pairs(float(radii.max()), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(len(radii))
    pairs = pairs[group[pairs[:, 0]] == group[pairs[:, 1]]]
    d = pts[pairs[:, 0]] - pts[pairs[:, 1]]
    dist = np.sort(np.hypot(d[:, 0], d[:, 1]))
    return np.searchsorted(dist, radii, side="right").astype(float)


def lattice_pair_fraction(width: int, height: int, radii: np.ndarray = DEFAULT_RADII) -> np.ndarray:
    """Probability that two distinct sites drawn uniformly from a ``width`` × ``height`` pixel grid lie within
    each radius of each other (cumulative in r).

    Exact on the lattice — the number of ordered pixel pairs at every offset (dx, dy), (width − |dx|)(height − |dy|),
    over all ordered pairs — where the continuous πr²/area is off by tens of per cent at a pixel or two.

    Examples
    --------
    >>> round(float(lattice_pair_fraction(3, 1, np.array([1.0]))[0]), 4)  # 2 of the 3 pairs are neighbours
    0.6667
    """
    radii = np.asarray(radii, float)
    n = width * height
    if n < 2:
        return np.zeros(len(radii))
    reach = int(np.floor(radii.max()))
    d = np.arange(-reach, reach + 1)
    dx, dy = np.meshgrid(d, d)
    dist = np.hypot(dx, dy).ravel()
    ways = (np.maximum(width - np.abs(dx), 0) * np.maximum(height - np.abs(dy), 0)).ravel().astype(float)
    ways[dist == 0] = 0.0
    order = np.argsort(dist)
    cum = np.concatenate([[0.0], np.cumsum(ways[order])])
    return cum[np.searchsorted(dist[order], radii, side="right")] / (n * (n - 1.0))


@functools.lru_cache(maxsize=8)
def _grid_rings(radii: tuple[float, ...]) -> np.ndarray:
    """The Thomas pair shape in the rings between ``radii`` at :func:`fit_pair_excess`'s grid of log σ
    ``(121, len(radii))`` (read-only: shared by every fit at these radii)."""
    r = np.asarray(radii, float)
    sig2 = np.exp(2.0 * np.linspace(np.log(0.3), np.log(30.0), 121))[:, None]
    out = np.diff(1.0 - np.exp(-r[None, :] ** 2 / (4.0 * sig2)), axis=1, prepend=0.0)
    out.flags.writeable = False
    return out


def fit_pair_excess(radii: np.ndarray, excess: np.ndarray, chance: np.ndarray) -> tuple[float, float]:
    """Fit ``Π · (1 − exp(−r²/4σ²))`` — the pairs of Thomas clusters (offsets N(0, σ²) per axis) within r — to
    counted excess pairs (cumulative in r) beside ``chance`` pairs expected within the same radii.

    The fit is made in the rings between consecutive radii (the cumulative counts share their pairs; the rings'
    counts are independent), each weighted by its expected count: chance + the fitted excess, in two passes
    (weights from the observed counts themselves would bias Π low).  At each σ, Π has a closed form (weighted
    least squares on one column); σ is found on a log grid from 0.3 to 30 px, then refined (a grid cannot stall
    on the flat loss of a weak excess).

    Returns
    -------
    (Pi, sigma)
        The total excess pairs (≥ 0; 0 when the counts show none) and the spread in pixels.

    Examples
    --------
    >>> r = DEFAULT_RADII
    >>> pi_, s = fit_pair_excess(r, 50 * (1 - np.exp(-r**2 / 4 / 2.0**2)), np.ones(len(r)))
    >>> round(float(pi_), 2), round(s, 1)
    (50.0, 2.0)
    """
    radii = np.asarray(radii, float)
    x = np.diff(np.asarray(excess, float), prepend=0.0)
    base = np.diff(np.asarray(chance, float), prepend=0.0)

    def ring(log_sigma: float) -> np.ndarray:
        return np.diff(1.0 - np.exp(-radii**2 / (4.0 * np.exp(2.0 * log_sigma))), prepend=0.0)

    def at(log_sigma: float, w: np.ndarray) -> tuple[float, float]:
        g = ring(log_sigma)
        pi_ = max(float(np.sum(w * g * x) / max(np.sum(w * g * g), 1e-300)), 0.0)
        return pi_, float(np.sum(w * (x - pi_ * g) ** 2))

    grid = np.linspace(np.log(0.3), np.log(30.0), 121)
    step = grid[1] - grid[0]
    rings = _grid_rings(tuple(radii.tolist()))  # (grid, rings): the shape at every grid point, once per radii
    w = 1.0 / np.maximum(base + np.maximum(x, 0.0), 1.0)
    v = float(grid[0])
    for _ in range(2):
        # every grid point at once (the closed-form Π and the loss of :func:`at`, vectorised: a Python loop over
        # the grid was 90 % of a fit, and the parametric bootstrap of :func:`pair_excess_draws` refits hundreds)
        gw = rings * w
        pis = np.maximum(gw @ x / np.maximum(np.sum(gw * rings, axis=1), 1e-300), 0.0)
        losses = np.sum(w * (x[None, :] - pis[:, None] * rings) ** 2, axis=1)
        j = int(np.argmin(losses))
        if pis[j] <= 0:
            return 0.0, 1.0
        from scipy import optimize  # here, not at import: scipy.optimize takes 0.2–0.3 s to import

        fine = optimize.minimize_scalar(lambda u: at(u, w)[1], bounds=(grid[j] - step, grid[j] + step),
                                        method="bounded", options={"xatol": 1e-6})
        v = float(fine.x) if fine.fun <= losses[j] else float(grid[j])
        w = 1.0 / np.maximum(base + at(v, w)[0] * ring(v), 1.0)
    return at(v, w)[0], float(np.exp(v))


def distinct_pair_share(mean_members: float, sigma: float, rng: np.random.Generator, clusters: int = 20000) -> float:
    """The share of a Thomas cluster's member pairs, λ²/2 on average for Poisson(λ) members, that remain pairs of
    distinct sites on the pixel grid (members at ``floor(centre + σ·z)``; members that share a pixel are one site,
    as a detected defect is one pixel).  A merge costs N − 1 pairs, not one: ≈ 0.91 at λ = 3.9, σ = 2 px,
    though a given pair shares a pixel only 2 % of the time.  By simulation of ``clusters`` clusters.

    Examples
    --------
    >>> round(distinct_pair_share(3.9, 2.0, np.random.default_rng(0)), 2)
    0.91
    """
    if mean_members <= 0:
        return 1.0
    size = rng.poisson(mean_members, clusters)
    parent = np.repeat(np.arange(clusters), size)
    centre = rng.uniform(0.0, 1.0, (clusters, 2))
    xy = np.floor(centre[parent] + sigma * rng.standard_normal((parent.size, 2))).astype(np.int64)
    kept = np.bincount(np.unique(np.column_stack([parent, xy]), axis=0)[:, 0], minlength=clusters)
    return float(np.sum(kept * (kept - 1.0)) / max(np.sum(size * (size - 1.0)), 1.0))


def pair_excess_draws(radii: np.ndarray, pairs: float, sigma: float, mean_members: float, chance: np.ndarray,
                      rng: np.random.Generator, draws: int = 200) -> np.ndarray:
    """Parametric bootstrap of :func:`fit_pair_excess`: ``draws`` refits ``(Π*, σ*)`` ``(draws, 2)`` of counts
    simulated at the fitted values — a Poisson number Π/(λ²/2) of Thomas clusters with Poisson(λ) members,
    λ = ``mean_members``, each member at ``floor(centre + σ·z)`` on the pixel grid (members that share a pixel
    make one site, as detected defects do), their own pairs counted within ``radii``, plus Poisson chance pairs
    in every ring (cumulative expectations ``chance``), the chance expectation subtracted as in the fit.  The
    number of clusters is the one whose *distinct* pairs (:func:`distinct_pair_share`) average Π.

    Why a bootstrap: σ is read off the shape of the excess across the rings, whose counts share the clusters'
    members (a cluster of N adds N(N − 1)/2 correlated pairs), so no closed form gives its error.  (Π's spread here,
    sd 61 pairs for 40 clusters of 4, is within 10 % of the closed form :func:`pair_excess_se` (66) and of the
    simulated patterns' own (69), which the rate's interval keeps using.)  Window edges are ignored (λ is
    the members landing on the sensor).

    Examples
    --------
    >>> r = DEFAULT_RADII
    >>> d = pair_excess_draws(r, 400.0, 2.0, 4.0, 0.5 * r**2, np.random.default_rng(1), draws=100)
    >>> d.shape, bool(1.5 < np.median(d[:, 1]) < 2.5)
    ((100, 2), True)
    """
    radii = np.asarray(radii, float)
    chance = np.asarray(chance, float)
    out = np.zeros((draws, 2))
    out[:, 1] = 1.0
    if pairs <= 0 or mean_members <= 0:
        return out
    share = distinct_pair_share(mean_members, sigma, rng)
    n_cl = rng.poisson(pairs / (share * mean_members**2 / 2.0), draws)
    cluster_draw = np.repeat(np.arange(draws), n_cl)
    size = rng.poisson(mean_members, cluster_draw.size)
    parent = np.repeat(np.arange(cluster_draw.size), size)
    centre = rng.uniform(0.0, 1.0, (cluster_draw.size, 2))  # the centre within its pixel
    xy = np.floor(centre[parent] + sigma * rng.standard_normal((parent.size, 2))).astype(np.int64)
    # one site per pixel within a cluster, members sorted by cluster
    keyed = np.unique(np.column_stack([parent, xy]), axis=0)
    parent, xy = keyed[:, 0], keyed[:, 1:].astype(float)
    own = np.zeros((draws, radii.size))
    for k in range(1, int(np.bincount(parent).max(initial=0))):  # every pair (i, i + k) of one cluster, once
        same = parent[:-k] == parent[k:]
        if not same.any():
            break
        d = np.hypot(*(xy[k:][same] - xy[:-k][same]).T)
        ring = np.searchsorted(radii, d, side="left")  # the first radius ≥ d (pairs beyond the last are not counted)
        keep = ring < radii.size
        np.add.at(own, (cluster_draw[parent[:-k][same][keep]], ring[keep]), 1.0)
    noise = rng.poisson(np.diff(chance, prepend=0.0), (draws, radii.size)).astype(float)
    observed = np.cumsum(own + noise, axis=1)
    for i in range(draws):
        out[i] = fit_pair_excess(radii, observed[i] - chance, chance)
    return out


def pair_excess_se(pairs: float, mean_members: float, chance: float) -> float:
    """Standard error of a fitted pair excess Π (:func:`fit_pair_excess`) of Thomas clusters whose detected
    members are Poisson with mean λ = ``mean_members``.

    Π sums the clusters' own pairs N(N − 1)/2: with a Poisson number n = Π/(λ²/2) of clusters, its variance is
    n·E[(N(N − 1)/2)²] = n·(λ⁴/4 + λ³ + λ²/2) — dominated by the clusters' sizes, not by their count.  The chance
    pairs subtracted add their Poisson variance: ``chance``, their expected count within the largest radius
    (where :func:`fit_pair_excess` reads Π).

    Examples
    --------
    >>> round(pair_excess_se(400.0, 4.0, 0.0), 1)   # 50 clusters of 4: √(50 · (64 + 64 + 8))
    82.5
    """
    if mean_members <= 0 or pairs <= 0:
        return float(np.sqrt(max(chance, 0.0)))
    lam = float(mean_members)
    clusters = pairs / (lam * lam / 2.0)
    return float(np.sqrt(clusters * (lam**4 / 4.0 + lam**3 + lam**2 / 2.0) + max(chance, 0.0)))


@dataclass
class ClarkEvans:
    """Clark–Evans aggregation index with Donnelly's edge correction.

    ``ratio`` < 1 means clustering, > 1 regularity; ``z`` is approximately
    standard normal for complete spatial randomness.
    """

    n: int
    mean_nn: float
    expected_nn: float
    ratio: float
    z: float

    def to_dict(self) -> dict[str, float]:
        return {"n": self.n, "mean_nn": self.mean_nn, "expected_nn": self.expected_nn, "ratio": self.ratio,
                "z": self.z}


def clark_evans(x: np.ndarray, y: np.ndarray, window: Window) -> ClarkEvans:
    """Mean nearest-neighbour distance against its expectation under complete spatial randomness."""
    n = len(x)
    if n < 3:
        return ClarkEvans(n, float("nan"), float("nan"), float("nan"), float("nan"))
    x0, y0, x1, y1 = window
    area = window_area(window)
    perimeter = 2.0 * ((x1 - x0) + (y1 - y0))
    pts = _centres(x, y)
    dist, _ = spatial.cKDTree(pts).query(pts, k=2)
    mean_nn = float(dist[:, 1].mean())
    expected = 0.5 * np.sqrt(area / n) + (0.0514 + 0.041 / np.sqrt(n)) * perimeter / n
    se = np.sqrt(0.0703 * area / n**2 + 0.037 * perimeter * np.sqrt(area / n**5))
    return ClarkEvans(n, mean_nn, float(expected), float(mean_nn / expected), float((mean_nn - expected) / se))


def thomas_excess(radii: np.ndarray, excess: float, sigma: float) -> np.ndarray:
    """K(r) − πr² of uniform sites mixed with Thomas clusters: A·(1 − exp(−r²/4σ²))."""
    return excess * (1.0 - np.exp(-np.asarray(radii, float) ** 2 / (4.0 * sigma**2)))


def fit_thomas_excess(radii: np.ndarray, k_observed: np.ndarray, sigma_max: float = 20.0) -> tuple[float, float]:
    """Minimum-contrast fit (Diggle's power 1/4) of ``πr² + A(1 − exp(−r²/4σ²))`` to an observed K.

    Returns
    -------
    (A, sigma)
        ``A`` ≥ 0 (pixels²) and ``sigma`` (pixels); ``A = 0`` when K shows no excess.
    """
    radii = np.asarray(radii, float)
    k_observed = np.maximum(np.asarray(k_observed, float), 0.0)
    if not np.all(np.isfinite(k_observed)):
        return 0.0, 1.0
    base = np.pi * radii**2

    def loss(theta: np.ndarray) -> float:
        a, s = np.exp(theta)
        model = base + thomas_excess(radii, a, s)
        return float(np.sum((k_observed**0.25 - model**0.25) ** 2))

    null_loss = float(np.sum((k_observed**0.25 - base**0.25) ** 2))
    from scipy import optimize  # here, not at import: scipy.optimize takes 0.2–0.3 s to import

    best = None
    for s0 in (0.7, 1.5, 3.0, 6.0):
        a0 = max(float(np.max(k_observed - base)), 1.0)
        res = optimize.minimize(loss, np.log([a0, s0]), method="Nelder-Mead",
                                options={"xatol": 1e-4, "fatol": 1e-10, "maxiter": 2000})
        if best is None or res.fun < best.fun:
            best = res
    a, s = np.exp(best.x)
    if best.fun >= null_loss or not np.isfinite(a):
        return 0.0, 1.0
    return float(a), float(min(s, sigma_max))
