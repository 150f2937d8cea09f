"""Replay issue 26's adversarial sweep against an installed ``forensics`` command and check every promise.

Issue 26 listed 24 defects (D01–D24) found by an adversarial sweep, D25 from a held-out identification
run, and the categories of cases that held up.  This script builds small fixtures in a
temporary folder (scenes from ``forensics simulate``, simulated PRNU cameras from the installed package's
sensor model (``forensics.demo.prnu``), constant and RGBA sets, small manifests, fingerprints and a database) and runs every
case the issue names through the command given by ``--forensics``, from the folder given by ``--cwd``, so it
can replay a wheel installed in a fresh venv from inside a copy of the checkout (where the checkout's own
``forensics/`` folder is the current folder).

For each case it checks what README.md promises (and the regression tests of tests/cli, tests/io,
tests/prnu, tests/_shared assert): the exit code (0 success, 2 usage, 3 bad input data, 130 Ctrl-C, 143
SIGTERM), one line on stderr for an error and never a traceback, no control character reaching the
terminal, standard JSON for ``--json``, no process of the run left alive (each command runs in a session of
its own, found afterwards in /proc), no input changed or deleted (every fixture file hashed after every
case), and nothing half-written (no output of a failed run, no ``.NAME.*.part``, ``.NAME.old-PID`` or
``.OUT.partial`` left where the run did not keep resumable work on purpose).

Run::

    python benchmarks/adversarial_replay.py                                   # the forensics on PATH
    python benchmarks/adversarial_replay.py --forensics /tmp/venv-wheel/bin/forensics --cwd /tmp/copy \
        --workers 2 --json replay.json

The fixtures are made with the Python interpreter of the tested install (read from the console script's
first line), so the script itself needs only the standard library.  The machinery (running, checking,
fixtures) is in ``_replay_harness.py``, the cases in ``_replay_cases.py``; ``--quick`` runs the subset the
test suite keeps (tests/cli/test_adversarial_replay.py).  Exit status: 0 when every case keeps its promise,
1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import _replay_cases  # noqa: F401 - registers the cases (benchmarks/ is on sys.path when a script runs)
from _replay_harness import CASES, Case, Ctx, Fixtures, Runner, python_of, tree_hashes


# ----------------------------------------------------------------------------- driver
@dataclass
class Outcome:
    case: str
    defect: str
    expected: str
    observed: str
    ok: bool
    problems: list[str]
    seconds: float
    stderr: str = ""  # of the case's last command, when the case fails


def run_case(item: Case, ctx: Ctx, before: dict[str, str]) -> Outcome:
    started = time.monotonic()
    try:
        seen, problems = item.body(ctx)
    except Exception as exc:  # a broken setup is a failed case, not a crashed replay
        seen, problems = f"replay error: {type(exc).__name__}: {exc}"[:160], ["the case could not run"]
    after = tree_hashes(ctx.fx.root)
    if after != before:
        changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
        problems.append(f"inputs changed: {changed[:3]}")
    import threading

    err = "" if not problems else getattr(ctx.run, "last_err", {}).get(threading.get_ident(), "")
    return Outcome(item.name, item.defect, item.expected, seen, not problems, problems,
                   round(time.monotonic() - started, 2), err)


def table(outcomes: list[Outcome]) -> str:
    width = max(len(o.case) for o in outcomes)
    lines = [f"{'case':<{width}}  {'defect':<6}  {'result':<4}  expected → observed"]
    for o in outcomes:
        lines.append(f"{o.case:<{width}}  {o.defect:<6}  {'pass' if o.ok else 'FAIL':<4}  {o.expected} → {o.observed}"
                     + ("" if o.ok else f"   [{'; '.join(o.problems)}]"))
    return "\n".join(lines)


def select(only: str | None, quick: bool) -> list[Case]:
    chosen = [c for c in CASES if not quick or c.quick]
    if only:
        pattern = re.compile(only)
        chosen = [c for c in chosen if pattern.search(c.name) or pattern.search(c.defect)]
    return chosen


# Cases that send signals at chosen moments, limit file sizes or race runs against each other run alone (after
# the others), so that a neighbour's load cannot change what they observe.
SERIAL = re.compile(r"SIG|kill|D01|D04|D13|D15|two simulate|concurrent|ulimit")


def replay(forensics: str, cwd: Path, workers: int, only: str | None = None, quick: bool = False,
           tmp: Path | None = None, jobs: int = 2, progress: Callable[[str], None] | None = None) -> list[Outcome]:
    """Build the fixtures and run the chosen cases (``jobs`` at a time, the timing-sensitive ones alone);
    returns one outcome per case, in the order of :data:`CASES`."""
    from concurrent.futures import ThreadPoolExecutor

    with tempfile.TemporaryDirectory(prefix="replay-", dir=tmp) as scratch:
        root = Path(scratch)
        runner = Runner(forensics, cwd, workers, root / "logs")
        python = python_of(forensics)
        fx = Fixtures(root / "inputs", runner, python, quick)
        before = tree_hashes(fx.root)
        chosen = list(enumerate(select(only, quick)))

        def one(numbered: tuple[int, Case]) -> Outcome:
            n, item = numbered
            work = root / "work" / f"case{n:03d}"
            work.mkdir(parents=True)
            outcome = run_case(item, Ctx(runner, fx, work, workers, python), before)
            if progress:
                progress(f"{'pass' if outcome.ok else 'FAIL'} {outcome.seconds:6.1f}s  {item.name}"
                         + ("" if outcome.ok else f"  [{'; '.join(outcome.problems)}]"))
            return outcome

        together = [x for x in chosen if not SERIAL.search(x[1].name)]
        alone = [x for x in chosen if SERIAL.search(x[1].name)]
        with ThreadPoolExecutor(max(1, jobs)) as pool:
            results = dict(zip([n for n, _ in together], pool.map(one, together), strict=True))
        results.update({n: one((n, item)) for n, item in alone})
        return [results[n] for n, _ in chosen]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--forensics", default=shutil.which("forensics"), help="the command to test (default: PATH)")
    parser.add_argument("--cwd", type=Path, default=Path.cwd(), help="folder to run it from (default: here)")
    parser.add_argument("--workers", type=int, default=2, help="workers for the cases that use them (default 2)")
    parser.add_argument("--only", help="regular expression on case names or defect ids")
    parser.add_argument("--quick", action="store_true", help="only the cheap subset the test suite runs")
    parser.add_argument("--jobs", type=int, default=2, help="cases run at once, except the timing-sensitive ones "
                        "(default 2)")
    parser.add_argument("--json", type=Path, help="write the outcomes here")
    parser.add_argument("--tmp", type=Path, help="parent of the temporary folder")
    args = parser.parse_args(argv)
    if not args.forensics:
        parser.error("no forensics on PATH; give --forensics")
    forensics = str(Path(args.forensics).absolute())
    started = time.monotonic()
    outcomes = replay(forensics, args.cwd.resolve(), args.workers, args.only, args.quick, args.tmp, args.jobs,
                      progress=lambda line: print(line, file=sys.stderr, flush=True))
    minutes = (time.monotonic() - started) / 60
    print(table(outcomes))
    passed = sum(o.ok for o in outcomes)
    defects = sorted({o.defect for o in outcomes if o.defect.startswith("D")})
    print(f"\n{passed} of {len(outcomes)} cases keep their promise ({len(outcomes) - passed} fail); "
          f"{len(defects)} defects covered; {minutes:.1f} min; forensics = {forensics}; cwd = {args.cwd}; "
          f"workers = {args.workers}")
    if args.json:
        args.json.write_text(json.dumps({"forensics": forensics, "cwd": str(args.cwd), "workers": args.workers,
                                         "passed": passed, "total": len(outcomes), "minutes": round(minutes, 2),
                                         "cases": [asdict(o) for o in outcomes]}, indent=1, allow_nan=False))
    return 0 if passed == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
