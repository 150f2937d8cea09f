"""The check's random streams, derived from one ``rng`` (the toolkit's convention, :mod:`forensics._shared.rng`).

The checker draws from several independent, reproducible streams: the fixed patterns of every device it
fits (the *same* draws for every fit of one check, so that fits compare like with like), the null
simulations of the fitted arrival model, and the simulated signatures of arrival candidates.  Each is a
fresh generator keyed by a small integer and derived from ``rng``'s seed sequence, so an integer seed
``s`` gives exactly the streams the checker has always used: ``default_rng(s)`` for the fixed patterns and
``default_rng([s, k])`` for stream ``k``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from forensics._shared.rng import RngLike, keyed_generator

#: Stream keys.
NULL_SIMULATIONS = 1
ARRIVAL_SIGNATURES = 7
#: bootstrap of a pixel-local pattern's size (forensics.check.pixels.pattern_size)
PATTERN_SIZE_STREAM = 11
#: parametric bootstrap of the defects' pair excess (forensics.check.arrivals.DefectCounts.co_arrival_draws)
PAIR_EXCESS_STREAM = 13


@dataclass(frozen=True)
class Streams:
    """The check's Monte-Carlo settings: the root ``rng`` and the number of null simulations."""

    rng: RngLike
    n_sim: int = 199

    def patterns(self) -> np.random.Generator:
        """Fixed patterns of a device being fitted (a fresh, identical stream for every fit)."""
        return keyed_generator(self.rng)

    def stream(self, key: int) -> np.random.Generator:
        return keyed_generator(self.rng, key)
