"""One streaming pass over a stack of images: count, mean, variance, minimum and maximum per pixel.

Memory is a handful of image-sized accumulators whatever the number of
images.  Integer images (uint8, uint16) are summed exactly in unsigned
integers — the cheapest pass there is, which keeps detection at reading
speed.  Other images are summed in float64 about a reference frame (the
first image), which avoids the cancellation of the naive sum-of-squares
formula while costing only three array operations per image.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress

#: uint32 sums of 16-bit values stay exact up to 65,537 images.
MAX_INTEGER_IMAGES = 65_000


@dataclass
class StackStats:
    """Per-pixel statistics of ``n`` images (arrays of the images' shape).

    ``var`` is the unbiased (ddof = 1) sample variance (zero when ``n == 1``);
    ``minimum`` and ``maximum`` keep the images' dtype.
    """

    n: int
    mean: np.ndarray
    var: np.ndarray
    minimum: np.ndarray
    maximum: np.ndarray

    @property
    def constant(self) -> np.ndarray:
        """True where every image had the same value (the paper's stuck-pixel test, eq. 11)."""
        return self.minimum == self.maximum

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var)


class StackAccumulator:
    """Accumulate :class:`StackStats` image by image.

    The first image fixes the shape, the dtype and the summation: exact
    unsigned-integer sums for uint8/uint16, float64 sums about the first
    image otherwise.

    Examples
    --------
    >>> acc = StackAccumulator()
    >>> for img in images:          # doctest: +SKIP
    ...     acc.add(img)
    >>> stats = acc.result()        # doctest: +SKIP
    """

    def __init__(self) -> None:
        self.n = 0
        self._dtype: np.dtype | None = None
        self._integer = False
        self._ref: np.ndarray | None = None  # float path: the reference frame
        self._s1 = self._s2 = self._work = self._min = self._max = None

    def add(self, image: np.ndarray, name: str = "image") -> None:
        """Add one image (any real dtype); all images must share one shape and dtype."""
        image = np.asarray(image)
        if self._dtype is None:
            self._start(image)
        elif image.shape != self._min.shape or image.dtype != self._dtype:
            raise InputError(f"{name}: {image.dtype} {image.shape} differs from the first image's "
                             f"{self._dtype} {self._min.shape}; a stack's images must all have one size and type")
        else:
            np.minimum(self._min, image, out=self._min)
            np.maximum(self._max, image, out=self._max)
        if self._integer:
            if self.n + 1 >= MAX_INTEGER_IMAGES:
                raise InputError(f"more than {MAX_INTEGER_IMAGES - 1} images in one stack; split the set")
            np.add(self._s1, image, out=self._s1)
            np.multiply(image, image, out=self._work, dtype=self._work.dtype)
            np.add(self._s2, self._work, out=self._s2)
        else:
            np.subtract(image, self._ref, out=self._work)
            self._s1 += self._work
            np.multiply(self._work, self._work, out=self._work)
            self._s2 += self._work
        self.n += 1

    def _start(self, image: np.ndarray) -> None:
        self._dtype = image.dtype
        self._min, self._max = image.copy(), image.copy()
        self._integer = image.dtype in (np.uint8, np.uint16)
        if self._integer:
            eight = image.dtype == np.uint8
            self._s1 = np.zeros(image.shape, np.uint32)
            self._s2 = np.zeros(image.shape, np.uint32 if eight else np.uint64)
            self._work = np.empty(image.shape, np.uint16 if eight else np.uint32)
        else:
            self._ref = image.astype(np.float64)
            self._s1 = np.zeros(image.shape, np.float64)
            self._s2 = np.zeros(image.shape, np.float64)
            self._work = np.empty(image.shape, np.float64)

    def result(self) -> StackStats:
        """Mean and unbiased variance (float32), computed in row blocks (no image-sized float64 temporaries)."""
        if self.n == 0 or self._s1 is None:
            raise InputError("no images to accumulate")
        n = self.n
        mean = np.empty(self._s1.shape, np.float32)
        var = np.zeros(self._s1.shape, np.float32)
        rows = max(1, 1_000_000 // max(1, int(np.prod(self._s1.shape[1:]))))
        for y in range(0, self._s1.shape[0], rows):
            block = slice(y, y + rows)
            s1 = self._s1[block].astype(np.float64)
            m = s1 / n
            mean[block] = m if self._integer else self._ref[block] + m
            if n > 1:
                v = self._s2[block].astype(np.float64)
                v -= s1 * m
                v /= n - 1
                np.maximum(v, 0.0, out=v)
                var[block] = v
        return StackStats(n, mean, var, self._min.copy(), self._max.copy())


def stack_stats(images: Iterable[np.ndarray], progress: Progress = no_progress, total: int | None = None,
                desc: str | None = "stack") -> StackStats:
    """Per-pixel statistics of ``images`` in one streaming pass."""
    acc = StackAccumulator()
    for i, image in enumerate(progress(images, total=total, desc=desc)):
        acc.add(image, name=f"image {i}")
    return acc.result()
