"""Results to bytes and back without pickle: a stored result can hold data, never code.

A checkpoint keeps the result of every finished work item in a file beside the output, and a resumed run
reads those files back.  With :mod:`pickle` a file planted there (a shared scratch folder is enough) would
run code as the user on the next resume, because unpickling calls whatever the file names.  This codec
writes an ``.npz`` archive instead — numpy's own format, read with ``allow_pickle=False`` — whose members
are the result's arrays, plus one member ``structure``: JSON describing what holds them.  Decoding can
rebuild only

* ``None``, ``bool``, ``int``, ``float`` (NaN and infinities included), ``complex``, ``str``, ``bytes``;
* ``list``, ``tuple``, ``dict`` (any of these keys), ``set``, ``frozenset``, :class:`pathlib.Path`;
* numpy arrays, scalars and dtypes (no object dtype: that would need pickle);
* dataclasses **defined in the forensics package and already imported**: the class is looked up in
  :data:`sys.modules` by name (never imported, no ``__getattr__`` hook consulted), must be a dataclass, and
  is filled field by field without calling its ``__init__`` (as pickle does), so no code of the file's
  choosing runs.

Anything else cannot be encoded (:class:`Unencodable`); a file that does not decode raises
:class:`Undecodable` — the caller treats it as absent.  Floats survive exactly (JSON writes the shortest
repr that round-trips) and arrays keep their dtype, shape and memory order, so a resumed run gives the same
bits as an uninterrupted one.

Examples
--------
>>> import numpy as np
>>> value = (3, {"k": np.arange(3.0)}, float("nan"))
>>> back = decode(encode(value))
>>> back[0], back[1]["k"].tolist(), back[2] != back[2]
(3, [0.0, 1.0, 2.0], True)
"""
from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import sys
import zipfile
from pathlib import Path, PurePath
from typing import Any, BinaryIO

import numpy as np

FORMAT = 1
_STRUCTURE = "structure"
_PACKAGE = "forensics"


class Unencodable(TypeError):
    """A value holds something this codec cannot store without pickle."""


class Undecodable(ValueError):
    """Bytes that are not a result this codec wrote (damaged, foreign, or planted)."""


# -- encoding --------------------------------------------------------------------------------------------------


def encode(value: Any) -> bytes:
    """The ``.npz`` bytes of ``value``; raises :class:`Unencodable` for what :func:`decode` could not rebuild."""
    buffer = io.BytesIO()
    dump(value, buffer)
    return buffer.getvalue()


def dump(value: Any, handle: BinaryIO) -> None:
    """Write ``value`` to the binary file ``handle`` as :func:`encode` does, without a copy of its arrays in memory.

    Raises :class:`Unencodable` before anything is written.
    """
    arrays: list[np.ndarray] = []
    tree = _encode(value, arrays)
    members = {f"a{i}": a for i, a in enumerate(arrays)}
    text = json.dumps({"format": FORMAT, "value": tree}, allow_nan=False, separators=(",", ":"))
    members[_STRUCTURE] = np.frombuffer(text.encode(), np.uint8)
    np.savez(handle, **members)  # uncompressed: results are mostly noise-like floats


def _array_ref(array: np.ndarray, arrays: list[np.ndarray]) -> int:
    if array.dtype.hasobject:
        raise Unencodable("a numpy array of Python objects (dtype object) cannot be stored without pickle")
    arrays.append(array)
    return len(arrays) - 1


def _encode(value: Any, arrays: list[np.ndarray]) -> Any:
    kind = type(value)
    if value is None or kind in (bool, str, int):
        return value
    if kind is float:
        return value if math.isfinite(value) else {"$float": repr(value)}
    if kind is complex:
        return {"$complex": [_encode(value.real, arrays), _encode(value.imag, arrays)]}
    if kind is list:
        return [_encode(v, arrays) for v in value]
    if kind in (tuple, set, frozenset):
        return {f"${kind.__name__}": [_encode(v, arrays) for v in value]}
    if kind is dict:
        return {"$dict": [[_encode(k, arrays), _encode(v, arrays)] for k, v in value.items()]}
    if kind is bytes:
        return {"$bytes": _array_ref(np.frombuffer(value, np.uint8), arrays)}
    if isinstance(value, PurePath):
        return {"$path": str(value)}
    if kind is np.ndarray:
        return {"$array": _array_ref(value, arrays)}
    if isinstance(value, np.generic):
        return {"$scalar": _array_ref(np.asarray(value), arrays)}
    if isinstance(value, np.dtype):
        if value.hasobject:
            raise Unencodable("a numpy dtype of Python objects cannot be stored")
        return {"$dtype": _encode(np.lib.format.dtype_to_descr(value), arrays)}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _encode_dataclass(value, arrays)
    raise Unencodable(f"a {kind.__module__}.{kind.__qualname__} cannot be stored without pickle")


def _encode_dataclass(value: Any, arrays: list[np.ndarray]) -> dict[str, Any]:
    kind = type(value)
    name = f"{kind.__module__}:{kind.__qualname__}"
    if _dataclass_type(name, strict=False) is not kind:
        raise Unencodable(f"{kind.__module__}.{kind.__qualname__} is not a dataclass of the forensics package")
    names = [f.name for f in dataclasses.fields(value)]
    extra = set(getattr(value, "__dict__", {})) - set(names)
    if extra:  # state decode would not restore
        raise Unencodable(f"{kind.__qualname__} holds attributes that are not fields ({', '.join(sorted(extra))})")
    return {"$dataclass": name, "fields": {n: _encode(getattr(value, n), arrays) for n in names}}


# -- decoding --------------------------------------------------------------------------------------------------


def decode(source: bytes | str | os.PathLike) -> Any:
    """The value stored by :func:`encode` (bytes, or the path of a file holding them).

    Raises :class:`Undecodable` for anything else — never runs code from the input.
    """
    return _read(source, shallow=False)


def check(source: bytes | str | os.PathLike) -> None:
    """Raise :class:`Undecodable` unless ``source`` holds a structure :func:`decode` accepts.

    Reads the archive's directory and its small ``structure`` member only, not the arrays' data, so it is
    cheap enough to run on every item of a checkpoint before deciding which items to recompute.
    """
    _read(source, shallow=True)


#: What numpy's reader and json raise on damaged or foreign bytes.
_READ_ERRORS = (OSError, ValueError, TypeError, KeyError, IndexError, AttributeError, EOFError, RecursionError,
                zipfile.BadZipFile)


def _read(source: bytes | str | os.PathLike, shallow: bool) -> Any:
    try:
        with io.BytesIO(source) if isinstance(source, bytes) else open(source, "rb") as handle:
            archive = np.load(handle, allow_pickle=False)  # a pickle raises ValueError here, unread
            if not isinstance(archive, np.lib.npyio.NpzFile):
                raise Undecodable("not an .npz archive")
            with archive:
                header = json.loads(bytes(archive[_STRUCTURE]).decode())
                if not isinstance(header, dict) or header.get("format") != FORMAT or "value" not in header:
                    raise Undecodable("not a structure this codec wrote")
                return _Decoder(archive, shallow).node(header["value"])
    except Undecodable:
        raise
    except _READ_ERRORS as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise Undecodable(f"{type(exc).__name__}: {exc}") from None


class _Decoder:
    """Rebuilds a structure tree; ``shallow`` checks that every array member exists without reading it."""

    def __init__(self, archive: Any, shallow: bool = False) -> None:
        self.archive = archive
        self.shallow = shallow

    def array(self, index: Any) -> np.ndarray:
        if type(index) is not int:
            raise Undecodable("an array reference is not an index")
        key = f"a{index}"
        if self.shallow:
            self._check_header(key)
            return np.zeros(0, np.uint8)
        return self.archive[key]  # allow_pickle=False: an object array raises ValueError

    def _check_header(self, key: str) -> None:
        """The member exists and its header (not its data) describes an array of plain values."""
        if key not in self.archive.files:
            raise Undecodable(f"missing array {key}")
        with self.archive.zip.open(f"{key}.npy") as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                _, _, dtype = np.lib.format.read_array_header_1_0(member)
            elif version == (2, 0):
                _, _, dtype = np.lib.format.read_array_header_2_0(member)
            else:  # not what np.savez writes for these members
                raise Undecodable(f"array {key}: .npy version {version}")
        if dtype.hasobject:
            raise Undecodable(f"array {key} holds Python objects")

    def node(self, node: Any) -> Any:
        if node is None or type(node) in (bool, str, int, float):
            return node
        if type(node) is list:
            return [self.node(v) for v in node]
        if type(node) is not dict or not node:
            raise Undecodable(f"unexpected {type(node).__name__} in the structure")
        tag = next(iter(node))
        body = node[tag]
        if tag == "$dataclass":
            if set(node) != {"$dataclass", "fields"}:
                raise Undecodable("a dataclass entry has other keys than its name and fields")
            return self.dataclass(body, node["fields"])
        if len(node) != 1:
            raise Undecodable(f"unexpected keys beside {tag}")
        if tag == "$float":
            if body not in ("nan", "inf", "-inf"):
                raise Undecodable(f"not a special float: {body!r}")
            return float(body)
        if tag == "$complex":
            real, imag = self.items(body)
            return complex(real, imag)
        if tag in ("$tuple", "$set", "$frozenset"):
            return {"$tuple": tuple, "$set": set, "$frozenset": frozenset}[tag](self.items(body))
        if tag == "$dict":
            return {self.node(k): self.node(v) for k, v in (self._pair(p) for p in self._list(body))}
        if tag == "$path":
            if type(body) is not str:
                raise Undecodable("a path is not a string")
            return Path(body)
        if tag == "$bytes":
            return self.array(body).tobytes()
        if tag == "$array":
            return self.array(body)
        if tag == "$scalar":
            return self.array(body)[()] if not self.shallow else None
        if tag == "$dtype":
            return np.lib.format.descr_to_dtype(self.node(body))
        raise Undecodable(f"unknown tag {tag!r}")

    @staticmethod
    def _list(body: Any) -> list[Any]:
        if type(body) is not list:
            raise Undecodable("expected a list")
        return body

    @staticmethod
    def _pair(pair: Any) -> tuple[Any, Any]:
        if type(pair) is not list or len(pair) != 2:
            raise Undecodable("a dictionary entry is not a pair")
        return pair[0], pair[1]

    def items(self, body: Any) -> list[Any]:
        return [self.node(v) for v in self._list(body)]

    def dataclass(self, name: Any, fields: Any) -> Any:
        kind = _dataclass_type(name, strict=True)
        if type(fields) is not dict:
            raise Undecodable("dataclass fields are not a mapping")
        names = [f.name for f in dataclasses.fields(kind)]
        if sorted(fields) != sorted(names):
            raise Undecodable(f"{name}: fields {sorted(fields)} are not {sorted(names)}")
        values = {n: self.node(fields[n]) for n in names}
        if self.shallow:
            return None
        # As pickle does: a bare instance filled field by field, without running __init__ or __post_init__
        # (object.__new__, not the class's own __new__; slots through object.__setattr__).
        obj = object.__new__(kind)
        if hasattr(obj, "__dict__"):
            obj.__dict__.update(values)
        else:
            for n, v in values.items():
                object.__setattr__(obj, n, v)
        return obj


def _dataclass_type(name: Any, strict: bool) -> type | None:
    """The dataclass named ``module:qualname``, if it is defined in the forensics package and already imported.

    Looked up in ``sys.modules`` and the modules' and classes' own ``__dict__`` — no import, no module
    ``__getattr__`` (the packages' lazy loaders), no descriptor.  ``strict`` raises :class:`Undecodable`
    instead of returning None.
    """
    def refuse(why: str) -> None:
        if strict:
            raise Undecodable(f"{name!r}: {why}")

    if type(name) is not str or ":" not in name:
        return refuse("not a class name")
    module_name, qualname = name.split(":", 1)
    if module_name != _PACKAGE and not module_name.startswith(_PACKAGE + "."):
        return refuse("not a class of the forensics package")
    module = sys.modules.get(module_name)
    if module is None:
        return refuse("its module is not imported")
    obj: Any = module
    for part in qualname.split("."):
        obj = vars(obj).get(part)
        if obj is None:
            return refuse("no such class")
    if not (isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == module_name
            and obj.__qualname__ == qualname):
        return refuse("not a dataclass")
    return obj
