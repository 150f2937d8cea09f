"""Detected defects against the simulated truth: which true defects were found, which detections are true.

The one matcher of the toolkit (used by the validation trials and by the demo): a detection and a true
defect match when they sit on the same pixel.  The truth is the device's catalogue at the detection's
time (:meth:`forensics.sensor.catalogue.DefectCatalogue.effective`: one record per site, stuck overriding
partially stuck), restricted to the region the detection analysed (``DetectionResult.mask``; the whole
frame when the detection kept no mask).  Detections only ever lie inside that region, so true positives
and false positives do not depend on the restriction.

Examples
--------
>>> m = match_truth(detection, device.catalogue, 2008.0)             # doctest: +SKIP
>>> m.recall(m.kind == PARTIAL), m.precision                          # doctest: +SKIP
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from forensics.defects.detection import DetectionResult
from forensics.sensor.catalogue import PARTIAL, DefectCatalogue

__all__ = ["TruthMatch", "match_truth", "count_true"]


@dataclass(frozen=True)
class TruthMatch:
    """The true defects of the analysed region at one time, and which of them a detection found.

    Attributes
    ----------
    x, y, kind, amplitude : ndarray
        The true defects inside the analysed region (amplitude in output DN).
    found : ndarray of bool
        Each true defect's site was detected (as any kind).
    found_same_kind : ndarray of bool
        Its site was detected as its own kind (e.g. a stuck pixel found stuck).
    n_detected : int
        Detections in all.
    true_positives : int
        Detections that sit on a true defect (of any kind).
    scale : float
        σ of d̂ of the detection's first channel (DN): the unit of :attr:`amplitude_sigma`.
    """

    x: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    amplitude: np.ndarray
    found: np.ndarray
    found_same_kind: np.ndarray
    n_detected: int
    true_positives: int
    scale: float

    def __len__(self) -> int:
        return len(self.x)

    @property
    def false_positives(self) -> int:
        """Detections on pixels that are not defective."""
        return self.n_detected - self.true_positives

    @property
    def precision(self) -> float:
        """True positives over detections (0 when nothing was detected)."""
        return self.true_positives / max(self.n_detected, 1)

    @property
    def amplitude_sigma(self) -> np.ndarray:
        """Amplitudes in units of σ of d̂."""
        return self.amplitude / self.scale

    def recall(self, select: np.ndarray | None = None) -> float:
        """Fraction of the (selected) true defects that were detected; NaN when none is selected."""
        sel = np.ones(len(self), bool) if select is None else np.asarray(select, bool)
        return float(np.mean(self.found[sel])) if sel.any() else float("nan")


def _region(detection: DetectionResult, truth: DefectCatalogue) -> np.ndarray:
    """Which true sites lie in the detection's analysed region."""
    if detection.mask is None:
        return np.ones(len(truth), bool)
    return detection.mask[truth.y, truth.x]


def match_truth(detection: DetectionResult, catalogue: DefectCatalogue, time: float) -> TruthMatch:
    """Match a detection to the true defects of ``catalogue`` at ``time`` (decimal years), pixel by pixel.

    Parameters
    ----------
    detection : DetectionResult
        Of frames taken at ``time``.
    catalogue : DefectCatalogue
        The simulated device's ground truth (e.g. ``device.catalogue`` or ``read_catalogue(defects.csv)``).
    time : float
        Capture time of the detection's frames.

    Returns
    -------
    TruthMatch
    """
    truth = catalogue.effective(time)
    truth = truth.select(_region(detection, truth))
    sites = list(zip(truth.x.tolist(), truth.y.tolist()))
    found = detection.sites()
    found_same = np.zeros(len(sites), bool)
    for k in np.unique(truth.kind).tolist():
        of_kind = detection.sites(int(k))
        idx = np.flatnonzero(truth.kind == k)
        found_same[idx] = [sites[i] in of_kind for i in idx]
    return TruthMatch(
        x=truth.x, y=truth.y, kind=truth.kind, amplitude=truth.amplitude,
        found=np.array([s in found for s in sites], bool), found_same_kind=found_same,
        n_detected=len(found), true_positives=len(found & set(sites)), scale=float(detection.fits[0].scale),
    )


def count_true(catalogue: DefectCatalogue, time: float, region: np.ndarray | None = None, kind: int | None = PARTIAL,
               above: float = -np.inf) -> int:
    """True defects at ``time`` inside ``region`` (a boolean image; None: everywhere) of one ``kind`` (None: any)
    with amplitude strictly above ``above`` DN — e.g. the defects a threshold τ can see."""
    eff = catalogue.effective(time)
    inside = np.ones(len(eff), bool) if region is None else region[eff.y, eff.x]
    if kind is not None:
        inside &= eff.kind == kind
    return int((inside & (eff.amplitude > above)).sum())
