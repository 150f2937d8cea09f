#!/usr/bin/env python3
"""One case of the model-check sweep under two revisions of the code, side by side in the same run.

Each revision's ``forensics``, ``fixtures`` and ``benchmarks`` are taken from git (``git archive``) into a
temporary folder; both run the same case (:func:`sweep_check.run_one`: write the hidden-effect dataset, the base
check, the check with the effect added) at the same time, one process each, so that both see the same machine
load.  Prints each revision's wall and CPU seconds and whether the two results agree (the sweep's figures:
errors, gof, flags; to ``--rtol``).

Usage::

    .venv/bin/python benchmarks/bench_check_versions.py --base 07b0096 --case dsnu,camera,1
    .venv/bin/python benchmarks/bench_check_versions.py --base 07b0096 --new HEAD --case dark_current,camera,1 --json out.json
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1] + '/benchmarks'); sys.path.insert(0, sys.argv[1])
from sweep_check import run_one
effect, conv, seed = sys.argv[2].split(',')
wall, cpu = time.perf_counter(), time.process_time()
result = run_one((effect, int(seed), conv))
result['bench_wall'] = time.perf_counter() - wall
result['bench_cpu'] = time.process_time() - cpu
print(json.dumps(result, default=str))
"""


def export(revision: str, into: Path) -> Path:
    """The revision's library, fixtures and benchmarks in ``into`` (fixtures also as ``forensics.fixtures``, as
    the installed package has them)."""
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "forensics", "fixtures", "benchmarks"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    subprocess.run(["cp", "-r", str(into / "fixtures"), str(into / "forensics" / "fixtures")], check=True)
    return into


def differences(a, b, rtol: float, path: str = "") -> list[str]:
    """Where two results differ (numbers beyond ``rtol``, anything else unequal); timings left out."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if key in ("seconds", "bench_wall", "bench_cpu"):
                continue
            out += differences(a.get(key), b.get(key), rtol, f"{path}.{key}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, rtol, f"{path}[{i}]")]
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        same = math.isclose(a, b, rel_tol=rtol, abs_tol=1e-12) or (math.isnan(a) and math.isnan(b))
        return [] if same else [f"{path}: {a} vs {b}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--new", default=None, help="git revision (default: the working tree)")
    ap.add_argument("--case", required=True, help="effect,convention,seed (e.g. dsnu,camera,1)")
    ap.add_argument("--rtol", type=float, default=1e-3, help="relative tolerance for 'same result'")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-versions-") as tmp:
        trees = {"base": export(args.base, Path(tmp) / "base")}
        trees["new"] = export(args.new, Path(tmp) / "new") if args.new else ROOT
        procs = {name: subprocess.Popen([sys.executable, "-c", _CHILD, str(tree), args.case], cwd=tree,
                                        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": ""})
                 for name, tree in trees.items()}
        results = {}
        for name, proc in procs.items():
            out, _ = proc.communicate()
            if proc.returncode:
                print(f"{name}: failed (exit {proc.returncode})", file=sys.stderr)
                return 1
            results[name] = json.loads(out.strip().splitlines()[-1])
    diff = differences(results["base"], results["new"], args.rtol)
    for name in ("base", "new"):
        r = results[name]
        print(f"{name:4s} {args.base if name == 'base' else (args.new or 'working tree'):>12s}: "
              f"{r['bench_wall']:7.1f} s wall, {r['bench_cpu']:7.1f} s CPU, pass {r.get('pass')}")
    print(f"speed-up {results['base']['bench_wall'] / results['new']['bench_wall']:.2f}x; "
          + ("same result" if not diff else f"{len(diff)} differences beyond rtol {args.rtol}:"))
    for line in diff[:20]:
        print("  " + line)
    if args.json:
        from forensics._shared.atomic import write_text
        from forensics._shared.jsonsafe import dumps

        record = {"case": args.case, "base": args.base, "new": args.new or "working tree", "results": results,
                  "differences": diff}
        write_text(args.json, dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
