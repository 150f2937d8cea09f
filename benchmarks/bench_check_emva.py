#!/usr/bin/env python3
"""The model check at the field's standard data and at real sensor sizes, side by side with emva1288 (issue 27).

Every workload of the issue's table runs here in child processes, each timed as a whole process (wall clock,
CPU seconds, peak memory of the process and its workers), with the machine's load average beside it:

``standard``  an EMVA 1288 exposure-variant series made by ``emva1288``'s own ``DatasetGenerator``
              (``forensics.fixtures.emva.make_standard_series``: 320 × 240, 12 bit, 20 steps, 8 spatial frames,
              96 frames, K = 0.1 DN/e⁻) — ``forensics model check --auto`` and ``emva1288.process`` on the same
              frames, and the quantities both compute (K, dark noise, DSNU, PRNU, dark current);
``series``    a photon-transfer series from the EMVA 1288 simulator (``make_emva_series``: 3 ISO × 3 exposures ×
              3 temperatures × dark + 3 flats × 2 repeats = 216 frames of 320 × 240);
``hidden``    a hidden-effect dataset (``forensics simulate hidden``, 128 × 128, 108 frames);
``large``     1 MP and 12 MP × 36 frames (ISO 100, 3 exposures, 2 temperatures, dark + 2 flats, 2 repeats) and
              24 MP × 20 frames, generated with the EMVA simulator.

emva1288 1.0.2's analysis needs NumPy < 2 (it calls ``np.asfarray``), so it runs in an environment of its own
(``--emva-python``, default ``/work/venv-emva/bin/python``; make it with
``python3 -m venv /work/venv-emva && /work/venv-emva/bin/pip install "numpy<2" emva1288``), by
``benchmarks/emva1288_analysis.py``.

Usage::

    .venv/bin/python benchmarks/bench_check_emva.py --parts standard --seeds 1 2 3 --work /tmp/bce
    .venv/bin/python benchmarks/bench_check_emva.py --parts series hidden --work /tmp/bce
    .venv/bin/python benchmarks/bench_check_emva.py --parts large --sizes 1MP 12MP --timeout 900 --work /tmp/bce
    .venv/bin/python benchmarks/bench_check_emva.py --parts large --tiles 256 --work /tmp/bce   # tile by tile

The figures are written as Markdown to stdout (and ``--json``); the machine is shared, so read the load average
beside each figure: wall times measured under load are upper bounds, CPU seconds are closer to the idle wall time.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FORENSICS = str(Path(sys.executable).with_name("forensics"))
EMVA_SCRIPT = str(Path(__file__).resolve().with_name("emva1288_analysis.py"))
#: Sizes of the ``large`` part: (height, width, frames design).
LARGE = {"1MP": (1000, 1000), "12MP": (3000, 4000), "24MP": (4000, 6000)}


def session_rss_mb(sid: int) -> float:
    """The summed RSS (MB) of every process of session ``sid`` (a child and all its workers), from /proc."""
    total = 0
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            if int(fields[3]) == sid:  # field 6 of stat: the session id
                total += int(fields[21]) * os.sysconf("SC_PAGE_SIZE")  # field 24: rss in pages
        except (OSError, ValueError, IndexError):
            continue
    return total / 2**20


def measure(cmd: list[str], timeout: float, cwd: str | None = None, env: dict | None = None) -> dict:
    """Run ``cmd`` as a child process: wall seconds, CPU seconds (user + system, from ``wait4``: the child and the
    descendants it reaped), peak memory (MB: the summed RSS of the child's whole session — it and its workers —
    sampled every 0.25 s), exit code, stdout; killed after ``timeout`` seconds (then ``timed_out``).

    Why sampled: ``wait4``'s ``ru_maxrss`` is not the child's own — on Linux it carried the peak of an earlier,
    larger child of this process (emva1288's analysis of 12 MP frames, 18.8 GB, was reported for the check run
    after it too)."""
    load = os.getloadavg()[0]
    if env is None:
        # as users run it: pip compiles an installed wheel's modules, and a checkout caches them on first import.
        # This machine sets PYTHONDONTWRITEBYTECODE=1, under which every run of the editable install compiled
        # the whole package from source again (0.2–0.3 s per process, a tenth of a small series' check)
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    out = tempfile.TemporaryFile()
    started = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.PIPE, cwd=cwd, env=env, start_new_session=True)
    timed_out = False
    peak, sampled = 0.0, 0.0
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if time.perf_counter() - started > timeout:
            timed_out = True
            os.killpg(proc.pid, signal.SIGKILL)
            pid, status, usage = os.wait4(proc.pid, 0)
            break
        if time.perf_counter() - sampled >= 0.25:
            peak, sampled = max(peak, session_rss_mb(proc.pid)), time.perf_counter()
        time.sleep(0.05)
    wall = time.perf_counter() - started
    proc.returncode = os.waitstatus_to_exitcode(status)
    stderr = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    out.seek(0)
    stdout = out.read().decode(errors="replace")
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "rss_mb": peak,
            "rc": proc.returncode, "timed_out": timed_out, "load_before": load, "load_after": os.getloadavg()[0],
            "stdout": stdout, "stderr": stderr[-2000:]}


def forensics_auto(folder: Path, timeout: float, extra: list[str] = ()) -> dict:
    """``forensics model check FOLDER --auto --json`` as a child process, its JSON parsed (None if it failed)."""
    run = measure([FORENSICS, "model", "check", str(folder), "--auto", "--json", "--quiet", *extra], timeout)
    try:
        run["result"] = json.loads(run["stdout"]) if run["rc"] == 0 else None
    except ValueError:
        run["result"] = None
    run["stdout"] = ""
    return run


def emva_analysis(emva_python: str, descriptor: Path | None = None, images: Path | None = None,
                  timeout: float = 600) -> dict:
    """emva1288's whole analysis (``emva1288.process``) as a child process."""
    args = [str(descriptor)] if descriptor is not None else ["--images", str(images)]
    run = measure([emva_python, EMVA_SCRIPT, *args], timeout)
    try:
        run["result"] = json.loads(run["stdout"].strip().splitlines()[-1]) if run["rc"] == 0 else None
    except (ValueError, IndexError):
        run["result"] = None
    run["stdout"] = ""
    return run


# ------------------------------------------------------------------------------------------- quantities
def param(result: dict | None, label: str) -> tuple[float | None, float | None]:
    """(value, SE) of a fitted parameter ``effect.name`` in a check's JSON (None when absent or not a result)."""
    if not result:
        return None, None
    for p in result.get("params", []):
        if f"{p['effect']}.{p['name']}" == label and p.get("converged", True):
            return p["value"], p.get("se")
    return None, None


def pattern(result: dict | None, effect: str) -> tuple[float | None, float | None]:
    """(size, SE) of an effect's pixel-local random-effect pattern as the frames show it (None when absent)."""
    if not result:
        return None, None
    for p in result.get("patterns", []):
        if p["effect"] == effect and p.get("size") is not None:
            return p["size"], p.get("size_se")
    return None, None


def dark_reference(folder: Path) -> float:
    """The reference temperature the check's dark-current fit uses for ``folder``'s frames: the effect's own rule
    (:meth:`~forensics.sensor.effects.DarkCurrent.fit`: 25 °C, moved to the dark frames' temperature when it lies
    outside them), applied to the manifest's conditions."""
    import collections
    from types import SimpleNamespace

    from forensics.io.dataset import open_dataset
    from forensics.sensor.effects import DarkCurrent

    counts = collections.Counter((f.exposure_s, f.temperature_c, f.subject) for f in open_dataset(folder).frames)
    groups = [SimpleNamespace(exposure_s=t, temperature_c=temp, subject=subject, n=n)
              for (t, temp, subject), n in counts.items()]
    return DarkCurrent().fit(SimpleNamespace(meas=SimpleNamespace(groups=groups))).t_ref


def our_quantities(result: dict | None, temperature_c: float, t_ref: float = 25.0
                   ) -> dict[str, tuple[float | None, float | None]]:
    """The check's estimates of what emva1288 reports, in emva1288's units: K (DN/e⁻) = shot_noise.g; the dark
    noise σ_y.dark (DN) = √(read² + input² + 1/12 + d²/12), d the converter's dither the check found (the read noise
    is then the noise before it); DSNU (DN) and PRNU (%) = the patterns' sizes as the frames
    show them; the dark current (DN/s) at the series' temperature from the fitted rate at ``t_ref``
    (:func:`dark_reference`; this script took 25 °C until the sixteenth session, but on the standard series the fit
    refers its rate to the frames' 22 °C: the 1.107 DN/s it printed was that rate, 1.490, carried from 25 to 22 °C
    as if it were at 25)."""
    k = param(result, "shot_noise.g")
    read, read_se = param(result, "read_noise.sigma")
    inp, inp_se = param(result, "input_noise.sigma_in")
    noise = None
    if read is not None:
        dither = float(((result or {}).get("quantiser") or {}).get("dither", 0.0))
        var = read**2 + (inp or 0.0) ** 2 + (1.0 + dither**2) / 12.0
        se = math.sqrt((read * (read_se or 0.0)) ** 2 + ((inp or 0.0) * (inp_se or 0.0)) ** 2) / math.sqrt(var)
        noise = (math.sqrt(var), se)
    dsnu = pattern(result, "dsnu")
    prnu = pattern(result, "prnu")
    rate, rate_se = param(result, "dark_current.rate")
    t_double, _ = param(result, "dark_current.t_double")
    dark = (None, None)
    if rate is not None:
        factor = 2.0 ** ((temperature_c - t_ref) / (t_double or 7.0))
        dark = (rate * factor, None if rate_se is None else rate_se * factor)
    return {"K": k, "sigma_y_dark": noise or (None, None), "DSNU_DN": dsnu,
            "PRNU_%": (None if prnu[0] is None else 100 * prnu[0], None if prnu[1] is None else 100 * prnu[1]),
            "dark_current_DN_s": dark}


def their_quantities(result: dict | None) -> dict[str, float | None]:
    r = result or {}
    return {"K": r.get("K"), "sigma_y_dark": r.get("sigma_y_dark"), "DSNU_DN": r.get("DSNU1288_DN"),
            "PRNU_%": r.get("PRNU1288"), "dark_current_DN_s": r.get("u_I_mean_DN")}


def fmt(v, spec: str = ".4g") -> str:
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def path_summary(result: dict | None) -> str:
    if not result:
        return "no result"
    if "tiles" in result:  # --tiles: the selection on the central tile, then the whole frame's tiles
        sel = result.get("selection") or {}
        steps = " → ".join(p["step"] for p in sel.get("path", []))
        same = [f"{p['effect']}.{p['name']}" for p in result["params"] if p.get("p_same") is not None
                and p["p_same"] < 0.001]
        return (f"central tile: {steps}; {len(result['tiles'])} tiles, error.pixel {fmt(result['error']['pixel'])}, "
                f"differ between tiles: {', '.join(same) or 'none'}")
    steps = " → ".join(p["step"] for p in result.get("path", []))
    return f"{steps}; stopped: {result.get('stopped', '?')}"


# ------------------------------------------------------------------------------------------- parts
def standard(work: Path, seeds: list[int], emva_python: str, timeout: float, rows: list[dict]) -> None:
    from forensics.fixtures.emva import StandardSeries, make_standard_series

    series = StandardSeries()
    for seed in seeds:
        folder = work / f"standard-{seed}"
        if not (folder / "manifest.csv").exists():
            make_standard_series(folder, seed, series, force=True)
        theirs = emva_analysis(emva_python, descriptor=folder / "EMVA1288descriptor.txt", timeout=timeout)
        ours = forensics_auto(folder, timeout)
        truth = json.loads((folder / "truth.json").read_text())
        rows.append({"part": "standard", "seed": seed, "frames": truth["frames"], "truth_K": truth["K"],
                     "emva": theirs, "forensics": ours,
                     "ours": our_quantities(ours["result"], series.temperature_c, dark_reference(folder)),
                     "theirs": their_quantities(theirs["result"])})


def emva_images(folder: Path, iso: float, temperature: float) -> dict:
    """emva1288's images dict for the frames of one ISO and temperature of a ``make_emva_series`` folder: per
    exposure a dark pair and the brightest flat's pair; the spatial data at the longest exposure."""
    from forensics.io.dataset import open_dataset

    frames = [f for f in open_dataset(folder).frames if f.iso == iso and f.temperature_c == temperature]
    t_max = max(f.exposure_s for f in frames)
    top = max(float(f.extra.get("light", "0").split()[0]) for f in frames)
    images: dict = {"temporal": {}, "spatial": {}}
    for f in frames:
        light = f.extra.get("light", "0")
        if light != "0" and float(light.split()[0]) != top:
            continue
        photons = 0.0 if light == "0" else float(light.split()[0]) * f.exposure_s / t_max
        key = str(f.exposure_s * 1e9)
        images["temporal"].setdefault(key, {}).setdefault(str(photons), []).append(str(f.path))
        if f.exposure_s == t_max:
            images["spatial"].setdefault(key, {}).setdefault(str(photons), []).append(str(f.path))
    return images


def simulator_series(work: Path, name: str, design, seed: int, emva_python: str | None, timeout: float,
                     rows: list[dict], part: str, extra: list[str] = ()) -> None:
    from forensics.fixtures.emva import make_emva_series

    folder = work / name
    if not (folder / "manifest.csv").exists():
        t0 = time.perf_counter()
        make_emva_series(folder, rng=seed, design=design, force=True)
        print(f"[{name}: written in {time.perf_counter() - t0:.0f} s]", file=sys.stderr)
    theirs = None
    iso, temp = min(design.gains), min(design.temperatures_c)
    if emva_python:
        spec = work / f"{name}-emva-images.json"
        spec.write_text(json.dumps(emva_images(folder, iso, temp)))
        theirs = emva_analysis(emva_python, images=spec, timeout=timeout)
    ours = forensics_auto(folder, timeout, extra)
    n = sum(1 for _ in open(folder / "manifest.csv")) - 1
    rows.append({"part": part, "name": name, "frames": n, "shape": list(design.shape),
                 "truth_K": design.gains[iso], "emva": theirs, "forensics": ours,
                 "ours": our_quantities(ours["result"], temp, dark_reference(folder)) if ours["result"] else None,
                 "theirs": their_quantities(theirs["result"]) if theirs else None})


def series(work: Path, emva_python: str, timeout: float, rows: list[dict]) -> None:
    from forensics.fixtures.emva import EmvaDesign

    design = replace(EmvaDesign(), gains={100: 0.5, 200: 1.0, 400: 2.0}, temperatures_c=(20.0, 28.0, 36.0),
                     flat_electrons=(200.0, 800.0, 3200.0))
    simulator_series(work, "series-216", design, 5, emva_python, timeout, rows, "series")


def large(work: Path, sizes: list[str], emva_python: str | None, timeout: float, rows: list[dict],
          tiles: int | None = None) -> None:
    """The large frames; with ``tiles``, ``--auto --tiles TILES`` (selection on the central tile, then every
    tile checked and combined: forensics.check.tiles)."""
    from forensics.fixtures.emva import EmvaDesign

    for size in sizes:
        shape = LARGE[size]
        design = replace(EmvaDesign(), shape=shape, gains={100: 0.5}, temperatures_c=(20.0, 36.0))
        if size == "24MP":  # 20 frames: one temperature less, one flat less, as the 24 MP row
            design = replace(design, exposures_s=(0.01, 0.02, 0.04, 0.08, 0.16), temperatures_c=(20.0,),
                             flat_electrons=(800.0,))
        extra = [] if tiles is None else ["--tiles", str(tiles)]
        simulator_series(work, f"large-{size}", design, 11, emva_python, timeout, rows,
                         "large" if tiles is None else f"large, --tiles {tiles}", extra)


def hidden(work: Path, timeout: float, rows: list[dict]) -> None:
    from forensics.fixtures.hidden import make_hidden

    for effect in ("none", "prnu", "dark_current"):
        folder = work / f"hidden-{effect}"
        if not (folder / "manifest.csv").exists():
            make_hidden(effect, folder, rng=1, force=True)
        ours = forensics_auto(folder, timeout)
        rows.append({"part": "hidden", "name": effect, "frames": 108, "forensics": ours, "emva": None})


# ------------------------------------------------------------------------------------------- report
def report(rows: list[dict]) -> None:
    print("| workload | frames | `model check --auto`: wall s / CPU s / peak MB (load) | result | emva1288.process: "
          "wall s / CPU s (load) | ratio (wall) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        f, e = r["forensics"], r.get("emva")
        name = f"{r['part']} {r.get('name', r.get('seed', ''))}"
        ours = (f"{f['wall']:.1f} / {f['cpu']:.1f} / {f['rss_mb']:.0f} ({f['load_before']:.1f})"
                + (" **timed out**" if f["timed_out"] else "") + ("" if f["rc"] == 0 or f["timed_out"] else f" rc {f['rc']}"))
        theirs = "—" if not e else f"{e['wall']:.2f} / {e['cpu']:.2f} ({e['load_before']:.1f})"
        ratio = "—" if not e or not e["wall"] else f"{f['wall'] / e['wall']:.0f}×"
        print(f"| {name} | {r['frames']} | {ours} | {path_summary(f['result'])} | {theirs} | {ratio} |")
    agree = [r for r in rows if r.get("ours") and r.get("theirs")]
    if agree:
        print("\n| workload | quantity | truth | emva1288 | model check (± SE) |")
        print("|---|---|---|---|---|")
        for r in agree:
            name = f"{r['part']} {r.get('name', r.get('seed', ''))}"
            for q, (v, se) in r["ours"].items():
                truth = r.get("truth_K") if q == "K" else None
                print(f"| {name} | {q} | {fmt(truth)} | {fmt(r['theirs'][q])} | {fmt(v)}"
                      + (f" ± {fmt(se, '.2g')}" if se is not None else "") + " |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=["standard", "series", "hidden"],
                        choices=["standard", "series", "hidden", "large"])
    parser.add_argument("--work", default="/tmp/bench-check-emva", help="folder for the generated data (kept)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1], help="seeds of the standard series")
    parser.add_argument("--sizes", nargs="+", default=["1MP", "12MP"], choices=list(LARGE))
    parser.add_argument("--emva-python", default="/work/venv-emva/bin/python")
    parser.add_argument("--tiles", type=int, default=None, metavar="SIZE",
                        help="large part: check the frames in tiles of SIZE × SIZE (model check --tiles)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds before a child is stopped")
    parser.add_argument("--json", help="also write every run's figures to this file")
    args = parser.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    emva = args.emva_python if Path(args.emva_python).exists() else None
    print(f"# model check side by side with emva1288 — {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.2f} at the start\n")
    rows: list[dict] = []
    if "standard" in args.parts:
        standard(work, args.seeds, emva, args.timeout, rows)
    if "series" in args.parts:
        series(work, emva, args.timeout, rows)
    if "hidden" in args.parts:
        hidden(work, args.timeout, rows)
    if "large" in args.parts:
        large(work, args.sizes, emva, args.timeout, rows, args.tiles)
    report(rows)
    print(f"\nload average at the end: {os.getloadavg()[0]:.2f}")
    if args.json:
        from forensics._shared.atomic import write_text

        write_text(args.json, json.dumps(rows, indent=1, default=float), force=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
