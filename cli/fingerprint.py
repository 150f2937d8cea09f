"""``forensics fingerprint``: build a PRNU fingerprint from a set of images, match images against it, and keep
fingerprints in a database (``fingerprint db add|list|remove``)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from textwrap import fill

from forensics.cli.common import (
    add_dark_options,
    add_execution_options,
    add_input_options,
    add_output_options,
    command_parser,
    dark_for,
    emit,
    executor_for,
    info,
    open_input,
    progress_for,
    warn,
)
from forensics.cli.common import finite_float, positive_float  # option types: values checked where parsed


def register(sub) -> None:
    parser = sub.add_parser("fingerprint", help="build PRNU camera fingerprints and match images against them",
                            description="Build a camera's PRNU fingerprint from a set of images, and score images "
                                        "against it (PCE at zero shift or NCC) with a decision at a threshold.")
    inner = parser.add_subparsers(dest="fingerprint_command", metavar="WHAT")

    build = command_parser(
        inner, "build", "estimate a camera's PRNU fingerprint from a set of images",
        "forensics fingerprint build flats/ -o camera.npz --region center:1024",
        fill("Maximum-likelihood fingerprint K = Σ W·I / Σ I² from the wavelet noise residuals W of every image in SET "
        "(streamed: one image in memory at a time; saturated pixels excluded), then zero-mean and DFT Wiener "
        "filtering.  20–50 bright, flat, unsaturated images (sky, wall, flat field) give the best fingerprint.  "
        "All images must have one size and orientation; content-free ones (constant, black or saturated) are "
        "left out with a warning.  The images are summed in chunks on local worker "
        "processes (or a Dask cluster); the result does not depend on how many.  An interrupted build resumes "
        "from the chunks kept in .FP.partial/ beside the output when run again.", 100))
    build.add_argument("set", metavar="SET", help="dataset folder (images, optional manifest.csv)")
    build.add_argument("-o", "--output", metavar="FP", required=True, help="fingerprint file to write (.npz)")
    build.add_argument("--region", default="full",
                       help="'full' (default), 'center:N' (centred N×N crop), or 'corners' (the paper's four "
                            "128×128 corner patches; 'corners:N' for N×N)")
    build.add_argument("--sigma", type=positive_float, default=3.0,
                       help="noise level of the wavelet denoiser on an 8-bit scale (default 3, the reference's)")
    add_input_options(build)
    add_dark_options(build)
    add_execution_options(build)
    add_output_options(build, report=False)
    build.set_defaults(handler=run_build, inputs=("set", "--dark"), outputs=("--output",))

    match = command_parser(
        inner, "match", "score each image of a set against a fingerprint, with a decision",
        "forensics fingerprint match camera.npz photos/ --metric pce --threshold 60",
        fill("Each image's residual (σ = 2, zero-mean, DFT Wiener) is correlated with I·K over the fingerprint's region. "
        "PCE (default) is looked for at zero shift only, unless --shift-range is given; its false-alarm probability "
        "accounts for the shifts and orientations searched.  A portrait image of a landscape sensor is tried in both "
        "quarter turns.  NCC has no universal threshold (it scales as 1/√pixels): give --threshold to get decisions.", 100))
    match.add_argument("fingerprint", metavar="FP", help="fingerprint file written by 'fingerprint build'")
    match.add_argument("set", metavar="SET", help="dataset folder of the images to score")
    match.add_argument("--metric", choices=["pce", "ncc"], default="pce", help="score (default pce)")
    match.add_argument("--threshold", type=finite_float, default=None,
                       help="decide 'match' when the score reaches it (default: 60 for PCE, none for NCC)")
    match.add_argument("--shift-range", type=_shift_range, default=0, metavar="R",
                       help="PCE only: search shifts up to ±R pixels (default 0: zero shift; 'all': every circular "
                            "shift, which inflates non-matching PCE)")
    match.add_argument("--sigma", type=positive_float, default=2.0, help="query residual noise level, 8-bit scale (default 2)")
    add_input_options(match)
    add_dark_options(match)
    add_execution_options(match)
    add_output_options(match)
    match.set_defaults(handler=run_match, inputs=("fingerprint", "set", "--dark"), outputs=("--report",))
    _register_db(inner)
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def _db_output_options(parser: argparse.ArgumentParser) -> None:
    """``--json`` and ``--quiet`` (a database is changed in place, so there is no --force or --report)."""
    group = parser.add_argument_group("output")
    group.add_argument("--json", action="store_true", help="print one JSON object on stdout instead of the summary")
    group.add_argument("--quiet", action="store_true", help="no notes on stderr")


def _register_db(inner: Any) -> None:
    """``fingerprint db add|list|remove``."""
    db = inner.add_parser("db", help="a database of device fingerprints: add, list, remove",
                          description=fill("A fingerprint database is a folder: an SQLite index (index.sqlite) with "
                                           "one row per device and the fingerprints in fingerprints/.  Any number of "
                                           "processes may read it while one writes; every change is atomic.", 100),
                          epilog="example:\n  forensics fingerprint db add cameras/ d70.npz --device 'Nikon D70 #0'\n"
                                 "  forensics fingerprint db list cameras/",
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = db.add_subparsers(dest="db_command", metavar="WHAT")

    add = command_parser(
        sub, "add", "add fingerprints to a database (created if missing)",
        "forensics fingerprint db add cameras/ d70.npz --device 'Nikon D70 #0' --serial 4012345",
        fill("Adds each fingerprint file (written by 'fingerprint build') to the database DB, all of them or, on any "
             "error, none.  The device id is --device, else the one the fingerprint's source images name (the "
             "'device' column of their manifest.csv, else EXIF make, model and body serial).  Make, model and serial "
             "default to the EXIF of the first source image; the capture-date range comes from the source images.  "
             "The quality figure is the effective number of images, n × (1 − saturated fraction): higher is better.",
             100))
    add.add_argument("database", metavar="DB", help="database folder (created when missing)")
    add.add_argument("fingerprints", metavar="FP", nargs="+", help="fingerprint file(s) (.npz)")
    add.add_argument("--device", metavar="ID", help="device id (only with one FP)")
    add.add_argument("--make", metavar="M", help="camera make (default: from EXIF)")
    add.add_argument("--model", metavar="M", help="camera model (default: from EXIF)")
    add.add_argument("--serial", metavar="S", help="body serial number (only with one FP; default: from EXIF)")
    add.add_argument("--replace", action="store_true", help="replace devices already in the database")
    _db_output_options(add)
    add.set_defaults(handler=run_db_add, inputs=("fingerprints",), outputs=("database",))

    lister = command_parser(sub, "list", "list the devices of a database",
                            "forensics fingerprint db list cameras/ --json",
                            "One row per device: id, make, model, serial, region, frame size, images, capture dates "
                            "and quality (effective number of images; higher is better).  --json gives every field.")
    lister.add_argument("database", metavar="DB", help="database folder")
    _db_output_options(lister)
    lister.set_defaults(handler=run_db_list, inputs=("database",), outputs=())

    remove = command_parser(sub, "remove", "remove a device from a database",
                            "forensics fingerprint db remove cameras/ 'Nikon D70 #0'",
                            "Deletes the device's index row (one transaction), then its fingerprint file.")
    remove.add_argument("database", metavar="DB", help="database folder")
    remove.add_argument("device", metavar="ID", help="device id (as 'db list' shows it)")
    _db_output_options(remove)
    remove.set_defaults(handler=run_db_remove, inputs=(), outputs=("database",))
    db.set_defaults(handler=lambda args: db.print_help() or 2)


def _shift_range(text: str) -> int | None:
    if text.strip().lower() == "all":
        return None
    try:
        value = int(text)
        if value < 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shift-range '{text}': give a whole number ≥ 0 or 'all'") from None
    return value


def run_build(args: argparse.Namespace) -> int:
    from forensics._shared.atomic import refuse_existing
    from forensics._shared.parallel import resumable_checkpoint
    from forensics.prnu.fingerprint import build_fingerprint, parse_region, raw_options

    region = parse_region(args.region)
    out = Path(args.output)
    refuse_existing(out, args.force, file=True)  # before hours of work, not after
    ds = open_input(args, args.set)
    ds.binning()  # frames of different binnings are refused, naming one of each (the build reads every frame anyway)
    info(args, f"building a fingerprint from {len(ds)} images of {ds.root} ({region.spec}) …")
    # Finished chunks are kept in .FP.partial beside the output until it is written: an interrupted build resumes.
    partial = out.with_name(f".{out.name}.partial")
    darks = open_input(args, args.dark) if args.dark else None
    config = _build_config(ds, region, args.sigma, darks, args.dark_doubling, args.dark_scale)
    with executor_for(args) as ex:
        dark = dark_for(args, darks, ex)
        images = ds if dark is not None else ds.frames  # a calibration reads each frame's exposure from the dataset
        with resumable_checkpoint(partial, config, args.force, inputs=[f.path for f in ds.frames]) as checkpoint:
            fp = build_fingerprint(images, region, args.sigma, progress=progress_for(args), executor=ex,
                                   checkpoint=checkpoint, name=str(ds.root), dark=dark,
                                   **raw_options(ds.frames[0].path))
            fp.save(out, force=args.force)
        execution = ex.info().to_dict()
    excluded = fp.parameters.get("excluded_pixel_fraction", 0.0)
    _warn_content_free(fp.parameters.get("excluded_frames", []), len(ds), str(ds.root))
    if fp.n_images < 10:
        warn(f"only {fp.n_images} images: a fingerprint from fewer than about 20 is noisy and matches weakly")

    def summary() -> str:
        h, w = fp.frame_shape
        return "\n".join([
            f"Fingerprint of {fp.n_images} images ({w}×{h}) from {ds.root} → {out}",
            f"  region {fp.region}: K is {fp.shape[1]}×{fp.shape[0]}, σ = {fp.sigma:g} (8-bit scale)",
            *_dark_lines(fp.parameters.get("dark_calibration")),
            f"  K: standard deviation {float(fp.K.std()):.4g}; saturated pixels excluded: {100 * excluded:.2f} %",
            f"  next: forensics fingerprint match {out} IMAGES/",
        ])

    emit(args, summary, lambda: {"output": str(out), **fp.to_dict(), "k_std": float(fp.K.std()),
                                 "execution": execution})
    return 0


def _dark_lines(cal: dict[str, Any] | None) -> list[str]:
    """The summary's line about a dark calibration: where from, how scaled, what share of its pattern the frames
    showed."""
    if not cal:
        return []
    shares = [f["dark_share"] for f in cal.get("frames", []) if f.get("dark_share") is not None]
    scales = [f["scale"] for f in cal.get("frames", [])]
    if cal.get("scale") == "fit" and scales:
        how = f"its dark pattern scaled to each frame's share of it, {min(scales):.3f}–{max(scales):.3f}"
    else:
        how = "by exposure" + (f"; the frames showed {min(shares):.3f}–{max(shares):.3f} of its dark pattern"
                               if shares else "")
    return [f"  dark-calibrated with {cal['source']} ({how})"]


def _warn_content_free(frames: list[dict[str, str]], total: int, where: str) -> None:
    """One warning for the content-free frames a build or a scoring left out (the first one's reason)."""
    if frames:
        warn(f"{len(frames)} of {total} frames of {where} are content-free and were left out (first, "
             f"{frames[0]['file']}: {frames[0]['reason']})")


def _build_config(ds: Any, region: Any, sigma: float, darks: Any = None, doubling: float | None = None,
                  scale: str = "exposure") -> dict[str, Any]:
    """What a build's chunks depend on: every input file (with its size and time), the dark set's, the settings."""
    from forensics import __version__
    from forensics.prnu.fingerprint import CHUNK_IMAGES

    config = {"command": "fingerprint build", "files": _file_stats(ds), "region": region.spec, "sigma": sigma,
              "chunk_images": CHUNK_IMAGES, "version": __version__}
    if darks is not None:
        config["dark"] = {"files": _file_stats(darks), "doubling_c": doubling, "scale": scale}
    return config


def _file_stats(ds: Any) -> list[list[Any]]:
    files = []
    for frame in ds.frames:
        try:
            stat = Path(frame.path).stat()
            files.append([str(frame.path), stat.st_size, stat.st_mtime_ns])
        except OSError:  # reported by the build itself, with the file's name
            files.append([str(frame.path), None, None])
    return files


def run_match(args: argparse.Namespace) -> int:
    from forensics.prnu.fingerprint import Fingerprint
    from forensics.prnu.match import match_set
    from forensics.report.prnu import match_report

    fp = Fingerprint.load(args.fingerprint)
    ds = open_input(args, args.set)
    if fp.region.startswith("corners") and args.shift_range != 0 and args.metric == "pce":
        warn("a shift search on a 'corners' fingerprint compares unrelated patches; zero shift is the right test")
    if fp.parameters.get("dark_calibration") and not args.dark:
        warn(f"{args.fingerprint} was built from dark-calibrated frames; raw CCD frames scored against it keep their "
             "dark pattern as noise: give --dark for them too")
    info(args, f"scoring {len(ds)} images of {ds.root} against {args.fingerprint} ({args.metric}) …")
    with executor_for(args) as ex:
        dark = dark_for(args, args.dark, ex)
        result = match_set(fp, ds, args.metric, threshold=args.threshold, shift_range=args.shift_range,
                           sigma=args.sigma, progress=progress_for(args), name=str(args.fingerprint), executor=ex,
                           dark=dark)
        execution = ex.info().to_dict()
    _warn_content_free([{"file": r["file"], "reason": r["excluded"]} for r in result.excluded], len(ds), str(ds.root))
    payload = result.to_dict()

    def summary() -> str:
        return _match_table(payload)

    if args.report:
        match_report(result).write(args.report, force=args.force)
        info(args, f"report: {Path(args.report) / 'index.html'}")
    emit(args, summary, {**payload, "execution": execution})
    return 0


def _fmt_p(p: float | None, log10: float | None) -> str:
    if p is None:
        return ""
    if p > 0:
        return f"{p:.2g}"
    return f"1e{log10:.0f}" if log10 is not None and math.isfinite(log10) else "0"


def _match_table(payload: dict[str, Any]) -> str:
    metric = payload["metric"]
    thr = payload["threshold"]
    head = (f"{payload['n_images']} images of {payload['set']} against {payload['fingerprint']} "
            f"(region {payload['region']}, {metric.upper()}"
            + (f" at {payload['shift_search']}" if metric == "pce" else "") + ")")
    width = max([len(r["file"]) for r in payload["scores"]] + [4])
    cols = f"{'file':<{width}}  {metric.upper():>10}"
    if metric == "pce":
        cols += f"  {'p_FA':>8}  {'NCC':>8}"
    cols += f"  {'rot':>3}  decision"
    lines = [head, cols]
    for r in payload["scores"]:
        if r.get("excluded") is not None:  # not scored: no number to show
            lines.append(f"{r['file']:<{width}}  {'—':>10}" + (f"  {'—':>8}  {'—':>8}" if metric == "pce" else "")
                         + f"  {'':>3}  content-free")
            continue
        line = f"{r['file']:<{width}}  {r['score']:>10.4g}"
        if metric == "pce":
            p = r["pce"] or {}
            line += f"  {_fmt_p(p.get('p_fa'), p.get('log10_p_fa')):>8}  {r['ncc']:>8.4f}"
        decision = "—" if r["match"] is None else ("match" if r["match"] else "no match")
        line += f"  {90 * r['rotation']:>3}  {decision}"
        lines.append(line)
    if thr is None:
        lines.append("no decisions: NCC has no universal threshold; give --threshold (or use --metric pce)")
    else:
        lines.append(f"{payload['n_match']} of {payload['n_images']} images reach the threshold {thr:g}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- fingerprint db


def run_db_add(args: argparse.Namespace) -> int:
    from forensics._shared.errors import InputError, UsageError

    files = [Path(f) for f in args.fingerprints]
    if len(files) > 1 and (args.device is not None or args.serial is not None):
        raise UsageError("--device and --serial name one device: give one FP file with them, or none to take "
                         "each device id from its fingerprint's source images")
    if len({f.resolve() for f in files}) < len(files):
        raise UsageError("the same FP file is given twice; give each fingerprint once")
    for f in files:  # before anything is written
        if not f.is_file():
            raise InputError(f"{f}: no such fingerprint file; build one with 'forensics fingerprint build'")
    folder = Path(args.database)
    entries, before, total = _add_to_database(args, folder, files)
    replaced = [e.device_id for e in entries if e.device_id in before]

    def summary() -> str:
        lines = [f"{'replaced' if e.device_id in replaced else 'added'} {e.device_id!r} "
                 f"({e.n_images} images, region {e.region}, {e.width}×{e.height}) ← {f}"
                 for e, f in zip(entries, files)]
        lines.append(f"{folder}: {total} device(s); next: forensics fingerprint db list {folder}")
        return "\n".join(lines)

    emit(args, summary, lambda: {"database": str(folder), "added": [e.to_dict() for e in entries],
                                 "replaced": replaced, "n_devices": total})
    return 0


def _add_to_database(args: argparse.Namespace, folder: Path, files: list[Path]) -> tuple[list[Any], set[str], int]:
    """Add the files in one transaction; a new database is made beside ``folder`` and renamed into place
    complete, so a failed first add leaves no empty database behind.

    Returns the entries added, the device ids present before, and the number of devices after.
    """
    import os
    import shutil

    from forensics._shared.atomic import mkdtemp_like_mkdir
    from forensics.prnu.database import FingerprintDatabase

    def add(db: FingerprintDatabase) -> tuple[list[Any], set[str], int]:
        before = {e.device_id for e in db.entries()}
        entries = db.add_many(files, [args.device] * len(files), make=args.make, model=args.model,
                              serial=args.serial, replace=args.replace)
        return entries, before, len(db)

    if folder.exists():
        return add(FingerprintDatabase(folder, create=True))  # an empty folder becomes a database
    folder.parent.mkdir(parents=True, exist_ok=True)
    stage = mkdtemp_like_mkdir(prefix=f".{folder.name}.", suffix=".part", dir=folder.parent)  # umask mode
    try:
        result = add(FingerprintDatabase(stage, create=True))
        try:
            os.rename(stage, folder)
        except OSError:
            if not folder.exists():
                raise
            return add(FingerprintDatabase(folder, create=True))  # another process made it meanwhile: add there
        return result
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def run_db_list(args: argparse.Namespace) -> int:
    from forensics.prnu.database import FingerprintDatabase

    db = FingerprintDatabase(args.database)
    entries = db.entries()
    emit(args, lambda: _db_table(str(db.folder), entries),
         lambda: {"database": str(db.folder), "n_devices": len(entries), "entries": [e.to_dict() for e in entries]})
    return 0


def run_db_remove(args: argparse.Namespace) -> int:
    from forensics.prnu.database import FingerprintDatabase

    db = FingerprintDatabase(args.database)
    entry = db.get(args.device)
    db.remove(args.device)
    left = len(db)
    emit(args, f"removed {entry.device_id!r} from {db.folder} ({left} device(s) left)",
         lambda: {"database": str(db.folder), "removed": entry.to_dict(), "n_devices": left})
    return 0


def _fmt_year(year: float | None) -> str:
    if year is None:
        return "?"
    from forensics.io.dataset import from_decimal_year

    return from_decimal_year(year).date().isoformat()


def _db_table(folder: str, entries: list[Any]) -> str:
    if not entries:
        return f"{folder}: no devices; add one with 'forensics fingerprint db add {folder} FP.npz'"
    rows = [["device", "make", "model", "serial", "region", "size", "images", "captured", "quality"]]
    for e in entries:
        dates = "" if e.first_captured is None else f"{_fmt_year(e.first_captured)}–{_fmt_year(e.last_captured)}"
        rows.append([e.device_id, e.make or "", e.model or "", e.serial or "", e.region, f"{e.width}×{e.height}",
                     str(e.n_images), dates, f"{e.quality:.1f}"])
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.rjust(w) if i in (6, 8) else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths)))
             .rstrip() for r in rows]
    lines.append(f"{len(entries)} device(s) in {folder}; quality = effective number of images (higher is better)")
    return "\n".join(lines)
