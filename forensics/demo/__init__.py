"""``forensics demo``: every capability of the toolkit, run end to end on built-in data.

The demo is a sequence of sections, one module each in this package
(``ageing``, ``prnu``, ``attribution``, ``defects``, ``ccd``, ``check``, ``impact``).  A section module defines::

    TITLE: str
    def run(workdir: Path, rng: RngLike, progress: Progress) -> DemoSection

``workdir`` is a scratch folder (deleted afterwards); ``rng`` is the run's
Generator or integer seed, passed to every section as given.  The section
does its science, has :mod:`forensics.report` draw its part of the report, and
returns it with a few summary lines for the terminal and its numbers for
``--json``.  Sections that are not built yet are simply absent.
"""
import lazy_loader as _lazy

# Public names load their module on first use (as in scikit-image), so that importing one module of
# this package does not import the whole domain.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "runner": ["SECTIONS", "DemoResult", "DemoSection", "available_sections", "run_demo"],
    },
)
