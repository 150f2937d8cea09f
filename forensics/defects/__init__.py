"""Pixel defects from ordinary images (the reference paper, section 3.2): detection of stuck and partially
stuck pixels from one streaming pass over a set, the growth of their number over epochs (the paper's
eq. 16–19, Chapman, Garwood rates, a Poisson trend test) and dating a set or a single image from the
defects it shows.  Dark-frame series (biases and darks at several exposures and temperatures) give every
pixel's dark rate, the temperature law and hot pixels at a threshold in ADU/s: ``darkseries`` (the per-pixel
fit), ``darkrounds`` (cosmic rays, diagnostics), ``darkgain`` (conversion gain), ``darklaw`` (the law),
``darkdetect`` (hot pixels, usable by growth and dating).  No figures: those are in
:mod:`forensics.report.defects` and :mod:`forensics.report.darkseries`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "darkdetect": ["CountComparison", "DarkDetectionResult", "DarkSettings", "compare_counts", "dark_epochs",
                       "detect_dark", "detect_dark_dataset", "is_dark_series", "series_frames"],
        "darkgain": ["GainEstimate", "dark_shot_gain", "flat_pair_gain"],
        "darklaw": ["LawPoint", "TemperatureLaw", "fit_temperature_law"],
        "darkseries": ["DarkSeriesFit", "FrameReport", "GroupFit", "SeriesFrame", "SeriesPlan", "fit_dark_series",
                       "plan_series"],
        "dating": ["ImageDating", "SetDating", "date_dataset", "date_image", "date_set"],
        "detection": [
            "DEFAULT_Q", "DEFAULT_SIGMA", "ChannelFit", "DetectionResult", "MaskSpec", "check_request", "detect",
            "detect_dataset", "detect_datasets",
            "parse_mask", "robust_normal",
        ],
        "growth": [
            "Epoch", "GrowthModel", "GrowthResult", "KindGrowth", "RateEstimate", "check_model_fields", "epochs_from_datasets",
            "estimate_growth",
        ],
    },
)
