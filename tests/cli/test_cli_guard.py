"""D02: no command writes over, into or around its inputs — with --force or not.

Every command's parser declares which arguments are inputs and which outputs; ``main`` refuses, before any
work and before anything is replaced or deleted, an output that *is* an input, *lies inside* one, or
*contains* one (exit 2, one line naming the output argument).  Each case below is run with and without
``--force`` and the whole data folder is compared byte for byte afterwards: nothing changed, nothing added.

The inputs here are placeholders (a few PNG images, files with the right names): the guard must refuse
before any of them is read, so their content does not matter — a command that got as far as reading them
would fail differently (exit 3) and the test would say so.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from forensics.cli.main import build_parser

# Every command that has both an input and an output: its arguments with {IN}-style placeholders, and which
# placeholder is the input the output is made to collide with.  OUT marks the output argument under test.
CASES = {
    "simulate age": (["simulate", "age", "{set}", "{OUT}"], "set"),
    "simulate hidden (plug-in file)": (["simulate", "hidden", "{plug}:Effect", "{OUT}"], "plug"),
    "fingerprint build": (["fingerprint", "build", "{set}", "-o", "{OUT}"], "set"),
    "fingerprint match --report (set)": (["fingerprint", "match", "{fp}", "{set}", "--report", "{OUT}"], "set"),
    "fingerprint match --report (fingerprint)": (["fingerprint", "match", "{fp}", "{set}", "--report", "{OUT}"], "fp"),
    "fingerprint db add": (["fingerprint", "db", "add", "{OUT}", "{fp}", "--device", "cam"], "fp"),  # --replace
    "same-device --report": (["same-device", "{set}", "{set2}", "--report", "{OUT}"], "set2"),
    "identify --report (set)": (["identify", "{set}", "--db", "{db}", "--report", "{OUT}"], "set"),
    "identify --report (database)": (["identify", "{set}", "--db", "{db}", "--report", "{OUT}"], "db"),
    "cluster -o": (["cluster", "{set}", "-o", "{OUT}"], "set"),
    "cluster --report": (["cluster", "{set}", "-o", "{free}", "--report", "{OUT}"], "set"),
    "defects detect --report": (["defects", "detect", "{set}", "--report", "{OUT}"], "set"),
    "defects detect --report (mask image)": (["defects", "detect", "{set}", "--mask", "{mask}", "--report", "{OUT}"],
                                             "mask"),
    "defects growth -o": (["defects", "growth", "{set}", "{set2}", "-o", "{OUT}"], "set2"),
    "defects growth --report": (["defects", "growth", "{set}", "{set2}", "--report", "{OUT}"], "set"),
    "date --report (query)": (["date", "{set}", "--model", "{model}", "--report", "{OUT}"], "set"),
    "date --report (model)": (["date", "{set}", "--model", "{model}", "--report", "{OUT}"], "model"),
    "date --report (reference)": (["date", "{set}", "--reference", "{set2}", "{set3}", "--report", "{OUT}"], "set3"),
    "model check --report": (["model", "check", "{set}", "--report", "{OUT}"], "set"),
    "model check --report (plug-in)": (["model", "check", "{set}", "--add", "{plug}:Effect", "--report", "{OUT}"],
                                       "plug"),
    "impact --report": (["impact", "{set}", "--report", "{OUT}"], "set"),
    "impact --checkpoint": (["impact", "{set}", "--checkpoint", "{OUT}"], "set"),
    "impact --report (sensor file)": (["impact", "{set}", "--sensors", "A,{sensor}", "--report", "{OUT}"], "sensor"),
    "impact --report (matcher file)": (["impact", "{set}", "--matcher", "{plug}:Matcher", "--report", "{OUT}"],
                                       "plug"),
}


@pytest.fixture
def data(tmp_path) -> Path:
    """Placeholder inputs under tmp_path/data: three sets of PNG images, a fingerprint file, a database folder,
    a growth model, a mask image, a sensor file and a plug-in module."""
    from forensics.io.images import write_image

    root = tmp_path / "data"
    rng = np.random.default_rng(0)
    for name in ("set", "set2", "set3"):
        for i in range(3):
            write_image(root / name / f"img_{i}.png", rng.integers(0, 255, (32, 48), dtype=np.uint8))
    write_image(root / "mask.png", np.full((32, 48), 255, np.uint8))
    (root / "db").mkdir()
    (root / "db" / "index.sqlite").write_bytes(b"placeholder")
    (root / "fp.npz").write_bytes(b"placeholder")
    (root / "model.json").write_text("{}")
    (root / "sensor.json").write_text("{}")
    (root / "plug.py").write_text("class Effect: pass\nclass Matcher: pass\n")
    return root


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` (hidden ones included) with its bytes (None for folders)."""
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() else None)
            for p in sorted(root.rglob("*"))}


def paths(data: Path) -> dict[str, str]:
    named = {"set": "set", "set2": "set2", "set3": "set3", "fp": "fp.npz", "db": "db", "model": "model.json",
             "sensor": "sensor.json", "plug": "plug.py", "mask": "mask.png"}
    out = {k: str(data / v) for k, v in named.items()}
    out["free"] = str(data.parent / "elsewhere")
    return out


def output_for(relation: str, target: str) -> str:
    """An output that ``is`` the input, lies ``inside`` it, or ``contains`` it (its parent folder)."""
    return {"is": target, "inside": str(Path(target) / "sub" / "out"), "contains": str(Path(target).parent)}[relation]


@pytest.mark.parametrize("force", [False, True], ids=["no-force", "force"])
@pytest.mark.parametrize("relation", ["is", "inside", "contains"])
@pytest.mark.parametrize("case", list(CASES))
def test_outputs_never_overwrite_or_delete_inputs(cli, data, case, relation, force):
    template, target_name = CASES[case]
    values = paths(data)
    out = output_for(relation, values[target_name])
    force_flag = "--replace" if template[:2] == ["fingerprint", "db"] else "--force"  # a database has no --force
    argv = [a.replace("{OUT}", out).format(**values) for a in template] + ([force_flag] if force else [])
    before = snapshot(data.parent)
    code, stdout, stderr = cli(*argv)
    assert code == 2, (argv, stderr)
    assert stderr.startswith("forensics: error: ") and stderr.count("\n") == 1, stderr
    assert "outside the inputs" in stderr and "Traceback" not in stderr
    assert snapshot(data.parent) == before, "an input (or the folder around it) was changed"


def test_a_link_to_an_input_is_the_input(cli, data, tmp_path):
    """An output named through a symbolic link (or '..') that leads into an input is refused too."""
    link = tmp_path / "link"
    link.symlink_to(data / "set", target_is_directory=True)
    before = snapshot(data)
    for out in (link, link / "report", data / "set2" / ".." / "set"):
        code, _, err = cli("defects", "detect", data / "set", "--report", out, "--force")
        assert code == 2 and "--report" in err and ("lies inside the input" in err or "is the input" in err), err
    assert snapshot(data) == before


def test_a_neighbour_with_a_common_prefix_is_no_input(data):
    """``set2`` is beside ``set``, not inside it: the guard compares whole path components."""
    from forensics.cli.common import guard_outputs

    args = argparse.Namespace(inputs=("set",), outputs=("--report",), set=str(data / "set"),
                              report=str(data / "set2"))
    guard_outputs(args)  # no error
    args.report = str(data / "set" / "x")
    with pytest.raises(Exception, match="lies inside the input"):
        guard_outputs(args)


def test_keywords_are_not_taken_for_paths(data, monkeypatch):
    """Option values that name no file (``centre``, ``masek``, ``A,H*500``) are no inputs, even where the output
    is the current folder's parent; a plug-in ``file.py:Class`` and each part of a comma list are."""
    from forensics.cli.common import declared_paths

    monkeypatch.chdir(data)
    args = argparse.Namespace(inputs=("--mask", "--sensors", "--matcher"), outputs=(), mask="centre",
                              sensors="A,H*500,sensor.json", matcher=["masek", "plug.py:Matcher"])
    inputs, _ = declared_paths(args)
    assert sorted(inputs) == ["plug.py", "sensor.json"]


# ----------------------------------------------------------------------------- every command declares
def _leaf_parsers(parser: argparse.ArgumentParser, prefix: str = "") -> dict[str, argparse.ArgumentParser]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return {prefix.strip(): parser}
    out = {}
    for action in subs:
        for name, child in action.choices.items():
            out.update(_leaf_parsers(child, f"{prefix} {name}"))
    return out


LEAVES = _leaf_parsers(build_parser())
#: Argument names that hold a path in some command.  A new command's path argument is caught here if its
#: parser forgets to declare it.
PATH_DESTS = {"set", "sets", "set_a", "set_b", "src", "out", "output", "report", "checkpoint", "database", "db",
              "fingerprint", "fingerprints", "query", "reference", "data", "path", "mask", "effect", "add",
              "sensors", "matcher"}
#: The same names where they hold no path.
NOT_PATHS = {("fingerprint db add", "model"), ("fingerprint db remove", "device")}


def test_every_command_is_covered():
    assert len(LEAVES) >= 20
    assert {"simulate age", "fingerprint db add", "identify", "cluster", "date", "impact", "demo"} <= set(LEAVES)


@pytest.mark.parametrize("command", sorted(LEAVES))
def test_every_command_declares_its_inputs_and_outputs(command):
    parser = LEAVES[command]
    defaults = parser._defaults
    assert "inputs" in defaults and "outputs" in defaults, f"{command}: set_defaults(inputs=…, outputs=…) missing"
    dests = {a.dest for a in parser._actions}
    declared = {name.lstrip("-").replace("-", "_") for name in (*defaults["inputs"], *defaults["outputs"])}
    assert declared <= dests, f"{command}: declares arguments it does not have: {declared - dests}"
    undeclared = {d for d in dests & PATH_DESTS if (command, d) not in NOT_PATHS} - declared
    assert not undeclared, f"{command}: path arguments not declared as inputs or outputs: {undeclared}"


def test_every_command_with_inputs_and_outputs_is_exercised():
    """The cases above cover every command that declares both an input and an output."""
    both = {c for c, p in LEAVES.items() if p._defaults["inputs"] and p._defaults["outputs"]}
    exercised = {" ".join(t[:k]) for t, _ in CASES.values() for k in (1, 2, 3)} & set(LEAVES)
    assert both <= exercised, both - exercised


def test_an_output_beside_the_inputs_is_written(cli, data, tmp_path):
    """The guard refuses only real overlaps: the ordinary case still runs (here to the command's own check)."""
    code, out, err = cli("simulate", "age", data / "set", tmp_path / "aged", "--years", "0,1", "--workers", "1",
                         "--quiet", "--sensor", "A")
    assert code == 0, err
    assert (tmp_path / "aged" / "year_001").is_dir()
