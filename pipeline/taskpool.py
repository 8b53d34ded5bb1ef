"""Where a node's independent tasks run: in this process, or on Dask workers.

A stage whose work splits into independent, seeded tasks (the reference's tiles,
``groundtruth/progressive.py``) hands them to ``ctx.tasks.map(fn, common, items)``: ``fn(common,
item)`` for every item, results in item order.  ``common`` is what every task reads (a scene
to build): on Dask it is sent to each worker once (``scatter(broadcast=True)``), not with
every task.  The pool never changes a result: a task's output depends on its arguments alone,
and the caller combines the results in item order, so the bytes are the same for any number
of workers (``dermis run --workers N``, ``--scheduler ADDRESS``).
"""
from __future__ import annotations

import contextlib
import time
from typing import Any, Callable, Iterator

from .errors import DermisError

__all__ = ["SerialPool", "DaskPool", "task_pool"]


class SerialPool:
    """Tasks one after another in this process."""

    workers = 1

    def __init__(self):
        self.task_seconds: list[float] = []

    def map(self, fn: Callable, common: Any, items: list) -> list:
        out = []
        for item in items:
            t0 = time.perf_counter()
            out.append(fn(common, item))
            self.task_seconds.append(time.perf_counter() - t0)
        return out

    def each_worker(self, fn: Callable, *args) -> None:
        """``fn(*args)`` in every process that ran tasks (here: this one), e.g. to free what
        the tasks kept."""
        fn(*args)


def _timed(fn, common, item):
    t0 = time.perf_counter()
    result = fn(common, item)
    return result, time.perf_counter() - t0


class DaskPool:
    """Tasks on the workers of a Dask client (a local cluster or a scheduler's)."""

    def __init__(self, client):
        self.client = client
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.task_seconds: list[float] = []

    def map(self, fn: Callable, common: Any, items: list) -> list:
        from distributed.scheduler import KilledWorker
        from .distributed import TASK_RETRIES
        shared = self.client.scatter(common, broadcast=True, hash=False)
        futures = self.client.map(_timed, [fn] * len(items), [shared] * len(items), items,
                                  pure=False, retries=TASK_RETRIES)
        try:
            done = self.client.gather(futures)
        except KilledWorker as exc:
            raise DermisError(f"a task of {getattr(fn, '__name__', fn)} killed its worker "
                              f"{TASK_RETRIES + 1} times ({exc}); finished nodes stay cached: "
                              "use fewer --workers or a smaller scene, and run again") from None
        self.task_seconds += [s for _, s in done]
        return [r for r, _ in done]

    def each_worker(self, fn: Callable, *args) -> None:
        """``fn(*args)`` on every worker, e.g. to free what the tasks kept."""
        self.client.run(fn, *args)


@contextlib.contextmanager
def task_pool(workers: int = 1, scheduler: str | None = None) -> Iterator:
    """A :class:`SerialPool` (one worker, no scheduler), else a :class:`DaskPool` on a local
    cluster of ``workers`` processes or on the scheduler at ``scheduler``; closed on exit."""
    if scheduler is None and workers <= 1:
        yield SerialPool()
        return
    from .distributed import _sigint_deferred, connect, local_cluster
    cluster = None
    if scheduler is None:
        with _sigint_deferred():
            cluster = local_cluster(workers)
    client = connect(scheduler, cluster)
    try:
        yield DaskPool(client)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
