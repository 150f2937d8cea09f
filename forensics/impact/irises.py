"""Synthetic near-infrared iris images, IITD-like: the stand-in for an iris database that may not be downloaded.

An *iris class* (one eye) is a fixed pattern in polar coordinates, :func:`iris_texture`, plus a limbus
radius.  :func:`render_iris` draws one acquisition of it: a 320×240 8-bit NIR eye image whose pupil
dilation, rotation, position, focus, illumination, eyelids, eyelashes, specular reflections and sensor
noise change from sample to sample (:class:`IrisVariation`), and returns the geometry it used
(:class:`IrisTruth`).  :func:`simulate_irises` writes a whole set in the dataset format.

Coordinates: ``x`` is the column and ``y`` the row of a pixel centre (pixel ``[i, j]`` is at ``x = j, y = i``);
angles are measured from the +x axis towards +y (clockwise on screen).  The texture's row ``t`` (0 at the
pupil, 1 at the limbus) and column ``θ`` (0..2π) are mapped to the eye by Daugman's rubber sheet between
the pupil and limbus circles, with a non-linear radial warp that depends on the pupil dilation: the
pupillary zone compresses more than the ciliary zone as the pupil widens, as the iris stroma does.
"""
from __future__ import annotations

import csv
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.special import expit

from forensics._shared.atomic import atomic_directory, write_json
from forensics._shared.errors import UsageError
from forensics._shared.limits import require_memory
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, as_generator, keyed_generator, seed_record
from forensics.io.dataset import write_manifest
from forensics.io.images import write_image

TWO_PI = 2.0 * np.pi
#: The file written beside ``manifest.csv`` with the geometry of every image.
TRUTH = "truth.csv"
#: The provenance file of a set (seed, size, variation).
SETTINGS = "irises.json"
#: Peak memory of one rendered iris per pixel: RSS measured at 2048² and 3072² (91–94 bytes).
IRIS_BYTES_PER_PIXEL = 100


@dataclass(frozen=True)
class IrisVariation:
    """How acquisitions of one eye differ (the defaults are an IITD-like NIR capture at 320×240).

    Ranges ``(low, high)`` are drawn uniformly per sample unless stated otherwise.

    Attributes
    ----------
    iris_radius
        Range of the limbus radius in px, drawn once per *class* (90–110).
    iris_radius_jitter
        Standard deviation in px of the per-sample change of the limbus radius (distance to the camera).
    pupil_radius
        Range of the pupil radius in px (22–45): the dilation, drawn independently for every sample.
    reference_dilation
        Pupil/limbus radius ratio at which the texture is undistorted (0.33).
    dilation_warp
        Strength of the non-linear radial warp (dimensionless, 0 = linear rubber sheet): the texture row
        seen at normalised radius ``u`` is ``u + warp · (ρ − reference_dilation) · u (1 − u)``, ``ρ`` the
        dilation ratio; must keep ``|warp · (ρ − reference)| < 1`` (checked).
    deformation_radial
        Amplitude of a smooth random radial displacement of the stroma, in units of the iris band width
        (low angular harmonics, vanishing at pupil and limbus).
    deformation_angular_deg
        Amplitude in degrees of a smooth random angular displacement of the stroma.
    poor_probability, poor_factor
        Probability that a sample is a poor acquisition (gaze off axis, eye moving, strained lid) whose
        stromal deformation and blur are ``poor_factor`` times larger: the tail of genuine scores.
    centre_jitter
        Largest offset in px of the limbus centre from the image centre, per axis; the offset is drawn
        uniformly among the positions that keep the limbus circle inside the image.
    pupil_offset
        Standard deviation in px, per axis, of the pupil centre relative to the limbus centre.
    rotation_std_deg, rotation_max_deg
        Standard deviation and clip in degrees of the eye's rotation (head tilt, cyclotorsion).
    blur_sigma
        Range of the Gaussian defocus blur's sigma in px (times ``poor_factor`` for a poor sample).
    gain
        Range of the illumination gain (multiplies every level below).
    gradient
        Largest relative change of illumination across the image (a linear ramp in a random direction).
    vignetting
        Relative darkening of the image corners (illuminator fall-off).
    upper_lid
        Range of the upper eyelid's coverage: how far its apex lies below the top of the limbus, as a
        fraction of the iris diameter (0 = touching the iris top; ≈ 0.35 reaches a mid-size pupil).
    lower_lid_probability
        Probability that the lower eyelid covers the bottom of the iris at all.
    lower_lid
        Range of the lower eyelid's coverage when it does (fraction of the iris diameter).
    eyelashes
        Range (inclusive integers) of the number of upper eyelashes.
    eyelash_length
        Range of eyelash lengths in px.
    specular_count
        Range (inclusive integers) of the number of specular reflections of the illuminator.
    specular_radius
        Range of their radii in px.
    specular_in_pupil
        Probability that a reflection lies inside the pupil (else on the lower iris).
    noise_std
        Standard deviation of the additive Gaussian sensor noise in DN.
    texture_contrast
        DN per unit of the texture (the texture has unit standard deviation).
    pupil_level, iris_level, sclera_level, skin_level
        Mean grey levels in DN before the illumination gain: pupil (≈ 15–40 after it), iris, sclera, skin.
    level_jitter
        Relative standard deviation of each of these levels per sample.
    """

    iris_radius: tuple[float, float] = (90.0, 110.0)
    iris_radius_jitter: float = 1.5
    pupil_radius: tuple[float, float] = (22.0, 45.0)
    reference_dilation: float = 0.33
    dilation_warp: float = 2.0
    deformation_radial: float = 0.04
    deformation_angular_deg: float = 2.0
    poor_probability: float = 0.05
    poor_factor: float = 2.5
    centre_jitter: float = 15.0
    pupil_offset: float = 2.0
    rotation_std_deg: float = 3.0
    rotation_max_deg: float = 8.0
    blur_sigma: tuple[float, float] = (0.6, 1.8)
    gain: tuple[float, float] = (0.85, 1.15)
    gradient: float = 0.12
    vignetting: float = 0.15
    upper_lid: tuple[float, float] = (0.05, 0.42)
    lower_lid_probability: float = 0.25
    lower_lid: tuple[float, float] = (0.0, 0.15)
    eyelashes: tuple[int, int] = (15, 60)
    eyelash_length: tuple[float, float] = (10.0, 32.0)
    specular_count: tuple[int, int] = (1, 2)
    specular_radius: tuple[float, float] = (2.0, 4.5)
    specular_in_pupil: float = 0.85
    noise_std: float = 2.5
    texture_contrast: float = 18.0
    pupil_level: float = 26.0
    iris_level: float = 110.0
    sclera_level: float = 200.0
    skin_level: float = 160.0
    level_jitter: float = 0.05

    def __post_init__(self) -> None:
        for name in ("iris_radius", "pupil_radius", "blur_sigma", "gain", "upper_lid", "lower_lid",
                     "eyelashes", "eyelash_length", "specular_count", "specular_radius"):
            low, high = getattr(self, name)
            if not low <= high:
                raise UsageError(f"IrisVariation.{name} = {getattr(self, name)}: give (low, high) with low ≤ high")
        for name in ("iris_radius_jitter", "deformation_radial", "deformation_angular_deg", "centre_jitter",
                     "pupil_offset", "rotation_std_deg", "rotation_max_deg", "gradient", "vignetting",
                     "noise_std", "texture_contrast", "level_jitter", "dilation_warp"):
            if not getattr(self, name) >= 0:
                raise UsageError(f"IrisVariation.{name} = {getattr(self, name)}: must be ≥ 0")
        if self.pupil_radius[0] <= 0 or self.pupil_radius[1] >= 0.8 * self.iris_radius[0]:
            raise UsageError(f"IrisVariation: pupil radii {self.pupil_radius} must be > 0 and below 0.8 × the "
                             f"smallest iris radius {self.iris_radius[0]}")
        if self.poor_factor < 1:
            raise UsageError(f"IrisVariation.poor_factor = {self.poor_factor}: must be ≥ 1")
        for name in ("lower_lid_probability", "specular_in_pupil", "poor_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise UsageError(f"IrisVariation.{name} = {getattr(self, name)}: must be a probability")
        worst = max(abs(self.pupil_radius[0] / self.iris_radius[1] - self.reference_dilation),
                    abs(self.pupil_radius[1] / self.iris_radius[0] - self.reference_dilation))
        if self.dilation_warp * worst >= 1:
            raise UsageError(f"IrisVariation.dilation_warp = {self.dilation_warp}: folds the iris for dilations "
                             f"{worst:.2f} from the reference; lower it below {1 / worst:.2f}")

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON-ready values (ranges as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


@dataclass(frozen=True)
class IrisTruth:
    """The geometry and acquisition settings of one rendered image (px, image coordinates, see the module).

    Attributes
    ----------
    pupil_x, pupil_y, pupil_r
        Pupil circle.
    iris_x, iris_y, iris_r
        Limbus circle.
    rotation_deg
        Rotation of the texture (its column 0 appears at this angle).
    dilation
        ``pupil_r / iris_r``.
    blur_sigma
        Defocus blur sigma in px.
    gain
        Illumination gain at the image centre.
    lid_x
        Column of both eyelids' apexes.
    upper_lid_y, upper_lid_k
        The upper lid margin is ``y = upper_lid_y + upper_lid_k (x − lid_x)²``; the eye is below it.
    lower_lid_y, lower_lid_k
        The lower lid margin is ``y = lower_lid_y − lower_lid_k (x − lid_x)²``; the eye is above it.
    occlusion
        Fraction of the iris annulus hidden by the eyelids.
    eyelashes, specular_count
        Numbers of eyelashes and specular reflections drawn.
    noise_std
        Sensor noise standard deviation in DN.
    poor
        1 for a poor acquisition (deformation and blur scaled by ``IrisVariation.poor_factor``), else 0.
    """

    pupil_x: float
    pupil_y: float
    pupil_r: float
    iris_x: float
    iris_y: float
    iris_r: float
    rotation_deg: float
    dilation: float
    blur_sigma: float
    gain: float
    lid_x: float
    upper_lid_y: float
    upper_lid_k: float
    lower_lid_y: float
    lower_lid_k: float
    occlusion: float
    eyelashes: int
    specular_count: int
    noise_std: float
    poor: int

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain Python numbers."""
        return {k: (int(v) if isinstance(v, (int, np.integer)) else float(v))
                for k, v in dataclasses.asdict(self).items()}


@dataclass
class IrisSetResult:
    """What :func:`simulate_irises` wrote."""

    out: Path
    classes: int
    samples: int
    n_images: int
    subjects: list[str]
    size: tuple[int, int]
    seed: Any
    variation: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return {"out": str(self.out), "classes": self.classes, "samples": self.samples, "n_images": self.n_images,
                "subjects": self.subjects, "size": {"height": self.size[0], "width": self.size[1]},
                "seed": self.seed, "variation": self.variation}


# ----------------------------------------------------------------------------------------------- texture


def iris_texture(rng: RngLike, shape: tuple[int, int] = (64, 512)) -> np.ndarray:
    """A class's fixed iris pattern in polar coordinates.

    Parameters
    ----------
    rng
        Generator or integer seed: the pattern's only source of randomness.
    shape
        ``(rows, columns)``: rows sample the normalised radius from 0 (pupil margin) to 1 (limbus),
        columns the angle ``2π · j / columns`` (periodic).

    Returns
    -------
    numpy.ndarray
        float32, zero mean and unit standard deviation (NIR reflectance relative to the iris mean):
        radial fibres at three angular scales (elongated along the radius, slightly twisted), crypts (dark,
        steep-walled blobs, mostly near the collarette), concentric contraction furrows in the outer part,
        a wavy collarette ring near a third of the radius with a step between pupillary and ciliary zone,
        pigment spots, a dark pupillary ruff and a darker limbal ring.
    """
    rows, cols = (int(s) for s in shape)
    if rows < 8 or cols < 32:
        raise UsageError(f"iris_texture: shape {tuple(shape)} is too small; give at least (8, 32)")
    rng = as_generator(rng)
    r = np.linspace(0.0, 1.0, rows, dtype=np.float32)[:, None]
    phi = (np.arange(cols, dtype=np.float32) * np.float32(TWO_PI / cols))[None, :]
    collar = _collarette_radius(rng, phi)
    tex = _fibres(rng, rows, cols)
    tex += _collarette(rng, r, collar)
    tex += _crypts(rng, r, phi, collar)
    tex += _furrows(rng, r, phi)
    tex += _spots(rng, r, phi)
    tex += -0.8 * np.exp(-r / 0.03) - 1.0 * np.clip((r - 0.85) / 0.15, 0.0, 1.0) ** 2
    tex -= tex.mean()
    tex /= max(float(tex.std()), 1e-6)
    return tex.astype(np.float32)


def _angle_diff(phi: np.ndarray, centre: float) -> np.ndarray:
    """``phi − centre`` wrapped into [−π, π)."""
    return (phi - centre + np.pi) % TWO_PI - np.pi


def _fibres(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Radial fibres: noise smoothed along the radius far more than along the angle, at three scales, twisted."""
    tex = np.zeros((rows, cols), np.float32)
    for sigma_r, sigma_deg, weight in ((0.10, 1.0, 1.0), (0.20, 3.0, 1.0), (0.30, 8.0, 0.6)):
        noise = rng.standard_normal((rows, cols), dtype=np.float32)
        smooth = ndimage.gaussian_filter(noise, (sigma_r * rows, np.radians(sigma_deg) / TWO_PI * cols),
                                         mode=("nearest", "wrap"))
        tex += weight * smooth / max(float(smooth.std()), 1e-6)
    # a smooth radius-dependent twist (fibres are not straight spokes): shift each row along the angle
    t = np.linspace(0.0, 1.0, rows)
    twist = sum(rng.normal(0.0, 0.03) * np.sin(np.pi * k * t + rng.uniform(0, TWO_PI)) for k in (1, 2, 3))
    freq = np.fft.rfftfreq(cols) * cols
    spectrum = np.fft.rfft(tex, axis=1) * np.exp(-1j * freq[None, :] * twist[:, None])
    return np.fft.irfft(spectrum, n=cols, axis=1).astype(np.float32)


def _collarette_radius(rng: np.random.Generator, phi: np.ndarray) -> np.ndarray:
    """The collarette's normalised radius against angle: ≈ 1/3 with a wavy, class-specific outline."""
    radius = rng.uniform(0.28, 0.38) + np.zeros_like(phi)
    for k in range(2, 13):
        radius = radius + rng.normal(0.0, 0.045 / np.sqrt(k)) * np.sin(k * phi + rng.uniform(0, TWO_PI))
    return np.clip(radius, 0.15, 0.55).astype(np.float32)


def _collarette(rng: np.random.Generator, r: np.ndarray, collar: np.ndarray) -> np.ndarray:
    """A bright ridge along the collarette and a level step between the pupillary and ciliary zones."""
    ridge = rng.uniform(0.9, 1.6) * np.exp(-0.5 * ((r - collar) / 0.025) ** 2)
    step = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.8) * expit((collar - r) / 0.02)
    return (ridge + step).astype(np.float32)


def _crypts(rng: np.random.Generator, r: np.ndarray, phi: np.ndarray, collar: np.ndarray) -> np.ndarray:
    """Crypts of Fuchs: dark radially elongated blobs with steep walls, clustered beyond the collarette."""
    out = np.zeros(np.broadcast_shapes(r.shape, phi.shape), np.float32)
    mean_collar = float(collar.mean())
    for _ in range(int(rng.poisson(14)) + 4):
        if rng.random() < 0.6:
            r0 = float(np.clip(rng.normal(mean_collar + 0.08, 0.08), 0.05, 0.9))
        else:
            r0 = float(rng.uniform(0.1, 0.85))
        theta0 = rng.uniform(0.0, TWO_PI)
        sigma_r, sigma_t = rng.uniform(0.03, 0.10), np.radians(rng.uniform(2.0, 7.0))
        blob = np.exp(-0.5 * ((r - r0) / sigma_r) ** 2 - 0.5 * (_angle_diff(phi, theta0) / sigma_t) ** 2)
        out -= rng.uniform(1.5, 3.5) * np.minimum(1.0, 1.6 * blob)
    return out


def _furrows(rng: np.random.Generator, r: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Contraction furrows: dark concentric arcs with wavy outlines in the outer (ciliary) part."""
    out = np.zeros(np.broadcast_shapes(r.shape, phi.shape), np.float32)
    for radius in np.sort(rng.uniform(0.55, 0.93, int(rng.integers(2, 6)))):
        wobble = sum(rng.normal(0.0, 0.01) * np.sin(k * phi + rng.uniform(0, TWO_PI)) for k in range(1, 5))
        half = np.radians(rng.uniform(40.0, 160.0))
        arc = expit((half - np.abs(_angle_diff(phi, rng.uniform(0, TWO_PI)))) / 0.15)
        width = rng.uniform(0.015, 0.035)
        out -= rng.uniform(1.0, 2.0) * arc * np.exp(-0.5 * ((r - radius - wobble) / width) ** 2)
    return out


def _spots(rng: np.random.Generator, r: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Pigment spots (naevi, mostly dark in NIR) and a few bright stromal flecks."""
    out = np.zeros(np.broadcast_shapes(r.shape, phi.shape), np.float32)
    for _ in range(int(rng.poisson(3))):
        r0, theta0 = rng.uniform(0.2, 0.95), rng.uniform(0.0, TWO_PI)
        sigma_r, sigma_t = rng.uniform(0.01, 0.03), np.radians(rng.uniform(0.7, 2.0))
        sign = -1.0 if rng.random() < 0.7 else 1.0
        out += sign * rng.uniform(1.5, 3.0) * np.exp(
            -0.5 * ((r - r0) / sigma_r) ** 2 - 0.5 * (_angle_diff(phi, theta0) / sigma_t) ** 2)
    return out


# ----------------------------------------------------------------------------------------------- rendering


def render_iris(texture: np.ndarray, rng: RngLike, size: tuple[int, int] = (240, 320),
                variation: IrisVariation = IrisVariation(),
                iris_r: float | None = None) -> tuple[np.ndarray, IrisTruth]:
    """One near-infrared eye image of the iris ``texture``.

    Parameters
    ----------
    texture
        The class's pattern from :func:`iris_texture` (rows = normalised radius, columns = angle).
    rng
        Generator or integer seed of everything that changes between acquisitions.
    size
        ``(height, width)`` of the image in px; it must hold the largest iris.
    variation
        The per-sample variability.
    iris_r
        The class's limbus radius in px (drawn from ``variation.iris_radius`` when None; pass the same value
        for every sample of a class, as :func:`simulate_irises` does).

    Returns
    -------
    image : numpy.ndarray
        uint8 ``size`` array: dark pupil, textured mid-grey iris, bright sclera and skin, upper (sometimes
        lower) eyelid with a dark lash line and a shadow, eyelashes over the top of the iris, saturated
        specular reflections (mostly in the pupil), defocus blur, uneven illumination, Gaussian noise.
    truth : IrisTruth
        The geometry and settings used.
    """
    texture = np.asarray(texture, np.float32)
    if texture.ndim != 2 or texture.shape[0] < 2 or texture.shape[1] < 4:
        raise UsageError(f"render_iris: texture must be a 2-D (radius, angle) array, got shape {texture.shape}")
    height, width = _check_size(size, variation, iris_r)
    rng = as_generator(rng)
    v = variation
    geo = _draw_geometry(rng, (height, width), v, iris_r)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    u, theta, pupil_alpha, limbus_alpha = _rubber_sheet(x, y, geo)
    levels = {name: getattr(v, f"{name}_level") * (1.0 + v.level_jitter * rng.standard_normal())
              for name in ("pupil", "iris", "sclera", "skin")}
    iris = levels["iris"] + v.texture_contrast * _sample_texture(texture, u, theta, geo, rng, v)
    sclera = levels["sclera"] * (1.0 - 0.1 * ((x - geo["iris_x"]) / (1.6 * geo["iris_r"])) ** 2)
    eyeball = pupil_alpha * levels["pupil"] + (1 - pupil_alpha) * ((1 - limbus_alpha) * iris + limbus_alpha * sclera)
    lids = _draw_lids(rng, geo, v)
    scene, open_alpha = _apply_lids(eyeball, x, y, lids, levels["skin"], rng)
    lashes = _eyelashes(rng, (height, width), lids, geo, v)
    scene *= np.exp(-lashes)
    spec_count = _speculars(scene, x, y, rng, geo, v)
    blur = float(rng.uniform(*v.blur_sigma)) * geo["severity"]
    scene = ndimage.gaussian_filter(scene, blur, mode="nearest")
    gain = float(rng.uniform(*v.gain))
    scene *= gain * _illumination(rng, x, y, v)
    scene += rng.normal(0.0, v.noise_std, scene.shape).astype(np.float32)
    image = np.clip(np.rint(scene), 0, 255).astype(np.uint8)
    annulus = (pupil_alpha < 0.5) & (limbus_alpha < 0.5)
    occlusion = float(np.mean(open_alpha[annulus] < 0.5)) if annulus.any() else 0.0
    truth = IrisTruth(
        pupil_x=geo["pupil_x"], pupil_y=geo["pupil_y"], pupil_r=geo["pupil_r"], iris_x=geo["iris_x"],
        iris_y=geo["iris_y"], iris_r=geo["iris_r"], rotation_deg=geo["rotation_deg"],
        dilation=geo["pupil_r"] / geo["iris_r"], blur_sigma=blur, gain=gain, lid_x=lids["x"],
        upper_lid_y=lids["upper_y"], upper_lid_k=lids["upper_k"], lower_lid_y=lids["lower_y"],
        lower_lid_k=lids["lower_k"], occlusion=occlusion, eyelashes=int(lids["lashes"]),
        specular_count=spec_count, noise_std=float(v.noise_std), poor=int(geo["severity"] > 1))
    return image, truth


def _check_size(size: tuple[int, int], variation: IrisVariation, iris_r: float | None) -> tuple[int, int]:
    """``(height, width)`` as ints, refused when the largest iris does not fit."""
    try:
        height, width = (int(s) for s in size)
    except (TypeError, ValueError):
        raise UsageError(f"size {size!r}: give (height, width) in px, e.g. (240, 320)") from None
    largest = variation.iris_radius[1] if iris_r is None else float(iris_r)
    largest += 3 * variation.iris_radius_jitter
    if min(height, width) < 2 * largest + 2:
        raise UsageError(f"size {height}×{width} (height×width) cannot hold an iris of radius {largest:.0f} px; "
                         "enlarge the image or lower IrisVariation.iris_radius")
    if iris_r is not None and not variation.pupil_radius[1] < 0.8 * float(iris_r):
        raise UsageError(f"iris_r = {iris_r}: too small for pupils up to {variation.pupil_radius[1]} px")
    return height, width


def _draw_geometry(rng: np.random.Generator, size: tuple[int, int], v: IrisVariation,
                   iris_r: float | None) -> dict[str, float]:
    """Limbus and pupil circles, rotation and the severity (1, or ``poor_factor`` for a poor sample)."""
    height, width = size
    base = float(rng.uniform(*v.iris_radius)) if iris_r is None else float(iris_r)
    jitter = v.iris_radius_jitter
    radius = base + float(np.clip(rng.normal(0.0, jitter), -3 * jitter, 3 * jitter)) if jitter > 0 else base
    centre = []
    for extent in (width, height):
        mid = (extent - 1) / 2.0
        low, high = max(-v.centre_jitter, radius + 1 - mid), min(v.centre_jitter, extent - 2 - radius - mid)
        centre.append(mid + float(rng.uniform(low, high)) if low < high else mid)
    pupil_r = float(rng.uniform(*v.pupil_radius))
    room = max(0.0, 0.9 * radius - pupil_r)
    offset = np.clip(rng.normal(0.0, v.pupil_offset, 2), -room / 1.5, room / 1.5)
    rotation = float(np.clip(rng.normal(0.0, v.rotation_std_deg), -v.rotation_max_deg, v.rotation_max_deg))
    severity = v.poor_factor if rng.random() < v.poor_probability else 1.0
    return {"severity": severity, "iris_x": centre[0], "iris_y": centre[1], "iris_r": radius, "pupil_x": centre[0] + float(offset[0]),
            "pupil_y": centre[1] + float(offset[1]), "pupil_r": pupil_r, "rotation_deg": rotation}


def _rubber_sheet(x: np.ndarray, y: np.ndarray,
                  geo: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Invert Daugman's rubber sheet: each pixel's normalised radius ``u`` (0 pupil, 1 limbus) and angle.

    The sheet maps ``(u, θ)`` to ``c_i + (1 − u) d + (r_p + u (R − r_p)) e(θ)``, ``d`` the pupil centre's
    offset from the limbus centre ``c_i``; a few fixed-point steps invert it (``|d|`` is small).
    Also returns the anti-aliased coverage of the pupil disc and of the outside of the limbus.
    """
    qx, qy = x - geo["iris_x"], y - geo["iris_y"]
    dx, dy = geo["pupil_x"] - geo["iris_x"], geo["pupil_y"] - geo["iris_y"]
    rp, radius = geo["pupil_r"], geo["iris_r"]
    u = np.clip((np.hypot(qx, qy) - rp) / (radius - rp), 0.0, 1.0)
    for _ in range(3):
        sx, sy = qx - (1 - u) * dx, qy - (1 - u) * dy
        u = np.clip((np.hypot(sx, sy) - rp) / (radius - rp), 0.0, 1.0)
    sx, sy = qx - (1 - u) * dx, qy - (1 - u) * dy
    theta = np.arctan2(sy, sx) % TWO_PI
    pupil_alpha = np.clip(rp - np.hypot(qx - dx, qy - dy) + 0.5, 0.0, 1.0)
    limbus_alpha = expit((np.hypot(qx, qy) - radius) / 0.9)
    return u, theta, pupil_alpha, limbus_alpha.astype(np.float32)


def _sample_texture(texture: np.ndarray, u: np.ndarray, theta: np.ndarray, geo: dict[str, float],
                    rng: np.random.Generator, v: IrisVariation) -> np.ndarray:
    """The texture seen at each pixel, after the dilation warp, the stromal deformation and the rotation."""
    rows, cols = texture.shape
    rho = geo["pupil_r"] / geo["iris_r"]
    t = u + v.dilation_warp * (rho - v.reference_dilation) * u * (1 - u)
    harmonics = np.arange(1, 4)[:, None]
    a_r, a_t = rng.normal(0, 1, (2, 3)) / np.sqrt(np.arange(1, 4))
    p_r, p_t = rng.uniform(0, TWO_PI, (2, 3))
    # low angular harmonics: evaluated on a 1-D angle table and looked up, to keep the pixel work vectorised
    table = np.linspace(0.0, TWO_PI, 721)
    radial = geo["severity"] * v.deformation_radial * (a_r[:, None] * np.sin(harmonics * table + p_r[:, None])).sum(0)
    angular = geo["severity"] * np.radians(v.deformation_angular_deg) * (a_t[:, None] * np.sin(harmonics * table + p_t[:, None])).sum(0)
    index = np.rint(theta * (720 / TWO_PI)).astype(np.intp)
    t = np.clip(t + 4 * u * (1 - u) * radial[index].astype(np.float32), 0.0, 1.0)
    angle = theta - np.radians(geo["rotation_deg"]) + angular[index].astype(np.float32)
    col = (angle % TWO_PI) * (cols / TWO_PI)
    padded = np.pad(texture, ((0, 0), (1, 2)), mode="wrap")
    inside = (u > 0) & (u < 1)
    out = np.zeros(u.shape, np.float32)
    out[inside] = ndimage.map_coordinates(padded, [t[inside] * (rows - 1), col[inside] + 1], order=1,
                                          mode="nearest", prefilter=False)
    return out


def _draw_lids(rng: np.random.Generator, geo: dict[str, float], v: IrisVariation) -> dict[str, float]:
    """Upper and lower eyelid margins as parabolas through the eye corners, and the eyelash count."""
    cy, radius = geo["iris_y"], geo["iris_r"]
    lid_x = geo["iris_x"] + rng.normal(0.0, 0.15 * radius)
    corner_y, corner_dx = cy + 0.1 * radius, 1.7 * radius
    upper_y = cy - radius + rng.uniform(*v.upper_lid) * 2 * radius
    upper_k = (corner_y - upper_y) / corner_dx ** 2 * rng.uniform(0.8, 1.2)
    cover = rng.uniform(*v.lower_lid) if rng.random() < v.lower_lid_probability else rng.uniform(-0.25, -0.02)
    lower_y = cy + radius - cover * 2 * radius
    lower_k = max(lower_y - corner_y, 1.0) / corner_dx ** 2 * rng.uniform(0.8, 1.2)
    lashes = int(rng.integers(v.eyelashes[0], v.eyelashes[1] + 1))
    return {"x": float(lid_x), "upper_y": float(upper_y), "upper_k": float(upper_k), "lower_y": float(lower_y),
            "lower_k": float(lower_k), "lashes": lashes}


def _apply_lids(eyeball: np.ndarray, x: np.ndarray, y: np.ndarray, lids: dict[str, float], skin_level: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cover the eyeball with skin outside the lid margins; a dark lash line, a crease and the lid's shadow."""
    dx2 = (x - lids["x"]) ** 2
    upper = lids["upper_y"] + lids["upper_k"] * dx2
    lower = lids["lower_y"] - lids["lower_k"] * dx2
    below_upper = expit((y - upper) / 0.8)
    above_lower = expit(lower - y)
    open_alpha = (below_upper * above_lower).astype(np.float32)
    shadow = 1.0 - 0.35 * np.exp(-np.maximum(y - upper, 0.0) / 6.0)
    height, width = y.shape
    coarse = rng.standard_normal((height // 16 + 2, width // 16 + 2)).astype(np.float32)
    mottle = ndimage.zoom(coarse, (height / coarse.shape[0], width / coarse.shape[1]), order=1)[:height, :width]
    skin = skin_level * (1.0 + 0.06 * mottle)
    opening = expit((lower - upper - 6.0) / 4.0)  # columns where the lids are apart
    skin -= 70.0 * np.exp(-0.5 * ((y - upper + 2.0) / 1.6) ** 2) * opening  # lash line on the upper lid margin
    skin -= 20.0 * np.exp(-0.5 * ((y - upper + 0.25 * (lower - upper) + 10.0) / 4.0) ** 2) * opening  # crease
    skin -= 25.0 * np.exp(-0.5 * ((y - lower - 1.5) / 1.5) ** 2) * opening * below_upper  # lower lid margin
    scene = open_alpha * eyeball * shadow + (1.0 - open_alpha) * skin
    return scene.astype(np.float32), open_alpha


def _eyelashes(rng: np.random.Generator, size: tuple[int, int], lids: dict[str, float],
               geo: dict[str, float], v: IrisVariation) -> np.ndarray:
    """Optical density of the upper eyelashes: curved strands from the lid margin, splatted bilinearly."""
    height, width = size
    n = lids["lashes"]
    density = np.zeros(height * width, np.float32)
    if n == 0:
        return density.reshape(size)
    radius = geo["iris_r"]
    root_x = lids["x"] + rng.uniform(-1.1, 1.1, n) * radius
    root_y = lids["upper_y"] + lids["upper_k"] * (root_x - lids["x"]) ** 2 - 1.0
    tilt = np.radians(25.0 * (root_x - lids["x"]) / radius + rng.normal(0.0, 10.0, n))
    length = rng.uniform(*v.eyelash_length, n)
    bend = rng.normal(0.0, 0.25, n) * length
    end_x, end_y = root_x + length * np.sin(tilt), root_y + length * np.cos(tilt)
    ctrl_x = (root_x + end_x) / 2 + bend * np.cos(tilt)
    ctrl_y = (root_y + end_y) / 2 - bend * np.sin(tilt)
    strength = rng.uniform(0.5, 1.1, n)
    steps = 48
    s = np.linspace(0.0, 1.0, steps)[None, :]
    px = ((1 - s) ** 2 * root_x[:, None] + 2 * (1 - s) * s * ctrl_x[:, None] + s ** 2 * end_x[:, None]).ravel()
    py = ((1 - s) ** 2 * root_y[:, None] + 2 * (1 - s) * s * ctrl_y[:, None] + s ** 2 * end_y[:, None]).ravel()
    weight = (strength[:, None] * (length[:, None] / steps) * (1.0 - 0.6 * s)).ravel()  # tapering to the tip
    x0, y0 = np.floor(px).astype(np.intp), np.floor(py).astype(np.intp)
    fx, fy = px - x0, py - y0
    for ox, oy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        cx, cy = x0 + ox, y0 + oy
        ok = (cx >= 0) & (cx < width) & (cy >= 0) & (cy < height)
        density += np.bincount(cy[ok] * width + cx[ok], (weight * w)[ok], minlength=height * width).astype(np.float32)
    return 1.6 * density.reshape(size)


def _speculars(scene: np.ndarray, x: np.ndarray, y: np.ndarray, rng: np.random.Generator,
               geo: dict[str, float], v: IrisVariation) -> int:
    """Paint illuminator reflections into ``scene`` (in place): mostly in the pupil, else low on the iris.

    A reflection is 3000 DN, far beyond full scale, so that even a strongly blurred one still clips at 255.
    """
    count = int(rng.integers(v.specular_count[0], v.specular_count[1] + 1))
    for _ in range(count):
        radius = float(rng.uniform(*v.specular_radius))
        angle = rng.uniform(0.0, TWO_PI)
        if rng.random() < v.specular_in_pupil:
            reach = max(geo["pupil_r"] - radius, 0.0) * 0.85 * np.sqrt(rng.random())
            cx, cy = geo["pupil_x"] + reach * np.cos(angle), geo["pupil_y"] + reach * np.sin(angle)
        else:
            angle = rng.uniform(np.radians(20), np.radians(160))  # lower half: upper is under the lid
            reach = geo["pupil_r"] + rng.uniform(0.1, 0.6) * (geo["iris_r"] - geo["pupil_r"])
            cx, cy = geo["iris_x"] + reach * np.cos(angle), geo["iris_y"] + reach * np.sin(angle)
        box = (slice(max(int(cy - radius - 2), 0), max(int(cy + radius + 3), 0)),
               slice(max(int(cx - radius - 2), 0), max(int(cx + radius + 3), 0)))
        alpha = np.clip(radius - np.hypot(x[box] - cx, y[box] - cy) + 0.5, 0.0, 1.0)
        scene[box] = scene[box] * (1 - alpha) + alpha * 3000.0
    return count


def _illumination(rng: np.random.Generator, x: np.ndarray, y: np.ndarray, v: IrisVariation) -> np.ndarray:
    """Relative illumination: a linear ramp in a random direction times a radial fall-off (1 at the centre)."""
    height, width = x.shape
    nx, ny = (x - (width - 1) / 2) / (width / 2), (y - (height - 1) / 2) / (height / 2)
    direction = rng.uniform(0.0, TWO_PI)
    ramp = 1.0 + rng.uniform(0.0, v.gradient) / 2 * (nx * np.cos(direction) + ny * np.sin(direction))
    return (ramp * (1.0 - v.vignetting * (nx ** 2 + ny ** 2) / 2)).astype(np.float32)


# ----------------------------------------------------------------------------------------------- data sets


def class_subject(class_index: int) -> str:
    """The subject of class ``k``: person ``k // 2 + 1``, eye ``L`` for even ``k`` and ``R`` for odd, e.g. ``001_L``."""
    return f"{class_index // 2 + 1:03d}_{'LR'[class_index % 2]}"


def simulate_irises(out: str | os.PathLike, classes: int, samples: int, rng: RngLike,
                    size: tuple[int, int] = (240, 320), variation: IrisVariation = IrisVariation(),
                    force: bool = False, progress: Progress = no_progress) -> IrisSetResult:
    """Write a synthetic iris set: ``classes`` eyes × ``samples`` images each.

    Parameters
    ----------
    out
        Output folder, written atomically (nothing appears until it is complete); refused if it exists
        unless ``force``.
    classes, samples
        Numbers of eyes (≥ 2) and of images per eye (≥ 2).  Class ``k`` is person ``k // 2 + 1``, eye ``L``
        for even ``k`` and ``R`` for odd ``k``.
    rng
        Generator or integer seed.  Class ``k``'s texture and limbus radius come from the sub-stream
        ``keyed_generator(rng, k)`` and its sample ``s`` from ``keyed_generator(rng, k, s + 1)``, so an image
        depends on the seed, its class and its sample number only (not on how many were asked for).
    size
        ``(height, width)`` in px.
    variation
        Per-sample variability (:class:`IrisVariation`).
    progress
        Progress wrapper over the classes.

    Writes ``OUT/<person>_<eye>_<sample>.png`` (8-bit grey, e.g. ``001_L_00.png``), ``OUT/manifest.csv``
    (``file``, ``device`` (empty), ``subject`` = ``<person>_<eye>``, ``eye``, ``person``, ``sample``),
    ``OUT/truth.csv`` (``file``, ``subject`` and the :class:`IrisTruth` fields) and ``OUT/irises.json``
    (seed record, size, counts and the variation).

    Raises
    ------
    UsageError
        Fewer than 2 classes or samples, a size that cannot hold the iris, or an existing ``out``.
    """
    for name, value in (("classes", classes), ("samples", samples)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
            raise UsageError(f"{name} = {value!r}: give an integer ≥ 2 (a matcher needs genuine and impostor pairs)")
    if samples > 100:
        raise UsageError(f"samples = {samples}: at most 100 per eye (file names have two digits)")
    height, width = _check_size(size, variation, None)
    require_memory(IRIS_BYTES_PER_PIXEL * height * width, f"a {width}×{height} iris image")
    out = Path(out)
    rows: list[dict[str, Any]] = []
    truths: list[dict[str, Any]] = []
    with atomic_directory(out, force=force) as tmp:
        for k in progress(range(classes), total=classes, desc="irises"):
            class_rng = keyed_generator(rng, k)
            texture = iris_texture(class_rng)
            iris_r = float(class_rng.uniform(*variation.iris_radius))
            subject = class_subject(k)
            for s in range(samples):
                image, truth = render_iris(texture, keyed_generator(rng, k, s + 1), (height, width), variation, iris_r)
                name = f"{subject}_{s:02d}.png"
                write_image(tmp / name, image)
                rows.append({"file": name, "device": None, "subject": subject, "person": f"{k // 2 + 1:03d}",
                             "eye": "LR"[k % 2], "sample": s})
                truths.append({"file": name, "subject": subject, **truth.to_dict()})
        write_manifest(tmp / "manifest.csv", rows)
        _write_truth(tmp / TRUTH, truths)
        seed = seed_record(rng)
        write_json(tmp / SETTINGS, {"seed": seed, "classes": int(classes), "samples": int(samples),
                                    "size": {"height": height, "width": width}, "variation": variation.to_dict()})
    return IrisSetResult(out, int(classes), int(samples), len(rows), [class_subject(k) for k in range(classes)],
                         (height, width), seed, variation.to_dict())


def _write_truth(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write ``truth.csv``: file, subject and the :class:`IrisTruth` fields (floats to 4 decimals)."""
    columns = ["file", "subject", *(f.name for f in dataclasses.fields(IrisTruth))]
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()})
