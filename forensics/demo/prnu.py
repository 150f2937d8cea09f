"""Demo section: the same-device test on simulated cameras whose truth is known.

Three comparisons, each with the paper's protocol (:func:`forensics.prnu.samedevice.same_device`):

1. two devices of one model (independent PRNU) — told apart, EER ≈ 0;
2. one device, young and after 50 years as the paper's sensor H (amplitude-heavy
   defects) — the median-residual fingerprints of the two epochs agree less than
   those of one epoch (table 2), because the old fingerprints carry the new
   defects' spikes;
3. one device, young and after 50 years as the paper's sensor A (the real iris
   sensor's growth rate and 3 DN amplitudes) — no detectable change: the
   defects are far too few and too faint to move a fingerprint.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress
from forensics._shared.rng import RngLike, as_generator, spawn
from forensics.prnu.samedevice import ImageSet, SameDeviceResult, same_device
from forensics.report.prnu import prnu_demo_report
from forensics.sensor.model import SensorModel, make_effect
from forensics.sensor.presets import preset
from forensics.sensor.scenes import pink_texture, scene

from . import DemoSection

TITLE = "Same device? PRNU fingerprints, EER with a bootstrap interval, fingerprint ageing"
SIZE = (256, 256)
SCENE_KINDS = ("smooth", "texture", "photo")


def sensor_model(name: str = "A", shape: tuple[int, int] = SIZE, *, sigma_k: float = 0.01, read_sigma: float = 1.0,
                 shot_g: float = 0.05, rate_scale: float = 1.0) -> SensorModel:
    """A virtual sensor of the paper's table 4 with PRNU and temporal noise (8-bit output).

    Parameters
    ----------
    name : str
        Preset 'A'..'H' (defect growth, offsets, stuck pixels).
    shape : (int, int)
    sigma_k : float
        PRNU standard deviation (relative gain), the ``prnu`` effect.
    read_sigma : float
        Read noise, DN.
    shot_g : float
        Shot-noise gain (variance per DN of signal): 0.05 gives σ ≈ 2.5 DN at mid-grey,
        typical of an 8-bit camera at base ISO.
    rate_scale : float
        Multiplies the preset's defect rates.
    """
    return preset(name, shape, bit_depth=8, rate_scale=rate_scale).with_effects(
        make_effect("prnu", sigma_k=sigma_k), make_effect("read_noise", sigma=read_sigma),
        make_effect("shot_noise", g=shot_g))


def _scene(shape: tuple[int, int], rng: np.random.Generator, kind: str) -> np.ndarray:
    if kind == "smooth":  # gentle shading, like skin or a wall: a 1/f³ pink field
        return np.clip(0.45 + 0.12 * pink_texture(shape, rng, exponent=3.0), 0.02, 0.98)
    return scene(shape, rng, 1, kind)


def simulated_set(device, n: int, time: float, rng: RngLike, name: str, *, kind: str = "smooth") -> ImageSet:
    """``n`` images of a realised device at ``time`` (decimal years), rendered on demand.

    Image ``i`` is the same whenever it is loaded (its scene and noise come from the
    ``i``-th child of ``rng``, :func:`forensics._shared.rng.spawn`: of ``SeedSequence(seed)``
    for an integer seed), so the set behaves like a folder of files without being held
    in memory.

    Parameters
    ----------
    device : forensics.sensor.model.Device
    n : int
    time : float
        Capture time; defects with an earlier onset are present.
    rng : numpy.random.Generator or int
        Spawns one child generator per image.
    name : str
    kind : {'smooth', 'texture', 'photo'}
        Scenes: 1/f³ pink shading, :func:`forensics.sensor.scenes.scene` textures (1/f^1.8,
        harder: the residual keeps more scene), or bundled photographs (slow).
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"kind={kind!r}: choose one of {', '.join(SCENE_KINDS)}")
    children = spawn(rng, n)
    shape = device.model.shape

    def render(i: int) -> np.ndarray:
        child = np.random.default_rng(children[i].bit_generator.seed_seq)  # a fresh stream at every load
        light = _scene(shape, child, kind) * np.float32(device.model.full_scale)
        return device.expose(light, device.context(time), child)

    return ImageSet.from_function(n, render, name)


def _line(label: str, r: SameDeviceResult) -> str:
    e, t = r.eer, r.ageing
    text = f"{label}: EER {100 * e.eer:.1f} % [{100 * e.ci[0]:.1f}, {100 * e.ci[1]:.1f}] → {e.decision}"
    if t is not None:
        text += f"; fingerprint consistency {t.consistency.mean:.2f}"
        if t.consistency.ci is not None:
            text += f" [{t.consistency.ci[0]:.2f}, {t.consistency.ci[1]:.2f}]"
    return text


def run(workdir: Path, rng: RngLike, progress: Progress, executor: Executor | None = None) -> DemoSection:
    """Run the three comparisons (about 15 s on 2 cores) and build the report section.

    ``rng`` (Generator or int seed) realises the devices, seeds the image sets and draws every selection
    and bootstrap.
    """
    rng = as_generator(rng)
    counts = dict(fingerprint_images=30, score_images=80, region="full", ageing_fingerprints=8, ageing_images=12,
                  n_boot=1000, progress=progress)
    n = 30 + 80
    years = 50.0
    seeds = rng.integers(0, 2**31, size=8)

    model = sensor_model("A")
    dev1, dev2 = model.realize(rng, [0.0]), model.realize(rng, [0.0])
    two = same_device(simulated_set(dev1, n, 0.0, int(seeds[0]), "device 1"),
                      simulated_set(dev2, n, 0.0, int(seeds[1]), "device 2"), rng, **counts)

    old_h = sensor_model("H").realize(rng, [0.0, years])
    aged_h = same_device(simulated_set(old_h, n, 0.0, int(seeds[2]), "H, new"),
                         simulated_set(old_h, n, years, int(seeds[3]), f"H, {years:g} years"), rng, **counts)

    old_a = sensor_model("A").realize(rng, [0.0, years])
    aged_a = same_device(simulated_set(old_a, n, 0.0, int(seeds[4]), "A, new"),
                         simulated_set(old_a, n, years, int(seeds[5]), f"A, {years:g} years"), rng, **counts)

    n_h = len(old_h.catalogue.effective(years))
    n_a = len(old_a.catalogue.effective(years))
    rep = prnu_demo_report(TITLE, two, aged_h, aged_a, size=SIZE, years=years, defects=(n_h, n_a),
                           fingerprint_images=counts["fingerprint_images"], score_images=counts["score_images"])
    summary = [
        "same device: " + _line("two devices", two),
        "same device: " + _line(f"sensor H new vs {years:g} y", aged_h),
        "same device: " + _line(f"sensor A new vs {years:g} y", aged_a),
    ]
    data = {"two_devices": _brief(two), "sensor_h_ageing": _brief(aged_h), "sensor_a_ageing": _brief(aged_a),
            "defects_after": {"H": n_h, "A": n_a}, "years": years}
    return DemoSection(TITLE, rep, summary, data)


def _brief(r: SameDeviceResult) -> dict:
    t = r.ageing
    out = {"eer": r.eer.eer, "eer_ci": list(r.eer.ci), "decision": r.eer.decision}
    if t is not None:
        out.update({"intra_a": t.intra_a.mean, "intra_b": t.intra_b.mean, "inter": t.inter.mean,
                    "consistency": t.consistency.mean,
                    "consistency_ci": list(t.consistency.ci) if t.consistency.ci else None})
    return out
