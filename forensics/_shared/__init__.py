"""Plumbing every other subpackage uses and none of them owns: the error types the CLI maps to exit codes,
atomic output (a file or folder appears whole or not at all), the progress convention, the exact fast
median filter, array helpers (grey conversions, full scale), the one JSON converter, the bounds on what one
request may allocate (:mod:`~forensics._shared.limits`), untrusted text made safe for a terminal
(:func:`printable`) and the one way random numbers enter the toolkit (``rng`` is a Generator or an integer
seed, see :mod:`forensics._shared.rng`).  It imports nothing else of the package.
"""
from forensics._shared.arrays import bits_full_scale, full_scale, grey_luma, grey_mean, infer_full_scale
from forensics._shared.atomic import (
    atomic_directory,
    atomic_file,
    current_umask,
    mkdtemp_like_mkdir,
    mkstemp_like_open,
    refuse_existing,
    refuse_inputs,
    write_bytes,
    write_json,
    write_text,
)
from forensics._shared.errors import ForensicsError, InputError, UsageError
from forensics._shared.filters import median_filter
from forensics._shared.jsonsafe import dumps, to_jsonable
from forensics._shared.limits import age_limit, memory_limit, pixel_limit, require_ages, require_memory, require_pixels
from forensics._shared.plugins import is_class_spec, load_class
from forensics._shared.progress import Progress, choose_progress, no_progress, tqdm_progress
from forensics._shared.rng import RngLike, as_generator, keyed_generator, seed_record, spawn
from forensics._shared.text import printable

__all__ = [
    "bits_full_scale", "full_scale", "grey_luma", "grey_mean", "infer_full_scale",
    "atomic_directory", "atomic_file", "current_umask", "mkdtemp_like_mkdir", "mkstemp_like_open", "refuse_existing",
    "refuse_inputs", "write_bytes", "write_json", "write_text",
    "ForensicsError", "InputError", "UsageError",
    "median_filter",
    "dumps", "to_jsonable",
    "age_limit", "memory_limit", "pixel_limit", "require_ages", "require_memory", "require_pixels",
    "is_class_spec", "load_class",
    "Progress", "choose_progress", "no_progress", "tqdm_progress",
    "RngLike", "as_generator", "keyed_generator", "seed_record", "spawn",
    "printable",
]
