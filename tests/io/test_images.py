"""Image I/O: round trips for every format and bit depth, metadata, raw mosaics, bad files."""
from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest

from forensics.fixtures.dng import write_dng
from forensics._shared.errors import InputError, UsageError
from forensics.io.images import read_image, read_info, read_raw, write_image


def _oiio_write(path, image, extra=None):
    """Write with OpenImageIO directly (formats forensics only reads: JPEG, BMP)."""
    channels = 1 if image.ndim == 2 else image.shape[2]
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], channels, image.dtype.name)
    for k, v in (extra or {}).items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(image.reshape(image.shape[0], image.shape[1], channels))
    out.close()


@pytest.mark.parametrize("ext", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3])
def test_lossless_round_trip(tmp_path, ext, dtype, channels):
    rng = np.random.default_rng(1)
    shape = (37, 53) if channels == 1 else (37, 53, 3)
    image = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    path = write_image(tmp_path / f"img{ext}", image)
    back = read_image(path)
    assert back.dtype == dtype and back.shape == shape
    np.testing.assert_array_equal(back, image)
    info = read_info(path)
    assert (info.width, info.height, info.channels, info.dtype) == (53, 37, channels, np.dtype(dtype))


@pytest.mark.parametrize("channels", [1, 3])
def test_bmp_round_trip(tmp_path, channels):
    rng = np.random.default_rng(2)
    shape = (20, 24) if channels == 1 else (20, 24, 3)
    image = rng.integers(0, 256, shape).astype(np.uint8)
    _oiio_write(tmp_path / "a.bmp", image)
    back = read_image(tmp_path / "a.bmp")
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back.reshape(image.shape) if back.ndim == image.ndim else back[..., 0], image)


def test_jpeg_read_keeps_uint8_and_metadata(tmp_path):
    yy, xx = np.mgrid[0:64, 0:96]
    image = np.stack([(xx * 2) % 256, (yy * 3) % 256, ((xx + yy) * 2) % 256], axis=2).astype(np.uint8)
    meta = {"Exif:DateTimeOriginal": "2011:03:04 05:06:07", "ExposureTime": 0.01, "Make": "ACME", "Model": "X1",
            "Exif:PhotographicSensitivity": 400, "Exif:BodySerialNumber": "SN123", "Compression": "jpeg:100"}
    _oiio_write(tmp_path / "a.jpg", image, meta)
    back = read_image(tmp_path / "a.jpg")
    assert back.dtype == np.uint8 and back.shape == image.shape
    # quality 100 JPEG of a smooth image: errors of a few DN at most (chroma subsampling included)
    assert np.abs(back.astype(int) - image).mean() < 3
    info = read_info(tmp_path / "a.jpg")
    assert info.captured is not None and info.captured.year == 2011 and info.captured.second == 7
    assert info.exposure_s == pytest.approx(0.01, rel=1e-3)  # EXIF stores a rational approximation
    assert info.make == "ACME" and info.model == "X1"
    assert info.iso == 400 and info.serial == "SN123"


def test_real_nikon_jpeg_metadata():
    from conftest import dresden_or_skip

    path = sorted((dresden_or_skip() / "natural").glob("Nikon_D70_0_*.JPG"))[0]
    info = read_info(path)
    assert info.make.startswith("NIKON") and info.model == "NIKON D70"
    assert info.captured is not None and info.exposure_s and info.exposure_s > 0
    assert read_image(path).dtype == np.uint8


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "BGGR", "GBRG"])
def test_raw_mosaic_through_rawpy(tmp_path, pattern):
    rng = np.random.default_rng(3)
    mosaic = rng.integers(64, 4096, (48, 64)).astype(np.uint16)
    path = write_dng(tmp_path / "frame.dng", mosaic, cfa_pattern=pattern, black_level=64, white_level=4095)
    raw = read_raw(path)
    np.testing.assert_array_equal(raw.mosaic, mosaic)
    assert raw.cfa_pattern == pattern
    assert raw.black_level == (64.0,) * 4 and raw.white_level == 4095
    assert raw.info.captured is not None and raw.info.captured.year == 2012
    np.testing.assert_array_equal(read_image(path), mosaic)


def test_write_is_atomic_and_refuses_overwrite(tmp_path):
    image = np.zeros((4, 4), np.uint8)
    path = write_image(tmp_path / "a.png", image)
    with pytest.raises(UsageError, match="already exists"):
        write_image(path, image + 1)
    assert read_image(path).max() == 0
    write_image(path, image + 1, force=True)
    assert read_image(path).max() == 1
    with pytest.raises(UsageError, match="input"):
        write_image(path, image, force=True, inputs=(path,))
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary files left behind


def test_write_rejects_unsupported(tmp_path):
    with pytest.raises(InputError, match="uint8 or uint16"):
        write_image(tmp_path / "a.png", np.zeros((4, 4), np.float64))
    with pytest.raises(InputError, match=r"\.png or \.tif"):
        write_image(tmp_path / "a.jpg", np.zeros((4, 4), np.uint8))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("ext", [".png", ".tif", ".jpg"])
def test_truncated_or_corrupt_files_name_the_file(tmp_path, ext):
    image = np.random.default_rng(4).integers(0, 255, (64, 64, 3)).astype(np.uint8)
    good = tmp_path / f"good{ext}"
    if ext == ".jpg":
        _oiio_write(good, image)
    else:
        write_image(good, image)
    data = good.read_bytes()
    bad = tmp_path / f"bad{ext}"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="bad") as err:
        read_image(bad)
    assert "\n" not in str(err.value)
    garbage = tmp_path / f"garbage{ext}"
    garbage.write_bytes(b"not an image at all" * 10)
    with pytest.raises(InputError, match="garbage"):
        read_image(garbage)
    with pytest.raises(InputError, match="does not exist"):
        read_image(tmp_path / f"missing{ext}")
