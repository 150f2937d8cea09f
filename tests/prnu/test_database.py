"""The fingerprint database: round trip, metadata, replace and remove rules, atomicity, concurrent readers.

Fingerprints are small: 64×64 arrays made directly (K from a seeded generator, so a reader in
another process can regenerate what it must find), or built from three 64×64 PNG images that
carry EXIF make, model, body serial and capture dates.
"""
from __future__ import annotations

import datetime
import json
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.errors import InputError, UsageError
from forensics.io.dataset import decimal_year
from forensics.prnu.database import FINGERPRINTS, DeviceEntry, FingerprintDatabase
from forensics.prnu.fingerprint import Fingerprint

SHAPE = (64, 64)
API_FIELDS = ["device_id", "make", "model", "serial", "region", "width", "height", "n_images", "first_captured",
              "last_captured", "quality", "provenance", "file"]


def _k(index: int, version: int) -> np.ndarray:
    return np.random.default_rng([index, version]).standard_normal(SHAPE).astype(np.float32)


def make_fp(index: int = 0, version: int = 1, files: list[str] | None = None, **parameters) -> Fingerprint:
    """A fingerprint whose K and image count say which (index, version) it is."""
    return Fingerprint(K=_k(index, version), region="full", sigma=3.0, files=files or [], n_images=version,
                       frame_shape=SHAPE, parameters={"version": version, **parameters})


def _files(db: FingerprintDatabase) -> list[str]:
    return sorted(p.name for p in (db.folder / FINGERPRINTS).iterdir())


@pytest.fixture
def db(tmp_path) -> FingerprintDatabase:
    return FingerprintDatabase(tmp_path / "db", create=True)


@pytest.fixture(scope="module")
def exif_images(tmp_path_factory) -> list[Path]:
    """Three 64×64 PNG images of one camera, captured on 1, 2 and 3 March 2011 (EXIF)."""
    from forensics.io.images import write_image

    folder = tmp_path_factory.mktemp("exif")
    rng = np.random.default_rng(5)
    return [write_image(folder / f"img{i}.png", rng.integers(60, 200, SHAPE, dtype=np.uint8),
                        metadata={"Make": "ACME", "Model": "Cam 1", "Exif:BodySerialNumber": "SN42",
                                  "Exif:DateTimeOriginal": f"2011:03:0{i + 1} 12:00:00"})
            for i in range(3)]


# ----------------------------------------------------------------------------- round trip


def test_add_list_get_load_round_trip(db):
    fp = make_fp(3, 7)
    entry = db.add(fp, "cam B", make="ACME", model="X1", serial="007")
    assert isinstance(entry, DeviceEntry) and list(entry.to_dict()) == API_FIELDS
    assert (entry.device_id, entry.make, entry.model, entry.serial) == ("cam B", "ACME", "X1", "007")
    assert (entry.region, entry.width, entry.height, entry.n_images) == ("full", 64, 64, 7)
    assert entry.first_captured is None and entry.last_captured is None  # no source files to read dates from
    assert entry.quality == 7.0  # no saturated pixels: the effective number of images is the count
    assert entry.file.startswith(f"{FINGERPRINTS}/") and (db.folder / entry.file).is_file()
    db.add(make_fp(1, 2), "cam A")
    assert len(db) == 2 and [e.device_id for e in db.entries()] == ["cam A", "cam B"]  # sorted by id
    assert db.get("cam B") == entry
    back = db.load("cam B")
    assert back.K.dtype == np.float32 and np.array_equal(back.K, fp.K)  # bit-identical
    assert back.n_images == 7 and back.region == "full" and back.frame_shape == SHAPE
    again = FingerprintDatabase(db.folder)  # reopened, and create=True on an existing database just opens it
    assert again.entries() == db.entries() == FingerprintDatabase(db.folder, create=True).entries()
    assert json.loads(json.dumps(entry.to_dict())) == entry.to_dict()  # JSON-ready


def test_metadata_from_the_source_images_exif(db, exif_images):
    from forensics.prnu.fingerprint import build_fingerprint

    fp = build_fingerprint(exif_images)
    entry = db.add(fp)  # no id given: make, model and body serial of the images name the device
    assert entry.device_id == "ACME Cam 1 #SN42"
    assert (entry.make, entry.model, entry.serial) == ("ACME", "Cam 1", "SN42")
    assert entry.first_captured == pytest.approx(decimal_year(datetime.datetime(2011, 3, 1, 12)))
    assert entry.last_captured == pytest.approx(decimal_year(datetime.datetime(2011, 3, 3, 12)))
    assert entry.n_images == 3 and entry.quality == pytest.approx(3 * (1 - fp.parameters["excluded_pixel_fraction"]))
    assert entry.provenance["source_folder"] == str(exif_images[0].parent.resolve())
    assert entry.provenance["files"] == [str(p) for p in exif_images]
    # arguments win over EXIF (another fingerprint: one pattern cannot be two devices)
    other = db.add(build_fingerprint(exif_images[:2]), "mine", make="M", model="N", serial="S")
    assert (other.make, other.model, other.serial) == ("M", "N", "S")


def test_device_from_manifest_and_from_provenance(db, tmp_path):
    from forensics.io.dataset import write_manifest
    from forensics.io.images import write_image

    folder = tmp_path / "set"
    rng = np.random.default_rng(2)
    for i in range(2):
        write_image(folder / f"f{i}.png", rng.integers(0, 255, SHAPE, dtype=np.uint8))
    write_manifest(folder / "manifest.csv", [{"file": f"f{i}.png", "device": "lab cam", "captured": 2010.25 + i / 4}
                                             for i in range(2)])
    entry = db.add(make_fp(0, 1, files=[str(folder / "f0.png"), str(folder / "f1.png")]))
    assert entry.device_id == "lab cam" and entry.provenance["device_id_from"].startswith("source images")
    assert (entry.first_captured, entry.last_captured) == pytest.approx((2010.25, 2010.5))
    assert db.add(make_fp(1, 1, device="from provenance")).device_id == "from provenance"


def test_no_device_id_is_refused(db, tmp_path):
    with pytest.raises(UsageError, match="--device"):
        db.add(make_fp())
    with pytest.raises(UsageError, match="--device"):  # source files that no longer exist say nothing either
        db.add(make_fp(files=[str(tmp_path / "gone.png")]))
    with pytest.raises(UsageError, match="printable"):
        db.add(make_fp(), "  ")
    assert len(db) == 0 and _files(db) == []


def test_sources_naming_two_devices_are_refused(db, exif_images, tmp_path):
    from forensics.io.images import write_image

    other = write_image(tmp_path / "other.png", np.zeros(SHAPE, np.uint8),
                        metadata={"Make": "ACME", "Model": "Cam 1", "Exif:BodySerialNumber": "SN43"})
    with pytest.raises(UsageError, match="2 devices"):
        db.add(make_fp(files=[str(exif_images[0]), str(other)]))


# ----------------------------------------------------------------------------- replace and remove


def test_duplicate_refused_and_replace(db):
    first = db.add(make_fp(0, 1), "cam")
    with pytest.raises(UsageError, match="already in the database"):
        db.add(make_fp(0, 2), "cam")
    assert db.get("cam") == first and np.array_equal(db.load("cam").K, _k(0, 1))
    second = db.add(make_fp(0, 2), "cam", replace=True)
    assert second.file != first.file and _files(db) == [Path(second.file).name]  # the old file is gone
    assert len(db) == 1 and db.get("cam").n_images == 2 and np.array_equal(db.load("cam").K, _k(0, 2))


def test_add_many_is_all_or_nothing(db):
    db.add(make_fp(0), "a")
    before, files = db.entries(), _files(db)
    with pytest.raises(UsageError, match="already"):  # the second of three exists: none is added
        db.add_many([make_fp(1), make_fp(2), make_fp(3)], ["b", "a", "c"])
    with pytest.raises(UsageError, match="two fingerprints"):
        db.add_many([make_fp(1), make_fp(2)], ["b", "b"])
    assert db.entries() == before and _files(db) == files
    entries = db.add_many([make_fp(1), make_fp(2)], ["b", "c"])
    assert [e.device_id for e in entries] == ["b", "c"] and len(db) == 3


def test_remove(db):
    entry = db.add(make_fp(0), "a")
    db.add(make_fp(1), "b")
    db.remove("a")
    assert [e.device_id for e in db.entries()] == ["b"] and not (db.folder / entry.file).exists()
    with pytest.raises(UsageError, match="no device 'a'"):
        db.remove("a")
    with pytest.raises(UsageError, match="db list"):
        db.get("a")
    with pytest.raises(UsageError, match="no device"):
        db.load("a")


# ----------------------------------------------------------------------------- atomicity


def test_interrupted_rename_leaves_the_database_unchanged(db, monkeypatch):
    from forensics._shared import atomic

    db.add(make_fp(0, 1), "cam")
    before, files = db.entries(), _files(db)

    def boom(*args, **kwargs):
        raise OSError("disk pulled out during the rename")

    monkeypatch.setattr(atomic.os, "replace", boom)
    with pytest.raises(OSError, match="disk pulled"):
        db.add(make_fp(1, 1), "new")
    with pytest.raises(OSError, match="disk pulled"):
        db.add(make_fp(0, 2), "cam", replace=True)
    monkeypatch.undo()
    assert db.entries() == before and _files(db) == files  # no row, no file, no temporary
    assert np.array_equal(db.load("cam").K, _k(0, 1))


def test_failure_after_the_file_is_written_leaves_the_database_unchanged(db, monkeypatch):
    db.add(make_fp(0, 1), "cam")
    before, files = db.entries(), _files(db)

    def boom(*args, **kwargs):
        raise RuntimeError("killed before the commit")

    monkeypatch.setattr(FingerprintDatabase, "_insert", staticmethod(boom))
    for device, replace in (("new", False), ("cam", True)):
        with pytest.raises(RuntimeError, match="killed"):
            db.add(make_fp(1, 2), device, replace=replace)
    monkeypatch.undo()
    assert db.entries() == before and _files(db) == files
    assert np.array_equal(db.load("cam").K, _k(0, 1))


def test_a_dead_writers_leftovers_are_invisible_and_swept(db):
    db.add(make_fp(0), "cam")
    stray = db.folder / FINGERPRINTS / "orphan-0000.npz"
    make_fp(9).save(stray)  # renamed into place, but its row was never committed
    (db.folder / FINGERPRINTS / ".half.npz.x.part").write_bytes(b"half")
    assert [e.device_id for e in db.entries()] == ["cam"]
    db.add(make_fp(1), "next")  # the next writer cleans up under its lock
    assert _files(db) == sorted(Path(e.file).name for e in db.entries())


# ----------------------------------------------------------------------------- readable errors


def test_missing_damaged_and_foreign_folders(tmp_path):
    with pytest.raises(InputError, match=f"{tmp_path / 'none'}: no such fingerprint database"):
        FingerprintDatabase(tmp_path / "none")
    assert not (tmp_path / "none").exists()
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"x")
    with pytest.raises(InputError, match="photos: not a fingerprint database"):
        FingerprintDatabase(tmp_path / "photos")
    with pytest.raises(InputError, match="not empty"):
        FingerprintDatabase(tmp_path / "photos", create=True)
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "index.sqlite").write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(InputError, match="junk: index.sqlite is not the index of a fingerprint database"):
        FingerprintDatabase(junk)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    with sqlite3.connect(foreign / "index.sqlite") as con:
        con.execute("CREATE TABLE things (x)")
    with pytest.raises(InputError, match="foreign: index.sqlite is not the index"):
        FingerprintDatabase(foreign)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert len(FingerprintDatabase(empty, create=True)) == 0  # an empty folder becomes a database


def test_newer_schema_is_refused(db):
    with sqlite3.connect(db.index) as con:
        con.execute("UPDATE schema SET version = 99")
    con.close()
    with pytest.raises(InputError, match="upgrade forensics"):
        FingerprintDatabase(db.folder)


def test_missing_or_changed_fingerprint_file(db):
    entry = db.add(make_fp(0), "cam")
    path = db.folder / entry.file
    make_fp(5).save(path, force=True)  # changed behind the database's back
    with pytest.raises(InputError, match="does not match the database index"):
        db.load("cam")
    path.unlink()
    with pytest.raises(InputError, match=r"fingerprint file .* of device 'cam' is missing; remove the entry"):
        db.load("cam")


# ----------------------------------------------------------------------------- concurrent readers

READER = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import numpy as np
    from forensics.prnu.database import FingerprintDatabase

    folder, stop, ready = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    db = FingerprintDatabase(folder)
    ready.touch()
    states, errors, loads = [], [], 0
    while True:
        finished = stop.exists()
        try:
            entries = db.entries()
            for e in entries:
                # the row is whole: its provenance and its columns tell the same version
                if e.provenance["parameters"]["version"] != e.n_images:
                    errors.append(f"row {e.device_id} mixes versions")
                fp = db.load(e.device_id)
                version = fp.parameters["version"]
                want = np.random.default_rng([int(e.device_id[1:]), version]).standard_normal((64, 64))
                if fp.n_images != version or not np.array_equal(fp.K, want.astype(np.float32)):
                    errors.append(f"file of {e.device_id} is not a complete version")
                loads += 1
            states.append([e.device_id for e in entries])
        except Exception as exc:  # any error is a failure of the guarantee
            errors.append(repr(exc))
        if finished:
            break
    print(json.dumps({"states": states, "errors": errors, "loads": loads}))
""")


def test_a_reader_in_another_process_sees_whole_states_only(db, tmp_path):
    """While this process adds ten devices and then replaces five, a reader process lists and loads
    everything in a loop: every listing is a prefix of the additions (an old or a new state), and every
    fingerprint it loads is a complete version whose file matches its row."""
    db.add(make_fp(0, 1), "d00")
    stop, ready = tmp_path / "stop", tmp_path / "ready"
    reader = subprocess.Popen([sys.executable, "-c", READER, str(db.folder), str(stop), str(ready)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert reader.poll() is None, reader.communicate()[1][-2000:]
            assert time.monotonic() < deadline, "the reader did not start"
            time.sleep(0.01)
        for i in range(1, 10):
            db.add(make_fp(i, 1), f"d{i:02d}")
            time.sleep(0.02)  # let the reader interleave
        for i in range(5):
            db.add(make_fp(i, 2), f"d{i:02d}", replace=True)
            time.sleep(0.02)
        stop.touch()
        out, err = reader.communicate(timeout=60)
    finally:
        if reader.poll() is None:
            reader.kill()
    assert reader.returncode == 0, err[-2000:]
    result = json.loads(out)
    assert result["errors"] == []
    prefixes = [[f"d{i:02d}" for i in range(k)] for k in range(1, 11)]
    assert all(state in prefixes for state in result["states"])
    assert result["states"][-1] == prefixes[-1]
    assert len({len(s) for s in result["states"]}) >= 2, "the reader never overlapped the writer"
    assert result["loads"] >= 10


WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from forensics.prnu.database import FingerprintDatabase
    from forensics.prnu.fingerprint import Fingerprint

    db, name = FingerprintDatabase(sys.argv[1]), sys.argv[2]
    for i in range(6):
        k = np.random.default_rng([ord(name), i]).standard_normal((64, 64)).astype(np.float32)
        db.add(Fingerprint(k, "full", 3.0, [], 1, (64, 64)), f"{name}{i}")
""")


def test_two_writer_processes_are_served_one_at_a_time(db):
    """Writers queue on the index's write lock: both processes' additions all arrive, with their files."""
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, str(db.folder), name], stderr=subprocess.PIPE, text=True)
             for name in ("p", "q")]
    for proc in procs:
        assert proc.wait(timeout=120) == 0, proc.stderr.read()[-2000:]
    ids = [e.device_id for e in db.entries()]
    assert ids == [f"{name}{i}" for name in "pq" for i in range(6)]
    assert _files(db) == sorted(Path(e.file).name for e in db.entries())
    assert all(np.array_equal(db.load(d).K, np.random.default_rng([ord(d[0]), int(d[1:])]).standard_normal((64, 64))
                              .astype(np.float32)) for d in ids)


# ----------------------------------------------------------------------------- integrity (issue 26)


def _set_file(db: FingerprintDatabase, device_id: str, value: str) -> None:
    with sqlite3.connect(db.index) as con:
        con.execute("UPDATE devices SET file = ? WHERE device_id = ?", (value, device_id))
    con.close()


@pytest.mark.parametrize("planted", ["absolute", "parent", "link", "subfolder"])
def test_index_file_column_cannot_reach_outside_the_database(db, tmp_path, planted):
    """D03: a ``file`` naming a path outside the fingerprints folder (absolute, '..', a link to a victim,
    a nested folder) is a damaged index: remove, add --replace and load refuse, and nothing is deleted."""
    entry = db.add(make_fp(0), "camA")
    victim = tmp_path / "victim.npz"
    victim.write_bytes(b"precious")
    if planted == "absolute":
        _set_file(db, "camA", str(victim))
    elif planted == "parent":
        _set_file(db, "camA", "../victim.npz")
    elif planted == "link":
        (db.folder / FINGERPRINTS / "link.npz").symlink_to(victim)
        _set_file(db, "camA", f"{FINGERPRINTS}/link.npz")
    else:
        _set_file(db, "camA", f"{FINGERPRINTS}/sub/x.npz")
    before = sorted(p.name for p in (db.folder / FINGERPRINTS).iterdir())
    for action in (lambda: db.remove("camA"), lambda: db.add(make_fp(1), "camA", replace=True),
                   lambda: db.add(make_fp(2), "camB"), lambda: db.load("camA")):
        with pytest.raises(InputError, match="the index is damaged"):
            action()
    assert victim.read_bytes() == b"precious"
    assert sorted(p.name for p in (db.folder / FINGERPRINTS).iterdir()) == before  # the real file was not swept
    assert (db.folder / entry.file).is_file() and [e.device_id for e in db.entries()] == ["camA"]


def test_a_fingerprints_folder_that_is_a_link_is_refused(tmp_path):
    db = FingerprintDatabase(tmp_path / "db", create=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.npz").write_bytes(b"x")
    (db.folder / FINGERPRINTS).rmdir()
    (db.folder / FINGERPRINTS).symlink_to(elsewhere)
    with pytest.raises(InputError, match="is a symbolic link"):
        FingerprintDatabase(db.folder)
    assert (elsewhere / "keep.npz").read_bytes() == b"x"


def _edit_metadata(path: Path, **changes) -> None:
    """Rewrite a fingerprint file's metadata in place (as an editor of the .npz would)."""
    with np.load(path) as data:
        k, meta = data["K"], json.loads(str(data["meta"][()]))
    meta.update(changes)
    with open(path, "wb") as handle:
        np.savez(handle, K=k, meta=np.array(json.dumps(meta)))


@pytest.mark.parametrize("change", [{"n_images": 99}, {"sigma": 5.0}, {"files": ["x.png"]},
                                    {"parameters": {"version": 7}}])
def test_checksum_covers_the_metadata_not_only_k(db, change):
    """D10: editing any metadata of a stored fingerprint is reported on load, naming the entry, even when K
    and the index's columns are unchanged (the frame shape, which changes identify's decisions: below)."""
    entry = db.add(make_fp(0), "camA")
    assert {"k_sha256", "fingerprint_sha256"} <= set(entry.provenance)
    _edit_metadata(db.folder / entry.file, **change)
    with pytest.raises(InputError, match=r"fingerprint of device 'camA' does not match the database index \(its "
                                         r"pattern or its metadata changed"):
        db.load("camA")


def test_checksum_mismatch_on_an_edited_frame_shape(db):
    """D10 as reported: frame_shape edited (the file still self-consistent) changes what identify would search."""
    k = np.random.default_rng(3).standard_normal((64, 64)).astype(np.float32)
    entry = db.add(Fingerprint(k, "center:64", 3.0, [], 5, (64, 64)), "camA")
    _edit_metadata(db.folder / entry.file, frame_shape=[64, 96])  # a centre crop of a wider frame: crops searched
    with pytest.raises(InputError, match=r"'camA' does not match the database index \(frame 96×64"):
        db.load("camA")


def test_entries_of_earlier_versions_stay_readable_and_checked_on_k(db):
    """Entries written before the full checksum (k_sha256 only) load, and a changed K is still reported."""
    entry = db.add(make_fp(0), "old")
    with sqlite3.connect(db.index) as con:
        prov = json.loads(con.execute("SELECT provenance FROM devices").fetchone()[0])
        del prov["fingerprint_sha256"]
        con.execute("UPDATE devices SET provenance = ?", (json.dumps(prov),))
    con.close()
    assert np.array_equal(db.load("old").K, make_fp(0).K)
    make_fp(5).save(db.folder / entry.file, force=True)
    with pytest.raises(InputError, match=r"its pattern changed \(checksum of K\)"):
        db.load("old")


def test_a_fingerprint_identical_to_another_device_is_refused(db, tmp_path):
    """D16: the same K under a second id (one file added twice, or a copy) is refused; under its own id with
    --replace it is allowed."""
    db.add(make_fp(0), "camA")
    with pytest.raises(UsageError, match="identical to the fingerprint of device 'camA'"):
        db.add(make_fp(0), "camB")
    path = make_fp(0).save(tmp_path / "copy.npz")
    with pytest.raises(UsageError, match="copy.npz: identical"):
        db.add_many([path], ["camC"])
    with pytest.raises(UsageError, match="identical"):  # twice in one addition
        db.add_many([make_fp(1), make_fp(1)], ["x", "y"])
    assert [e.device_id for e in db.entries()] == ["camA"]
    db.add(make_fp(0), "camA", replace=True)


@pytest.mark.parametrize("bad", ["nan", "inf", "constant"])
def test_a_fingerprint_without_a_usable_pattern_is_never_stored(db, tmp_path, bad):
    """D20: an all-NaN (or any non-finite) or constant K is refused by add, from memory or from a file."""
    k = make_fp(0).K.copy()
    if bad == "nan":
        k[:] = np.nan
    elif bad == "inf":
        k[3, 4] = np.inf
    else:
        k[:] = 0.5
    fp = Fingerprint(k, "full", 3.0, [], 4, SHAPE)
    with pytest.raises(InputError, match="NaN or infinite|constant"):
        db.add(fp, "camA")
    fp.save(tmp_path / "bad.npz")
    with pytest.raises(InputError, match="bad.npz: K (holds|is constant)"):
        db.add_many([tmp_path / "bad.npz"], ["camA"])
    assert len(db) == 0 and _files(db) == []


def test_lookups_and_removal_strip_the_device_id(db):
    """D21: ids are stored stripped, so ' camA ' finds and removes 'camA'."""
    db.add(make_fp(0), " camA ")
    assert [e.device_id for e in db.entries()] == ["camA"]
    assert db.get(" camA ").device_id == "camA" and " camA " in db
    db.remove(" camA ")
    assert len(db) == 0 and _files(db) == []
