"""Loading a user's class from ``module.path:Class`` or ``path/to/file.py:Class`` (effects, matchers).

Instances of such classes travel to worker processes by pickle (:mod:`forensics._shared.parallel`).  A class
from an importable module pickles as usual; one loaded from a file cannot be imported by name in another
process, so its instances are pickled as the file's absolute path, the class name and their state, and the
worker loads the file again (workers share the file system, as they share the images).
"""
from __future__ import annotations

import copyreg
import functools
import importlib
import importlib.util
from pathlib import Path
from typing import Any

from forensics._shared.errors import UsageError

__all__ = ["is_class_spec", "load_class"]


def is_class_spec(spec: str) -> bool:
    """Whether ``spec`` has the form ``module.path:Class`` or ``path/to/file.py:Class``."""
    where, sep, name = spec.rpartition(":")
    if not sep or not where or not name.isidentifier():
        return False
    return where.endswith(".py") or all(part.isidentifier() for part in where.split("."))


def load_class(spec: str, what: str) -> type:
    """The class named by ``spec`` (``module.path:Class`` or ``path/to/file.py:Class``).

    ``what`` names the kind of object in messages ("effect", "matcher").  Any error while importing the
    user's code is a :class:`UsageError` naming the spec: it is the user's file, not our input data.
    """
    if not is_class_spec(spec):
        raise UsageError(f"{what} '{spec}': give module.path:Class or path/to/file.py:Class")
    where, _, name = spec.rpartition(":")
    try:
        if where.endswith(".py"):
            path = Path(where)
            if not path.is_file():
                raise UsageError(f"{what} '{spec}': no such file {where}")
            mod_spec = importlib.util.spec_from_file_location(f"forensics_user_{what}_{path.stem}", path)
            if mod_spec is None or mod_spec.loader is None:
                raise UsageError(f"{what} '{spec}': cannot load {where} as Python")
            module = importlib.util.module_from_spec(mod_spec)
            mod_spec.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except UsageError:
        raise
    except Exception as exc:  # noqa: BLE001 — whatever the user's module raises on import
        raise UsageError(f"cannot load the {what} '{spec}': {type(exc).__name__}: {exc}") from exc
    cls = getattr(module, name, None)
    if cls is None:
        raise UsageError(f"{what} '{spec}': {where} has no {name}")
    if not isinstance(cls, type):
        raise UsageError(f"{what} '{spec}': {name} is not a class")
    if where.endswith(".py"):
        copyreg.pickle(cls, functools.partial(_reduce_by_spec, f"{Path(where).absolute()}:{name}", what))
    return cls


def _reduce_by_spec(spec: str, what: str, obj: Any) -> Any:
    reduced = object.__reduce_ex__(obj, 2)  # (copyreg.__newobj__, (cls, *args), state, …) for plain classes
    if reduced[0] is copyreg.__newobj__ and reduced[1][0] is type(obj):
        return (_new_by_spec, (spec, what, *reduced[1][1:]), *reduced[2:])
    return reduced  # the class pickles itself its own way


def _new_by_spec(spec: str, what: str, *args: Any) -> Any:
    """A bare instance of the class named by ``spec``, loaded again in this process (pickle sets its state)."""
    cls = load_class(spec, what)  # registers the class here too, so the instance can travel on
    return cls.__new__(cls, *args)
