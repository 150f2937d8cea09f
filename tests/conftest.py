"""Shared test helpers.

One conftest only: a second ``conftest.py`` in a sub-folder is imported under the same module name, and
``from conftest import ...`` in a test then finds whichever was imported first (CI failed that way)."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def cli(capsys):
    """Run the ``forensics`` command in-process; returns (exit code, stdout, stderr)."""
    from forensics.cli.main import main

    def run(*argv: str) -> tuple[int, str, str]:
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse usage errors
            code = int(exc.code or 0)
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture
def cli_json(cli):
    """Run a command with --json and parse stdout; fails the test on a non-zero exit."""

    def run(*argv: str) -> dict:
        code, out, err = cli(*argv, "--json")
        assert code == 0, err
        return json.loads(out)

    return run


def dresden_or_skip() -> Path:
    path = SHARED_DATA / "dresden-nikon"
    if not path.is_dir():
        pytest.skip(f"real-camera data not found at {path} (present in CI; absent on a fresh machine)")
    return path


def shared_or_skip(name: str) -> Path:
    """A file or folder of ``../shared/data`` (real data whose terms forbid copies in the repository), or skip."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"real data not found at {path} (present in CI; absent on a fresh machine)")
    return path


@pytest.fixture(scope="module")
def dask_cluster():
    """A ``dask.distributed.LocalCluster`` with two single-threaded worker processes, one per test module.

    Not per session: a cluster's scheduler runs in the test process's event loop and its workers keep
    heart-beating, which slowed every later test of that process (the suite took 8.8 min instead of 5.5)."""
    pytest.importorskip("distributed", reason="dask[distributed] is a test dependency")
    from forensics._shared.parallel import start_local_cluster

    cluster = start_local_cluster(2)
    try:
        yield cluster
    finally:
        cluster.close()


# The synthetic captures every matcher test of tests/impact encodes.


def _eye_renderer():
    """The synthetic eye of test_segment.py, loaded by path (works whatever pytest's import mode)."""
    spec = importlib.util.spec_from_file_location("_impact_eye", Path(__file__).with_name("impact") / "test_segment.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.render_eye


STEP = 2 * np.pi / 240          # one angular sample of Masek's 240-column texture


@pytest.fixture(scope="module")
def captures():
    """Five eyes, two captures each: other noise, a 3-sample (4.5°) rotation and a 1-px move in between."""
    render_eye = _eye_renderer()
    out = {}
    for eye in range(5):
        for cap in range(2):
            out[eye, cap] = render_eye(texture_seed=100 + eye, noise_seed=10 * eye + cap, rotation=3 * STEP * cap,
                                       pupil=(158.0 + cap, 122.0 - cap, 38.0 + cap), iris=(160.0 + cap, 120.0, 100.0))
    return out
