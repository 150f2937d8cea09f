"""Matchers: Masek's and Ko et al.'s iris codes, the vectorised all-against-all, external programs, the loader."""
from __future__ import annotations

import importlib.util
import pickle
import shlex
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError, UsageError
from forensics.impact.matchers import (
    BUILTIN_MATCHERS,
    ExternalMatcher,
    IrisCode,
    KoMatcher,
    MasekMatcher,
    Matcher,
    compare_all,
    hamming_all,
    hamming_distance,
    load_matcher,
    load_matchers,
)
from forensics.impact.segment import Segmenter


def _eye_renderer():
    """The synthetic eye of test_segment.py, loaded by path (works whatever pytest's import mode)."""
    spec = importlib.util.spec_from_file_location("_impact_eye", Path(__file__).with_name("test_segment.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.render_eye


render_eye = _eye_renderer()
STEP = 2 * np.pi / 240          # one angular sample of Masek's 240-column texture


@pytest.fixture(scope="module")
def templates(captures):
    seg = Segmenter()
    masek, ko = MasekMatcher(seg), KoMatcher(seg)
    return {"masek": (masek, {k: masek.encode(v) for k, v in captures.items()}),
            "ko": (ko, {k: ko.encode(v) for k, v in captures.items()})}


# --------------------------------------------------------------------------- recognition
# Bounds.  An impostor comparison XORs two unrelated codes: each valid bit differs with probability 1/2 for
# Masek's phase bits, so the distance is a binomial fraction around 0.5 whose spread is set by the number
# of *independent* bits (the Log-Gabor filter correlates neighbours; Daugman counts ~250 degrees of freedom
# in 2048 bits, i.e. ~1000 here, σ ≈ 0.016).  Minimising over 17 shifts takes it ~2σ lower (≈0.47, as
# observed); 0.40 is more than 4σ below that.  Genuine pairs differ only by noise, a pixel of segmentation
# and the residue of rotation interpolation: a few percent of the bits, so 0.15 leaves room.
# Ko's codes are mostly "flat" (0): for a bit set with frequency q, chance disagreement is 2q(1−q) ≈ 0.34,
# and impostors observe ≈0.29 after 5 shifts (spread ≈0.01 over ~4300 correlated bits); 0.25 is 4σ below.
# A 4.5° rotation is almost half a 10° cell, which moves cell means: genuine pairs sit near 0.18, so the
# genuine bound is 0.22; a rotation by a whole cell costs nothing (tested below).
BOUNDS = {"masek": (0.15, 0.40), "ko": (0.22, 0.25)}


@pytest.mark.parametrize("name", ["masek", "ko"])
def test_genuine_pairs_are_closer_than_impostors(templates, name):
    matcher, t = templates[name]
    genuine_max, impostor_min = BOUNDS[name]
    eyes = range(5)
    genuine = [matcher.compare(t[e, 0], t[e, 1]) for e in eyes]
    impostor = [matcher.compare(t[e, 0], t[f, 1]) for e in eyes for f in eyes if e != f]
    assert max(genuine) < genuine_max, genuine
    assert min(impostor) > impostor_min, min(impostor)
    assert max(impostor) <= 0.6


@pytest.mark.parametrize("name", ["masek", "ko"])
def test_distance_is_zero_to_itself_and_symmetric(templates, name):
    matcher, t = templates[name]
    keys = list(t)
    for k in keys:
        assert matcher.compare(t[k], t[k]) == 0.0
    for a in keys[:4]:
        for b in keys[4:8]:
            assert matcher.compare(t[a], t[b]) == matcher.compare(t[b], t[a])


@pytest.mark.parametrize("name", ["masek", "ko"])
def test_shift_invariance(templates, name):
    matcher, t = templates[name]
    code = t[0, 0]
    for s in range(-matcher.max_shift, matcher.max_shift + 1):
        assert matcher.compare(code, code.shifted(s)) == 0.0
        assert matcher.compare(code.shifted(s), code) == 0.0
    # Just beyond the search range the code no longer lines up with itself.
    assert matcher.compare(code, code.shifted(matcher.max_shift + 6)) > 0.1


def test_rotating_the_eye_by_whole_steps_costs_little():
    # Masek: 5 angular samples (7.5°); Ko: one 10° cell, which its sliding groups turn into an exact shift.
    for matcher, angle in ((MasekMatcher(), 5 * STEP), (KoMatcher(), np.radians(10.0))):
        base = matcher.encode(render_eye(texture_seed=7, noise_seed=1))
        turned = matcher.encode(render_eye(texture_seed=7, noise_seed=2, rotation=angle))
        assert matcher.compare(base, turned) < 0.08, matcher.name


def test_failed_comparisons_are_a_distance_of_one():
    matcher = MasekMatcher()
    code = matcher.encode(render_eye())
    bits, mask = code.unpack()
    empty = IrisCode.from_bits(bits, np.zeros_like(mask))
    assert matcher.compare(code, empty) == 1.0
    assert matcher.compare_all([code, empty], [empty])[:, 0].tolist() == [1.0, 1.0]


def test_masek_code_layout():
    matcher = MasekMatcher()
    code = matcher.encode(render_eye())
    assert code.bits.shape == (240, 5) and code.bits_per_column == 40 and code.n_bits == 9600
    assert code.segmentation is not None and code.segmentation.ok
    bits, mask = code.unpack()
    # Both bits of a sample share its mask; the eyelid removes part of the top (columns near 60).
    assert np.array_equal(mask[:, 0::2], mask[:, 1::2])
    assert mask[50:70].mean() < mask[170:190].mean()
    # Phase bits are balanced.
    assert 0.4 < bits[mask].mean() < 0.6


# --------------------------------------------------------------------------- Ko et al.
def test_ko_group_codes_follow_the_cumulative_sum():
    codes = KoMatcher.group_codes
    # Rising values: S = −2, −3, −3, −2, 0; the minimum (first) at k=1, the maximum at k=4 → cells 2–4 "up".
    assert codes(np.array([1.0, 2, 3, 4, 5])).tolist() == [0, 0, 1, 1, 1]
    # Falling values: the mirror image, "down".
    assert codes(np.array([5.0, 4, 3, 2, 1])).tolist() == [0, 0, 2, 2, 2]
    # A peak in the middle: S = −1, 1, 1, 0, 0 (max k=1, min k=0) → only cell 1 rises.
    assert codes(np.array([1.0, 4, 2, 1, 2])).tolist() == [0, 1, 0, 0, 0]
    assert codes(np.full(5, 3.0)).tolist() == [0, 0, 0, 0, 0]
    # Any leading shape: vectorised over groups.
    assert codes(np.array([[1.0, 2, 3, 4, 5], [5.0, 4, 3, 2, 1]])).shape == (2, 5)


def test_ko_code_holds_every_group_position():
    matcher = KoMatcher()
    rng = np.random.default_rng(0)
    texture = rng.normal(100, 20, size=(30, 360)).astype(np.float32)
    mask = np.ones(texture.shape, bool)
    mask[:, 100:130] = False                  # three masked cell columns (10..12)
    code = matcher.encode_texture(texture, mask)
    rows, cols, g = 10, 36, 5
    assert code.bits.shape == (cols, 15) and code.bits_per_column == rows * (g + 1) * 2
    bits, valid = code.unpack()
    bits = bits.reshape(cols, rows, g + 1, 2)
    valid = valid.reshape(cols, rows, g + 1, 2)
    means, ok = matcher.cells(texture, mask)
    assert ok.sum() == rows * (cols - 3)
    # Horizontal window starting at cell w: its cells w..w+4 hold its codes at positions 0..4.
    for w in (0, 15, 33):                      # 33 wraps around to cells 0 and 1
        cells = (w + np.arange(g)) % cols
        expect = KoMatcher.group_codes(means[:, cells])                     # (rows, g)
        for o, c in enumerate(cells):
            got = bits[c, :, o, 0].astype(int) + 2 * bits[c, :, o, 1].astype(int)
            assert got.tolist() == expect[:, o].tolist()
            assert valid[c, :, o, 0].all()
    # A window touching a masked cell is invalid for all of its cells.
    assert not valid[9, :, 0, 0].any()          # window 9..13 includes cells 10..12
    assert valid[13, :, 0, 0].all()             # window 13..17 is clear
    # Vertical codes: fixed blocks of 5 cell rows.
    expect_v = KoMatcher.group_codes(means[0:5, 20])
    got_v = bits[20, 0:5, g, 0].astype(int) + 2 * bits[20, 0:5, g, 1].astype(int)
    assert got_v.tolist() == expect_v.tolist()


# --------------------------------------------------------------------------- bit-packed all-against-all
def _random_codes(rng, n, columns, bits_per_column):
    """Codes with realistic holes: random drop-outs, an eyelid-like block of columns, a few almost empty."""
    codes = []
    for i in range(n):
        bits = rng.random((columns, bits_per_column)) < 0.5
        mask = rng.random((columns, bits_per_column)) < 0.92
        start = rng.integers(0, columns)
        width = rng.integers(0, columns // 3)
        mask[(start + np.arange(width)) % columns] = False
        if i % 5 == 3:
            mask &= rng.random(mask.shape) < 0.05     # below the valid-bit minimum for most shifts
        codes.append(IrisCode.from_bits(bits, mask))
    return codes


@pytest.mark.parametrize("name", ["masek", "ko"])
def test_compare_all_equals_the_pairwise_loop_exactly(templates, name):
    matcher, t = templates[name]
    rng = np.random.default_rng(1)
    real = list(t.values())[:4]
    columns, bpc = real[0].columns, real[0].bits_per_column
    a = real[:2] + _random_codes(rng, 9, columns, bpc)
    b = real[2:] + _random_codes(rng, 8, columns, bpc)
    fast = matcher.compare_all(a, b)
    loop = np.array([[matcher.compare(x, y) for y in b] for x in a])
    assert fast.shape == (11, 10)
    assert np.array_equal(fast, loop)
    assert (fast == 1.0).any()                      # some pairs had too few valid bits
    assert np.array_equal(compare_all(matcher, a, b), fast)


def test_hamming_all_with_padding_and_small_chunks():
    rng = np.random.default_rng(2)
    # 13 bits per column (padded to 2 bytes), 37 columns (74 bytes, padded to 80 = 10 words).
    a = _random_codes(rng, 13, 37, 13)
    b = _random_codes(rng, 17, 37, 13)
    loop = np.array([[hamming_distance(x, y, 4, 20) for y in b] for x in a])
    # Smallest chunks (one code of a × 16 of b, so b splits 16 + 1), medium, everything in one block.
    for memory, block in ((1, 1), (2**14, 2**12), (2**26, 2**26)):
        assert np.array_equal(hamming_all(a, b, 4, 20, memory=memory, block_bytes=block), loop)


def test_planes_under_one_mask_equal_hamming_all_plane_by_plane_and_shift_by_shift():
    # Monro's DCT template: three bit planes under one mask; hamming_planes counts the valid bits once per shift
    # and must still give, for every plane and shift, hamming_all of the shifted codes (small blocks split both
    # sides; a template whose planes' masks differ goes plane by plane, also exactly).
    from forensics.impact.iriscode import hamming_planes

    rng = np.random.default_rng(5)

    def templates(n: int, shared: bool = True) -> list[tuple[IrisCode, ...]]:
        masks = _random_codes(rng, n, 29, 12)
        return [tuple(IrisCode.from_bits(rng.random((29, 12)) < 0.5,
                                         m.unpack()[1] if shared or p == 0 else rng.random((29, 12)) < 0.9)
                      for p in range(3)) for m in masks]

    a, b = templates(9), templates(11)
    odd = [*b[:10], templates(1, shared=False)[0]]
    shifts = [-2, -1, 0, 1, 2]
    for other in (b, odd):
        for chunk in ((2, 3), (32, 256)):
            got = hamming_planes(a, other, shifts, 40, chunk=chunk)
            for k, s in enumerate(shifts):
                for p in range(3):
                    want = hamming_all([t[p] for t in a], [t[p].shifted(s) for t in other], 0, 40)
                    assert np.array_equal(got[k, p], want)
    assert (got == 1.0).any() and (got < 1.0).any()


def test_mismatched_codes_are_refused():
    small = IrisCode.from_bits(np.zeros((10, 8), bool), np.ones((10, 8), bool))
    big = IrisCode.from_bits(np.zeros((12, 8), bool), np.ones((12, 8), bool))
    with pytest.raises(InputError, match="different layouts"):
        MasekMatcher().compare(small, big)
    with pytest.raises(InputError, match="different layouts"):
        hamming_all([small], [big], 1, 1)


def test_iris_code_round_trip_and_pickle():
    rng = np.random.default_rng(3)
    bits, mask = rng.random((20, 11)) < 0.5, rng.random((20, 11)) < 0.8
    code = IrisCode.from_bits(bits, mask)
    got_bits, got_mask = code.unpack()
    assert np.array_equal(got_mask, mask) and np.array_equal(got_bits, bits & mask)
    assert code.n_valid == mask.sum() and code.n_bits == 220
    assert np.array_equal(code.shifted(3).unpack()[0], np.roll(bits & mask, 3, axis=0))
    again = pickle.loads(pickle.dumps(code))
    assert np.array_equal(again.bits, code.bits) and again.bits_per_column == 11
    # Matchers travel to worker processes without their segmenter's cache.
    matcher = MasekMatcher()
    matcher.encode(render_eye())
    clone = pickle.loads(pickle.dumps(matcher))
    assert clone.segmenter._seg is None and clone.max_shift == 8


# --------------------------------------------------------------------------- the interface and compare_all
class _Mean:
    """A toy matcher without compare_all: the absolute difference of mean grey values."""

    name = "mean"
    higher_is_similar = False

    def encode(self, image):
        return float(np.mean(image))

    def compare(self, a, b):
        return abs(a - b)


def test_protocol_and_fallback_loop():
    assert isinstance(MasekMatcher(), Matcher) and isinstance(KoMatcher(), Matcher)
    assert isinstance(_Mean(), Matcher) and isinstance(ExternalMatcher("true"), Matcher)
    scores = compare_all(_Mean(), [1.0, 2.0, 5.0], [0.0, 4.0])
    assert scores.tolist() == [[1.0, 3.0], [2.0, 2.0], [5.0, 1.0]]

    class Wrong(_Mean):
        def compare_all(self, a, b):
            return np.zeros((1, 1))

    with pytest.raises(InputError, match="shape"):
        compare_all(Wrong(), [1.0, 2.0], [1.0])


# --------------------------------------------------------------------------- external matchers
EXTERNAL = textwrap.dedent("""\
    import sys

    from forensics.io.images import read_image

    args = sys.argv[1:]
    mode = args.pop(0) if args[0].startswith("--") else ""
    if args[0] == "encode":
        with open(args[2], "w") as f:
            f.write(repr(float(read_image(args[1]).mean())))
    elif args[0] == "compare":
        if mode == "--fail":
            sys.stderr.write("cannot compare these\\n")
            sys.exit(3)
        if mode == "--junk":
            print("about 3")
            sys.exit(0)
        a, b = (float(open(p).read()) for p in args[1:3])
        print(abs(a - b))
    """)


@pytest.fixture
def external(tmp_path):
    script = tmp_path / "ext_matcher.py"
    script.write_text(EXTERNAL)
    return f"{shlex.quote(sys.executable)} {shlex.quote(str(script))}"


def test_external_matcher_protocol(external):
    matcher = ExternalMatcher(external, higher_is_similar=False)
    dark = np.full((24, 32), 40, np.uint8)
    light = np.full((24, 32), 50, np.uint8)
    ta, tb = matcher.encode(dark), matcher.encode(light)
    assert isinstance(ta, bytes) and float(ta) == 40.0
    assert matcher.compare(ta, tb) == 10.0
    assert compare_all(matcher, [ta], [ta, tb]).tolist() == [[0.0, 10.0]]


def test_external_matcher_errors_name_the_command(external, tmp_path):
    with pytest.raises(InputError, match="ext_matcher.py.*exit status 3: cannot compare these"):
        ExternalMatcher(external + " --fail").compare(b"1", b"2")
    with pytest.raises(InputError, match="ext_matcher.py.*'about 3', not one number"):
        ExternalMatcher(external + " --junk").compare(b"1", b"2")
    with pytest.raises(InputError, match="no-such-program-here"):
        ExternalMatcher("no-such-program-here").compare(b"1", b"2")
    with pytest.raises(InputError, match="uint8 or uint16"):
        ExternalMatcher(external).encode(np.zeros((4, 4), np.float32))


# --------------------------------------------------------------------------- loading
USER_MATCHER = textwrap.dedent('''\
    """A user's matcher: grey-level histogram intersection (a similarity)."""
    import numpy as np


    class HistogramMatcher:
        name = "histogram"
        higher_is_similar = True

        def __init__(self, bins=32):
            self.bins = bins

        def encode(self, image):
            hist, _ = np.histogram(np.asarray(image), bins=self.bins, range=(0, 256))
            return hist / max(hist.sum(), 1)

        def compare(self, a, b):
            return float(np.minimum(a, b).sum())


    class NoCompare:
        name = "half"
        higher_is_similar = False

        def encode(self, image):
            return image


    class Nameless:
        def encode(self, image):
            return image

        def compare(self, a, b):
            return 0.0


    class NeedsArguments(HistogramMatcher):
        def __init__(self, model_path):
            super().__init__()
    ''')


def test_load_builtins_share_a_segmenter():
    seg = Segmenter()
    masek, ko = load_matcher("masek", seg), load_matcher("ko", seg)
    assert isinstance(masek, MasekMatcher) and isinstance(ko, KoMatcher)
    assert masek.segmenter is seg and ko.segmenter is seg
    assert set(BUILTIN_MATCHERS) == {"masek", "ko", "qsw", "dct", "cr", "cb"}
    both = load_matchers(["masek", "ko"])
    assert both[0].segmenter is both[1].segmenter
    img = render_eye()
    both[0].encode(img)
    both[1].encode(img)
    assert both[0].segmenter.computed == 1      # one segmentation for both matchers


def test_load_user_classes(tmp_path, monkeypatch):
    path = tmp_path / "user_matcher.py"
    path.write_text(USER_MATCHER)
    matcher = load_matcher(f"{path}:HistogramMatcher")
    assert isinstance(matcher, Matcher) and matcher.name == "histogram" and matcher.higher_is_similar
    a, b = matcher.encode(render_eye()), matcher.encode(render_eye(texture_seed=5))
    assert matcher.compare(a, a) == pytest.approx(1.0)
    scores = compare_all(matcher, [a, b], [a, b])
    assert scores.shape == (2, 2) and scores[0, 1] == scores[1, 0] < 1.0
    # module.path:Class, for a module on sys.path and for the toolkit's own classes.
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_matcher("user_matcher:HistogramMatcher").name == "histogram"
    assert isinstance(load_matcher("forensics.impact.matchers:KoMatcher"), KoMatcher)


def test_load_external_specs(external):
    distance = load_matcher(f"cmd:{external}")
    similarity = load_matcher(f"cmd+sim:{external}")
    assert isinstance(distance, ExternalMatcher) and not distance.higher_is_similar
    assert isinstance(similarity, ExternalMatcher) and similarity.higher_is_similar
    assert distance.name == f"cmd:{external}"
    t = distance.encode(np.full((8, 8), 9, np.uint8))
    assert distance.compare(t, t) == 0.0


def test_bad_specs_say_what_is_accepted(tmp_path):
    path = tmp_path / "user_matcher.py"
    path.write_text(USER_MATCHER)
    broken = tmp_path / "broken.py"
    broken.write_text("def oops(:\n")
    forms = "masek, ko.*module.path:Class.*file.py:Class.*cmd:COMMAND.*cmd\\+sim:COMMAND"
    for spec in ("nope", "", "Masek", "a b:C", ":Class", "module:"):
        with pytest.raises(UsageError, match=forms):
            load_matcher(spec)
    cases = {
        f"{tmp_path}/missing.py:X": "no such file",
        "no_such_module_xyz:Thing": "cannot load the matcher.*ModuleNotFoundError",
        f"{broken}:X": "cannot load the matcher.*SyntaxError",
        "json:NoSuchClass": "json has no NoSuchClass",
        "json:dumps": "dumps is not a class",
        f"{path}:NoCompare": "lacks compare",
        f"{path}:Nameless": "lacks name, higher_is_similar",
        f"{path}:NeedsArguments": "constructible with no arguments",
        "cmd:": "needs a command",
    }
    for spec, message in cases.items():
        with pytest.raises(UsageError, match=message):
            load_matcher(spec)
    with pytest.raises(UsageError, match="unique.*masek"):
        load_matchers(["masek", "ko", "masek"])


@pytest.mark.parametrize("name", ["masek", "ko"])
def test_upper_triangle_scores_equal_the_full_matrix(templates, name):
    # The experiment scores only the pairs i < j, in bands of rows; each must be the full matrix's exactly.
    from forensics.impact.experiment import _upper_scores

    matcher, t = templates[name]
    codes = list(t.values())
    i, j = np.triu_indices(len(codes), 1)
    for enrol, probe in ((codes, codes), (codes, codes[::-1])):
        assert np.array_equal(_upper_scores(matcher, enrol, probe, 3), compare_all(matcher, enrol, probe)[i, j])
