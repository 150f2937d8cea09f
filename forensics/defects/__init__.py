"""Pixel defects from ordinary images (the reference paper, section 3.2): detection of stuck and partially
stuck pixels from one streaming pass over a set, the growth of their number over epochs (the paper's
eq. 16–19, Chapman, Garwood rates, a Poisson trend test) and dating a set or a single image from the
defects it shows.  No figures: those are in :mod:`forensics.report.defects`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
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
