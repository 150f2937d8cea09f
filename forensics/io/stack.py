"""One streaming pass over a stack of images: count, mean, variance, minimum and maximum per pixel.

Memory is a handful of image-sized accumulators whatever the number of
images.  Integer images (uint8, uint16) are summed exactly in unsigned
integers — the cheapest pass there is, which keeps detection at reading
speed.  Other images are summed in float64 about a reference frame (the
first image), which avoids the cancellation of the naive sum-of-squares
formula while costing only three array operations per image.

A long stack is cut into chunks of :data:`STACK_CHUNK` frames that can be
accumulated anywhere (:func:`accumulate_chunk`, a work item of
:mod:`forensics._shared.parallel`: it reads its frames from their paths) and
merged exactly (:meth:`StackAccumulator.merge`), folded in chunk order
(:func:`stack_sets`).  Integer sums add exactly, so integer stacks give
bit-identical statistics however they are chunked; float stacks agree with
one pass to float64 rounding (see :meth:`StackAccumulator.merge`) and are
bit-identical across backends, because the chunking depends on the data only.
"""
from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.errors import InputError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.text import printable

if TYPE_CHECKING:  # the execution layer is imported only where a parallel pass runs
    from forensics._shared.parallel import Executor

#: uint32 sums of 16-bit values stay exact up to 65,537 images.
MAX_INTEGER_IMAGES = 65_000
#: Frames per work item of a parallel stack pass.  Fixed (never derived from the number of workers) so that
#: float stacks fold identically on every backend.  Small enough that a set of the recommended 50 frames keeps
#: a few workers busy; large enough that a chunk's partial sums (10–16 bytes a sample, at most its decoded
#: frames' size) cost less to ship back than the chunk costs to decode.
STACK_CHUNK = 8


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
        self.first_name: str | None = None  # the first image (named when a merged partial does not fit)
        self._dtype: np.dtype | None = None
        self._integer = False
        self._ref: np.ndarray | None = None  # float path: the reference frame
        self._s1 = self._s2 = self._work = self._min = self._max = None

    def add(self, image: np.ndarray, name: str = "image") -> None:
        """Add one image (any real dtype); all images must share one shape and dtype."""
        image = np.asarray(image)
        if self._dtype is None:
            self._start(image, name)
        elif image.shape != self._min.shape or image.dtype != self._dtype:
            raise InputError(f"{printable(str(name))}: {image.dtype} {image.shape} differs from the first image's "
                             f"{self._dtype} {self._min.shape}; a stack's images must all have one size and type")
        else:
            np.minimum(self._min, image, out=self._min)
            np.maximum(self._max, image, out=self._max)
        work = self._scratch()
        if self._integer:
            self._check_count(self.n + 1)
            np.add(self._s1, image, out=self._s1)
            np.multiply(image, image, out=work, dtype=work.dtype)
            np.add(self._s2, work, out=self._s2)
        else:
            np.subtract(image, self._ref, out=work)
            self._s1 += work
            np.multiply(work, work, out=work)
            self._s2 += work
        self.n += 1

    def _start(self, image: np.ndarray, name: str) -> None:
        self._dtype = image.dtype
        self.first_name = name
        self._min, self._max = image.copy(), image.copy()
        self._integer = image.dtype in (np.uint8, np.uint16)
        if self._integer:
            eight = image.dtype == np.uint8
            self._s1 = np.zeros(image.shape, np.uint32)
            self._s2 = np.zeros(image.shape, np.uint32 if eight else np.uint64)
        else:
            self._ref = image.astype(np.float64)
            self._s1 = np.zeros(image.shape, np.float64)
            self._s2 = np.zeros(image.shape, np.float64)

    def _scratch(self) -> np.ndarray:
        """The image-sized work buffer of :meth:`add` (made on first use: a merged or unpickled
        accumulator that only merges never needs it)."""
        if self._work is None:
            eight = self._dtype == np.uint8
            dtype = (np.uint16 if eight else np.uint32) if self._integer else np.float64
            self._work = np.empty(self._s1.shape, dtype)
        return self._work

    @staticmethod
    def _check_count(n: int) -> None:
        if n >= MAX_INTEGER_IMAGES:
            raise InputError(f"more than {MAX_INTEGER_IMAGES - 1} images in one stack; split the set")

    def __getstate__(self) -> dict[str, Any]:
        # the scratch buffer is an image of garbage: never ship it between processes
        return {**self.__dict__, "_work": None}

    def merge(self, other: "StackAccumulator") -> "StackAccumulator":
        """Add the images accumulated by ``other`` to this accumulator (in place; returns ``self``).

        The parallel form of :meth:`add`: ``a.merge(b)`` holds the images of ``a`` then those of ``b``.
        Integer sums add exactly, so the statistics are bit-identical to one pass over all images.  Float
        sums are kept about this accumulator's reference frame: ``other``'s are moved onto it first
        (Chan et al.'s pairwise update in shifted form — with d = r_b − r_a,
        Σ(x − r_a) = Σ(x − r_b) + n_b·d and Σ(x − r_a)² = Σ(x − r_b)² + 2d·Σ(x − r_b) + n_b·d²), which
        equals one pass up to float64 rounding (a few ulps of the sums; float32 results within an ulp or two).
        ``other`` is left unusable (its arrays may be reused).
        """
        if other.n == 0:
            return self
        if self.n == 0:
            self.__dict__.update(other.__dict__)
            return self
        if other._min.shape != self._min.shape or other._dtype != self._dtype:
            raise InputError(f"{printable(str(other.first_name))}: {other._dtype} {other._min.shape} differs from the first image's "
                             f"{self._dtype} {self._min.shape}; a stack's images must all have one size and type")
        np.minimum(self._min, other._min, out=self._min)
        np.maximum(self._max, other._max, out=self._max)
        if self._integer:
            self._check_count(self.n + other.n)
            self._s1 += other._s1
            self._s2 += other._s2
        else:
            d = np.subtract(other._ref, self._ref)
            term = np.multiply(d, other._s1)
            term *= 2.0
            self._s2 += other._s2
            self._s2 += term
            np.multiply(d, d, out=term)
            term *= other.n
            self._s2 += term
            d *= other.n
            self._s1 += other._s1
            self._s1 += d
        self.n += other.n
        return self

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


# =========================================================================== chunks of frames on the execution layer
def prefetch(items: Iterable[Any], depth: int = 2) -> Iterator[Any]:
    """Yield ``items`` while a background thread produces the next ``depth`` ones (decoding overlaps computing)."""
    import queue

    box: queue.Queue = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                if stop.is_set():
                    return
                box.put((True, item))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the consumer
            box.put((False, exc))
            return
        box.put((True, done))

    worker = threading.Thread(target=produce, daemon=True)
    worker.start()
    try:
        while True:
            ok, item = box.get()
            if not ok:
                raise item
            if item is done:
                return
            yield item
    finally:
        stop.set()
        while worker.is_alive():
            try:
                box.get_nowait()
            except Exception:  # noqa: BLE001
                worker.join(0.01)


def accumulate_paths(paths: Sequence[str]) -> StackAccumulator:
    """Read the images at ``paths`` in order (decoding one ahead) into a partial :class:`StackAccumulator`."""
    from forensics.io.images import read_image

    acc = StackAccumulator()
    for path, image in zip(paths, prefetch(read_image(p) for p in paths)):
        acc.add(image, name=str(path))
    return acc


def accumulate_chunk(item: tuple[int, tuple[str, ...]]) -> tuple[int, StackAccumulator]:
    """Work item of :func:`stack_sets`: ``(set index, frame paths)`` → ``(set index, partial accumulator)``.

    Module-level so the execution layer's workers import it by reference; it reads its frames itself.
    """
    index, paths = item
    return index, accumulate_paths(paths)


def chunk_items(path_sets: Sequence[Sequence[Any]], chunk: int | None = None) -> list[tuple[int, tuple[str, ...]]]:
    """The work items of :func:`stack_sets`: each set's paths cut into :data:`STACK_CHUNK`-frame pieces, set by set.

    The cut depends on the number of frames only — never on the workers — which keeps float folds identical.
    """
    from forensics._shared.parallel import chunks

    size = STACK_CHUNK if chunk is None else chunk
    items = []
    for index, paths in enumerate(path_sets):
        names = [str(p) for p in paths]
        items += [(index, tuple(names[r.start:r.stop])) for r in chunks(len(names), size)]
    return items


def stack_sets(path_sets: Sequence[Sequence[Any]], executor: "Executor | None" = None,
               progress: Progress = no_progress, desc: str | None = "reading",
               chunk: int | None = None) -> Iterator[StackStats]:
    """Per-pixel statistics of several image sets, yielded set by set, their chunks spread over ``executor``.

    Every (set, chunk) pair is one work item, so all workers are busy even when one set has fewer chunks
    than there are workers.  Each set's partial accumulators are merged in chunk order as they come back
    (:meth:`StackAccumulator.merge`), and a set is yielded as soon as its last chunk is in — the caller can
    work on it while the workers read the next sets.

    Parameters
    ----------
    path_sets
        One sequence of image paths per set (each non-empty).
    executor
        The execution layer (None: in this process).
    progress, desc
        One progress bar counting the chunks of every set.
    chunk
        Frames per work item (default :data:`STACK_CHUNK`); part of the data, never the number of workers.

    Raises
    ------
    InputError
        An empty set, an unreadable image, or images of different sizes or types within a set.
    """
    from forensics._shared.parallel import resolve

    for index, paths in enumerate(path_sets):
        if len(paths) == 0:
            raise InputError(f"image set {index + 1} has no images")
    items = chunk_items(path_sets, chunk)
    per_set = [sum(1 for k, _ in items if k == index) for index in range(len(path_sets))]
    return _fold_sets(resolve(executor).map(accumulate_chunk, items, progress=progress, desc=desc), per_set)


def _fold_sets(parts: Iterator[tuple[int, StackAccumulator]], per_set: list[int]) -> Iterator[StackStats]:
    """Merge each set's partial accumulators in chunk order; yield its statistics when its last chunk is in.

    ``parts`` come in item order (:meth:`Executor.map`) and the items run set by set, so this is the ordered
    reduction (``ex.reduce``) of every set in turn — without holding every set's sums at once.
    """
    remaining = list(per_set)
    acc: StackAccumulator | None = None
    for index, part in parts:
        acc = part if acc is None else acc.merge(part)
        remaining[index] -= 1
        if remaining[index] == 0:
            yield acc.result()
            acc = None


def stack_paths(paths: Sequence[Any], executor: "Executor | None" = None, progress: Progress = no_progress,
                desc: str | None = "reading", chunk: int | None = None) -> StackStats:
    """Per-pixel statistics of the images at ``paths``: :func:`stack_sets` of one set."""
    (stats,) = stack_sets([paths], executor, progress, desc, chunk)  # drain it: the progress bar closes
    return stats
