"""The exact content digest: SHA-256 over a value's types and bits, for reuse that must be exact.

Two values with the same :func:`content_digest` are equal value by value, in the same types and memory layout
(arrays: dtype, shape, strides and bytes; floats: their exact bits), so a deterministic function gives them
the same result.  Used to reuse iris templates, comparison scores and segmentation steps
(:mod:`forensics.impact.reuse`, :mod:`forensics.impact.segment.memo`) only where that is provably exact.
"""
from __future__ import annotations

import dataclasses
import hashlib
import struct
from typing import Any

import numpy as np


def content_digest(value: Any) -> bytes | None:
    """SHA-256 of a value's complete content, or None for a value holding a type it does not know.

    Known: None, bool, int, float (its exact bits), complex, str, bytes, numpy arrays and scalars (dtype,
    shape, strides and bytes; object arrays are unknown), tuples, lists, dicts (in their order) and dataclass
    instances (their class and every attribute), recursively; every value's type is part of the digest.
    """
    digest = hashlib.sha256()
    return digest.digest() if _feed(digest, value) else None


def _feed(digest: Any, value: Any) -> bool:
    """Add ``value`` to ``digest`` with its type; False when a part of it is of an unknown type."""
    tag = f"{type(value).__module__}.{type(value).__qualname__}|".encode()
    digest.update(tag)
    if isinstance(value, (np.ndarray, np.generic)):
        a = np.asarray(value)
        if a.dtype.hasobject:
            return False
        digest.update(f"{a.dtype.str}{a.shape}{a.strides}".encode())
        digest.update(np.ascontiguousarray(a).tobytes())
        return True
    if value is None or isinstance(value, (bool, int, str)):
        digest.update(repr(value).encode() + b";")
        return True
    if isinstance(value, float):
        digest.update(struct.pack("<d", value))   # the exact bits (repr would merge NaN payloads)
        return True
    if isinstance(value, complex):
        digest.update(struct.pack("<dd", value.real, value.imag))
        return True
    if isinstance(value, (bytes, bytearray)):
        digest.update(f"{len(value)}:".encode() + bytes(value))
        return True
    if isinstance(value, (tuple, list)):
        digest.update(f"{len(value)}[".encode())
        return all(_feed(digest, item) for item in value)
    if isinstance(value, dict):
        digest.update(f"{len(value)}{{".encode())
        return all(_feed(digest, k) and _feed(digest, v) for k, v in value.items())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        # Every attribute, not only the fields: a cached value stored on the instance is content too.
        state = dict(vars(value)) if hasattr(value, "__dict__") else {}
        state.update({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
        digest.update(f"{len(state)}(".encode())
        return all(_feed(digest, k) and _feed(digest, state[k]) for k in sorted(state))
    return False
