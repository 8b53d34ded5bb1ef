"""Artifact store: one directory per (node, key), atomic writes, concurrent writers, checksums.

Layout of a cache directory::

    .lock                        shared (flock) by every running dermis process, exclusive
                                 for ``dermis clean``
    <node>/<key>/                one finished artifact: data files + meta.json (written last,
                                 with the sha256 of every data file)
    index/<node>.json            the key parts of the node's newest artifact (for `status`)
    .tmp/<host>-<pid>-<uuid>/    work in progress; renamed into place when complete

Concurrency (several processes or machines sharing one cache): an artifact directory appears
only by renaming a complete temporary directory, so distinct keys never block each other and
a key written twice is harmless (the second writer finds a valid entry and drops its own
copy).  A run killed mid-stage leaves only ``.tmp`` debris, never trusted; debris of dead
processes on this host is removed by the next run.  Integrity: an entry counts only if its
``meta.json`` is a JSON object that records every data file of the entry (plain names of
files inside it, nothing else) with its size and checksum, every file it lists as an output
is among them, an entry that held an artifact still holds both its files, and every data
file matches its record (:meth:`Store.verify`, :func:`entry_problem`); anything else is
reported corrupted and rebuilt, never used.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import shutil
import socket
import uuid
from contextlib import contextmanager
from pathlib import Path

from .errors import CacheLockedError, DermisError

__all__ = ["Store", "CACHE_ENV_VAR", "file_digest", "entry_problem"]

CACHE_ENV_VAR = "DERMIS_CACHE"
META = "meta.json"
ARTIFACT_FILES = ("data.npz", "fields.json")   # pipeline/artifacts.py save(): both or none


def file_digest(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes (input files enter cache keys by content, not by name)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class Store:
    """A cache directory of artifacts addressed by node id and key."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()


    # -- paths
    def artifact_dir(self, node: str, key: str) -> Path:
        return self.root / node / key

    def has(self, node: str, key: str) -> bool:
        return (self.artifact_dir(node, key) / META).is_file()

    def meta(self, node: str, key: str) -> dict:
        path = self.artifact_dir(node, key) / META
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            meta, why = None, f"{exc}"
        else:
            why = entry_problem(meta)
        if why is not None:
            raise DermisError(f"cache entry {path.parent} is damaged ({why}); run again to "
                              "rebuild it") from None
        return meta

    def output_files(self, node: str, key: str) -> list[Path]:
        """The files the entry lists as outputs (its ``files``): each one of its recorded data
        files, so a path inside the entry (:func:`entry_problem` refuses anything else)."""
        meta = self.meta(node, key)
        return [self.artifact_dir(node, key) / name for name in meta.get("files", [])]

    # -- index (last key parts per node, for staleness reasons)
    def read_index(self, node: str) -> dict | None:
        """The node's newest key and key parts, or None (none written, or unreadable)."""
        path = self.root / "index" / f"{node}.json"
        try:
            entry = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        if not (isinstance(entry, dict) and isinstance(entry.get("key"), str)
                and isinstance(entry.get("parts", {}), dict)):
            return None
        return entry

    def write_index(self, node: str, entry: dict) -> None:
        self._atomic_write_text(self.root / "index" / f"{node}.json",
                                json.dumps(entry, indent=1, sort_keys=True))

    def verify(self, node: str, key: str, *, deep: bool = True) -> str | None:
        """None if the entry is complete and intact, else why not (missing file, bad checksum).

        ``deep=False`` checks only that every recorded file is there with its recorded size
        (cheap, for planning); entries are verified deeply before their data is used.
        """
        d = self.artifact_dir(node, key)
        stamp = _stamp(d)
        if deep and stamp is not None and _VERIFIED.get(d) == stamp:
            return None
        try:
            meta = json.loads((d / META).read_text())
        except FileNotFoundError:
            return "not built"
        except (OSError, ValueError) as exc:
            return f"{META} unreadable ({exc})"
        problem = entry_problem(meta) or _unrecorded(d, meta["checksums"])
        if problem is not None:
            return problem
        sums, sizes = meta["checksums"], meta.get("sizes", {})
        for name, digest in sums.items():
            f = d / name
            if f.is_symlink() or not f.is_file():
                return f"{name} is missing" if not f.is_symlink() else f"{name} is a link"
            if name in sizes and f.stat().st_size != sizes[name]:
                return f"{name} has {f.stat().st_size} bytes, not {sizes[name]}"
            if deep and file_digest(f) != digest:
                return f"{name} does not match its checksum"
        if deep and stamp is not None:
            _VERIFIED[d] = stamp
        return None

    # -- writing
    @contextmanager
    def writing(self, node: str, key: str):
        """Yield a temporary directory; on success it becomes the artifact directory.

        The caller writes the data files and ``meta.json``; the store adds the checksums of
        the data files to ``meta.json`` and renames the directory into place.  If another
        writer got there first with a valid entry, this copy is dropped.
        """
        tmp = self.root / ".tmp" / f"{_host()}-{os.getpid()}-{uuid.uuid4().hex}"
        tmp.mkdir(parents=True)
        try:
            yield tmp
            if not (tmp / META).is_file():
                raise RuntimeError(f"stage wrote no {META} for {node}")
            meta = json.loads((tmp / META).read_text())
            data = [p for p in sorted(tmp.iterdir()) if p.is_file() and p.name != META]
            meta["checksums"] = {p.name: file_digest(p) for p in data}
            meta["sizes"] = {p.name: p.stat().st_size for p in data}
            (tmp / META).write_text(json.dumps(meta, indent=1, sort_keys=True, default=str))
            final = self.artifact_dir(node, key)
            final.parent.mkdir(parents=True, exist_ok=True)
            for _ in range(3):
                try:
                    os.rename(tmp, final)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                        raise
                    if self.verify(node, key) is None:   # someone else wrote it: keep theirs
                        break
                    self._discard(final)                  # forced rerun or a corrupted entry
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def discard(self, node: str, key: str) -> None:
        """Remove an entry (atomically: readers see all of it or none)."""
        d = self.artifact_dir(node, key)
        _VERIFIED.pop(d, None)
        self._discard(d)

    def _discard(self, path: Path) -> None:
        """Move an entry aside atomically, then delete it (readers never see half of it)."""
        trash = self.root / ".tmp" / f"{_host()}-{os.getpid()}-{uuid.uuid4().hex}-old"
        try:
            os.rename(path, trash)
        except FileNotFoundError:
            return
        shutil.rmtree(trash, ignore_errors=True)

    @staticmethod
    def _atomic_write_text(path: Path, text: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
        tmp.write_text(text)
        os.replace(tmp, path)

    # -- housekeeping
    @contextmanager
    def locked(self, exclusive: bool = False):
        """Hold the cache: shared by runs (any number at once, also across machines through
        the cache's file system), exclusive for ``clean``.  A conflicting holder gives
        :class:`CacheLockedError` at once."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            fh = open(self.root / ".lock", "a+")
        except OSError as exc:
            raise CacheLockedError(f"cache {self.root} cannot be used: {exc.strerror}; choose "
                                   "another with --cache DIR or $DERMIS_CACHE") from None
        try:
            try:
                fcntl.flock(fh, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
            except OSError:
                what = "cleaned" if exclusive else "used"
                raise CacheLockedError(
                    f"cache {self.root} cannot be {what} now: another dermis process holds it "
                    f"({'a run' if exclusive else 'a clean'}); wait for it to finish or choose "
                    "another cache with --cache DIR") from None
            self._remove_debris()
            yield self
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
            fh.close()

    def _remove_debris(self) -> None:
        """Remove temporary folders of processes on this host that no longer exist."""
        tmp_root = self.root / ".tmp"
        if not tmp_root.is_dir():
            return
        for d in tmp_root.iterdir():
            host, _, rest = d.name.partition("-")
            pid = rest.partition("-")[0]
            if pid.isdigit() and not owner_gone(host, int(pid)):
                continue  # work in progress here, or on another machine
            shutil.rmtree(d, ignore_errors=True)

    def clean(self, node_prefix: str | None = None) -> int:
        """Remove all artifacts (or those of one stage: node ``stage`` or ``stage-*``); count removed."""
        if not self.root.is_dir():
            return 0
        removed = 0
        with self.locked(exclusive=True):
            for d in sorted(self.root.iterdir()):
                if d.name.startswith(".") or not d.is_dir():
                    continue
                if d.name == "index":
                    continue
                if node_prefix and not (d.name == node_prefix
                                        or d.name.startswith(node_prefix + "-")):
                    continue
                removed += sum(1 for _ in d.iterdir())
                shutil.rmtree(d)
                idx = self.root / "index" / f"{d.name}.json"
                idx.unlink(missing_ok=True)
        return removed


def _plain_name(name) -> bool:
    """A file directly inside an entry: no separator, not ``.``/``..``, not meta.json."""
    return (isinstance(name, str) and name not in ("", ".", "..", META)
            and not any(c in name for c in "/\\\0"))


def entry_problem(meta) -> str | None:
    """Why a parsed ``meta.json`` cannot describe a valid entry, or None.

    An entry names only files inside itself: its ``checksums`` and ``sizes`` record the same
    plain file names, every name in ``files`` (the outputs copied to the output folder) is one
    of them, and an entry that held an artifact (``"artifact"`` set, or either of
    :data:`ARTIFACT_FILES` recorded) records both of its files.  An entry that records no data
    file at all is valid only when it says it held none (``"artifact": null``, no files)."""
    if not isinstance(meta, dict):
        return f"{META} holds {json.dumps(meta)[:40]}, not an object"
    sums, sizes = meta.get("checksums"), meta.get("sizes")
    if not isinstance(sums, dict) or not all(isinstance(v, str) for v in sums.values()):
        return f"{META} records no checksums"
    if sizes is not None and (not isinstance(sizes, dict) or set(sizes) != set(sums) or not all(
            isinstance(v, int) for v in sizes.values())):
        return f"{META} records sizes of other files than its checksums"
    outside = sorted(str(n) for n in sums if not _plain_name(n))
    if outside:
        return f"{META} names {outside[0]!r}, which is not a file inside the entry"
    files = meta.get("files", [])
    if not isinstance(files, list):
        return f"{META} lists its output files as {json.dumps(files)[:40]}, not a list"
    foreign = [n for n in files if not isinstance(n, str) or n not in sums]
    if foreign:
        return (f"{META} lists the output {str(foreign[0])!r}, which is not one of the entry's "
                "recorded files")
    held = [n for n in ARTIFACT_FILES if n in sums]
    if (meta.get("artifact") or held) and len(held) != len(ARTIFACT_FILES):
        missing = next(n for n in ARTIFACT_FILES if n not in sums)
        return f"{META} records no {missing} (the entry held an artifact)"
    if not sums and "artifact" not in meta:
        return f"{META} records no data files"
    return None


def _unrecorded(d: Path, sums: dict) -> str | None:
    """A data file in the entry that its meta.json does not record (names starting with a
    dot, e.g. NFS's ``.nfs*`` placeholders, and folders are not data files)."""
    try:
        names = sorted(p.name for p in d.iterdir() if not p.name.startswith(".")
                       and p.name != META and (p.is_symlink() or not p.is_dir()))
    except OSError as exc:
        return f"entry unreadable ({exc.strerror or exc})"
    extra = [n for n in names if n not in sums]
    return f"{extra[0]} is not recorded in its {META}" if extra else None


# Entries deep-verified by this process, with the (size, mtime) of every file then: a file
# rewritten since is hashed again.
_VERIFIED: dict[Path, tuple] = {}


def _stamp(d: Path) -> tuple | None:
    try:
        return tuple((p.name, st.st_size, st.st_mtime_ns) for p in sorted(d.iterdir())
                     for st in [p.stat()])
    except OSError:
        return None


def _host() -> str:
    return socket.gethostname().replace("-", "_") or "host"


def owner_token() -> str:
    """``<host>-<pid>`` of this process, for names of work in progress (the host without
    dashes, so the token splits at them)."""
    return f"{_host()}-{os.getpid()}"


def owner_gone(host: str, pid: int) -> bool:
    """Whether the process ``pid`` of ``host`` (as :func:`owner_token` spells it) no longer
    exists; a process of another host is never judged gone (it may be working on a shared
    file system)."""
    return host == _host() and not _alive(pid)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
