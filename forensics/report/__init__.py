"""Everything that is drawn or laid out: the HTML writer (:class:`Report`, :func:`new_figure`) and one
module of figures per domain — :mod:`~forensics.report.ageing`, :mod:`~forensics.report.prnu`,
:mod:`~forensics.report.defects`, :mod:`~forensics.report.darkseries` (dark-frame series),
:mod:`~forensics.report.scores`, :mod:`~forensics.report.validate`, :mod:`~forensics.report.cluster`,
:mod:`~forensics.report.identify`, :mod:`~forensics.report.check` (the model check's), :mod:`~forensics.report.impact`,
:mod:`~forensics.report.segmentation` — plus the demo's page (:mod:`~forensics.report.demo`).  Report functions
take result objects and never re-estimate; science modules never import this package.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "ageing": ["ageing_demo_report", "counts_figure", "crops_figure", "onset_map_figure"],
        "check": ["check_report", "selection_report", "tiles_report"],
        "cluster": ["add_clusters", "cluster_report"],
        "darkseries": ["dark_report"],
        "defects": ["dating_report", "detection_report", "growth_report"],
        "demo": ["demo_page"],
        "html": ["Report", "new_figure"],
        "identify": ["add_identification", "identification_report"],
        "impact": ["histograms_figure", "impact_report", "matchers_figure", "sensors_figure"],
        "prnu": ["add_same_device", "match_report", "same_device_report"],
        "scores": ["plot_det", "plot_score_histograms"],
        "segmentation": ["SegmentedImage", "overlay_figure", "segmentation_report"],
        "validate": ["validation_report"],
    },
)
