"""Does sensor ageing hurt recognition?  The reference paper's experiment (section 5) for any matcher.

:mod:`~forensics.impact.irises` writes synthetic near-infrared iris sets (IITD-like) in the dataset format;
:mod:`~forensics.impact.segment` finds pupil and limbus (CAHT- or WAHET-like) and unwraps the iris (Daugman's
rubber sheet); :mod:`~forensics.impact.matchers` holds the matcher interface, its registry and loader;
:mod:`~forensics.impact.iriscode` the bit-packed codes and Hamming distances of the built-ins
:mod:`~forensics.impact.masek` (1-D Log-Gabor) and :mod:`~forensics.impact.ko` (cumulative sums), with
:mod:`~forensics.impact.spectral` their exact counts at every shift by cross-correlation (long codes, many shifts);
:mod:`~forensics.impact.experiment` ages a set with
virtual sensors and measures the EER against age, with class-level bootstrap intervals and a paired trend
test; :mod:`~forensics.impact.reuse` lets it copy the scores of pairs whose templates did not change, and the
templates whose rubber-sheet band did not change.  No figures: those are in :mod:`forensics.report.impact`.
"""
import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "irises": ["IrisVariation", "IrisTruth", "iris_texture", "render_iris", "simulate_irises"],
        "segment": ["SEGMENTATIONS", "Segmentation", "Segmenter", "normalise", "segment_iris"],
        "iriscode": ["IrisCode"],
        "masek": ["MasekMatcher"],
        "ko": ["KoMatcher"],
        "matchers": [
            "BUILTIN_MATCHERS", "ExternalMatcher", "Matcher", "compare_all", "load_matcher", "load_matchers",
            "template_failure",
        ],
        "qsw": ["QswMatcher"],
        "dct": ["DctMatcher", "DctTemplate"],
        "cr": ["CrMatcher"],
        "cb": ["CbMatcher", "CbTemplate"],
        "reuse": ["ScoredPairs", "score_digest", "template_digest"],
        "experiment": [
            "PROTOCOLS", "ImpactResult", "SensorSpec", "Spread", "Trend", "UnitResult", "parse_sensors", "run_impact",
        ],
    },
)
