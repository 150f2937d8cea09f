"""Merge the finished (sensor, age) items of ``forensics impact`` checkpoints into one result and report.

Run::

    .venv/bin/python benchmarks/impact_merge.py CKPT [CKPT ...] OUT.json [--report DIR]

Every run must have the same seed, ages, matchers, protocols and images (its ``config.json``).  Each sensor's
device and frame noise come from its own keyed stream (``keyed_generator(seed, 1, crc32(name))``) and the class
resamples from ``keyed_generator(seed, 2)``, so a sensor's units do not depend on which other sensors a run
had: units of ``--sensors A,…`` and ``--sensors G,H`` runs merge into exactly what one ``--sensors A,G,H`` run
gives, and the trends and spreads are recomputed from the merged units (``experiment.trends``/``spreads``).
A sensor is taken when all its ages are present; a missing age-0 item of a sensor whose other ages are there
is the run's reuse of the first sensor's age 0 (age 0 of a noiseless sensor is the source image).  Sensors
with missing items are left out and named.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from forensics._shared import safecodec
from forensics._shared.atomic import write_bytes
from forensics.impact.experiment import ImpactResult, _classes, spreads, trends
from forensics.io.dataset import open_dataset


def merge(folders: list[Path]) -> ImpactResult:
    units, sensors, config = [], [], None
    for folder in folders:
        c = json.loads((folder / "config.json").read_text())
        c = c.get("config", c)
        if config is not None and any(c[k] != config[k] for k in ("ages", "matchers", "protocols", "seed", "files")):
            raise SystemExit(f"{folder}: other settings than {folders[0]}")
        config = config or c
        ages = c["ages"]
        for s_index, name in enumerate(c["sensors"]):
            paths = [folder / f"item-sensor{s_index:02d}-age{a:03d}.npz" for a in range(len(ages))]
            if not paths[0].exists() and all(p.exists() for p in paths[1:]):
                zero = sorted(folder.glob("item-sensor*-age000.npz"))
                if zero:
                    print(f"{folder}: sensor {name}'s age 0 is {zero[0].name} (reused by the run)")
                    paths[0] = zero[0]
            if not all(p.exists() for p in paths) or name in sensors:
                print(f"{folder}: sensor {name} left out ({sum(p.exists() for p in paths)} of {len(ages)} ages)")
                continue
            for a_index, path in enumerate(paths):
                units += [dataclasses.replace(u, sensor=name, age=ages[a_index])
                          for u in safecodec.decode(path)["units"]]
            sensors.append(name)
    if not units:
        raise SystemExit("no complete sensor in these checkpoints")
    first = units[0].eer
    n_classes = len(_classes(open_dataset(config["source"]))[1])
    result = ImpactResult(config["source"], len(config["files"]), n_classes, first.n_genuine, first.n_impostor,
                          False, sensors, config["ages"], config["matchers"], config["protocols"], config["n_boot"],
                          config["level"], config["seed"], units, segmentations=config["segmentations"])
    result.trends = trends(result)
    result.spreads = spreads(result)
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--report", type=Path)
    args = ap.parse_args(argv)
    result = merge(args.checkpoints)
    write_bytes(args.out, json.dumps(result.to_dict(), indent=1).encode(), force=True)
    print(f"merged sensors {', '.join(result.sensors)}: {len(result.units)} units -> {args.out}")
    if args.report:
        from forensics.report.impact import impact_report

        page = impact_report(result, "Figure 6 on IITD 001-040 (merged runs)").write(args.report, force=True)
        print(f"report: {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
