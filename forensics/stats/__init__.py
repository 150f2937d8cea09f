"""Statistics shared by every domain: verification scores (ROC, EER, DET, bootstrap intervals; EERs whose
comparisons share images resampled by class, ``clustered``), count
statistics (exact Garwood / Clopper–Pearson / mid-p intervals, Poisson regression, trend tests, deviance),
the moments of clipped and quantised readouts (near 0 and full scale), the χ², F, t and normal tails
(``tails``: ``scipy.special`` as ``scipy.stats`` calls it, without importing ``scipy.stats``), robust fits (``robust``), Holm's adjustment (``multiple``), and the spatial statistics of defect sites (Ripley's K and L, Clark–Evans, Thomas excess).  No figures:
those are in :mod:`forensics.report.scores`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "counts": [
            "LEVEL", "PoissonFit", "TrendTest", "clopper_pearson", "garwood", "midp_binomial", "poisson_deviance",
            "poisson_glm", "trend_test", "laplace_trend_z",
        ],
        "censored": ["clipped_normal_moments", "readout_moments", "readout_variance_harmonics"],
        "tails": ["chi2_isf", "chi2_ppf", "chi2_sf", "f_sf", "norm_isf", "norm_sf", "t_sf"],
        "robust": ["origin_slope"],
        "multiple": ["holm_adjusted"],
        "clustered": ["ClassBootstrap", "PairedScores", "binned_eer", "class_bootstrap_eer", "class_weights"],
        "scores": [
            "BootstrapResult", "DetCurve", "EerResult", "OperatingPoint", "Roc", "as_scores", "auc",
            "bootstrap_ci", "bootstrap_eer", "decision_threshold_at_far", "det_curve", "eer", "eer_convex_hull",
            "roc",
        ],
        "spatial": [
            "ClarkEvans", "clark_evans", "co_arrival_pairs", "fit_pair_excess", "fit_thomas_excess",
            "lattice_pair_fraction", "pair_excess_se", "ripley_k", "ripley_l", "thomas_excess", "window_area",
        ],
    },
)
