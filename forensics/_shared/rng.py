"""The one way random numbers enter the toolkit.

Convention (the same in every module): a public function that draws random numbers has a parameter
``rng`` that accepts either a :class:`numpy.random.Generator` or an integer seed (:data:`RngLike`);
it calls :func:`as_generator` once and passes the generator down.  An integer seed ``s`` gives exactly
``numpy.random.default_rng(s)``, so ``f(rng=7)`` and ``f(rng=np.random.default_rng(7))`` draw the same
numbers.  Independent work items (images, devices, trials) draw from their own streams — children
made by :func:`spawn` (``SeedSequence.spawn``) or the keyed sub-stream of :func:`keyed_generator`
(``default_rng([seed, *key])`` for an integer seed) — never from the order in which they run.  There is no
default seed and no global state: ``None`` is refused.
"""
from __future__ import annotations

from typing import Any, Union

import numpy as np

#: What every ``rng`` parameter accepts.
RngLike = Union[np.random.Generator, int, np.integer, np.random.SeedSequence]


def as_generator(rng: RngLike) -> np.random.Generator:
    """The generator for ``rng``: itself if it is a Generator, else ``default_rng(rng)``.

    Raises
    ------
    TypeError
        For ``None``, floats, legacy ``RandomState`` objects and anything else.
    """
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (bool, np.bool_)):
        raise TypeError("rng must be a numpy.random.Generator or an integer seed, not a bool")
    if isinstance(rng, (int, np.integer)):
        if rng < 0:
            raise TypeError(f"a seed must be a non-negative integer, got {rng}")
        return np.random.default_rng(int(rng))
    if isinstance(rng, np.random.SeedSequence):
        return np.random.default_rng(rng)
    raise TypeError("rng must be a numpy.random.Generator or an integer seed "
                    f"(e.g. numpy.random.default_rng(0) or 0), got {type(rng).__name__}")


def spawn(rng: RngLike, n: int) -> list[np.random.Generator]:
    """``n`` independent child generators of ``rng`` (``SeedSequence.spawn``).

    For an integer seed ``s`` the children are those of ``SeedSequence(s)``: the i-th item's stream
    depends on ``s`` and ``i`` only, whatever order or process it runs in.
    """
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, (bool, np.bool_)):
        return [np.random.default_rng(s) for s in np.random.SeedSequence(int(rng)).spawn(n)]
    return list(as_generator(rng).spawn(n))


def keyed_generator(rng: RngLike, *key: int) -> np.random.Generator:
    """The generator of the sub-stream ``key`` of ``rng``: ``default_rng([seed, *key])`` for an integer seed.

    For a Generator (or SeedSequence) the key extends its seed sequence's entropy, keeping its spawn key,
    so ``rng=7`` and ``rng=default_rng(7)`` give the same sub-streams, children made by
    :func:`spawn` give different ones, and the generator's own state is neither
    used nor advanced: a work item's stream depends on the run's seed and the item's key only, whatever
    order or process it runs in.
    """
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, (bool, np.bool_)):
        if rng < 0:
            raise TypeError(f"a seed must be a non-negative integer, got {rng}")
        return np.random.default_rng([int(rng), *(int(k) for k in key)])
    seq = rng if isinstance(rng, np.random.SeedSequence) else as_generator(rng).bit_generator.seed_seq
    entropy = seq.entropy
    base = [int(e) for e in entropy] if isinstance(entropy, (list, tuple, np.ndarray)) else [int(entropy)]
    return np.random.default_rng(np.random.SeedSequence([*base, *(int(k) for k in key)], spawn_key=seq.spawn_key,
                                                        pool_size=seq.pool_size))


def seed_record(rng: RngLike) -> Any:
    """What to write into an output's provenance so that a run can be repeated: the seed itself when an
    integer was given, else the generator's seed sequence (entropy and spawn key)."""
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, (bool, np.bool_)):
        return int(rng)
    seq = rng if isinstance(rng, np.random.SeedSequence) else as_generator(rng).bit_generator.seed_seq
    entropy = seq.entropy
    if isinstance(entropy, (list, tuple, np.ndarray)):  # a keyed sub-stream: [seed, *key]
        entropy = [int(e) for e in entropy]
    elif entropy is not None:
        entropy = int(entropy)
    return {"entropy": entropy,
            "spawn_key": [int(k) for k in seq.spawn_key]}
