"""Hit rates and speed of the iris segmentations on hand-checked marks, optionally with a report of the misses.

Run::

    .venv/bin/python benchmarks/bench_segmentation.py [--data ../shared/data/iitd-iris-001-040]
        [--marks tests/impact/data/iitd_marks.csv] [--method caht --method wahet] [--report DIR]
        [--exhaustive [--all]]

For every method: the segmentation of every marked image, the hit rate of the pupil and the limbus (issue 29's
criterion: centre within 3 px, radius within 10 %), the misses the segmentation flagged as failed, and the CPU
time per image (process time, so that other programs on a shared machine do not inflate it).  With
``--report DIR`` a page per method (``DIR/<method>``) shows the overlays of the images that missed a mark or
failed a check.  With ``--exhaustive`` the CAHT-like segmentation is run a second time with the limbus
refinement's exhaustive circle search (``coarse=0``) instead of the coarse-to-fine one, and the images whose
circles differ are listed with the CPU times of both (``--all``: on every image of ``--data``, not only the
marked ones).  The images stay where they are: nothing is copied.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from forensics.impact.segment import SEGMENTATIONS, segment_iris
from forensics.impact.segment.evaluate import hit_rates, read_marks
from forensics.io.images import read_image

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "iitd-iris-001-040"))
    ap.add_argument("--marks", default=str(ROOT / "tests" / "impact" / "data" / "iitd_marks.csv"))
    ap.add_argument("--method", action="append", choices=sorted(SEGMENTATIONS))
    ap.add_argument("--report", metavar="DIR")
    ap.add_argument("--exhaustive", action="store_true",
                    help="compare caht's coarse-to-fine search with the exhaustive one")
    ap.add_argument("--all", action="store_true", help="with --exhaustive: every image of --data")
    args = ap.parse_args(argv)
    marks = read_marks(args.marks)
    data = Path(args.data)
    if not data.is_dir():
        print(f"{data}: no such folder (give --data)", file=sys.stderr)
        return 2
    if args.exhaustive:
        files = sorted(p.name for p in data.glob("*.png")) if args.all else [m.file for m in marks]
        _compare_searches(data, files)
        return 0
    for method in args.method or ["caht", "wahet"]:
        segs, cpu = {}, 0.0
        for mark in marks:
            image = read_image(data / mark.file)
            t0 = time.process_time()
            segs[mark.file] = segment_iris(image, method)
            cpu += time.process_time() - t0
        rates = hit_rates(segs, marks)
        line = [f"{method}: {rates.n} images, {1000 * cpu / rates.n:.0f} ms CPU per image"]
        for boundary, clear in (("pupil", False), ("limbus", False), ("limbus", True), ("both", False)):
            hits, n = rates.rate(boundary, clear)
            line.append(f"{boundary}{' (clear)' if clear else ''} {hits}/{n} = {100 * hits / n:.1f} %")
        flagged, misses = rates.flagged()
        line.append(f"flagged {flagged} of {misses} misses; {sum(not s.ok for s in segs.values())} flagged in all")
        print("; ".join(line))
        if args.report:
            from forensics.report.segmentation import SegmentedImage, segmentation_report

            items = (SegmentedImage(m.file, read_image(data / m.file), segs[m.file], m) for m in marks)
            page = segmentation_report(items, rates, method).write(Path(args.report) / method, force=True)
            print(f"  report: {page}")
    return 0


def _compare_searches(data: Path, files: list[str]) -> None:
    """Print the images whose CAHT circles differ between the coarse-to-fine and the exhaustive search."""
    import math

    cpu = {6: 0.0, 0: 0.0}
    differ = []
    for name in files:
        image = read_image(data / name)
        segs = {}
        for coarse in cpu:
            t0 = time.process_time()
            segs[coarse] = segment_iris(image, "caht", coarse=coarse)
            cpu[coarse] += time.process_time() - t0
        fast, full = segs[6], segs[0]
        if (fast.pupil, fast.iris, fast.ok) != (full.pupil, full.iris, full.ok):
            shift = math.hypot(fast.iris[0] - full.iris[0], fast.iris[1] - full.iris[1])
            differ.append(name)
            print(f"  {name}: exhaustive {full.iris} ok={full.ok}; coarse-to-fine {fast.iris} ok={fast.ok}; "
                  f"limbus centre {shift:.2f} px apart")
    n = len(files)
    print(f"caht: {len(differ)} of {n} images differ; CPU per image: coarse-to-fine {1000 * cpu[6] / n:.0f} ms, "
          f"exhaustive {1000 * cpu[0] / n:.0f} ms ({cpu[0] / cpu[6]:.2f}× faster)")


if __name__ == "__main__":
    sys.exit(main())
