"""The checkpoint codec: exact round trips of what work items return; nothing else rebuilt, nothing run."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from forensics._shared.safecodec import Undecodable, Unencodable, decode, encode
from forensics.stats.clustered import ClassBootstrap


@dataclasses.dataclass
class _NotOurs:
    x: int


def test_results_round_trip_exactly():
    rng = np.random.default_rng(0)
    value = {
        "ints": [0, -1, 2**70], "floats": (0.1, -0.0, 1e-310, math.inf, -math.inf), "complex": 1 - 2j,
        3: None, (1, "a"): {True, False}, "frozen": frozenset({1.5}), "bytes": b"\x00\xff", "path": Path("/x/y"),
        "f64": rng.normal(size=(5, 3)), "fortran": np.asfortranarray(rng.normal(size=(4, 6)).astype(np.float32)),
        "u16": rng.integers(0, 65535, (3, 4), dtype=np.uint16), "empty": np.zeros((0, 3)),
        "scalars": [np.float32(0.1), np.int64(-5), np.bool_(True)], "dtype": np.dtype(">u2"),
        "structured": np.dtype([("a", "<f4"), ("b", "<i2", (2,))]),
        "dataclass": ClassBootstrap(0.1, (0.05, 0.2), 0.95, rng.random(7), 10, 90, 0.001),
    }
    back = decode(encode(value))
    assert back.keys() == value.keys()
    for key in ("ints", "complex", 3, (1, "a"), "frozen", "bytes", "path", "scalars", "dtype", "structured"):
        assert back[key] == value[key] and type(back[key]) is type(value[key]), key
    assert [math.copysign(1, f) for f in back["floats"]] == [1, -1, 1, 1, -1] and back["floats"] == value["floats"]
    assert [type(s) for s in back["scalars"]] == [np.float32, np.int64, np.bool_]
    for key in ("f64", "fortran", "u16", "empty"):
        assert back[key].dtype == value[key].dtype and back[key].shape == value[key].shape
        assert back[key].tobytes(order="A") == value[key].tobytes(order="A"), key
    assert back["fortran"].flags.f_contiguous
    cb = back["dataclass"]
    assert type(cb) is ClassBootstrap and cb.ci == (0.05, 0.2) and np.array_equal(cb.replicates, value["dataclass"].replicates)
    assert math.isnan(decode(encode(math.nan)))


@pytest.mark.parametrize("value", [_NotOurs(1), object(), np.array([object()]), lambda: 0, {1: _NotOurs(2)},
                                   np.ma.masked_array([1.0])])
def test_what_cannot_be_rebuilt_safely_is_refused_when_written(value):
    with pytest.raises(Unencodable):
        encode(value)


@pytest.mark.parametrize("name", ["os:system", "builtins:eval", "subprocess:Popen", "forensics.cli.main:main",
                                  "forensics._shared.parallel:Executor", "forensics.not_imported:Thing",
                                  "tests._shared.test_safecodec:_NotOurs"])
def test_only_dataclasses_of_the_package_are_rebuilt(name):
    text = f'{{"format":1,"value":{{"$dataclass":"{name}","fields":{{}}}}}}'.encode()
    import io

    buffer = io.BytesIO()
    np.savez(buffer, structure=np.frombuffer(text, np.uint8))
    with pytest.raises(Undecodable):
        decode(buffer.getvalue())


@pytest.mark.parametrize("data", [b"", b"garbage", b"PK\x03\x04broken", b"\x80\x04K\x01."])
def test_foreign_bytes_do_not_decode(data):
    with pytest.raises(Undecodable):
        decode(data)
