"""Artifact store: one directory per (node, key), atomic writes, a lock per cache.

Layout of a cache directory::

    .lock                        held (flock) by the running dermis process
    <node>/<key>/                one finished artifact: data files + meta.json (written last)
    index/<node>.json            the key parts of the node's newest artifact (for `status`)
    .tmp/<uuid>/                 work in progress; renamed into place when complete

An artifact directory is created by renaming a complete temporary directory, so
a run killed mid-stage leaves only ``.tmp`` debris, which is never trusted and is
removed by the next run.  ``meta.json`` is the validity marker.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
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

    # -- writing
    @contextmanager
    def writing(self, node: str, key: str):
        """Yield a temporary directory; on success it becomes the artifact directory."""
        tmp = self.root / ".tmp" / uuid.uuid4().hex
        tmp.mkdir(parents=True)
        try:
            yield tmp
            if not (tmp / META).is_file():
                raise RuntimeError(f"stage wrote no {META} for {node}")
            final = self.artifact_dir(node, key)
            final.parent.mkdir(parents=True, exist_ok=True)
            if final.exists():  # same key computed again (forced): replace it
                shutil.rmtree(final)
            os.replace(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    @staticmethod
    def _atomic_write_text(path: Path, text: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}")
        tmp.write_text(text)
        os.replace(tmp, path)

    # -- housekeeping
    @contextmanager
    def locked(self):
        """Hold the cache's lock; a second process gets :class:`CacheLockedError` at once."""
        self.root.mkdir(parents=True, exist_ok=True)
        lock_path = self.root / ".lock"
        fh = open(lock_path, "a+")
        try:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                fh.seek(0)
                holder = fh.read().strip() or "unknown"
                raise CacheLockedError(
                    f"cache {self.root} is in use by another dermis process (pid {holder}); "
                    f"wait for it to finish or choose another cache with --cache DIR") from None
            fh.seek(0)
            fh.truncate()
            fh.write(str(os.getpid()))
            fh.flush()
            shutil.rmtree(self.root / ".tmp", ignore_errors=True)  # debris of killed runs
            yield self
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
            fh.close()

    def clean(self, node_prefix: str | None = None) -> int:
        """Remove all artifacts (or those of one stage: node ``stage`` or ``stage-*``); count removed."""
        if not self.root.is_dir():
            return 0
        removed = 0
        with self.locked():
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
