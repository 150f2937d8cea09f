"""One streaming pass over a stack of images: count, mean, variance, minimum and maximum per pixel.

Memory is a handful of image-sized accumulators whatever the number of
images.  Sums are kept in float64 about a reference frame (the first image),
which avoids the cancellation of the naive sum-of-squares formula while
costing only three array operations per image.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .progress import Progress, no_progress


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

    Examples
    --------
    >>> acc = StackAccumulator()
    >>> for img in images:          # doctest: +SKIP
    ...     acc.add(img)
    >>> stats = acc.result()        # doctest: +SKIP
    """

    def __init__(self) -> None:
        self.n = 0
        self._ref: np.ndarray | None = None
        self._s1: np.ndarray | None = None
        self._s2: np.ndarray | None = None
        self._min: np.ndarray | None = None
        self._max: np.ndarray | None = None
        self._delta: np.ndarray | None = None

    def add(self, image: np.ndarray, name: str = "image") -> None:
        """Add one image (any real dtype); all images must share one shape."""
        image = np.asarray(image)
        if self._ref is None:
            self._ref = image.astype(np.float64)
            self._s1 = np.zeros(image.shape, np.float64)
            self._s2 = np.zeros(image.shape, np.float64)
            self._delta = np.empty(image.shape, np.float64)
            self._min = image.copy()
            self._max = image.copy()
        elif image.shape != self._ref.shape:
            raise InputError(f"{name}: shape {image.shape} differs from the first image's {self._ref.shape}; "
                             "a stack's images must all have one size")
        else:
            np.minimum(self._min, image, out=self._min)
            np.maximum(self._max, image, out=self._max)
        np.subtract(image, self._ref, out=self._delta)
        self._s1 += self._delta
        np.multiply(self._delta, self._delta, out=self._delta)
        self._s2 += self._delta
        self.n += 1

    def result(self) -> StackStats:
        """The statistics so far (float32 mean and variance)."""
        if self.n == 0 or self._ref is None:
            raise InputError("no images to accumulate")
        mean_delta = self._s1 / self.n
        if self.n > 1:
            var = (self._s2 - self.n * mean_delta**2) / (self.n - 1)
            np.maximum(var, 0.0, out=var)
        else:
            var = np.zeros_like(mean_delta)
        mean = (self._ref + mean_delta).astype(np.float32)
        return StackStats(self.n, mean, var.astype(np.float32), self._min.copy(), self._max.copy())


def stack_stats(images: Iterable[np.ndarray], progress: Progress = no_progress, total: int | None = None,
                desc: str | None = "stack") -> StackStats:
    """Per-pixel statistics of ``images`` in one streaming pass."""
    acc = StackAccumulator()
    for i, image in enumerate(progress(images, total=total, desc=desc)):
        acc.add(image, name=f"image {i}")
    return acc.result()
