"""Statistics shared by every domain: verification scores (ROC, EER, DET, bootstrap intervals), count
statistics (exact Garwood / Clopper–Pearson / mid-p intervals, Poisson regression, trend test, deviance)
and the spatial statistics of defect sites (Ripley's K and L, Clark–Evans, Thomas excess).  No figures:
those are in :mod:`forensics.report.scores`.
"""
from forensics.stats.counts import (
    LEVEL,
    PoissonFit,
    TrendTest,
    clopper_pearson,
    garwood,
    midp_binomial,
    poisson_deviance,
    poisson_glm,
    trend_test,
)
from forensics.stats.scores import (
    BootstrapResult,
    DetCurve,
    EerResult,
    OperatingPoint,
    Roc,
    as_scores,
    auc,
    bootstrap_ci,
    bootstrap_eer,
    decision_threshold_at_far,
    det_curve,
    eer,
    eer_convex_hull,
    roc,
)
from forensics.stats.spatial import (
    ClarkEvans,
    clark_evans,
    fit_thomas_excess,
    ripley_k,
    ripley_l,
    thomas_excess,
    window_area,
)

__all__ = [
    "LEVEL", "PoissonFit", "TrendTest", "clopper_pearson", "garwood", "midp_binomial", "poisson_deviance",
    "poisson_glm", "trend_test",
    "BootstrapResult", "DetCurve", "EerResult", "OperatingPoint", "Roc", "as_scores", "auc", "bootstrap_ci",
    "bootstrap_eer", "decision_threshold_at_far", "det_curve", "eer", "eer_convex_hull", "roc",
    "ClarkEvans", "clark_evans", "fit_thomas_excess", "ripley_k", "ripley_l", "thomas_excess", "window_area",
]
