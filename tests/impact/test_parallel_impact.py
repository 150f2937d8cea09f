"""The recognition experiment on the execution layer: the same EERs, trends and spreads on every backend, resumable.

A tiny but non-trivial run: 6 synthetic eyes × 2 images with strong acquisition variation (so that the EERs are
not all zero), two sensors — B with read noise (every aged frame draws its own keyed noise) and H × 2000 (whose
defects ruin the images by year 96) — ages 0 and 96, Masek and Ko, both protocols.  Every task's randomness comes from keyed streams, results come back in task order and the
class bootstrap runs on the same arrays wherever the task runs, so the results are compared for equality —
estimates, intervals, every bootstrap replicate, histograms, trends and spreads — not to a tolerance.
"""
from __future__ import annotations

import os
import textwrap

import numpy as np
import pytest

from forensics._shared.errors import UsageError
from forensics._shared.parallel import Executor
from forensics.impact.experiment import SensorSpec, parse_sensors, run_impact
from forensics.impact.irises import IrisVariation, simulate_irises
from forensics.impact.matchers import MasekMatcher, load_matcher, load_matchers
from forensics.io.dataset import open_dataset
from forensics.sensor.effects import ReadNoise
from forensics.sensor.presets import preset

AGES, SEED, N_BOOT = [0.0, 96.0], 3, 200
# Rotations beyond Masek's shift range and frequent poor acquisitions: some genuine pairs look like impostors.
HARD = IrisVariation(rotation_std_deg=15, rotation_max_deg=40, poor_probability=0.5, poor_factor=4.0)


@pytest.fixture(scope="module")
def irises(tmp_path_factory):
    root = tmp_path_factory.mktemp("impact") / "irises"
    simulate_irises(root, 6, 2, rng=5, variation=HARD)
    return open_dataset(root)


def _sensors(source) -> list[SensorSpec]:
    shape = source.shape()[:2]
    noisy = SensorSpec("B+noise", preset("B", shape, bit_depth=8).with_effects(ReadNoise(sigma=4.0)))
    return [noisy, *parse_sensors("H*2000", shape, 8)]


def _run(source, executor=None, matchers=None, seed=SEED, **options):
    return run_impact(source, _sensors(source), AGES, matchers or load_matchers(["masek", "ko"]), rng=seed,
                      n_boot=N_BOOT, executor=executor, **options)


@pytest.fixture(scope="module")
def reference(irises):
    return _run(irises, Executor("in-process"))


def assert_identical(a, b) -> None:
    """Every number of two results equal, bootstrap replicates and histograms included."""
    da, db = a.to_dict(), b.to_dict()
    for d in (da, db):
        d.pop("elapsed_s")
        d.pop("resumed_units")
        d.pop("reused_units")
        d.pop("computed_pairs")
        d.pop("copied_pairs")
        d.pop("reused_templates")
        d.pop("reused_steps")
    assert da == db
    assert len(a.units) == len(b.units)
    for ua, ub in zip(a.units, b.units):
        assert np.array_equal(ua.eer.replicates, ub.eer.replicates, equal_nan=True)
        assert ua.histogram == ub.histogram


def test_the_reference_run_is_not_trivial(reference):
    # Guards the comparisons below: EERs that differ between sensors, ages and matchers, none degenerate.
    eers = {u.eer.estimate for u in reference.units}
    assert len(eers) >= 3 and max(eers) > 0
    assert reference.trend("H×2000", "masek", "same-age").change > 0
    assert len(reference.units) == 2 * 2 * 2 * 2  # sensors × ages × matchers × protocols


def test_local_processes_give_the_in_process_result(irises, reference):
    with Executor("processes", workers=2) as ex:
        parallel = _run(irises, ex)
    assert_identical(parallel, reference)


def test_dask_cluster_gives_the_in_process_result(irises, reference, dask_cluster):
    with Executor("dask", scheduler=dask_cluster.scheduler_address) as ex:
        distributed = _run(irises, ex)
    assert_identical(distributed, reference)


class Interrupted(Exception):
    pass


class DyingMasek(MasekMatcher):
    """Masek's matcher that stops the run after ``budget`` encodes, as a killed process would."""

    def __init__(self, budget: int, segmenter=None) -> None:
        super().__init__(segmenter)
        self.budget = budget

    def encode(self, image):
        self.budget -= 1
        if self.budget < 0:
            raise Interrupted
        return super().encode(image)


def test_a_run_interrupted_in_process_resumes_on_workers_to_the_identical_result(irises, reference, tmp_path):
    ckpt = tmp_path / "ckpt"
    masek = DyingMasek(2 * 12 + 5)  # two whole (sensor, age) tasks of 12 images, then die inside the third
    with pytest.raises(Interrupted):
        _run(irises, Executor("in-process"), [masek, load_matcher("ko", masek.segmenter)], checkpoint=ckpt)
    assert sorted(p.name for p in ckpt.glob("item-*.npz")) == ["item-sensor00-age000.npz", "item-sensor01-age000.npz"]
    with Executor("processes", workers=2) as ex:
        resumed = _run(irises, ex, checkpoint=ckpt)
    assert resumed.resumed_units == 2 * 2 * 2  # two tasks × two matchers × two protocols
    assert_identical(resumed, reference)
    assert len(list(ckpt.glob("item-*.npz"))) == 4
    with pytest.raises(UsageError, match="other settings"):
        _run(irises, seed=SEED + 1, checkpoint=ckpt)


USER_MATCHER = textwrap.dedent('''
    import os
    import numpy as np


    class Thumbnail:
        """Correlation of 16×16 block means; notes which process encoded each image."""

        name = "thumbnail"
        higher_is_similar = True
        log = {log!r}

        def encode(self, image):
            with open(self.log, "a") as fh:
                fh.write(f"{{os.getpid()}}\\n")
            h, w = image.shape[0] // 16 * 16, image.shape[1] // 16 * 16
            blocks = np.asarray(image[:h, :w], float).reshape(h // 16, 16, w // 16, 16).mean(axis=(1, 3)).ravel()
            blocks -= blocks.mean()
            return blocks / (np.linalg.norm(blocks) or 1.0)

        def compare(self, a, b):
            return float(a @ b)
''')


def test_a_matcher_from_a_users_file_runs_on_worker_processes(irises, tmp_path):
    log = tmp_path / "pids.txt"
    (tmp_path / "thumb.py").write_text(USER_MATCHER.format(log=str(log)))
    matcher = load_matcher(f"{tmp_path / 'thumb.py'}:Thumbnail")
    alone = _run(irises, Executor("in-process"), [matcher])
    log.unlink()
    with Executor("processes", workers=2) as ex:
        parallel = _run(irises, ex, [matcher])
    assert_identical(parallel, alone)
    pids = set(log.read_text().split())
    assert pids and str(os.getpid()) not in pids  # encoded in the workers, not here


class Unpicklable:
    """A matcher holding a lambda: it cannot leave this process."""

    name = "unpicklable"
    higher_is_similar = True

    def __init__(self) -> None:
        self.reduce = lambda image: np.asarray(image, float)[::24, ::24].ravel()

    def encode(self, image):
        v = self.reduce(image)
        v = v - v.mean()
        return v / (np.linalg.norm(v) or 1.0)

    def compare(self, a, b):
        return float(a @ b)


def test_a_matcher_that_cannot_be_pickled_runs_in_process_with_a_warning(irises):
    alone = _run(irises, Executor("in-process"), [Unpicklable()])
    with Executor("processes", workers=2) as ex, pytest.warns(RuntimeWarning, match="unpicklable.*cannot be sent"):
        fallback = _run(irises, ex, [Unpicklable()])
    assert_identical(fallback, alone)


class CountingMasek(MasekMatcher):
    """Masek's matcher that counts its encodes."""

    def __init__(self, segmenter=None) -> None:
        super().__init__(segmenter)
        self.encodes = 0

    def encode(self, image):
        self.encodes += 1
        return super().encode(image)


REUSE_AGES = [0.0, 8.0, 16.0]


def _reuse_sensors(source) -> list[SensorSpec]:
    # A and D add no frame noise: at age 0 both record the source image, and A's defects of year 8 are still all
    # it has at year 16 (3 distinct image sets in 13 ages on this set).  B+noise draws new noise every frame, so
    # nothing of it can be reused.
    return [*parse_sensors("A,D", source.shape()[:2], 8), _sensors(source)[0]]


@pytest.fixture(scope="module")
def recomputed(irises):
    """The reuse tests' run with every (sensor, age) and every comparison computed, and its encode count."""
    masek = CountingMasek()
    result = run_impact(irises, _reuse_sensors(irises), REUSE_AGES, [masek, load_matcher("ko", masek.segmenter)],
                        rng=SEED, n_boot=N_BOOT, reuse=False)
    return result, masek.encodes


def test_reusing_identical_aged_images_gives_the_identical_result(irises, recomputed):
    # Both protocols: enrol-0 reuse must also match the enrolment images.
    masek = CountingMasek()
    fast = run_impact(irises, _reuse_sensors(irises), REUSE_AGES, [masek, load_matcher("ko", masek.segmenter)],
                      rng=SEED, n_boot=N_BOOT, reuse=True)
    fast_encodes = masek.encodes
    slow, slow_encodes = recomputed
    n = len(irises)
    assert slow_encodes == 3 * 3 * n and slow.reused_units == 0
    # The digests find at least D's age 0 (= A's) and A's year 16 (= its year 8); B+noise is computed in full.
    assert fast_encodes <= slow_encodes - 2 * n and fast.reused_units >= 2 * 2 * 2
    assert fast_encodes >= 3 * n + 2   # B+noise's 3 ages, plus at least A's first image set and its defects
    assert_identical(fast, slow)


def test_reusing_the_scores_of_identical_templates_on_workers_gives_the_identical_result(irises, recomputed):
    # The chains (one work item per sensor, its ages in order) on two worker processes, against every comparison
    # computed in this process.  A defect lands in the sampled iris of only some images, so the later ages of A
    # and D copy most of their scores from the age before; B+noise changes every template at every age.
    with Executor("processes", workers=2) as ex:
        fast = run_impact(irises, _reuse_sensors(irises), REUSE_AGES, load_matchers(["masek", "ko"]), rng=SEED,
                          n_boot=N_BOOT, executor=ex)
    slow, _ = recomputed
    assert_identical(fast, slow)
    pairs = len(irises) * (len(irises) - 1) // 2
    per_unit = pairs                         # every comparison of a unit: the pairs i < j
    assert slow.copied_pairs == 0 and slow.computed_pairs == per_unit * len(slow.units)
    # Every unit's comparisons were computed, copied, or came with a whole (sensor, age) of identical images.
    assert fast.computed_pairs + fast.copied_pairs + per_unit * fast.reused_units == slow.computed_pairs
    # Beyond the enrol-0 protocol at age 0 (its gallery is the same-age one: all copied, in the two age-0 tasks
    # computed, A's and B+noise's), scores were copied across ages: A's and D's defects.
    age0_copies = 2 * 2 * pairs
    assert fast.copied_pairs > age0_copies
    assert fast.computed_pairs < slow.computed_pairs - per_unit * fast.reused_units