"""The reference paper's virtual sensors A–H (tables 3 and 4).

Rates are in defects per megapixel per year; amplitudes are given in 8-bit DN
and scaled to the output bit depth by ``(2**bits − 1) / 255``.
"""
from __future__ import annotations

from forensics._shared.arrays import bits_full_scale
from forensics.sensor.effects import Growth, Offset, Stuck
from forensics._shared.errors import UsageError
from forensics.sensor.model import SensorModel

#: Table 3: growth rates (defects / MP / year) of partially stuck pixels.
LAMBDA_H100 = 0.6659
LAMBDA_APS = 0.7432
LAMBDA_CCD = 0.5694
#: Table 3: amplitudes (8-bit DN).
A_PS_H100 = 3.0
A_S = 255.0

#: Table 4: sensor → (λ_ps, λ_s, a_ps).  Sensor E has no partially stuck pixels ('—' in the paper).
PRESETS: dict[str, tuple[float, float, float]] = {
    "A": (LAMBDA_H100, 0.0, A_PS_H100),
    "B": (LAMBDA_H100, LAMBDA_APS, A_PS_H100),
    "C": (LAMBDA_APS, 0.0, A_PS_H100),
    "D": (LAMBDA_CCD, 0.0, A_PS_H100),
    "E": (0.0, LAMBDA_APS, 0.0),
    "F": (4 * LAMBDA_H100, 0.0, 2 * A_PS_H100),
    "G": (4 * LAMBDA_H100, 0.0, 100.0),
    "H": (8 * LAMBDA_H100, 5 * LAMBDA_APS, 100.0),
}


def preset(name: str, shape: tuple[int, int], bit_depth: int = 8, t0: float = 0.0, counting: str = "poisson",
           rate_scale: float = 1.0) -> SensorModel:
    """The paper's virtual sensor ``name`` (A–H) as a :class:`SensorModel`.

    Parameters
    ----------
    name
        One of ``A`` … ``H`` (case-insensitive).
    shape
        ``(height, width)`` of the images.
    bit_depth
        Output bits; the paper's 8-bit amplitudes are scaled to it.
    t0
        Decimal year at which ageing starts.
    counting
        ``'poisson'`` (default) or the paper's ``'deterministic'`` counts.
    rate_scale
        Multiplies both rates (to age faster in demonstrations; 1 reproduces the paper).
    """
    key = name.upper()
    if key not in PRESETS:
        raise UsageError(f"unknown sensor preset '{name}'; choose one of {', '.join(PRESETS)}")
    lam_ps, lam_s, a_ps = PRESETS[key]
    scale = bits_full_scale(bit_depth) / bits_full_scale(8)
    growth = Growth(rate_partial=lam_ps * rate_scale, rate_stuck=lam_s * rate_scale, amp_partial=a_ps * scale,
                    amp_stuck=A_S * scale, counting=counting)
    return SensorModel(shape=shape, bit_depth=bit_depth, effects=[growth, Offset(), Stuck()], t0=t0)
