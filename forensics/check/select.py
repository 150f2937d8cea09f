"""Several effects at once: forward selection from the base model.

:func:`forward_select` starts from a model (the base model plus any effects the user added), checks it,
adds the top *flagged* candidate (ΔBIC > 10 and Holm p < 0.01), checks again, and repeats until nothing is
flagged.  Every step is checked against the same :class:`~forensics.check.evidence.Evidence` (built once from
the data), so the steps compare like with like.  The path — ``base → +A → +B …`` with the error and the
goodness of fit at each step — is a :class:`SelectionResult`.

An addition is kept only if it improves the fit: some channel's error falls beyond its noise
(:data:`ERROR_TOL`) or some failing goodness of fit recovers (:data:`GOF_RISE`).  If the top candidate does
not, the next flagged one is tried (once per model); if that fails too, the path stops and says why.  :func:`check_auto` is the convenience entry point from a dataset.

On the execution layer (``executor``) the frames are read condition by condition; the path itself is fitted
in this process: each step depends on the one before, and a step fits its second candidate only when the
first is not kept — fitting both side by side would usually spend a second fit to gain nothing (the top
flagged candidate is usually kept) and could only finish later than fitting the first alone.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from forensics._shared.errors import ForensicsError, UsageError
from forensics._shared.progress import Progress, no_progress
from forensics._shared.rng import RngLike
from forensics.check.classes import CLASSES
from forensics.check.evidence import Evidence
from forensics.check.measurements import Measurements, Region
from forensics.check.result import CheckResult
from forensics.check.pipeline import base_model, prepare, resolve_effects, run_check
from forensics.io.dataset import Dataset
from forensics.sensor.model import Effect

if TYPE_CHECKING:
    from forensics._shared.parallel import Executor

#: An error channel "falls beyond its noise" when it drops by more than this fraction of its value.  The pixel
#: channel's is computed from the number n of held-out pixel means (:func:`pixel_error_tolerance`); this value
#: is used only when n is unknown.  Variance and growth are coarser, binned or counted, statistics.
ERROR_TOL: dict[str, float] = {"pixel": 0.02, "variance": 0.10, "growth": 0.10}
#: standard errors an error must fall by (one-sided, ≈ 0.1 % by chance)
ERROR_SIGMAS = 3.0
#: A goodness of fit "recovers" when a p-value below :data:`GOF_FAIL` rises by at least this factor (the
#: spatial channel's Monte-Carlo p cannot go below 1/(n_sim + 1) = 0.005, so a recovery reads 0.005 → ≥ 0.05).
GOF_RISE = 10.0
GOF_FAIL = 0.05

NOTHING_FLAGGED = "nothing flagged"
MAX_STEPS = "max steps"
#: Default cap on the effects ``--auto`` adds.  A camera of the EMVA 1288 simulator has six beyond the base model
#: (dark current, gain, shot noise, input noise, DSNU, PRNU); a cap of five stopped its photon-transfer series one
#: short, with the conversion gain biased by the missing input noise (0.536 for 0.5).  The cap bounds the time on
#: data where something stays flagged whatever is added.
DEFAULT_MAX_STEPS = 8
NO_IMPROVEMENT = "no improvement"


@dataclass
class Attempt:
    """A candidate tried at a step and not kept, and why."""

    effect: str
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Step:
    """One model on the path: its effects, the check's summary, and what was tried to get here.

    ``result`` (the full :class:`CheckResult`, for the report) is not serialised.
    """

    effects: list[str]
    added: str | None  #: the effect this step added (None for the starting model)
    error: dict[str, Any]
    gof: dict[str, float | None]
    flagged: list[str]
    top: dict[str, Any] | None  #: the top-ranked candidate: effect, delta_bic, p, flagged
    rejected: list[Attempt] = field(default_factory=list)  #: tried before this step and not kept
    result: CheckResult | None = field(default=None, repr=False)

    @property
    def label(self) -> str:
        return "base" if self.added is None else f"+{self.added}"

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.label, "added": self.added, "effects": self.effects, "error": self.error,
                "gof": self.gof, "flagged": self.flagged, "top": self.top,
                "rejected": [a.to_dict() for a in self.rejected]}


@dataclass
class SelectionResult:
    """The forward-selection path and why it stopped.

    ``stopped`` is the sentence shown to the user; ``reason`` its code (:data:`NOTHING_FLAGGED`,
    :data:`MAX_STEPS` or :data:`NO_IMPROVEMENT`).  :attr:`result` is the final model's check, whose
    ``baseline`` is the starting model's check when anything was added.
    """

    steps: list[Step]
    stopped: str
    reason: str
    rejected: list[Attempt] = field(default_factory=list)  #: tried after the last step and not kept

    @property
    def result(self) -> CheckResult:
        return self.steps[-1].result

    @property
    def added(self) -> list[str]:
        return [s.added for s in self.steps if s.added is not None]

    def to_dict(self) -> dict[str, Any]:
        """The final check's keys plus ``path`` (one object per step), ``added``, ``stopped`` and ``reason``."""
        out = self.result.to_dict() if self.result is not None else {}
        out.update({"path": [s.to_dict() for s in self.steps], "added": self.added, "stopped": self.stopped,
                    "reason": self.reason, "rejected": [a.to_dict() for a in self.rejected]})
        return out


def _top(result: CheckResult) -> dict[str, Any] | None:
    if not result.candidates:
        return None
    c = result.candidates[0]
    return {"effect": c.effect, "delta_bic": c.delta_bic, "p": c.p, "flagged": c.flagged}


def make_step(result: CheckResult, added: str | None, rejected: Sequence[Attempt] = ()) -> Step:
    """The summary of one check on the path."""
    return Step(effects=list(result.effects), added=added, error=result.error, gof=result.gof,
                flagged=result.flagged, top=_top(result), rejected=list(rejected), result=result)


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def pixel_error_tolerance(n: int | None) -> float:
    """Relative fall of a held-out pixel error over ``n`` pixel means that is beyond its sampling noise.

    Under the model the error² is a mean of n squared z-scores, relative SD √(2/n), so the error's own relative
    SD is 1/√(2n); a fall of :data:`ERROR_SIGMAS` of those is kept.  The two errors compared are scored on the
    same held-out means, so their difference is less noisy than this: the rule is conservative.
    """
    if not n:
        return ERROR_TOL["pixel"]
    return ERROR_SIGMAS / math.sqrt(2.0 * n)


def paired_fall(before: CheckResult, after: CheckResult, cls: str | None) -> tuple[float, float] | None:
    """The fall of a class's held-out error² from ``before`` to ``after``, scored on the same means, and its
    standard error: (Σ r²_before − Σ r²_after) / Σ floor over the pixel means scored in the class by both
    models, SE from the spread of the per-mean differences.  Most of either error's sampling noise is common to
    both and cancels; None without the held-out terms or with fewer than 10 common means.  ``cls`` None: every
    class together (the means in the same class in both models)."""
    if before.heldout is None or after.heldout is None or (cls is not None and cls not in CLASSES):
        return None
    a, b = before.heldout, after.heldout
    same = a.classes == b.classes if cls is None else (a.classes == CLASSES.index(cls)) & (b.classes == a.classes)
    both = same & np.isfinite(a.r2) & np.isfinite(b.r2)
    n = int(both.sum())
    if n < 10:
        return None
    d = a.r2[both].astype(np.float64) - b.r2[both]
    den = float(b.floor[both].sum(dtype=np.float64))
    if den <= 0:
        return None
    return float(d.sum()) / den, math.sqrt(n * float(d.var())) / den


def improvement(before: CheckResult, after: CheckResult) -> str | None:
    """What improved from ``before`` to ``after`` (a short phrase), or None if nothing did beyond its noise.

    A pixel class's error counts as fallen when its error² falls by :data:`ERROR_SIGMAS` standard errors of the
    paired difference (:func:`paired_fall`); without the held-out terms, by the unpaired (conservative)
    tolerance of :func:`pixel_error_tolerance` — but not where the error² of all classes together rose by as many
    paired standard errors.  A failing gof's rise does not count where any one class's error² rose so."""
    classes = before.error.get("classes") or {}
    # one class's fall does not make up for the held-out error² of all classes together risen beyond its paired
    # noise: on a dark series whose only repeats were its biases, a nonlinearity lowered the hot pixels' error²
    # (paired z 3.1) while the normal pixels' rose (z −294, error 2.5 → 4.4), and was kept.  (Tried first and not
    # kept: vetoing every improvement by any one class's rise — where prnu and dark_current were hidden, adding
    # prnu lowers the normal pixels' error and may raise a few hot pixels', and the selection stalled; and by the
    # pooled rise — shot_noise on the EMVA simulator's series was refused, a variance error falling by orders of
    # magnitude against a pixel error² risen by a significant sliver.)
    total = paired_fall(before, after, None)
    pooled_rose = total is not None and -total[0] > ERROR_SIGMAS * total[1]
    falls = {cls: paired_fall(before, after, cls) for cls in classes}
    for cls, b in classes.items():
        a = (after.error.get("classes") or {}).get(cls)
        fall = falls[cls]
        if not pooled_rose and fall is not None and _finite(b) and _finite(a) and fall[0] > ERROR_SIGMAS * fall[1]:
            return f"error.classes.{cls} {b:.4g} → {a:.4g} (paired z {fall[0] / max(fall[1], 1e-300):.1f})"
    n_means = (after.data or {}).get("held_out_means") or {}
    worst = max((c for c in classes if _finite(classes[c])), key=lambda c: classes[c], default=None)
    pairs = [(f"error.{key}", before.error.get(key), after.error.get(key),
              pixel_error_tolerance(n_means.get(worst)) if key == "pixel" else tol) for key, tol in ERROR_TOL.items()]
    pairs += [(f"error.classes.{cls}", b, (after.error.get("classes") or {}).get(cls),
               pixel_error_tolerance(n_means.get(cls)))
              for cls, b in classes.items()]  # error.pixel is the worst class's
    for label, b, a, tol in pairs:
        if pooled_rose and (label == "error.pixel" or label.startswith("error.classes.")):
            continue
        if _finite(b) and _finite(a) and a < (1.0 - tol) * b:
            return f"{label} {b:.3g} → {a:.3g}"
    # nor does a failing gof's rise make up for any one class's error risen beyond its noise (on a dark series a
    # nonlinearity with β = 0.43 lifted gof.pixel from 2e-236 to 2e-234 while error.pixel went 1.62 → 2.81)
    rose = any(fall is not None and -fall[0] > ERROR_SIGMAS * fall[1] for fall in falls.values())
    for key, b in before.gof.items():
        a = after.gof.get(key)
        if not rose and _finite(b) and _finite(a) and b < GOF_FAIL and a >= GOF_RISE * max(b, 1e-300):
            return f"gof.{key} {b:.2g} → {a:.2g}"
    return None


def _problem(before: CheckResult, after: CheckResult) -> str | None:
    """A fit that cannot be scored: one that did not settle, a non-finite error where the model has one, or a
    pixel class scored before and empty after (every pixel of it taken for a defect)."""
    unsettled = [p.label for p in after.params if not p.converged]
    if unsettled:
        return f"the fit did not converge ({', '.join(unsettled)})"
    bad = [k for k in ERROR_TOL if after.error.get(k) is not None and not _finite(after.error[k])]
    if bad:
        return f"the fit gave a non-finite error.{bad[0]}"
    lost = [c for c, v in (before.error.get("classes") or {}).items()
            if _finite(v) and not _finite((after.error.get("classes") or {}).get(c))]
    return f"no {lost[0]} pixels are left to score" if lost else None


def _try(ev: Evidence, effects: list[Effect], current: CheckResult, name: str) -> tuple[CheckResult | None, str]:
    """Fit ``effects`` + ``name``; the new check if it improves on ``current``, else None and why not."""
    try:
        # (assuming the converter the current model found: the new model's noise fit picks one again, and a change
        # costs it a second fit — on EMVA 1288's dithered series at every step)
        new = run_check(ev, [*effects, *resolve_effects([name])], dither=(current.quantiser or {}).get("dither"))
    except (ForensicsError, ArithmeticError, ValueError, RuntimeError) as exc:  # the fit reports a problem
        return None, f"adding {name} failed: {exc}"
    problem = _problem(current, new)
    if problem:
        return None, f"adding {name}: {problem}"
    if improvement(current, new) is None:
        return None, f"adding {name} did not lower the error or raise a failing gof p beyond its noise"
    return new, ""


def forward_select(ev: Evidence, start_effects: Sequence[Effect], max_steps: int = DEFAULT_MAX_STEPS,
                   start: CheckResult | None = None) -> SelectionResult:
    """Add the top flagged candidate and refit, until nothing is flagged.

    Parameters
    ----------
    ev
        Evidence built once from the data; every step is fitted to it.
    start_effects
        The starting model (usually :func:`~forensics.check.pipeline.base_model` plus the user's ``--add``);
        not changed.
    max_steps
        At most this many effects are added.
    start
        The starting model's check, if already computed (``run_check(ev, start_effects)``).

    Returns
    -------
    SelectionResult
        The path (first step: the starting model), and why it stopped.  At each step the flagged candidates
        are tried in rank order; one is kept if it improves the fit (:func:`improvement`); at most two are
        tried per model (a candidate not kept may be tried again once another one has been added).  Every
        kept step adds an effect, so the path ends after at most ``max_steps`` additions.
    """
    if max_steps < 0:
        raise UsageError(f"max_steps must be ≥ 0, not {max_steps}")
    effects = list(start_effects)
    current = start if start is not None else run_check(ev, effects)
    steps = [make_step(current, None)]
    refused: list[Attempt] = []
    while True:
        if not current.flagged:
            return _done(steps, refused, NOTHING_FLAGGED, "nothing flagged")
        if len(steps) - 1 >= max_steps:
            return _done(steps, refused, MAX_STEPS, f"max steps ({max_steps}) reached; still flagged: "
                         + ", ".join(current.flagged))
        for name in current.flagged[:2]:  # the top flagged candidate, else the next one
            new, why = _try(ev, effects, current, name)
            if new is None:
                refused.append(Attempt(name, why))
                continue
            effects.append(resolve_effects([name])[0])
            new.baseline = steps[0].result
            steps.append(make_step(new, name, refused))
            refused = []  # the model changed: a candidate not kept before may be tried again
            current = new
            break
        else:
            return _done(steps, refused, NO_IMPROVEMENT, "; ".join(a.reason for a in refused[-2:]))


def _done(steps: list[Step], refused: list[Attempt], reason: str, stopped: str) -> SelectionResult:
    return SelectionResult(steps=steps, stopped=stopped, reason=reason, rejected=refused)


def check_auto(data: Dataset | str | Path | Measurements, add: Sequence[str | Effect] = (), rng: RngLike = 0,
               max_steps: int = DEFAULT_MAX_STEPS, n_sim: int = 199, progress: Progress = no_progress,
               region: Region | None = None, executor: Executor | None = None) -> SelectionResult:
    """Forward selection on a dataset: the base model plus ``add``, then flagged candidates one at a time.

    Parameters
    ----------
    data
        Dataset (or its folder, or prepared :class:`Measurements`).
    add
        Effects the starting model has on top of the base model (names, ``module:Class``, ``file.py:Class``
        or instances, as in :func:`~forensics.check.pipeline.check`).
    rng
        Generator or integer seed of the Monte-Carlo simulations (the same streams at every step).
    max_steps
        At most this many candidates are added.
    n_sim
        Monte-Carlo simulations of the fitted arrival model.
    progress
        Progress callable for reading the frames.
    region
        ``(top, left, height, width)``: check only this part of every frame (default the whole frame).
    executor
        The execution layer (None: in this process): the conditions are read on it; the path is fitted here
        (see the module docstring).

    Returns
    -------
    SelectionResult
    """
    ev, extra = prepare(data, add, rng, n_sim, progress, region, executor)
    return forward_select(ev, [*base_model(ev.black_level), *extra], max_steps=max_steps)
