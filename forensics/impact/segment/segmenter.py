"""The segmentations by name, and the :class:`Segmenter` that segments and unwraps an image once for all matchers.

``SEGMENTATIONS`` maps a name to a function ``(image, **params) -> Segmentation``: ``caht`` (contrast-adjusted
Hough transforms, :mod:`~forensics.impact.segment.caht`) and ``wahet`` (weighted adaptive Hough and
ellipsopolar transforms, :mod:`~forensics.impact.segment.wahet`), the reference paper's two.
"""
from __future__ import annotations

import hashlib
import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from forensics._shared.errors import UsageError
from forensics.impact.segment.caht import segment_caht
from forensics.impact.segment.common import Segmentation
from forensics.impact.segment.memo import StepMemo
from forensics.impact.segment.normalise import normalise
from forensics.impact.segment.wahet import segment_wahet

#: Segmentation methods by name.
SEGMENTATIONS: dict[str, Callable[..., Segmentation]] = {"caht": segment_caht, "wahet": segment_wahet}
#: The default segmentation.
DEFAULT_SEGMENTATION = "caht"


def segmentation_function(method: str) -> Callable[..., Segmentation]:
    """The segmentation called ``method``.

    Raises
    ------
    UsageError
        For an unknown name (the message lists the known ones).
    """
    try:
        return SEGMENTATIONS[method]
    except KeyError:
        raise UsageError(f"unknown segmentation {method!r}; choose from {', '.join(SEGMENTATIONS)}") from None


def takes_memo(method: str) -> bool:
    """Whether the segmentation called ``method`` can reuse steps through a ``memo`` (:class:`StepMemo`)."""
    return "memo" in inspect.signature(segmentation_function(method)).parameters


def segment_iris(image: np.ndarray, method: str = DEFAULT_SEGMENTATION, **params: Any) -> Segmentation:
    """Segment an eye image with the named method (``caht`` or ``wahet``); ``params`` go to that method."""
    return segmentation_function(method)(image, **params)


@dataclass
class Segmenter:
    """Segmentation and normalisation parameters plus a one-image cache.

    Two matchers encoding the same image one after the other (the experiment's order) share one
    segmentation: the cache key is a BLAKE2b digest of the image bytes, shape and dtype (≈0.1 ms at 320×240).
    The cache keeps the last image's segmentation and its unwrapped bands, one per ``(radial, angular)``.

    Parameters
    ----------
    method
        Segmentation name (:data:`SEGMENTATIONS`).
    segment_params
        Keyword arguments for the segmentation function.
    normalise_params
        Keyword arguments for :func:`~forensics.impact.segment.normalise.normalise` other than the size.
    radial, angular
        Default band size of :meth:`unwrap`.
    min_usable
        An image whose band has less than this fraction of usable samples (eyelids, lashes, reflections,
        outside the image) is a segmentation failure ("too little usable iris"): a code from a handful of
        samples would be compared as if it were an eye.
    """

    method: str = DEFAULT_SEGMENTATION
    segment_params: dict[str, Any] = field(default_factory=dict)
    normalise_params: dict[str, Any] = field(default_factory=dict)
    radial: int = 20
    angular: int = 240
    min_usable: float = 0.25
    _key: bytes | None = field(default=None, init=False, repr=False, compare=False)
    _seg: Segmentation | None = field(default=None, init=False, repr=False, compare=False)
    _bands: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _steps: dict | None = field(default=None, init=False, repr=False, compare=False)
    #: Segmentations actually computed (cache misses); for tests and diagnostics.
    computed: int = field(default=0, init=False, compare=False)

    def __post_init__(self) -> None:
        segmentation_function(self.method)  # an unknown name fails here, not at the first image

    @staticmethod
    def image_key(image: np.ndarray) -> bytes:
        """A fast digest of the pixels, shape and dtype."""
        a = np.ascontiguousarray(image)
        hsh = hashlib.blake2b(a.tobytes(), digest_size=16)
        hsh.update(repr((a.shape, a.dtype.str)).encode())
        return hsh.digest()

    def segment(self, image: np.ndarray, memo: StepMemo | None = None) -> Segmentation:
        """The segmentation of ``image`` (cached).

        With a ``memo`` a segmentation that can (:func:`takes_memo`) reuses its costly steps where their inputs
        are byte-identical to those of the memo's earlier entries, with the same result; the memo collects the
        entries of this image (also on a cache hit).
        """
        key = self.image_key(image)
        if key != self._key or self._seg is None:
            params = dict(self.segment_params)
            if memo is not None and takes_memo(self.method):
                params["memo"] = memo
            seg = segment_iris(image, self.method, **params)
            self._key, self._seg, self._bands = key, seg, {}
            self._steps = dict(memo.entries) if memo is not None else None
            self.computed += 1
        elif memo is not None and self._steps is not None:
            memo.entries.update(self._steps)
        return self._seg

    def unwrap(self, image: np.ndarray, radial: int | None = None, angular: int | None = None
               ) -> tuple[np.ndarray, np.ndarray, Segmentation]:
        """``(texture, mask, segmentation)`` of ``image`` (see :func:`normalise`); cached, arrays read-only.

        The segmentation returned is marked failed when the band has less than ``min_usable`` usable samples.
        """
        seg = self.segment(image)
        size = (int(radial or self.radial), int(angular or self.angular))
        if size not in self._bands:
            texture, mask = normalise(image, seg, size[0], size[1], **self.normalise_params)
            texture.flags.writeable = False
            mask.flags.writeable = False
            usable = float(mask.mean())
            band_seg = seg if usable >= self.min_usable else seg.failed(
                f"too little usable iris ({100 * usable:.0f} % of the band)")
            self._bands[size] = (texture, mask, band_seg)
        return self._bands[size]

    def __getstate__(self) -> dict[str, Any]:
        # The cache is worth nothing in another process: do not ship it.
        state = self.__dict__.copy()
        state.update(_key=None, _seg=None, _bands={}, _steps=None)
        return state
