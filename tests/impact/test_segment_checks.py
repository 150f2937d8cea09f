"""Segmentation plumbing: the methods by name, failure detection and reporting, hit rates against marks.

Synthetic eyes come from test_segment.py's renderer (known circles); no real data is needed here.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError, UsageError
from forensics.impact.matchers import load_matchers, template_failure
from forensics.impact.segment import SEGMENTATIONS, Segmentation, Segmenter, plausibility, segment_iris
from forensics.impact.segment.evaluate import BoundaryMark, circle_error, hit_rates, is_hit, read_marks


def _test_segment_module():
    spec = importlib.util.spec_from_file_location("_impact_eye", Path(__file__).with_name("test_segment.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_eye = _test_segment_module()
render_eye, PUPIL, IRIS = _eye.render_eye, _eye.PUPIL, _eye.IRIS


def test_methods_by_name_and_unknown_names():
    assert set(SEGMENTATIONS) == {"caht", "wahet"}
    img = render_eye()
    for method in SEGMENTATIONS:
        seg = segment_iris(img, method)
        assert seg.method == method
    with pytest.raises(UsageError, match="unknown segmentation 'hough'.*caht, wahet"):
        segment_iris(img, "hough")
    with pytest.raises(UsageError, match="unknown segmentation"):
        Segmenter(method="hough")
    with pytest.raises(UsageError, match="unknown segmentation"):
        load_matchers(["masek"], segmentation="hough")
    assert load_matchers(["masek", "ko"], segmentation="wahet")[0].segmenter.method == "wahet"


@pytest.mark.parametrize("pupil, iris, expected", [
    ((160.0, 120.0, 30.0), (160.0, 120.0, 100.0), ""),
    ((160.0, 120.0, 90.0), (160.0, 120.0, 100.0), "radius ratio 0.90"),       # pupil nearly as large as iris
    ((160.0, 120.0, 5.0), (160.0, 120.0, 100.0), "radius ratio 0.05"),        # a pin-prick "pupil"
    ((235.0, 120.0, 30.0), (160.0, 120.0, 100.0), "pupil not inside the iris"),
    ((-20.0, 120.0, 20.0), (-20.0, 120.0, 100.0), "% of the iris inside the image"),
])
def test_plausibility_names_what_is_wrong(pupil, iris, expected):
    reason = plausibility(pupil, iris, (240, 320))
    if expected:
        assert expected in reason
    else:
        assert reason == ""


@pytest.mark.parametrize("method", sorted(SEGMENTATIONS))
@pytest.mark.parametrize("case", ["closed", "skin"])
def test_an_image_without_a_visible_eye_is_a_failure_with_a_reason(method, case):
    if case == "closed":      # a blink: the lid down over the whole iris (its margin below the limbus)
        img = render_eye(eyelid=IRIS[1] + IRIS[2] + 5, spot=None)
    else:                     # skin only: a smooth bright gradient with noise
        rng = np.random.default_rng(3)
        img = np.clip(170 + 0.1 * np.arange(320)[None, :] + rng.normal(0, 3, (240, 320)), 0, 255).astype(np.uint8)
    seg = segment_iris(img, method)
    assert not seg.ok and seg.reason


def test_too_little_usable_iris_is_a_failure():
    img = render_eye()
    # Everything brighter than 0.3 of full scale counted as reflection: the iris (~105/255) is masked, the band's
    # usable fraction drops below 25 % and the segmentation becomes a failure.
    segmenter = Segmenter(normalise_params={"reflection": 0.3}, min_usable=0.25)
    _t, mask, seg = segmenter.unwrap(img)
    assert mask.mean() < 0.25
    assert not seg.ok and "too little usable iris" in seg.reason
    assert Segmenter().unwrap(img)[2].ok
    # The template of a matcher carries the failure; a healthy eye's does not.
    from forensics.impact.masek import MasekMatcher

    assert template_failure(MasekMatcher(segmenter).encode(img)) is not None
    assert template_failure(MasekMatcher().encode(img)) is None
    assert template_failure(object()) is None


def test_failed_segmentation_keeps_its_reasons():
    seg = Segmentation(pupil=PUPIL, iris=IRIS).failed("weak limbus (0.10)").failed("too little usable iris")
    assert not seg.ok and seg.reason == "weak limbus (0.10); too little usable iris"


# --------------------------------------------------------------------------- hit rates
def test_hit_criterion_is_the_issues():
    truth = (100.0, 100.0, 50.0)
    assert is_hit((102.9, 100.0, 50.0), truth)                  # 2.9 px
    assert not is_hit((102.2, 102.2, 50.0), truth)              # 3.1 px
    assert is_hit((100.0, 100.0, 54.9), truth) and not is_hit((100.0, 100.0, 55.2), truth)   # 10 %


def test_hit_rates_count_each_boundary_and_the_clear_subset():
    marks = [BoundaryMark("a.png", (10, 10, 5), (10, 10, 20)),
             BoundaryMark("b.png", (50, 50, 5), (50, 50, 20)),
             BoundaryMark("c.png", (90, 90, 5), (90, 90, 20), limbus_clear=False),
             BoundaryMark("d.png", (1, 1, 1), (1, 1, 2))]          # no segmentation: skipped
    segs = {"a.png": Segmentation((10, 10, 5), (10, 10, 20)),                    # both hit
            "b.png": Segmentation((50, 50, 5), (60, 50, 20), ok=False, reason="x"),  # limbus 10 px off
            "c.png": Segmentation((95, 90, 5), (90, 90, 20))}                    # pupil 5 px off
    rates = hit_rates(segs, marks)
    assert rates.n == 3
    assert rates.rate("pupil") == (2, 3) and rates.rate("limbus") == (2, 3) and rates.rate("both") == (1, 3)
    assert rates.rate("limbus", clear_only=True) == (1, 2)
    assert [m.file for m in rates.misses()] == ["b.png", "c.png"]
    assert rates.flagged() == (1, 2)
    d = rates.to_dict()
    assert d["limbus"]["rate"] == pytest.approx(2 / 3) and len(d["images"]) == 3
    with pytest.raises(InputError, match="no segmentation matches"):
        hit_rates({"z.png": segs["a.png"]}, marks)


def test_read_marks_checks_its_file(tmp_path):
    good = tmp_path / "marks.csv"
    good.write_text("file,pupil_x,pupil_y,pupil_r,iris_x,iris_y,iris_r,limbus\n"
                    "a.png,1,2,3,4,5,6,clear\nb.png,1,2,3,4,5,6,uncertain\n")
    marks = read_marks(good)
    assert marks[0] == BoundaryMark("a.png", (1.0, 2.0, 3.0), (4.0, 5.0, 6.0), True)
    assert not marks[1].limbus_clear
    bad = tmp_path / "bad.csv"
    bad.write_text("file,pupil_x,pupil_y,pupil_r,iris_x,iris_y\na.png,1,2,3,4,5\n")
    with pytest.raises(InputError, match="missing column.*iris_r"):
        read_marks(bad)
    bad.write_text("file,pupil_x,pupil_y,pupil_r,iris_x,iris_y,iris_r\na.png,1,2,-3,4,5,6\n")
    with pytest.raises(InputError, match="line 2.*positive radii"):
        read_marks(bad)
    bad.write_text("file,pupil_x,pupil_y,pupil_r,iris_x,iris_y,iris_r\na.png,1,2,x,4,5,6\n")
    with pytest.raises(InputError, match="line 2.*not a number"):
        read_marks(bad)
    with pytest.raises(InputError, match="cannot read"):
        read_marks(tmp_path / "absent.csv")
    # The repository's ground truth reads.
    repo_marks = read_marks(Path(__file__).with_name("data") / "iitd_marks.csv")
    assert len(repo_marks) == 134 and sum(not m.limbus_clear for m in repo_marks) == 6


def test_segmentation_report_lists_each_problem_image_with_its_errors(tmp_path):
    from forensics.report.segmentation import SegmentedImage, segmentation_report

    img = render_eye()
    good = segment_iris(img)
    marks = {"hit.png": BoundaryMark("hit.png", PUPIL, IRIS),
             "miss.png": BoundaryMark("miss.png", PUPIL, (IRIS[0] + 8.0, IRIS[1], IRIS[2]))}
    failed = good.failed("weak limbus (0.10)")
    items = [SegmentedImage("hit.png", img, good, marks["hit.png"]),
             SegmentedImage("miss.png", img, good, marks["miss.png"]),
             SegmentedImage("failed.png", img, failed, None)]
    rates = hit_rates({"hit.png": good, "miss.png": good}, marks.values())
    page = segmentation_report(items, rates, "caht").write(tmp_path / "rep", force=True)
    html = Path(page).read_text()
    # The miss shows its limbus error (8 px off the mark) and the failure its reason; the hit is not listed.
    assert "miss.png" in html and "failed.png" in html and "hit.png" not in html
    assert "weak limbus (0.10)" in html
    limbus_error = circle_error(good.iris, marks["miss.png"].iris)[0]
    assert limbus_error > 3 and f"{limbus_error:.1f} px" in html
    assert len(list((tmp_path / "rep").glob("overlay_*.png"))) == 2


# --------------------------------------------------------------------------- WAHET's boundary support
def test_wahet_support_scores_where_the_boundary_meets_each_rays_strongest_rise():
    from forensics.impact.segment.wahet import _agreement

    cols = np.arange(100.0)
    rise = np.tile(np.exp(-0.5 * ((cols - 50) / 4.0) ** 2), (8, 1))       # every ray: a soft rise peaking at 50
    valid = np.ones_like(rise, dtype=bool)
    rows = np.ones(8, dtype=bool)
    assert _agreement(rise, valid, np.full(8, 50.0), rows, 10) == pytest.approx(1.0)
    # One σ off the peak: the rise there relative to the ray's strongest, exp(−1/2), not "missed".
    assert _agreement(rise, valid, np.full(8, 54.0), rows, 10) == pytest.approx(np.exp(-0.5), rel=1e-6)
    # Nowhere near a rise (the ray's strongest within the window is its own tail): close to 0.
    assert _agreement(rise, valid, np.full(8, 80.0), rows, 10) < 0.01
    # Rays that leave the image, or lie outside the sectors asked for, neither support nor contradict.
    off = np.full(8, 50.0)
    off[:4] = 80.0
    valid[:4, :] = False
    assert _agreement(rise, valid, off, rows, 10) == pytest.approx(1.0)
    assert _agreement(rise, np.ones_like(valid), off, np.arange(8) >= 4, 10) == pytest.approx(1.0)
    assert _agreement(rise, np.ones_like(valid), off, rows, 10) == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("width", [10.0, 15.0])
@pytest.mark.parametrize("seed", range(3))
def test_wahet_accepts_a_soft_limbus(width, seed):
    # Real near-infrared limbi are ramps of 10–20 px from iris to sclera at 320 × 240.  WAHET's former support
    # (the share of rays whose strongest rise lies within 1.5 px of the contour) rejected a correct circle on such
    # ramps (here at width 10 seed 0, width 15 seeds 0 and 2; on the IITD eyes 60 of 62 rejections were correct).
    img = render_eye(texture_seed=seed + 3, noise_seed=seed, limbus_width=width)
    seg = segment_iris(img, "wahet")
    assert seg.ok, seg.reason
    assert circle_error(seg.pupil, PUPIL)[0] <= 2.0 and circle_error(seg.pupil, PUPIL)[1] <= 0.05
    centre, radius = circle_error(seg.iris, IRIS)
    # The ramp's middle is the truth; the steepest rise of a textured ramp may sit anywhere on its inner half, so
    # the radius is held to half the ramp (7.5 % of 100 px).  The limbus's vertical position comes from its
    # lateral sectors only (the lid hides its top) and is drawn towards the pupil's, 2 px lower here: 5 px.
    assert radius <= 0.5 * width / IRIS[2] and centre <= 5.0, seg.iris


@pytest.mark.parametrize("case", ["closed", "skin"])
def test_wahet_still_rejects_an_eye_it_cannot_see_with_a_soft_limbus(case):
    # The gentler support must not let a blink through: the lid over a soft-limbus eye, or skin alone.
    if case == "closed":
        img = render_eye(eyelid=IRIS[1] + IRIS[2] + 5, spot=None, limbus_width=15.0)
    else:
        rng = np.random.default_rng(4)
        img = np.clip(160 + 0.2 * np.arange(320)[None, :] + rng.normal(0, 6, (240, 320)), 0, 255).astype(np.uint8)
    seg = segment_iris(img, "wahet")
    assert not seg.ok and seg.reason
