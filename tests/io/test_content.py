"""Content-free frames (:mod:`forensics.io.content`): constant, black or saturated frames are told apart from
frames with content, whatever their pixel type, colour or black level."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.io.content import MIN_EXPOSED, content_problem, frame_content


def test_constant_frames_are_content_free_at_any_level():
    for value, word in ((0, "all black"), (255, "all saturated"), (128, "")):
        problem = content_problem(np.full((32, 48), value, np.uint8))
        assert problem is not None and problem.startswith(f"constant: every pixel is {value}") and word in problem
    assert content_problem(np.full((8, 8, 3), 0.25, np.float32)) is not None


def test_a_black_frame_with_a_few_hot_pixels_is_content_free():
    """The D06 case: a handful of defects is all a black frame holds (0.05 % of its pixels exposed)."""
    frame = np.zeros((256, 256), np.uint8)
    frame[:3, :10] = 40
    content = frame_content(frame)
    assert content.exposed == pytest.approx(30 / 256**2) and content.black == pytest.approx(1 - 30 / 256**2)
    problem = content.problem()
    assert problem is not None and "mostly black" in problem and "0.04578 %" in problem


def test_mostly_saturated_frames_are_content_free_and_named_so():
    frame = np.full((100, 100), 65535, np.uint16)
    frame[0, :50] = 1000  # 0.5 % exposed
    problem = content_problem(frame)
    assert problem is not None and "mostly saturated" in problem


def test_natural_frames_with_large_clipped_areas_keep_their_content():
    """A night sky (70 % black) or blown highlights (40 % saturated) leave plenty of exposed pixels."""
    rng = np.random.default_rng(0)
    frame = rng.integers(1, 255, (200, 300), dtype=np.uint8)
    frame[:140] = 0
    assert frame_content(frame).exposed == pytest.approx(0.3) and content_problem(frame) is None
    frame = rng.integers(1, 255, (200, 300), dtype=np.uint8)
    frame[:80] = 255
    assert content_problem(frame) is None
    # the threshold itself: just below 1 % exposed is refused, at 1 % it is not
    frame = np.zeros((100, 100), np.uint8)
    frame.flat[: int(MIN_EXPOSED * frame.size) - 1] = 7
    assert content_problem(frame) is not None
    frame.flat[: int(MIN_EXPOSED * frame.size)] = 7
    assert content_problem(frame) is None


def test_levels_black_level_arrays_colour_and_pieces():
    # a raw mosaic with a black level of 64: pixels at or below it are black
    frame = np.full((64, 64), 64, np.uint16)
    frame[::2, ::2] = 63
    assert content_problem(frame, black_level=64.0) is not None
    assert content_problem(frame, black_level=0.0) is None  # the same pixels are exposed above black 0
    # a per-pixel black level (a tiled 2×2 CFA pattern)
    black = np.tile(np.array([[63.0, 64.0], [64.0, 64.0]]), (32, 32))
    assert frame_content(frame, black).exposed == 0.0
    # colour: saturated if any channel is, black only if every channel is
    rgb = np.zeros((10, 10, 3), np.uint8)
    rgb[..., 0] = 200  # pure red: exposed
    assert frame_content(rgb).exposed == 1.0
    rgb[..., 1] = 255
    assert frame_content(rgb).saturated == 1.0
    # a saturation level below the container's full scale (12-bit data in 16 bits)
    data = np.random.default_rng(1).integers(4000, 4096, (32, 32)).astype(np.uint16)
    assert frame_content(data, saturation_level=4095).saturated > 0
    # pieces of one frame (a fingerprint's four corners) are counted together
    assert frame_content([np.zeros((4, 4), np.uint8), np.full((4, 4), 9, np.uint8)]).exposed == 0.5
