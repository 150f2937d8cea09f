"""Time ``check_auto`` on one folder and compare two such runs (issue 27: the check's cost per pixel).

    # one run: CPU and wall seconds, peak RSS, load average, full predictions made, and every result
    python benchmarks/time_check_auto.py run /tmp/bce27/hidden-prnu --out after.json
    python benchmarks/time_check_auto.py run /tmp/bce27/standard-1 --region 88,128,64,64 --out after.json
    # a commit's code side by side with the worktree's: a snapshot on PYTHONPATH
    git archive <commit> forensics | tar -x -C /tmp/snap && PYTHONPATH=/tmp/snap python ... run ...
    # how far the results moved: each parameter in its standard errors, errors, gof, the path
    python benchmarks/time_check_auto.py compare before.json after.json

The data: ``make_hidden("prnu", out, rng=1)`` (128 × 128 × 108 frames) and ``fixtures.emva.make_standard_series``
(seed 1: 320 × 240 × 96 frames; the region ``88,128,64,64`` is its central 64 × 64).  CPU seconds are the
process's own (``time.process_time``); on a shared machine they are inflated by the load, so compare runs made
side by side.
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import os
import resource
import sys
import time


def run(folder: str, region: str | None, out: str | None) -> dict:
    from forensics.check import prediction
    from forensics.check.select import check_auto
    from forensics.sensor.model import Device

    calls: collections.Counter = collections.Counter()

    def counted(cls, name):
        inner = getattr(cls, name)

        def wrapper(*a, **k):
            calls[name] += 1
            return inner(*a, **k)

        setattr(cls, name, wrapper)

    counted(prediction.Predictor, "predict")
    counted(Device, "mean_signal")
    box = tuple(int(v) for v in region.split(",")) if region else None
    load0 = os.getloadavg()[0]
    cpu, wall = time.process_time(), time.time()
    path = check_auto(folder, region=box)
    cpu, wall = time.process_time() - cpu, time.time() - wall
    res = path.result
    d = res.to_dict()
    record = {"cpu_s": cpu, "wall_s": wall, "load": [load0, os.getloadavg()[0]],
              "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "calls": dict(calls),
              "added": path.added, "stopped": path.stopped,
              "not_converged": [p.label for p in res.params if not p.converged],
              "params": {f"{p.effect}.{p.name}": [p.value, p.se] for p in res.params},
              "error": d.get("error"), "gof": d.get("gof"),
              "path": [{"step": s.label, "error": s.error, "gof": s.gof, "flagged": s.flagged} for s in path.steps]}
    if out:
        with open(out, "w") as fh:
            json.dump(record, fh, indent=1, default=str)
    print(json.dumps({k: record[k] for k in ("cpu_s", "wall_s", "load", "peak_rss_mb", "calls", "added")}))
    return record


def _flat(d, prefix=""):
    out = {}
    for k, v in (d or {}).items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def compare(a_path: str, b_path: str) -> None:
    a, b = (json.load(open(p)) for p in (a_path, b_path))
    print(f"cpu {a['cpu_s']:.2f} → {b['cpu_s']:.2f} s; peak RSS {a['peak_rss_mb']:.0f} → {b['peak_rss_mb']:.0f} MB; "
          f"added {a['added']} → {b['added']}; not converged {b['not_converged']}")
    worst = 0.0
    for k, (v, se) in a["params"].items():
        v2, _ = b["params"].get(k, (None, None))
        if v2 is None:
            print(f"  {k}: missing")
            continue
        moved = abs(v2 - v)
        z = moved / se if se else math.nan
        worst = max(worst, z) if se else worst
        print(f"  {k:32s} {v:.9g} → {v2:.9g}  " + (f"{z:.2g} SE" if se else f"relative {moved / max(abs(v), 1e-300):.2g}"))
    print(f"  largest move: {worst:.2g} SE")
    for key in ("error", "gof"):
        fa, fb = _flat(a[key]), _flat(b[key])
        for k in fa:
            print(f"  {key}.{k}: {fa[k]} → {fb.get(k)}")
    for sa, sb in zip(a["path"], b["path"]):
        print(f"  step {sa['step']} → {sb['step']}: flagged {sa['flagged']} → {sb['flagged']}")


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    r = sub.add_parser("run")
    r.add_argument("folder")
    r.add_argument("--region", help="top,left,height,width")
    r.add_argument("--out")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    args = parser.parse_args(argv)
    if args.what == "run":
        run(args.folder, args.region, args.out)
    else:
        compare(args.before, args.after)


if __name__ == "__main__":
    main(sys.argv[1:])
