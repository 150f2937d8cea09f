"""Running the demo: its sections one after the other, then one page (see :mod:`forensics.demo`)."""
from __future__ import annotations

import importlib
import importlib.util
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from forensics._shared.parallel import Executor
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike, seed_record
from forensics.report.demo import demo_page
from forensics.report.html import Report


SECTIONS = ("ageing", "prnu", "attribution", "defects", "ccd", "check", "impact")
_PACKAGE = "forensics.demo"


@dataclass
class DemoSection:
    """One section's results: a report fragment, lines for the terminal, and machine-readable data."""

    title: str
    report: Report
    summary: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)


@dataclass
class DemoResult:
    report_path: Path
    sections: list[DemoSection]
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return {"report": str(self.report_path), "seconds": round(self.seconds, 1),
                "sections": {s.title: s.data for s in self.sections}}


def available_sections() -> list[str]:
    return [name for name in SECTIONS if importlib.util.find_spec(f"{_PACKAGE}.{name}") is not None]


def run_demo(out: str | os.PathLike, rng: RngLike = 0, force: bool = False, progress: Progress = no_progress,
             only: list[str] | None = None, executor: Executor | None = None) -> DemoResult:
    """Run every available section (or those in ``only``) and write ``out/index.html`` (atomically).

    ``executor`` runs the sections' batch work (ageing, defect statistics, the recognition experiment;
    default: in this process); the page is the same whichever runs it.

    ``rng`` (Generator or int seed) is handed to every section as given, so with an integer each section
    draws from ``default_rng(seed)`` of its own, independently of which other sections run.
    """
    from forensics._shared.atomic import refuse_existing

    refuse_existing(out, force)
    started = time.perf_counter()
    sections = []
    with tempfile.TemporaryDirectory(prefix="forensics-demo-") as scratch:
        for name in available_sections():
            if only and name not in only:
                continue
            module = importlib.import_module(f"{_PACKAGE}.{name}")
            workdir = Path(scratch) / name
            workdir.mkdir()
            sections.append((name, module.run(workdir, rng, progress, executor)))
        path = demo_page(sections, seed_record(rng)).write(out, force=force)
    return DemoResult(path, [s for _, s in sections], time.perf_counter() - started)
