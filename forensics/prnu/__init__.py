"""Photo-response non-uniformity (PRNU): noise residuals (wavelet and median), streamed maximum-likelihood
fingerprints, matching (NCC, PCE with false-alarm probabilities), the reference paper's same-device
protocol (EER with a bootstrap interval) and its fingerprint-ageing table (table 2).  No figures: those
are in :mod:`forensics.report.prnu`.
"""
from forensics.prnu.ageing import (
    AgeingTable,
    MedianFingerprintBuilder,
    PairStatistic,
    ageing_table,
    build_ageing_fingerprints,
)
from forensics.prnu.fingerprint import Fingerprint, FingerprintBuilder, Region, build_fingerprint, parse_region
from forensics.prnu.match import (
    PCE_THRESHOLD,
    QUERY_SIGMA,
    MatchScore,
    PceResult,
    Query,
    SetMatch,
    match_set,
    ncc,
    pce,
    prepare_query,
    score_matrix,
    score_pair,
    score_query,
)
from forensics.prnu.residual import median_residual, residual_and_grey, wavelet_residual, wiener_dft, zero_mean_cfa
from forensics.prnu.samedevice import (
    EerVerdict,
    ImageSet,
    SameDeviceResult,
    SetPlan,
    SetSummary,
    eer_verdict,
    expected_eer_ci_width,
    plan_set,
    same_device,
)

__all__ = [
    "AgeingTable", "MedianFingerprintBuilder", "PairStatistic", "ageing_table", "build_ageing_fingerprints",
    "Fingerprint", "FingerprintBuilder", "Region", "build_fingerprint", "parse_region",
    "PCE_THRESHOLD", "QUERY_SIGMA", "MatchScore", "PceResult", "Query", "SetMatch", "match_set", "ncc", "pce",
    "prepare_query", "score_matrix", "score_pair", "score_query",
    "median_residual", "residual_and_grey", "wavelet_residual", "wiener_dft", "zero_mean_cfa",
    "EerVerdict", "ImageSet", "SameDeviceResult", "SetPlan", "SetSummary", "eer_verdict", "expected_eer_ci_width",
    "plan_set", "same_device",
]
