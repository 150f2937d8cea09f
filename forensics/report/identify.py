"""Figures and report of 1:N identification (:mod:`forensics.prnu.identify`).

Drawing and page layout only: each function takes an
:class:`~forensics.prnu.identify.IdentificationResult` and adds to or returns a :class:`Report`.
"""
from __future__ import annotations

import math

import numpy as np

from forensics.prnu.identify import IdentificationResult, QueryIdentification
from forensics.report.html import Report, new_figure

__all__ = ["add_identification", "identification_report", "plot_best_pce"]


def _signed_log(values: np.ndarray) -> np.ndarray:
    """``sign · log10(1 + |v|)``: PCE spans decades and may be negative."""
    return np.sign(values) * np.log10(1.0 + np.abs(values))


def plot_best_pce(ax, queries: list[QueryIdentification]) -> None:
    """Each image's best PCE (dot, coloured by decision) against the PCE it needed (dash), on a signed log scale."""
    x = np.arange(len(queries))
    best = np.array([q.best.pce if q.best else np.nan for q in queries], float)
    need = np.array([q.pce_threshold if math.isfinite(q.pce_threshold) else np.nan for q in queries], float)
    decision = np.array([q.decision for q in queries])
    shown = _signed_log(best)
    for kind, style in (("attributed", dict(color="C2", s=18)), ("unknown", dict(color="C3", s=18, marker="x")),
                        ("ambiguous", dict(color="C1", s=22, marker="D"))):
        chosen = decision == kind
        if chosen.any() or kind != "ambiguous":
            ax.scatter(x[chosen], shown[chosen], zorder=3, label=kind, **style)
    ax.scatter(x, _signed_log(need), color="0.3", marker="_", s=120, zorder=2, label="PCE needed at the p_FA")
    runner = np.array([q.runner_up.pce if q.runner_up else np.nan for q in queries], float)
    if np.isfinite(runner).any():
        ax.scatter(x, _signed_log(runner), color="C0", s=8, alpha=0.6, zorder=1, label="runner-up")
    ax.set_xlabel("image (in set order)")
    ax.set_ylabel("sign · log10(1 + |PCE|)")
    ax.legend(frameon=False, fontsize=8)


def _p_text(q: QueryIdentification) -> str:
    if q.best is None:
        return "—"
    return f"{q.p_fa:.2g}" if q.p_fa > 0 else f"1e{q.log10_p_fa:.0f}"


def _geometry(q: QueryIdentification) -> str:
    return q.best.geometry() if q.best is not None else (q.note or "")


def add_identification(result: IdentificationResult, rep: Report, *, prefix: str = "") -> None:
    """Add the per-image best PCE against its threshold and the identification table to a Report."""
    n = len(result.queries)
    others = "".join(f", {result.n_decided(d)} {d}" for d in ("ambiguous", "excluded") if result.n_decided(d))
    rep.text(f"{n} images against {len(result.devices)} fingerprints: {result.n_attributed} attributed, "
             f"{result.n_decided('unknown')} unknown{others}, at a false-alarm probability of {result.pfa:g} per "
             "image.")
    rep.text(f"Decision: {result.correction}. The PCE normalises the peak by the correlation energy of the shifts "
             "in its 8×8 block phase, since JPEG blocks make the null variance depend on it.", note=True)
    s = result.settings
    scales = s.get("scales")
    rep.table(["setting", "value"], [
        ["rotations", s.get("rotations")],
        ["crop (offset) search", "yes" if s.get("crop_search") else "no"],
        ["scales", "1 only" if not scales else (
            ",".join(f"{v:g}" for v in scales["values"]) if scales.get("values") else
            f"{scales['lo']:g}–{scales['hi']:g}, " + (f"step {scales['step']:g}" if scales.get("step") else
                                                       f"grid error ≤ {scales['max_error_px']:g} px"))],
        ["pre-screen", "off" if not s.get("prescreen") else
         f"on (sketch n/{s['prescreen']['compression']}, keep ≥ {s['prescreen']['min_keep']})"],
    ])
    if n:
        fig, ax = new_figure(max(6.4, min(14.0, 0.12 * n + 4)), 4)
        plot_best_pce(ax, result.queries)
        rep.figure(fig, f"{prefix}best_pce", "Each image's best PCE against the PCE it needed for an attribution "
                   "(which grows with the positions, scales and rotations searched), and the runner-up's PCE.")
    budgets = [(q.source, q.budget) for q in result.queries
               if q.budget and q.budget["aligned"]["n_tests"] and q.budget["searched"]["n_tests"]]
    if budgets:
        rep.table(["file", "aligned tests", "aligned share", "PCE needed aligned", "searched positions",
                   "searched share", "PCE needed searched"],
                  [[f, b["aligned"]["n_tests"], f"{100 * b['aligned']['share']:g} %", f"{b['aligned']['pce_threshold']:.1f}",
                    b["searched"]["n_tests"], f"{100 * b['searched']['share']:g} %",
                    f"{b['searched']['pce_threshold']:.1f}"] for f, b in budgets],
                  caption="The false-alarm budget split between same-size images at zero shift and the crop/scale "
                          "searches of other sensor sizes (weights summing to the number of tests)")
    notes = [[q.source, q.decision, q.note] for q in result.queries if q.decision in ("ambiguous", "excluded")]
    if notes:
        rep.table(["file", "decision", "why"], notes, caption="Images not attributed to one device, and why")
    counts = result.counts()
    if counts:
        rep.table(["device", "images attributed"], [[d, k] for d, k in sorted(counts.items())])
    rep.table(
        ["file", "best device", "PCE", "p_FA (corrected)", "PCE needed", "decision", "runner-up", "runner-up PCE",
         "geometry"],
        [[q.source, (" = ".join(q.matches) if q.decision == "ambiguous" else q.best.device_id) if q.best else "—", f"{q.best.pce:.1f}" if q.best else "—", _p_text(q),
          f"{q.pce_threshold:.1f}" if math.isfinite(q.pce_threshold) else "—", q.decision,
          q.runner_up.device_id if q.runner_up else "—", f"{q.runner_up.pce:.1f}" if q.runner_up else "—",
          _geometry(q)] for q in result.queries],
        caption="Identification of each image",
    )


def identification_report(result: IdentificationResult, command: str = "") -> Report:
    """A page for one identification run; ``command`` (the command line that ran it) is shown first."""
    rep = Report(f"Identification: {result.name or 'images'}")
    if command:
        rep.preformatted(command)
    add_identification(result, rep)
    return rep
