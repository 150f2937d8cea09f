"""``forensics cluster``: group an unlabelled collection of images by the camera that took them."""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path
from textwrap import fill
from typing import Any

from forensics.cli.common import (
    probability,
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    emit,
    executor_for,
    info,
    open_input,
    progress_for,
    warn,
)
from forensics.cli.common import positive_float  # option types: values checked where parsed


def register(sub: Any) -> None:
    parser = command_parser(
        sub, "cluster", "group a collection of images by camera (PRNU); the number of cameras is found",
        "forensics cluster photos/ -o by-camera/ --pfa 1e-3",
        fill("Every image's noise residual (times its intensity, over a centred square crop) is correlated with every "
             "other's; clusters are merged while the correlation of their summed residuals passes a threshold "
             "derived from the measured null distribution (residuals correlated with shifted ones) at the stated "
             "false-alarm probability, Šidák-corrected over every comparison; images left alone are then tested "
             "against each cluster.  Images that match nothing stay unattributed.  Only images of one frame size "
             "(up to a 90° rotation) are compared; portrait images of a landscape collection are turned.  OUT is a "
             "dataset: one folder per device (images hard-linked, or copied across file systems), manifest.csv "
             "with a device column, clusters.json and similarity.npz.  Residuals take about crop² × 4 bytes per "
             "image on disk beside OUT.", 100))
    parser.add_argument("set", metavar="SET", help="dataset folder of the images to group (manifest.csv optional)")
    parser.add_argument("-o", "--output", metavar="OUT", required=True,
                        help="dataset folder to write: OUT/<device>/ images, OUT/manifest.csv, OUT/clusters.json")
    parser.add_argument("--pfa", type=probability, default=1e-3, metavar="P",
                        help="probability that any image is put with another camera's images (default 1e-3)")
    parser.add_argument("--crop", type=int, default=1024, metavar="N",
                        help="side of the centred square compared (default 1024; at most the short side, rounded "
                             "down to a multiple of 8; larger crops find weaker images)")
    parser.add_argument("--sigma", type=positive_float, default=2.0,
                        help="residual noise level, 8-bit scale (default 2, the reference's query residual)")
    add_input_options(parser)
    add_execution_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run, inputs=("set",), outputs=("--output", "--report"))


def _captured(frame: Any) -> float | None:
    """A frame's capture time (manifest, else EXIF), None when unknown or unreadable."""
    from forensics._shared.errors import InputError

    try:
        return frame.captured
    except InputError:
        return None


def run(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing, refuse_inputs
    from forensics.prnu.cluster import cluster_images, write_cluster_dataset

    out = refuse_existing(Path(args.output), args.force)  # before the work, not after
    if args.report:
        refuse_existing(args.report, args.force)
    ds = open_input(args, args.set)
    refuse_inputs(out, [ds.root])
    info(args, f"clustering {len(ds)} images of {ds.root} by camera (crop {args.crop}, p_FA {args.pfa:g}) …")
    out.parent.mkdir(parents=True, exist_ok=True)
    # The residual store goes beside OUT: the output's file system, which workers of a cluster share.
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".work", dir=out.parent))
    try:
        with executor_for(args) as ex:
            result = cluster_images(ds, p_fa=args.pfa, crop=args.crop, sigma=args.sigma,
                                    names=[f.file for f in ds.frames], executor=ex, workdir=work,
                                    progress=progress_for(args))
            execution = ex.info().to_dict()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    written = write_cluster_dataset(result, out, captured=[_captured(f) for f in ds.frames], force=args.force)
    for message in result.warnings:
        warn(message)
    if args.report:
        from forensics.report.cluster import cluster_report

        cluster_report(result, command="forensics " + " ".join(sys.argv[1:])).write(args.report, force=args.force)
        info(args, f"report: {Path(args.report) / 'index.html'}")
    payload = {**result.to_dict(), "set": str(ds.root), **written, "execution": execution}
    emit(args, lambda: _summary(payload), payload)
    return 0


def _summary(p: dict[str, Any]) -> str:
    n_dev = p["n_clusters"]
    lines = [(f"{p['n_images']} images of {p['set']} → {n_dev} device{'s' if n_dev != 1 else ''}, "
              f"{p['n_unattributed']} unattributed (probability ≤ {p['p_fa']:g} that any image is put with another "
              "camera's)")]
    for g in p["groups"]:
        frame = f"{g['frame']['width']}×{g['frame']['height']}"
        null = g["null"]
        if null is None:
            lines.append(f"  {frame}: {g['n_images']} image(s), not compared")
            continue
        lo, hi = null["sigma_ci"]
        c = g["crop"]
        merge = g["threshold_merge_z"]
        attach = g["threshold_attach_z"]
        lines.append(f"  {frame}: {g['n_images']} images ({g['n_rotated']} turned), crop {c}², null σ·crop "
                     f"{null['sigma'] * c:.2f} [{lo * c:.2f}, {hi * c:.2f}] from {null['n_samples']} null samples"
                     + (" (pooled)" if null["pooled"] else "")
                     + f"; merge at z ≥ {merge:.2f}" + (f", attach at z ≥ {attach:.2f}" if attach is not None else ""))
    width = max([len(c["label"]) for c in p["clusters"]] + [len("unattributed")])
    lines.append(f"{'device':<{width}}  {'images':>6}  {'mean z':>7}  {'weakest z':>9}  {'attached':>8}")
    for c in p["clusters"]:
        weakest = c["weakest_z"]
        lines.append(f"{c['label']:<{width}}  {c['size']:>6}  {c['mean_z']:>7.1f}  "
                     f"{weakest if weakest is not None else float('nan'):>9.1f}  {c['n_attached']:>8}")
    lines.append(f"{'unattributed':<{width}}  {p['n_unattributed']:>6}")
    lines.append(f"→ {p['output']}: one folder per device, manifest.csv with a device column "
                 f"({p['linked']} images hard-linked, {p['copied']} copied)")
    if p["clusters"]:
        first = p["clusters"][0]["label"]
        lines.append(f"next: forensics fingerprint build {Path(p['output']) / first} -o {first}.npz")
    return "\n".join(lines)
