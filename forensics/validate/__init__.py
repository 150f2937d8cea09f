"""The defect estimators against simulated truth: trials that realise devices from the paper's presets,
image them through the sensor model and run the real pipeline, scored by recall, precision, bias, RMSE
and interval coverage; and the one matcher of detected defects to the simulated truth.  The report of a
run is in :mod:`forensics.report.validate`.
"""
from forensics.validate.trials import (
    Metric,
    ValidationResult,
    ValidationSettings,
    dating_records,
    defects_records,
    summarise_dating,
    summarise_defects,
    validate_dating,
    validate_defects,
)
from forensics.validate.truth import TruthMatch, count_true, match_truth

__all__ = [
    "Metric", "ValidationResult", "ValidationSettings", "dating_records", "defects_records", "summarise_dating",
    "summarise_defects", "validate_dating", "validate_defects",
    "TruthMatch", "count_true", "match_truth",
]
