"""A fitted model's figures for a dark series, in the units an astronomer measures in (ADU = DN, ADU/s, e⁻/ADU).

Where a model with a dark current was fitted to dark frames at two or more temperatures (a cooled CCD's bias
and dark series), :func:`dark_figures` states what the fitted parameters mean there:

* the **mean dark rate** of a normal pixel at each set point's effective temperature (the exposure-weighted mean
  of the measured temperatures of its dark frames) and at the whole degree nearest to it (the set point),
  r̄·2^((T − T_ref)/T_d), with a 95 % interval from the parameters' covariance (delta method on ln rate);
* the **median dark rate** of the analysed pixels there (every interior pixel's fitted rate — the mean, its own
  non-uniformity value, a hot pixel's own extra rate — carried with the fitted law), the figure the field's
  per-pixel regressions give, with a distribution-free 95 % interval (order statistics: the pixels analysed as a
  sample of the sensor's);
* the **doubling temperature** T_d, the **read noise** and the **conversion gain** 1/g in e⁻/ADU, each with its
  95 % interval;
* the **bias** of each set point: the model's mean prediction for its bias frames' normal pixels beside the
  frames' own mean (the model has one bias for all temperatures: a difference between them is named).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics.check.classes import NORMAL, dark_groups
from forensics.check.result import ParamEstimate
from forensics.check.singles import temperature_clusters
from forensics.sensor.catalogue import PARTIAL
from forensics.stats.tails import median_order_bounds

if TYPE_CHECKING:
    from forensics.check.evidence import Evidence
    from forensics.check.fit import FittedModel

Z95 = 1.959963984540054


def _param(params: list[ParamEstimate], label: str) -> ParamEstimate | None:
    return next((p for p in params if p.label == label and p.identifiable and p.converged and p.se is not None), None)


def _interval(value: float, se: float) -> list[float]:
    return [value - Z95 * se, value + Z95 * se]


def carried_rate(rate: ParamEstimate, t_double: ParamEstimate, t_ref: float, temperature: float) -> dict[str, Any]:
    """r̄·2^((T − T_ref)/T_d) with its 95 % interval (delta method on ln rate, the covariance of r̄ and T_d
    included)."""
    r, td = rate.value, t_double.value
    value = r * 2.0 ** ((temperature - t_ref) / td)
    c = -(temperature - t_ref) * math.log(2.0) / td**2  # ∂ ln rate / ∂ T_d
    cov = rate.cov.get(t_double.label, 0.0)
    if r <= 0:  # at the bound: only an upper limit is meaningful, from the rate's own standard error
        return {"temperature_c": temperature, "value": value,
                "interval": [0.0, (r + Z95 * rate.se) * 2.0 ** ((temperature - t_ref) / td)]}
    var = (rate.se / r) ** 2 + c * c * t_double.se**2 + 2.0 * c * cov / r
    sd = math.sqrt(max(var, 0.0))
    return {"temperature_c": temperature, "value": value,
            "interval": [value * math.exp(-Z95 * sd), value * math.exp(Z95 * sd)]}


def median_interval(values: np.ndarray) -> tuple[float, list[float]]:
    """The median of ``values`` and its distribution-free 95 % interval (order statistics, binomial ½)."""
    x = np.sort(values)
    n = x.size
    lo, hi = median_order_bounds(n, 0.025)
    return float(np.median(x)), [float(x[max(lo - 1, 0)]), float(x[min(hi, n - 1)])]


def pixel_rates(ev: Evidence, fitted: FittedModel, key: str, rate: float) -> np.ndarray:
    """Every pixel's fitted dark rate at T_ref (DN/s, ``(H, W)``): the mean, its non-uniformity value and a hot
    (partially stuck) pixel's own extra rate."""
    device = fitted.device
    out = np.full(ev.shape, rate, float)
    per_px = device.state.get(key)
    if per_px is not None:
        out += np.asarray(per_px, float).reshape(ev.shape)
    cat = device.catalogue
    extra = cat.extra.get(f"{key}.rate")
    if extra is not None and len(cat):
        hot = cat.kind == PARTIAL
        np.add.at(out, (cat.y[hot], cat.x[hot]), np.asarray(extra, float)[hot])
    return out


def dark_figures(ev: Evidence, fitted: FittedModel) -> dict[str, Any] | None:
    """The dark series' figures (see the module's notes), or None without a fitted dark current or without
    dark frames of an exposure at two or more temperatures."""
    dc = next((e for e in fitted.effects if e.name == "dark_current"), None)
    if dc is None:
        return None
    rate, t_double = _param(fitted.params, f"{dc.key}.rate"), _param(fitted.params, f"{dc.key}.t_double")
    meas = ev.meas
    dark = [g for g in meas.groups if dark_groups([g])[0] and g.temperature_c is not None]
    clusters = [[dark[i] for i in c] for c in temperature_clusters(dark)]
    clusters = [c for c in clusters if any((g.exposure_s or 0) > 0 for g in c)]
    if rate is None or t_double is None or len(clusters) < 2:
        return None
    per_pixel = pixel_rates(ev, fitted, dc.key, rate.value)[meas.interior]
    sets = []
    for c in clusters:
        exposed = [g for g in c if (g.exposure_s or 0) > 0]
        t_eff = float(np.average([g.temperature_c for g in exposed], weights=[g.exposure_s * g.n for g in exposed]))
        factor = 2.0 ** ((t_eff - dc.t_ref) / t_double.value)
        median, interval = median_interval(per_pixel * factor)
        entry = {"effective_temperature_c": t_eff, "frames": int(sum(g.n for g in c)),
                 "mean_rate": carried_rate(rate, t_double, dc.t_ref, t_eff),
                 "mean_rate_at_set_point": carried_rate(rate, t_double, dc.t_ref, float(round(t_eff))),
                 "median_rate": {"temperature_c": t_eff, "value": median, "interval": interval}}
        entry.update(_bias(ev, fitted, [g for g in c if not g.exposure_s]))
        sets.append(entry)
    out: dict[str, Any] = {"t_ref_c": dc.t_ref, "set_points": sets,
                           "t_double_c": {"value": t_double.value, "interval": _interval(t_double.value, t_double.se)}}
    read = _param(fitted.params, "read_noise.sigma")
    if read is not None:
        out["read_noise_adu"] = {"value": read.value, "interval": _interval(read.value, read.se)}
    shot = _param(fitted.params, "shot_noise.g")
    if shot is not None and shot.value > 0:
        lo, hi = shot.value + Z95 * shot.se, shot.value - Z95 * shot.se
        # an interval reaching g = 0 has no upper end in e⁻/ADU: None (JSON null)
        out["gain_e_per_adu"] = {"value": 1.0 / shot.value, "interval": [1.0 / lo, 1.0 / hi if hi > 0 else None]}
    return out


def _bias(ev: Evidence, fitted: FittedModel, biases: list[Any]) -> dict[str, Any]:
    """The bias frames' level at one set point: the model's mean prediction for their interior normal pixels and
    the frames' own mean, with its standard error from the pixels' noise."""
    rows = [r for r, g in enumerate(ev.rgroups) if any(g is b for b in biases)]
    if not rows:
        return {}
    px = fitted.pixels
    m = np.stack([(px.weight[r] > 0) & (px.classes[r] == NORMAL) & ev.meas.interior for r in rows])
    model = float(np.mean(fitted.mu_a[rows][m]))
    data = float(np.mean(ev.meas.mean_a[rows][m]))
    se = float(np.sqrt(np.sum(1.0 / px.weight[rows][m]))) / int(m.sum())
    return {"bias": {"model": model, "frames": data, "frames_interval": _interval(data, se)}}


def format_dark_figures(fig: dict[str, Any]) -> list[str]:
    """The figures as lines of text (for the command's summary)."""
    def iv(x: dict[str, Any], fmt: str = ".4g") -> str:
        lo, hi = x["interval"]
        return f"{x['value']:{fmt}} [{lo:{fmt}}, {'∞' if hi is None else format(hi, fmt)}]"

    lines = [f"Dark series (ADU = DN; 95 % intervals; rates carried with the fitted law from T_ref = "
             f"{fig['t_ref_c']:g} °C)"]
    for s in fig["set_points"]:
        at = s["mean_rate_at_set_point"]
        lines.append(f"  at {s['effective_temperature_c']:.2f} °C ({s['frames']} frames): mean dark rate "
                     f"{iv(s['mean_rate'])} ADU/s, median {iv(s['median_rate'])} ADU/s; at {at['temperature_c']:g} °C "
                     f"mean {iv(at)} ADU/s")
        if "bias" in s:
            b = s["bias"]
            lines.append(f"    bias frames: {iv({'value': b['frames'], 'interval': b['frames_interval']}, '.2f')} ADU, "
                         f"model {b['model']:.2f} ADU")
    lines.append(f"  doubling temperature T_d {iv(fig['t_double_c'])} °C")
    if "read_noise_adu" in fig:
        lines.append(f"  read noise {iv(fig['read_noise_adu'])} ADU")
    if "gain_e_per_adu" in fig:
        lines.append(f"  conversion gain {iv(fig['gain_e_per_adu'])} e⁻/ADU")
    return lines
