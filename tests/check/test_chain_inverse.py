"""The typical chain's inverse (forensics.check.prediction.ChainInverse): the closed form of an affine chain gives
what the tabulated inverse (np.interp over the chain) gives, ends clamped alike; a curved chain keeps the table."""
import numpy as np

from forensics.check.prediction import ChainInverse


def test_affine_chain_in_closed_form():
    fs = 4095.0
    grid = np.linspace(-0.25 * fs, 2.0 * fs, 128 * 128)
    chain = 0.37 * grid + 64.0  # a gain and a black level
    inverse = ChainInverse(chain, grid, fs)
    assert inverse.affine is not None
    out = np.random.default_rng(1).uniform(-2000.0, 6000.0, 5000)  # beyond both ends of the table too
    # the table's own linear interpolation is exact for a line up to rounding (~1e-12 of the full scale)
    np.testing.assert_allclose(inverse.invert(out), np.interp(out, chain, grid), rtol=0, atol=1e-9 * fs)


def test_curved_chain_keeps_the_table():
    fs = 4095.0
    grid = np.linspace(-0.25 * fs, 2.0 * fs, 4096)
    chain = grid + 1e-4 * np.clip(grid, 0, None) ** 1.5  # a non-linearity
    inverse = ChainInverse(chain, grid, fs)
    assert inverse.affine is None
    out = np.linspace(0.0, fs, 777)
    np.testing.assert_array_equal(inverse.invert(out), np.interp(out, chain, grid))
