"""Iris segmentation: pupil and limbus boundaries, eyelids, and Daugman's rubber sheet.

Two segmentations, as in the reference paper (USIT's): :mod:`~forensics.impact.segment.caht` (contrast-adjusted
circular Hough transforms) and :mod:`~forensics.impact.segment.wahet` (weighted adaptive Hough and ellipsopolar
transforms), selected by name (:data:`SEGMENTATIONS`, :func:`segment_iris`, :class:`Segmenter`).  Shared parts:
:mod:`~forensics.impact.segment.common` (the :class:`Segmentation` result, image preparation, plausibility
checks), :mod:`~forensics.impact.segment.edges` (edge pixels, eyelids), :mod:`~forensics.impact.segment.boundary`
(boundaries on radial profiles), :mod:`~forensics.impact.segment.normalise` (rubber sheet and noise mask),
:mod:`~forensics.impact.segment.morphology` (binary morphology with discs, scipy's pixels faster),
:mod:`~forensics.impact.segment.memo` (exact reuse of costly steps between images that differ in a few pixels:
:class:`StepMemo`) and :mod:`~forensics.impact.segment.evaluate` (hit rates against hand-checked circles).
"""
import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "common": ["Segmentation", "plausibility"],
        "caht": ["segment_caht"],
        "wahet": ["segment_wahet"],
        "normalise": ["normalise", "sample_grid"],
        "segmenter": ["DEFAULT_SEGMENTATION", "SEGMENTATIONS", "Segmenter", "segment_iris"],
        "evaluate": ["BoundaryMark", "HitRates", "hit_rates", "read_marks"],
        "memo": ["StepMemo"],
    },
)
