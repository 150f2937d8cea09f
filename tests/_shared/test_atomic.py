"""Atomic output: modes that follow the umask, clean failures that name the file, nothing left beside."""
from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest

from forensics._shared.atomic import atomic_directory, atomic_file, current_umask, write_bytes, write_text
from forensics._shared.checkpoint import resumable_directory


@pytest.fixture(params=[0o022, 0o002], ids=["umask022", "umask002"])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _modes(root: Path) -> dict[str, int]:
    """Permission bits of ``root`` and of everything under it."""
    return {str(p.relative_to(root.parent)): p.stat().st_mode & 0o777 for p in [root, *sorted(root.rglob("*"))]}


def _assert_plain_modes(root: Path, umask: int) -> None:
    """Every folder under ``root`` has the mode ``mkdir()`` gives, every file the mode ``open()`` gives."""
    for name, mode in _modes(root).items():
        expected = (0o777 if (root.parent / name).is_dir() else 0o666) & ~umask
        assert mode == expected, f"{name}: {mode:o}, not {expected:o}"


def test_the_umask_is_read_without_changing_it(umask):
    assert current_umask() == umask
    assert current_umask() == umask


def test_files_and_folders_follow_the_umask(umask, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    write_text(out / "a.txt", "a")
    with atomic_file(out / "b.bin") as handle:
        handle.write(b"b")
    with atomic_directory(out / "report") as folder:
        (folder / "index.html").write_text("<p>")
    with pytest.raises(KeyboardInterrupt), resumable_directory(out / "aged", {"k": 1}) as (work, checkpoint):
        checkpoint.save("0000000", [1.0])
        raise KeyboardInterrupt  # the working folder and its checkpoint stay, to resume from
    assert (out / ".aged.partial" / ".items" / "item-0000000.npz").is_file()
    _assert_plain_modes(out, umask)
    with resumable_directory(out / "aged", {"k": 1}) as (work, checkpoint):
        (work / "result.txt").write_text("done")
    _assert_plain_modes(out, umask)


def test_aged_images_written_by_workers_follow_the_umask(umask, tmp_path):
    from forensics._shared.parallel import Executor
    from forensics.sensor.presets import preset
    from forensics.sensor.simulate import age_dataset, make_scenes

    source = make_scenes(tmp_path / "src", 3, (24, 32), rng=1)
    # The fork server may predate this umask (started by an earlier test): workers must take the driver's.
    with Executor("processes", workers=2) as ex:
        age_dataset(source, tmp_path / "aged", preset("H", (24, 32)), [0.0, 5.0], rng=2, executor=ex)
    _assert_plain_modes(tmp_path / "aged", umask)
    _assert_plain_modes(tmp_path / "src", umask)


def test_a_fingerprint_database_follows_the_umask(umask, tmp_path, cli):
    from forensics.prnu.fingerprint import build_fingerprint
    from forensics.sensor.simulate import make_scenes

    source = make_scenes(tmp_path / "src", 3, (24, 32), rng=1)
    build_fingerprint(source.frames, "full").save(tmp_path / "fp.npz")
    code, _, err = cli("fingerprint", "db", "add", tmp_path / "db", tmp_path / "fp.npz", "--device", "cam")
    assert code == 0, err
    _assert_plain_modes(tmp_path / "db", umask)
    assert (tmp_path / "fp.npz").stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_report_folder_replacing_a_file_leaves_nothing_beside(tmp_path):
    (tmp_path / "report").write_text("an earlier report, as one file")
    with atomic_directory(tmp_path / "report", force=True) as folder:
        (folder / "index.html").write_text("<p>")
    assert [p.name for p in tmp_path.iterdir()] == ["report"]
    assert (tmp_path / "report" / "index.html").is_file()


def test_a_file_output_onto_a_folder_is_refused_in_one_line(tmp_path, cli):
    from forensics.sensor.simulate import make_scenes

    make_scenes(tmp_path / "src", 3, (24, 32), rng=1)
    (tmp_path / "fp").mkdir()
    (tmp_path / "fp" / "keep.txt").write_text("not to be deleted")
    code, out, err = cli("fingerprint", "build", tmp_path / "src", "-o", tmp_path / "fp", "--force", "--workers", "1")
    assert code == 2
    assert err.strip().splitlines() == [f"forensics: error: {tmp_path / 'fp'}: is a folder, and the output is a file; "
                                        f"give a file name (e.g. {tmp_path / 'fp'}/NAME), or remove the folder first"]
    assert (tmp_path / "fp" / "keep.txt").read_text() == "not to be deleted"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fp", "src"]


def test_a_full_device_cleans_up_and_names_the_file(tmp_path):
    """A write that the device refuses (here EFBIG, a file-size limit: the kernel's own error, on the path a
    full disk's ENOSPC takes) removes the temporary file and raises an OSError naming the output."""
    code = f"""
import errno, resource, sys
from forensics._shared.atomic import write_bytes
resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))  # Python ignores SIGXFSZ: write() fails with EFBIG
try:
    write_bytes({str(tmp_path / "big.bin")!r}, bytes(1 << 20))
except OSError as exc:
    print(errno.errorcode[exc.errno], exc.filename)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["EFBIG", str(tmp_path / "big.bin")]
    assert list(tmp_path.iterdir()) == []  # no output, no temporary file


def test_device_errors_without_a_name_get_the_output_name(tmp_path):
    class Full:
        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as caught, atomic_file(tmp_path / "x.bin"):
        Full().write(b"x")
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(tmp_path / "x.bin")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError) as other, atomic_file(tmp_path / "y.bin"):
        raise FileNotFoundError(errno.ENOENT, "an input", "/some/input")
    assert other.value.filename == "/some/input"  # an error about another file keeps its name


def test_write_bytes_replaces_only_with_force(tmp_path):
    from forensics._shared.errors import UsageError

    write_bytes(tmp_path / "x", b"1")
    with pytest.raises(UsageError, match="already exists"):
        write_bytes(tmp_path / "x", b"2")
    write_bytes(tmp_path / "x", b"2", force=True)
    assert (tmp_path / "x").read_bytes() == b"2"
