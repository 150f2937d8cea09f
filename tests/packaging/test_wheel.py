"""The built wheel installs nothing but ``forensics`` at the top level, and works from there — from any folder.

The wheel is built from a copy of the source tree (pip, isolated build: setuptools comes from the package
index like any other package) and installed twice: with ``--target`` into an empty folder (run with that
folder first on ``sys.path``; the test checks that the code that runs is the installed copy, not the
editable checkout), and into a fresh virtual environment as a user's ``pip install .`` would, whose console
script then runs parallel commands from inside the copy of the checkout — where the checkout's own
``forensics/`` folder (without ``cli``) is the current folder.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, Path]:
    """``(copy of the checkout, wheel built from it)``."""
    work = tmp_path_factory.mktemp("wheel")
    src = work / "src"
    # A copy without build/ or egg-info leftovers, so the wheel reflects pyproject.toml alone.
    skip_top = {".venv", "build", ".git", "report", "benchmarks", ".pytest_cache", ".hypothesis"}

    def ignore(folder: str, names: list[str]) -> set[str]:
        top = Path(folder) == ROOT
        return {n for n in names if n == "__pycache__" or n.endswith(".egg-info") or (top and n in skip_top)}

    shutil.copytree(ROOT, src, ignore=ignore)
    dist = work / "dist"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(dist)],
                           capture_output=True, text=True)
    if build.returncode != 0:
        pytest.fail(f"building the wheel failed:\n{build.stderr[-2000:]}")
    return src, next(dist.glob("forensics-*.whl"))


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    site = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel[1])],
                   check=True, capture_output=True)
    return site


def _run(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(site))
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=cwd)


def test_only_forensics_at_the_top_level(installed):
    top = {p.name for p in installed.iterdir() if p.name not in ("bin", "__pycache__")}
    assert {t for t in top if not t.endswith(".dist-info")} == {"forensics"}
    assert [t for t in top if t.endswith(".dist-info")] == [next(t for t in top if t.startswith("forensics-"))]
    for sub in ("cli", "fixtures", "check", "sensor", "_shared"):
        assert (installed / "forensics" / sub / "__init__.py").exists()


def test_installed_copy_runs(installed, tmp_path):
    probe = _run(installed, "-c", "import forensics.check, forensics.cli.main, forensics.fixtures.hidden as h; "
                                  "print(forensics.check.__file__); print(h.__file__)", cwd=tmp_path)
    assert probe.returncode == 0, probe.stderr
    for line in probe.stdout.split():
        assert Path(line).is_relative_to(installed), line
    helped = _run(installed, "-m", "forensics.cli.main", "--help", cwd=tmp_path)
    assert helped.returncode == 0 and "demo" in helped.stdout
    demo = _run(installed, "-m", "forensics.cli.main", "demo", "--only", "ageing", "--out", str(tmp_path / "r"),
                "--quiet", cwd=tmp_path)
    assert demo.returncode == 0, demo.stderr[-2000:]
    assert (tmp_path / "r" / "index.html").exists()


def test_no_top_level_cli_or_fixtures_in_the_wheel(installed):
    record = next(installed.glob("forensics-*.dist-info")) / "RECORD"
    tops = {line.split("/")[0].split(",")[0] for line in record.read_text().splitlines()}
    assert not {"cli", "fixtures", "tests", "benchmarks"} & tops


@pytest.fixture(scope="module")
def user_venv(wheel, tmp_path_factory) -> Path:
    """A fresh virtual environment with the wheel installed (not editable) — its ``bin`` folder.

    Its dependencies come from this test environment's site-packages, listed in a ``.pth`` file (a plain
    path line: appended to ``sys.path`` after the venv's own site-packages, its ``.pth`` files not run), so
    nothing is downloaded and the installed ``forensics`` is the only one the venv can import.
    """
    import sysconfig
    import venv

    root = tmp_path_factory.mktemp("venv") / "env"
    venv.create(root, with_pip=False)
    python = root / "bin" / "python"
    site = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    Path(site, "test-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
                              str(wheel[1])], capture_output=True, text=True)
    assert install.returncode == 0, install.stderr[-2000:]
    return root / "bin"


def _forensics(bin_dir: Path, *args: str | Path, cwd: Path) -> subprocess.CompletedProcess:
    """The venv's console script, in ``cwd``, with none of this test process's Python path settings."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSAFEPATH", "PYTHONHOME")}
    return subprocess.run([str(bin_dir / "forensics"), *map(str, args)], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=300)


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_parallel_command_runs_from_inside_the_checkout(wheel, user_venv, tmp_path):
    checkout = wheel[0]
    assert (checkout / "forensics").is_dir() and not (checkout / "forensics" / "cli").exists()  # the shadow
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    probe = subprocess.run([str(user_venv / "python"), "-c", "import forensics; print(forensics.__file__)"],
                           capture_output=True, text=True, cwd=elsewhere)
    assert Path(probe.stdout.strip()).is_relative_to(user_venv.parent), probe  # the installed copy, not editable
    # Ten images: two chunks of a fingerprint build (8 a chunk), so both commands really use two workers.
    scenes = _forensics(user_venv, "simulate", "scenes", tmp_path / "src", "--count", "10", "--size", "48x32",
                        "--bits", "16", "--seed", "1", "--quiet", cwd=elsewhere)
    assert scenes.returncode == 0, scenes.stderr[-2000:]
    outputs = {}
    for name, cwd in (("inside", checkout), ("outside", elsewhere)):
        aged = _forensics(user_venv, "simulate", "age", tmp_path / "src", tmp_path / f"aged-{name}", "--sensor", "H",
                          "--years", "0,10", "--seed", "5", "--workers", "2", "--json", cwd=cwd)
        assert aged.returncode == 0, aged.stderr[-2000:]
        assert '"backend": "processes"' in aged.stdout
        built = _forensics(user_venv, "fingerprint", "build", tmp_path / "src", "-o", tmp_path / f"fp-{name}.npz",
                           "--workers", "2", "--json", cwd=cwd)
        assert built.returncode == 0, built.stderr[-2000:]
        assert '"backend": "processes"' in built.stdout
        outputs[name] = (_tree(tmp_path / f"aged-{name}"), (tmp_path / f"fp-{name}.npz").read_bytes())
    inside, outside = outputs["inside"], outputs["outside"]
    assert inside[0].keys() == outside[0].keys() and len(inside[0]) == 2 * 11 + 2  # 2 ages × (10 + manifest) + 2
    assert all(inside[0][k] == outside[0][k] for k in inside[0]), "aged images differ with the working folder"
    assert inside[1] == outside[1], "the fingerprint differs with the working folder"
    pytest.importorskip("distributed")
    # A local Dask cluster's workers (spawned, not forked from the server) from inside the checkout too.
    dask = _forensics(user_venv, "simulate", "age", tmp_path / "src", tmp_path / "aged-dask", "--sensor", "H", "--years",
                      "0,10", "--seed", "5", "--scheduler", "local", "--workers", "2", "--json", cwd=checkout)
    assert dask.returncode == 0, dask.stderr[-2000:]
    assert '"backend": "dask"' in dask.stdout
    assert _tree(tmp_path / "aged-dask") == outside[0]
