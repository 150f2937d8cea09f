"""The one determinism convention: ``rng`` is a Generator or an integer seed, children come from spawn."""
import numpy as np
import pytest

from forensics._shared.rng import as_generator, keyed_generator, seed_record, spawn


def test_int_seed_equals_default_rng():
    assert np.array_equal(as_generator(7).random(5), np.random.default_rng(7).random(5))
    g = np.random.default_rng(3)
    assert as_generator(g) is g


@pytest.mark.parametrize("bad", [None, 1.5, "7", True, -1, np.random.RandomState(0)])
def test_refuses_anything_else(bad):
    with pytest.raises(TypeError):
        as_generator(bad)


def test_spawn_depends_on_seed_and_index_only():
    a = [g.random(3) for g in spawn(11, 4)]
    b = [g.random(3) for g in spawn(np.random.default_rng(11), 4)]
    c = [g.random(3) for g in spawn(11, 6)][:4]  # more children leave the first ones unchanged
    for x, y, z in zip(a, b, c):
        assert np.array_equal(x, y) and np.array_equal(x, z)
    assert not np.array_equal(a[0], a[1])


def test_seed_record_repeats_the_run():
    assert seed_record(5) == 5
    child = spawn(5, 3)[2]
    rec = seed_record(child)
    seq = np.random.SeedSequence(rec["entropy"], spawn_key=tuple(rec["spawn_key"]))
    assert np.array_equal(np.random.default_rng(seq).random(4), spawn(5, 3)[2].random(4))


def test_keyed_generator_int_and_generator_agree():
    from forensics._shared.rng import spawn

    a = keyed_generator(7, 2, 3).random(4)
    np.testing.assert_array_equal(a, np.random.default_rng([7, 2, 3]).random(4))
    g = np.random.default_rng(7)
    np.testing.assert_array_equal(keyed_generator(g, 2, 3).random(4), a)
    assert g.random() == np.random.default_rng(7).random()  # the generator's own state is not advanced
    c0, c1 = spawn(7, 2)
    assert keyed_generator(c0, 1).random() != keyed_generator(c1, 1).random() != keyed_generator(7, 1).random()
