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


# ----------------------------------------------------------------------------- regressions of issue 26

_WRITE_UNDER_LIMITS = r"""
import os, resource, signal, sys
import numpy as np
from forensics.io.images import read_image, write_image
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # as Python does by default: a write past the limit fails (EFBIG)
folder, ext = sys.argv[1], sys.argv[2]
yy, xx = np.mgrid[0:240, 0:320]
image = ((xx * 7 + yy * 3) % 256 ^ np.random.default_rng(0).integers(0, 32, (240, 320))).astype(np.uint8)
size = os.path.getsize(write_image(os.path.join(folder, "whole" + ext), image))
failures = accepted = 0
# Every limit through the last 9 kB (the writers' final buffered flush, which no library error reports)
for limit in list(range(size - 9000, size + 1, 61)) + [size - 1]:
    target = os.path.join(folder, "cut" + ext)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
    try:
        write_image(target, image)
    except OSError as exc:
        failures += 1
        message = str(exc)
    else:
        resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
        assert np.array_equal(read_image(target), image), limit  # whatever is accepted is whole
        accepted += 1
        os.unlink(target)
    resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert sorted(os.listdir(folder)) == ["whole" + ext], (limit, os.listdir(folder))  # no temporary left
print(failures, accepted, message)
"""


@pytest.mark.parametrize("ext", [".png", ".tif"])
def test_writes_cut_short_by_a_file_size_limit_fail_whole_and_leave_nothing(tmp_path, ext):
    """D01: OpenImageIO's PNG writer returns true after a short write, and a short final flush is reported by
    no one: under every size limit below the file's size, the write must fail and leave nothing behind."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _WRITE_UNDER_LIMITS, str(tmp_path), ext], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    failures, accepted, message = run.stdout.split(" ", 2)
    assert int(failures) == 149 and int(accepted) == 0  # every limit lies below the size: every write fails
    assert f"cut{ext}" in message and "the file size limit of" in message and message.count("\n") == 1


def test_a_failed_write_in_simulate_age_never_leaves_a_truncated_image(tmp_path):
    """D01 end to end: under ``ulimit -f`` no unreadable PNG is moved into place, and the run does not pass."""
    import subprocess
    import sys

    from forensics.sensor.simulate import make_scenes

    make_scenes(tmp_path / "src", 4, (240, 320), 3)
    script = ("import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
              "resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000)); "
              "from forensics.cli.main import main; sys.exit(main(sys.argv[1:]))")
    run = subprocess.run([sys.executable, "-c", script, "simulate", "age", str(tmp_path / "src"), str(tmp_path / "out"),
                          "--sensor", "H", "--years", "0,8", "--seed", "5", "--workers", "1", "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 3 and "scene_0000.png: file too large" in run.stderr  # the file named, one line
    assert len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()
    written = [p for p in tmp_path.rglob("*.png") if "src" not in p.parts]
    for path in written:  # what a resume would keep: every image present is whole
        read_image(path)


def _rgba(dtype, alpha):
    top = np.iinfo(dtype).max
    colour = np.random.default_rng(5).integers(1, top, (12, 16, 3), endpoint=True).astype(dtype)
    return colour, np.dstack([colour, np.full((12, 16), alpha, dtype)])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("alpha_fraction", [0.0, 0.5, 1.0])
def test_alpha_is_dropped_and_colour_values_are_the_files_own(tmp_path, dtype, alpha_fraction):
    """D05: PNG stores colour unassociated with alpha; alpha 128 must not halve it, alpha 0 must not blank it."""
    alpha = round(alpha_fraction * np.iinfo(dtype).max)
    colour, rgba = _rgba(dtype, alpha)
    path = tmp_path / "rgba.png"
    spec = oiio.ImageSpec(16, 12, 4, np.dtype(dtype).name)
    spec.alpha_channel = 3
    spec.attribute("oiio:UnassociatedAlpha", 1)  # the values given are stored as they are, as PNG specifies
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(rgba)
    out.close()
    back = read_image(path)
    assert back.shape == colour.shape and back.dtype == dtype
    np.testing.assert_array_equal(back, colour)
    assert read_info(path).channels == 3  # the header agrees with the pixels (D18: "differs from itself")


def test_grey_with_alpha_reads_as_grey(tmp_path):
    grey = np.arange(12 * 16, dtype=np.uint8).reshape(12, 16)
    path = tmp_path / "ga.png"
    _oiio_write(path, np.dstack([grey, np.zeros_like(grey)]), {"oiio:UnassociatedAlpha": 1})
    np.testing.assert_array_equal(read_image(path), grey)
    assert read_info(path).shape == (12, 16)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_a_decompression_bomb_is_refused_from_its_header(tmp_path):
    """D12: a 300 kB file whose header declares 2.5 billion pixels is refused before anything is allocated.

    Big enough to pass OpenImageIO's own ratio check (at most 10,000 : 1), as a real zlib bomb (about
    1,000 : 1) does; its image data is a stub, so decoding it would fail otherwise — the pixel-limit message
    shows the header was checked first."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 50_000, 50_000, 8, 0, 0, 0, 0)  # 50,000 × 50,000 grey, 8-bit
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"prVt", bytes(300_000))
                     + _png_chunk(b"IDAT", zlib.compress(bytes(50_001))) + _png_chunk(b"IEND", b""))
    for read in (read_image, read_info):
        with pytest.raises(InputError, match=r"bomb\.png: the image has 2,500,000,000 pixels, more than the limit "
                                             r".*FORENSICS_MAX_PIXELS"):
            read(bomb)


def test_the_pixel_limit_counts_channels_and_covers_raw_files(tmp_path, monkeypatch):
    rgb = write_image(tmp_path / "rgb.png", np.zeros((48, 64, 3), np.uint8))
    dng = write_dng(tmp_path / "frame.dng", np.full((48, 64), 100, np.uint16))
    monkeypatch.setenv("FORENSICS_MAX_PIXELS", "9215")  # 48 × 64 × 3 = 9,216 values; the mosaic 3,072
    with pytest.raises(InputError, match="rgb.png: the image has 9,216 pixels"):
        read_image(rgb)
    assert read_raw(dng).mosaic.shape == (48, 64)
    monkeypatch.setenv("FORENSICS_MAX_PIXELS", "3071")
    with pytest.raises(InputError, match="frame.dng: the image has 3,072 pixels"):
        read_raw(dng)
    monkeypatch.setenv("FORENSICS_MAX_PIXELS", "9216")
    assert read_image(rgb).shape == (48, 64, 3)


@pytest.mark.parametrize("shape", [(1, 1), (1, 30), (30, 1)])
def test_frames_too_small_to_analyse_are_refused_naming_file_and_size(tmp_path, shape):
    """D21: a 1×1 frame failed deep in a filter with no file named; now its header is refused, named."""
    path = write_image(tmp_path / "tiny.png", np.zeros(shape, np.uint8))
    for read in (read_image, read_info):
        with pytest.raises(InputError, match=rf"tiny\.png: the image is {shape[1]}×{shape[0]} pixels, too small"):
            read(path)
    assert read_image(write_image(tmp_path / "two.png", np.zeros((2, 2), np.uint8))).shape == (2, 2)


_READ_CORRUPT = r"""
import sys
from forensics.io.images import read_image
from forensics._shared.errors import InputError
try:
    read_image(sys.argv[1])
except InputError as exc:
    print(exc)
"""


def test_a_corrupt_png_gives_one_line_and_no_library_chatter(tmp_path):
    """D21: libpng printed its own "libpng error: …" line on the terminal besides the tool's message."""
    import subprocess
    import sys

    good = write_image(tmp_path / "good.png", np.random.default_rng(4).integers(0, 255, (64, 64), dtype=np.uint8))
    data = bytearray(good.read_bytes())
    data[len(data) // 2] ^= 0xFF  # a flipped byte inside the image data: a CRC error while decoding
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    run = subprocess.run([sys.executable, "-c", _READ_CORRUPT, str(bad)], capture_output=True, text=True, timeout=60)
    assert run.stderr == ""  # nothing but the message itself
    assert run.stdout.count("\n") == 1 and "bad.png: cannot read the image" in run.stdout and "PNG read error" in run.stdout


def test_other_output_on_stderr_is_not_swallowed_while_reading(capfd):
    """Only libpng's own lines are dropped; anything else written to fd 2 meanwhile comes through."""
    import os

    from forensics.io.images import _quiet_native_stderr

    with _quiet_native_stderr(True):
        os.write(2, b"libpng error: IDAT: CRC error\n")
        os.write(2, b"a warning of someone else\n")
    assert capfd.readouterr().err == "a warning of someone else\n"


def test_tiffs_written_carry_no_write_date_and_tiff_datetime_is_no_capture_date(tmp_path):
    """D23: OpenImageIO stamped the write time as DateTime, later read back as the capture date."""
    plain = write_image(tmp_path / "plain.tif", np.zeros((4, 4), np.uint8))
    spec_in = oiio.ImageInput.open(str(plain))
    assert spec_in.spec().getattribute("DateTime") is None
    spec_in.close()
    assert read_info(plain).captured is None
    # DateTime is when the file was changed (Exif 2.32, tag 306): not a capture date in an ordinary image ...
    edited = write_image(tmp_path / "edited.tif", np.zeros((4, 4), np.uint8), metadata={"DateTime": "2015:01:01 00:00:00"})
    assert read_info(edited).captured is None
    # ... DateTimeOriginal is, and wins over DateTimeDigitized
    both = write_image(tmp_path / "both.tif", np.zeros((4, 4), np.uint8),
                       metadata={"Exif:DateTimeOriginal": "2011:02:03 04:05:06", "Exif:DateTimeDigitized": "2012:01:01 00:00:00",
                                 "DateTime": "2015:01:01 00:00:00"})
    assert read_info(both).captured.isoformat() == "2011-02-03T04:05:06"


def test_exif_exposure_zero_and_implausible_dates_are_unknown(tmp_path):
    """D20: EXIF writers store 0 for an unknown exposure, and reset clocks write 1970: neither is a value."""
    path = write_image(tmp_path / "a.tif", np.zeros((4, 4), np.uint8),
                       metadata={"ExposureTime": 0.0, "Exif:DateTimeOriginal": "1970:01:01 00:00:00"})
    info = read_info(path)
    assert info.exposure_s is None and info.captured is None
    path = write_image(tmp_path / "b.tif", np.zeros((4, 4), np.uint8),
                       metadata={"ExposureTime": 0.25, "Exif:DateTimeOriginal": "2011:01:01 00:00:00"})
    info = read_info(path)
    assert info.exposure_s == 0.25 and info.captured.year == 2011


def test_what_is_not_a_regular_file_is_refused_without_blocking(tmp_path):
    """D19: a pipe named like an image must not block the reader; loops, folders, NUL and long names name the file."""
    import os
    import threading

    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    outcome = []

    def read() -> None:
        try:
            read_image(fifo)
        except InputError as exc:
            outcome.append(str(exc))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(30)
    assert outcome and "pipe.png: is not a regular file" in outcome[0]
    (tmp_path / "loop.png").symlink_to(tmp_path / "loop.png")
    (tmp_path / "folder.png").mkdir()
    cases = {"loop.png": "a loop of symbolic links", "folder.png": "is a folder", "x" * 300 + ".png": "too long",
             "nul\0.png": "NUL", "missing.png": "does not exist", "frame.dng": "does not exist"}
    for name, reason in cases.items():
        with pytest.raises(InputError, match=reason) as err:
            read_image(tmp_path / name)
        assert "\n" not in str(err.value)


def test_a_file_name_that_is_not_utf8_is_refused_and_printable(tmp_path):
    """D11: a Latin-1 file name crashed in the image library, then in printing the message."""
    import os

    name = os.fsdecode(b"caf\xe9.png")
    write_image(tmp_path / "ok.png", np.zeros((4, 4), np.uint8))
    os.rename(tmp_path / "ok.png", tmp_path / name)
    with pytest.raises(InputError, match=r"caf\\xe9\.png: the path is not valid UTF-8") as err:
        read_image(tmp_path / name)
    str(err.value).encode("utf-8")  # printable on a strict UTF-8 stream
