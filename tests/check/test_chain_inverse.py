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


def test_a_response_that_turns_over_inverts_on_its_rising_branch():
    # y = i − β·i²/fs with β = 0.43 peaks at i = fs/(2β) ≈ 1.16 fs, inside the table's 2 fs: every output below the
    # peak has two lights; the sensor's is the smaller root, i = fs·(1 − √(1 − 4βy/fs))/(2β)
    fs, beta = 65535.0, 0.43
    grid = np.linspace(-0.25 * fs, 2.0 * fs, 256 * 256)
    chain = grid - beta * grid ** 2 / fs
    inverse = ChainInverse(chain, grid, fs)
    peak = fs / (4 * beta)
    out = np.linspace(-0.2 * fs, 0.999 * peak, 2001)
    root = fs * (1 - np.sqrt(1 - 4 * beta * out / fs)) / (2 * beta)
    # linear interpolation of a parabola on a grid of step h errs by ≤ h²·|y''|/8 in output, i.e. in light
    # ≤ that over the slope; the slope falls to 1 − 2β·i/fs ≥ 0.04 at 99.9 % of the peak's output
    h = grid[1] - grid[0]
    slope = 1 - 2 * beta * root / fs
    np.testing.assert_array_less(np.abs(inverse.invert(out) - root), (h * h * 2 * beta / fs / 8) / slope + 1e-6 * fs)
    # above the peak no light gives the output: the brightest light of the branch, the peak's
    np.testing.assert_allclose(inverse.invert(np.array([1.01 * peak, 2 * fs])), fs / (2 * beta), rtol=1e-4)
