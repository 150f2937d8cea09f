"""Exceptions shared by the whole toolkit.

The command layer maps them to exit codes: :class:`InputError` (bad input
data) to 3, :class:`UsageError` (a request that cannot be honoured as given,
such as an output that exists without ``--force``) to 2.
"""
from __future__ import annotations


class ForensicsError(Exception):
    """Base class of every error the library raises on purpose."""


class InputError(ForensicsError):
    """Input data that cannot be used: the message names the file or field and what to do."""


class UsageError(ForensicsError):
    """A request that cannot be carried out as asked (e.g. an existing output without force)."""
