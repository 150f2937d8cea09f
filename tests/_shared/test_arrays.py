"""Full scale and the two grey conversions (BT.601 luma for PRNU, channel mean for defects)."""
import numpy as np
import pytest

from forensics._shared.arrays import bits_full_scale, full_scale, grey_luma, grey_mean, infer_full_scale
from forensics._shared.errors import InputError
from forensics.io.dataset import split_epochs


def test_full_scale():
    assert full_scale(np.uint8) == 255 and full_scale(np.uint16) == 65535 and full_scale(np.float32) == 1.0
    assert bits_full_scale(12) == 4095
    assert infer_full_scale(np.uint16, 4000) == 4095 and infer_full_scale(np.uint16, 5000) == 16383
    assert infer_full_scale(np.uint8, 3) == 255
    with pytest.raises(InputError):
        full_scale(np.complex64)


def test_grey_conversions_differ_only_for_colour():
    rgb = np.zeros((2, 3, 3), np.uint16)
    rgb[..., 1] = 300  # a defect on the green channel only
    assert np.allclose(grey_luma(rgb), 0.587 * 300)  # what the eye (and JPEG) sees
    assert np.allclose(grey_mean(rgb), 100.0)  # the offset spread evenly: 300 DN over 3 channels
    grey = np.arange(6, dtype=np.uint16).reshape(2, 3)
    assert np.array_equal(grey_luma(grey), grey) and np.array_equal(grey_mean(grey), grey)
    assert grey_mean(rgb, np.float64).dtype == np.float64 and grey_luma(rgb).dtype == np.float32
    with pytest.raises(InputError):
        grey_mean(np.zeros((2, 2, 2)))


def test_split_epochs():
    epoch, times = split_epochs(np.array([2.0, 0.0, 0.1, 2.2, 5.0]), 0.25)
    assert epoch.tolist() == [1, 0, 0, 1, 2]
    assert times.tolist() == pytest.approx([0.05, 2.1, 5.0])
    assert split_epochs(np.array([]), 1.0)[0].size == 0
