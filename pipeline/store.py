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
``meta.json`` is there and every data file matches its recorded checksum
(:meth:`Store.verify`); anything else is reported corrupted and rebuilt, never used.
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

__all__ = ["Store", "CACHE_ENV_VAR", "file_digest"]

CACHE_ENV_VAR = "DERMIS_CACHE"
META = "meta.json"


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
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise DermisError(f"cache entry {path} is unreadable ({exc}); remove it with "
                              f"`dermis clean --cache {self.root}`") from None

    # -- index (last key parts per node, for staleness reasons)
    def read_index(self, node: str) -> dict | None:
        path = self.root / "index" / f"{node}.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return None

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
        sums = meta.get("checksums")
        if not isinstance(sums, dict):
            return f"{META} records no checksums"
        sizes = meta.get("sizes", {})
        for name, digest in sums.items():
            f = d / name
            if not f.is_file():
                return f"{name} is missing"
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
            if host == _host() and pid.isdigit() and _alive(int(pid)):
                continue
            if host != _host() and pid.isdigit():
                continue  # another machine's work in progress
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


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
