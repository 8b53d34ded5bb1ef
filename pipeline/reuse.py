"""Results kept by the content of their inputs: :func:`content_key` (a digest of arrays and
plain values; hashing the 1.13M-triangle mesh takes ~30 ms), :class:`RecentResults` (the
last few results of one computation, thread-safe), :class:`KeyedLocks`, and
:func:`built_once` (an object's lazily built attribute, built by one thread).  A run's shared
intermediates (pipeline/shared.py) and a few pure functions' tables (the gather's profile
tables, subsurface/gather.py) are kept in them.
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from contextlib import contextmanager

import numpy as np

__all__ = ["content_key", "RecentResults", "KeyedLocks", "built_once"]

# Held while an attribute of :func:`built_once` is built; re-entrant, since one build may ask
# for another (an environment map's control table needs its product tables).
_BUILDING = threading.RLock()
_MISSING = object()


def built_once(owner, attr: str, build):
    """``owner.<attr>``, made by ``build()`` and kept on ``owner`` the first time any thread
    asks; threads asking meanwhile wait for it (an environment map's sampling tables take
    ~0.5 GB while built: the render and the irradiance nodes of a run building them at once
    doubled its peak, pipeline/resources.py).  ``build()`` may return None: that is kept too."""
    value = getattr(owner, attr, _MISSING)
    if value is not _MISSING:
        return value
    with _BUILDING:
        value = getattr(owner, attr, _MISSING)
        if value is _MISSING:
            value = build()
            setattr(owner, attr, value)
        return value


def content_key(*parts) -> str:
    """Digest of arrays (dtype, shape and bytes) and plain values (their repr)."""
    h = hashlib.blake2b(digest_size=16)
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.view(np.uint8).reshape(-1).data if a.size else b"")
        else:
            h.update(repr(p).encode())
        h.update(b"|")
    return h.hexdigest()


class KeyedLocks:
    """One lock per key, held with ``with locks(key):`` -- threads asking for the same key
    wait for each other, other keys go on; a key's lock is dropped by its last holder."""

    def __init__(self):
        self._locks: dict = {}          # key -> [lock, holders]
        self._guard = threading.Lock()

    @contextmanager
    def __call__(self, key):
        with self._guard:
            entry = self._locks.setdefault(key, [threading.Lock(), 0])
            entry[1] += 1
        try:
            with entry[0]:
                yield
        finally:
            with self._guard:
                entry[1] -= 1
                if entry[1] == 0:
                    del self._locks[key]


class RecentResults:
    """The ``size`` most recently used results of one computation, by key (thread-safe: when
    several threads ask for a missing key at once, one computes it and the others wait)."""

    def __init__(self, size: int):
        self.size = int(size)
        self._items: OrderedDict = OrderedDict()
        self._making = KeyedLocks()
        self._lock = threading.Lock()

    def _stored(self, key):
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return True, self._items[key]
        return False, None

    def get(self, key, make):
        """The result stored under ``key``, else ``make()`` stored under it."""
        found, value = self._stored(key)
        if found:
            return value
        with self._making(key):
            found, value = self._stored(key)    # made by another thread meanwhile
            if found:
                return value
            value = make()
            with self._lock:
                self._items[key] = value
                while len(self._items) > self.size:
                    self._items.popitem(last=False)
            return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
