"""``forensics info`` and the reading of inputs through the command line: one line and exit 3 for bad input,
untrusted text escaped on the terminal, and the adversarial cases that held up kept holding."""
from __future__ import annotations

import json
import os

import numpy as np
import OpenImageIO as oiio
import pytest

from forensics.io.images import write_image


def _set(root, n=3, shape=(8, 10), manifest=None):
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        write_image(root / f"f{i}.png", np.random.default_rng(i).integers(0, 255, shape).astype(np.uint8))
    if manifest is not None:
        (root / "manifest.csv").write_text(manifest, encoding="utf-8")
    return root


def _one_line_error(code, out, err, *needles):
    assert code == 3, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    for needle in needles:
        assert needle in err
    assert "\x1b" not in err


def test_info_on_a_path_that_does_not_exist_says_so(cli, tmp_path):
    """D21: `info nonexistent` said "not a folder"."""
    _one_line_error(*cli("info", tmp_path / "nonexistent"), "nonexistent: does not exist")


def test_info_refuses_a_pipe_given_as_the_path(cli, tmp_path):
    """D19: a FIFO given as the path is refused, not opened (which would block)."""
    os.mkfifo(tmp_path / "pipe.png")
    _one_line_error(*cli("info", tmp_path / "pipe.png"), "pipe.png: is not a regular file")


def test_info_escapes_control_characters_of_manifest_fields(cli, cli_json, tmp_path):
    """D22: file names and manifest fields with ESC sequences reached the terminal raw."""
    root = _set(tmp_path / "set", manifest="file,device,subject\nf0.png,\x1b[2J\x1b]0;owned\x07cam,sky\n")
    code, out, err = cli("info", root)
    assert code == 0, err
    assert "\x1b" not in out and "\x07" not in out
    assert "devices: \\x1b[2J\\x1b]0;owned\\x07cam" in out
    assert cli_json("info", root)["devices"] == ["\x1b[2J\x1b]0;owned\x07cam"]  # JSON keeps the value, escaped as JSON


def test_info_escapes_control_characters_of_folder_names(cli, tmp_path):
    root = _set(tmp_path / "evil\x1b[31mred")
    code, out, err = cli("info", root)
    assert code == 0, err
    assert "\x1b" not in out and "evil\\x1b[31mred: 3 images" in out


def test_info_escapes_exif_strings_of_an_image_file(cli, tmp_path):
    path = tmp_path / "a.jpg"
    spec = oiio.ImageSpec(16, 12, 3, "uint8")
    spec.attribute("Make", "ACME\x1b[8m")
    spec.attribute("Model", "X1\rFAKE")
    out_img = oiio.ImageOutput.create(str(path))
    assert out_img.open(str(path), spec) and out_img.write_image(np.zeros((12, 16, 3), np.uint8))
    out_img.close()
    code, out, err = cli("info", path)
    assert code == 0, err
    assert "\x1b" not in out and "\r" not in out
    assert "ACME\\x1b[8m" in out and "X1\\x0dFAKE" in out


def test_info_refuses_an_unterminated_quote_instead_of_counting_one_image(cli, tmp_path):
    """D09: `info` counted 1 of 11 images after a stray quote."""
    rows = "".join(f"f{i}.png,x\n" for i in range(1, 11))
    root = _set(tmp_path / "set", n=11, manifest='file,subject\nf0.png,"open\n' + rows)
    _one_line_error(*cli("info", root), "manifest.csv, line 2: a quoted field runs past the end of the line")


def test_info_refuses_a_duplicated_row(cli, tmp_path):
    """D08: every row twice was counted twice."""
    root = _set(tmp_path / "set", manifest="file\nf0.png\nf1.png\nf0.png\nf1.png\n")
    _one_line_error(*cli("info", root), "line 4: file 'f0.png' is already listed on line 2")


@pytest.mark.parametrize("manifest, needle", [
    ("file,captured\nf0.png,0001-01-01\n", "field 'captured' = '0001-01-01'"),
    ("file,temperature_c\nf0.png,-300\n", "field 'temperature_c' = '-300'"),
    ("file,black_level\nf0.png,nan\n", "field 'black_level' = 'nan'"),
    ("file,device,file\nf0.png,a,f1.png\n", "the column 'file' is named twice"),
    ("file,iso\nf0.png,fast\n", "field 'iso' = 'fast' is not a number"),  # held up: bad manifest values
])
def test_info_refuses_bad_manifest_values_in_one_line(cli, tmp_path, manifest, needle):
    """D20/D11, and the bad values that already held up."""
    _one_line_error(*cli("info", _set(tmp_path / "set", manifest=manifest)), "manifest.csv, line", needle)


def test_info_accepts_iso_basic_dates(cli_json, tmp_path):
    """D21: 20090701 was refused as a decimal year out of range."""
    summary = cli_json("info", _set(tmp_path / "set", n=2, manifest="file,captured\nf0.png,20090701\nf1.png,20100101T000000\n"))
    assert summary["captured"] == pytest.approx([2009.4959, 2010.0], abs=1e-4)


def test_info_on_a_file_name_that_is_not_utf8(cli, tmp_path):
    """D11: a non-UTF-8 file name ended in a traceback; the message itself must print."""
    root = _set(tmp_path / "set", n=1)
    os.rename(root / "f0.png", os.fsencode(root) + b"/caf\xe9.png")
    _one_line_error(*cli("info", root), "caf\\xe9.png: the path is not valid UTF-8")


def test_corrupt_images_and_mixed_sizes_are_named(cli, tmp_path):
    """Held up (keep it so): a corrupt image and a set of mixed sizes each give one line naming the file."""
    root = _set(tmp_path / "set")
    (root / "f1.png").write_bytes((root / "f1.png").read_bytes()[:40])
    _one_line_error(*cli("info", root), "f1.png")
    mixed = _set(tmp_path / "mixed")
    write_image(mixed / "odd.png", np.zeros((9, 10), np.uint8))
    _one_line_error(*cli("info", mixed), "odd.png: size 10×9×1 differs")


def test_simulate_age_accepts_rgba_sources_and_keeps_capture_dates(cli, tmp_path):
    """D18: `simulate age` on RGBA said the first image differs from itself; D23: TIFF outputs keep the
    capture dates the simulation writes (in the manifests), and carry no write date of their own."""
    from forensics.io.dataset import open_dataset
    from forensics.io.images import read_info

    src = tmp_path / "rgba"
    src.mkdir()
    for i in range(2):
        path = src / f"f{i}.png"
        spec = oiio.ImageSpec(24, 20, 4, "uint8")
        spec.alpha_channel = 3
        out = oiio.ImageOutput.create(str(path))
        pixels = np.dstack([np.full((20, 24, 3), 60 + i, np.uint8), np.full((20, 24), 128, np.uint8)])
        assert out.open(str(path), spec) and out.write_image(pixels)
        out.close()
    code, out, err = cli("simulate", "age", src, tmp_path / "aged", "--sensor", "H", "--years", "0,8", "--seed", "1",
                         "--workers", "1", "--start", "2001", "--quiet", "--json")
    assert code == 0, err
    aged = open_dataset(tmp_path / "aged" / "year_008")
    assert aged.shape() == (20, 24, 3) and list(aged.captured_times()) == [2009.0, 2009.0]
    tif_src = _set(tmp_path / "tif", n=2, shape=(20, 24))
    for p in list(tif_src.glob("*.png")):
        write_image(p.with_suffix(".tif"), np.zeros((20, 24), np.uint8))
        p.unlink()
    code, out, err = cli("simulate", "age", tif_src, tmp_path / "aged_tif", "--sensor", "H", "--years", "0,8",
                         "--seed", "1", "--workers", "1", "--start", "2001", "--quiet", "--json")
    assert code == 0, err
    aged = open_dataset(tmp_path / "aged_tif" / "year_008")
    assert [f.path.suffix for f in aged] == [".tif", ".tif"] and list(aged.captured_times()) == [2009.0, 2009.0]
    assert all(read_info(f.path).captured is None for f in aged)  # the file itself claims no date
    assert json.loads(out)["n_images"] == 2
