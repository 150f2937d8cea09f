"""Partial stack accumulators merged in chunk order equal one streaming pass (integers bit for bit)."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics._shared.parallel import Executor
from forensics.io.images import write_image
from forensics.io.stack import StackAccumulator, StackStats, stack_paths, stack_sets, stack_stats


def _frames(dtype: type, n: int, shape: tuple[int, ...] = (24, 32), seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    if np.issubdtype(dtype, np.integer):
        top = np.iinfo(dtype).max
        frames = [rng.integers(0, top + 1, shape).astype(dtype) for _ in range(n)]
        for f in frames:  # full-scale samples everywhere in one column: the widest sums of squares
            f[:, 0] = top
        return frames
    # an offset far above the spread, as in real frames: what the reference-frame sums are for
    return [(1000.0 + rng.normal(0.0, 5.0, shape)).astype(dtype) for _ in range(n)]


def _merged(frames: list[np.ndarray], size: int) -> StackStats:
    """Accumulate chunks of ``size`` frames separately (through pickle, as a worker returns them), merge in order."""
    acc = StackAccumulator()
    for start in range(0, len(frames), size):
        part = StackAccumulator()
        for f in frames[start:start + size]:
            part.add(f)
        acc.merge(pickle.loads(pickle.dumps(part)))
    return acc.result()


def _identical(a: StackStats, b: StackStats) -> bool:
    return (a.n == b.n and all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("mean", "var", "minimum", "maximum"))
            and a.minimum.dtype == b.minimum.dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("size", [1, 3, 4, 10, 11])
def test_integer_merge_is_bit_identical_to_one_pass(dtype, size):
    """Chunks of 1 (every chunk a single image), uneven cuts (10 = 3+3+3+1, 4+4+2) and one chunk: the same bits."""
    frames = _frames(dtype, 10, seed=size)
    assert _identical(_merged(frames, size), stack_stats(frames))


def test_colour_integer_merge_is_bit_identical():
    frames = _frames(np.uint16, 7, shape=(12, 16, 3), seed=5)
    assert _identical(_merged(frames, 3), stack_stats(frames))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_merge_equals_one_pass_to_rounding(dtype):
    """Float sums are moved onto the first chunk's reference frame, which rounds differently from one pass.

    The sums agree to a few float64 ulps (relative ~1e-15 of Σ(x − r)², with |x − r| ~ 5 DN); mean and var
    are then rounded to float32, so they differ by at most an ulp or two of float32: rtol 1e-6 (≈ 8 ulps)
    holds with a wide margin and still fails for any wrong term of the shift (which is O(1) of var)."""
    frames = _frames(dtype, 13, seed=7)
    ref = stack_stats(frames)
    for size in (1, 4, 13):
        got = _merged(frames, size)
        assert got.n == ref.n
        assert np.array_equal(got.minimum, ref.minimum) and np.array_equal(got.maximum, ref.maximum)
        np.testing.assert_allclose(got.mean, ref.mean, rtol=1e-6, atol=0)
        np.testing.assert_allclose(got.var, ref.var, rtol=1e-6, atol=1e-6 * float(ref.var.max()))
    assert np.array_equal(_merged(frames, 13).var, ref.var)  # one chunk is the one pass


def test_merge_refuses_other_sizes_and_too_many_images():
    a, b = StackAccumulator(), StackAccumulator()
    a.add(np.zeros((4, 5), np.uint16), name="first.png")
    b.add(np.zeros((4, 6), np.uint16), name="odd.png")
    with pytest.raises(InputError, match="odd.png"):
        a.merge(b)
    c = StackAccumulator()
    c.add(np.zeros((4, 5), np.uint8), name="eight.png")
    with pytest.raises(InputError, match="eight.png"):
        a.merge(c)
    d = StackAccumulator()
    d.add(np.zeros((4, 5), np.uint16))
    a.n = 64_999  # as if nearly full: the merged count would overflow the exact sums
    with pytest.raises(InputError, match="split the set"):
        a.merge(d)


def test_merging_into_or_from_an_empty_accumulator_and_adding_after_unpickling():
    frames = _frames(np.uint16, 5, seed=3)
    part = StackAccumulator()
    for f in frames[:3]:
        part.add(f)
    acc = StackAccumulator().merge(pickle.loads(pickle.dumps(part))).merge(StackAccumulator())
    for f in frames[3:]:
        acc.add(f)  # the scratch buffer, not shipped, is made again
    assert _identical(acc.result(), stack_stats(frames))


def test_stack_paths_read_by_chunks_on_processes(tmp_path):
    """From files: chunks of 3 frames on two worker processes give the one-pass statistics of the same images."""
    frames = _frames(np.uint16, 8, seed=11)
    paths = [write_image(tmp_path / f"f{i}.png", f) for i, f in enumerate(frames)]
    ref = stack_stats(frames)
    assert _identical(stack_paths(paths, chunk=3), ref)
    with Executor("processes", workers=2) as ex:
        first, second = stack_sets([paths, paths[:5]], ex, chunk=3)
    assert _identical(first, ref) and _identical(second, stack_stats(frames[:5]))
    with pytest.raises(InputError, match="no images"):
        list(stack_sets([paths, []]))
