"""The command line on a synthetic FITS dark series (fixtures.darkseries): info, defects detect/growth, date."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ccd") / "series"
    truth = make_dark_series(folder, 11, DarkSeriesDesign(n_flats=4))
    return folder, truth


def test_info_lists_the_frames_conditions(series, cli_json, cli):
    folder, _ = series
    out = cli_json("info", folder)
    assert out["devices"] == ["Simulated CCD"] and out["n_images"] == 36
    kinds = {(r["frame_type"], r["exposure_s"], r["set_temperature_c"]): r["n"] for r in out["frame_types"]}
    assert kinds[("bias", 0.0, -10.0)] == 10 and kinds[("dark", 300.0, -5.0)] == 1 and kinds[("flat", 23.0, -5.0)] == 4
    code, text, _ = cli("info", folder)
    assert code == 0 and "set point" in text and "bias" in text
    one = cli_json("info", next(folder.glob("dark*300s*.fits")))
    assert one["exposure_s"] == 300.0 and one["frame_type"] == "dark" and one["set_temperature_c"] in (-10.0, -5.0)


def test_defects_detect_on_a_dark_series(series, cli_json, cli, tmp_path):
    folder, truth = series
    law, report = tmp_path / "law.json", tmp_path / "report"
    out = cli_json("defects", "detect", folder, "--rate-threshold", "1", "--t-ref", "-10", "--save-law", law,
                   "--report", report, "--workers", "1", "--quiet")
    assert out["units"] == "ADU/s at t_ref" and out["t_ref_c"] == -10.0 and out["threshold_adu_per_s"] == 1.0
    true_hot = int((truth.rate_at(-10.0) > 1.0).sum())
    assert abs(out["hot_pixels"] - true_hot) <= 5
    assert [g["set_temperature_c"] for g in out["series"]["groups"]] == [-10.0, -5.0]
    assert json.loads(law.read_text())["format"] == "forensics-dark-law/1"
    names = {p.name for p in report.iterdir()}
    assert {"index.html", "dark_level.png", "rate_temperature.png", "rate_histogram.png", "hot_map.png"} <= names
    code, text, _ = cli("defects", "detect", folder, "--rate-threshold", "1", "--t-ref", "-10", "--workers", "1",
                        "--quiet")
    assert code == 0 and "hot pixels:" in text and "T_d" in text


def _linked(folder: Path, to: Path) -> Path:
    """A folder of links to every FITS frame of ``folder`` (frames can then be replaced without touching it)."""
    to.mkdir()
    for path in folder.glob("*.fits"):
        (to / path.name).symlink_to(path)
    return to


def test_single_temperature_series_needs_a_law(series, cli, cli_json, tmp_path):
    folder, _ = series
    warm = tmp_path / "warm"
    warm.mkdir()
    for path in folder.glob("*-05.0C-*.fits"):
        if not path.name.startswith("flat"):
            (warm / path.name).symlink_to(path)
    code, _, err = cli("defects", "detect", warm, "--rate-threshold", "1", "--t-ref", "-10", "--workers", "1")
    assert code == 3 and "temperature law" in err and err.count("\n") <= 2
    out = cli_json("defects", "detect", warm, "--rate-threshold", "1", "--t-ref", "-10", "--doubling", "6",
                   "--workers", "1", "--quiet")
    assert out["law"]["bulk"]["doubling_c"] == 6.0


def test_growth_and_dating_from_dark_series(tmp_path, cli_json):
    design = replace(DarkSeriesDesign(), setpoints=(-10.0,), hot_fraction=0.02, n_bias=6)
    base = None
    folders = []
    for epoch, (start, new) in enumerate([("2017-09-08T20:00:00", 0), ("2019-09-08T20:00:00", 120),
                                          ("2021-09-08T20:00:00", 120)]):
        folder = tmp_path / f"epoch{epoch}"
        base = make_dark_series(folder, 200 + epoch, replace(design, start=start), sensor=base, new_hot=new)
        folders.append(folder)
    model = tmp_path / "model.json"
    growth = cli_json("defects", "growth", folders[0], folders[1], "-o", model, "--rate-threshold", "1",
                      "--t-ref", "-10", "--doubling", "5", "--workers", "1", "--quiet")
    assert growth["threshold"]["units"] == "ADU/s" and growth["partial"]["new_per_interval"][0] > 80
    dated = cli_json("date", folders[2], "--model", model, "--workers", "1", "--quiet")
    assert dated["interval"][0] <= 2021.69 <= (dated["interval"][1] or 1e9)
    frame = next(folders[1].glob("dark*300s*.fits"))
    single = cli_json("date", frame, "--model", model, "--workers", "1", "--quiet")
    assert single["query"] == "image" and single["n_defects"] > 0


def test_bad_fits_in_a_series_is_named(series, cli, tmp_path):
    folder, _ = series
    broken = _linked(folder, tmp_path / "broken")
    victim = sorted(folder.glob("dark*.fits"))[0]
    (broken / victim.name).unlink()
    (broken / victim.name).write_bytes(victim.read_bytes()[:5000])  # truncated
    code, _, err = cli("defects", "detect", broken, "--rate-threshold", "1", "--workers", "1")
    assert code == 3 and victim.name in err


def test_manifest_accepts_bias_exposure_zero(series, cli_json, tmp_path):
    folder, _ = series
    rows = ["file,exposure_s,subject"]
    for path in sorted(folder.glob("bias*.fits"))[:3]:
        rows.append(f"{path},0,dark")
    (tmp_path / "manifest.csv").write_text("\n".join(rows) + "\n")
    out = cli_json("info", tmp_path, "--allow-outside")
    assert out["n_images"] == 3 and out["conditions"][0]["exposure_s"] == 0.0


def test_a_law_of_another_binning_is_refused(series, cli, cli_json, tmp_path):
    """A law saved from unbinned frames (XBINNING 1) is refused on a 2×2-binned series, in one line naming the law
    file and both binnings (a binned pixel sums four pixels' dark charge: the law's rate classes mean other
    pixels); a law file written before the binning was kept still loads, with a warning that it cannot be checked;
    one --doubling holds at any binning."""
    folder, _ = series
    law = tmp_path / "law.json"
    cli_json("defects", "detect", folder, "--rate-threshold", "1", "--t-ref", "-10", "--save-law", law,
             "--workers", "1", "--quiet")
    assert json.loads(law.read_text())["binning"] == [1, 1]
    binned = tmp_path / "binned"
    make_dark_series(binned, 12, DarkSeriesDesign(shape=(32, 48), setpoints=(-5.0,), binning=2))
    code, _, err = cli("defects", "detect", binned, "--rate-threshold", "1", "--t-ref", "-10", "--law", law,
                       "--workers", "1")
    assert code == 3 and len(err.strip().splitlines()) == 1
    assert str(law) in err and "1×1" in err and "2×2" in err
    old = tmp_path / "old-law.json"
    obj = json.loads(law.read_text())
    del obj["binning"]
    old.write_text(json.dumps(obj))
    code, _, err = cli("defects", "detect", binned, "--rate-threshold", "1", "--t-ref", "-10", "--law", old,
                       "--workers", "1", "--quiet")
    assert code == 0 and "cannot check that the law was fitted on frames of this binning" in err
    code, _, err = cli("defects", "detect", binned, "--rate-threshold", "1", "--t-ref", "-10", "--doubling", "6",
                       "--workers", "1", "--quiet")
    assert code == 0 and "binning" not in err


def test_a_series_mixing_binnings_is_refused(series, cli, tmp_path):
    folder, _ = series
    mixed = _linked(folder, tmp_path / "mixed")
    from astropy.io import fits

    odd = sorted(mixed.glob("dark*.fits"))[0]
    with fits.open(odd.resolve()) as h:
        data, header = h[0].data.copy(), h[0].header.copy()
    header["XBINNING"] = header["YBINNING"] = 2
    odd.unlink()
    fits.PrimaryHDU(data, header).writeto(odd)  # same size, another binning (a sub-frame binned on the chip)
    fp = tmp_path / "fp.npz"
    for command in (("info", mixed), ("defects", "detect", mixed), ("model", "check", mixed),
                    ("fingerprint", "build", mixed, "-o", fp)):
        code, _, err = cli(*command, "--quiet")
        assert code == 3 and len(err.strip().splitlines()) == 1, command
        assert odd.name in err and "2×2" in err and "1×1" in err
    assert not fp.exists()
