"""Scene images for users who have none: scikit-image's bundled photographs and procedural textures.

Nothing is downloaded: only the sample images that ship inside scikit-image
are used, plus seeded 1/f ("pink") textures.  Every function takes ``rng``, a Generator or an integer
seed (:func:`forensics._shared.rng.as_generator`).
"""
from __future__ import annotations

import numpy as np

from forensics._shared.arrays import bits_full_scale
from forensics._shared.rng import RngLike, as_generator

#: scikit-image sample images bundled with the package (no network needed).
BUNDLED = ("camera", "astronaut", "coffee", "chelsea", "brick", "grass", "gravel", "rocket", "moon", "coins", "clock",
           "immunohistochemistry", "hubble_deep_field", "cell", "retina")


def pink_texture(shape: tuple[int, int], rng: RngLike, exponent: float = 1.8) -> np.ndarray:
    """A zero-mean, unit-variance random field with power spectrum ∝ 1/f^exponent (float32)."""
    rng = as_generator(rng)
    h, w = shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    amplitude = f ** (-exponent / 2.0)
    amplitude[0, 0] = 0.0
    spectrum = amplitude * (rng.standard_normal(amplitude.shape) + 1j * rng.standard_normal(amplitude.shape))
    field = np.fft.irfft2(spectrum, s=shape)
    field = (field - field.mean()) / (field.std() + 1e-12)
    return field.astype(np.float32)


def _bundled(name: str) -> np.ndarray:
    import skimage.data

    img = getattr(skimage.data, name)()
    if img.ndim == 3:
        img = img[..., :3]
    return img.astype(np.float32) / 255.0


def _fit_to(img: np.ndarray, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Random crop of a random scale of ``img`` covering ``shape``."""
    from skimage.transform import resize

    h, w = shape
    scale = max(h / img.shape[0], w / img.shape[1]) * rng.uniform(1.0, 1.6)
    new = (max(h, int(np.ceil(img.shape[0] * scale))), max(w, int(np.ceil(img.shape[1] * scale))))
    img = resize(img, new + img.shape[2:], order=1, anti_aliasing=True, preserve_range=True).astype(np.float32)
    y = rng.integers(0, img.shape[0] - h + 1)
    x = rng.integers(0, img.shape[1] - w + 1)
    img = img[y:y + h, x:x + w]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    return img


def scene(shape: tuple[int, int], rng: RngLike, channels: int = 1, kind: str = "mixed") -> np.ndarray:
    """One scene in [0, 1] (float32), ``(H, W)`` or ``(H, W, 3)``.

    ``kind``: ``'photo'`` (a bundled photograph, randomly cropped and scaled),
    ``'texture'`` (a pink-noise texture with a smooth illumination gradient) or
    ``'mixed'`` (either, at random).
    """
    rng = as_generator(rng)
    if kind == "mixed":
        kind = "photo" if rng.random() < 0.5 else "texture"
    if kind == "photo":
        img = _fit_to(_bundled(BUNDLED[rng.integers(len(BUNDLED))]), shape, rng)
        if img.ndim == 2 and channels == 3:
            img = np.repeat(img[..., None], 3, axis=2)
        elif img.ndim == 3 and channels == 1:
            img = img @ np.array([0.299, 0.587, 0.114], np.float32)
    elif kind == "texture":
        base = 0.5 + 0.15 * pink_texture(shape, rng)
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
        gx, gy = rng.uniform(-0.2, 0.2, 2)
        base += gx * (xx / shape[1] - 0.5) + gy * (yy / shape[0] - 0.5)
        if channels == 3:
            tint = rng.uniform(0.8, 1.2, 3).astype(np.float32)
            img = base[..., None] * tint
        else:
            img = base
    else:
        raise ValueError(f"unknown scene kind {kind!r}")
    gain = rng.uniform(0.7, 1.1)
    return np.clip(img * gain, 0.02, 0.98).astype(np.float32)


def scene_image(shape: tuple[int, int], rng: RngLike, channels: int = 1, bit_depth: int = 8,
                kind: str = "mixed") -> np.ndarray:
    """A scene quantised to ``bit_depth`` bits (uint8 or uint16)."""
    rng = as_generator(rng)
    full = bits_full_scale(bit_depth)
    img = np.rint(scene(shape, rng, channels, kind) * full)
    return img.astype(np.uint8 if bit_depth <= 8 else np.uint16)
