"""Photo-response non-uniformity (PRNU): noise residuals (wavelet and median), streamed maximum-likelihood
fingerprints, a database of device fingerprints, matching (NCC, PCE with false-alarm probabilities), the
reference paper's same-device protocol (EER with a bootstrap interval) and its fingerprint-ageing table
(table 2).  No figures: those are in :mod:`forensics.report.prnu`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "ageing": [
            "AgeingTable", "MedianFingerprintBuilder", "PairStatistic", "ageing_table",
            "build_ageing_fingerprints",
        ],
        "agreement": ["adjusted_rand_index", "completeness", "purity"],
        "cluster": [
            "ClusterNull", "ClusterResult", "DeviceCluster", "ImageAssignment", "SizeGroup", "cluster_images",
            "comparison_residual",
        ],
        "calibration": ["CalibratedFrame", "DarkCalibration", "DarkGroup", "FrameCalibration", "dark_calibration"],
        "clusterwrite": ["write_cluster_dataset"],
        "database": ["DeviceEntry", "FingerprintDatabase"],
        "fingerprint": ["Fingerprint", "FingerprintBuilder", "FingerprintJob", "build_fingerprint", "build_fingerprints"],
        "geometry": ["ScaleSearch"],
        "imageset": ["ImageSet"],
        "identify": ["IdentificationResult", "QueryIdentification", "identify", "prescreen_miss_rate"],
        "prescreen": ["Prescreen"],
        "match": [
            "PCE_THRESHOLD", "QUERY_SIGMA", "MatchScore", "PceResult", "Query", "SetMatch", "match_set", "ncc",
            "pce", "prepare_query", "score_matrix", "score_pair", "score_query",
        ],
        "region": ["Region", "parse_region"],
        "residual": ["cfa_residual_and_grey", "median_residual", "residual_and_grey", "wavelet_residual", "wiener_dft",
                     "zero_mean_cfa"],
        "samedevice": [
            "EerVerdict", "SameDeviceResult", "SetPlan", "SetSummary", "eer_verdict",
            "expected_eer_ci_width", "plan_set", "same_device",
        ],
    },
)
