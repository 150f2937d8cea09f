"""Everything that is drawn or laid out: the HTML writer (:class:`Report`, :func:`new_figure`) and one
module of figures per domain — :mod:`~forensics.report.ageing`, :mod:`~forensics.report.prnu`,
:mod:`~forensics.report.defects`, :mod:`~forensics.report.scores`, :mod:`~forensics.report.validate`
(and the model check's) — plus the demo's page.  Report functions take result objects and never
re-estimate; science modules never import this package.
"""
from forensics.report.defects import dating_report, detection_report, growth_report
from forensics.report.html import Report, new_figure
from forensics.report.prnu import add_same_device, match_report, same_device_report
from forensics.report.scores import plot_det, plot_score_histograms
from forensics.report.validate import validation_report

__all__ = [
    "Report", "new_figure",
    "dating_report", "detection_report", "growth_report",
    "add_same_device", "match_report", "same_device_report",
    "plot_det", "plot_score_histograms",
    "validation_report",
]
