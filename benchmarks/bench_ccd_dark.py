"""What dark calibration (``--dark``) changes in a CCD's PRNU fingerprint: the 2017 STL-1001E flats.

Run::

    .venv/bin/python benchmarks/bench_ccd_dark.py [--data ../shared/data/sbig-stl1001e-2017]

Measured, on 1024 × 1024 frames, region ``full``, one process:

1. **How much of the dark pattern each frame carries** (:func:`forensics.prnu.calibration.dark_pattern_share`):
   its excess over its neighbours at the 256 hottest isolated pixels against the excess the darks predict (1: a raw
   frame; 0: dark-subtracted already).  The darks' master is fitted on the biases and the single darks of 10–300 s
   (32 frames); the ten repeated 60 s darks are left out of it and measured as raw frames.
2. **Leave-one-out PCE** of each of the ten flats against the fingerprint of the other nine (zero shift), and the NCC
   of the fingerprint of all ten with the dark pattern of a 23 s frame (offset + 23·rate of the −10 °C group: the
   same hot pixels and bias structure, with noise independent of every −5 °C frame; high-pass: minus its 5 × 5
   local mean; winsorised at its 99.9 % quantile of |value|, since the rates span 0.2–1,600 ADU/s and the hottest
   pixel alone would otherwise make the NCC), with its null standard deviation σ₀, for:

   * ``flats``: the published flats, as they are (no --dark; what --dark refuses, see 1);
   * ``flats, subtracted twice``: the same with the calibration forced on (``DarkCalibration.apply`` without the
     check): what --dark would do if it did not refuse;
   * ``flats --dark-scale fit``: the dark pattern scaled to what each flat shows (its measured share);
   * ``re-darkened``, ``re-darkened --dark`` and ``… --dark-scale fit``:
     each flat with a real dark pattern added back, measured on frames
     the calibration does not use — the median of five −5 °C biases (0–4) plus (median of the ten 60 s darks −
     that bias)·23/60, minus the 100 ADU pedestal — so they are raw flats again, with this camera's own PRNU and
     dark pattern; calibrated with a master fitted *without* those frames (biases 5–9, the single darks), so the
     pattern removed is an independent estimate of the one added.

   The last column is the NCC of each fingerprint (of all ten) with the published flats' own over the bulk: pixels
   below 1 ADU/s with no hotter neighbour (the PRNU, away from where the dark pattern lives).

The re-darkened flats are written as FITS into a temporary folder (never the repository: the data's terms forbid
copies).  Takes ≈ 2–3 minutes and ≈ 0.8 GB on one core (the dark-series fit's peak).
"""
from __future__ import annotations

import argparse
import glob
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from forensics.io.dataset import open_dataset
from forensics.io.fits import read_fits
from forensics.prnu.calibration import dark_calibration, dark_pattern_share
from forensics.prnu.fingerprint import build_fingerprint
from forensics.prnu.imageset import ImageSet
from forensics.prnu.match import score_query

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "sbig-stl1001e-2017"
PEDESTAL = 100.0  # CCDSoft's BIAS keyword on every frame: the pedestal its auto-dark subtraction adds


def link(folder: Path, paths: list[str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for p in paths:
        os.symlink(p, folder / Path(p).name)
    return folder


def redarken(flats: list[str], pattern: np.ndarray, folder: Path) -> Path:
    """Each flat + pattern − pedestal, written as 16-bit FITS with the flat's header (astropy)."""
    from astropy.io import fits

    folder.mkdir(parents=True, exist_ok=True)
    for p in flats:
        with fits.open(p) as hdul:
            data = hdul[0].data.astype(np.float64) + pattern - PEDESTAL
            hdu = fits.PrimaryHDU(np.clip(np.rint(data), 0, 65535).astype(np.uint16))
            for key in ("EXPTIME", "SET-TEMP", "CCD-TEMP", "IMAGETYP", "INSTRUME", "DATE-OBS"):
                hdu.header[key] = hdul[0].header[key]
        hdu.writeto(folder / Path(p).name)
    return folder


def ncc(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """NCC and its null standard deviation √(Σ a²b²)/(‖a‖‖b‖) (``tests/prnu/test_dark_calibration.py``)."""
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    norm = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / norm), float(np.sqrt(((a * b) ** 2).sum()) / norm)


def leave_one_out(images: ImageSet, white: float | None) -> list[float]:
    """PCE of each image against the fingerprint of the others."""
    options = {} if white is None else {"white_level": white}
    out = []
    for i in range(len(images)):
        others = images.subset([j for j in range(len(images)) if j != i])
        fp = build_fingerprint(others, "full", 3.0, **options)
        out.append(float(score_query(fp, images.load(i), "pce", **options).value))
    return out


def forced(cal, ds) -> ImageSet:
    """The frames calibrated without the check that refuses dark-subtracted frames."""
    frames = list(ds.frames)
    hows = [cal.plan(str(f.path), f.exposure_s, f.get("temperature_c"), -5.0) for f in frames]

    def loader(f, how):
        return lambda: cal.apply(f.load(), how, str(f.path))

    return ImageSet([loader(f, h) for f, h in zip(frames, hows)], [str(f.path) for f in frames], "forced")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT)
    args = parser.parse_args()
    d = args.data
    if not d.is_dir():
        raise SystemExit(f"{d}: the 2017 STL-1001E series is not there")
    start = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        flats = sorted(glob.glob(str(d / "flat-*")))
        b5 = sorted(glob.glob(str(d / "biases-Neg5-*")))
        d60 = sorted(glob.glob(str(d / "darks-expos1-*")))
        singles = sorted(glob.glob(str(d / "darks-expos*s-*")))
        full = dark_calibration(link(tmp / "darks", sorted(glob.glob(str(d / "bias-Neg10-*"))) + b5 + singles))
        cold = sorted(glob.glob(str(d / "bias-Neg10-*")))
        split = dark_calibration(link(tmp / "darks_split", cold + b5[5:] + singles))
        fitted, split_fitted = replace(full, scale="fit"), replace(split, scale="fit")
        g = 1  # the −5 °C group
        print(f"dark calibration fitted in {time.time() - start:.0f} s")

        print("\n1. share of the predicted dark pattern (slope ± SE, 256 probe pixels)")
        for label, paths, t in (("flats (23 s)", flats, 23.0), ("60 s darks", d60, 60.0)):
            shares = [dark_pattern_share(read_fits(p).data, full.groups[g], full.plan(p, t, None, -5.0),
                                         full.white_level)[:2] for p in paths]
            s = np.array(shares)
            print(f"  {label:14s} share {s[:, 0].min():+.3f} … {s[:, 0].max():+.3f}   SE ≤ {s[:, 1].max():.4f}")

        bias = np.median([read_fits(p).data.astype(np.float32) for p in b5[:5]], axis=0)
        dark60 = np.median([read_fits(p).data.astype(np.float32) for p in d60], axis=0)
        pattern = bias + (dark60 - bias) * (23.0 / 60.0)
        again = open_dataset(redarken(flats, pattern, tmp / "redarkened"))
        raw = open_dataset(link(tmp / "flats", flats))

        # the reference pattern: the −10 °C group's (its own biases and darks), whose noise is independent of both the
        # pattern added and the one removed (each −5 °C estimate would correlate with one of them through its noise)
        grp = full.groups[0]
        predicted = grp.offset + 23.0 * grp.rate
        high = predicted - ndimage.uniform_filter(predicted.astype(np.float64), 5)
        # rates span 0.2-1,600 ADU/s: unbounded, the hottest pixel alone would make the NCC (σ₀ ≈ |NCC|)
        cap = float(np.quantile(np.abs(high), 0.999))
        high = np.clip(high, -cap, cap)
        # the bulk: pixels below 1 ADU/s with no hotter pixel in their 3 × 3 neighbourhood
        bulk = ~ndimage.binary_dilation(grp.rate >= 1.0, np.ones((3, 3), bool))

        cases = [("flats", ImageSet.of(raw), None),
                 ("flats, subtracted twice", forced(full, raw), full.white_level),
                 ("flats --dark-scale fit", fitted.calibrated_set(raw), full.white_level),
                 ("re-darkened", ImageSet.of(again), None),
                 ("re-darkened --dark", split.calibrated_set(again), split.white_level),
                 ("re-darkened --dark-scale fit", split_fitted.calibrated_set(again), split.white_level)]
        print("\n2. leave-one-out PCE (fingerprint of 9, the 10th scored) and NCC(K of 10, dark pattern)")
        print(f"  {'flats':30s} {'PCE min':>10s} {'median':>10s} {'max':>10s} {'NCC(K, dark)':>13s} {'σ₀':>7s}"
              f" {'NCC(K, K_flats) bulk':>20s}")
        reference = None
        for label, images, white in cases:
            t0 = time.time()
            pces = leave_one_out(images, white)
            fp = build_fingerprint(images, "full", 3.0, **({} if white is None else {"white_level": white}))
            c, sd = ncc(fp.K, high)
            reference = fp.K if reference is None else reference  # the published flats' own fingerprint
            print(f"  {label:30s} {min(pces):10.4g} {np.median(pces):10.4g} {max(pces):10.4g} {c:13.4f} {sd:7.4f}"
                  f" {ncc(fp.K[bulk], reference[bulk])[0]:20.4f}   ({time.time() - t0:.0f} s)")
    print(f"\ntotal {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
