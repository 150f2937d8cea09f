"""The one conversion of results to standard JSON.

Every JSON the toolkit writes — ``--json`` on stdout, result files, fingerprint metadata, checkpoints — goes
through :func:`to_jsonable` and :func:`dumps`: numpy scalars and arrays become numbers and lists, paths
strings, objects with ``to_dict()`` their dictionaries, and a float that is not finite (NaN, ±inf) becomes
``null``.  ``dumps`` passes ``allow_nan=False``, so the non-standard tokens ``NaN`` and ``Infinity`` (which
strict parsers reject) can never be written.

Examples
--------
>>> import numpy as np
>>> dumps({"eer": np.float32(0.25), "ci": [float("nan"), 1.0]})
'{"eer": 0.25, "ci": [null, 1.0]}'
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def to_jsonable(obj: Any) -> Any:
    """``obj`` with numpy values, paths and ``to_dict()`` objects converted and non-finite floats as None."""
    import numpy as np

    if hasattr(obj, "to_dict") and not isinstance(obj, type):
        return to_jsonable(obj.to_dict())
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def dumps(obj: Any, **options: Any) -> str:
    """Standard JSON text of ``obj`` (:func:`to_jsonable` applied; ``allow_nan=False``); ``options`` go to
    :func:`json.dumps` (``indent``, ``sort_keys``)."""
    return json.dumps(to_jsonable(obj), allow_nan=False, **options)
