#!/usr/bin/env python3
"""How stable is a segmentation under changes that do not move the eye?  A label-free check on real eyes.

Held-out subjects differ from the shared ones in contrast, exposure and position; a segmentation that is right for
the right reasons returns the same circles when an image is mirrored, shifted, or its grey levels are remapped
monotonically.  For every image of the folder the segmentation (``--segmentation``) is run on the image and on

* ``flip``: the mirror image (left–right; circles mapped back),
* ``gain``: 0.8 × grey + 20 (another exposure and black level, rounded to 8 bits),
* ``gamma``: grey^1.25 (another sensor response),
* ``shift``: the image moved 7 px to the left, the right edge repeated (another framing; circles mapped back),

and the pupil and limbus circles of each variant are compared with the original's under the issue's hit criterion
(centre within 3 px, radius within 10 %).  Where hand-checked marks exist (``tests/impact/data/iitd_marks.csv``)
each variant's hits on them are counted too, so that a change of segmentation can be seen to gain stability
without losing accuracy.  Nothing is tuned on this: it measures.

Run (the images stay in ../shared; research use only)::

    .venv/bin/python benchmarks/bench_segmentation_stability.py [--data ../shared/data/iitd-iris-001-040]
        [--segmentation caht] [--workers 2] [--marked-only] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from forensics.impact.segment.evaluate import is_hit, read_marks  # noqa: E402
from forensics.impact.segment.segmenter import segment_iris  # noqa: E402
from forensics.io.images import read_image  # noqa: E402

Circle = tuple[float, float, float]
#: The variants: name → (image → image, circle found on it → circle in the original's coordinates).
SHIFT = 7


def variants(img: np.ndarray) -> Iterator[tuple[str, np.ndarray, Callable[[Circle], Circle]]]:
    """The image and its variants, each with the map of its circles back to the original's coordinates."""
    f = img.astype(np.float64)
    w = img.shape[1]
    yield "orig", img, lambda c: c
    yield "flip", img[:, ::-1].copy(), lambda c: (w - 1 - c[0], c[1], c[2])
    yield "gain", np.clip(np.rint(0.8 * f + 20.0), 0, 255).astype(np.uint8), lambda c: c
    yield "gamma", np.clip(np.rint(255.0 * (f / 255.0) ** 1.25), 0, 255).astype(np.uint8), lambda c: c
    yield ("shift", np.pad(img, ((0, 0), (0, SHIFT)), mode="edge")[:, SHIFT:].copy(),
           lambda c: (c[0] + SHIFT, c[1], c[2]))


def segment_variants(args: tuple[Path, str]) -> tuple[str, dict[str, dict]]:
    """Every variant's pupil and limbus (original coordinates) and whether its checks passed."""
    path, method = args
    img = read_image(path)
    img = img if img.ndim == 2 else img.mean(axis=2).astype(img.dtype)
    out = {}
    for name, image, back in variants(img):
        seg = segment_iris(image, method)
        out[name] = {"pupil": list(back(seg.pupil)), "iris": list(back(seg.iris)), "ok": bool(seg.ok)}
    return path.name, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "iitd-iris-001-040")
    parser.add_argument("--marks", type=Path, default=ROOT / "tests" / "impact" / "data" / "iitd_marks.csv")
    parser.add_argument("--segmentation", default="caht")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--marked-only", action="store_true", help="only the images with hand-checked marks")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"{args.data}: not found (the shared IITD subjects); nothing measured", file=sys.stderr)
        return 3
    marks = {m.file: m for m in read_marks(args.marks)} if args.marks.exists() else {}
    files = sorted(p for p in args.data.rglob("*") if p.suffix.lower() in (".png", ".bmp", ".jpg", ".tif"))
    if args.marked_only:
        files = [f for f in files if f.name in marks]
    with ProcessPoolExecutor(args.workers) as pool:
        results = dict(pool.map(segment_variants, [(f, args.segmentation) for f in files], chunksize=8))
    names = [n for n, _, _ in variants(np.zeros((4, 4), np.uint8))]
    summary: dict[str, dict] = {}
    for v in names:
        row: dict[str, object] = {"checks passed": sum(r[v]["ok"] for r in results.values())}
        if v != "orig":
            for part in ("pupil", "iris"):
                row[f"{part} as orig"] = sum(is_hit(r[v][part], r["orig"][part]) for r in results.values())
        for part in ("pupil", "iris"):
            marked = [(r[v][part], getattr(marks[n], part)) for n, r in results.items() if n in marks]
            if marked:
                row[f"{part} hits marks"] = sum(is_hit(found, truth) for found, truth in marked)
        summary[v] = row
    n, n_marked = len(results), sum(n in marks for n in results)
    print(f"{args.segmentation}: {n} images ({n_marked} with marks); counts per variant")
    columns = sorted({k for row in summary.values() for k in row})
    print("| variant | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for v, row in summary.items():
        print(f"| {v} | " + " | ".join(str(row.get(c, "—")) for c in columns) + " |")
    moved = {v: sorted(name for name, r in results.items() if not is_hit(r[v]["iris"], r["orig"]["iris"]))
             for v in names if v != "orig"}
    print("limbus moved beyond the criterion under every variant: "
          + (", ".join(sorted(set.intersection(*(set(m) for m in moved.values())))) or "none"))
    if args.json:
        args.json.write_text(json.dumps({"segmentation": args.segmentation, "images": n, "marked": n_marked,
                                         "summary": summary, "moved": moved, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
