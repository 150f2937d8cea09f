"""Merge the finished (sensor, age) items of ``forensics impact`` checkpoints into one result and report.

Run::

    .venv/bin/python benchmarks/impact_merge.py CKPT [CKPT ...] OUT.json [--report DIR]

Every run must have the same seed, ages, matchers, protocols and images (its ``config.json``).  Each sensor's
device and frame noise come from its own keyed stream (``keyed_generator(seed, 1, crc32(name))``) and the class
resamples from ``keyed_generator(seed, 2)``, so a sensor's units do not depend on which other sensors a run
had: units of ``--sensors A,…`` and ``--sensors G,H`` runs merge into exactly what one ``--sensors A,G,H`` run
gives, and the trends and spreads are recomputed from the merged units (``experiment.trends``/``spreads``).
A checkpoint's items are (sensor, age) tasks (``item-sensorSS-ageAAA.npz``) and, from runs with score reuse,
chains of one sensor's later ages (``item-sensorSS-chain.npz``, its ``cells``); both are read.
A run's reused (sensor, age) tasks have no item of their own (their aged images are byte for byte those of an
earlier task).  Give the run's ``--json`` output after the folder (``CKPT:RUN.json``) and each missing item is
taken from the one stored item whose units have exactly the run's EERs and intervals for that (sensor, age),
every matcher and protocol (refused when none or several match); without it only a missing age 0 is filled,
from the run's first age-0 item (age 0 of a noiseless sensor is the source image).  Sensors with items still
missing are left out and named.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from types import SimpleNamespace

from forensics._shared import safecodec
from forensics._shared.atomic import write_bytes
from forensics.impact.experiment import ImpactResult, _classes, _digest_task, parse_sensors, spreads, trends
from forensics.io.dataset import open_dataset
from forensics.sensor.simulate import source_bit_depth


def _fingerprint(units) -> list:
    return sorted((u.matcher, u.protocol, u.eer.estimate, tuple(u.eer.ci)) for u in units)


def _digest(config: dict, s_index: int, a_index: int) -> bytes:
    """The run's digest of the aged images of one (sensor, age) (``experiment._digest_task``)."""
    frames = open_dataset(config["source"]).frames
    first = frames[0].load()
    job = SimpleNamespace(sensors=parse_sensors(",".join(config["sensors"]), first.shape[:2], source_bit_depth(first.dtype)),
                          ages=config["ages"], root=config["seed"], paths=[str(f.path) for f in frames],
                          dtype=first.dtype.str, shape=first.shape)
    return _digest_task(job, (s_index, a_index))


def _stored_cells(folder: Path) -> dict[tuple[int, int], list]:
    """The units of every (sensor index, age index) stored in a checkpoint, from task and chain items alike."""
    cells = {}
    for path in sorted(folder.glob("item-sensor*.npz")):
        stored, s_index = safecodec.decode(path), int(path.stem[11:13])
        if path.stem.endswith("-chain"):
            cells.update({(s_index, int(a_index)): units for a_index, units in stored["cells"]})
        else:
            cells[s_index, int(path.stem[-3:])] = stored["units"]
    return cells


def _stand_in(folder: Path, config: dict, run: dict, cells: dict, s_index: int, a_index: int) -> tuple[int, int]:
    """The stored (sensor, age) of a reused one: equal units in the run's output and equal aged images."""
    sensor, age = config["sensors"][s_index], config["ages"][a_index]
    want = sorted((u["matcher"], u["protocol"], u["eer"], tuple(u["ci"])) for u in run["units"]
                  if u["sensor"] == sensor and u["age"] == age)
    hits = [cell for cell, units in sorted(cells.items()) if _fingerprint(units) == want]
    if len(hits) > 1:  # equal EERs by coincidence: the aged images decide
        mine = _digest(config, s_index, a_index)
        hits = [cell for cell in hits if _digest(config, *cell) == mine]
    if len(hits) != 1:
        raise SystemExit(f"{folder}: {len(hits)} stored items match sensor {sensor} at {age:g} years; expected one")
    return hits[0]


def merge(folders: list[Path], runs: list[dict | None]) -> ImpactResult:
    units, sensors, config = [], [], None
    for folder, run in zip(folders, runs):
        c = json.loads((folder / "config.json").read_text())
        c = c.get("config", c)
        if config is not None and any(c[k] != config[k] for k in ("ages", "matchers", "protocols", "seed", "files")):
            raise SystemExit(f"{folder}: other settings than {folders[0]}")
        config = config or c
        ages = c["ages"]
        cells = _stored_cells(folder)
        for s_index, name in enumerate(c["sensors"]):
            found: list[tuple[int, int] | None] = [(s_index, a) if (s_index, a) in cells else None
                                                   for a in range(len(ages))]
            if run is not None and name in run["sensors"]:
                for a_index, cell in enumerate(found):
                    if cell is None:
                        found[a_index] = _stand_in(folder, c, run, cells, s_index, a_index)
                        print(f"{folder}: sensor {name} at {ages[a_index]:g} years is sensor "
                              f"{c['sensors'][found[a_index][0]]} at {ages[found[a_index][1]]:g} years (reused)")
            if found[0] is None and all(found[1:]):
                zero = sorted(cell for cell in cells if cell[1] == 0)
                if zero:
                    print(f"{folder}: sensor {name}'s age 0 is sensor {c['sensors'][zero[0][0]]}'s (reused by the run)")
                    found[0] = zero[0]
            if not all(found) or name in sensors:
                print(f"{folder}: sensor {name} left out ({sum(f is not None for f in found)} of {len(ages)} ages)")
                continue
            for a_index, cell in enumerate(found):
                units += [dataclasses.replace(u, sensor=name, age=ages[a_index]) for u in cells[cell]]
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
    ap.add_argument("checkpoints", nargs="+", help="checkpoint folders, each optionally :RUN.json")
    ap.add_argument("out", type=Path)
    ap.add_argument("--report", type=Path)
    args = ap.parse_args(argv)
    folders, runs = [], []
    for spec in args.checkpoints:
        folder, _, run = spec.partition(":")
        folders.append(Path(folder))
        runs.append(json.loads(Path(run).read_text()) if run else None)
    result = merge(folders, runs)
    write_bytes(args.out, json.dumps(result.to_dict(), indent=1).encode(), force=True)
    print(f"merged sensors {', '.join(result.sensors)}: {len(result.units)} units -> {args.out}")
    if args.report:
        from forensics.report.impact import impact_report

        page = impact_report(result, "Figure 6 on IITD 001-040 (merged runs)").write(args.report, force=True)
        print(f"report: {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
