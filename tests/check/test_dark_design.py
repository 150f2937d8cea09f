"""What a dark series' design lets the model check determine (issue 28's variants of other years' series,
``benchmarks/RESULTS_ccd_variants.md``): a single set point gives no doubling temperature, and a series in which
no condition repeats is refused with the true reason."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from forensics._shared.errors import InputError
from forensics.check import check
from forensics.check.classes import NORMAL
from forensics.check.measurements import load_measurements
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from forensics.io.fits import SETPOINT_TOLERANCE_C
from forensics.sensor.effects import ONE_TEMPERATURE_SPAN_C, DarkCurrent

#: The check's model (one T_d, no read-out charge, no offset jitter, no column pattern), at one set point; the
#: thermistor wanders by its default 0.05 °C, so the conditions' mean readings differ by hundredths of a degree —
#: from which a T_d of 5.13 ± 0.63 °C was fitted before (the variant "one set point").  The bulk rate is 0.34
#: ADU/s at the set point (the 2017 series' at −5 °C): at 0.085 ADU/s the check's mean rate comes out 15 % above
#: the truth whether T_d is held or fitted, with two set points too (RESULTS_ccd_variants.md: a separate finding).
ONE_SETPOINT = DarkSeriesDesign(shape=(40, 48), offset_jitter=0.0, readout_s=0.0, column_pattern=0.0,
                                rate_bulk=0.68, doubling_hot=5.0, hot_fraction=0.01, hot_min=3.0, hot_max=10.0,
                                n_repeat_dark=6, setpoints=(-15.0,))


def _groups(*temperatures: float, exposure: float = 60.0):
    return SimpleNamespace(meas=SimpleNamespace(groups=[
        SimpleNamespace(temperature_c=t, exposure_s=exposure, n=1, subject="dark") for t in temperatures]))


def test_the_one_temperature_band_is_one_set_points():
    """A set point's frames are grouped within ±SETPOINT_TOLERANCE_C of it, so their conditions span at most
    twice that: the band in which T_d is held."""
    assert ONE_TEMPERATURE_SPAN_C == 2 * SETPOINT_TOLERANCE_C


@pytest.mark.parametrize("temperatures, held", [((-15.02, -14.97, -15.0), True), ((-15.9, -14.1), True),
                                                 ((-10.2, -5.0), False), ((-16.0, -13.9), False)])
def test_dark_current_holds_t_double_at_one_temperature(temperatures, held):
    fitted = DarkCurrent().fit(_groups(*temperatures))
    assert fitted.t_double_held is held
    assert ("t_double" in fitted.free_params()) is not held
    assert ("t_double" in fitted.held()) is held
    assert "rate" in fitted.free_params()


@pytest.fixture(scope="module")
def one_setpoint(tmp_path_factory):
    folder = tmp_path_factory.mktemp("one_setpoint")
    truth = make_dark_series(folder, 0, ONE_SETPOINT)
    return truth, check(folder, add=["shot_noise", "dark_current"], baseline=False)


def test_one_set_point_gives_no_doubling_temperature(one_setpoint):
    """T_d is stated as not identifiable, at the value it was held at (the default 7 °C), with the reason; the
    rate is still fitted, at T_ref moved to the set point, and covers the truth: the mean rate of the pixels the
    model classes normal, within 3 standard errors (the frames lie within 0.1 °C of T_ref, where the held T_d
    changes the rate by less than 0.1 %)."""
    truth, result = one_setpoint
    params = {p.label: p for p in result.params}
    td = params["dark_current.t_double"]
    assert not td.identifiable and td.se is None and td.value == DarkCurrent().t_double
    assert "one temperature" in td.note and "held at 7" in td.note
    rate = params["dark_current.rate"]
    assert rate.identifiable and rate.converged and rate.se is not None
    normal = result.heldout.classes[0] == NORMAL
    interior = np.zeros(ONE_SETPOINT.shape, bool)
    interior[3:-3, 3:-3] = True
    expected = float(truth.rate_at(-15.0)[normal & interior].mean())
    assert abs(rate.value - expected) < 3 * rate.se
    assert result.data["dark_series"] is None  # no law to state at one temperature
    assert result.to_dict()["params"]  # the held parameter serialises (se None → null)


def test_a_dark_series_without_a_repeat_is_refused_with_its_reason(tmp_path):
    """Every frame measured 1.5 °C and more off its set point (a sensor that never settled), so no condition
    repeats: refused naming the cause and a frame, not pooled as photographs (which stopped a check with a dark
    current on "'dark_current' needs the field 'exposure_s' for every frame")."""
    from astropy.io import fits

    design = DarkSeriesDesign(shape=(24, 32), exposures=(10.0, 30.0), n_bias=3)
    make_dark_series(tmp_path, 0, design)
    files = sorted(tmp_path.iterdir())
    for i, f in enumerate(files):
        with fits.open(f, mode="update") as h:
            h[0].header["CCD-TEMP"] = h[0].header["SET-TEMP"] + 1.5 + 0.1 * i
    with pytest.raises(InputError) as err:
        load_measurements(tmp_path)
    msg = str(err.value)
    assert f"{len(files)} of {len(files)} frames were measured more than 1 °C from their set point" in msg
    assert files[0].name in msg and "\n" not in msg
    assert "exposure_s" not in msg
