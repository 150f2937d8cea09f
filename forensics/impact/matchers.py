"""The matcher interface, its loader, and the built-in matchers by name.

A **matcher** is anything with ``name: str``, ``higher_is_similar: bool``, ``encode(image) -> template`` and
``compare(a, b) -> float`` (:class:`Matcher`); it may add a vectorised ``compare_all(templates_a,
templates_b) -> ndarray`` (use the module function :func:`compare_all`, which falls back on a double loop).

Built-ins (both distances, ``higher_is_similar = False``; both take an optional shared
:class:`~forensics.impact.segment.Segmenter` so one segmentation serves both):

``masek``  :class:`MasekMatcher` — L. Masek, *Recognition of Human Iris Patterns for Biometric
    Identification* (2003): each row of the 20×240 rubber sheet is filtered along the angle with a 1-D
    Log-Gabor filter (wavelength 18 samples, σ/f = 0.5); the phase of each response is quantised to two bits
    (signs of the real and imaginary parts).  9600 bits.
``ko``     :class:`KoMatcher` — J.-G. Ko, Y.-H. Gil, J.-H. Yoo and K.-I. Chung, "A novel and efficient feature
    extraction method for iris recognition", *ETRI Journal* 29(3), 2007: cells of 3×10 samples of a 30×360
    rubber sheet, cumulative sums of cell-mean deviations in groups of 5 cells, coded up/down/flat.

Both compare by the fractional Hamming distance over bits valid in both masks, minimised over circular
shifts along the angle; :meth:`~MasekMatcher.compare_all` does N×M templates at once on bit-packed 64-bit
words with ``np.bitwise_count`` and gives exactly the values of the pairwise loop.

The other four algorithms of the reference paper (USIT's ``qsw``, ``dct``, ``cr``, ``cb``) are in modules of
their own (:mod:`forensics.impact.qsw`, :mod:`~forensics.impact.dct`, :mod:`~forensics.impact.cr`,
:mod:`~forensics.impact.cb`) and built in by name too.

Matcher specs for :func:`load_matcher`: a built-in name | ``module.path:Class`` | ``path/to/file.py:Class``
| ``cmd:COMMAND`` (an external distance) | ``cmd+sim:COMMAND`` (an external similarity).  See
:class:`ExternalMatcher` for the command protocol.

Matchers travel to worker processes by pickle (the experiment runs on :mod:`forensics._shared.parallel`);
instances of a ``file.py:Class`` travel as the file's path, the class name and their state
(:mod:`forensics._shared.plugins`).
"""
from __future__ import annotations

import math
import shlex
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from forensics._shared.errors import InputError, UsageError
from forensics._shared.plugins import is_class_spec, load_class
from forensics.impact.iriscode import IrisCode, IrisCodeMatcher, hamming_all, hamming_distance
from forensics.impact.ko import KoMatcher
from forensics.impact.masek import MasekMatcher, log_gabor_1d
from forensics.impact.segment import DEFAULT_SEGMENTATION, Segmenter


# --------------------------------------------------------------------------- interface
@runtime_checkable
class Matcher(Protocol):
    """What the experiment needs from a recognition system.

    ``encode`` turns an image (``(H, W)`` array as read, e.g. uint8) into a template of any type;
    ``compare`` scores two templates; ``higher_is_similar`` says which way the score points (False for
    distances).  An optional ``compare_all(templates_a, templates_b) -> ndarray`` of shape
    ``(len(a), len(b))`` is used by :func:`compare_all` when present; it must equal the loop of ``compare``.
    """

    name: str
    higher_is_similar: bool

    def encode(self, image: np.ndarray) -> Any: ...

    def compare(self, a: Any, b: Any) -> float: ...


def compare_all(matcher: Any, templates_a: Sequence[Any], templates_b: Sequence[Any]) -> np.ndarray:
    """The ``(len(a), len(b))`` float64 matrix of scores ``matcher.compare(a[i], b[j])``.

    Uses the matcher's own ``compare_all`` when it has one (checked for shape), else a double loop.
    """
    own = getattr(matcher, "compare_all", None)
    shape = (len(templates_a), len(templates_b))
    if callable(own):
        scores = np.asarray(own(templates_a, templates_b), dtype=np.float64)
        if scores.shape != shape:
            raise InputError(f"matcher {getattr(matcher, 'name', matcher)!r}: compare_all returned shape "
                             f"{scores.shape}, expected {shape}")
        return scores
    out = np.empty(shape, dtype=np.float64)
    for i, a in enumerate(templates_a):
        for j, b in enumerate(templates_b):
            out[i, j] = float(matcher.compare(a, b))
    return out


def template_failure(template: Any) -> str | None:
    """Why a template's segmentation failed, or None.

    A template that carries a :class:`~forensics.impact.segment.Segmentation` (as ``template.segmentation``,
    like the built-ins' :class:`IrisCode`) with ``ok`` False is a failure to acquire: the experiment leaves its
    comparisons out and counts it.  Templates of other matchers are never failures.
    """
    seg = getattr(template, "segmentation", None)
    if seg is None or getattr(seg, "ok", True):
        return None
    return str(getattr(seg, "reason", "") or "segmentation failed")


# --------------------------------------------------------------------------- built-ins
#: Built-in matchers by name: a class, or ``module:Class`` for those in modules of their own (loaded on first
#: use, so that importing the matchers does not import every algorithm).
BUILTIN_MATCHERS: dict[str, type | str] = {
    "masek": MasekMatcher, "ko": KoMatcher,
    "qsw": "forensics.impact.qsw:QswMatcher", "dct": "forensics.impact.dct:DctMatcher",
    "cr": "forensics.impact.cr:CrMatcher", "cb": "forensics.impact.cb:CbMatcher",
}


# --------------------------------------------------------------------------- external programs
class ExternalMatcher:
    """A matcher that is a program, run once per encode and once per comparison.

    Protocol (``CMD`` is ``command`` split like a shell would, without a shell):

    * ``CMD encode IMAGE.png TEMPLATE`` must write the template file; the image is the array written as an
      8- or 16-bit grey PNG.  The template is kept as the file's bytes.
    * ``CMD compare TEMPLATE_A TEMPLATE_B`` must print one number (the score) on stdout.

    A non-zero exit status, a missing template file, a timeout or an output that is not one number raise
    :class:`~forensics._shared.errors.InputError` naming the command.  There is no batch mode: budget one
    process start per comparison (a few ms in C, ~30 ms for a Python script).

    Parameters
    ----------
    command
        The program and its leading arguments, e.g. ``"python my_matcher.py"``.
    higher_is_similar
        True if the printed score is a similarity, False for a distance.
    name
        Name in results; default ``"cmd:" + command``.
    timeout
        Seconds allowed per call (None: no limit).
    """

    def __init__(self, command: str, higher_is_similar: bool = False, name: str | None = None,
                 timeout: float | None = 60.0) -> None:
        self.command = command
        self.argv = shlex.split(command)
        if not self.argv:
            raise UsageError("cmd: needs a command, e.g. cmd:'python my_matcher.py'")
        self.higher_is_similar = bool(higher_is_similar)
        self.name = name or f"cmd:{command}"
        self.timeout = timeout

    def _run(self, *args: str) -> str:
        try:
            proc = subprocess.run([*self.argv, *args], capture_output=True, text=True, timeout=self.timeout,
                                  check=False)
        except FileNotFoundError as exc:
            raise InputError(f"external matcher '{self.command}': cannot run it ({exc})") from exc
        except subprocess.TimeoutExpired as exc:
            raise InputError(f"external matcher '{self.command}' {args[0]}: no answer within {self.timeout} s") from exc
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()
            detail = f": {tail[-1]}" if tail else ""
            raise InputError(f"external matcher '{self.command}' {args[0]} failed with exit status "
                             f"{proc.returncode}{detail}")
        return proc.stdout

    def encode(self, image: np.ndarray) -> bytes:
        """Run ``CMD encode IMAGE TEMPLATE`` and return the template file's bytes."""
        from forensics.io.images import write_image

        img = np.asarray(image)
        if img.dtype not in (np.uint8, np.uint16):
            raise InputError(f"external matcher '{self.command}': images must be uint8 or uint16, got {img.dtype}")
        with tempfile.TemporaryDirectory(prefix="forensics-matcher-") as tmp:
            image_path = Path(tmp) / "image.png"
            template_path = Path(tmp) / "template"
            write_image(image_path, img)
            self._run("encode", str(image_path), str(template_path))
            if not template_path.is_file():
                raise InputError(f"external matcher '{self.command}' encode wrote no template file")
            return template_path.read_bytes()

    def compare(self, a: bytes, b: bytes) -> float:
        """Run ``CMD compare A B`` on the two templates and parse the number it prints."""
        with tempfile.TemporaryDirectory(prefix="forensics-matcher-") as tmp:
            pa, pb = Path(tmp) / "a", Path(tmp) / "b"
            pa.write_bytes(bytes(a))
            pb.write_bytes(bytes(b))
            out = self._run("compare", str(pa), str(pb))
        try:
            value = float(out.strip())
        except ValueError:
            shown = out.strip()[:60] or "nothing"
            raise InputError(f"external matcher '{self.command}' compare printed {shown!r}, not one number") from None
        if math.isnan(value):
            raise InputError(f"external matcher '{self.command}' compare printed NaN")
        return value


# --------------------------------------------------------------------------- loading
SPEC_FORMS = ("a built-in name (" + ", ".join(BUILTIN_MATCHERS) + "), module.path:Class, path/to/file.py:Class, "
              "cmd:COMMAND (distance) or cmd+sim:COMMAND (similarity)")


def _check_matcher(obj: Any, spec: str) -> Any:
    missing = [attr for attr in ("encode", "compare") if not callable(getattr(obj, attr, None))]
    missing += [attr for attr in ("name", "higher_is_similar") if not hasattr(obj, attr)]
    if missing:
        raise UsageError(f"matcher '{spec}' lacks {', '.join(missing)}: a matcher needs encode(image), "
                         "compare(a, b), name and higher_is_similar")
    if not isinstance(obj.name, str) or not obj.name:
        raise UsageError(f"matcher '{spec}': name must be a non-empty string")
    if not isinstance(obj.higher_is_similar, (bool, np.bool_)):
        raise UsageError(f"matcher '{spec}': higher_is_similar must be True or False")
    return obj


def load_matcher(spec: str, segmenter: Segmenter | None = None) -> Matcher:
    """A matcher from a spec string.

    Parameters
    ----------
    spec
        A built-in name (:data:`BUILTIN_MATCHERS`); ``module.path:Class``; ``path/to/file.py:Class``
        (loaded with ``importlib.util.spec_from_file_location``); ``cmd:COMMAND`` (an
        :class:`ExternalMatcher` whose score is a distance) or ``cmd+sim:COMMAND`` (a similarity).  A user's
        class is instantiated with no arguments.
    segmenter
        Shared segmenter for the built-ins (ignored by the others).

    Raises
    ------
    UsageError
        For a spec of none of these forms, a module, file or class that cannot be loaded, or an object
        lacking ``encode``/``compare``/``name``/``higher_is_similar`` (the message names what is missing).
    """
    spec = str(spec).strip()
    if spec in BUILTIN_MATCHERS:
        builtin = BUILTIN_MATCHERS[spec]
        return (load_class(builtin, "matcher") if isinstance(builtin, str) else builtin)(segmenter=segmenter)
    for prefix, similar in (("cmd:", False), ("cmd+sim:", True)):
        if spec.startswith(prefix):
            return ExternalMatcher(spec[len(prefix):].strip(), higher_is_similar=similar, name=spec)
    if not is_class_spec(spec):
        raise UsageError(f"unknown matcher '{spec}'; give {SPEC_FORMS}")
    cls = load_class(spec, "matcher")
    cls_name = cls.__name__
    try:
        obj = cls()
    except Exception as exc:
        raise UsageError(f"matcher '{spec}': {cls_name}() failed ({type(exc).__name__}: {exc}); a matcher class "
                         "must be constructible with no arguments") from exc
    return _check_matcher(obj, spec)


def load_matchers(specs: Sequence[str], segmentation: str = DEFAULT_SEGMENTATION) -> list[Matcher]:
    """Matchers for several specs, the built-ins sharing one :class:`Segmenter` (one segmentation per image).

    Parameters
    ----------
    specs
        Matcher specs (see :func:`load_matcher`).
    segmentation
        The built-ins' segmentation: ``caht`` or ``wahet`` (:data:`~forensics.impact.segment.SEGMENTATIONS`).

    Raises
    ------
    UsageError
        For a bad spec (see :func:`load_matcher`), an unknown segmentation or two matchers with the same name.
    """
    segmenter = Segmenter(method=segmentation)
    matchers = [load_matcher(s, segmenter=segmenter) for s in specs]
    names = [m.name for m in matchers]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise UsageError(f"matcher names must be unique; {', '.join(dupes)} given more than once")
    return matchers
