"""Intermediates the nodes of one run share, declared and keyed by content.

Several nodes of a run need the same expensive intermediate: every image of a mesh casts
its shadow rays on one Embree scene, the ~20 images of a geometry shade one surface pass,
the low mesh's two bump variants gather over one octree.  Each such intermediate is a
:class:`Shared` *kind*, declared once as a module constant next to the code that makes it
(``EMBREE_SCENES = Shared("embree_scene", keep=2)``).  A stage lists the kinds its node
uses in ``SHARES``; at run time ``ctx.shared`` is a :class:`RunCache` view that hands out
only those kinds (asking for an undeclared kind is a programming error, raised at once).

Keys are content, never object identity: plain values (str, int, float, bool, None, bytes)
and tuples of them, typically :func:`content_key` digests of arrays or the cache keys of
the artifacts an intermediate is made from.  The cache is thread-safe: when two nodes
running at once ask for a missing key, one makes it and the other waits for the result
(no iteration over a dict that other threads write).  Everything is dropped when the run
ends (docs/software.md "Running nodes at once").
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Hashable, TypeVar

from .reuse import RecentResults

__all__ = ["Shared", "RunCache", "check_key"]

T = TypeVar("T")
_PLAIN = (str, int, float, bool, bytes, type(None))


@dataclass(frozen=True)
class Shared:
    """One kind of run-wide intermediate.

    ``name`` identifies it (unique in the package); ``keep`` is how many of its values a run
    holds (the most recently used ones; 0 = all of them until the run ends)."""

    name: str
    keep: int = 0


def check_key(key: Hashable) -> None:
    """Refuse keys that are not plain content (an object's id or the object itself would
    tie the value to one Python object rather than to what it holds)."""
    if isinstance(key, tuple):
        for part in key:
            check_key(part)
    elif not isinstance(key, _PLAIN):
        raise TypeError(f"shared-result keys are plain values or tuples of them, not "
                        f"{type(key).__name__}: {key!r:.80}")


class RunCache:
    """A run's shared intermediates, by kind and content key (thread-safe)."""

    def __init__(self, allowed: frozenset | None = None, _stores: dict | None = None,
                 _lock: threading.Lock | None = None):
        self._allowed = allowed                       # None: every kind (library use, tests)
        self._stores = {} if _stores is None else _stores
        self._lock = threading.Lock() if _lock is None else _lock

    def restricted(self, kinds) -> "RunCache":
        """A view of the same store that hands out only ``kinds`` (a node's declared SHARES)."""
        return RunCache(frozenset(k.name for k in kinds), self._stores, self._lock)

    def _store(self, kind: Shared) -> RecentResults:
        if not isinstance(kind, Shared):
            raise TypeError(f"a shared kind is a Shared, not {type(kind).__name__}")
        if self._allowed is not None and kind.name not in self._allowed:
            raise LookupError(f"shared kind {kind.name!r} is not declared in the node's "
                              f"SHARES ({', '.join(sorted(self._allowed)) or 'none'})")
        with self._lock:
            store = self._stores.get(kind.name)
            if store is None:
                store = self._stores[kind.name] = RecentResults(kind.keep or (1 << 62))
            return store

    def get(self, kind: Shared, key: Hashable, make: Callable[[], T]) -> T:
        """The value of ``kind`` under ``key``, made by ``make()`` once per run."""
        return self.get_made(kind, key, make)[0]

    def get_made(self, kind: Shared, key: Hashable, make: Callable[[], T]) -> tuple[T, bool]:
        """(value, made): as :meth:`get`; ``made`` says whether this call computed it (what
        the making measured, e.g. kernel seconds, belongs to this caller only then)."""
        check_key(key)
        made = []

        def making():
            made.append(True)
            return make()
        return self._store(kind).get(key, making), bool(made)
