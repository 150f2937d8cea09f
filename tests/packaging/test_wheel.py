"""The built wheel installs nothing but ``forensics`` at the top level, and works from there.

The wheel is built from the source tree (pip, isolated build: setuptools comes from the package
index like any other package), installed with ``--target`` into an empty folder, and run with that
folder first on ``sys.path``; the test checks that the code that runs is the installed copy, not
the editable checkout.
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
def installed(tmp_path_factory) -> Path:
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
    wheel = next(dist.glob("forensics-*.whl"))
    site = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
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
