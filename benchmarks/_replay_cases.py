"""The cases of issue 26's adversarial sweep, each defect D01–D25 with its variants and the categories
that held up; registered with :func:`_replay_harness.case` in the order they run."""
from __future__ import annotations

import contextlib
import json
import os
import pickle
import re
import shutil
import signal
import sqlite3
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from _replay_harness import (  # benchmarks/ is on sys.path when a script runs
    EDIT_META, ESC, SAME_K, W, Ctx, Run, age_args, case, check, copy_set, modes, observed, png_whole,
    session_processes, simple, strays, strict_json, tree_hashes,
)


# --- D01: failed image writes
STRAY_IMAGE = re.compile(r"^\..+\.part\.png$")
def _d01(workers: Callable[[Ctx], int]):
    def body(c: Ctx):
        out = c.work / "out"
        r = c.run("simulate", "age", c.fx.bigscenes, out, "--sensor", "H", "--years", "0:16:8", "--seed", "5", "--quiet",
                  W, workers(c), fsize=100 * 1024)
        problems = check(r, 3, "file too large")
        if out.exists():
            problems.append("OUT exists after a failed run")
        # Kept for a rerun: whole images under their own names, and a worker's unfinished temporary
        # (.NAME.*.part.png, stopped with the run), which the rerun sweeps.
        broken = [p for p in c.work.rglob("*.png") if not png_whole(p) and not STRAY_IMAGE.match(p.name)]
        problems += [f"truncated PNG kept: {p.name}" for p in broken]
        problems += [f"stray: {s}" for s in strays(c.work, allow_partial=True)]
        again = c.run("simulate", "age", c.fx.bigscenes, out, "--sensor", "H", "--years", "0:16:8", "--seed", "5",
                      "--quiet", W, workers(c))
        problems += [f"rerun without the limit: {p}" for p in check(again, 0)]
        problems += [f"after the rerun, stray: {s}" for s in strays(c.work)]
        problems += [f"after the rerun, truncated: {p.name}" for p in c.work.rglob("*.png") if not png_whole(p)]
        return observed(r) + f"; rerun exit {again.code}", problems
    return body


case("D01 ulimit -f 100, simulate age --workers 1", "D01", "exit 3 'file too large', no truncated PNG; rerun 0")(_d01(lambda c: 1))
case("D01 ulimit -f 100, simulate age --workers N", "D01", "exit 3 'file too large', no truncated PNG; rerun 0")(
    _d01(lambda c: c.workers))

# --- D02: outputs that are, contain or lie inside an input
GUARD = "outside the inputs"
simple("D02 match --report SET --force", "D02", 2,
       lambda c: ["fingerprint", "match", c.fx.fp / "cam0.npz", c.fx.cam0, "--report", c.fx.cam0, "--force"], GUARD,
       quick=True)
simple("D02 build -o SET/img.png --force", "D02", 2,
       lambda c: ["fingerprint", "build", c.fx.cam0, "-o", c.fx.cam0 / "0.png", "--force"], GUARD)
simple("D02 build -o (folder holding SET) --force", "D02", 2,
       lambda c: ["fingerprint", "build", c.fx.cam0, "-o", c.fx.root, "--force"], GUARD)
simple("D02 growth -o SET2/model.json --force", "D02", 2,
       lambda c: ["defects", "growth", c.fx.aged / "year_000", c.fx.aged / "year_004", "-o",
                  c.fx.aged / "year_004" / "m.json", "--force"], GUARD)
simple("D02 defects detect --report SET --force", "D02", 2,
       lambda c: ["defects", "detect", c.fx.scenes, "--report", c.fx.scenes, "--force"], GUARD)
simple("D02 same-device --report SET_B/sub --force", "D02", 2,
       lambda c: ["same-device", c.fx.cam0, c.fx.cam1, "--report", c.fx.cam1 / "r", "--force"], GUARD)
simple("D02 identify --report DB --force", "D02", 2,
       lambda c: ["identify", c.fx.cam0, "--db", c.fx.fp, "--report", c.fx.fp, "--force"], GUARD)
simple("D02 date --report MODEL --force", "D02", 2,
       lambda c: ["date", c.fx.scenes, "--model", c.fx.root / "model.json", "--report", c.fx.root / "model.json",
                  "--force"], GUARD)
simple("D02 model check --report DATA/r --force", "D02", 2,
       lambda c: ["model", "check", c.fx.scenes, "--report", c.fx.scenes / "r", "--force"], GUARD)
simple("D02 simulate age OUT=SRC --force", "D02", 2,
       lambda c: ["simulate", "age", c.fx.scenes, c.fx.scenes, "--force"], GUARD)


# --- D03: the index's file column
def _d03(planted: Callable[[Ctx], str], command: str):
    def body(c: Ctx):
        db, victim = c.work / "db", c.work / "victim"
        first = c.run("fingerprint", "db", "add", db, c.fx.fp / "cam0.npz", "--device", "camA")
        if first.code != 0:
            return observed(first), ["setup: db add failed"]
        victim.write_text("keep me")
        with contextlib.closing(sqlite3.connect(db / "index.sqlite")) as con, con:
            con.execute("UPDATE devices SET file = ?", (planted(c),))
        argv = (["fingerprint", "db", "remove", db, "camA"] if command == "remove" else
                ["fingerprint", "db", "add", db, c.fx.fp / "cam0.npz", "--device", "camA", "--replace"])
        r = c.run(*argv)
        problems = check(r, 3, "the index is damaged")
        if not victim.exists() or victim.read_text() != "keep me":
            problems.append("the victim file was deleted or changed")
        return observed(r), problems
    return body


for _where, _planted in (("../victim", lambda c: "../victim"), ("/abs/victim", lambda c: str(c.work / "victim"))):
    for _cmd in ("remove", "add --replace"):
        case(f"D03 index file={_where}, db {_cmd}", "D03", "exit 3 'the index is damaged', victim kept",
             quick=_cmd == "remove" and _where == "../victim")(_d03(_planted, _cmd.split()[0]))


# --- D04, D15, D13 and the held-up resume: an interrupted two-worker ageing run
def _interrupt(c: Ctx, src: Path, out: Path, signum: int, workers: int | None = None) -> Run:
    """Start ageing ``src`` into ``out`` and send ``signum`` once its first work item is saved."""
    started = time.monotonic()
    proc, log = c.run.start(*age_args(c, src, out, workers))
    items = out.parent / f".{out.name}.partial" / ".items"
    deadline = time.monotonic() + 120
    while not any(items.glob("item-*.npz")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if proc.poll() is None:
        os.kill(proc.pid, signum)
    return c.run.finish(proc, log, started)


_REFERENCE: dict[str, dict[str, str]] = {}


def reference(c: Ctx) -> dict[str, str]:
    """The lifetime set aged in one uninterrupted one-worker run (computed once)."""
    if "tree" not in _REFERENCE:
        out = c.work / "reference"
        r = c.run(*age_args(c, c.fx.lifetime, out, 1))
        if r.code != 0:
            raise RuntimeError(f"reference run failed: {r.err.strip()}")
        _REFERENCE["tree"] = tree_hashes(out)
    return _REFERENCE["tree"]


class Planted:
    """A pickle that, if ever loaded, creates ``marker`` (what D04's planted checkpoint did)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


@case("D04 planted pickles in .OUT.partial/.items, resume", "D04",
      "resume exit 0, planted code never runs, output byte-identical")
def _d04(c: Ctx):
    ref = reference(c)
    out, marker = c.work / "aged", c.work / "code-ran"
    killed = _interrupt(c, c.fx.lifetime, out, signal.SIGKILL)
    items = c.work / ".aged.partial" / ".items"
    found = sorted(items.glob("item-*.npz"))
    if not found:
        return observed(killed), ["setup: no checkpoint item to plant over"]
    for p in found[:3]:
        p.write_bytes(pickle.dumps(Planted(marker)))
    (items / "item-0000099.pkl").write_bytes(pickle.dumps(Planted(marker)))
    r = c.run(*age_args(c, c.fx.lifetime, out))
    problems = check(r, 0)
    if marker.exists():
        problems.append("planted code ran")
    if r.code == 0 and tree_hashes(out) != ref:
        problems.append("resumed output differs from an uninterrupted run")
    return observed(r), problems


@case("D15 source image replaced after kill -9, resume", "D15", "exit 2 'has changed since', work kept")
def _d15(c: Ctx):
    src = copy_set(c.fx.lifetime, c.work / "src")
    out = c.work / "aged"
    _interrupt(c, src, out, signal.SIGKILL)
    images = sorted(src.glob("*.png"))
    images[-1].write_bytes(images[0].read_bytes())
    r = c.run(*age_args(c, src, out))
    problems = check(r, 2, "has changed since")
    if out.exists():
        problems.append("OUT written from mixed inputs")
    if not (c.work / ".aged.partial").is_dir():
        problems.append("the interrupted work was deleted")
    return observed(r), problems


@case("D13 SIGTERM of simulate age --workers N", "D13", "exit 143, one line, no process left, work kept")
def _d13_term(c: Ctx):
    out = c.work / "aged"
    r = _interrupt(c, c.fx.lifetime, out, signal.SIGTERM)
    problems = check(r, 143, "terminated by SIGTERM")
    if out.exists():
        problems.append("OUT exists after an interrupted run")
    if not (c.work / ".aged.partial" / ".items").is_dir():
        problems.append("resumable work not kept")
    return observed(r), problems


@case("D13 kill -9 of simulate age --workers N", "D13", "no process of the run survives")
def _d13_kill(c: Ctx):
    r = _interrupt(c, c.fx.lifetime, c.work / "aged", signal.SIGKILL)
    problems = [] if r.code == -signal.SIGKILL else [f"exit {r.code}, not killed"]
    if r.orphans:
        problems.append(f"{len(r.orphans)} process(es) survived kill -9 of the command")
    return f"killed ({r.code}), {len(r.orphans)} survivor(s)", problems


def _d13_other(argv: Callable[[Ctx], list], signum: int):
    def body(c: Ctx):
        started = time.monotonic()
        proc, log = c.run.start(*argv(c))
        deadline = time.monotonic() + 60
        # Signalled once a worker exists beside the command, its fork server and resource tracker (4 processes):
        # what used to be left behind.
        while proc.poll() is None and len(session_processes(proc.pid)) < 4 and time.monotonic() < deadline:
            time.sleep(0.02)
        alive = proc.poll() is None
        if alive:
            os.kill(proc.pid, signum)
        r = c.run.finish(proc, log, started)
        problems = [] if alive else ["the command ended before its workers could be signalled"]
        if r.orphans:
            problems.append(f"{len(r.orphans)} process(es) survived")
        if signum == signal.SIGTERM:
            problems += check(r, 143, "terminated by SIGTERM")
        elif r.code != -signal.SIGKILL:
            problems.append(f"exit {r.code}, not killed")
        problems += [f"stray: {s}" for s in strays(c.work, allow_partial=True)]
        return f"exit {r.code}, {len(r.orphans)} survivor(s)", problems
    return body


# (model check, the other example, runs small data in its own process: defects detect starts workers.)
case("D13 SIGTERM of defects detect --workers N", "D13", "exit 143, no process left")(_d13_other(
    lambda c: ["defects", "detect", c.fx.lifetime, "--mask", "all", W, c.workers, "--quiet", "--report", c.work / "r"],
    signal.SIGTERM))
case("D13 kill -9 of fingerprint build --workers N", "D13", "no process left")(_d13_other(
    lambda c: ["fingerprint", "build", c.fx.lifetime, "-o", c.work / "fp.npz", W, c.workers, "--quiet"],
    signal.SIGKILL))


@case("held: SIGINT (Ctrl-C) of simulate age --workers N", "held", "exit 130, one line, no process left")
def _ctrl_c(c: Ctx):
    r = _interrupt(c, c.fx.lifetime, c.work / "aged", signal.SIGINT)
    problems = check(r, 130, "interrupted")
    return observed(r), problems


@case("held: kill -9 then resume is byte-identical", "held", "resume exit 0, tree equal to an uninterrupted run")
def _resume(c: Ctx):
    ref = reference(c)
    out = c.work / "aged"
    _interrupt(c, c.fx.lifetime, out, signal.SIGKILL)
    r = c.run(*age_args(c, c.fx.lifetime, out))
    problems = check(r, 0)
    if r.code == 0 and tree_hashes(out) != ref:
        problems.append("resumed output differs")
    problems += [f"stray: {s}" for s in strays(c.work)]
    return observed(r), problems


@case("D11 two simulate age runs into one OUT at once", "D11", "second exit 2 'another run is writing', first 0")
def _two_runs(c: Ctx):
    out = c.work / "aged"
    started = time.monotonic()
    proc, log = c.run.start(*age_args(c, c.fx.lifetime, out))
    items = c.work / ".aged.partial" / ".items"
    deadline = time.monotonic() + 120
    while not any(items.glob("item-*.npz")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    second = c.run(*age_args(c, c.fx.lifetime, out))
    first = c.run.finish(proc, log, started)
    problems = check(second, 2, "another run is writing")
    problems += [f"first run: {p}" for p in check(first, 0)]
    return f"second {observed(second)}; first exit {first.code}", problems


# --- D05 / D18: alpha dropped
def _alpha(which: str):
    def body(c: Ctx):
        runs = [c.run("fingerprint", "build", c.fx.root / s, "-o", c.work / f"{s}.npz", W, 1, "--quiet")
                for s in ("rgb", which)]
        problems = [p for r in runs for p in check(r, 0)]
        if not problems:
            same = subprocess.run([c.python, "-c", SAME_K, c.work / "rgb.npz", c.work / f"{which}.npz"],
                                  capture_output=True, text=True).stdout.strip()
            if same != "same":
                problems.append(f"K from the {which} set differs from the RGB set's (alpha not dropped)")
        return observed(runs[1]), problems
    return body


case("D05 RGBA alpha 128 read as its RGB", "D05", "exit 0, K identical to the RGB set's")(_alpha("rgba128"))
case("D05 RGBA alpha 0 read as its RGB", "D05", "exit 0, K identical to the RGB set's")(_alpha("rgba0"))
simple("D18 simulate age on RGBA sources", "D18", 0,
       lambda c: ["simulate", "age", c.fx.rgba128, c.work / "aged", "--sensor", "H", "--years", "0,8", "--seed", "1",
                  W, 1, "--quiet"])

# --- D06 / D07 / D17: content-free frames
simple("D06 fingerprint build of black frames", "D06", 3,
       lambda c: ["fingerprint", "build", c.fx.black, "-o", c.work / "b.npz", W, 1, "--quiet"], "content-free",
       absent=lambda c: [c.work / "b.npz"], quick=True)
simple("D06 match good FP against black frames", "D06", 3,
       lambda c: ["fingerprint", "match", c.fx.fp / "cam0.npz", c.fx.black, W, 1, "--quiet"], "content-free")
simple("D06 identify white frames", "D06", 3,
       lambda c: ["identify", c.fx.white, "--db", _db_with_cam0(c), W, 1, "--quiet"], "saturated")
simple("D07 same-device black vs white", "D07", 3,
       lambda c: ["same-device", c.fx.black, c.fx.white, "--region", "full", W, 1, "--quiet",
                  "--ageing-fingerprints", "0"], "all black")
simple("D17 model check on all-black frames", "D17", 3,
       lambda c: ["model", "check", c.fx.black, W, 1, "--quiet"], "content-free")
simple("D17 model check on all-white frames", "D17", 3,
       lambda c: ["model", "check", c.fx.white, W, 1, "--quiet"], "content-free")


def _db_with_cam0(c: Ctx, device: str = "cam0") -> Path:
    db = c.work / "db"
    r = c.run("fingerprint", "db", "add", db, c.fx.fp / "cam0.npz", "--device", device)
    if r.code != 0:
        raise RuntimeError(f"setup: db add failed: {r.err.strip()}")
    return db


# --- D08 / D09: malformed manifests
simple("D08 duplicate manifest rows (info)", "D08", 3,
       lambda c: ["info", copy_set(c.fx.tiny, c.work / "s", "file\nf0.png\nf1.png\nf0.png\nf1.png\n")],
       "already listed", quick=True)
simple("D08 duplicate row via another name (same-device)", "D08", 3,
       lambda c: ["same-device", copy_set(c.fx.cam0, c.work / "a", "file\n0.png\n1.png\n2.png\n./0.png\n"), c.fx.cam1,
                  W, 1, "--quiet"], "already listed")
simple("D09 unterminated quote (info)", "D09", 3,
       lambda c: ["info", copy_set(c.fx.tiny, c.work / "s", 'file,subject\nf0.png,"open\nf1.png,x\nf2.png,y\n')],
       "quoted field runs past")


# --- D10: checksum over metadata
def _d10(fp: str, change: str):
    def body(c: Ctx):
        db = c.work / "db"
        add = c.run("fingerprint", "db", "add", db, c.fx.fp / fp, "--device", "cam0")
        stored = next((db / "fingerprints").glob("*.npz"), None)
        if add.code != 0 or stored is None:
            return observed(add), ["setup: db add failed"]
        subprocess.run([c.python, "-c", EDIT_META, stored, change], check=True, capture_output=True)
        r = c.run("identify", c.fx.cam1, "--db", db, W, 1, "--quiet")
        return observed(r), check(r, 3, "'cam0' does not match the database index")
    return body


case("D10 edited n_images of a stored fingerprint, identify", "D10", "exit 3 naming the entry")(
    _d10("cam0.npz", '{"n_images": 99}'))
case("D10 edited frame_shape (centre crop of a wider frame), identify", "D10", "exit 3 naming the entry")(
    _d10("cam0c.npz", '{"frame_shape": [96, 192]}'))


# --- D11: about twenty inputs that ended in a traceback
def _loop_manifest(c: Ctx) -> Path:
    s = copy_set(c.fx.tiny, c.work / "s", "file\nf0.png\nloop.png\n")
    (s / "loop.png").symlink_to("loop.png")
    return s


def _latin1_name(c: Ctx) -> Path:
    s = copy_set(c.fx.tiny, c.work / "s")
    os.rename(s / "f0.png", os.fsencode(s) + b"/caf\xe9.png")
    return s


def _manifest_dir(c: Ctx) -> Path:
    s = copy_set(c.fx.tiny, c.work / "s")
    (s / "manifest.csv").mkdir()
    return s


D11 = [
    ("manifest row naming a symlink loop", ["info", _loop_manifest], 3, "loop.png"),
    ("non-UTF-8 file name", ["info", _latin1_name], 3, "caf\\xe9.png"),
    ("UTF-16 manifest", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s", "file\nf0.png\n".encode("utf-16"))], 3,
     "manifest.csv"),
    ("Latin-1 manifest", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s", "file,subject\nf0.png,caf\xe9\n"
                                                     .encode("latin-1"))], 3, "manifest.csv"),
    ("field over 131,072 characters", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s",
                                                                  "file,subject\nf0.png," + "x" * 140_000 + "\n")], 3,
     "manifest.csv"),
    ("manifest.csv is a folder", ["info", _manifest_dir], 3, "manifest.csv"),
    ("NUL in file", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s", "file\nf0\x00.png\n")], 3, "manifest.csv"),
    ("300-character name in file", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s", "file\n" + "a" * 300 + ".png\n")],
     3, "manifest.csv"),
    ("black_level=nan", ["info", lambda c: copy_set(c.fx.tiny, c.work / "s", "file,black_level\nf0.png,nan\n")], 3,
     "black_level"),
    ("truncated .npz, db add", ["fingerprint", "db", "add", lambda c: c.work / "db",
                                lambda c: c.fx.fp / "truncated.npz", "--device", "x"], 3, "truncated.npz"),
    ("truncated .npz, fingerprint match", ["fingerprint", "match", lambda c: c.fx.fp / "truncated.npz",
                                           lambda c: c.fx.cam0, W, "1", "--quiet"], 3, "truncated.npz"),
    ("metadata missing a key, db add", ["fingerprint", "db", "add", lambda c: c.work / "db",
                                        lambda c: c.fx.fp / "nokey.npz", "--device", "x"], 3, "nokey.npz"),
    ("metadata missing a key, match", ["fingerprint", "match", lambda c: c.fx.fp / "nokey.npz",
                                       lambda c: c.fx.cam0, W, "1", "--quiet"], 3, "nokey.npz"),
    ("metadata of the wrong type, db add", ["fingerprint", "db", "add", lambda c: c.work / "db",
                                            lambda c: c.fx.fp / "wrongtype.npz", "--device", "x"], 3, "wrongtype.npz"),
    ("metadata of the wrong type, match", ["fingerprint", "match", lambda c: c.fx.fp / "wrongtype.npz",
                                           lambda c: c.fx.cam0, W, "1", "--quiet"], 3, "wrongtype.npz"),
    ("date --model given a JSON list", ["date", lambda c: c.fx.scenes, "--model", lambda c: _write(c, "m.json", "[1, 2]")],
     3, "m.json"),
    ("simulate scenes --size 0x0", ["simulate", "scenes", lambda c: c.work / "s", "--size", "0x0"], 2, "--size"),
    ("simulate scenes --size 1x1", ["simulate", "scenes", lambda c: c.work / "s", "--size", "1x1"], 2, "--size"),
    ("simulate scenes --size 64x", ["simulate", "scenes", lambda c: c.work / "s", "--size", "64x"], 2, "--size"),
    ("fingerprint build -o EXISTING_DIR --force", ["fingerprint", "build", lambda c: c.fx.cam0, "-o",
                                                   lambda c: _mkdir(c, "folder"), "--force", W, "1", "--quiet"], 2,
     "is a folder"),
]


def _write(c: Ctx, name: str, text: str) -> Path:
    (c.work / name).write_text(text)
    return c.work / name


def _mkdir(c: Ctx, name: str) -> Path:
    (c.work / name).mkdir(exist_ok=True)
    (c.work / name / "keep.txt").write_text("keep")
    return c.work / name


def _lazy(parts: list) -> Callable[[Ctx], list]:
    return lambda c: [p(c) if callable(p) else p for p in parts]


for _i, (_what, _parts, _code, _needle) in enumerate(D11):
    simple(f"D11 {_what}", "D11", _code, _lazy(_parts), _needle, quick=_i in (1, 5, 16),
           absent=lambda c: [c.work / "db"])


@case("D11 truncated .npz in a database, identify", "D11", "exit 3 naming the stored file")
def _d11_identify(c: Ctx):
    db = _db_with_cam0(c)
    stored = next((db / "fingerprints").glob("*.npz"))
    stored.write_bytes((c.fx.fp / "truncated.npz").read_bytes())
    r = c.run("identify", c.fx.cam1, "--db", db, W, 1, "--quiet")
    return observed(r), check(r, 3, stored.name)


# --- D12: bounded requests
simple("D12 --years 0:1e6:1", "D12", 2,
       lambda c: ["simulate", "age", c.fx.scenes, c.work / "aged", "--years", "0:1e6:1"], "FORENSICS_MAX_AGES",
       absent=lambda c: [c.work / "aged", c.work / ".aged.partial"], timeout=30, quick=True)
simple("D12 PNG whose header declares 2.5 G pixels", "D12", 3, lambda c: ["info", c.fx.root / "bomb.png"],
       "FORENSICS_MAX_PIXELS", timeout=30)
simple("D12 defects detect --q 99999", "D12", 2,
       lambda c: ["defects", "detect", c.fx.scenes, "--q", "99999", "--report", c.work / "r"], "--q 99999",
       absent=lambda c: [c.work / "r"], timeout=30)
simple("D12 simulate scenes --size 100000x100000", "D12", 2,
       lambda c: ["simulate", "scenes", c.work / "s", "--size", "100000x100000"], "FORENSICS_MEMORY_LIMIT",
       absent=lambda c: [c.work / "s"], timeout=30)
simple("D12 simulate irises --size 100000x100000", "D12", 2,
       lambda c: ["simulate", "irises", c.work / "s", "--size", "100000x100000"], "FORENSICS_MEMORY_LIMIT",
       absent=lambda c: [c.work / "s"], timeout=30)


# --- D14: a full disk (a file-size limit: the kernel's EFBIG on the path ENOSPC takes)
def _d14(argv: Callable[[Ctx], list], out: Callable[[Ctx], Path], limit: int, named: Callable[[Ctx], tuple]):
    """A write refused by the device: exit 3 naming the file, no output, no temporary; the ``.OUT.partial`` of a
    resumable command (its finished work, for a rerun once there is room) is allowed."""
    def body(c: Ctx):
        r = c.run(*argv(c), fsize=limit)
        problems = check(r, 3, *named(c))
        if os.path.lexists(out(c)):
            problems.append("the output exists after a failed write")
        problems += [f"stray: {s}" for s in strays(c.work, allow_partial=True)]
        return observed(r), problems
    return body


case("D14 ulimit -f 20: fingerprint build -o", "D14", "exit 3 naming the file, no partial output")(_d14(
    lambda c: ["fingerprint", "build", c.fx.cam0, "-o", c.work / "fp.npz", W, 1, "--quiet"],
    lambda c: c.work / "fp.npz", 20 * 1024, lambda c: (f"{c.work / '.fp.npz.partial'}/", ": file too large")))
case("D14 ulimit -f 20: simulate scenes", "D14", "exit 3 naming the file, no partial output")(_d14(
    lambda c: ["simulate", "scenes", c.work / "s", "--count", "3", "--size", "320x240", "--rgb", "--quiet"],
    lambda c: c.work / "s", 20 * 1024, lambda c: (f"{c.work / 's' / 'scene_0000.png'}: file too large",)))
case("D14 ulimit -f 20: defects detect --report", "D14", "exit 3 naming the report, no partial report")(_d14(
    lambda c: ["defects", "detect", c.fx.bigscenes, "--mask", "all", W, 1, "--quiet", "--report", c.work / "r"],
    lambda c: c.work / "r", 20 * 1024, lambda c: (f"{c.work / 'r'}: file too large",)))


# --- D16
@case("D16 the same fingerprint under a second id", "D16", "exit 2 'identical'")
def _d16(c: Ctx):
    db = _db_with_cam0(c, "camA")
    r = c.run("fingerprint", "db", "add", db, c.fx.fp / "cam0.npz", "--device", "camB")
    return observed(r), check(r, 2, "identical to the fingerprint of device 'camA'")


# --- D19: what blocks
def _fifo_manifest(c: Ctx) -> Path:
    s = copy_set(c.fx.tiny, c.work / "s")
    os.mkfifo(s / "manifest.csv")
    return s


def _fifo_image(c: Ctx, manifest: str | None = None) -> Path:
    s = copy_set(c.fx.tiny, c.work / "s", manifest)
    os.mkfifo(s / "f9.png")
    return s


simple("D19 manifest.csv is a FIFO (info)", "D19", 3, lambda c: ["info", _fifo_manifest(c)], "manifest.csv",
       timeout=30, quick=True)
simple("D19 manifest.csv is a FIFO (fingerprint build)", "D19", 3,
       lambda c: ["fingerprint", "build", _fifo_manifest(c), "-o", c.work / "fp.npz", W, 1, "--quiet"], "manifest.csv",
       timeout=30)
simple("D19 a FIFO named like an image given to info", "D19", 3, lambda c: ["info", c.fx.root / "pipe.png"],
       "is not a regular file", timeout=30)
simple("D19 a manifest row naming a FIFO", "D19", 3,
       lambda c: ["info", _fifo_image(c, "file\nf0.png\nf9.png\n")], "f9.png", timeout=30)


@case("D19 a FIFO named like an image in a set without manifest", "D19", "exit 0 at once, the FIFO not an image")
def _fifo_in_set(c: Ctx):
    r = c.run("info", _fifo_image(c), "--json", timeout=30)
    problems = check(r, 0, json_out=True)
    if not problems and strict_json(r.out).get("n_images") != 3:
        problems.append(f"n_images {strict_json(r.out).get('n_images')}, not 3")
    return observed(r), problems

# --- D20: values that should be refused
D20_MANIFEST = [
    ("captured=0001-01-01", "file,captured\nf0.png,0001-01-01\n", "captured"),
    ("temperature_c=-300", "file,temperature_c\nf0.png,-300\n", "temperature_c"),
    ("a duplicated file column", "file,device,file\nf0.png,a,f1.png\n", "named twice"),
]
for _what, _manifest, _needle in D20_MANIFEST:
    simple(f"D20 {_what}", "D20", 3,
           (lambda m: lambda c: ["info", copy_set(c.fx.tiny, c.work / "s", m)])(_manifest), _needle)
D20_OPTIONS = [
    ("--years nan", lambda c: ["simulate", "age", c.fx.scenes, c.work / "a", "--years", "nan"], "--years"),
    ("--years 0,8,8", lambda c: ["simulate", "age", c.fx.scenes, c.work / "a", "--years", "0,8,8"], "--years"),
    ("--tau -1", lambda c: ["defects", "detect", c.fx.scenes, "--tau", "-1"], "--tau"),
    ("--sigma nan (detect)", lambda c: ["defects", "detect", c.fx.scenes, "--sigma", "nan"], "--sigma"),
    ("--threshold nan", lambda c: ["fingerprint", "match", c.fx.fp / "cam0.npz", c.fx.cam0, "--threshold", "nan"],
     "--threshold"),
    ("--sigma nan (identify)", lambda c: ["identify", c.fx.cam0, "--db", c.fx.fp, "--sigma", "nan"], "--sigma"),
]
for _what, _argv, _option in D20_OPTIONS:
    simple(f"D20 {_what}", "D20", 2, _argv, f"argument {_option}", quick=_what == "--years nan",
           absent=lambda c: [c.work / "a"])
simple("D20 an all-NaN fingerprint, db add", "D20", 3,
       lambda c: ["fingerprint", "db", "add", c.work / "db", c.fx.fp / "nan.npz", "--device", "x"], "nan.npz",
       absent=lambda c: [c.work / "db"])
simple("D20 same-device X X", "D20", 2,
       lambda c: ["same-device", c.fx.cam0, c.fx.cam0, "--region", "full", W, 1, "--quiet"], "same 6 images")


@case("D20 EXIF exposure 0 and a 1970 date are unknown", "D20", "exit 0, exposure_s and captured null")
def _exif0(c: Ctx):
    r = c.run("info", c.fx.root / "exif0.jpg", "--json")
    problems = check(r, 0, json_out=True)
    if not problems:
        got = strict_json(r.out)
        for key in ("exposure_s", "captured"):
            if got.get(key) is not None:
                problems.append(f"{key} = {got.get(key)!r}, not unknown")
    return observed(r), problems


@case("D20 a growth model with reversed dates", "D20", "exit 3 naming the model file")
def _reversed(c: Ctx):
    model = json.loads((c.fx.root / "model.json").read_text())
    model["dates"] = model["dates"][::-1]
    path = _write(c, "reversed.json", json.dumps(model))
    r = c.run("date", c.fx.scenes, "--model", path, W, 1, "--quiet")
    return observed(r), check(r, 3, "reversed.json")


# --- D21: small breaches
simple("D21 simulate scenes --count 0", "D21", 2, lambda c: ["simulate", "scenes", c.work / "s", "--count", "0"],
       "--count", absent=lambda c: [c.work / "s"], quick=True)
simple("D21 identify --sigma -1", "D21", 2, lambda c: ["identify", c.fx.cam0, "--db", c.fx.fp, "--sigma=-1"],
       "--sigma")


@case("D21 corrupt PNG: one line, no 'libpng error'", "D21", "exit 3, exactly one line naming the file")
def _libpng(c: Ctx):
    s = copy_set(c.fx.tiny, c.work / "s")
    data = (s / "f1.png").read_bytes()
    (s / "f1.png").write_bytes(data[:60] + bytes(len(data) - 60))
    r = c.run("fingerprint", "build", s, "-o", c.work / "fp.npz", W, 1, "--quiet")
    problems = check(r, 3, "f1.png")
    if "libpng" in r.err:
        problems.append("libpng's own line on stderr")
    return observed(r), problems


@case("D21 1x1 frames: the error names the file", "D21", "exit 3 naming the file")
def _tiny_frames(c: Ctx):
    s = c.work / "s"
    s.mkdir()
    subprocess.run([c.python, "-c", "import sys, numpy as np; from forensics.io.images import write_image; "
                    "[write_image(f'{sys.argv[1]}/p{i}.png', np.full((1, 1), 9 + i, np.uint8)) for i in range(3)]",
                    s], check=True, capture_output=True)
    r = c.run("defects", "detect", s, W, 1, "--quiet")
    return observed(r), check(r, 3, "p0.png")


simple("D21 info nonexistent", "D21", 3, lambda c: ["info", c.work / "nonexistent"], "does not exist", quick=True)


@case("D21 db remove ' camA ' strips the id", "D21", "exit 0, removed 'camA'")
def _strip(c: Ctx):
    db = _db_with_cam0(c, "camA")
    r = c.run("fingerprint", "db", "remove", db, " camA ")
    problems = check(r, 0)
    if "removed 'camA'" not in r.out:
        problems.append("no 'removed camA' on stdout")
    return observed(r), problems


@case("D21 ISO basic date 20090701 accepted", "D21", "exit 0, captured 2009.4959")
def _iso_basic(c: Ctx):
    s = copy_set(c.fx.tiny, c.work / "s", "file,captured\nf0.png,20090701\nf1.png,20100101T000000\nf2.png,2011\n")
    r = c.run("info", s, "--json")
    problems = check(r, 0, json_out=True)
    if not problems:
        got = strict_json(r.out).get("captured") or []
        if not got or abs(got[0] - 2009.4959) > 1e-3:
            problems.append(f"captured {got}")
    return observed(r), problems


@case("D21 --report FILE --force leaves no .FILE.old-PID", "D21", "exit 0, report folder, nothing beside")
def _old(c: Ctx):
    (c.work / "r").write_text("an earlier report, as one file")
    r = c.run("defects", "detect", c.fx.scenes, "--mask", "all", W, 1, "--quiet", "--report", c.work / "r", "--force")
    problems = check(r, 0)
    if sorted(p.name for p in c.work.iterdir()) != ["r"] or not (c.work / "r" / "index.html").is_file():
        problems.append(f"beside the report: {sorted(p.name for p in c.work.iterdir())}")
    return observed(r), problems


# --- D22: terminal escapes
def _esc_set(c: Ctx) -> Path:
    folder = c.work / f"set{ESC}]0;pwned\x07"
    folder.mkdir()
    rows = ["file,device"]
    for i, p in enumerate(sorted(c.fx.scenes.glob("*.png"))[:3]):
        name = f"img{ESC}[31m_{i}.png"
        shutil.copy(p, folder / name)
        rows.append(f"{name},cam{ESC}[2J")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder


simple("D22 ESC in names and fields: info", "D22", 0, lambda c: ["info", _esc_set(c)], quick=True)
simple("D22 ESC in names and fields: defects detect", "D22", 0,
       lambda c: ["defects", "detect", _esc_set(c), "--mask", "all", W, 1])
simple("D22 ESC in a missing path's error", "D22", 3,
       lambda c: ["date", c.work / f"missing{ESC}[2J", "--model", c.fx.root / "model.json"], "missing\\x1b[2J")
simple("D22 ESC in an option value", "D22", 2, lambda c: ["simulate", "scenes", c.work / "s", "--count", f"{ESC}[2J"],
       "--count")


# --- D23: TIFF dates
@case("D23 aged TIFFs carry no write date; manifest dates kept", "D23", "exit 0, file captured null, set 2009.0")
def _d23(c: Ctx):
    r = c.run("simulate", "age", c.fx.tifs, c.work / "aged", "--sensor", "H", "--years", "0,8", "--seed", "1",
              "--start", "2001", W, 1, "--quiet")
    problems = check(r, 0)
    if problems:
        return observed(r), problems
    tif = sorted((c.work / "aged" / "year_008").glob("*.tif"))
    one = c.run("info", tif[0], "--json")
    whole = c.run("info", c.work / "aged" / "year_008", "--json")
    problems += check(one, 0, json_out=True) + check(whole, 0, json_out=True)
    if not problems:
        if strict_json(one.out).get("captured") is not None:
            problems.append("the TIFF claims a capture date of its own")
        if strict_json(whole.out).get("captured") != [2009.0, 2009.0]:
            problems.append(f"set captured {strict_json(whole.out).get('captured')}")
    return observed(one), problems


# --- D24: umask
def _umask(mask: int):
    def body(c: Ctx):
        r = c.run("simulate", "age", c.fx.scenes, c.work / "aged", "--sensor", "H", "--years", "0,8", "--seed", "1",
                  W, c.workers, "--quiet", umask=mask)
        d = c.run("fingerprint", "db", "add", c.work / "db", c.fx.fp / "cam0.npz", "--device", "cam", umask=mask)
        problems = check(r, 0) + check(d, 0)
        for root in (c.work / "aged", c.work / "db"):
            if not root.exists():
                continue
            for name, mode in modes(root).items():
                want = (0o777 if (root.parent / name).is_dir() else 0o666) & ~mask
                if mode != want:
                    problems.append(f"{name}: {mode:o}, not {want:o}")
                    break
        return f"exit {r.code}/{d.code}", problems
    return body


case("D24 umask 022: ageing (N workers) and db add", "D24", "folders 755, files 644")(_umask(0o022))
case("D24 umask 002: ageing (N workers) and db add", "D24", "folders 775, files 664")(_umask(0o002))


# --- D25: a database of several sensor sizes
@case("D25 identify against two sensor sizes reports both shares", "D25", "exit 0, aligned and searched 0.5 each")
def _d25(c: Ctx):
    db = _db_with_cam0(c)
    add = c.run("fingerprint", "db", "add", db, c.fx.fp / "big.npz", "--device", "big")
    r = c.run("identify", c.fx.cam0, "--db", db, W, 1, "--quiet", "--json")
    problems = check(add, 0) + check(r, 0, json_out=True)
    if not problems:
        got = strict_json(r.out)
        budget = got["queries"][0].get("budget", {})
        if {k: budget.get(k, {}).get("share") for k in ("aligned", "searched")} != {"aligned": 0.5, "searched": 0.5}:
            problems.append(f"budget {budget}")
        if got.get("n_attributed") != 6:
            problems.append(f"{got.get('n_attributed')} of 6 attributed")
    return observed(r), problems


# ----------------------------------------------------------------------------- held up: keep it so
@case("held: corrupt image in a set (info, fingerprint build)", "held", "exit 3 naming the file")
def _corrupt(c: Ctx):
    s = copy_set(c.fx.tiny, c.work / "s")
    (s / "f1.png").write_bytes((s / "f1.png").read_bytes()[:40])
    (s / "f2.png").write_bytes(b"not an image at all")
    runs = [c.run("info", s), c.run("fingerprint", "build", s, "-o", c.work / "fp.npz", W, 1, "--quiet")]
    problems = [p for r in runs for p in check(r, 3, "f1.png")]
    if (c.work / "fp.npz").exists():
        problems.append("fp.npz written")
    return observed(runs[1]), problems


@case("held: mixed frame sizes", "held", "exit 3 naming the odd file")
def _mixed(c: Ctx):
    s = copy_set(c.fx.tiny, c.work / "s")
    shutil.copy(c.fx.scenes / "scene_0000.png", s / "odd.png")
    runs = [c.run("info", s), c.run("defects", "detect", s, W, 1, "--quiet")]
    return observed(runs[1]), [p for r in runs for p in check(r, 3, "odd.png")]


def _outside(kind: str):
    def body(c: Ctx):
        s = copy_set(c.fx.tiny, c.work / "s")
        shutil.copy(c.fx.tiny / "f0.png", c.work / "victim.png")
        if kind == "link":
            (s / "link.png").symlink_to(c.work / "victim.png")
        name = {"dotdot": "../victim.png", "absolute": str(c.work / "victim.png"), "link": "link.png"}[kind]
        (s / "manifest.csv").write_text(f"file\nf0.png\n{name}\n")
        r = c.run("info", s)
        allowed = c.run("info", s, "--allow-outside", "--json")
        return observed(r), check(r, 3, "outside") + check(allowed, 0, json_out=True)
    return body


for _kind in ("dotdot", "absolute", "link"):
    case(f"held: manifest row leaving the folder ({_kind})", "held", "exit 3; with --allow-outside exit 0",
         quick=_kind == "dotdot")(_outside(_kind))
simple("held: bad manifest value iso=fast", "held", 3,
       lambda c: ["info", copy_set(c.fx.tiny, c.work / "s", "file,iso\nf0.png,fast\n")], "not a number")


def _damaged_index(content: Callable[[bytes], bytes]):
    def body(c: Ctx):
        db = _db_with_cam0(c)
        index = db / "index.sqlite"
        for extra in ("index.sqlite-wal", "index.sqlite-shm"):
            (db / extra).unlink(missing_ok=True)
        index.write_bytes(content(index.read_bytes()))
        runs = [c.run("fingerprint", "db", "list", db), c.run("identify", c.fx.cam0, "--db", db, W, 1, "--quiet")]
        return observed(runs[0]), [p for r in runs for p in check(r, 3, "index.sqlite")]
    return body


case("held: index.sqlite is garbage", "held", "exit 3 naming index.sqlite")(_damaged_index(lambda b: b"garbage" * 100))
case("held: index.sqlite truncated", "held", "exit 3 naming index.sqlite")(_damaged_index(lambda b: b[:1000]))


def _db_add_interrupted(signum: int, delay: float):
    def body(c: Ctx):
        db = _db_with_cam0(c)
        started = time.monotonic()
        proc, log = c.run.start("fingerprint", "db", "add", db, c.fx.fp / "cam1.npz", "--device", "cam1")
        time.sleep(delay)
        if proc.poll() is None:
            os.kill(proc.pid, signum)
        r = c.run.finish(proc, log, started)
        problems = []
        # -SIGINT with nothing on stderr: the signal came after the command had finished, while Python exited
        finished = r.code == -signal.SIGINT and not r.err.strip()
        if r.code not in (0, 130, -signal.SIGKILL) and not finished:
            problems.append(f"interrupted add exit {r.code}")
        if r.code == 130:
            problems += check(r, 130)
        listed = c.run("fingerprint", "db", "list", db, "--json")
        problems += check(listed, 0, json_out=True)
        again = c.run("fingerprint", "db", "add", db, c.fx.fp / "cam1.npz", "--device", "cam1", "--replace")
        problems += check(again, 0)
        final = c.run("fingerprint", "db", "list", db, "--json")
        problems += check(final, 0, json_out=True)
        if not problems and len(strict_json(final.out).get("entries", strict_json(final.out))) != 2:
            problems.append(f"after a second add: {final.out[:200]}")
        problems += [f"stray: {s}" for s in strays(db)]
        return f"interrupted exit {r.code}; list exit {listed.code}", problems
    return body


for _sig, _delay in ((signal.SIGKILL, 0.4), (signal.SIGKILL, 0.9), (signal.SIGINT, 0.7)):
    case(f"held: {signal.Signals(_sig).name} after {_delay}s of db add", "held",
         "database whole: list 0, a new add 0, no leftovers")(_db_add_interrupted(_sig, _delay))


@case("held: three concurrent db writers and a reader", "held", "every add exit 0, three entries")
def _concurrent(c: Ctx):
    db = _db_with_cam0(c, "seed")
    c.run("fingerprint", "db", "remove", db, "seed")
    started = time.monotonic()
    procs = [c.run.start("fingerprint", "db", "add", db, c.fx.fp / f, "--device", d)
             for f, d in (("cam0.npz", "a"), ("cam1.npz", "b"), ("big.npz", "c"))]
    procs.append(c.run.start("fingerprint", "db", "list", db, "--json"))
    runs = [c.run.finish(p, log, started) for p, log in procs]
    problems = [p for r in runs[:3] for p in check(r, 0)] + check(runs[3], 0, json_out=True)
    final = c.run("fingerprint", "db", "list", db, "--json")
    problems += check(final, 0, json_out=True)
    if not problems:
        got = strict_json(final.out)
        entries = got.get("entries", got) if isinstance(got, dict) else got
        if len(entries) != 3:
            problems.append(f"{len(entries)} entries, not 3")
    return "exits " + ",".join(str(r.code) for r in runs), problems


simple("held: option check --workers 0", "held", 2, lambda c: ["defects", "detect", c.fx.scenes, W, "0"],
       "argument --workers", quick=True)
simple("held: option check --seed -1", "held", 2,
       lambda c: ["simulate", "age", c.fx.scenes, c.work / "a", "--seed", "-1"], "argument --seed")
simple("held: option check unknown option", "held", 2, lambda c: ["info", c.fx.scenes, "--no-such-option"],
       "unrecognized")
simple("held: option check --pfa 2", "held", 2, lambda c: ["identify", c.fx.cam0, "--db", c.fx.fp, "--pfa", "2"],
       "argument --pfa")
simple("held: simulate age OUT inside SRC", "held", 2,
       lambda c: ["simulate", "age", c.fx.scenes, c.fx.scenes / "aged"], GUARD)
simple("held: cluster -o inside SET", "held", 2, lambda c: ["cluster", c.fx.cam0, "-o", c.fx.cam0 / "out"], GUARD)
simple("held: cluster -o containing SET", "held", 2, lambda c: ["cluster", c.fx.cam0, "-o", c.fx.root], GUARD)


@case("held: HTML in a set name is escaped in the report", "held", "exit 0, &lt;img in index.html, no raw <img")
def _html(c: Ctx):
    s = copy_set(c.fx.tiny, c.work / "<img src=x onerror=alert(1)>")
    r = c.run("defects", "detect", s, "--mask", "all", W, 1, "--quiet", "--report", c.work / "r")
    problems = check(r, 0)
    if not problems:
        page = (c.work / "r" / "index.html").read_text()
        if "<img src=x" in page or "&lt;img src=x onerror=alert(1)&gt;" not in page:
            problems.append("the name is not escaped in the page")
    return observed(r), problems


@case("held: --json is standard JSON (fingerprint match)", "held", "exit 0, strict JSON")
def _json(c: Ctx):
    r = c.run("fingerprint", "match", c.fx.fp / "cam0.npz", c.fx.cam1, W, c.workers, "--quiet", "--json")
    return observed(r), check(r, 0, json_out=True)


@case("held: parallel commands on N workers (wheel from the checkout)", "held", "exit 0 for defects detect, "
      "same-device, fingerprint build on N workers")
def _parallel(c: Ctx):
    runs = [c.run("defects", "detect", c.fx.scenes, "--mask", "all", W, c.workers, "--quiet"),
            c.run("fingerprint", "build", c.fx.cam0, "-o", c.work / "fp.npz", W, c.workers, "--quiet"),
            c.run("same-device", c.fx.cam0, c.fx.cam1, "--region", "full", W, c.workers, "--quiet",
                  "--ageing-fingerprints", "0", "--bootstrap", "100", "--json")]
    return ", ".join(str(r.code) for r in runs), [p for r in runs for p in check(r, 0)]
