"""Tests of forensics.prnu.fingerprint: regions, the streaming ML estimator, saturation, persistence."""
from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from forensics._shared.errors import InputError, UsageError
from forensics.prnu.fingerprint import (
    Fingerprint,
    FingerprintBuilder,
    Region,
    build_fingerprint,
    intensity,
    parse_region,
    postprocess,
    region_residual_and_intensity,
    saturation_mask,
)

SHAPE = (192, 256)


def corr(a: np.ndarray, b: np.ndarray) -> float:
    a = np.asarray(a, np.float64).ravel() - np.mean(a)
    b = np.asarray(b, np.float64).ravel() - np.mean(b)
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def flat_scene(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A flat-ish scene: 120 ± 25 of very smooth shading (8-bit units)."""
    field = ndimage.gaussian_filter(rng.normal(0, 1, shape), 24)
    return 120 + 25 * field / field.std()


def camera_image(rng: np.random.Generator, scene: np.ndarray, k: np.ndarray, noise: float = 2.0) -> np.ndarray:
    img = scene * (1 + k) + rng.normal(0, noise, scene.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def camera() -> dict:
    rng = np.random.default_rng(424242)
    k = rng.normal(0, 0.01, SHAPE)
    images = [camera_image(rng, flat_scene(rng, SHAPE), k) for _ in range(16)]
    return {"k": k, "images": images}


# ----------------------------------------------------------------------------- regions


@pytest.mark.parametrize(
    "text, kind, size, spec",
    [
        ("full", "full", None, "full"),
        ("center:512", "center", (512, 512), "center:512"),
        ("centre:64x96", "center", (64, 96), "center:64x96"),
        ("corners", "corners", (128, 128), "corners:128"),
        ("Corners:64", "corners", (64, 64), "corners:64"),
    ],
)
def test_parse_region(text, kind, size, spec):
    region = parse_region(text)
    assert (region.kind, region.size, region.spec) == (kind, size, spec)
    assert parse_region(region.spec) == region


@pytest.mark.parametrize("text", ["", "middle", "center", "center:abc", "center:8", "corners:64x32", "full:3"])
def test_parse_region_rejects(text):
    with pytest.raises(UsageError):
        parse_region(text)


def test_center_crop_keeps_cfa_phase():
    region = parse_region("center:64")
    (rows, cols), = region.pieces((101, 203))
    assert rows.start % 2 == 0 and cols.start % 2 == 0
    assert rows.stop - rows.start == 64 and cols.stop - cols.start == 64
    with pytest.raises(InputError):
        region.pieces((50, 300))


def test_corners_mosaic_layout():
    frame = np.arange(101 * 203).reshape(101, 203)
    region = parse_region("corners:16")
    mosaic = region.extract(frame)
    assert mosaic.shape == (32, 32)
    pieces = region.pieces(frame.shape)
    assert all(r.start % 2 == 0 and c.start % 2 == 0 for r, c in pieces)
    np.testing.assert_array_equal(mosaic[:16, :16], frame[:16, :16])
    np.testing.assert_array_equal(mosaic[:16, 16:], frame[:16, 186:202])  # 203 - 16 = 187 -> 186 (even)
    np.testing.assert_array_equal(mosaic[16:, :16], frame[84:100, :16])  # 101 - 16 = 85 -> 84
    np.testing.assert_array_equal(mosaic[16:, 16:], frame[84:100, 186:202])
    rgb = np.stack([frame] * 3, axis=-1)
    assert region.extract(rgb).shape == (32, 32, 3)


# ----------------------------------------------------------------------------- the estimator


def test_fingerprint_improves_with_more_images(camera):
    """corr(K, k) follows 1/√(1 + c/n): the ML estimate's noise variance falls as 1/n.

    With ρ₁ the single-image correlation, c = 1/ρ₁² − 1.  Measured over 6 seeds,
    the spread around this curve is below 0.01; 0.04 leaves a wide margin.
    """
    k, images = camera["k"], camera["images"]
    builder = FingerprintBuilder()
    rho = {}
    for n, image in enumerate(images, start=1):
        builder.add(image)
        if n in (1, 4, 16):
            rho[n] = corr(builder.result().K, k)
    assert rho[1] < rho[4] < rho[16]
    c = 1 / rho[1] ** 2 - 1
    for n in (4, 16):
        assert rho[n] == pytest.approx(1 / np.sqrt(1 + c / n), abs=0.04)
    assert rho[16] > 0.8


def test_streaming_equals_batch_formula(camera):
    images = camera["images"][:6]
    builder = FingerprintBuilder()
    for image in images:
        builder.add(image)
    pairs = [region_residual_and_intensity(img, "full", 3.0) for img in images]
    w = np.stack([p[0] for p in pairs]).astype(np.float64)
    i = np.stack([p[1] for p in pairs]).astype(np.float64)
    batch = (w * i).sum(axis=0) / (i * i).sum(axis=0)
    # float32 products summed in float64 vs all-float64: relative rounding ~1e-7
    np.testing.assert_allclose(builder.raw_estimate(), batch, rtol=1e-5, atol=1e-7 * np.abs(batch).max())
    np.testing.assert_allclose(builder.result().K, postprocess(batch, "full", SHAPE), atol=1e-5 * np.abs(batch).max())


def test_build_fingerprint_streams_an_iterable(camera):
    images = camera["images"][:3]
    fp_gen = build_fingerprint((img for img in images), sources=["a", "b", "c"])
    builder = FingerprintBuilder()
    for img in images:
        builder.add(img)
    np.testing.assert_array_equal(fp_gen.K, builder.result().K)
    assert fp_gen.files == ["a", "b", "c"] and fp_gen.n_images == 3

    class FrameLike:
        def __init__(self, path: str, image: np.ndarray) -> None:
            self.path, self._image = Path(path), image

        def load(self) -> np.ndarray:
            return self._image

    fp_frames = build_fingerprint([FrameLike(f"/x/{n}.png", img) for n, img in enumerate(images)])
    assert fp_frames.files == ["/x/0.png", "/x/1.png", "/x/2.png"]
    np.testing.assert_array_equal(fp_frames.K, fp_gen.K)
    with pytest.raises(UsageError):
        build_fingerprint([])


def test_saturated_pixels_are_excluded_from_numerator_and_denominator(camera):
    """Adding an image whose patch is clipped leaves K unchanged on the patch (and its dilation)."""
    images = camera["images"]
    clipped = images[0].copy()
    clipped[40:60, 70:100] = 255
    without = FingerprintBuilder()
    for img in images[1:4]:
        without.add(img)
    with_clipped = FingerprintBuilder()
    for img in [clipped, *images[1:4]]:
        with_clipped.add(img)
    mask = saturation_mask(clipped, dilate=1)
    assert mask.sum() == 22 * 32  # the 20×30 patch grown by one pixel on each side
    np.testing.assert_array_equal(with_clipped.raw_estimate()[mask], without.raw_estimate()[mask])
    # ...but the clipped image does contribute elsewhere
    assert not np.array_equal(with_clipped.raw_estimate()[~mask], without.raw_estimate()[~mask])


def test_always_saturated_pixels_give_zero():
    rng = np.random.default_rng(9)
    img = rng.integers(50, 200, (64, 64), dtype=np.uint8)
    img[10:20, 10:20] = 255
    builder = FingerprintBuilder(saturation_dilate=0)
    builder.add(img)
    builder.add(img)
    assert np.all(builder.raw_estimate()[10:20, 10:20] == 0)


def test_saturation_mask_and_intensity():
    img = np.full((10, 12, 3), 100, np.uint8)
    img[4, 5, 2] = 255  # one channel clipped is enough
    assert saturation_mask(img, dilate=0).sum() == 1
    assert saturation_mask(img, dilate=1).sum() == 9
    assert saturation_mask(img.astype(np.uint16), level=255, dilate=0).sum() == 1
    grey = np.array([[0.0, 100.0, 252.0, 255.0]], np.float32)
    out = intensity(grey, 255.0, rolloff=True)
    assert out[0, 1] == 100 and out[0, 2] == pytest.approx(252)
    assert out[0, 3] == pytest.approx(252 * np.exp(-9 / 6))  # the reference's roll-off
    assert intensity(grey, 255.0, black_level=10.0, rolloff=False)[0, 1] == 90
    np.testing.assert_array_equal(grey, [[0, 100, 252, 255]])  # not modified


def test_per_cfa_black_level_on_a_mosaic():
    mosaic = np.full((8, 8), 300.0, np.float32)
    out = intensity(mosaic, 4095.0, black_level=(10, 20, 30, 40), rolloff=False)
    np.testing.assert_array_equal(out[:2, :2], [[290, 280], [270, 260]])


def test_frames_of_another_size_are_refused(camera):
    builder = FingerprintBuilder()
    builder.add(camera["images"][0])
    with pytest.raises(InputError, match="rotated"):
        builder.add(np.ascontiguousarray(camera["images"][1].T))
    with pytest.raises(InputError):
        builder.add(camera["images"][1].astype(np.uint16))
    with pytest.raises(UsageError):
        FingerprintBuilder().result()


def test_inputs_are_not_modified(camera):
    image = camera["images"][0].copy()
    image.flags.writeable = False
    builder = FingerprintBuilder(region="corners:32")
    builder.add(image)
    np.testing.assert_array_equal(image, camera["images"][0])


@pytest.mark.parametrize("spec, shape", [("center:64", (64, 64)), ("corners:32", (64, 64)), ("full", SHAPE)])
def test_regions_give_the_region_shape(camera, spec, shape):
    fp = build_fingerprint(camera["images"][:4], region=spec)
    assert fp.K.shape == shape and fp.shape == shape and fp.K.dtype == np.float32
    assert fp.frame_shape == SHAPE and fp.region == parse_region(spec).spec
    # the fingerprint of a region is the fingerprint of those pixels
    truth = parse_region(spec).extract(camera["k"])
    assert corr(fp.K, truth) > 0.5


def test_memory_does_not_grow_with_the_number_of_images(camera):
    """Peak traced memory while adding 12 images is that of adding 3 (±10 %)."""
    images = camera["images"]

    def peak(n: int) -> int:
        builder = FingerprintBuilder(workers=1)
        builder.add(images[0])
        tracemalloc.start()
        for j in range(n):
            builder.add(images[1 + j % 15])
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        return top

    assert peak(12) <= 1.1 * peak(3)


# ----------------------------------------------------------------------------- persistence


def test_save_load_round_trip(camera, tmp_path):
    fp = build_fingerprint(camera["images"][:3], region="center:64", sources=["x/1.jpg", "x/2.jpg", "x/3.jpg"])
    path = fp.save(tmp_path / "cam.npz")
    back = Fingerprint.load(path)
    np.testing.assert_array_equal(back.K, fp.K)
    assert back.to_dict() == fp.to_dict()
    assert back.files == ["x/1.jpg", "x/2.jpg", "x/3.jpg"] and back.n_images == 3
    assert back.frame_shape == SHAPE and back.region == "center:64" and back.sigma == 3.0
    assert back.parameters["residual"]["wavelet"] == "db4"
    json.dumps(back.to_dict())  # JSON-ready
    with pytest.raises(UsageError):
        fp.save(path)  # exists
    fp.save(path, force=True)
    assert [p.name for p in tmp_path.iterdir()] == ["cam.npz"]  # no temporary left behind


def test_load_rejects_other_files(tmp_path):
    with pytest.raises(InputError):
        Fingerprint.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(InputError):
        Fingerprint.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, K=np.zeros((4, 4)))
    with pytest.raises(InputError):
        Fingerprint.load(other)


def test_region_is_a_value():
    assert Region("center", (32, 32)) == parse_region("center:32")
    assert str(parse_region("corners")) == "corners:128"


# ----------------------------------------------------------------------------- damaged files and content (issue 26)


def _meta_file(path: Path, source: Path, **changes) -> Path:
    with np.load(source) as data:
        k, meta = data["K"], json.loads(str(data["meta"][()]))
    for key, value in changes.items():
        if value is ...:
            del meta[key]
        else:
            meta[key] = value
    np.savez(path, K=k, meta=np.array(json.dumps(meta)))
    return path


@pytest.mark.parametrize("damage, message", [
    ("half", "damaged one"), ("head", "damaged one"), ("crc", "damaged one"),
    ("missing frame_shape", "metadata key 'frame_shape' is missing"),
    ("missing region", "metadata key 'region' is missing"),
    ("frame_shape 5", "metadata 'frame_shape' is 5, not two positive whole numbers"),
    ("sigma text", "metadata 'sigma' is 'abc', not a positive number"),
    ("files number", "metadata 'files' is 3, not a list of names"),
    ("meta list", "its metadata is a JSON list"), ("npy", "a single array"), ("no K", "no 'K' in the file"),
    ("shape", "K has shape"),
])
def test_damaged_fingerprint_files_give_one_line_errors(camera, tmp_path, damage, message):
    """D20: truncated or corrupted .npz files and metadata missing a key or of the wrong type are an InputError
    naming the file (never a traceback from zipfile, EOF, KeyError or TypeError)."""
    good = build_fingerprint(camera["images"][:2], region="center:64").save(tmp_path / "good.npz")
    raw = good.read_bytes()
    bad = tmp_path / "bad.npz"
    if damage == "half":
        bad.write_bytes(raw[: len(raw) // 2])
    elif damage == "head":
        bad.write_bytes(raw[:40])
    elif damage == "crc":  # a byte of K's data flipped: the zip's CRC fails
        data = bytearray(raw)
        data[len(data) // 3] ^= 0xFF
        bad.write_bytes(bytes(data))
    elif damage.startswith("missing"):
        _meta_file(bad, good, **{damage.split()[1]: ...})
    elif damage == "frame_shape 5":
        _meta_file(bad, good, frame_shape=5)
    elif damage == "sigma text":
        _meta_file(bad, good, sigma="abc")
    elif damage == "files number":
        _meta_file(bad, good, files=3)
    elif damage == "shape":
        _meta_file(bad, good, shape=[32, 32])
    elif damage == "meta list":
        np.savez(bad, K=np.zeros((64, 64), np.float32), meta=np.array("[1, 2]"))
    elif damage == "npy":
        with open(bad, "wb") as handle:
            np.save(handle, np.zeros(3))
    else:
        np.savez(bad, meta=np.array("{}"))
    with pytest.raises(InputError, match=message) as info:
        Fingerprint.load(bad)
    assert str(info.value).startswith(str(bad)) and "\n" not in str(info.value)


@pytest.mark.parametrize("bad", ["nan", "inf", "constant"])
def test_fingerprints_without_a_usable_pattern_are_refused_on_load(camera, tmp_path, bad):
    """D20: a non-finite or constant K cannot be read back as a fingerprint (so it is never matched)."""
    fp = build_fingerprint(camera["images"][:2], region="center:64")
    fp.K[:] = {"nan": np.nan, "inf": np.inf, "constant": 0.0}[bad]
    fp.save(tmp_path / "k.npz")
    with pytest.raises(InputError, match="k.npz: K (holds 4096 NaN or infinite|is constant)"):
        Fingerprint.load(tmp_path / "k.npz")


def _black_with_hot_pixels(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A black frame whose only exposed pixels are 30 hot pixels (the D06 case)."""
    frame = np.zeros(shape, np.uint8)
    frame.flat[np.random.default_rng(7).choice(frame.size, 30, replace=False)] = rng.integers(30, 60, 30)
    return frame


def test_content_free_frames_are_left_out_of_a_fingerprint(camera):
    """D06: black, saturated and constant frames among good ones are excluded (listed with why), and the
    fingerprint is exactly the one of the good frames alone; their order among the chunks does not matter."""
    rng = np.random.default_rng(3)
    good = camera["images"][:10]
    junk = [_black_with_hot_pixels(rng, SHAPE), np.full(SHAPE, 255, np.uint8), np.full(SHAPE, 90, np.uint8)]
    mixed = good[:4] + junk[:1] + good[4:7] + junk[1:] + good[7:]
    names = [f"f{i}.png" for i in range(len(mixed))]
    fp = build_fingerprint(mixed, sources=names)
    clean = build_fingerprint(good)
    assert fp.n_images == 10 and fp.files == [n for n, im in zip(names, mixed) if any(im is g for g in good)]
    excluded = fp.parameters["excluded_frames"]
    assert [e["file"] for e in excluded] == ["f4.png", "f8.png", "f9.png"]
    assert "mostly black" in excluded[0]["reason"] and "all saturated" in excluded[1]["reason"]
    assert "constant: every pixel is 90" in excluded[2]["reason"]
    # summed in other chunks than the clean build, so equal to rounding (same images, same weights)
    np.testing.assert_allclose(fp.K, clean.K, rtol=0, atol=1e-6 * float(np.abs(clean.K).max()))
    # streamed image by image and built in chunks: the same bits, skipped frames included
    streamed = build_fingerprint(iter(mixed), sources=names)
    np.testing.assert_array_equal(streamed.K, fp.K)
    assert streamed.parameters["excluded_frames"] == excluded


def test_a_set_of_content_free_frames_is_refused(camera):
    """D06: a fingerprint of all-black frames (or of black frames with a few hot pixels) is refused with the
    set's name and why, instead of 'matching' other black frames at PCE 10⁴."""
    rng = np.random.default_rng(4)
    with pytest.raises(InputError, match=r"black set: all 9 frame\(s\) given for the fingerprint are content-free, "
                                         r".*mostly black"):
        build_fingerprint([_black_with_hot_pixels(rng, SHAPE) for _ in range(9)], name="black set")
    with pytest.raises(InputError, match=r"all 3 frame\(s\).*all black"):
        build_fingerprint(iter([np.zeros(SHAPE, np.uint8)] * 3))
