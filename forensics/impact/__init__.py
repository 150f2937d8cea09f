"""Does sensor ageing hurt recognition?  The reference paper's experiment (section 5) for any matcher.

:mod:`~forensics.impact.irises` writes synthetic near-infrared iris sets (IITD-like) in the dataset format;
:mod:`~forensics.impact.segment` finds pupil and limbus and unwraps the iris (Daugman's rubber sheet);
:mod:`~forensics.impact.matchers` holds the matcher interface, its loader and the built-in iris codes
(Masek's 1-D Log-Gabor, Ko et al.'s cumulative sums); :mod:`~forensics.impact.experiment` ages a set with
virtual sensors and measures the EER against age, with class-level bootstrap intervals and a paired trend
test.  No figures: those are in :mod:`forensics.report.impact`.
"""
import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "irises": ["IrisVariation", "IrisTruth", "iris_texture", "render_iris", "simulate_irises"],
        "segment": ["Segmentation", "Segmenter", "normalise", "segment_iris"],
        "matchers": [
            "BUILTIN_MATCHERS", "ExternalMatcher", "IrisCode", "KoMatcher", "MasekMatcher", "Matcher",
            "compare_all", "load_matcher", "load_matchers",
        ],
        "experiment": [
            "PROTOCOLS", "ImpactResult", "SensorSpec", "Spread", "Trend", "UnitResult", "parse_sensors", "run_impact",
        ],
    },
)
