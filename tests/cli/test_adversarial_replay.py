"""The adversarial replay (benchmarks/adversarial_replay.py) kept in CI: its quick subset, run through the
installed console script from a folder of its own, and its checks shown to catch a broken promise.

The whole replay (124 cases, about 4.5 minutes on two shared cores) is run by hand against a wheel, from
elsewhere and from inside a copy of the checkout (benchmarks/RESULTS_replay.md); the quick subset (15 cases,
one or more per family: the output guard, the index's paths, content-free sets, malformed manifests,
undecodable names, bounded requests, a FIFO manifest, option values, escaped terminal text, manifests leaving
their folder) takes about 20 s.
"""
from __future__ import annotations

import importlib
import os
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


class Replay:
    """The driver and its harness as one namespace (the scripts import each other as benchmarks/ siblings)."""

    def __init__(self):
        self.driver = importlib.import_module("adversarial_replay")
        self.harness = importlib.import_module("_replay_harness")

    def __getattr__(self, name):
        return getattr(self.driver, name) if hasattr(self.driver, name) else getattr(self.harness, name)


@pytest.fixture(scope="module")
def replay():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        yield Replay()
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def test_the_quick_replay_keeps_every_promise(replay, tmp_path):
    forensics = shutil.which("forensics", path=str(Path(sys.executable).parent))
    if forensics is None:
        pytest.skip("no forensics console script beside this interpreter (run through dev.py's .venv)")
    outcomes = replay.replay(forensics, tmp_path, workers=2, quick=True, tmp=tmp_path)
    assert len(outcomes) >= 15 and len({o.defect for o in outcomes}) >= 10
    failed = [f"{o.case}: {'; '.join(o.problems)} ({o.observed})" for o in outcomes if not o.ok]
    assert failed == []
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the replay's own folder is gone


def test_the_checks_catch_broken_promises(replay, tmp_path):
    """Each check fails on the breach it is there for, so a passing replay means something."""
    run = replay.Run
    assert replay.check(run(["x"], 3, "", "forensics: error: a.png: bad\n", 0.1), 3, "a.png") == []
    assert replay.check(run(["x"], 1, "", "forensics: error: a\n", 0.1), 3) == ["exit 1, not 3"]
    traceback = "Traceback (most recent call last):\n  File x\nValueError: v\nforensics: error: v\n"
    assert "traceback on stderr" in replay.check(run(["x"], 3, "", traceback, 0.1), 3)
    assert "2 lines on stderr" in replay.check(run(["x"], 3, "", "libpng error: bad\nforensics: error: a\n", 0.1), 3)
    assert "raw ESC on the terminal" in replay.check(run(["x"], 0, "\x1b[2J", "", 0.1), 0)
    assert any("not standard JSON" in p for p in replay.check(run(["x"], 0, '{"a": NaN}', "", 0.1), 0, json_out=True))
    assert "1 process(es) survived the command" in replay.check(run(["x"], 0, "", "", 0.1, [4242]), 0)
    usage = "usage: forensics info [-h]\n                      PATH\nforensics info: error: argument --x: bad\n"
    assert replay.check(run(["x"], 2, "", usage, 0.1), 2, "argument --x") == []
    (tmp_path / ".out.1234.part").mkdir()
    (tmp_path / ".report.old-99").write_text("")
    (tmp_path / ".aged.partial").mkdir()
    assert sorted(replay.strays(tmp_path)) == [".aged.partial", ".out.1234.part", ".report.old-99"]
    assert sorted(replay.strays(tmp_path, allow_partial=True)) == [".out.1234.part", ".report.old-99"]
    cut = tmp_path / "cut.png"
    cut.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))
    assert not replay.png_whole(cut)


def test_a_changed_input_fails_the_case(replay, tmp_path):
    """The inputs are hashed after every case: a case that changes one fails, whatever it printed."""
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.png").write_bytes(b"a")
    before = replay.tree_hashes(tmp_path / "in")

    def vandal(ctx):
        (tmp_path / "in" / "a.png").write_bytes(b"b")
        os.unlink(tmp_path / "in" / "a.png")
        return "exit 0", []

    class Fx:
        root = tmp_path / "in"

    ctx = replay.Ctx(None, Fx(), tmp_path, 2, sys.executable)
    outcome = replay.run_case(replay.Case("vandal", "D02", "nothing changed", vandal), ctx, before)
    assert not outcome.ok and outcome.problems == ["inputs changed: ['a.png']"]
