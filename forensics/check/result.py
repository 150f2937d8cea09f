"""The check's results: dataclasses with ``to_dict()`` for ``--json`` (reports take these, never recompute)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class ParamEstimate:
    """A fitted parameter: its value and standard error, or why the data do not determine it.

    ``identifiable`` False: the data carry no information on it or it trades off exactly against other
    parameters (``note`` says which); its value is then where the fit started and ``se`` is None.
    ``converged`` False: the fit did not settle; the value is not a result.
    ``bound`` ``"lower"``/``"upper"``: the fit rests on that bound of the parameter (e.g. a noise σ at 0); a
    symmetric interval would step outside the allowed range, so ``limit`` is the one-sided 95 % limit
    (bound ± 1.645·SE: at a boundary the likelihood-ratio statistic is a 50:50 mixture of 0 and χ²₁, whose
    95 % point is 1.645²).
    """

    effect: str
    name: str
    value: float
    se: float | None
    unit: str = ""
    identifiable: bool = True
    converged: bool = True
    note: str = ""
    bound: str = ""
    limit: float | None = None
    #: covariances with the other identifiable parameters fitted alongside (``effect.name`` → value), for
    #: quantities derived from several (a dark rate carried to another temperature with the fitted T_d)
    cov: dict[str, float] = dataclasses.field(default_factory=dict)
    #: False where the estimate is no peak of a near-quadratic likelihood (the largest of several values: its error
    #: is skewed), so that its standard error describes it but is no weight to pool it by across tiles
    quadratic: bool = True

    @property
    def label(self) -> str:
        return f"{self.effect}.{self.name}"

    def summary(self) -> str:
        """``value ± se unit``, or why there is no value."""
        if not self.converged:
            return f"did not converge ({self.note})" if self.note else "did not converge"
        if not self.identifiable:
            return f"not identifiable from these data ({self.note})"
        if self.bound and self.limit is not None:
            side = "<" if self.bound == "lower" else ">"
            unit = f" {self.unit}" if self.unit else ""
            return f"{self.value:.6g}{unit} (at its {self.bound} bound; {side} {self.limit:.4g} at 95 %)"
        se = "" if self.se is None else f" ± {self.se:.4g}"
        return f"{self.value:.6g}{se} {self.unit}".rstrip()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class PatternEstimate:
    effect: str
    name: str
    blocks: int
    rms: float
    maximum: float
    hyper: str | None = None
    hyper_value: float | None = None
    #: pixel-local patterns: the size as the frames show it (split-half, free of the noise floor) and its SE
    size: float | None = None
    size_se: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class CheckRow:
    statistic: str
    measured: float
    predicted: float
    z: float | None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class ChannelTest:
    """One channel's test of a candidate: LM (or likelihood-ratio) statistic, degrees of freedom, sample size."""

    channel: str
    lm: float
    df: int
    n: int
    detail: str
    boundary: bool = False  #: variance component tested at zero: the null distribution is ½χ²₀ + ½χ²₁
    absorbed: bool = False  #: the model's own parameters absorb (almost) all of the signature
    #: a fixed pattern's statistic as far as both halves of the frames show it (the split-half z², 0 when z ≤ 0);
    #: ``None`` for a test that is not of a fixed pattern
    confirmed: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Candidate:
    """One candidate effect's evidence."""

    effect: str
    delta_bic: float
    p: float
    flagged: bool
    lm: float
    df: int
    p_raw: float
    q: int
    tests: list[ChannelTest]
    evidence: str
    absorbed: bool = False
    #: the predicted ΔBIC with each fixed pattern's statistic taken only as far as both halves show it
    #: (:attr:`ChannelTest.confirmed`); ``None`` when no fixed pattern is tested
    delta_bic_confirmed: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "delta_bic": self.delta_bic, "delta_bic_confirmed": self.delta_bic_confirmed,
                "p": self.p, "flagged": self.flagged, "lm": self.lm, "df": self.df, "p_raw": self.p_raw, "q": self.q,
                "evidence": self.evidence, "tests": [t.to_dict() for t in self.tests]}


@dataclass
class StructureTest:
    """One test of the residual for structure (see :mod:`forensics.check.structure`)."""

    kind: str  #: ``column``, ``row``, ``radial``, ``trend`` or ``misfit trend``
    label: str  #: in words, e.g. "column-wise pattern"
    statistic: float  #: whitened χ² (profiles) or t of the slope (trends)
    df: float
    p: float
    p_holm: float  #: Holm-adjusted over every structure test run
    size: float  #: profiles: rms of the bin means in the residual, noise removed; trends: slope × range
    unit: str
    pattern_rms: float | None = None  #: profiles: rms of a bin-to-bin independent pattern leaving that residual
    share: float | None = None  #: profiles: share of the residual variance (DN²) in the bin means
    covariate: str | None = None
    slope: float | None = None
    slope_se: float | None = None
    sees: str = ""  #: what the test can and cannot see

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def summary(self) -> str:
        """E.g. "column-wise pattern, 3.1 DN rms (p = 1e-12)"."""
        if self.kind in ("column", "row", "radial"):
            size = self.pattern_rms if self.pattern_rms is not None else self.size
            what = f"{size:.2g} DN rms"
        else:
            what = f"slope {self.slope:.3g} ± {self.slope_se:.2g} ({self.size:.3g} {self.unit})"
        p = "p < 1e-300" if self.p_holm < 1e-300 else f"p = {self.p_holm:.2g}"
        return f"{self.label}, {what} ({p})"


@dataclass
class StructureResult:
    """Residual structure no fitted effect explains: every test, and the strongest one named (or None)."""

    tests: list[StructureTest]
    named: StructureTest | None
    notes: list[str] = dataclasses.field(default_factory=list)
    plots: dict[str, Any] | None = None  #: profiles and trends for the report (not serialised)

    def to_dict(self) -> dict[str, Any]:
        return {"named": None if self.named is None else self.named.to_dict(),
                "summary": None if self.named is None else self.named.summary(),
                "tests": [t.to_dict() for t in self.tests], "notes": self.notes}


@dataclass
class PlotData:
    """Arrays kept for the report (not serialised)."""

    residual_map: np.ndarray
    rms_map: np.ndarray
    consistency_map: np.ndarray
    class_map: np.ndarray
    covariates: dict[str, dict[str, Any]]
    counts: dict[str, Any]
    ripley: dict[str, Any]
    variance: dict[str, Any]


@dataclass(frozen=True)
class HeldOut:
    """The held-out half's squared residuals and noise floors per (condition, pixel) (float32, NaN where not
    scored) and the pixel classes they were scored in: two models fitted to the same data are compared on the
    same means (:func:`~forensics.check.select.paired_fall`)."""

    r2: np.ndarray
    floor: np.ndarray
    classes: np.ndarray


@dataclass
class CheckResult:
    """Everything :func:`check` found.  ``to_dict()`` gives the documented JSON."""

    effects: list[str]
    params: list[ParamEstimate]
    patterns: list[PatternEstimate]
    error: dict[str, Any]
    gof: dict[str, float | None]
    checks: list[CheckRow]
    candidates: list[Candidate]
    warnings: list[str]
    data: dict[str, Any]
    plots: PlotData | None = None
    baseline: "CheckResult | None" = None
    structure: StructureResult | None = None
    #: the converter the variance channel shows: ``dither`` (DN; 0 none) and, where the data could tell, the
    #: variance channel's χ² under each converter compared (:func:`~forensics.check.fit.fit_noise_and_quantiser`)
    quantiser: dict[str, Any] | None = None
    #: held-out terms for paired comparisons of models (not part of ``to_dict``)
    heldout: HeldOut | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def flagged(self) -> list[str]:
        return [c.effect for c in self.candidates if c.flagged]

    def to_dict(self) -> dict[str, Any]:
        out = {"effects": self.effects, "error": self.error, "gof": self.gof,
               "candidates": [c.to_dict() for c in self.candidates],
               "params": [p.to_dict() for p in self.params], "patterns": [p.to_dict() for p in self.patterns],
               "checks": [c.to_dict() for c in self.checks], "warnings": self.warnings, "data": self.data}
        if self.structure is not None:
            out["structure"] = self.structure.to_dict()
        if self.quantiser is not None:
            out["quantiser"] = self.quantiser
        if self.baseline is not None:
            out["before"] = {"effects": self.baseline.effects, "error": self.baseline.error,
                             "gof": self.baseline.gof, "flagged": self.baseline.flagged}
        return out
