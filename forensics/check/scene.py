"""The scene under each pixel, estimated from its neighbours (a leave-one-out local quadratic fit)."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from forensics.defects.detection import robust_normal

SCENE_SIZE = 7


def loo_quadratic_kernel(size: int = SCENE_SIZE) -> np.ndarray:
    """Weights of a least-squares quadratic surface fitted to a ``size × size`` window *without* its centre,
    evaluated at the centre: exact for any quadratic scene, independent of the centre pixel's noise."""
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    keep = ~((yy == 0) & (xx == 0))
    x, y = xx[keep], yy[keep]
    design = np.column_stack([np.ones_like(x), x, y, x * x, y * y, x * y])
    weights = np.linalg.solve(design.T @ design, design.T)[0]
    kernel = np.zeros((size, size))
    kernel[keep] = weights
    return kernel


KERNEL = loo_quadratic_kernel()
#: Noise of the scene estimate relative to one pixel's: Σw² (0.081 for 7 × 7).
KERNEL_VAR = float(np.sum(KERNEL**2))


def scene_estimate_and_fill(image: np.ndarray, exclude: np.ndarray | None = None, kernel: np.ndarray = KERNEL,
                            passes: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The light each pixel would show if it were typical, estimated from its neighbours, and the image as
    filtered (defects and outliers replaced by their fill values).

    The leave-one-out quadratic ``kernel`` is applied to the image in which the
    ``exclude`` mask (known defects) and outliers (more than 6 robust σ from
    their estimate) are replaced by the mean of their good 5 × 5 neighbours; a
    few passes settle the outlier set.  Unlike a local median, the estimate is
    unbiased for any quadratic scene (vignetting), and its noise is known:
    σ²·Σw² (0.081 σ² for 7 × 7).
    """
    img = np.asarray(image, np.float64)
    base = np.zeros(img.shape, bool) if exclude is None else np.asarray(exclude, bool)
    bad = base
    est = img
    for _ in range(passes):
        if bad.any():
            good = (~bad).astype(np.float64)
            num = ndimage.uniform_filter(img * good, size=5, mode="reflect")
            den = ndimage.uniform_filter(good, size=5, mode="reflect")
            wide = den < 1e-6
            if wide.any():
                num = np.where(wide, ndimage.uniform_filter(img * good, size=15, mode="reflect"), num)
                den = np.where(wide, ndimage.uniform_filter(good, size=15, mode="reflect"), den)
            filled = np.where(bad, num / np.maximum(den, 1e-12), img)
        else:
            filled = img
        est = ndimage.correlate(filled, kernel, mode="reflect")
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
