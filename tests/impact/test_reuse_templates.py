"""Reuse of templates whose rubber-sheet band did not change (:func:`forensics.impact.reuse.encode_reusing`).

A built-in matcher's template is ``encode_texture`` of the band (texture, usability mask, segmentation) that
the shared :class:`~forensics.impact.segment.Segmenter` unwraps; a template is reused exactly when that band is
byte-identical, and then equals a fresh encoding.  On real eyes (where ``../shared`` has them) the experiment
gives the same result, number for number, with every reuse and with none.
"""
from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from forensics.impact.experiment import parse_sensors, run_impact
from forensics.impact.masek import MasekMatcher
from forensics.impact.matchers import ExternalMatcher, load_matchers
from forensics._shared.digest import content_digest
from forensics.impact.matchers import compare_all
from forensics.impact.reuse import band_encoder, encode_reusing, score_digest, template_digest
from forensics.impact.segment.normalise import footprint
from forensics.io.dataset import open_dataset

ALL = ["masek", "ko", "qsw", "dct", "cr", "cb"]
IITD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "iitd-iris-001-040"


class Subclass(MasekMatcher):
    """A user's subclass: it could change ``encode`` or ``encode_texture``, so it is never reused."""


def test_only_the_exact_built_in_classes_reuse_templates():
    assert all(band_encoder(m) for m in load_matchers(ALL))
    assert not band_encoder(Subclass())
    assert not band_encoder(ExternalMatcher("true", name="cmd:true"))


@pytest.mark.parametrize("name", ALL)
def test_a_template_is_reused_exactly_when_its_band_is_unchanged(captures, name):
    (matcher,) = load_matchers([name])
    image = captures[0, 0]
    key, template, reused = encode_reusing(matcher, image, None)
    assert not reused and key is not None
    assert template_digest(template) == template_digest(matcher.encode(image))
    # The same pixels again: the band's digest agrees and the stored template is handed back.
    again = encode_reusing(matcher, image.copy(), (key, template))
    assert again[0] == key and again[1] is template and again[2]
    # A pixel of the iris changed: the band changes, the template is encoded anew and equals a fresh encoding.
    seg = matcher.segmenter.segment(image)
    row, col = int(round(seg.iris[1])), int(round(seg.iris[0] + (seg.pupil[2] + seg.iris[2]) / 2))   # mid-iris
    spot = image.copy()
    spot[row - 1:row + 2, col - 1:col + 2] = 255 - spot[row - 1:row + 2, col - 1:col + 2]
    changed = encode_reusing(matcher, spot, (key, template))
    assert changed[0] != key and not changed[2]
    assert template_digest(changed[1]) == template_digest(matcher.encode(spot))
    # A stored digest that does not match is never trusted, whatever template is offered with it.
    other = encode_reusing(matcher, image, (b"not this band", "a stale template"))
    assert not other[2] and template_digest(other[1]) == template_digest(template)


@pytest.mark.parametrize("name", ["masek", "cb"])
def test_a_band_whose_pixels_and_segmentation_are_unchanged_is_not_even_unwrapped(captures, name, monkeypatch):
    (matcher,) = load_matchers([name])
    image = captures[0, 0]
    key, template, _ = encode_reusing(matcher, image, None)
    seg = matcher.segmenter.segment(image)
    y0, y1, x0, x1 = footprint(seg, matcher.radial, matcher.angular, image.shape)
    outside = image.copy()
    outside[0, 0] ^= 1                                   # a corner pixel, outside the box the unwrapping reads
    assert y0 > 0 and x0 > 0
    inside = image.copy()
    row, col = int(round(seg.iris[1])), int(round(seg.iris[0] + (seg.pupil[2] + seg.iris[2]) / 2))   # mid-iris
    inside[row, col] ^= 64
    want_outside = template_digest(load_matchers([name])[0].encode(outside))
    want_inside = template_digest(load_matchers([name])[0].encode(inside))
    assert content_digest(matcher.segmenter.segment(outside)) == content_digest(seg)   # the corner moves nothing

    def no_unwrap(*args, **kwargs):
        raise AssertionError("unwrapped")

    with monkeypatch.context() as patch:
        patch.setattr(type(matcher.segmenter), "unwrap", no_unwrap)
        again = encode_reusing(matcher, outside, (key, template), image)
        assert again[0] == key and again[1] is template and again[2]
        assert template_digest(again[1]) == want_outside
        # A template encoded with another segmentation (here: marked failed) is never taken without unwrapping.
        other = dataclasses.replace(template, segmentation=seg.failed("another segmentation"))
        with pytest.raises(AssertionError, match="unwrapped"):
            encode_reusing(matcher, outside, (key, other), image)
    # A changed pixel in the box: unwrapped and encoded anew, equal to a fresh encoding.
    changed = encode_reusing(matcher, inside, (key, template), image)
    assert not changed[2] and template_digest(changed[1]) == want_inside


def _with_quality(template, quality):
    """The template with its segmentation's edge support (and every nested code's) set to ``quality``."""
    seg = dataclasses.replace(template.segmentation, quality=quality)
    codes = getattr(template, "codes", None)
    if codes is not None:       # dct: the planes carry the segmentation too
        codes = tuple(tuple(dataclasses.replace(c, segmentation=seg) for c in row) for row in codes)
        return dataclasses.replace(template, codes=codes, segmentation=seg)
    return dataclasses.replace(template, segmentation=seg)


@pytest.mark.parametrize("name", ALL)
def test_scores_are_keyed_by_the_code_alone_for_the_built_ins(captures, name):
    # A new defect often moves only the segmentation's edge support and leaves the code as it was: such a template
    # keeps its scores (score_digest), and every comparison indeed gives the same numbers for it.
    (matcher,) = load_matchers([name])
    templates = [matcher.encode(captures[e, c]) for e in range(3) for c in range(2)]
    moved = _with_quality(templates[0], templates[0].segmentation.quality / 2)
    assert template_digest(moved) != template_digest(templates[0])
    assert score_digest(matcher, moved) == score_digest(matcher, templates[0])
    want = compare_all(matcher, templates, templates)
    assert np.array_equal(compare_all(matcher, [moved, *templates[1:]], [moved, *templates[1:]]), want)
    # Another code is another key; a user's matcher is keyed by the whole template.
    assert len({score_digest(matcher, t) for t in templates}) == len(templates)
    assert score_digest(Subclass(), moved) == template_digest(moved) != template_digest(templates[0])


def test_a_subclass_encodes_every_image(captures):
    matcher = Subclass()
    key, template, reused = encode_reusing(matcher, captures[0, 0], (b"x", "stale"))
    assert key is None and not reused and template_digest(template) == template_digest(matcher.encode(captures[0, 0]))


@pytest.mark.realdata
@pytest.mark.slow
def test_real_eyes_give_the_same_result_with_every_reuse_and_with_none(tmp_path):
    # Sensor A over the paper's 13 ages on 8 real eyes (4 classes × 2): its 4 distinct aged-image sets are
    # computed in a chain whose later ages reuse the templates of unchanged bands and the scores of unchanged
    # templates; without reuse all 13 ages are computed from scratch.  All six algorithms, both protocols.
    if not (IITD / "manifest.csv").is_file():
        pytest.skip(f"the IITD iris images are not at {IITD} (research-use data kept outside the repository)")
    by_class: dict[str, list] = {}
    for f in open_dataset(IITD).frames:
        by_class.setdefault(f.subject, []).append(f)
    frames = [f for name in sorted(by_class)[30:34] for f in by_class[name][:2]]
    with open(tmp_path / "manifest.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["file", "subject"])
        for f in frames:
            (tmp_path / f.file).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / f.file).symlink_to(Path(f.path).resolve())      # linked, never copied
            writer.writerow([f.file, f.subject])
    source = open_dataset(tmp_path, allow_outside=True)
    sensors = parse_sensors("A", source.shape()[:2], 8)
    ages = [float(a) for a in range(0, 97, 8)]
    runs = {reuse: run_impact(source, sensors, ages, load_matchers(ALL), rng=2, n_boot=50, reuse=reuse)
            for reuse in (True, False)}
    fast, slow = runs[True], runs[False]
    assert fast.reused_templates > 0 and slow.reused_templates == 0 and fast.reused_units > 0
    assert fast.reused_steps > 0 and slow.reused_steps == 0
    a, b = fast.to_dict(), slow.to_dict()
    for d in (a, b):
        for how in ("elapsed_s", "resumed_units", "reused_units", "computed_pairs", "copied_pairs",
                    "reused_templates", "reused_steps"):
            d.pop(how)
    assert a == b
    for ua, ub in zip(fast.units, slow.units):
        assert np.array_equal(ua.eer.replicates, ub.eer.replicates, equal_nan=True) and ua.histogram == ub.histogram
