"""Count statistics: the grouped Laplace trend test and the Poisson deviance."""
import numpy as np
import pytest

from forensics.stats.counts import laplace_trend_z, poisson_deviance


def test_laplace_z_is_standard_normal_under_a_constant_rate():
    """2,000 simulated histories with uniform arrival times grouped into unequal intervals: the mean of z has
    a standard error of 1/√2000 ≈ 0.022 and its sd one of ≈ 0.016, so ±0.08 and ±0.06 are > 3.5σ bounds."""
    rng = np.random.default_rng(5)
    times = np.array([0.0, 1.0, 3.0, 4.0, 8.0, 10.0])
    z = []
    for _ in range(2000):
        arrivals = rng.uniform(0, 10, rng.poisson(40))
        z.append(laplace_trend_z(np.histogram(arrivals, times)[0], times))
    z = np.array(z)
    assert abs(z.mean()) < 0.08 and abs(z.std() - 1) < 0.06


def test_laplace_z_sees_acceleration_and_handles_empty_histories():
    times = np.arange(0.0, 11.0, 2.0)
    assert laplace_trend_z([2, 5, 10, 20, 40], times) > 5
    assert laplace_trend_z([40, 20, 10, 5, 2], times) < -5
    assert laplace_trend_z([0, 0, 0, 0, 0], times) is None
    assert laplace_trend_z([3], [1.0, 1.0]) is None


def test_poisson_deviance():
    assert poisson_deviance([3, 5], [3, 5]) == pytest.approx(0.0)
    # 2·[o·log(o/e) − (o − e)], with 0·log 0 = 0
    assert poisson_deviance([0, 4], [1, 2]) == pytest.approx(2 * (1 + 4 * np.log(2) - 2))
