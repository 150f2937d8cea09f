"""The reference paper's ageing simulation (AGEDIMAGESEQUENCE) and scene sets.

:func:`age_dataset` takes a source dataset (images captured at T0), realises
one simulated device from a :class:`~forensics.sensor.model.SensorModel`, and writes
one dataset per sample time: every source image with the defects the device
has at that time.  The device's defect history is shared by all its images
(one device, one history), and earlier defects persist (*once defective,
always defective*).
"""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from forensics import __version__
from forensics._shared.atomic import atomic_directory, refuse_inputs, write_json
from forensics._shared.parallel import Executor, resolve, resumable_directory
from forensics.io.dataset import Dataset, write_manifest
from forensics._shared.errors import InputError, UsageError
from forensics._shared.limits import require_ages, require_memory
from forensics.io.images import write_image
from forensics.sensor.model import Device, SensorModel
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator, keyed_generator, seed_record
from forensics.sensor.scenes import scene_image


def parse_years(spec: str) -> list[float]:
    """Parse ``start:stop:step`` (inclusive of stop) or a comma list into sample ages in years.

    The ages are finite, ≥ 0, distinct (also in their folder names, :func:`step_name`: one decimal) and at
    most :func:`~forensics._shared.limits.age_limit` many — counted before the list is built, so that
    ``0:1e9:1`` is refused at once.

    Raises
    ------
    UsageError
        Naming ``--years`` and what to give instead.

    >>> parse_years("0:96:8")[:3], len(parse_years("0:96:8"))
    ([0.0, 8.0, 16.0], 13)
    """
    spec = spec.strip()
    what = f"--years '{spec}'"
    try:
        if ":" in spec:
            parts = [float(p) for p in spec.split(":")]
            if len(parts) != 3 or not all(map(math.isfinite, parts)) or parts[2] <= 0 or parts[1] < parts[0]:
                raise ValueError
            start, stop, step = parts
            count = (stop - start) / step + 1  # may be inf for a denormal step: checked before int()
            require_ages(count, what)
            n = int(np.floor((stop - start) / step + 1e-9)) + 1
            years = [start + i * step for i in range(n)]
        else:
            years = [float(p) for p in spec.split(",")]
            if not all(map(math.isfinite, years)):
                raise ValueError
    except ValueError:
        raise UsageError(f"{what}: give START:STOP:STEP with finite numbers and STEP > 0 (e.g. 0:96:8) or a "
                         "list of ages (0,4,8)") from None
    require_ages(len(years), what)
    if any(y < 0 for y in years):
        raise UsageError(f"{what}: ages must be ≥ 0")
    names: dict[str, float] = {}
    for age in sorted(years):
        name = step_name(age)
        if name in names:
            twice = "is given twice" if names[name] == age else f"and {names[name]:g} share the folder {name}"
            raise UsageError(f"{what}: the age {age:g} {twice}; give each age once, at least 0.1 year apart")
        names[name] = age
    return sorted(years)


def step_name(age: float) -> str:
    """Folder name of the dataset at ``age`` years, e.g. ``year_008`` or ``year_002.5``."""
    return f"year_{int(age):03d}" if float(age).is_integer() else f"year_{age:05.1f}"


@dataclass
class AgeingResult:
    """What :func:`age_dataset` wrote."""

    out: Path
    steps: list[Path]
    ages: list[float]
    n_images: int
    catalogue_rows: int
    counts: dict[str, list[int]] = field(default_factory=dict)
    sensor: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"out": str(self.out), "steps": [str(s) for s in self.steps], "ages": self.ages,
                "n_images": self.n_images, "defects": self.catalogue_rows, "counts": self.counts,
                "sensor": self.sensor}


#: Peak memory of :meth:`SensorModel.realize` per raw defect arrival: RSS measured for 17 and 69 million
#: arrivals on 1 MP (sensor H, rate × 20,000 and × 80,000, 96 years): about 240 bytes each.
ARRIVAL_BYTES = 240
#: Peak memory of one scene per pixel: RSS of :func:`~forensics.sensor.scenes.scene_image` measured at 2048² and
#: 4096²: grey textures 40 bytes, colour textures 56, photographs 86–88 (a bundled photograph is resized in
#: float64 up to 1.6× the frame).
SCENE_BYTES_PER_PIXEL = 96


def expected_arrivals(model: SensorModel, span: float) -> float:
    """The mean number of defects the arrival effects of ``model`` draw over ``span`` years (before sites
    repeat): constant rates (``rate_partial``, ``rate_stuck``), clusters (``rate`` × ``mean_size``) and
    accelerating growth (``theta`` · span^``beta``), per megapixel."""
    from forensics.sensor.model import Stage

    per_mp = 0.0
    for effect in model.effects:
        if effect.stage != Stage.ARRIVAL:
            continue
        per_mp += (getattr(effect, "rate_partial", 0.0) + getattr(effect, "rate_stuck", 0.0)) * span
        per_mp += getattr(effect, "rate", 0.0) * getattr(effect, "mean_size", 1.0) * span
        if hasattr(effect, "theta"):
            per_mp += effect.theta * span ** getattr(effect, "beta", 1.0)
    return per_mp * model.megapixels


def check_ageing_request(model: SensorModel, ages: list[float], what: str = "the ageing") -> None:
    """Refuse (:class:`UsageError`, before anything is drawn) a defect history that would not fit in memory."""
    n = expected_arrivals(model, max(ages, default=0.0))
    require_memory(ARRIVAL_BYTES * n, f"{what} (about {n:,.0f} defect arrivals over {max(ages, default=0.0):g} "
                                      "years)")


def source_bit_depth(dtype: np.dtype) -> int:
    """8 for uint8 sources, 16 for uint16; other dtypes are refused."""
    if dtype == np.uint8:
        return 8
    if dtype == np.uint16:
        return 16
    raise InputError(f"source images of dtype {dtype} cannot be aged; use 8- or 16-bit images")


def age_dataset(
    source: Dataset,
    out: str | os.PathLike,
    model: SensorModel,
    ages: list[float],
    rng: RngLike,
    start_year: float | None = None,
    sensor_name: str | None = None,
    force: bool = False,
    progress: Progress = no_progress,
    image_format: str | None = None,
    executor: Executor | None = None,
) -> AgeingResult:
    """Age every image of ``source`` over ``ages`` (years after T0) and write one dataset per age.

    Parameters
    ----------
    source
        Images captured at T0 (all one size).  Each is read once, by the worker that ages it.
    out
        Output folder (refused if it exists unless ``force``).  It is built in ``.OUT.partial`` beside it and
        renamed into place when complete; an interrupted run leaves that folder, and the same call made
        again resumes from the images already aged (other settings are refused).
    model
        The sensor model; its ``shape`` must match the images and its ``t0`` is T0.
    ages
        Sample ages in years (e.g. ``parse_years('0:96:8')``).
    rng
        Generator or integer seed of the device's random history (drawn from ``rng`` itself) and of the
        per-frame noise (image ``i`` at step ``j`` from the sub-stream ``(i, j)`` of
        :func:`~forensics._shared.rng.keyed_generator`: ``default_rng([seed, i, j])`` for an integer seed),
        so the images are identical whichever backend and however many workers age them.
    start_year
        Decimal year of T0 written into the manifests (default ``model.t0``).
    image_format
        Extension of the outputs (default: the source's if PNG/TIFF, else ``.png``).
    executor
        Where the images are aged (:mod:`forensics._shared.parallel`; default in this process).  One item
        per source image; the device is shipped once per worker.

    Writes ``OUT/year_NNN/`` (images + ``manifest.csv``), ``OUT/defects.csv``
    (the ground-truth catalogue: x, y, kind, amplitude, onset_year) and
    ``OUT/sensor.json`` (size, parameters, and ``seed``: :func:`forensics._shared.rng.seed_record` of
    ``rng``, the integer itself when one was given).
    """
    out = Path(out)
    refuse_inputs(out, [source.root])
    shape = source.shape()
    first_dtype = source.frames[0].info().dtype
    if tuple(shape[:2]) != tuple(model.shape):
        raise InputError(f"{source.root}: images are {shape[1]}×{shape[0]} but the sensor is {model.shape[1]}×{model.shape[0]}")
    bits = source_bit_depth(first_dtype)
    if bits != model.bit_depth:
        raise InputError(f"{source.root}: images are {bits}-bit but the sensor model is {model.bit_depth}-bit")
    if start_year is not None:
        model = dataclasses.replace(model, t0=float(start_year))
    t0 = model.t0
    times = [t0 + a for a in ages]
    seed = seed_record(rng)
    device = model.realize(as_generator(rng), times)
    contexts = [device.context(t) for t in times]
    names = [step_name(a) for a in ages]
    files = [_output_name(frame, image_format) for frame in source.frames]
    if len(set(files)) != len(files):
        duplicate = next(f for f in files if files.count(f) > 1)
        raise InputError(f"{source.root}: two source images would both be written as '{duplicate}'; "
                         "give them different names")
    sensor = {"size": {"width": model.shape[1], "height": model.shape[0], "channels": 1 if len(shape) == 2 else shape[2]},
              "sensor": sensor_name, "seed": seed, "t0": t0, "ages": list(ages), "model": model.to_dict(),
              "source": str(source.root), "forensics_version": __version__}
    config = {**sensor, "files": [f.file for f in source.frames], "outputs": files}
    # The sources' content digests join the stamp: a source replaced after an interruption is not mixed in.
    with resumable_directory(out, config, force=force, inputs=[f.path for f in source.frames]) as (work, checkpoint):
        for name in names:
            (work / name).mkdir(exist_ok=True)
        job = _AgeingJob(device, contexts, names, rng, first_dtype.str, tuple(shape), str(work))
        items = [(index, str(frame.path), fname) for index, (frame, fname) in enumerate(zip(source.frames, files))]
        for _ in resolve(executor).map(_age_one_image, items, shared=job, progress=progress, desc="ageing",
                                       checkpoint=checkpoint):
            pass
        for step, name in enumerate(names):
            rows = [{"file": fname, "device": _device_name(sensor_name, seed), "captured": contexts[step].time,
                     "exposure_s": frame.exposure_s, "iso": frame.iso, "temperature_c": frame.temperature_c,
                     "subject": frame.subject, "source_file": frame.file, "age_years": ages[step]}
                    for frame, fname in zip(source.frames, files)]
            write_manifest(work / name / "manifest.csv", rows, force=True)
        write_catalogue(work / "defects.csv", device, force=True)
        write_json(work / "sensor.json", sensor, force=True)
    counts = {"partial": [int(c) for c in device.catalogue.counts(times, kind=0)],
              "stuck": [int(c) for c in device.catalogue.counts(times, kind=1)]}
    return AgeingResult(out, [out / n for n in names], list(ages), len(source), len(device.catalogue), counts, sensor)


def _output_name(frame: Any, image_format: str | None) -> str:
    suffix = frame.path.suffix.lower()
    ext = image_format or (suffix if suffix in (".png", ".tif", ".tiff") else ".png")
    return f"{Path(frame.file).stem}{ext}"


@dataclass
class _AgeingJob:
    """What every ageing worker needs once: the device, the sample contexts and where to write."""

    device: Device
    contexts: list
    names: list[str]
    rng: RngLike
    dtype: str
    shape: tuple[int, ...]
    work: str


def _age_one_image(job: _AgeingJob, item: tuple[int, str, str]) -> None:
    """Read source image ``index`` from its path, age it at every step, write one file per step."""
    from forensics.io.images import read_image

    index, path, fname = item
    image = read_image(path)
    if image.dtype.str != job.dtype or image.shape != job.shape:
        raise InputError(f"{path}: {image.dtype} {image.shape} differs from the first image "
                         f"({np.dtype(job.dtype)} {job.shape}); a source set must be uniform")
    for aged, name in zip(aged_exposures(job.device, image, job.contexts, job.rng, index), job.names):
        # Overwrite: a resumed run may find the file of an item that was interrupted half-way.
        write_image(Path(job.work) / name / fname, aged, force=True)


def aged_exposures(device: Device, image: np.ndarray, contexts: list, rng: RngLike, index: int,
                   first_step: int = 0) -> list[np.ndarray]:
    """Source image ``index`` as ``device`` records it under each context (one per age).

    The frame at step ``k`` draws its noise from ``keyed_generator(rng, index, first_step + k)``: the same
    image at the same step is the same whichever command ages it, in whatever order.
    """
    return [device.expose(image, ctx, keyed_generator(rng, index, first_step + k)) for k, ctx in enumerate(contexts)]


def _device_name(sensor_name: str | None, seed: Any) -> str:
    """The manifests' device name: ``sim-<sensor>-<seed>`` (the seed's entropy for a generator)."""
    tag = seed if not isinstance(seed, dict) else f"{seed['entropy']}" + "".join(f"-{k}" for k in seed["spawn_key"])
    return f"sim-{sensor_name or 'custom'}-{tag}"


def write_catalogue(path: str | os.PathLike, device: Device, force: bool = False) -> Path:
    """Write the device's ground-truth defects as CSV: x, y, kind, amplitude, onset_year, source, extras."""
    from forensics._shared.atomic import atomic_file
    import csv

    rows = device.catalogue.to_rows()
    columns = ["x", "y", "kind", "amplitude", "onset_year", "source"] + sorted(device.catalogue.extra)
    with atomic_file(path, force=force, mode="w") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return Path(path)


def read_catalogue(path: str | os.PathLike):
    """Read a ``defects.csv`` back into a :class:`~forensics.sensor.model.DefectCatalogue`."""
    import csv

    from forensics.sensor.catalogue import KIND_CODES, DefectCatalogue

    path = Path(path)
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the defect catalogue ({exc})") from exc
    try:
        base = {"x", "y", "kind", "amplitude", "onset_year", "source"}
        extras = [k for k in (rows[0] if rows else {}) if k not in base]
        return DefectCatalogue(
            np.array([int(r["x"]) for r in rows], np.int64), np.array([int(r["y"]) for r in rows], np.int64),
            np.array([KIND_CODES[r["kind"]] for r in rows], np.int8), np.array([float(r["amplitude"]) for r in rows]),
            np.array([float(r["onset_year"]) for r in rows]), np.array([r.get("source", "") for r in rows], dtype=object),
            {k: np.array([float(r[k]) for r in rows]) for k in extras})
    except (KeyError, ValueError) as exc:
        raise InputError(f"{path}: malformed defect catalogue ({exc}); expected columns x, y, kind, amplitude, onset_year") from exc


def make_scenes(out: str | os.PathLike, n: int, shape: tuple[int, int], rng: RngLike, channels: int = 1,
                bit_depth: int = 8, kind: str = "mixed", start_year: float | None = None, device: str | None = None,
                force: bool = False, progress: Progress = no_progress, ext: str = ".png") -> Dataset:
    """Write ``n`` scene images (a dataset with a manifest) for users who have no images of their own.

    ``rng`` (Generator or integer seed) draws every scene, one after the other.
    """
    from forensics.io.dataset import open_dataset

    out = Path(out)
    require_memory(SCENE_BYTES_PER_PIXEL * shape[0] * shape[1], f"a {shape[1]}×{shape[0]} scene")
    rng = as_generator(rng)
    rows = []
    with atomic_directory(out, force=force) as tmp:
        for i in progress(range(n), total=n, desc="scenes"):
            name = f"scene_{i:04d}{ext}"
            write_image(tmp / name, scene_image(shape, rng, channels, bit_depth, kind))
            rows.append({"file": name, "device": device, "captured": start_year, "subject": f"scene {i}"})
        write_manifest(tmp / "manifest.csv", rows)
    return open_dataset(out)
