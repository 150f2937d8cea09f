"""Datasets: manifest parsing, EXIF fallback, lazy iteration, grouping, and bad manifests."""
from __future__ import annotations

import numpy as np
import pytest

from forensics.io.dataset import decimal_year, from_decimal_year, open_dataset, parse_captured, write_manifest
from forensics._shared.errors import InputError
from forensics.io.images import write_image


def _folder(tmp_path, n=4, shape=(8, 10), manifest=None):
    for i in range(n):
        write_image(tmp_path / f"f{i}.png", np.full(shape, i, np.uint8))
    if manifest is not None:
        (tmp_path / "manifest.csv").write_text(manifest)
    return tmp_path


def test_captured_formats():
    assert parse_captured("2009.5") == 2009.5
    assert parse_captured("2009-07-02T12:00:00") == pytest.approx(2009.5)  # 2009 has 365 days; mid-year
    assert parse_captured("2010-01-01") == 2010.0
    assert parse_captured("2009-07-02T12:00:00Z") == pytest.approx(2009.5)
    assert parse_captured("20090702T120000") == pytest.approx(2009.5)  # ISO 8601 basic form
    assert parse_captured("20100101") == 2010.0
    assert parse_captured("1975") == 1975.0 and parse_captured("2199.99") == 2199.99  # the plausible range's ends
    for bad in ("yesterday", "2009-13-01", "12", "1974.99", "2200", "2200-01-01", "1970-01-01T00:00:00Z", "nan", "inf"):
        with pytest.raises(ValueError):
            parse_captured(bad)


def test_decimal_year_round_trip():
    for year in (2000.0, 2009.123456, 2024.999):
        assert decimal_year(from_decimal_year(year)) == pytest.approx(year, abs=1 / (366 * 86400))


def test_manifest_columns_and_extras(tmp_path):
    _folder(tmp_path, manifest="file,device,captured,exposure_s,iso,temperature_c,subject,lens\n"
                               "f0.png,camA,2009-01-01,0.01,100,20,sky,50mm\n"
                               "f1.png,camA,2013.5,0.02,200,-5,grass,35mm\n")
    ds = open_dataset(tmp_path)
    assert ds.has_manifest and len(ds) == 2
    f0, f1 = ds
    assert (f0.device, f0.captured, f0.exposure_s, f0.iso, f0.temperature_c, f0.subject) == (
        "camA", 2009.0, 0.01, 100.0, 20.0, "sky")
    assert f1.extra == {"lens": "35mm"} and f1.temperature_c == -5
    assert ds.epoch() == pytest.approx((2009.0 + 2013.5) / 2)
    assert [len(e) for e in ds.epochs()] == [1, 1]
    assert list(ds.group_by("subject")) == ["sky", "grass"]


def test_no_manifest_lists_images_in_order(tmp_path):
    _folder(tmp_path, n=3)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / ".f9.png.part").write_text("temporary")
    ds = open_dataset(tmp_path)
    assert [f.file for f in ds] == ["f0.png", "f1.png", "f2.png"]
    assert ds.shape() == (8, 10)
    assert ds[0].captured is None  # PNG without EXIF


def test_iteration_is_lazy(tmp_path, monkeypatch):
    _folder(tmp_path, n=5)
    ds = open_dataset(tmp_path)
    loaded = []
    import forensics.io.dataset as mod

    real = mod.read_image
    monkeypatch.setattr(mod, "read_image", lambda p: loaded.append(p) or real(p))
    images = ds.images()
    assert loaded == []
    first = next(images)
    assert len(loaded) == 1 and first.max() == 0


def test_missing_values_come_from_exif(tmp_path):
    from forensics.io.images import write_image as wi

    wi(tmp_path / "a.tif", np.zeros((4, 4), np.uint8), metadata={"Exif:DateTimeOriginal": "2010:07:02 12:00:00",
                                                                 "ExposureTime": 0.5})
    (tmp_path / "manifest.csv").write_text("file,iso\na.tif,800\n")
    frame = open_dataset(tmp_path)[0]
    assert frame.iso == 800 and frame.exposure_s == pytest.approx(0.5)
    assert frame.captured == pytest.approx(decimal_year(from_decimal_year(2010.5)), abs=0.003)


@pytest.mark.parametrize(
    "manifest, match",
    [
        ("name,device\nf0.png,a\n", r"no 'file' column"),
        ("file,captured\nf0.png,2009\nmissing.png,2009\n", r"line 3: file 'missing.png' does not exist"),
        ("file,captured\nf0.png,last summer\n", r"line 2: field 'captured' = 'last summer'"),
        ("file,exposure_s\nf0.png,fast\n", r"field 'exposure_s' = 'fast' is not a number"),
        ("file,iso\nf0.png,-100\n", r"field 'iso' = '-100' is out of range"),
        ("file,captured\n", r"no rows"),
    ],
)
def test_bad_manifest_names_file_line_and_field(tmp_path, manifest, match):
    _folder(tmp_path, manifest=manifest)
    with pytest.raises(InputError, match=match) as err:
        open_dataset(tmp_path)
    assert "manifest.csv" in str(err.value) and "\n" not in str(err.value)


def test_empty_folder_and_not_a_folder(tmp_path):
    with pytest.raises(InputError, match="no images found"):
        open_dataset(tmp_path)
    with pytest.raises(InputError, match="nope: does not exist"):
        open_dataset(tmp_path / "nope")
    (tmp_path / "file.png").write_bytes(b"")
    with pytest.raises(InputError, match="file.png: not a folder"):
        open_dataset(tmp_path / "file.png")


def test_mixed_sizes_name_the_odd_file(tmp_path):
    _folder(tmp_path, n=2)
    write_image(tmp_path / "f5.png", np.zeros((9, 10), np.uint8))
    with pytest.raises(InputError, match=r"f5\.png: size 10×9×1 differs from the other images. 10×8×1"):
        open_dataset(tmp_path).shape()


def test_missing_dates_name_the_field(tmp_path):
    _folder(tmp_path, manifest="file,captured\nf0.png,2009\nf1.png,\n")
    with pytest.raises(InputError, match=r"f1\.png: no capture date: the field 'captured'"):
        open_dataset(tmp_path).captured_times()


def test_write_manifest_round_trip(tmp_path):
    _folder(tmp_path, n=2)
    write_manifest(tmp_path / "manifest.csv", [{"file": "f0.png", "captured": 2001.25, "extra_col": "x"},
                                               {"file": "f1.png", "captured": 2002.0, "iso": 100.0}])
    ds = open_dataset(tmp_path)
    assert [f.captured for f in ds] == [2001.25, 2002.0]
    assert ds[0].extra["extra_col"] == "x" and ds[1].iso == 100


def test_manifest_paths_leaving_the_folder_are_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    write_image(outside / "secret.png", np.zeros((8, 10), np.uint8))
    root = tmp_path / "set"
    _folder(root, n=3)
    (root / "link.png").symlink_to(outside / "secret.png")
    rows = {"dotdot": "../outside/secret.png", "absolute": str(outside / "secret.png"), "symlink": "link.png"}
    for kind, name in rows.items():
        (root / "manifest.csv").write_text(f"file,device\nf0.png,a\n{name},a\n")
        with pytest.raises(InputError, match=r"manifest.csv, line 3: file .* outside the dataset folder.*--allow-outside"):
            open_dataset(root)
        ds = open_dataset(root, allow_outside=True)
        assert ds[1].path.resolve() == (outside / "secret.png").resolve(), kind
    # A path that only passes through '..' but ends inside stays allowed, and so do links within the folder.
    (root / "inner.png").symlink_to(root / "f2.png")
    (root / "manifest.csv").write_text("file\nf0.png\n../set/f1.png\ninner.png\n")
    assert len(open_dataset(root)) == 3


def test_cli_refuses_a_manifest_leaving_the_folder_unless_allowed(cli, tmp_path):
    root = tmp_path / "set"
    _folder(root, n=2)
    write_image(tmp_path / "elsewhere.png", np.zeros((8, 10), np.uint8))
    (root / "manifest.csv").write_text("file\nf0.png\n../elsewhere.png\n")
    code, out, err = cli("info", root)
    assert code == 3 and len(err.strip().splitlines()) == 1
    assert "line 3" in err and "--allow-outside" in err
    code, out, err = cli("info", root, "--allow-outside")
    assert code == 0 and "2 images" in out
    code, out, err = cli("simulate", "age", root, tmp_path / "aged", "--years", "0,1")
    assert code == 3 and "outside the dataset folder" in err and not (tmp_path / "aged").exists()
