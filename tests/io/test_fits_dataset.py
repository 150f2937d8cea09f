"""A folder of FITS frames as a dataset: the headers are its manifest (conditions, frame type as subject, device),
a manifest still overrides, compressed and multi-extension files are listed, a bad frame is named."""
from __future__ import annotations

import numpy as np
import pytest

fits = pytest.importorskip("astropy.io.fits")

from forensics._shared.errors import InputError  # noqa: E402
from forensics.io.dataset import DARK_SUBJECT, open_dataset  # noqa: E402
from forensics.io.describe import summarize_dataset  # noqa: E402


def _hdu(kind: str, exposure: float, measured: float, setpoint: float, *, serial: str | None = "12345",
         value: int = 1000) -> fits.PrimaryHDU:
    hdu = fits.PrimaryHDU(np.full((8, 10), value, np.uint16))
    hdu.header.update({"IMAGETYP": kind, "EXPTIME": exposure, "CCD-TEMP": measured, "SET-TEMP": setpoint,
                       "INSTRUME": "SBIG STL-1001E", "DATE-OBS": "2017-09-08T21:18:13.698", "EGAIN": 2.06})
    if serial:
        hdu.header["SERIALNO"] = serial
    return hdu


@pytest.fixture
def folder(tmp_path):
    root = tmp_path / "ccd"
    root.mkdir()
    _hdu("Bias Frame", 0.0, -10.1, -10.0).writeto(root / "a-bias.fits")
    _hdu("Dark Frame", 60.0, -4.9, -5.0).writeto(root / "b-dark.fit")
    _hdu("Dark Frame", 60.0, -2.5, -5.0).writeto(root / "c-dark-unsettled.fits")  # 2.5 °C off its set point
    _hdu("Flat Field", 23.0, -5.0, -5.0).writeto(root / "d-flat.fts")
    fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(np.full((8, 10), 1200, np.uint16),
                                                        header=_hdu("Light Frame", 5.0, -5.0, -5.0).header)]
                 ).writeto(root / "e-light.fits.fz")
    return root


def test_headers_are_the_manifest(folder):
    ds = open_dataset(folder)
    assert not ds.has_manifest and [f.file for f in ds] == ["a-bias.fits", "b-dark.fit", "c-dark-unsettled.fits",
                                                             "d-flat.fts", "e-light.fits.fz"]
    by_name = {f.file: f for f in ds}
    bias, dark, flat, light = (by_name[n] for n in ("a-bias.fits", "b-dark.fit", "d-flat.fts", "e-light.fits.fz"))
    # the frame type as the subject convention: frames taken without light are 'dark' (a bias is exposure 0)
    assert (bias.subject, dark.subject, flat.subject, light.subject) == (DARK_SUBJECT, DARK_SUBJECT, "flat", "light")
    assert [f.get("frame_type") for f in (bias, dark, flat, light)] == ["bias", "dark", "flat", "light"]
    assert bias.exposure_s == 0.0 and dark.exposure_s == 60.0
    # the measured temperature is the condition; the set point is kept beside it
    assert dark.temperature_c == pytest.approx(-4.9) and float(dark.get("set_temperature_c")) == -5.0
    assert float(dark.get("gain_e_per_adu")) == pytest.approx(2.06)
    assert ds.devices() == ["SBIG STL-1001E #12345"]
    assert bias.captured == pytest.approx(2017 + (250 + (21 + 18 / 60) / 24) / 365, abs=1e-4)
    assert light.load().dtype == np.uint16 and int(light.load()[0, 0]) == 1200  # the compressed extension


def test_grouping_by_condition_sees_the_header_values(folder):
    conditions = open_dataset(folder).conditions()
    # the condition is the set point; the thermistor's -10.1 °C is a reading around it
    assert (0.0, None, -10.0, DARK_SUBJECT) in conditions
    assert sum(len(v) for v in conditions.values()) == 5


def test_readings_around_one_set_point_are_one_condition(tmp_path):
    """A cooled CCD's thermistor reads in steps around its set point (the 2017 STL-1001E: -10.20 and -9.79 °C);
    counting each reading as a condition made `info` report 19 conditions for a series taken at 2 set points."""
    root = tmp_path / "ccd"
    root.mkdir()
    for i, measured in enumerate((-10.20, -9.79, -10.20)):
        _hdu("Dark Frame", 60.0, measured, -10.0).writeto(root / f"dark{i}.fits")
    _hdu("Dark Frame", 60.0, -5.2, -5.0).writeto(root / "dark-warm.fits")
    conditions = open_dataset(root).conditions()
    assert {k: len(v) for k, v in conditions.items()} == {(60.0, None, -10.0, DARK_SUBJECT): 3,
                                                          (60.0, None, -5.0, DARK_SUBJECT): 1}


def test_info_lists_conditions_and_frames_off_their_set_point(folder):
    rows = summarize_dataset(open_dataset(folder)).frame_types
    darks = [r for r in rows if r["frame_type"] == "dark"]
    assert len(darks) == 1 and darks[0]["n"] == 2 and darks[0]["set_temperature_c"] == -5.0
    assert darks[0]["off_set_point"] == ["c-dark-unsettled.fits"]  # 2.5 °C off: named; 0.1 °C off: not
    assert darks[0]["temperature_c"] == [pytest.approx(-4.9), pytest.approx(-2.5)]
    assert {r["frame_type"] for r in rows} == {"bias", "dark", "flat", "light"}


def test_a_manifest_overrides_the_headers(folder):
    (folder / "manifest.csv").write_text(
        "file,device,subject,temperature_c,frame_type\n"
        "a-bias.fits,camera-7,,,\n"
        "b-dark.fit,,light,-20,\n"
        "d-flat.fts,,,,light\n")
    ds = open_dataset(folder)
    frames = {f.file: f for f in ds}
    assert frames["a-bias.fits"].device == "camera-7" and frames["a-bias.fits"].subject == DARK_SUBJECT
    assert frames["b-dark.fit"].subject == "light" and frames["b-dark.fit"].temperature_c == -20.0
    assert frames["b-dark.fit"].device == "SBIG STL-1001E #12345"  # not given: from the header
    assert frames["d-flat.fts"].get("frame_type") == "light"
    # filled before grouping: the bias's header set point; the dark's manifest temperature (its header set point
    # of -5 °C belongs to the header's temperature, which the manifest replaced)
    assert {(0.0, None, -10.0, DARK_SUBJECT), (60.0, None, -20.0, "light")} <= set(ds.conditions())


def test_device_without_a_serial_is_the_instrument(tmp_path):
    _hdu("Dark Frame", 10.0, -10.0, -10.0, serial=None).writeto(tmp_path / "d.fits")
    assert open_dataset(tmp_path).devices() == ["SBIG STL-1001E"]


def test_a_bad_frame_in_a_folder_is_named_in_one_line(folder):
    (folder / "f-broken.fits").write_bytes((folder / "b-dark.fit").read_bytes()[:2880])  # header, no data
    with pytest.raises(InputError) as err:
        [f.load() for f in open_dataset(folder)]
    assert "f-broken.fits" in str(err.value) and "\n" not in str(err.value)
    (folder / "f-broken.fits").write_bytes(b"SIMPLE  = nonsense" + b" " * 100)
    with pytest.raises(InputError) as err:
        open_dataset(folder)
    assert "f-broken.fits" in str(err.value) and "\n" not in str(err.value)


def test_a_header_that_contradicts_its_data_is_refused_in_one_line(tmp_path, cli):
    path = tmp_path / "dark.fits"
    _hdu("Dark Frame", 60.0, -5.0, -5.0).writeto(path)
    raw = path.read_bytes()
    card = b"NAXIS2  =                    8"
    assert raw.count(card) == 1
    lying = tmp_path / "lying.fits"  # the header claims 800 rows (16 kB, past the file's 2880-byte data block)
    lying.write_bytes(raw.replace(card, b"NAXIS2  =                  800"))
    code, out, err = cli("info", str(tmp_path / "lying.fits"))
    assert code == 0 and "800" in out  # the header alone is read: it describes what it claims
    (tmp_path / "dark.fits").unlink()
    code, _, err = cli("defects", "detect", str(tmp_path), "--workers", "1", "--quiet")
    assert code == 3 and "lying.fits" in err and len(err.strip().splitlines()) == 1


def test_a_set_point_that_is_not_a_number_is_a_label(tmp_path):
    """A manifest may write any text in an extra column: a set point like 'cooled' leaves the measured temperature
    as the condition, and info's frame table lists it without a set point instead of failing."""
    root = tmp_path / "ccd"
    root.mkdir()
    _hdu("Dark Frame", 60.0, -9.8, -10.0).writeto(root / "dark.fits")
    (root / "manifest.csv").write_text("file,set_temperature_c\ndark.fits,cooled\n")
    ds = open_dataset(root)
    assert list(ds.conditions()) == [(60.0, None, pytest.approx(-9.8), DARK_SUBJECT)]
    rows = summarize_dataset(ds).frame_types
    assert [(r["frame_type"], r["set_temperature_c"], r["n"]) for r in rows] == [("dark", None, 1)]


def test_info_names_a_truncated_frame_that_every_pixel_reader_refuses(folder, cli):
    """A frame cut short (an interrupted copy) has a whole header: ``info`` used to list the folder as sound while
    every command reading pixels stopped on the file.  ``info`` now names it (its header is still described, the
    sound frames are not named), and reading its pixels still stops with one line naming it."""
    (folder / "e-light.fits.fz").unlink()  # only uncompressed frames: the dark series below
    whole = (folder / "b-dark.fit").read_bytes()
    (folder / "g-cut.fits").write_bytes(whole[: len(whole) - 1500])  # its data block, 1500 bytes short
    summary = summarize_dataset(open_dataset(folder))
    assert len(summary.unreadable) == 1 and "g-cut.fits" in summary.unreadable[0]
    assert "truncated" in summary.unreadable[0]
    code, out, _ = cli("info", str(folder))
    assert code == 0 and "unreadable:" in out and "g-cut.fits" in out
    with pytest.raises(InputError, match="g-cut.fits: cannot read the image data") as err:
        [frame.load() for frame in open_dataset(folder)]
    assert "\n" not in str(err.value)


def test_info_groups_frames_without_a_set_point_as_detect_does(tmp_path, cli):
    """Without SET-TEMP, biases and darks at −10 and −5 °C were one row per exposure spanning both temperatures
    ("bias 0 ? 20 −10.10 … −4.85"); info now groups them by the clusters of measured temperature that
    ``defects detect`` uses (one function, :func:`forensics.io.dataset.temperature_groups`): the same groups."""
    from forensics.defects.darkdetect import series_frames
    from forensics.defects.darkseries import plan_series
    from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series

    design = DarkSeriesDesign(shape=(8, 10), exposures=(10.0, 60.0), n_bias=3, set_temp_header=False,
                              temperature_wander=0.1)
    make_dark_series(tmp_path, 0, design)
    ds = open_dataset(tmp_path)
    rows = summarize_dataset(ds).frame_types
    centres = sorted({r["measured_c"] for r in rows})
    # a cluster's centre is its readings' median: within 4 wanders (0.4 °C) of the set point it was taken at
    assert len(centres) == 2 and abs(centres[0] + 10.0) < 0.4 and abs(centres[1] + 5.0) < 0.4
    got = {(r["frame_type"], r["exposure_s"], r["measured_c"]): r["n"] for r in rows}
    assert got == {(kind, t, c): (3 if kind == "bias" else 1)
                   for c in centres for kind, t in (("bias", 0.0), ("dark", 10.0), ("dark", 60.0))}
    assert all(r["set_temperature_c"] is None and r["temperature_c"][1] - r["temperature_c"][0] < 1.0 for r in rows)
    plan = plan_series(series_frames(ds))
    assert sorted(plan.label(g) for g in range(len(plan.groups))) == [f"measured {c:+.1f} °C" for c in centres]
    code, out, _ = cli("info", str(tmp_path))
    assert code == 0 and all(out.count(f"measured {c:+.1f}") == 3 for c in centres)


def test_binning_from_the_header_or_the_manifest(tmp_path):
    """XBINNING/YBINNING become the column ``binning`` (a manifest may give it: ``2x2`` or ``2``); a frame that states
    none is unknown and mixes with any; two stated binnings refuse the dataset naming a frame of each."""
    from forensics.io.dataset import binning, common_binning

    root = tmp_path / "ccd"
    root.mkdir()
    for i in range(3):
        hdu = _hdu("Dark Frame", 60.0, -5.0, -5.0)
        hdu.header["XBINNING"] = hdu.header["YBINNING"] = 1
        hdu.writeto(root / f"d{i}.fits")
    _hdu("Dark Frame", 60.0, -5.0, -5.0).writeto(root / "unstated.fits")
    ds = open_dataset(root)
    assert [binning(f) for f in ds] == [(1, 1), (1, 1), (1, 1), None]
    assert ds.binning() == (1, 1) and ds.shape() == (8, 10)
    (root / "manifest.csv").write_text("file,binning\nd0.fits,\nd1.fits,2\nd2.fits,\nunstated.fits,\n")
    ds = open_dataset(root)
    with pytest.raises(InputError) as err:
        ds.shape()
    msg = str(err.value)
    assert msg.startswith(str(root / "d1.fits")) and "binned 2×2" in msg
    assert "d0.fits and 1 more frames are binned 1×1" in msg
    assert common_binning([("a", None), ("b", None)]) is None
    (root / "manifest.csv").write_text("file,binning\nd1.fits,2 by 2\n")
    with pytest.raises(InputError, match="d1.fits: binning '2 by 2' is not a binning"):
        open_dataset(root).binning()
