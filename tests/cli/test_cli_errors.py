"""D11, D21, D22: every failure is one line with the right exit code, and untrusted text cannot act on the
terminal.

Exit codes: 2 usage error, 3 bad input data or files, 1 a bug ("internal error", traceback with
FORENSICS_DEBUG=1) or out of memory.  Everything printed for a human passes ``printable()``; JSON output is
left to ``json``, which escapes control characters itself.
"""
from __future__ import annotations

import csv
import errno
import json
import signal
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

import forensics.cli.info
from forensics._shared.errors import InputError, UsageError
from forensics._shared.text import printable
from forensics.cli.errors import describe

ESC = "\x1b"


def one_line(err: str) -> bool:
    return err.count("\n") == 1 and err.startswith("forensics: ") and "Traceback" not in err


@pytest.fixture
def images(tmp_path) -> Path:
    from forensics.io.images import write_image

    rng = np.random.default_rng(1)
    for i in range(3):
        write_image(tmp_path / "set" / f"img_{i}.png", rng.integers(20, 230, (32, 48), dtype=np.uint8))
    return tmp_path / "set"


# ----------------------------------------------------------------------------- D11: exceptions → one line
@pytest.mark.parametrize("exc, code, words", [
    (UsageError("--x 1: no"), 2, "--x 1: no"),
    (InputError("a.png: bad"), 3, "a.png: bad"),
    (OSError(errno.ENOSPC, "No space left on device", "out/a.png"), 3, "out/a.png: disk full"),
    (IsADirectoryError(errno.EISDIR, "Is a directory", "out.npz"), 3, "out.npz: is a folder"),
    (OSError(errno.ELOOP, "Too many levels of symbolic links", "loop"), 3, "loop: too many levels of symbolic links"),
    (OSError(errno.ENAMETOOLONG, "File name too long", "x" * 300), 3, "file name too long"),
    (PermissionError(errno.EACCES, "Permission denied", "secret"), 3, "secret: permission denied"),
    (FileNotFoundError(errno.ENOENT, "No such file or directory", "a", None, "b"), 3, "a → b: no such file or folder"),
    (OSError(errno.EBADF, "Bad file descriptor"), 3, "Bad file descriptor"),
    (UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"), 3, "not valid utf-8"),
    (csv.Error("field larger than field limit (131072)"), 3, "malformed CSV (field larger"),
    (zipfile.BadZipFile("File is not a zip file"), 3, "damaged .npz"),
    (EOFError("No data left in file"), 3, "ended early"),
    (json.JSONDecodeError("Expecting value", "[1,", 3), 3, "malformed JSON: Expecting value at line 1, column 4"),
    (MemoryError(), 1, "out of memory"),
    (KeyboardInterrupt(), 130, "interrupted"),
    (RuntimeError("boom\nsecond line"), 1, "internal error: RuntimeError: boom second line (rerun with "
                                           "FORENSICS_DEBUG=1 for the traceback; please report it)"),
    (KeyError("k"), 1, "internal error: KeyError"),
])
def test_every_exception_becomes_one_line_and_an_exit_code(exc, code, words):
    got_code, message = describe(exc)
    assert got_code == code
    assert words in message and "\n" not in message


@pytest.fixture
def failing(monkeypatch):
    """Make ``forensics info`` raise the given exception (its handler is bound when the parser is built)."""

    def install(exc: BaseException) -> None:
        def run(args):
            raise exc
        monkeypatch.setattr(forensics.cli.info, "run", run)

    return install


@pytest.mark.parametrize("exc, code", [
    (OSError(errno.ENOSPC, "No space left on device", "out/a.png"), 3),
    (csv.Error("new-line character seen in unquoted field"), 3),
    (MemoryError(), 1),
    (ValueError("unexpected"), 1),
])
def test_main_prints_one_line_not_a_traceback(cli, failing, monkeypatch, exc, code):
    monkeypatch.delenv("FORENSICS_DEBUG", raising=False)
    failing(exc)
    got, out, err = cli("info", ".")
    assert got == code and out == "" and one_line(err), err


def test_debug_shows_the_traceback(cli, failing, monkeypatch):
    monkeypatch.setenv("FORENSICS_DEBUG", "1")
    failing(ValueError("unexpected"))
    code, _, err = cli("info", ".")
    assert code == 1
    assert "Traceback (most recent call last)" in err and err.rstrip().endswith("please report it)")


def test_a_library_warning_is_one_escaped_line(cli, monkeypatch, images):
    def run(args):
        warnings.warn(f"odd file {ESC}[2Jname", UserWarning)
        return 0
    monkeypatch.delenv("FORENSICS_DEBUG", raising=False)
    monkeypatch.setattr(forensics.cli.info, "run", run)
    code, _, err = cli("info", images)
    assert code == 0 and err == "warning: odd file \\x1b[2Jname\n"


def test_date_model_of_the_wrong_shape_is_bad_input(cli, images, tmp_path):
    for text in ("[1, 2]", '"text"', "{}", "{not json", '{"format": "forensics-growth-model/1"}'):
        (tmp_path / "model.json").write_text(text)
        code, _, err = cli("date", images, "--model", tmp_path / "model.json")
        assert code == 3 and one_line(err) and "model.json" in err, (text, err)


@pytest.mark.parametrize("size", ["0x0", "1x1", "64x", "x64", "axb", "64x48x3", "-64x48"])
def test_scene_size_is_a_usage_error(cli, tmp_path, size):
    code, _, err = cli("simulate", "scenes", tmp_path / "s", "--size", size)
    assert code == 2 and "argument --size" in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_fingerprint_into_an_existing_folder_is_one_line(cli, images, tmp_path):
    (tmp_path / "folder").mkdir()
    code, _, err = cli("fingerprint", "build", images, "-o", tmp_path / "folder", "--force", "--workers", "1",
                       "--quiet")
    assert code in (2, 3) and one_line(err) and "folder" in err, err
    assert (tmp_path / "folder").is_dir()


def test_an_output_under_a_file_is_one_line(cli, tmp_path):
    (tmp_path / "file").write_text("x")
    code, _, err = cli("simulate", "scenes", tmp_path / "file" / "sub", "--count", "2", "--size", "16x16")
    assert code == 3 and one_line(err) and "file" in err


# Ctrl-C or SIGTERM while the command is still starting: the signal is sent from an import hook when the named
# module starts loading — inside cli/main.py's own imports (the output helpers) or inside the building of the
# parser (the last command module) — so the test does not depend on timing.
_STOP_WHILE_IMPORTING = """
import os, signal, sys
class Trip:
    def find_spec(self, name, path=None, target=None):
        if name == sys.argv[1]:
            os.kill(os.getpid(), int(sys.argv[2]))
        return None
sys.meta_path.insert(0, Trip())
from forensics.cli.main import main
sys.exit(main(sys.argv[3:]))
"""


@pytest.mark.parametrize("module", ["forensics._shared.jsonsafe", "forensics.cli.impact"], ids=["imports", "parser"])
@pytest.mark.parametrize("signum, code, line", [(signal.SIGINT, 130, "forensics: interrupted"),
                                                (signal.SIGTERM, 143, "forensics: terminated by SIGTERM")],
                         ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_starting_is_one_line_not_a_traceback(tmp_path, module, signum, code, line):
    """Found by the adversarial replay: Ctrl-C in the first second of a command (importing the library, building
    the parser) printed the traceback of whatever module was loading and died of SIGINT; SIGTERM there ended
    it without a word."""
    # the command as a user's shell starts it: Ctrl-C not ignored (a test run started in the background of a
    # non-interactive shell hands its children SIGINT ignored, and Python then installs no handler for it)
    run = subprocess.run([sys.executable, "-c", _STOP_WHILE_IMPORTING, module, str(int(signum)), "info", str(tmp_path)],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert run.returncode == code and run.stderr == line + "\n" and run.stdout == "", run.stderr


def test_a_worker_stopped_while_starting_ends_silently(tmp_path):
    """A worker process imports cli/main.py while it re-runs the console script as ``__mp_main__``; stopped
    there (the pool stops its workers when a run is interrupted), it must not print the command's line too —
    the adversarial replay saw "terminated by SIGTERM" twice."""
    code = "import sys, types; sys.modules['__mp_main__'] = types.ModuleType('__mp_main__'); " + _STOP_WHILE_IMPORTING
    run = subprocess.run([sys.executable, "-c", code, "forensics._shared.jsonsafe", str(int(signal.SIGTERM)), "info",
                          str(tmp_path)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == -signal.SIGTERM and run.stderr == "", run.stderr


# ----------------------------------------------------------------------------- D21: exit codes
@pytest.mark.parametrize("argv", [
    ["simulate", "scenes", "OUT", "--count", "0"],
    ["simulate", "scenes", "OUT", "--count", "-3"],
    ["simulate", "irises", "OUT", "--classes", "0"],
    ["simulate", "age", "SRC", "OUT", "--seed", "-1"],
    ["defects", "detect", "SET", "--workers", "0"],
    ["same-device", "A", "B", "--seed", "-1"],
    ["identify", "SET", "--db", "DB", "--sigma", "-1"],
    ["model", "check", "DATA", "--max-steps", "0"],
    ["validate", "defects", "--trials", "0"],
    ["demo", "--seed", "x"],
])
def test_bad_option_values_are_usage_errors(cli, argv):
    code, _, err = cli(*argv)
    assert code == 2 and "error: argument" in err and "Traceback" not in err, err


def test_requests_that_cannot_work_are_usage_errors(cli, tmp_path):
    """Found in the sweep of the commands: an unknown demo section ran nothing and exited 0; validation frames
    too small for the median window failed as bad input data (3) although there is no input."""
    code, _, err = cli("demo", "--only", "nonexistent", "--out", tmp_path / "o")
    assert code == 2 and one_line(err) and "--only nonexistent" in err and not (tmp_path / "o").exists()
    code, _, err = cli("validate", "defects", "--size", "8x8", "--trials", "1", "--workers", "1")
    assert code == 2 and one_line(err) and "give at least 16x16" in err


# ----------------------------------------------------------------------------- D22: terminal escapes
@pytest.mark.parametrize("raw, shown", [
    ("plain × é 中", "plain × é 中"),
    ("two\nlines\tand a tab", "two\nlines\tand a tab"),
    (f"{ESC}[2J{ESC}]0;title\x07", "\\x1b[2J\\x1b]0;title\\x07"),
    ("over\rwrite", "over\\x0dwrite"),
    ("csi\x9b31m del\x7f nul\x00", "csi\\x9b31m del\\x7f nul\\x00"),
    ("evil\u202egnp.exe", "evil\\u202egnp.exe"),
    ("bad byte \udcff in a name", "bad byte \\xff in a name"),
])
def test_printable_escapes_control_characters(raw, shown):
    assert printable(raw) == shown


def test_file_names_and_manifest_fields_reach_the_terminal_escaped(cli, tmp_path):
    from forensics.io.dataset import write_manifest
    from forensics.io.images import write_image

    folder = tmp_path / f"set{ESC}]0;pwned\x07"
    rng = np.random.default_rng(2)
    rows = []
    for i in range(3):
        name = f"img{ESC}[31m_{i}.png"
        write_image(folder / name, rng.integers(20, 230, (32, 48), dtype=np.uint8))
        rows.append({"file": name, "device": f"cam{ESC}[2J", "captured": 2010.0})
    write_manifest(folder / "manifest.csv", rows)
    code, out, err = cli("info", folder)
    assert code == 0, err
    assert ESC not in out + err and "\\x1b[2J" in out and "\\x1b]0;pwned" in out
    code, out, err = cli("defects", "detect", folder, "--mask", "all", "--workers", "1", "--quiet")
    assert code == 0, err
    assert ESC not in out + err and "\\x1b]0;pwned" in out
    code, out, err = cli("defects", "detect", folder, "--mask", "all", "--workers", "1", "--json")
    assert code == 0 and json.loads(out)["set"] == str(folder)  # JSON keeps the name exact (escaped by json)
    code, out, err = cli("date", tmp_path / f"missing{ESC}[2J", "--model", tmp_path / "m.json")
    assert code == 3 and ESC not in err and "missing\\x1b[2J" in err
    code, out, err = cli("simulate", "scenes", tmp_path / "s", "--count", f"{ESC}[2J")
    assert code == 2 and ESC not in err
