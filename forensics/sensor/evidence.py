"""What an effect may ask of the measurements when it is fitted or tested (model checking).

The model checker (:mod:`forensics.check`) passes an object with exactly these members to
:meth:`Effect.fit <forensics.sensor.model.Effect.fit>`, :meth:`Effect.probe <forensics.sensor.model.Effect.probe>`
and :meth:`Effect.signature <forensics.sensor.model.Effect.signature>`.  They are protocols, so that the
sensor model does not depend on the checker (``forensics.sensor`` never imports ``forensics.check``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np

if TYPE_CHECKING:
    from forensics.sensor.model import Effect


class PairExcess(NamedTuple):
    """Pairs of defect sites that arrived at the same epoch close together, beyond chance (a Thomas fit)."""

    rate: float  #: excess pairs per megapixel per year (0: none beyond chance)
    sigma: float  #: their spread: each site's offset from its cluster's centre, px per axis
    chance: float  #: the chance pairs subtracted within 3σ, whose Poisson noise the excess carries
    exposure: float  #: megapixel-years observed (the interior × the span from the first to the last epoch)
    radii: tuple[float, ...] = ()  #: the radii (px) the pairs were counted within
    chance_within: tuple[float, ...] = ()  #: the chance pairs expected within each of them


class Evidence(Protocol):
    """The measured defect statistics an effect's own estimator (:meth:`Effect.fit`) may use."""

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` of the analysed pixels."""
        ...

    def amplitude_max(self, kind: int, default: float) -> float:
        """Largest detected amplitude of defects of ``kind`` (unbiased), ``default`` when none was detected."""
        ...

    def amplitude_se(self, kind: int) -> float | None:
        """Standard error of :meth:`amplitude_max` (None where it is no estimate: none detected, or stuck pixels,
        whose maximum is the full scale)."""
        ...

    def detect_fraction(self, kind: int, amplitude: float) -> float:
        """Fraction of uniform amplitudes in [0, ``amplitude``] above the detection threshold of ``kind``."""
        ...

    def arrival_rate(self, kind: int) -> float:
        """Detected arrivals of ``kind`` per megapixel per year."""
        ...

    def site_intensity(self) -> float:
        """Defective sites per pixel at the last epoch."""
        ...

    def site_rate(self) -> float:
        """Defective sites of the last epoch (every kind) per megapixel per year of the observed span."""
        ...

    def cluster_excess(self) -> tuple[float, float]:
        """Thomas-cluster excess (A, σ) of Ripley's K of the defect sites at the last epoch."""
        ...

    def co_arrival_excess(self) -> PairExcess:
        """Pairs of sites that arrived at the same epoch, close together, beyond chance (every such pair of a
        cluster's detected members counts once)."""
        ...

    def distinct_pair_share(self, mean_members: float) -> float:
        """The share of the member pairs of clusters of ``mean_members`` detected members, at the fitted spread,
        that are pairs of distinct sites on the pixel grid (:func:`forensics.stats.spatial.distinct_pair_share`)."""
        ...

    def co_arrival_draws(self, mean_members: float) -> np.ndarray:
        """Refits ``(Π*, σ*)`` of the pair excess on counts simulated at the fitted excess for clusters of
        ``mean_members`` detected members (a parametric bootstrap, :func:`forensics.stats.spatial.pair_excess_draws`;
        the same draws for the same arguments)."""
        ...


class ChannelSignature(Protocol):
    """How one parameter of an effect moves one channel's statistics (see :class:`forensics.check.Signature`)."""

    channel: str
    name: str
    x: np.ndarray
    blocks: np.ndarray | None
    pixel_local: bool


class SignatureEvidence(Evidence, Protocol):
    """:class:`Evidence` of a fitted model, which also computes the generic signature of an effect."""

    def signature(self, effect: "Effect") -> list[ChannelSignature]:
        """The generic finite-difference signature of ``effect`` (not in the model) at its null values."""
        ...
