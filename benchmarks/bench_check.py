"""Time and peak memory of the model check (issue 9 item 8): hidden-effect datasets and 24 MP frames.

Run::

    .venv/bin/python benchmarks/bench_check.py                      # everything below (≈ 5 min on 2 cores,
                                                                    # + 3 min to write the 24 MP frames once)
    .venv/bin/python benchmarks/bench_check.py --parts kernels hidden
    .venv/bin/python benchmarks/bench_check.py --parts large --sizes 256x384 512x768 1000x1500

Parts:

``kernels``
    The scene estimate's edge estimates and plane fills and the structure tests' bin covariance, side by side
    with the plain implementations they replaced (per-row / per-pixel loops over the clipped kernels; box
    filters over the whole image for every fill; a dense label-pair histogram per kernel offset), on a
    128 × 128 frame (the hidden-effect datasets), 512 × 768 and 4000 × 6000 (24 MP).  Same results: the
    edge estimates and the bin covariance are bit-identical; the plane fills agree to 1e-9 except where the
    plain version solved a singular 3 × 3 system (collinear good pixels) with rounding noise.
``hidden``
    ``forensics model check DIR --auto`` on the hidden-effect datasets
    (``forensics simulate hidden EFFECT DIR --seed 1``, 128 × 128, 108 frames), each in a fresh child process:
    wall time and peak RSS (``VmHWM`` of the child; ``ru_maxrss`` would include the parent's peak).  Target ≤ 60 s each on 2 cores.
``large``
    20 frames of 24 MP (6000 × 4000, 16-bit PNG, ``forensics.fixtures.hidden.make_hidden`` with hidden PRNU:
    dark and flat, 10 frames each, one epoch; written once into ``--large-dir``): the streaming read into
    per-condition statistics (``load_measurements``, whole frames), and ``model check --auto`` on the same
    design at the ``--sizes`` given, to show how the fit's time and memory grow with the pixel count.

Every child reports the load average; the machine is shared, so the figures are upper bounds.  OpenBLAS
threads spin when the cores are busy: ``--blas-threads 1`` runs the children with ``OPENBLAS_NUM_THREADS=1``
(see RESULTS_check.md, "Speed").
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _timing import timeit

EFFECTS = ("none", "prnu", "dark_current", "gain", "nonlinearity", "shot_noise", "clusters", "accelerating_growth")
LARGE = (4000, 6000)


# ------------------------------------------------------------------------------ plain implementations
def plain_edge_estimates(image: np.ndarray, estimate: np.ndarray, kernel_size: int = 7) -> None:
    """The per-row / per-corner-pixel loop that :func:`forensics.check.scene.edge_estimates` replaced."""
    from forensics.check.scene import clipped_kernel

    h = kernel_size // 2
    H, W = image.shape
    padded = np.pad(image, h)
    rows = [(y, min(y, h), min(H - 1 - y, h)) for y in range(H)]
    cols = [(x, min(x, h), min(W - 1 - x, h)) for x in range(W)]
    edge_rows = [r for r in rows if r[1] < h or r[2] < h]
    edge_cols = [c for c in cols if c[1] < h or c[2] < h]

    def apply(ys, xs, top, bottom, left, right):
        k = clipped_kernel(kernel_size, top, bottom, left, right)
        ylo, yhi = (ys.start, ys.stop) if isinstance(ys, slice) else (ys, ys + 1)
        xlo, xhi = (xs.start, xs.stop) if isinstance(xs, slice) else (xs, xs + 1)
        acc = np.zeros((yhi - ylo, xhi - xlo))
        for dy in range(-h, h + 1):
            for dx in range(-h, h + 1):
                wt = k[dy + h, dx + h]
                if wt:
                    acc += wt * padded[ylo + h + dy:yhi + h + dy, xlo + h + dx:xhi + h + dx]
        estimate[ylo:yhi, xlo:xhi] = acc

    for y, top, bottom in edge_rows:
        apply(y, slice(h, W - h), top, bottom, h, h)
        for x, left, right in edge_cols:
            apply(y, x, top, bottom, left, right)
    for x, left, right in edge_cols:
        apply(slice(h, H - h), x, h, h, left, right)


def plain_plane_fill(image: np.ndarray, good: np.ndarray, size: int = 5, wide: int = 15) -> np.ndarray:
    """Box filters over the whole image, per window size: what :func:`forensics.check.scene.plane_fill` was."""
    from scipy import ndimage

    h, w = image.shape
    out = np.array(image, np.float64, copy=True)
    todo = np.flatnonzero(~good)
    g = good.astype(np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    yy -= h / 2
    xx -= w / 2
    img = np.where(good, image, 0.0)
    for n in (size, wide):
        if not todo.size:
            break

        def box(v, n=n, todo=todo):
            return ndimage.uniform_filter(v, size=n, mode="constant").ravel()[todo]

        s1, sx, sy = box(g), box(g * xx), box(g * yy)
        sxx, syy, sxy = box(g * xx * xx), box(g * yy * yy), box(g * xx * yy)
        A = np.stack([np.stack([s1, sx, sy], -1), np.stack([sx, sxx, sxy], -1), np.stack([sy, sxy, syy], -1)], -2)
        b = np.stack([box(img), box(img * xx), box(img * yy)], -1)
        ok = (s1 * n * n >= 2.5) & (np.abs(np.linalg.det(A)) > 1e-12 * np.maximum(s1, 1e-300) ** 3)
        coef = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
        at = todo[ok]
        out.ravel()[at] = coef[:, 0] + coef[:, 1] * xx.ravel()[at] + coef[:, 2] * yy.ravel()[at]
        todo = todo[~ok]
    if todo.size:
        out.ravel()[todo] = float(np.mean(image[good])) if good.any() else 0.0
    return out


def plain_pair_sums(left, right, kernel, n_left, n_right):
    """A dense ``n_left × n_right`` histogram per kernel offset (what ``structure._pair_sums`` was)."""
    h, w = left.shape
    c = kernel.shape[0] // 2
    out = np.zeros(n_left * n_right)
    for dy in range(-c, c + 1):
        for dx in range(-c, c + 1):
            wt = kernel[dy + c, dx + c]
            if wt == 0.0:
                continue
            a = left[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
            b = right[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
            ok = (a >= 0) & (b >= 0)
            out += wt * np.bincount(a[ok] * n_right + b[ok], minlength=n_left * n_right)
    return out.reshape(n_left, n_right)


def kernels(shapes: list[tuple[int, int]], repeat: int) -> None:
    from forensics.check import scene, structure

    rng = np.random.default_rng(0)
    print("\n| step | frame | plain (s) | now (s) | speed-up | same result |")
    print("|---|---|---|---|---|---|")
    for shape in shapes:
        h, w = shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        img = 1000 - 0.02 * (yy - h / 2) ** 2 / h - 0.03 * (xx - w / 2) ** 2 / w + rng.normal(0, 2, shape)
        # the bad pixels of a scene estimate: defects (≈ 1 %, clusters of them at the corner) and outliers
        good = rng.random(shape) > 0.01
        good[:3, :3] = False
        label = f"{w}×{h}"
        e_plain, e_now = np.zeros(shape), np.zeros(shape)
        tp, _, _ = timeit(lambda img=img, e=e_plain: plain_edge_estimates(img, e), repeat)
        scene.edge_estimates(img, e_now)  # builds the cached band for this shape
        tn, _, _ = timeit(lambda img=img, e=e_now: scene.edge_estimates(img, e), repeat)
        print(f"| scene edge estimates | {label} | {tp:.4f} | {tn:.4f} | {tp / tn:.0f}× | "
              f"{'bit-identical' if np.array_equal(e_plain, e_now) else 'DIFFERENT'} |", flush=True)
        tp, _, fp = timeit(lambda img=img, good=good: plain_plane_fill(img, good), repeat if h * w < 5e6 else 1)
        tn, _, fn = timeit(lambda img=img, good=good: scene.plane_fill(img, good), repeat)
        rel = np.abs(fp - fn) > 1e-9 * np.abs(fp)
        print(f"| plane fill ({int((~good).sum())} pixels) | {label} | {tp:.4f} | {tn:.4f} | {tp / tn:.0f}× | "
              f"{'within 1e-9' if not rel.any() else f'within 1e-9 but {int(rel.sum())} (singular windows)'} |",
              flush=True)
        if h * w > 5e6:
            continue  # the dense histogram needs 36 M bins per offset at 24 MP (minutes)
        used = good.copy()
        b = 3
        used[:b] = used[-b:] = used[:, :b] = used[:, -b:] = False
        lab = structure._labels(shape, used)["column"][0]
        nb = int(lab.max()) + 1
        tp, _, gp = timeit(lambda lab=lab, nb=nb: plain_pair_sums(lab, lab, structure.A2, nb, nb), 1)
        tn, _, gn = timeit(lambda lab=lab, nb=nb: structure.bin_covariance(lab, nb), 1)
        print(f"| bin covariance (columns, first call; cached after) | {label} | {tp:.3f} | {tn:.3f} | "
              f"{tp / tn:.1f}× | {'bit-identical' if np.array_equal(gp, gn) else 'DIFFERENT'} |", flush=True)


# ------------------------------------------------------------------------------ children
def rss_mb() -> float:
    """Peak resident set size of this process (MB): VmHWM, which, unlike ``getrusage``'s ``ru_maxrss``, does
    not carry over the parent's peak across fork and exec."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def child(mode: str, folder: str) -> dict:
    """Run one measurement in this (fresh) process; the CLI's own output is discarded."""
    before = rss_mb()
    t0 = time.perf_counter()
    extra: dict = {}
    if mode in ("auto", "check"):
        from forensics.cli.main import main as cli_main

        argv = ["model", "check", folder, "--json", "--quiet"] + (["--auto"] if mode == "auto" else [])
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            rc = cli_main(argv)
        result = json.loads(out.getvalue())
        extra = {"rc": rc, "added": result.get("added"), "error_pixel": (result.get("error") or {}).get("pixel")}
    elif mode == "load":
        from forensics.check.measurements import load_measurements

        meas = load_measurements(folder)
        extra = {"shape": list(meas.shape), "conditions": len(meas.groups),
                 "arrays_mb": sum(a.nbytes for a in (meas.mean_all, meas.var_all, meas.lo, meas.hi, meas.mean_a,
                                                     meas.mean_b, meas.var_resid, meas.scene_all)) / 2**20}
    else:
        raise SystemExit(f"unknown child mode {mode}")
    return {"mode": mode, "seconds": time.perf_counter() - t0, "peak_mb": rss_mb(), "rss_before_mb": before,
            "load": os.getloadavg()[0], **extra}


def run_child(mode: str, folder: Path, blas_threads: int | None) -> dict:
    env = dict(os.environ)
    if blas_threads:
        env["OPENBLAS_NUM_THREADS"] = str(blas_threads)
    out = subprocess.run([sys.executable, __file__, "--child", mode, str(folder)], check=True, capture_output=True,
                         text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def hidden(work: Path, effects: list[str], blas_threads: int | None) -> None:
    from forensics.fixtures.hidden import make_hidden

    print(f"\n`forensics model check DIR --auto` (OPENBLAS_NUM_THREADS={blas_threads or 'default'})\n")
    print("| hidden effect | added | error.pixel | time (s) | peak RSS (MB) | load avg |")
    print("|---|---|---|---|---|---|")
    times = []
    for effect in effects:
        folder = work / f"hidden_{effect}"
        if not folder.is_dir():
            make_hidden(effect, folder, rng=1)
        r = run_child("auto", folder, blas_threads)
        times.append(r["seconds"])
        err = r["error_pixel"]
        print(f"| {effect} | {', '.join(r['added'] or []) or '—'} | {err if err is None else format(err, '.3g')} | "
              f"{r['seconds']:.1f} | {r['peak_mb']:.0f} | {r['load']:.1f} |", flush=True)
    print(f"\nlongest {max(times):.1f} s, mean {np.mean(times):.1f} s")


def large_design(shape: tuple[int, int]):
    from forensics.fixtures.hidden import Design

    # dark + flat, 10 frames each, one epoch; defect rates 1/100 of the hidden sets' (≈ 300 partially stuck
    # and 40 stuck pixels arrive per year on 24 MP, still ~10× a real sensor's)
    return Design(shape=shape, ages=(0.0,), subjects={"dark": 0.0, "flat_high": 1400.0}, exposures=(1.0,),
                  isos=(100.0,), temperatures=(20.0,), repeats=10, rate_partial=13.0, rate_stuck=1.75)


def large(work: Path, sizes: list[tuple[int, int]], blas_threads: int | None, full: bool) -> None:
    from forensics.fixtures.hidden import make_hidden

    big = work / "frames_24mp"
    if not big.is_dir():
        t0 = time.perf_counter()
        make_hidden("prnu", big, rng=1, design=large_design(LARGE))
        print(f"\n(wrote 20 frames of 6000×4000 into {big} in {time.perf_counter() - t0:.0f} s)")
    print(f"\n20 frames (dark + flat, 10 each), OPENBLAS_NUM_THREADS={blas_threads or 'default'}\n")
    print("| what | frame | pixels | time (s) | peak RSS (MB) | RSS per pixel (B) | load avg |")
    print("|---|---|---|---|---|---|---|")
    r = run_child("load", big, blas_threads)
    print(f"| read + per-condition statistics (load_measurements) | 6000×4000 | 24.0 M | {r['seconds']:.1f} | "
          f"{r['peak_mb']:.0f} | {r['peak_mb'] * 2**20 / 24e6:.0f} | {r['load']:.1f} |", flush=True)
    runs = [(s, work / f"frames_{s[1]}x{s[0]}") for s in sizes]
    if full:
        runs.append((LARGE, big))
    for shape, folder in runs:
        if not folder.is_dir():
            make_hidden("prnu", folder, rng=1, design=large_design(shape))
        r = run_child("auto", folder, blas_threads)
        n = shape[0] * shape[1]
        print(f"| model check --auto (added {', '.join(r['added'] or []) or '—'}) | {shape[1]}×{shape[0]} | "
              f"{n / 1e6:.2f} M | {r['seconds']:.1f} | {r['peak_mb']:.0f} | {r['peak_mb'] * 2**20 / n:.0f} | "
              f"{r['load']:.1f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=["kernels", "hidden", "large"],
                        choices=["kernels", "hidden", "large"])
    parser.add_argument("--effects", nargs="+", default=list(EFFECTS))
    parser.add_argument("--sizes", nargs="*", default=["256x384", "512x768"],
                        help="frame sizes HxW for model check --auto on the large design")
    parser.add_argument("--full-24mp", action="store_true",
                        help="also run model check --auto on the 24 MP frames (needs ≈ 60 GB; see RESULTS)")
    parser.add_argument("--work", default=None, help="folder for the datasets (default: a temporary one)")
    parser.add_argument("--blas-threads", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--child", nargs=2, metavar=("MODE", "FOLDER"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    print(f"# model check benchmark (issue 9 item 8), {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print("command: " + " ".join([Path(sys.executable).name, *sys.argv]))
    with contextlib.ExitStack() as stack:
        work = Path(args.work) if args.work else Path(stack.enter_context(tempfile.TemporaryDirectory()))
        work.mkdir(parents=True, exist_ok=True)
        if "kernels" in args.parts:
            kernels([(128, 128), (512, 768), LARGE], args.repeat)
        if "hidden" in args.parts:
            hidden(work, args.effects, args.blas_threads)
        if "large" in args.parts:
            sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes]
            large(work, sizes, args.blas_threads, args.full_24mp)
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
