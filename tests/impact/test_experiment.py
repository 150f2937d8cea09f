"""The ageing-impact experiment with a small stand-in matcher: exactness, ageing, pairing, resuming."""
from __future__ import annotations

import zlib

import numpy as np
import pytest

from forensics._shared.errors import InputError, UsageError
from forensics._shared.rng import keyed_generator
from forensics.impact.experiment import parse_sensors, run_impact
from forensics.io.dataset import open_dataset, write_manifest
from forensics.io.images import write_image
from forensics.sensor.effects import ReadNoise
from forensics.sensor.presets import preset
from forensics.sensor.simulate import age_dataset
from forensics.stats.scores import eer

SHAPE = (32, 48)


class BlockMatcher:
    """Correlation of 4×4 block means: a matcher simple enough to score by hand."""

    name = "blocks"
    higher_is_similar = True

    def encode(self, image: np.ndarray) -> np.ndarray:
        blocks = image.astype(np.float64).reshape(SHAPE[0] // 4, 4, SHAPE[1] // 4, 4).mean(axis=(1, 3)).ravel()
        blocks -= blocks.mean()
        return blocks / np.linalg.norm(blocks)

    def compare(self, a: np.ndarray, b: np.ndarray) -> float:
        return float(a @ b)


class Interrupted(Exception):
    pass


class FailingMatcher(BlockMatcher):
    """Stops the run after ``budget`` encodes, as a killed process would."""

    def __init__(self, budget: int) -> None:
        self.budget = budget

    def encode(self, image: np.ndarray) -> np.ndarray:
        self.budget -= 1
        if self.budget < 0:
            raise Interrupted
        return super().encode(image)


def _write_set(root, classes: int = 8, samples: int = 4, seed: int = 0, subjects: bool = True, noise: float = 28.0):
    rng = np.random.default_rng(seed)
    rows = []
    root.mkdir()
    for c in range(classes):
        base = rng.normal(128, 30, SHAPE)
        for s in range(samples):
            image = np.clip(base + rng.normal(0, noise, SHAPE), 0, 255).astype(np.uint8)
            name = f"c{c:02d}_{s}.png"
            write_image(root / name, image)
            rows.append({"file": name, "subject": f"class{c:02d}" if subjects else None})
    write_manifest(root / "manifest.csv", rows)
    return open_dataset(root)


def _comparable(result) -> dict:
    out = result.to_dict()
    out.pop("elapsed_s")
    out.pop("resumed_units")
    for how in ("reused_units", "computed_pairs", "copied_pairs", "reused_templates",
                "reused_steps"):                                  # how it was obtained, not what it is
        out.pop(how)
    return out


def test_eers_equal_a_plain_loop_over_the_aged_images_of_age_dataset(tmp_path):
    source = _write_set(tmp_path / "src")
    sensors = parse_sensors("H*50", SHAPE, 8)
    ages = [0.0, 48.0]
    result = run_impact(source, sensors, ages, [BlockMatcher()], rng=4, n_boot=50)
    # The same device and frame noise, through the ageing command's own code.
    model = preset("H", SHAPE, bit_depth=8, rate_scale=50.0)
    aged = age_dataset(source, tmp_path / "aged", model, ages, start_year=2000.0,
                       rng=keyed_generator(4, 1, zlib.crc32(sensors[0].name.encode())))
    matcher = BlockMatcher()
    labels = [f.subject for f in source.frames]
    for step, age in zip(aged.steps, ages):
        templates = [matcher.encode(f.load()) for f in open_dataset(step).frames]
        enrol = [matcher.encode(f.load()) for f in open_dataset(aged.steps[0]).frames]
        for protocol, gallery in (("same-age", templates), ("enrol-0", enrol)):
            genuine, impostor = [], []
            for a in range(len(labels)):
                for b in range(a + 1, len(labels)):
                    (genuine if labels[a] == labels[b] else impostor).append(matcher.compare(gallery[a], templates[b]))
            unit = result.unit(sensors[0].name, age, "blocks", protocol)
            assert unit.eer.estimate == pytest.approx(eer(genuine, impostor).eer, abs=1e-12)
            assert unit.eer.n_genuine == len(genuine) == 8 * 6
            assert unit.eer.n_impostor == len(impostor)
    # At age 0 the two protocols compare the same images.
    assert result.unit(sensors[0].name, 0.0, "blocks", "enrol-0").eer.estimate == \
        result.unit(sensors[0].name, 0.0, "blocks", "same-age").eer.estimate


def test_a_realistic_sensor_shows_no_trend_and_an_extreme_one_a_rise(tmp_path):
    # Noise that makes the stand-in matcher err now and then at age 0 (EER of a few per cent).
    source = _write_set(tmp_path / "src", classes=30, samples=4, seed=1, noise=60.0)
    sensors = parse_sensors("A,H*2000", SHAPE, 8)
    result = run_impact(source, sensors, [0, 24, 48, 72, 96], [BlockMatcher()], rng=8, n_boot=300,
                        protocols=["same-age"])
    realistic = result.trend("A", "blocks", "same-age")
    # Sensor A gets ≈ 0.67 defects per megapixel per year: about 0.1 defect in 1,536 pixels over 96 years.
    assert not realistic.significant
    extreme = result.trend("H×2000", "blocks", "same-age")
    # H × 2000 makes most pixels defective by year 96.  The defects are the same in every image, a pattern
    # common to all classes, so impostor correlations rise (the block means dilute it: seeds 7–9 all give
    # slope intervals above zero, the lowest bound +0.07 points per decade).
    assert extreme.significant and extreme.slope > 0 and extreme.change > 0
    spread = next(s for s in result.spreads if s.age == 96.0)
    assert spread.n_sensors == 2 and spread.minimum <= spread.mean <= spread.maximum
    assert spread.mean_ci[0] <= spread.mean <= spread.mean_ci[1]


def test_an_interrupted_run_resumes_to_the_identical_result(tmp_path):
    source = _write_set(tmp_path / "src", classes=6, samples=3)
    sensors = parse_sensors("B,H*50", SHAPE, 8)
    ages = [0.0, 32.0, 64.0]
    whole = run_impact(source, sensors, ages, [BlockMatcher()], rng=11, n_boot=40)
    ckpt = tmp_path / "ckpt"
    # Two sensors × three ages × 18 images: die in the middle of the fourth (sensor, age).  Every task is
    # computed (no reuse of identical aged images: B and H×50 share their age 0) so that the count is exact.
    with pytest.raises(Interrupted):
        run_impact(source, sensors, ages, [FailingMatcher(3 * 18 + 5)], rng=11, n_boot=40, checkpoint=ckpt,
                   reuse=False)
    resumed = run_impact(source, sensors, ages, [BlockMatcher()], rng=11, n_boot=40, checkpoint=ckpt, reuse=False)
    assert resumed.resumed_units == 3 * 2  # three (sensor, age) units × two protocols
    assert _comparable(resumed) == _comparable(whole)
    # The execution layer's Checkpoint refuses a folder made with other settings (a usage error, exit 2).
    with pytest.raises(UsageError, match="other settings"):
        run_impact(source, sensors, ages, [BlockMatcher()], rng=12, n_boot=40, checkpoint=ckpt)


def test_impostor_sample_keeps_every_genuine_pair(tmp_path):
    source = _write_set(tmp_path / "src", classes=6, samples=3)
    result = run_impact(source, parse_sensors("A", SHAPE, 8), [0.0], [BlockMatcher()], rng=2, n_boot=20,
                        impostors=40, protocols=["same-age"])
    assert result.impostors_sampled and result.n_impostor == 40 and result.n_genuine == 6 * 3


def test_bad_input(tmp_path):
    source = _write_set(tmp_path / "src", subjects=False)
    with pytest.raises(InputError, match="subject"):
        run_impact(source, parse_sensors("A", SHAPE, 8), [0.0], [BlockMatcher()], rng=0, n_boot=10)
    good = _write_set(tmp_path / "good")
    with pytest.raises(UsageError, match="age 0"):
        run_impact(good, parse_sensors("A", SHAPE, 8), [8.0], [BlockMatcher()], rng=0, n_boot=10)
    with pytest.raises(UsageError, match="preset"):
        parse_sensors("Z", SHAPE, 8)
    with pytest.raises(InputError, match="bits"):
        run_impact(good, parse_sensors("A", SHAPE, 16), [0.0], [BlockMatcher()], rng=0, n_boot=10)


def test_a_generator_gives_the_result_of_its_integer_seed(tmp_path):
    # Tasks derive every stream from the run's seed sequence (never a generator's state), so rng=5 and
    # default_rng(5) age, sample and resample identically; only the seed record differs in form.
    source = _write_set(tmp_path / "src", classes=5, samples=3, noise=60.0)
    sensors = [parse_sensors("H*50", SHAPE, 8)[0]]
    sensors.append(type(sensors[0])("noisy", preset("B", SHAPE, bit_depth=8).with_effects(ReadNoise(sigma=6.0))))

    def everything(rng):
        result = run_impact(source, sensors, [0.0, 40.0], [BlockMatcher()], rng=rng, n_boot=30, impostors=50)
        out = _comparable(result)
        return (out.pop("seed"), out, [u.histogram for u in result.units],
                [u.eer.replicates.tolist() for u in result.units])

    generator = np.random.default_rng(5)
    generator.random(3)  # its state is never used
    by_int, by_gen = everything(5), everything(generator)
    assert by_int[0] == 5 and by_gen[0] != 5
    assert by_int[1:] == by_gen[1:]
    other = everything(6)
    assert other[2] != by_int[2] and other[3] != by_int[3]  # the frame noise and the resamples follow the seed


class WindowMatcher:
    """Pixels of a 12×12 window where the image is brightest (like an iris, at a place of each image's own):
    a defect changes the templates of the images whose window it falls in, and only those."""

    name = "window"
    higher_is_similar = True

    def encode(self, image: np.ndarray) -> np.ndarray:
        means = image.astype(np.float64).reshape(SHAPE[0] // 4, 4, SHAPE[1] // 4, 4).mean(axis=(1, 3))
        r, c = np.unravel_index(int(np.argmax(means)), means.shape)
        r, c = min(4 * r, SHAPE[0] - 12), min(4 * c, SHAPE[1] - 12)
        return image[r:r + 12, c:c + 12].astype(np.float64)

    def compare(self, a: np.ndarray, b: np.ndarray) -> float:
        return -float(np.abs(a - b).mean())


@pytest.mark.parametrize("impostors", [None, 60])
def test_scores_copied_from_identical_templates_give_the_result_of_computing_them(tmp_path, impostors):
    # All pairs (the banded upper triangle) and a sample of impostor pairs (pair by pair: no compare_all), both
    # protocols: the same result as computing every comparison, with scores copied across ages.  Low noise, so
    # that a class's images share their window and the EER (0.17–0.44 here) moves with the defects.
    source = _write_set(tmp_path / "src", classes=6, samples=3, noise=8.0)
    sensors = parse_sensors("H*50", SHAPE, 8)
    ages = [0.0, 16.0, 32.0, 48.0]
    runs = {reuse: run_impact(source, sensors, ages, [WindowMatcher()], rng=4, n_boot=40, impostors=impostors,
                              reuse=reuse) for reuse in (True, False)}
    assert _comparable(runs[True]) == _comparable(runs[False])
    for a, b in zip(runs[True].units, runs[False].units):
        assert np.array_equal(a.eer.replicates, b.eer.replicates, equal_nan=True) and a.histogram == b.histogram
    pairs = runs[False].computed_pairs // len(runs[False].units)
    fast = runs[True]
    assert fast.computed_pairs + fast.copied_pairs + pairs * fast.reused_units == runs[False].computed_pairs
    assert fast.copied_pairs > pairs          # more than the enrol-0 protocol's copy of the age-0 scores
    assert fast.computed_pairs > 2 * pairs    # and defects did change templates after age 0
    assert len({u.eer.estimate for u in fast.units}) >= 3
