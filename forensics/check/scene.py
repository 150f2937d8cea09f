"""The scene under each pixel, estimated from its neighbours (a leave-one-out local quadratic fit)."""
from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage, sparse

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


@functools.lru_cache(maxsize=8)
def _edge_band(shape: tuple[int, int], kernel_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels within ``kernel_size // 2`` of the edge of an image of ``shape`` (rows, columns),
    their window's flat offsets ``(size², N)`` (clipped into the image; a place outside has weight 0) and their
    clipped kernels' weights ``(size², N)``.  Cached (read-only): every pass over every image of one shape
    shares them."""
    h = kernel_size // 2
    H, W = shape
    rows, cols = np.r_[0:h, H - h:H], np.r_[0:h, W - h:W]  # the band: whole edge rows, edge columns between
    middle = np.arange(h, H - h)
    ys = np.concatenate([np.repeat(rows, W), np.repeat(middle, cols.size)])
    xs = np.concatenate([np.tile(np.arange(W), rows.size), np.tile(cols, middle.size)])
    top, bottom = np.minimum(ys, h), np.minimum(H - 1 - ys, h)
    left, right = np.minimum(xs, h), np.minimum(W - 1 - xs, h)
    weights = np.empty((kernel_size * kernel_size, ys.size))
    index = np.empty((kernel_size * kernel_size, ys.size), np.intp)
    kernels = {}
    for key in set(zip(top.tolist(), bottom.tolist(), left.tolist(), right.tolist())):
        kernels[key] = clipped_kernel(kernel_size, *key).ravel()
    code = ((top * (h + 1) + bottom) * (h + 1) + left) * (h + 1) + right
    for key, k in kernels.items():
        t, b, l, r = key
        sel = code == ((t * (h + 1) + b) * (h + 1) + l) * (h + 1) + r
        weights[:, sel] = k[:, None]
    j = 0
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            index[j] = np.clip(ys + dy, 0, H - 1) * W + np.clip(xs + dx, 0, W - 1)
            j += 1
    for a in (ys, xs, index, weights):
        a.flags.writeable = False
    return ys, xs, index, weights


@functools.lru_cache(maxsize=8)
def _edge_operator(shape: tuple[int, int], kernel_size: int, power: int, transpose: bool = False) -> sparse.csr_array:
    """The edge band's clipped kernels (:func:`_edge_band`) as a sparse matrix ``(band pixels, H·W)`` — weights to
    the power ``power`` — or its transpose.  Cached per shape.

    Why a sparse matrix: the band's estimates as a loop of 49 gathers (and their transpose as 49 scatters over
    the whole frame) were a fifth of the joint solve's time; one sparse product does either.  A row's columns
    are the window's places in row-major order (zero weights, the places outside the image, left out), so the
    estimates are summed in the order a per-pixel loop over the clipped kernel would."""
    H, W = shape
    ys, _, index, weights = _edge_band(shape, kernel_size)
    rows = np.broadcast_to(np.arange(ys.size), index.shape)
    keep = weights != 0
    matrix = sparse.csr_array(((weights[keep] ** power), (rows[keep], index[keep])), shape=(ys.size, H * W))
    matrix.sum_duplicates()  # (none: a place inside the image appears once per window)
    return matrix.T.tocsr() if transpose else matrix


def _band_position(py: np.ndarray, px: np.ndarray, shape: tuple[int, int], kernel_size: int) -> np.ndarray:
    """Each edge-band pixel's position in :func:`_edge_band`'s order (whole edge rows first, then the edge
    columns of the rows between)."""
    h = kernel_size // 2
    H, W = shape
    band_row = np.where(py < h, py, py - (H - 2 * h))  # among the 2h whole edge rows
    col = np.where(px < h, px, px - (W - 2 * h))  # among the 2h edge columns
    return np.where((py < h) | (py >= H - h), band_row * W + px, 2 * h * W + (py - h) * (2 * h) + col)


def kernel_columns(shape: tuple[int, int], pixels: np.ndarray, power: int = 1) -> sparse.csr_array:
    """Columns ``pixels`` (flat indices) of :func:`kernel_estimate`'s matrix K (default kernel, weights to the power
    ``power``), as the rows of a sparse ``(len(pixels), H·W)`` matrix: row i holds K_pq for q = ``pixels[i]``.
    ``M @ u`` is then ``Kᵀ·u`` at those pixels and ``M.T @ e`` is ``K·e`` for ``e`` nonzero only there.  For
    images larger than the kernel in both directions (smaller ones reflect: :func:`kernel_transpose` probes).

    Why: the joint solve needs Kᵀ per frame only where the frames' coupling differs from a common profile (a
    few pixels: :class:`~forensics.check.joint_solve.FactoredCoupling`); a transpose over the whole frame per
    frame was a sixth of the check's time on 320 × 240 frames."""
    size = SCENE_SIZE
    h = size // 2
    H, W = shape
    if H <= 2 * h + 1 or W <= 2 * h + 1:
        raise ValueError("kernel_columns needs an image larger than the kernel in both directions")
    pixels = np.asarray(pixels, np.intp)
    qy, qx = np.divmod(pixels, W)
    dy, dx = (a.ravel() for a in np.mgrid[-h:h + 1, -h:h + 1])
    py, px = qy[:, None] - dy[None], qx[:, None] - dx[None]  # K_pq ≠ 0 only for q = p + offset
    inside = (py >= 0) & (py < H) & (px >= 0) & (px < W)
    interior = inside & (py >= h) & (py < H - h) & (px >= h) & (px < W - h)
    weights = np.where(interior, KERNEL.ravel()[None], 0.0)
    band = inside & ~interior
    _, _, _, band_weights = _edge_band((H, W), size)
    slot = np.broadcast_to(np.arange(size * size), py.shape)[band]  # the offset's place in p's clipped window
    weights[band] = band_weights[slot, _band_position(py[band], px[band], (H, W), size)]
    keep = weights != 0
    rows = np.broadcast_to(np.arange(pixels.size)[:, None], py.shape)
    return sparse.csr_array((weights[keep] ** power, (rows[keep], (py * W + px)[keep])), shape=(pixels.size, H * W))


def edge_estimates(image: np.ndarray, estimate: np.ndarray, kernel_size: int = SCENE_SIZE) -> None:
    """Replace, in ``estimate``, the values within ``kernel_size // 2`` of the image's edge by the leave-one-out
    quadratic fitted to the part of the window inside the image.

    A reflected border would put a kink into any gradient (vignetting is steepest there): the edge pixels'
    estimates would be off by about the gradient, the pixels taken for outliers, and their fill values would
    spoil the interior estimates next to them.

    Every edge pixel at once (:func:`_edge_band`): the window's places are summed in row-major order, as a
    per-pixel loop over the clipped kernel would (a place outside the image has weight 0 and adds 0)."""
    h = kernel_size // 2
    H, W = image.shape
    if H <= 2 * h + 1 or W <= 2 * h + 1:
        return
    ys, xs, _, _ = _edge_band((H, W), kernel_size)
    estimate[ys, xs] = _edge_operator((H, W), kernel_size, 1) @ np.asarray(image, np.float64).ravel()


KERNEL = loo_quadratic_kernel()
#: Noise of the scene estimate relative to one pixel's: Σw² (0.081 for 7 × 7).
KERNEL_VAR = float(np.sum(KERNEL**2))


def _radial_coefficients(kernel: np.ndarray) -> tuple[float, float] | None:
    """(c₀, c₂) with ``kernel`` = c₀ + c₂·(x² + y²) off its centre and 0 at it, or None if it is not of that form.

    The leave-one-out quadratic's weights are: they are the design's basis functions (1, x, y, x², y², xy)
    weighted by the row of (DᵀD)⁻¹ that evaluates the fit at the centre, and on a window symmetric under
    x → −x, y → −y and x ↔ y that row has no x, y or xy part and equal x² and y² parts."""
    n = kernel.shape[0]
    h = n // 2
    if kernel.shape != (n, n) or n < 5 or n % 2 == 0:
        return None
    c2 = (kernel[h, h + 2] - kernel[h, h + 1]) / 3.0
    c0 = kernel[h, h + 1] - c2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    model = c0 + c2 * (xx * xx + yy * yy)
    model[h, h] = 0.0
    if not np.allclose(model, kernel, rtol=0.0, atol=1e-14 * float(np.abs(kernel).max())):
        return None
    return float(c0), float(c2)


#: (c₀, c₂) of :data:`KERNEL` (see :func:`_radial_coefficients`).
_KERNEL_RADIAL = _radial_coefficients(KERNEL)
#: Rows of an image summed per block by :func:`correlate_kernel` (its temporaries stay in the cache).
_ROWS_PER_BLOCK = 64


def _padded_rows(img: np.ndarray, y0: int, y1: int, h: int, mode: str) -> np.ndarray:
    """Rows ``y0 − h … y1 + h − 1`` of ``img`` padded by ``h`` on every side as ``ndimage`` extends it ("reflect":
    d c b a | a b c d, numpy's "symmetric"; "constant": zeros), in float64 — one block, not the whole frame.
    (One gather by reflected row and column indices: ``np.pad`` cost as much as the sums it served on tiles.)"""
    H, W = img.shape
    r = np.arange(y0 - h, y1 + h)
    c = np.arange(-h, W + h)
    if mode == "reflect":
        r = np.where(r < 0, -r - 1, r)
        r = np.where(r >= H, 2 * H - 1 - r, r)
        c = np.where(c < 0, -c - 1, c)
        c = np.where(c >= W, 2 * W - 1 - c, c)
        return img[r[:, None], c[None, :]].astype(np.float64)
    block = np.zeros((r.size, W + 2 * h))
    inside = (r >= 0) & (r < H)
    block[inside, h:W + h] = img[r[inside]]
    return block


def correlate_kernel(image: np.ndarray, mode: str = "reflect") -> np.ndarray:
    """``ndimage.correlate(image, KERNEL, mode=mode)`` for ``mode`` "reflect" or "constant" (zero outside),
    from box sums and squared-offset sums along each axis (equal to it within rounding: ~10⁻¹⁵ relative).

    Why by hand: the kernel is c₀ + c₂·(x² + y²) off its centre (:func:`_radial_coefficients`), so the 49-tap
    correlation is c₀·(7 × 7 box sum − centre) + c₂·(Σ x²·I + Σ y²·I), each a pair of 7-tap sums along the two
    axes; as contiguous slices of the padded image, a block of rows at a time, that is about 2–2.7× faster than
    ``scipy.ndimage.correlate`` on frames of 134² to 320 × 240 (benchmarks/RESULTS_check.md, eighteenth session)
    — the correlation was a fifth of the check's time.  Computed in float64, padded a block at a time (memory of a
    block besides the output, as for a whole 24 MP frame); returned in ``image``'s dtype."""
    img = np.asarray(image)
    if _KERNEL_RADIAL is None or img.ndim != 2 or mode not in ("reflect", "constant") or min(img.shape) < 4:
        return ndimage.correlate(img, KERNEL, mode=mode)
    c0, c2 = _KERNEL_RADIAL
    h = SCENE_SIZE // 2
    H, W = img.shape
    out = np.empty((H, W), np.float64)
    for y0 in range(0, H, _ROWS_PER_BLOCK):
        y1 = min(y0 + _ROWS_PER_BLOCK, H)
        rows = _padded_rows(img, y0, y1, h, mode)
        n = y1 - y0
        s1 = rows[:, 2:W + 2] + rows[:, 4:W + 4]  # the pairs of columns at |x| = 1, 2, 3
        s2 = rows[:, 1:W + 1] + rows[:, 5:W + 5]
        s3 = rows[:, 0:W] + rows[:, 6:W + 6]
        box = rows[:, 3:W + 3] + s1
        box += s2
        box += s3  # Σ over x of the row
        x2 = s2 * 4.0
        x2 += s1
        x2 += 9.0 * s3  # Σ x²·I over x
        t1 = box[2:n + 2] + box[4:n + 4]
        t2 = box[1:n + 1] + box[5:n + 5]
        t3 = box[0:n] + box[6:n + 6]
        est = box[3:n + 3] + t1
        est += t2
        est += t3  # the 7 × 7 box sum
        est -= img[y0:y1]
        est *= c0
        radial = t2 * 4.0
        radial += t1
        radial += 9.0 * t3  # Σ y²·I
        for d in range(2 * h + 1):
            radial += x2[d:d + n]  # + Σ x²·I
        radial *= c2
        est += radial
        out[y0:y1] = est
    return out.astype(img.dtype, copy=False) if img.dtype == np.float32 else out


def plane_fill(image: np.ndarray, good: np.ndarray, size: int = 5, wide: int = 15) -> np.ndarray:
    """The image with every pixel that is not ``good`` replaced by the least-squares plane through the good
    pixels of its ``size × size`` window (inside the image only), evaluated there; ``wide × wide`` where the
    window has fewer than 3 good pixels.

    A plane is exact for any gradient, also at an edge or next to other gaps, where a box mean is off by
    about the gradient (vignetting is steepest at the edges) and would spoil the neighbours' estimates.

    Only the windows of the pixels to fill are visited (their moments summed offset by offset, in coordinates
    relative to the pixel), so the cost grows with the number of pixels filled, not with the image."""
    out = np.array(image, np.float64, copy=True)
    good = np.asarray(good, bool)
    ty, tx = np.nonzero(~good)
    for n in (size, wide):
        if not ty.size:
            break
        m = _window_moments(out, good, ty, tx, n)
        s1, sx, sy, sxx, syy, sxy, b0, bx, by = m / float(n * n)  # box means, as a uniform filter gives them
        A = np.stack([np.stack([s1, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], -2)
        b = np.stack([b0, bx, by], -1)
        ok = (s1 * n * n >= 2.5) & (np.abs(np.linalg.det(A)) > 1e-12 * np.maximum(s1, 1e-300) ** 3)
        coef = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        out[ty[ok], tx[ok]] = coef[:, 0]  # the plane at the pixel itself (the origin of its coordinates)
        ty, tx = ty[~ok], tx[~ok]
    if ty.size:
        out[ty, tx] = float(np.mean(image[good])) if good.any() else 0.0
    return out


def _window_moments(image: np.ndarray, good: np.ndarray, ty: np.ndarray, tx: np.ndarray, n: int,
                    chunk: int = 16384) -> np.ndarray:
    """Per pixel (ty, tx), sums over the good pixels of its ``n × n`` window inside the image of 1, x, y, x², y²,
    xy, v, v·x, v·y (x, y relative to the pixel, v the image value): ``(9, len(ty))``."""
    h, w = image.shape
    r = n // 2
    dy, dx = (a.ravel() for a in np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64))
    powers = np.stack([np.ones_like(dx), dx, dy, dx * dx, dy * dy, dx * dy], -1)  # (n², 6)
    oy, ox = dy.astype(np.intp), dx.astype(np.intp)
    m = np.empty((9, ty.size))
    for lo in range(0, ty.size, chunk):
        yy = ty[lo:lo + chunk, None] + oy
        xx = tx[lo:lo + chunk, None] + ox
        use = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        np.clip(yy, 0, h - 1, out=yy)
        np.clip(xx, 0, w - 1, out=xx)
        use &= good[yy, xx]
        v = np.where(use, image[yy, xx], 0.0)
        m[:6, lo:lo + chunk] = (use.astype(np.float64) @ powers).T
        m[6:, lo:lo + chunk] = (v @ powers[:, :3]).T
    return m


def kernel_estimate(image: np.ndarray, kernel: np.ndarray = KERNEL) -> np.ndarray:
    """The scene kernel applied to ``image`` (reflecting at the edges; the scene kernel's clipped windows within
    its half-width of the edge): the linear part of :func:`scene_estimate_and_fill`."""
    est = correlate_kernel(image) if kernel is KERNEL else ndimage.correlate(image, kernel, mode="reflect")
    if kernel.shape[0] == SCENE_SIZE:
        edge_estimates(image, est)
    return est


def kernel_transpose(image: np.ndarray, power: int = 1) -> np.ndarray:
    """The transpose of :func:`kernel_estimate` (default kernel) applied to ``image``: ``Kᵀ·u`` with
    ``(Kᵀ·u)_q = Σ_p K_pq·u_p`` — how much each pixel's value enters all the estimates, weighted by ``u``.
    ``power=2``: the same with the squared weights K_pq² (the coupling's share of a pixel's own information).

    Interior rows are the plain kernel, whose transpose is a convolution with zeros outside; the edge band's
    clipped windows (:func:`_edge_band`) are scattered back by their own weights."""
    u = np.asarray(image, np.float64)
    h = SCENE_SIZE // 2
    H, W = u.shape
    if H <= 2 * h + 1 or W <= 2 * h + 1:  # no edge band (kernel_estimate reflects): the transpose by probing
        return _probed_transpose(u, power)
    inner = np.zeros_like(u)
    inner[h:H - h, h:W - h] = u[h:H - h, h:W - h]
    # (the kernel is symmetric: its convolution is its correlation)
    out = correlate_kernel(inner, "constant") if power == 1 else ndimage.convolve(inner, KERNEL**power,
                                                                                 mode="constant", cval=0.0)
    ys, xs, _, _ = _edge_band((H, W), SCENE_SIZE)
    flat = out.ravel()
    flat += _edge_operator((H, W), SCENE_SIZE, power, transpose=True) @ u[ys, xs]
    return out


def _probed_transpose(u: np.ndarray, power: int) -> np.ndarray:
    """Kᵀ·u from the matrix of :func:`kernel_estimate`, one column per pixel (small images only)."""
    n = u.size
    eye = np.eye(n).reshape(n, *u.shape)
    columns = np.stack([kernel_estimate(e).ravel() for e in eye], axis=1)  # K[:, q] = K·e_q
    return ((columns**power).T @ u.ravel()).reshape(u.shape)


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
        est = kernel_estimate(filled, kernel)
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
