"""WAHET-like segmentation (placeholder while being written)."""
from __future__ import annotations

import numpy as np

from forensics.impact.segment.common import Segmentation


def segment_wahet(image: np.ndarray, **params) -> Segmentation:
    raise NotImplementedError
