"""Fixtures shared by the matcher tests: the same synthetic captures for every algorithm."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest


def _eye_renderer():
    """The synthetic eye of test_segment.py, loaded by path (works whatever pytest's import mode)."""
    spec = importlib.util.spec_from_file_location("_impact_eye", Path(__file__).with_name("test_segment.py"))
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
