"""Plumbing every other subpackage uses and none of them owns: the error types the CLI maps to exit codes,
atomic output (a file or folder appears whole or not at all), the progress convention, the exact fast
median filter, the exact content digest (for reuse only where provably exact), array helpers (grey
conversions, full scale), the one JSON converter, the bounds on what one request may allocate
(:mod:`~forensics._shared.limits`), untrusted text made safe for a terminal (:func:`printable`) and the one
way random numbers enter the toolkit (``rng`` is a Generator or an integer seed, see
:mod:`forensics._shared.rng`).  It imports nothing else of the package.
"""
import lazy_loader as _lazy

# Names load their module on first use (as in the domain packages): the CLI imports this package before it
# knows the command, and importing every helper eagerly (scipy.ndimage for the median filter) cost a third of a
# second at every command's start, before the signal handlers of a start-up were in place.
__getattr__, __dir__, __all__ = _lazy.attach(
    __name__,
    submod_attrs={
        "arrays": ["bits_full_scale", "full_scale", "grey_luma", "grey_mean", "infer_full_scale"],
        "atomic": [
            "atomic_directory", "atomic_file", "current_umask", "mkdtemp_like_mkdir", "mkstemp_like_open",
            "refuse_existing", "refuse_inputs", "write_bytes", "write_json", "write_text",
        ],
        "digest": ["content_digest"],
        "errors": ["ForensicsError", "InputError", "UsageError"],
        "filters": ["median_filter"],
        "jsonsafe": ["dumps", "to_jsonable"],
        "limits": ["age_limit", "memory_limit", "pixel_limit", "require_ages", "require_memory", "require_pixels"],
        "plugins": ["is_class_spec", "load_class"],
        "progress": ["Progress", "choose_progress", "no_progress", "tqdm_progress"],
        "rng": ["RngLike", "as_generator", "keyed_generator", "seed_record", "spawn"],
        "text": ["printable"],
    },
)
