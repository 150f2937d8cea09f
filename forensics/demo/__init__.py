"""``forensics demo``: every capability of the toolkit, run end to end on built-in data.

The demo is a sequence of sections, one module each in this package
(``ageing``, ``prnu``, ``defects``, ``check``).  A section module defines::

    TITLE: str
    def run(workdir: Path, seed: int, progress: Progress) -> DemoSection

``workdir`` is a scratch folder (deleted afterwards); the section returns its
part of the report and a few summary lines for the terminal.  Sections that
are not built yet are simply absent.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from forensics._shared.progress import Progress, no_progress
from forensics.report.html import Report

SECTIONS = ("ageing", "prnu", "defects", "check")


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
    return [name for name in SECTIONS if importlib.util.find_spec(f"{__name__}.{name}") is not None]


def run_demo(out: str | os.PathLike, seed: int = 0, force: bool = False, progress: Progress = no_progress,
             only: list[str] | None = None) -> DemoResult:
    """Run every available section and write ``out/index.html`` (atomically)."""
    from forensics._shared.atomic import refuse_existing

    refuse_existing(out, force)
    started = time.perf_counter()
    page = Report("forensics demo: what a sensor leaves in its images")
    page.text("Everything on this page was computed from built-in, simulated data whose truth is known, "
              f"with seed {seed}. Re-run with 'forensics demo --seed N' for another draw.")
    sections = []
    with tempfile.TemporaryDirectory(prefix="forensics-demo-") as scratch:
        for name in available_sections():
            if only and name not in only:
                continue
            module = importlib.import_module(f"{__name__}.{name}")
            workdir = Path(scratch) / name
            workdir.mkdir()
            section = module.run(workdir, seed, progress)
            sections.append(section)
            page.heading(section.title)
            page.extend(section.report, prefix=f"{name}_")
    path = page.write(out, force=force)
    return DemoResult(path, sections, time.perf_counter() - started)
