"""Checkpoints: nothing stored can run code, changed inputs are noticed, one run at a time, work never lost.

The planted files would each create a marker file if unpickled (``os.system`` through ``__reduce__``); the
tests check that the marker never appears, and that the run still gives the right answer.
"""
from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from forensics._shared import safecodec
from forensics._shared.checkpoint import Checkpoint, resumable_directory
from forensics._shared.errors import UsageError
from forensics._shared.parallel import Executor
from forensics.fixtures import workitems

CONFIG = {"what": "test", "seed": 1}
ITEMS = [(i, -1) for i in range(6)]
EXPECTED = [i + 100 for i in range(6)]


class _Planted:
    """Unpickling this runs a shell command that creates ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _planted_files(folder: Path, marker: Path) -> None:
    """Every way of planting a pickle in a checkpoint folder that a loader might take for an item."""
    payload = pickle.dumps(_Planted(marker))
    (folder / "item-0000000.npz").write_bytes(payload)  # a pickle under the item's name
    (folder / "item-0000001.pkl").write_bytes(payload)  # under the name earlier versions used
    # A real .npz whose array member is a pickled object array, referenced by a valid structure.
    with open(folder / "item-0000002.npz", "wb") as handle:
        np.savez(handle, structure=np.frombuffer(b'{"format":1,"value":{"$array":0}}', np.uint8),
                 a0=np.array([_Planted(marker)], dtype=object), allow_pickle=True)
    # A .npy (not an archive) holding the pickled object array.
    with open(folder / "item-0000003.npz", "wb") as handle:
        np.save(handle, np.array([_Planted(marker)], dtype=object), allow_pickle=True)
    # A structure naming functions and classes outside what the codec rebuilds.
    for index, name in ((4, "os:system"), (5, "forensics.cli.main:main")):
        text = f'{{"format":1,"value":{{"$dataclass":"{name}","fields":{{}}}}}}'.encode()
        with open(folder / f"item-{index:07d}.npz", "wb") as handle:
            np.savez(handle, structure=np.frombuffer(text, np.uint8))


@pytest.mark.parametrize("backend", ["in-process", "processes"])
def test_planted_checkpoint_is_never_executed(tmp_path, backend):
    marker = tmp_path / "code-ran"
    folder = tmp_path / "ck"
    Checkpoint(folder, CONFIG)
    _planted_files(folder, marker)
    with pytest.warns(UserWarning) as caught, Executor(backend, workers=2) as ex:
        got = list(ex.map(workitems.fail_on, ITEMS, checkpoint=Checkpoint(folder, CONFIG)))
    assert got == EXPECTED  # every planted item computed again
    assert not marker.exists()
    text = " ".join(str(w.message) for w in caught)
    assert "item-0000001.pkl" in text and "computed again" in text
    assert {p.name for p in folder.glob("item-*.npz")} == {f"item-{i:07d}.npz" for i in range(6)}
    assert [safecodec.decode(folder / f"item-{i:07d}.npz") for i in range(6)] == EXPECTED  # replaced by results


def test_planted_pickle_is_not_executed_when_ageing_resumes(tmp_path):
    """The issue's case: a pickle planted in ``.OUT.partial/.items`` of an interrupted ``simulate age``."""
    from forensics.io.images import read_image
    from forensics.sensor.presets import preset
    from forensics.sensor.simulate import age_dataset, make_scenes

    source = make_scenes(tmp_path / "src", 3, (24, 32), rng=1)

    def age(out, **options):
        return age_dataset(source, out, preset("H", (24, 32)), [0.0, 5.0], rng=2, **options)

    with pytest.raises(KeyboardInterrupt):
        age(tmp_path / "aged", progress=_interrupt_after(1))
    marker = tmp_path / "code-ran"
    items = tmp_path / ".aged.partial" / ".items"
    for name in ("item-0000000.npz", "item-0000001.npz", "item-0000002.npz"):
        (items / name).write_bytes(pickle.dumps(_Planted(marker)))
    with pytest.warns(UserWarning, match="computed again"):
        age(tmp_path / "aged")
    assert not marker.exists()
    age(tmp_path / "fresh")
    for frame in source.frames:
        for step in ("year_000", "year_005"):
            assert np.array_equal(read_image(tmp_path / "aged" / step / frame.path.name),
                                  read_image(tmp_path / "fresh" / step / frame.path.name))


def _interrupt_after(n: int):
    def progress(iterable, total=None, desc=None):
        for count, item in enumerate(iterable):
            if count == n:
                raise KeyboardInterrupt
            yield item

    return progress


def test_an_item_that_does_not_decode_is_computed_again(tmp_path):
    folder = tmp_path / "ck"
    ex = Executor("in-process")
    blocks = [(7, i) for i in range(6)]
    expected = [workitems.noisy_block(b) for b in blocks]
    list(ex.map(workitems.noisy_block, blocks, checkpoint=Checkpoint(folder, CONFIG)))
    (folder / "item-0000001.npz").write_bytes(b"not an archive")
    (folder / "item-0000002.npz").write_bytes((folder / "item-0000002.npz").read_bytes()[:-30])  # truncated
    # Damaged inside an array's data: the cheap check (headers only) passes, reading it fails its CRC.
    path = folder / "item-0000003.npz"
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("a0.npy")
    start = data.index(b"\x93NUMPY", info.header_offset)  # the member's data (stored, not compressed)
    data[start + info.file_size - 1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match="computing it again|computed again") as caught:
        got = list(ex.map(workitems.noisy_block, blocks, checkpoint=Checkpoint(folder, CONFIG)))
    assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True))
    assert len(caught) == 3


@pytest.mark.skipif(not hasattr(os, "getuid") or os.getuid() != 0, reason="needs root to give a file away")
def test_items_of_another_user_are_not_trusted(tmp_path):
    folder = tmp_path / "ck"
    ck = Checkpoint(folder, CONFIG)
    ck.save("0000000", 999)  # a result no run of this function would give
    os.chown(folder / "item-0000000.npz", 4242, 4242)
    with pytest.warns(UserWarning, match="another user"):
        got = list(Executor("in-process").map(workitems.fail_on, ITEMS, checkpoint=Checkpoint(folder, CONFIG)))
    assert got == EXPECTED


def test_results_the_codec_cannot_store_are_returned_but_not_kept(tmp_path):
    folder = tmp_path / "ck"
    ex = Executor("in-process")
    with pytest.warns(UserWarning, match="not kept for resuming"):
        got = list(ex.map(workitems.echo, [{1, 2}, object], checkpoint=Checkpoint(folder, CONFIG)))
    assert got == [{1, 2}, object]
    assert [p.name for p in folder.glob("item-*")] == ["item-0000000.npz"]


def test_a_replaced_input_is_noticed(tmp_path):
    inputs = [tmp_path / "a.png", tmp_path / "b.png"]
    for path in inputs:
        path.write_bytes(path.name.encode())
    Checkpoint(tmp_path / "ck", CONFIG, inputs=inputs)
    Checkpoint(tmp_path / "ck", CONFIG, inputs=inputs)  # same contents: resumes
    os.utime(inputs[0], (0, 0))  # a new time alone changes nothing
    Checkpoint(tmp_path / "ck", CONFIG, inputs=inputs)
    inputs[1].write_bytes(b"another image")
    with pytest.raises(UsageError, match=r"b\.png has changed since"):
        Checkpoint(tmp_path / "ck", CONFIG, inputs=inputs)


def test_a_replaced_source_image_is_noticed_when_ageing_resumes(tmp_path):
    from forensics.io.dataset import open_dataset
    from forensics.io.images import read_image, write_image
    from forensics.sensor.presets import preset
    from forensics.sensor.simulate import age_dataset, make_scenes

    source = make_scenes(tmp_path / "src", 4, (24, 32), rng=1)
    model = preset("H", (24, 32))
    with pytest.raises(KeyboardInterrupt):
        age_dataset(source, tmp_path / "aged", model, [0.0, 5.0], rng=2, progress=_interrupt_after(2))
    frames = source.frames
    # Same name, size and type: only the content says it is another image.
    write_image(frames[3].path, read_image(frames[0].path), force=True)
    source = open_dataset(tmp_path / "src")
    with pytest.raises(UsageError, match=f"{frames[3].path.name} has changed since"):
        age_dataset(source, tmp_path / "aged", model, [0.0, 5.0], rng=2)
    assert (tmp_path / ".aged.partial" / ".items").is_dir()  # refused, not deleted
    age_dataset(source, tmp_path / "aged", model, [0.0, 5.0], rng=2, force=True)  # starts again
    age_dataset(source, tmp_path / "fresh", model, [0.0, 5.0], rng=2)
    for name in ("year_000", "year_005"):
        for frame in frames:
            a = read_image(tmp_path / "aged" / name / frame.path.name)
            assert np.array_equal(a, read_image(tmp_path / "fresh" / name / frame.path.name))


def test_a_refused_resume_keeps_the_interrupted_work(tmp_path):
    with pytest.raises(KeyboardInterrupt), resumable_directory(tmp_path / "out", CONFIG) as (work, ck):
        ck.save("0000000", 1)
        raise KeyboardInterrupt
    with pytest.raises(UsageError, match="other settings"):
        with resumable_directory(tmp_path / "out", {**CONFIG, "seed": 2}):
            pass
    with resumable_directory(tmp_path / "out", CONFIG) as (work, ck):
        assert ck.has("0000000") and ck.load("0000000") == 1


def test_a_second_run_into_the_same_output_is_refused(tmp_path):
    with resumable_directory(tmp_path / "out", CONFIG) as (work, ck):
        (work / "file").write_text("first run")
        with pytest.raises(UsageError, match="another run is writing"):
            with resumable_directory(tmp_path / "out", CONFIG, force=True):
                pass
        assert (work / "file").read_text() == "first run"
    assert (tmp_path / "out" / "file").read_text() == "first run"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["file"]  # no lock, no checkpoint left


def test_two_simulate_age_runs_into_one_output_one_is_refused(tmp_path):
    from forensics.sensor.simulate import make_scenes

    make_scenes(tmp_path / "src", 24, (192, 256), bit_depth=16, rng=2)
    command = [sys.executable, "-m", "forensics.cli.main", "simulate", "age", tmp_path / "src", tmp_path / "aged",
               "--sensor", "H", "--years", "0:100:10", "--seed", "3", "--workers", "2", "--quiet"]
    first = subprocess.Popen(list(map(str, command)), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        items = tmp_path / ".aged.partial" / ".items"
        while not any(items.glob("item-*.npz")) and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        # the first run is held while the second tries (on a loaded machine it could otherwise finish in between,
        # and the second would rightly find a finished output instead)
        os.killpg(first.pid, signal.SIGSTOP)
        try:
            assert first.poll() is None, first.stderr.read()
            second = subprocess.run(list(map(str, command)), capture_output=True, text=True)
        finally:
            os.killpg(first.pid, signal.SIGCONT)
        assert first.wait(timeout=120) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            os.killpg(first.pid, signal.SIGKILL)
    assert second.returncode == 2
    assert second.stderr.strip().splitlines() == [
        f"forensics: error: {tmp_path / '.aged.partial'}: another run is writing this output now; wait for it to "
        "finish, or choose another output"]
    assert len(list((tmp_path / "aged" / "year_100").glob("*.png"))) == 24
