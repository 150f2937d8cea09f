"""Pixel defects from ordinary images (the reference paper, section 3.2): detection of stuck and partially
stuck pixels from one streaming pass over a set, the growth of their number over epochs (the paper's
eq. 16–19, Chapman, Garwood rates, a Poisson trend test) and dating a set or a single image from the
defects it shows.  No figures: those are in :mod:`forensics.report.defects`.
"""
from forensics.defects.dating import ImageDating, SetDating, date_dataset, date_image, date_set
from forensics.defects.detection import (
    DEFAULT_Q,
    DEFAULT_SIGMA,
    ChannelFit,
    DetectionResult,
    MaskSpec,
    detect,
    detect_dataset,
    parse_mask,
    robust_normal,
)
from forensics.defects.growth import (
    Epoch,
    GrowthModel,
    GrowthResult,
    KindGrowth,
    RateEstimate,
    epochs_from_datasets,
    estimate_growth,
)

__all__ = [
    "ImageDating", "SetDating", "date_dataset", "date_image", "date_set",
    "DEFAULT_Q", "DEFAULT_SIGMA", "ChannelFit", "DetectionResult", "MaskSpec", "detect", "detect_dataset",
    "parse_mask", "robust_normal",
    "Epoch", "GrowthModel", "GrowthResult", "KindGrowth", "RateEstimate", "epochs_from_datasets", "estimate_growth",
]
