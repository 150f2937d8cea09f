"""``forensics model effects``, ``forensics model check`` and ``forensics simulate hidden``."""
from __future__ import annotations

import json

import pytest

from forensics.cli.main import main

USER = '''
from dataclasses import dataclass
from forensics.sensor.model import Effect, Stage, param


@dataclass
class Pedestal(Effect):
    name = "pedestal_shift"
    description = "a constant added to every pixel"
    stage = Stage.DARK
    value: float = param(0.0, "DN", "the constant", null=0.0, free=True)

    def apply(self, signal, ctx, rng):
        signal += self.value
        return signal
'''


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "lab"
    assert main(["simulate", "hidden", "nonlinearity", str(out), "--seed", "2", "--quiet"]) == 0
    return out


def test_effects_lists_every_effect(capsys):
    assert main(["model", "effects"]) == 0
    text = capsys.readouterr().out
    for name in ("growth", "offset", "stuck", "prnu", "dark_current", "gain", "nonlinearity", "shot_noise",
                 "clusters", "accelerating_growth"):
        assert f"  {name} " in text
    assert "needs: exposure_s, temperature_c" in text and "needs: iso" in text
    assert main(["model", "effects", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["effects"]
    assert {r["name"] for r in rows} >= {"prnu", "clusters"}
    assert all({"description", "fields", "params", "role", "stage"} <= set(r) for r in rows)


def test_simulate_hidden_writes_truth(data, capsys):
    truth = json.loads((data / "truth.json").read_text())
    assert truth["hidden"] == "nonlinearity"
    assert (data / "manifest.csv").read_text().splitlines()[0].startswith("file,device,captured,exposure_s,iso")


def test_check_json_keys_and_named_effect(data, capsys):
    assert main(["model", "check", str(data), "--json", "--seed", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["effects"] == ["growth", "offset", "stuck", "read_noise", "black_level"]
    assert set(out["error"]) == {"pixel", "classes", "variance", "growth"}
    assert set(out["gof"]) == {"pixel", "variance", "growth", "spatial"}
    first = out["candidates"][0]
    assert first["effect"] == "nonlinearity" and first["flagged"] is True
    assert {"effect", "delta_bic", "p", "flagged"} <= set(first)
    # A 128² dataset of 108 frames is far below the pixel-frames that repay starting worker processes: without
    # --workers the check runs in this process; an explicit count is obeyed.
    assert out["execution"]["backend"] == "in-process"


def test_check_human_output_with_add_and_report(data, tmp_path, capsys):
    user = tmp_path / "user.py"
    user.write_text(USER)
    report = tmp_path / "report"
    code = main(["model", "check", str(data), "--add", "nonlinearity", "--add", f"{user}:Pedestal",
                 "--report", str(report), "--quiet"])
    assert code == 0
    text = capsys.readouterr().out
    for heading in ("Fitted parameters", "Error (held-out", "Goodness of fit", "Checks", "Candidates"):
        assert heading in text
    assert "nonlinearity.beta" in text and "pedestal_shift.value" in text and "(before:" in text
    assert "Nothing flagged" in text
    names = {p.name for p in report.iterdir()}
    assert {"index.html", "residual_maps.png", "covariates.png", "counts.png", "ripley.png"} <= names
    html = (report / "index.html").read_text()
    assert "before" in html and "after" in html
    # the report exists now: refused without --force
    assert main(["model", "check", str(data), "--report", str(report), "--quiet"]) == 2


def test_bad_input_exit_codes(tmp_path, data, capsys):
    assert main(["model", "check", str(tmp_path / "missing")]) == 3
    assert main(["model", "check", str(data), "--add", "no_such_effect"]) == 2
    assert main(["model", "check", str(data), "--add", "offset"]) == 2  # already in the model
    err = capsys.readouterr().err
    assert "no_such_effect" in err and "already in the model" in err


# ------------------------------------------------------------------------------------------- --auto
@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "pair"
    assert main(["simulate", "hidden", "prnu,dark_current", str(out), "--seed", "1", "--quiet"]) == 0
    return out


def test_simulate_hidden_takes_several_effects(pair, tmp_path, capsys):
    truth = json.loads((pair / "truth.json").read_text())
    assert truth["hidden_effects"] == ["prnu", "dark_current"] and truth["hidden"] == "prnu+dark_current"
    assert main(["simulate", "hidden", "prnu", "dark_current", str(tmp_path / "rep"), "--seed", "1"]) == 0
    assert "with prnu + dark_current hidden" in capsys.readouterr().out
    assert json.loads((tmp_path / "rep" / "truth.json").read_text())["hidden_effects"] == ["prnu", "dark_current"]


def test_check_auto_json_and_report(pair, tmp_path, capsys):
    report = tmp_path / "report"
    assert main(["model", "check", str(pair), "--auto", "--json", "--seed", "1", "--report", str(report)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [p["step"] for p in out["path"]][0] == "base"
    assert sorted(out["added"]) == ["dark_current", "prnu"] and out["stopped"] == "nothing flagged"
    assert {"effects", "error", "gof", "candidates", "before"} <= set(out)
    assert all({"error", "gof", "flagged", "top"} <= set(p) for p in out["path"])
    assert out["error"]["pixel"] <= 1.1 and not [c for c in out["candidates"] if c["flagged"]]
    names = {p.name for p in report.iterdir()}
    assert {"index.html", "ladder.png", "residual_maps.png"} <= names
    assert "Forward selection" in (report / "index.html").read_text()


def test_check_auto_ladder_and_max_steps(pair, capsys):
    assert main(["model", "check", str(pair), "--auto", "--max-steps", "1", "--seed", "1", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "Forward selection (--auto)" in text and "Stopped: max steps (1) reached" in text
    ladder = text[text.index("Forward selection (--auto)"):].splitlines()
    assert ladder[2].lstrip().startswith("base") and ladder[3].lstrip().startswith("+")
    assert "Same model by hand: forensics model check" in text
    assert main(["model", "check", str(pair), "--max-steps", "2"]) == 2
    assert "--max-steps needs --auto" in capsys.readouterr().err


def test_max_steps_help_names_the_library_default(capsys):
    from forensics.check.select import DEFAULT_MAX_STEPS

    with pytest.raises(SystemExit):
        main(["model", "check", "--help"])
    assert f"DEFAULT_MAX_STEPS, {DEFAULT_MAX_STEPS})" in " ".join(capsys.readouterr().out.split())
