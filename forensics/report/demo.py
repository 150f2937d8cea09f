"""The page of ``forensics demo``: an introduction, then every section's own report under its heading."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from forensics.report.html import Report

__all__ = ["demo_page"]


def demo_page(sections: Sequence[tuple[str, Any]], seed: Any) -> Report:
    """One page from ``(name, section)`` pairs, each section with ``title`` and ``report`` (a :class:`Report`
    whose figures are renamed ``<name>_…``); ``seed`` is what the run's provenance records."""
    page = Report("forensics demo: what a sensor leaves in its images")
    page.text("Everything on this page was computed from built-in, simulated data whose truth is known, "
              f"with seed {seed}, except the cooled CCD's section, which uses the real frames of one camera where "
              "they are on the machine (it says so). Re-run with 'forensics demo --seed N' for another draw.")
    for name, section in sections:
        page.heading(section.title)
        page.extend(section.report, prefix=f"{name}_")
    return page
