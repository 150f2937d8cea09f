"""Write the STL-1001E-like variants of benchmarks/RESULTS_ccd_variants.md into /tmp/ccdvar/v/<name>, truth.json beside each.

The bias_exptime variant is no_flats with EXPTIME = 0.12 written into every bias (astropy, mode="update")."""
import json, shutil, sys, os
from pathlib import Path
import numpy as np
from forensics.fixtures.darkseries import DarkSeriesDesign, make_dark_series
from astropy.io import fits

ROOT = Path("/tmp/ccdvar/v")
BASE = dict(n_flats=10, n_repeat_dark=10)
VARIANTS = {
    "base": {},
    "sp_three": dict(setpoints=(-20.0, -15.0, 0.0)),
    "sp_single": dict(setpoints=(-15.0,), n_flats=0, n_repeat_dark=0),
    "sp_zero_only": dict(setpoints=(0.0,)),
    "exposures_other": dict(exposures=(5.0, 15.0, 45.0, 120.0, 600.0)),
    "multi_per_exp": dict(frames_per_exposure=3, n_bias=5, n_repeat_dark=0),
    "no_flats": dict(n_flats=0),
    "flats_low": dict(flat_level=3000.0),
    "flats_high": dict(flat_level=45000.0),
    "flats_autodark": dict(auto_dark=True),
    "no_bias": dict(n_bias=0),
    "one_bias": dict(n_bias=1),
    "wander": dict(temperature_wander=0.6),
    "unsettled": dict(unsettled=True),
    "never_settles": dict(temperature_wander=2.0),
    "hdr_exposure": dict(exposure_key="EXPOSURE"),
    "hdr_upper": dict(type_words=(("bias", "BIAS"), ("dark", "DARK"), ("flat", "FLAT"))),
    "hdr_lower": dict(type_words=(("bias", "bias"), ("dark", "dark"), ("flat", "flat"))),
    "hdr_light": dict(type_words=(("flat", "Light Frame"),)),
    "date_seconds": dict(date_style="seconds"),
    "date_split": dict(date_style="split"),
    "no_settemp": dict(set_temp_header=False),
    "binning2": dict(binning=2),
    "ext_fit": dict(suffix=".fit"),
    "ext_FIT": dict(suffix=".FIT"),
    "ext_fts": dict(suffix=".fts"),
    "odd_size": {},
    "truncated": {},
    "never_settles_all": {},  # every frame's CCD-TEMP 1.5 °C and more above its set point: no condition repeats
    "binning2_one_sp": dict(binning=2, setpoints=(-5.0,), n_flats=0, n_repeat_dark=0),
    "mixed_binning": {},  # one dark re-labelled XBINNING 2 at the same size (a binned sub-frame)
}

def truth_summary(truth):
    d = truth.design
    out = {"setpoints": {}}
    for sp in d.setpoints:
        temps = [f["temperature_c"] for f in truth.files if f["set_temperature_c"] == sp and f["kind"] == "dark"]
        t = float(np.mean(temps))
        out["setpoints"][str(sp)] = {"mean_temp": t, "median_rate_at_mean_temp": float(np.median(truth.rate_at(t))),
                                    "median_rate_at_sp": float(np.median(truth.rate_at(sp)))}
    out["hot_at_-10_gt1"] = int((truth.rate_at(-10.0) > 1).sum())
    out["bias"] = float(np.median(truth.bias_map))
    out["read_noise"] = d.read_noise
    out["gain"] = d.gain
    out["n_files"] = len(truth.files)
    out["cosmic_hits"] = len(truth.cosmic_hits)
    return out

def main(names):
    for name in names:
        folder = ROOT / name
        if folder.exists():
            shutil.rmtree(folder)
        design = DarkSeriesDesign(**{**BASE, **VARIANTS[name]})
        truth = make_dark_series(folder / "all", 0, design)
        files = sorted((folder / "all").iterdir())
        if name == "odd_size":  # one dark of another size (a 2×2-binned frame among unbinned ones)
            victim = next(f for f in files if f.name.startswith("dark"))
            with fits.open(victim) as h:
                data, hdr = h[0].data[::2, ::2].copy(), h[0].header.copy()
            hdr["XBINNING"] = hdr["YBINNING"] = 2
            victim.unlink(); fits.PrimaryHDU(data, hdr).writeto(victim)
        if name == "never_settles_all":
            for i, f in enumerate(files):
                with fits.open(f, mode="update") as h:
                    h[0].header["CCD-TEMP"] = h[0].header["SET-TEMP"] + 1.5 + 0.01 * i
        if name == "mixed_binning":
            victim = next(f for f in files if f.name.startswith("dark"))
            with fits.open(victim, mode="update") as h:
                h[0].header["XBINNING"] = h[0].header["YBINNING"] = 2
        if name == "truncated":  # one dark cut short (a copy interrupted)
            victim = next(f for f in files if f.name.startswith("dark"))
            raw = victim.read_bytes(); victim.write_bytes(raw[: len(raw) * 2 // 3])
        # flats and darks apart, as the README's worked example links them
        for sub, kinds in (("flats", ("flat",)), ("darks", ("bias", "dark"))):
            (folder / sub).mkdir()
            for f in files:
                if f.name.split("-")[0] in kinds:
                    os.symlink(f, folder / sub / f.name)
        (folder / "truth.json").write_text(json.dumps(truth_summary(truth), indent=1))
        print(name, len(files))

if __name__ == "__main__":
    main(sys.argv[1:] or list(VARIANTS))
