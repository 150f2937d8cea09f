"""The scene under each pixel, estimated from its neighbours (a leave-one-out local quadratic fit)."""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from forensics.defects.detection import robust_normal

SCENE_SIZE = 7


def loo_quadratic_kernel(size: int = SCENE_SIZE) -> np.ndarray:
    """Weights of a least-squares quadratic surface fitted to a ``size × size`` window *without* its centre,
    evaluated at the centre: exact for any quadratic scene, independent of the centre pixel's noise."""
    h = size // 2
    return clipped_kernel(size, h, h, h, h).copy()


@functools.lru_cache(maxsize=256)
def clipped_kernel(size: int, top: int, bottom: int, left: int, right: int) -> np.ndarray:
    """:func:`loo_quadratic_kernel` for a window cut by the image's edge: ``top`` … ``right`` are the rows and
    columns available on each side of the centre (at most ``size // 2``); weights of missing places are 0.
    Cached (read-only): the same few edge windows recur in every pass over every image."""
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    keep = ~((yy == 0) & (xx == 0)) & (yy >= -top) & (yy <= bottom) & (xx >= -left) & (xx <= right)
    x, y = xx[keep], yy[keep]
    design = np.column_stack([np.ones_like(x), x, y, x * x, y * y, x * y])
    weights = np.linalg.lstsq(design, np.eye(len(x)), rcond=None)[0][0]
    kernel = np.zeros((size, size))
    kernel[keep] = weights
    kernel.flags.writeable = False
    return kernel


def edge_estimates(image: np.ndarray, estimate: np.ndarray, kernel_size: int = SCENE_SIZE) -> None:
    """Replace, in ``estimate``, the values within ``kernel_size // 2`` of the image's edge by the leave-one-out
    quadratic fitted to the part of the window inside the image.

    A reflected border would put a kink into any gradient (vignetting is steepest there): the edge pixels'
    estimates would be off by about the gradient, the pixels taken for outliers, and their fill values would
    spoil the interior estimates next to them."""
    h = kernel_size // 2
    H, W = image.shape
    if H <= 2 * h + 1 or W <= 2 * h + 1:
        return
    padded = np.pad(image, h)
    rows = [(y, min(y, h), min(H - 1 - y, h)) for y in range(H)]
    cols = [(x, min(x, h), min(W - 1 - x, h)) for x in range(W)]
    edge_rows = [r for r in rows if r[1] < h or r[2] < h]
    edge_cols = [c for c in cols if c[1] < h or c[2] < h]
    inner_rows = slice(h, H - h)
    inner_cols = slice(h, W - h)

    def apply(ys: slice | int, xs: slice | int, top: int, bottom: int, left: int, right: int) -> None:
        k = clipped_kernel(kernel_size, top, bottom, left, right)
        ylo = ys.start if isinstance(ys, slice) else ys
        yhi = ys.stop if isinstance(ys, slice) else ys + 1
        xlo = xs.start if isinstance(xs, slice) else xs
        xhi = xs.stop if isinstance(xs, slice) else xs + 1
        acc = np.zeros((yhi - ylo, xhi - xlo))
        for dy in range(-h, h + 1):
            for dx in range(-h, h + 1):
                wt = k[dy + h, dx + h]
                if wt:
                    acc += wt * padded[ylo + h + dy:yhi + h + dy, xlo + h + dx:xhi + h + dx]
        estimate[ylo:yhi, xlo:xhi] = acc

    for y, top, bottom in edge_rows:  # edge rows: inner columns share one kernel per row, corners per pixel
        apply(y, inner_cols, top, bottom, h, h)
        for x, left, right in edge_cols:
            apply(y, x, top, bottom, left, right)
    for x, left, right in edge_cols:
        apply(inner_rows, x, h, h, left, right)


KERNEL = loo_quadratic_kernel()
#: Noise of the scene estimate relative to one pixel's: Σw² (0.081 for 7 × 7).
KERNEL_VAR = float(np.sum(KERNEL**2))


def plane_fill(image: np.ndarray, good: np.ndarray, size: int = 5, wide: int = 15) -> np.ndarray:
    """The image with every pixel that is not ``good`` replaced by the least-squares plane through the good
    pixels of its ``size × size`` window (inside the image only), evaluated there; ``wide × wide`` where the
    window has fewer than 3 good pixels.

    A plane is exact for any gradient, also at an edge or next to other gaps, where a box mean is off by
    about the gradient (vignetting is steepest at the edges) and would spoil the neighbours' estimates."""
    h, w = image.shape
    out = np.array(image, np.float64, copy=True)
    todo = np.flatnonzero(~good)
    g = good.astype(np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    yy -= h / 2
    xx -= w / 2
    img = np.where(good, image, 0.0)
    for n in (size, wide):
        if not todo.size:
            break

        def box(v: np.ndarray) -> np.ndarray:
            return ndimage.uniform_filter(v, size=n, mode="constant").ravel()[todo]

        s1, sx, sy = box(g), box(g * xx), box(g * yy)
        sxx, syy, sxy = box(g * xx * xx), box(g * yy * yy), box(g * xx * yy)
        A = np.stack([np.stack([s1, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], -2)
        b = np.stack([box(img), box(img * xx), box(img * yy)], -1)
        ok = (s1 * n * n >= 2.5) & (np.abs(np.linalg.det(A)) > 1e-12 * np.maximum(s1, 1e-300) ** 3)
        coef = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        at = todo[ok]
        out.ravel()[at] = coef[:, 0] + coef[:, 1] * xx.ravel()[at] + coef[:, 2] * yy.ravel()[at]
        todo = todo[~ok]
    if todo.size:
        out.ravel()[todo] = float(np.mean(image[good])) if good.any() else 0.0
    return out


def scene_estimate_and_fill(image: np.ndarray, exclude: np.ndarray | None = None, kernel: np.ndarray = KERNEL,
                            passes: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The light each pixel would show if it were typical, estimated from its neighbours, and the image as
    filtered (defects and outliers replaced by their fill values).

    The leave-one-out quadratic ``kernel`` is applied to the image in which the
    ``exclude`` mask (known defects) and outliers (more than 6 robust σ from
    their estimate) are replaced by a plane through their good neighbours
    (:func:`plane_fill`); a few passes settle the outlier set.  Unlike a local median, the estimate is
    unbiased for any quadratic scene (vignetting), and its noise is known:
    σ²·Σw² (0.081 σ² for 7 × 7).
    """
    img = np.asarray(image, np.float64)
    base = np.zeros(img.shape, bool) if exclude is None else np.asarray(exclude, bool)
    bad = base
    est = img
    for _ in range(passes):
        filled = plane_fill(img, ~bad) if bad.any() else img
        est = ndimage.correlate(filled, kernel, mode="reflect")
        if kernel.shape[0] == SCENE_SIZE:
            edge_estimates(filled, est)
        resid = img - est
        keep = resid[~bad]
        mad = robust_normal(keep)[1] if keep.size else 0.0
        new_bad = base | (np.abs(resid) > 6.0 * max(mad, 1e-9))
        if np.array_equal(new_bad, bad):
            break
        bad = new_bad
    return est, filled


def scene_estimate(image: np.ndarray, exclude: np.ndarray | None = None, kernel: np.ndarray = KERNEL,
                   passes: int = 4) -> np.ndarray:
    """The scene estimate alone (see :func:`scene_estimate_and_fill`)."""
    return scene_estimate_and_fill(image, exclude, kernel, passes)[0]


def kernel_scatter(mask: np.ndarray, kernel: np.ndarray = KERNEL) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source, destination, weight) triples such that correlating an image that is zero outside ``mask`` with
    ``kernel`` is ``bincount(destination, weight · image.ravel()[source])`` (reflecting at the edges)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    k = kernel.shape[0] // 2
    src, dst, wts = [], [], []
    for dy in range(-k, k + 1):
        for dx in range(-k, k + 1):
            wt = kernel[k + dy, k + dx]
            if wt == 0:
                continue
            # out[p] = Σ_q K[q − p + k] · img[q]  ⇒  the source at (ys, xs) feeds p = (ys − dy, xs − dx)
            py, px = ys - dy, xs - dx
            ok = (py >= 0) & (py < h) & (px >= 0) & (px < w)
            src.append(ys[ok] * w + xs[ok])
            dst.append(py[ok] * w + px[ok])
            wts.append(np.full(int(ok.sum()), wt))
    if not src:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    return np.concatenate(src), np.concatenate(dst), np.concatenate(wts)
