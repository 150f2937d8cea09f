"""Where in the frame a fingerprint lives (:class:`Region`, :func:`parse_region`): the whole frame, a centred
crop that keeps the CFA phase, or the reference paper's four corner patches stored as one mosaic (see
:mod:`forensics.prnu.fingerprint`).
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from forensics._shared.errors import InputError, UsageError

__all__ = ["Region", "Slices", "parse_region"]

Slices = tuple[slice, slice]


@dataclass(frozen=True)
class Region:
    """Where in the frame the fingerprint lives.

    Attributes
    ----------
    kind : {'full', 'center', 'corners'}
    size : (int, int) or None
        Crop size (height, width) for 'center'; patch size (N, N) for 'corners'.
    """

    kind: str
    size: tuple[int, int] | None = None

    @property
    def spec(self) -> str:
        """The text form accepted by :func:`parse_region`."""
        if self.kind == "full":
            return "full"
        assert self.size is not None
        h, w = self.size
        text = str(h) if h == w else f"{h}x{w}"
        return f"{self.kind}:{text}"

    def __str__(self) -> str:
        return self.spec

    def pieces(self, frame_shape: Sequence[int]) -> list[Slices]:
        """The (row, column) slices of the frame that make up the region, in mosaic order."""
        fh, fw = int(frame_shape[0]), int(frame_shape[1])
        if self.kind == "full":
            return [(slice(0, fh), slice(0, fw))]
        assert self.size is not None
        h, w = self.size
        if self.kind == "center":
            if h > fh or w > fw:
                raise InputError(f"region {self.spec} does not fit in a {fh}×{fw} frame; choose a smaller crop")
            top = ((fh - h) // 2) & ~1
            left = ((fw - w) // 2) & ~1
            return [(slice(top, top + h), slice(left, left + w))]
        # corners: start coordinates rounded down to even so every patch keeps the CFA phase
        if 2 * h > fh or 2 * w > fw:
            raise InputError(f"region {self.spec}: four {h}×{w} corners do not fit in a {fh}×{fw} frame")
        bottom = (fh - h) & ~1
        right = (fw - w) & ~1
        return [
            (slice(0, h), slice(0, w)),
            (slice(0, h), slice(right, right + w)),
            (slice(bottom, bottom + h), slice(0, w)),
            (slice(bottom, bottom + h), slice(right, right + w)),
        ]

    def shape(self, frame_shape: Sequence[int]) -> tuple[int, int]:
        """Shape of the region's array (the mosaic for 'corners')."""
        if self.kind == "full":
            return int(frame_shape[0]), int(frame_shape[1])
        self.pieces(frame_shape)  # validates the fit
        assert self.size is not None
        h, w = self.size
        return (h, w) if self.kind == "center" else (2 * h, 2 * w)

    def mosaic_slices(self, frame_shape: Sequence[int]) -> list[Slices]:
        """Where each piece goes in the region's array (same order as :meth:`pieces`)."""
        if self.kind != "corners":
            h, w = self.shape(frame_shape)
            return [(slice(0, h), slice(0, w))]
        assert self.size is not None
        h, w = self.size
        return [
            (slice(0, h), slice(0, w)),
            (slice(0, h), slice(w, 2 * w)),
            (slice(h, 2 * h), slice(0, w)),
            (slice(h, 2 * h), slice(w, 2 * w)),
        ]

    def extract(self, array: np.ndarray) -> np.ndarray:
        """The region's pixels of a frame ((H, W) or (H, W, C)) as one new array (mosaic for 'corners')."""
        array = np.asarray(array)
        pieces = self.pieces(array.shape)
        out = np.empty(self.shape(array.shape) + array.shape[2:], array.dtype)
        for src, dst in zip(pieces, self.mosaic_slices(array.shape)):
            out[dst] = array[src]
        return out


_REGION_RE = re.compile(r"^(center|centre|corners)(?::(\d+)(?:[x×](\d+))?)?$")


def parse_region(spec: str | Region) -> Region:
    """Parse ``"full"``, ``"center:N"``, ``"center:HxW"``, ``"corners"`` or ``"corners:N"``.

    Raises
    ------
    UsageError
        For any other text (the message lists the accepted forms).
    """
    if isinstance(spec, Region):
        return spec
    text = str(spec).strip().lower()
    if text == "full":
        return Region("full")
    m = _REGION_RE.match(text)
    if m:
        kind = "center" if m.group(1) in ("center", "centre") else "corners"
        if m.group(2) is None:
            if kind == "center":
                raise UsageError(f"region {spec!r}: give the crop size, e.g. 'center:512'")
            return Region("corners", (128, 128))
        h = int(m.group(2))
        w = int(m.group(3)) if m.group(3) else h
        if kind == "corners" and w != h:
            raise UsageError(f"region {spec!r}: corner patches are square, e.g. 'corners:128'")
        if h < 16 or w < 16:
            raise UsageError(f"region {spec!r}: crops smaller than 16 pixels carry no usable fingerprint")
        return Region(kind, (h, w))
    raise UsageError(f"region {spec!r}: expected 'full', 'center:N' (or 'center:HxW'), or 'corners' / 'corners:N'")
