"""The defect estimators against simulated truth: trials that realise devices from the paper's presets,
image them through the sensor model and run the real pipeline, scored by recall, precision, bias, RMSE
and interval coverage; and the one matcher of detected defects to the simulated truth.  The report of a
run is in :mod:`forensics.report.validate`.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "trials": [
            "Metric", "ValidationResult", "ValidationSettings", "check_request", "dating_records", "defects_records",
            "summarise_dating", "summarise_defects", "validate_dating", "validate_defects",
        ],
        "truth": ["TruthMatch", "count_true", "match_truth"],
    },
)
