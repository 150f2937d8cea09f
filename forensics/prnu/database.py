"""A database of camera fingerprints that needs no server: a folder with an SQLite index.

Layout::

    DB/
      index.sqlite              one row per device (SQLite, WAL journal)
      fingerprints/<id>-<token>.npz   each fingerprint, written by Fingerprint.save

Concurrency and atomicity
-------------------------
The index is in SQLite's write-ahead-log mode: any number of readers (other processes,
other machines on a shared disk that supports locking) read a consistent snapshot while
one writer writes.  Writers take SQLite's write lock (``BEGIN IMMEDIATE``) for the whole
change and are served one at a time.

An addition writes the fingerprint file first (under a temporary name, renamed into place
and flushed to disk) and then commits its index row; a removal deletes the row and then
the file.  Every version of a fingerprint gets a file name of its own, so a replaced file
is deleted only after the row naming its successor is committed.  A reader therefore
finds, for every row it sees, a complete file: the old state or the new, never a mixture.
If a writer dies between the two steps, the file it left names no row and is invisible;
the next writer deletes it.  A reader that read a row just before a writer replaced or
removed it reads the row again (:meth:`FingerprintDatabase.load`).

Quality
-------
:attr:`DeviceEntry.quality` is the fingerprint's *effective number of images*,
``n_images × (1 − excluded pixel fraction)`` (saturated pixels carry no weight).  The
estimator's noise variance per pixel falls as ``1 / quality`` for images of similar
brightness and texture, so a matching query's PCE grows with it until the query's own
noise dominates.  Higher is better; 20–50 bright, flat images are usual.  It says nothing
about the images' content (flat fields give better fingerprints than textured scenes of
the same count), and it is not a prediction of any PCE: the signal-to-noise ratio of a
fingerprint cannot be separated from ``K`` alone, since the sensor's true pattern and the
estimation noise are both white.

Integrity
---------
Each row keeps two SHA-256 checksums in its provenance: ``fingerprint_sha256`` over ``K``'s bytes *and*
the fingerprint's metadata (region, frame shape, σ, images, parameters: everything identification
uses), checked when the fingerprint is loaded, so a file changed behind the database's back — its
pattern or its metadata — is reported, naming the entry; and ``k_sha256`` over ``K`` alone, which
identifies the pattern: a fingerprint identical to one already in the database under another id is
refused (two indistinguishable entries would make every decision between them arbitrary).  Entries
added by earlier versions have ``k_sha256`` only; they stay readable, checked on ``K`` and on the
index's region and frame-size columns (which hold what identification uses of the metadata).

Every path the database reads, writes or deletes is confined to its folder: the index's ``file``
column must be a plain name of the form it writes (``fingerprints/<name>.npz``), a regular file in the
``fingerprints`` folder; anything else (an absolute path, ``..``, a link) is a damaged index, refused
with nothing changed.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import re
import secrets
import shutil
import sqlite3
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from forensics import __version__
from forensics._shared.atomic import current_umask, mkdtemp_like_mkdir
from forensics._shared.errors import InputError, UsageError
from forensics._shared.jsonsafe import dumps
from forensics.prnu.fingerprint import Fingerprint, check_fingerprint

__all__ = ["DeviceEntry", "FingerprintDatabase", "SCHEMA_VERSION", "INDEX", "FINGERPRINTS"]

DB_FORMAT = "forensics-fingerprint-db"
SCHEMA_VERSION = 1
INDEX = "index.sqlite"
FINGERPRINTS = "fingerprints"
#: Seconds a writer waits for another writer's lock before giving up.
LOCK_TIMEOUT_S = 60.0
MAX_ID_LENGTH = 200
#: The only form of the index's ``file`` column: a plain ``.npz`` name in the fingerprints folder (see _safe_name).
_FILE_RE = re.compile(rf"{FINGERPRINTS}/[A-Za-z0-9][A-Za-z0-9._-]{{0,99}}\.npz")

_SCHEMA = f"""
CREATE TABLE schema (format TEXT NOT NULL, version INTEGER NOT NULL);
INSERT INTO schema VALUES ('{DB_FORMAT}', {SCHEMA_VERSION});
CREATE TABLE devices (
    device_id TEXT PRIMARY KEY NOT NULL,
    make TEXT, model TEXT, serial TEXT,
    region TEXT NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL,
    n_images INTEGER NOT NULL,
    first_captured REAL, last_captured REAL,
    quality REAL NOT NULL,
    provenance TEXT NOT NULL,
    file TEXT NOT NULL UNIQUE
);
"""
_COLUMNS = ("device_id", "make", "model", "serial", "region", "width", "height", "n_images", "first_captured",
            "last_captured", "quality", "provenance", "file")


@dataclass(frozen=True)
class DeviceEntry:
    """One device of a :class:`FingerprintDatabase` (everything but the fingerprint's array).

    Attributes
    ----------
    device_id : str
    make, model, serial : str or None
        From the caller, else the EXIF of the fingerprint's first source image.
    region : str
        The fingerprint's region spec (:func:`forensics.prnu.fingerprint.parse_region`).
    width, height : int
        Frame size the fingerprint was made at.
    n_images : int
    first_captured, last_captured : float or None
        Decimal years: the earliest and latest capture dates of the source images (their
        dataset manifest, else EXIF), None when no source file could be read.
    quality : float
        Effective number of images (see the module notes); higher is better.
    provenance : dict
        Source folder and files, σ, estimator parameters, K's SHA-256, library version,
        date added, where the device id came from, and anything the caller added.
    file : str
        The fingerprint file, relative to the database folder.
    """

    device_id: str
    make: str | None
    model: str | None
    serial: str | None
    region: str
    width: int
    height: int
    n_images: int
    first_captured: float | None
    last_captured: float | None
    quality: float
    provenance: dict
    file: str

    def to_dict(self) -> dict[str, Any]:
        """All fields as JSON-ready data."""
        return asdict(self)


# ----------------------------------------------------------------------------- helpers


def _k_digest(k: np.ndarray) -> str:
    """SHA-256 of K as stored (float32, C order): the pattern's identity."""
    return hashlib.sha256(np.ascontiguousarray(k, np.float32).tobytes()).hexdigest()


def _fingerprint_digest(fp: Fingerprint) -> str:
    """SHA-256 of K and of the fingerprint's metadata (canonical JSON of :meth:`Fingerprint.to_dict`)."""
    digest = hashlib.sha256(np.ascontiguousarray(fp.K, np.float32).tobytes())
    digest.update(b"\0")
    digest.update(dumps(fp.to_dict(), sort_keys=True, separators=(",", ":")).encode())
    return digest.hexdigest()


def _check_id(device_id: Any, what: str) -> str:
    """A device id as given, stripped; refused when empty, too long or holding control characters."""
    text = str(device_id).strip()
    if not text or len(text) > MAX_ID_LENGTH or any(ord(c) < 32 for c in text):
        raise UsageError(f"device id {device_id!r} ({what}): give 1-{MAX_ID_LENGTH} printable characters")
    return text


def _safe_name(device_id: str) -> str:
    """A file-name stem for a device id: its safe characters and a random token (one name per version)."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", device_id).strip("._-")[:60] or "device"
    return f"{stem}-{secrets.token_hex(4)}"


def _fsync(path: Path) -> None:
    """Flush a file and its folder's entry to disk, so that a committed row never names a file lost in a power cut."""
    for target in (path, path.parent):
        fd = os.open(target, os.O_RDONLY)
        try:
            os.fsync(fd)
        except OSError:  # some file systems cannot flush a folder; the file itself was flushed above
            if target == path:
                raise
        finally:
            os.close(fd)


def _provenance_digest(provenance: Any) -> str | None:
    """``k_sha256`` of a row's provenance text (None when it has none or cannot be read)."""
    try:
        value = json.loads(provenance).get("k_sha256")
    except (TypeError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def _mismatch(entry: DeviceEntry, fp: Fingerprint) -> str | None:
    """What differs between a fingerprint file and its index row (module notes), or None."""
    if fp.region != entry.region:
        return f"region {fp.region}, the index says {entry.region}"
    if tuple(fp.frame_shape) != (entry.height, entry.width):
        return (f"frame {fp.frame_shape[1]}×{fp.frame_shape[0]}, the index says {entry.width}×{entry.height}")
    full, k_only = entry.provenance.get("fingerprint_sha256"), entry.provenance.get("k_sha256")
    if full is not None:
        return None if _fingerprint_digest(fp) == full else "its pattern or its metadata changed (checksum)"
    if k_only is not None and _k_digest(fp.K) != k_only:  # an entry of an earlier version: K's checksum only
        return "its pattern changed (checksum of K)"
    return None


def _init_index(path: Path) -> None:
    """Create an index with the schema at ``path`` (a new file) in WAL mode."""
    con = sqlite3.connect(path, isolation_level=None)
    try:
        con.execute("PRAGMA journal_mode=WAL")  # persistent: every later connection reads in WAL mode
        con.executescript(f"BEGIN;{_SCHEMA}COMMIT;")
    finally:
        con.close()
    os.chmod(path, 0o666 & ~current_umask())  # sqlite makes 0644 whatever the umask; its -wal/-shm follow this


@dataclass
class _SourceInfo:
    """What the fingerprint's source images say about the device (all optional)."""

    devices: list[str]
    make: str | None
    model: str | None
    serial: str | None
    first: float | None
    last: float | None


def _source_frames(files: Sequence[str]) -> list[Any]:
    """Dataset frames of the source files that exist: from their folder's manifest when it has one."""
    from forensics.io.dataset import MANIFEST, Frame, open_dataset

    manifests: dict[Path, dict[Path, Any]] = {}
    frames = []
    for name in files:
        if not name:
            continue
        path = Path(name)
        if not path.is_file():
            continue
        folder = path.parent
        if folder not in manifests:
            manifests[folder] = {}
            if (folder / MANIFEST).is_file():
                # a damaged manifest only costs its metadata here: the files' EXIF is still read
                with contextlib.suppress(InputError, OSError, ValueError):
                    ds = open_dataset(folder, allow_outside=True)
                    manifests[folder] = {f.path.resolve(): f for f in ds.frames}
        frames.append(manifests[folder].get(path.resolve()) or Frame(path=path, file=path.name))
    return frames


def _read_sources(files: Sequence[str]) -> _SourceInfo:
    """Devices, EXIF make/model/serial (first readable file) and the capture-date range of the source images."""
    devices: list[str] = []
    times: list[float] = []
    first_info = None
    for frame in _source_frames(files):
        try:
            device, when = frame.get("device"), frame.captured
            if first_info is None:
                first_info = frame.info()
        except (InputError, OSError, ValueError):  # unreadable header: nothing known from this file
            continue
        if device and device not in devices:
            devices.append(device)
        if when is not None:
            times.append(float(when))
    return _SourceInfo(
        devices=devices,
        make=getattr(first_info, "make", None),
        model=getattr(first_info, "model", None),
        serial=getattr(first_info, "serial", None),
        first=min(times) if times else None,
        last=max(times) if times else None,
    )


def _common_folder(files: Sequence[str]) -> str | None:
    parents = [str(Path(f).resolve().parent) for f in files if f]
    if not parents:
        return None
    with contextlib.suppress(ValueError):
        return os.path.commonpath(parents)
    return None


# ----------------------------------------------------------------------------- the database


class FingerprintDatabase:
    """A folder of device fingerprints with an SQLite index (see the module notes).

    Parameters
    ----------
    folder : str or PathLike
        The database folder.
    create : bool
        Create the database when ``folder`` does not exist or is an empty folder.

    Raises
    ------
    InputError
        If the folder is missing (and ``create`` is false), or is not a fingerprint
        database (no index, a foreign or damaged index, a newer schema).

    Examples
    --------
    >>> db = FingerprintDatabase("cameras", create=True)              # doctest: +SKIP
    >>> db.add(Fingerprint.load("d70.npz"), "Nikon D70 #0")           # doctest: +SKIP
    >>> [e.device_id for e in db.entries()]                           # doctest: +SKIP
    ['Nikon D70 #0']
    >>> fp = db.load("Nikon D70 #0")                                  # doctest: +SKIP
    """

    def __init__(self, folder: str | os.PathLike, create: bool = False) -> None:
        self.folder = Path(folder)
        self.index = self.folder / INDEX
        if not self.index.exists():
            self._create_or_refuse(create)
        self._check_schema()
        files = self.folder / FINGERPRINTS
        if not files.is_dir() or files.is_symlink():
            what = "is a symbolic link" if files.is_symlink() else "is missing"
            raise InputError(f"{self.folder}: the database's '{FINGERPRINTS}' folder {what}; the database is damaged: "
                             "restore it from a copy or build a new one")

    def __repr__(self) -> str:
        return f"FingerprintDatabase({str(self.folder)!r})"

    # ------------------------------------------------------------------ opening

    def _create_or_refuse(self, create: bool) -> None:
        folder = self.folder
        if folder.exists() and not folder.is_dir():
            raise InputError(f"{folder}: is a file, not a fingerprint database folder; give the database folder")
        if not create:
            if not folder.exists():
                raise InputError(f"{folder}: no such fingerprint database; create one with "
                                 f"'forensics fingerprint db add {folder} FP.npz'")
            raise InputError(f"{folder}: not a fingerprint database (no {INDEX}); give a database folder")
        if not folder.exists():
            self._create_new_folder()
        elif any(not p.name.startswith(".") for p in folder.iterdir()):
            raise InputError(f"{folder}: not a fingerprint database (no {INDEX}) and not empty; give a new or empty "
                             "folder for a new database")
        else:
            self._create_in_empty_folder()

    def _create_new_folder(self) -> None:
        """Build the database in a temporary sibling and rename it into place: never seen half-made."""
        folder = self.folder
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = mkdtemp_like_mkdir(prefix=f".{folder.name}.", suffix=".part", dir=folder.parent)
        try:
            _init_index(tmp / INDEX)
            (tmp / FINGERPRINTS).mkdir()
            try:
                os.rename(tmp, folder)
            except OSError:
                if not (folder / INDEX).exists():  # not another process creating the same database
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _create_in_empty_folder(self) -> None:
        """Make the index under a temporary name and link it into place (no-clobber if another process won)."""
        fd, name = tempfile.mkstemp(prefix=f".{INDEX}.", suffix=".part", dir=self.folder)
        os.close(fd)
        tmp = Path(name)
        try:
            tmp.unlink()  # sqlite creates the file itself
            _init_index(tmp)
            (self.folder / FINGERPRINTS).mkdir(exist_ok=True)
            with contextlib.suppress(FileExistsError):
                os.link(tmp, self.index)
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()

    def _check_schema(self) -> None:
        try:
            con = sqlite3.connect(self.index.resolve().as_uri() + "?mode=rw", uri=True, timeout=LOCK_TIMEOUT_S)
            try:
                rows = con.execute("SELECT format, version FROM schema").fetchall()
            finally:
                con.close()
        except sqlite3.Error as exc:
            raise InputError(f"{self.folder}: {INDEX} is not the index of a fingerprint database ({exc}); the folder "
                             "is damaged or belongs to another program") from exc
        if len(rows) != 1 or rows[0][0] != DB_FORMAT:
            raise InputError(f"{self.folder}: {INDEX} is not the index of a fingerprint database; the folder belongs "
                             "to another program")
        if int(rows[0][1]) > SCHEMA_VERSION:
            raise InputError(f"{self.folder}: database schema {rows[0][1]} is newer than this forensics "
                             f"({__version__}, schema {SCHEMA_VERSION}) reads; upgrade forensics")

    @contextlib.contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        """A short-lived connection (none is kept: safe across fork and for many processes)."""
        uri = self.index.resolve().as_uri() + "?mode=rw"  # never creates a missing index
        try:
            con = sqlite3.connect(uri, uri=True, timeout=LOCK_TIMEOUT_S, isolation_level=None)
        except sqlite3.Error as exc:
            raise InputError(f"{self.folder}: cannot open {INDEX} ({exc}); check the folder and its permissions") from exc
        try:
            con.execute("PRAGMA synchronous=FULL")
            yield con
        except sqlite3.OperationalError as exc:
            if "locked" in str(exc) or "busy" in str(exc):
                raise InputError(f"{self.folder}: another process has been writing to the database for more than "
                                 f"{LOCK_TIMEOUT_S:g} s; try again when it has finished") from exc
            raise InputError(f"{self.folder}: the database index failed ({exc}); check the folder") from exc
        except sqlite3.DatabaseError as exc:
            raise InputError(f"{self.folder}: the database index is damaged ({exc}); restore it from a copy") from exc
        finally:
            con.close()

    @contextlib.contextmanager
    def _write(self) -> Iterator[tuple[sqlite3.Connection, list[Path]]]:
        """One write transaction under the writers' lock.

        Yields the connection and a list the caller appends the files it writes to; on any
        failure the transaction is rolled back and those files deleted, so nothing is left.
        """
        with self._connect() as con:
            con.execute("BEGIN IMMEDIATE")  # the write lock, held until COMMIT: writers queue here
            written: list[Path] = []
            try:
                self._sweep(con)
                yield con, written
                con.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    con.execute("ROLLBACK")
                for path in written:
                    with contextlib.suppress(FileNotFoundError):
                        path.unlink()
                raise

    def _path(self, rel: Any, device_id: Any) -> Path:
        """The fingerprint file an index row names, confined to the fingerprints folder (module notes).

        Raises
        ------
        InputError
            The ``file`` column is not a plain name of the expected form, or names a link or a non-file.
        """
        folder = self.folder / FINGERPRINTS
        path = folder / Path(str(rel)).name
        if (not isinstance(rel, str) or not _FILE_RE.fullmatch(rel) or path.is_symlink()
                or (path.exists() and not path.is_file())):
            raise InputError(f"{self.folder}: the index names {str(rel)[:120]!r} as the file of device {device_id!r}, "
                             f"which is not a fingerprint file of its '{FINGERPRINTS}' folder: the index is damaged "
                             "(nothing was changed); restore the database from a copy")
        return path

    def _sweep(self, con: sqlite3.Connection) -> None:
        """Delete files no row names (left by a writer that died); safe under the write lock.

        Every row's file is checked first (:meth:`_path`): with a damaged index nothing is deleted.
        """
        rows = con.execute("SELECT device_id, file FROM devices").fetchall()
        named = {str(self._path(rel, device_id).relative_to(self.folder).as_posix()) for device_id, rel in rows}
        for path in (self.folder / FINGERPRINTS).iterdir():
            rel = f"{FINGERPRINTS}/{path.name}"
            stray = path.name.endswith(".part") or (path.suffix == ".npz" and rel not in named)
            if stray and path.is_file():
                with contextlib.suppress(OSError):
                    path.unlink()

    # ------------------------------------------------------------------ reading

    def _row_entry(self, row: Sequence[Any]) -> DeviceEntry:
        values = dict(zip(_COLUMNS, row))
        try:
            values["provenance"] = json.loads(values["provenance"])
        except (TypeError, json.JSONDecodeError) as exc:
            raise InputError(f"{self.folder}: the entry {values['device_id']!r} has a damaged provenance ({exc}); "
                             "remove it and add the fingerprint again") from exc
        return DeviceEntry(**values)

    def entries(self) -> list[DeviceEntry]:
        """Every device, sorted by device id (one consistent snapshot)."""
        with self._connect() as con:
            rows = con.execute(f"SELECT {', '.join(_COLUMNS)} FROM devices ORDER BY device_id").fetchall()
        return [self._row_entry(r) for r in rows]

    def _find(self, device_id: str) -> DeviceEntry | None:
        with self._connect() as con:
            row = con.execute(f"SELECT {', '.join(_COLUMNS)} FROM devices WHERE device_id = ?",
                              (str(device_id).strip(),)).fetchone()  # ids are stored stripped (_check_id)
        return None if row is None else self._row_entry(row)

    def get(self, device_id: str) -> DeviceEntry:
        """The entry of ``device_id``.

        Raises
        ------
        UsageError
            If the database has no such device.
        """
        entry = self._find(device_id)
        if entry is None:
            raise UsageError(f"{self.folder}: no device {device_id!r}; 'forensics fingerprint db list "
                             f"{self.folder}' shows the device ids")
        return entry

    def __len__(self) -> int:
        with self._connect() as con:
            return int(con.execute("SELECT COUNT(*) FROM devices").fetchone()[0])

    def __contains__(self, device_id: object) -> bool:
        return isinstance(device_id, str) and self._find(device_id) is not None

    def load(self, device_id: str) -> Fingerprint:
        """The fingerprint of ``device_id``, checked against its index row (K's SHA-256, region).

        Raises
        ------
        UsageError
            If the database has no such device.
        InputError
            If its file is missing or does not match the index.
        """
        for attempt in range(2):
            entry = self.get(device_id)
            path = self._path(entry.file, entry.device_id)
            try:
                fp = Fingerprint.load(path)
                break
            except InputError:
                if path.exists():
                    raise
                if attempt:
                    raise InputError(f"{self.folder}: the fingerprint file {entry.file} of device {device_id!r} is "
                                     f"missing; remove the entry (forensics fingerprint db remove {self.folder} "
                                     f"'{device_id}') and add the fingerprint again") from None
                # a writer replaced or removed the entry between our reading its row and its file: read the row again
        problem = _mismatch(entry, fp)
        if problem is not None:
            raise InputError(f"{path}: the fingerprint of device {entry.device_id!r} does not match the database index "
                             f"({problem}): changed outside the database; add it again with --replace")
        return fp

    # ------------------------------------------------------------------ writing

    def add(self, fingerprint: Fingerprint, device_id: str | None = None, *, make: str | None = None,
            model: str | None = None, serial: str | None = None, provenance: dict | None = None,
            replace: bool = False) -> DeviceEntry:
        """Add one fingerprint (see :meth:`add_many`)."""
        return self.add_many([fingerprint], [device_id], make=make, model=model, serial=serial,
                             provenances=[provenance or {}], replace=replace)[0]

    def add_many(self, fingerprints: Sequence[Fingerprint | str | os.PathLike],
                 device_ids: Sequence[str | None] | None = None, *, make: str | None = None,
                 model: str | None = None, serial: str | None = None,
                 provenances: Sequence[dict] | None = None, replace: bool = False) -> list[DeviceEntry]:
        """Add fingerprints in one transaction: all of them, or (on any error) none.

        Parameters
        ----------
        fingerprints : sequence of Fingerprint or paths
            Paths are read one at a time (memory: one fingerprint).
        device_ids : sequence of str or None, optional
            One per fingerprint; where None, the id comes from the fingerprint's
            ``parameters['device']``, else from its source images (their manifest's
            ``device`` column, else EXIF make, model and body serial) when they all agree.
        make, model, serial : str, optional
            Default: the EXIF of the fingerprint's first readable source image.
        provenances : sequence of dict, optional
            Extra provenance of each fingerprint (e.g. the file it was read from).
        replace : bool
            Replace existing devices of the same id (refused otherwise).

        Returns
        -------
        list of DeviceEntry, in the order given

        Raises
        ------
        UsageError
            No device id can be found (give one), an id exists and ``replace`` is false,
            one id is given twice, or a fingerprint is identical (same ``K``) to another device's.
        InputError
            A fingerprint file cannot be read or holds no usable pattern (NaN, constant), or the
            index is damaged (a ``file`` outside the fingerprints folder); nothing is written.
        """
        n = len(fingerprints)
        ids = list(device_ids) if device_ids is not None else [None] * n
        extra = list(provenances) if provenances is not None else [{}] * n
        if len(ids) != n or len(extra) != n:
            raise UsageError("add_many: give one device id (or None) and one provenance per fingerprint")
        added: list[DeviceEntry] = []
        old_files: list[Path] = []
        with self._write() as (con, written):
            rows = con.execute("SELECT device_id, file, provenance FROM devices").fetchall()
            existing = {device_id: rel for device_id, rel, _ in rows}
            patterns = {_provenance_digest(prov): device_id for device_id, _, prov in rows}
            for item, device_id, prov in zip(fingerprints, ids, extra):
                if isinstance(item, Fingerprint):
                    fp = item
                    check_fingerprint(fp, f"fingerprint {len(added) + 1}")
                else:
                    fp = Fingerprint.load(item)  # checked as it is read
                    prov = {"fingerprint_file": str(Path(item).resolve()), **prov}
                entry = self._describe(fp, device_id, make, model, serial, prov)
                if any(e.device_id == entry.device_id for e in added):
                    raise UsageError(f"device id {entry.device_id!r} is given to two fingerprints; one id per device")
                twin = patterns.get(entry.provenance["k_sha256"])
                if twin is not None and twin != entry.device_id:
                    raise UsageError(f"{prov.get('fingerprint_file') or 'the fingerprint'}: identical to the fingerprint "
                                     f"of device {twin!r} (same K); two devices cannot have one pattern, so "
                                     "identification could not tell them apart: add it once, under one id")
                if entry.device_id in existing:
                    if not replace:
                        raise UsageError(f"{self.folder}: device {entry.device_id!r} is already in the database; "
                                         "add it with --replace to replace its fingerprint")
                    old_files.append(self._path(existing[entry.device_id], entry.device_id))  # checked before writing
                patterns[entry.provenance["k_sha256"]] = entry.device_id
                path = self.folder / entry.file
                written.append(path)
                fp.save(path)  # temporary name, then rename (atomic_file)
                _fsync(path)
                self._insert(con, entry)
                added.append(entry)
                del fp  # one fingerprint in memory at a time
        for old in old_files:  # after the commit: a reader of the old row finds the new one (see load)
            with contextlib.suppress(FileNotFoundError):
                old.unlink()
        return added

    @staticmethod
    def _insert(con: sqlite3.Connection, entry: DeviceEntry) -> None:
        values = entry.to_dict()
        values["provenance"] = json.dumps(values["provenance"], default=str)
        con.execute(f"INSERT OR REPLACE INTO devices ({', '.join(_COLUMNS)}) VALUES ({', '.join('?' * len(_COLUMNS))})",
                    [values[c] for c in _COLUMNS])

    def _describe(self, fp: Fingerprint, device_id: str | None, make: str | None, model: str | None,
                  serial: str | None, extra: dict) -> DeviceEntry:
        """The entry of a fingerprint about to be added (reads its source images' metadata)."""
        name = extra.get("fingerprint_file") or "the fingerprint"
        sources = _read_sources(fp.files)
        if device_id is not None:
            device_id, origin = _check_id(device_id, "given"), "given"
        elif fp.parameters.get("device"):
            device_id, origin = _check_id(fp.parameters["device"], f"{name}'s provenance"), "fingerprint provenance"
        elif len(sources.devices) == 1:
            device_id, origin = _check_id(sources.devices[0], "source images"), "source images (manifest or EXIF)"
        elif sources.devices:
            raise UsageError(f"{name}: its source images name {len(sources.devices)} devices "
                             f"({', '.join(sources.devices[:3])}); give the device id with --device")
        else:
            raise UsageError(f"{name}: no device id in its provenance or its source images' manifest or EXIF; "
                             "give one with --device")
        excluded = float(fp.parameters.get("excluded_pixel_fraction", 0.0) or 0.0)
        height, width = (int(v) for v in fp.frame_shape)
        provenance = {
            "added": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "forensics_version": __version__,
            "device_id_from": origin,
            "source_folder": _common_folder(fp.files),
            "files": list(fp.files),
            "sigma": float(fp.sigma),
            "k_shape": [int(v) for v in fp.K.shape],
            "parameters": fp.to_dict()["parameters"],
            "quality": {"figure": "effective number of images = n_images * (1 - excluded_pixel_fraction)",
                        "excluded_pixel_fraction": excluded},
            **extra,
            "k_sha256": _k_digest(fp.K),
            "fingerprint_sha256": _fingerprint_digest(fp),
        }
        return DeviceEntry(
            device_id=device_id,
            make=make if make is not None else sources.make,
            model=model if model is not None else sources.model,
            serial=serial if serial is not None else sources.serial,
            region=fp.region,
            width=width,
            height=height,
            n_images=int(fp.n_images),
            first_captured=sources.first,
            last_captured=sources.last,
            quality=float(fp.n_images) * (1.0 - excluded),
            provenance=provenance,
            file=f"{FINGERPRINTS}/{_safe_name(device_id)}.npz",
        )

    def remove(self, device_id: str) -> None:
        """Remove a device: its row in one transaction, then its file.

        Raises
        ------
        UsageError
            If the database has no such device.
        InputError
            If its row names a file outside the fingerprints folder (a damaged index): nothing is deleted.
        """
        key = str(device_id).strip()  # ids are stored stripped (_check_id)
        with self._write() as (con, _):
            row = con.execute("SELECT file FROM devices WHERE device_id = ?", (key,)).fetchone()
            if row is None:
                raise UsageError(f"{self.folder}: no device {key!r}; 'forensics fingerprint db list "
                                 f"{self.folder}' shows the device ids")
            path = self._path(row[0], key)  # before anything is deleted
            con.execute("DELETE FROM devices WHERE device_id = ?", (key,))
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
