"""Run stage graphs as independent tasks on Dask distributed (or serially).

Every node of every graph becomes one Dask task named by its cache key, so a node that several
graphs share (the mesh prep of every sweep point) runs once, and independent nodes (the render
cells of a matrix, the points of a sweep) run in parallel.  Workers share the content-addressed
cache (:class:`~dermis.pipeline.store.Store` allows concurrent writers): each task loads its
inputs from the cache, runs one node and writes its artifact; a task that dies (a killed worker)
is retried and, stages being deterministic, writes the same bytes.

``workers=1`` and no scheduler run the graphs in this process, one after another.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import time
from dataclasses import dataclass, field

from .graph import Node, NodeReport, RunSummary, execute, key_parts, node_key, plan_order
from .errors import DermisError
from .store import Store

__all__ = ["run_graphs", "DistributedStats"]

TASK_RETRIES = 2   # a killed worker's task is resubmitted this many times
# Seconds to reach a ``--scheduler`` before giving up (Dask's own default, 30 s, left a
# mistyped address hanging that long before its OSError).
CONNECT_TIMEOUT_S = 10


@dataclass
class DistributedStats:
    """How a distributed run went: tasks, their durations, and the overhead around them."""

    tasks: int = 0
    ran: int = 0
    wall_seconds: float = 0.0
    task_seconds: list = field(default_factory=list)    # node seconds of the tasks that ran
    workers: int = 1
    critical_path_seconds: float = 0.0   # longest dependency chain of node seconds
    cpu_seconds: float = 0.0             # this process's CPU seconds (serial: all the work)

    @property
    def overhead_per_task(self) -> float:
        """Wall time not explained by the node work, per task, with perfect packing assumed."""
        if not self.tasks:
            return 0.0
        busy = sum(self.task_seconds) / max(self.workers, 1)
        return max(self.wall_seconds - busy, 0.0) / self.tasks

    def to_dict(self) -> dict:
        n = len(self.task_seconds)
        busy = sum(self.task_seconds)
        return {"tasks": self.tasks, "ran": self.ran, "workers": self.workers,
                "wall_seconds": self.wall_seconds,
                "task_seconds_total": busy,
                "mean_task_seconds": busy / n if n else 0.0,
                "overhead_per_task_seconds": self.overhead_per_task,
                "critical_path_seconds": self.critical_path_seconds,
                # the best wall time any number of workers could reach with these task times
                "bound_speedup": (busy / max(self.critical_path_seconds, busy / self.workers)
                                  if busy else 0.0),
                "process_cpu_seconds": self.cpu_seconds}


def _keys(nodes: dict[str, Node], order: list[str]) -> dict[str, str]:
    keys: dict[str, str] = {}
    for nid in order:
        keys[nid] = node_key(key_parts(nodes[nid], keys))
    return keys


def _ancestors(nodes: dict[str, Node], nid: str) -> dict[str, Node]:
    out, todo = {}, [nid]
    while todo:
        n = todo.pop()
        if n not in out:
            out[n] = nodes[n]
            todo.extend(nodes[n].dep_ids)
    return out


def _run_task(nodes: dict[str, Node], nid: str, cache_root: str, device: str | None,
              warm: tuple = (), planned: str | None = None, *_deps_done) -> dict:
    """One Dask task: run node ``nid`` (its inputs are already in the cache).

    ``warm`` names modules imported before the node is timed (first imports of heavy
    libraries are a per-process cost, not the node's)."""
    import importlib
    from .api import RunContext
    for name in (*warm, nodes[nid].module):
        importlib.import_module(name)
    store = Store(cache_root)
    with store.locked():
        summary = execute(nodes, [nid], store, RunContext(device=device))
    rep = next(r for r in summary.nodes if r.id == nid)
    if planned is not None and rep.key != planned:
        # the worker hashed other code than the planner did (sources edited during the run,
        # or a worker with another checkout): its artifact is not the one the sweep reads
        raise DermisError(f"{nid}: cache key planned {planned} but the worker computed "
                          f"{rep.key}: the code it runs differs from the code that planned the "
                          "run (files edited meanwhile, or another checkout); run again")
    return {"id": nid, "key": rep.key, "status": rep.status, "seconds": rep.seconds,
            "kernel_seconds": rep.kernel_seconds, "reasons": rep.reasons, "path": rep.path}


def run_graphs(graphs: list[tuple[dict[str, Node], list[str]]], cache_root, *,
               workers: int = 1, scheduler: str | None = None, device: str | None = None,
               progress=None, warm: tuple = ()) -> tuple[list[RunSummary], DistributedStats]:
    """Build every graph's targets; returns one summary per graph and the run's statistics.

    Parameters
    ----------
    graphs : list of (nodes, targets) from :func:`dermis.pipeline.plan.build_graph`
    cache_root : the shared cache directory
    workers : local worker processes (a Dask LocalCluster when > 1)
    scheduler : address of an existing Dask scheduler (its workers must see ``cache_root``)
    progress : callable(done, running, failed, total), optional
    warm : module names each worker imports before timing a node
    """
    t0, c0 = time.perf_counter(), time.process_time()
    store = Store(cache_root)
    plans = []
    tasks: dict[str, tuple] = {}          # task name -> (nodes subgraph, node id, dep task names)
    for nodes, targets in graphs:
        order = plan_order(nodes, targets)
        keys = _keys(nodes, order)
        plans.append((nodes, order, keys))
        for nid in order:
            name = f"{nid}-{keys[nid]}"
            if name not in tasks:
                deps = tuple(f"{d}-{keys[d]}" for d in nodes[nid].dep_ids)
                tasks[name] = (_ancestors(nodes, nid), nid, deps)
    stats = DistributedStats(tasks=len(tasks), workers=max(workers, 1))
    if scheduler is None and workers <= 1:
        results = _run_serial(tasks, str(store.root), device, progress, warm)
    else:
        results = _run_dask(tasks, str(store.root), device, workers, scheduler, progress, warm)
    stats.wall_seconds = time.perf_counter() - t0
    stats.cpu_seconds = time.process_time() - c0
    finish: dict[str, float] = {}
    for name, (_, _, deps) in tasks.items():       # topological order
        finish[name] = results[name]["seconds"] * (results[name]["status"] == "ran") + max(
            (finish[d] for d in deps), default=0.0)
    stats.critical_path_seconds = max(finish.values(), default=0.0)
    stats.ran = sum(1 for r in results.values() if r["status"] == "ran")
    stats.task_seconds = [r["seconds"] for r in results.values() if r["status"] == "ran"]
    summaries = []
    for nodes, order, keys in plans:
        reps = []
        for nid in order:
            r = results[f"{nid}-{keys[nid]}"]
            reps.append(NodeReport(nid, nodes[nid].stage, r["status"], r["seconds"],
                                   r["kernel_seconds"], keys[nid], r["reasons"], r["path"]))
        summaries.append(RunSummary(reps))
    return summaries, stats


def _run_serial(tasks, cache_root, device, progress, warm) -> dict:
    results, done = {}, 0
    for name, (sub, nid, _) in tasks.items():      # insertion order is topological
        results[name] = _run_task(sub, nid, cache_root, device, warm, name.rsplit("-", 1)[1])
        done += 1
        if progress:
            progress(done, 0, 0, len(tasks))
    return results


# Thread pools a node's libraries start, each told its share of the cores through the worker
# process's environment: OpenMP (open3d's ray casting), OpenBLAS/MKL, and PoCL's pthread
# device (its compute units).  Dask's nanny starts workers with OMP_NUM_THREADS=1
# (distributed.nanny.pre-spawn-environ): a 1-worker cluster then cast rays on one core and
# took 46.5 s where the serial run took 24.6 s (bench/results/sweep_dask.json rerun_quiet).
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
              "POCL_MAX_PTHREAD_COUNT")


# The nanny also sets MALLOC_TRIM_THRESHOLD_=65536 (to hand freed memory back to the system
# early); setting it at all switches off glibc's adaptive mmap threshold, so every large numpy
# array is a fresh mmap and page faults: node work ran ~1.5x slower in a worker than in the
# serial process (bench/results/sweep_dask.json).  Unset for local clusters.
UNSET_ENV = ("MALLOC_TRIM_THRESHOLD_",)


def worker_environment(threads: int) -> dict[str, str]:
    """Environment of a worker process that may use ``threads`` cores."""
    return {name: str(int(threads)) for name in THREAD_ENV}


def local_cluster(workers: int, threads: int | None = None):
    """A Dask LocalCluster of ``workers`` processes, one task at a time each, every worker's
    libraries sized to ``threads`` cores (default: this machine's cores / workers, >= 1), so
    that the workers share the cores instead of oversubscribing or idling them; and glibc's
    allocator left as in a plain process (the nanny's MALLOC_TRIM_THRESHOLD_ unset, see
    UNSET_ENV)."""
    import dask
    from dask.distributed import LocalCluster
    if threads is None:
        threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    unset = {f"distributed.nanny.pre-spawn-environ.{k}": None for k in UNSET_ENV}
    # The nannies run in this process and write their pre-spawn variables into os.environ,
    # which the workers inherit (and any later cluster's workers too): keep UNSET_ENV out of
    # it while they spawn and give this process its own environment back afterwards.
    saved = dict(os.environ)
    for k in UNSET_ENV:
        os.environ.pop(k, None)
    try:
        with dask.config.set(unset):       # read when the nannies are made, below
            return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                dashboard_address=None, env=worker_environment(threads),
                                preload=[__name__])   # dask_setup: Ctrl-C left to this process
    finally:
        for k in set(os.environ) | set(saved):     # only what changed
            if k not in saved:
                del os.environ[k]
            elif os.environ.get(k) != saved[k]:
                os.environ[k] = saved[k]


def dask_setup(worker) -> None:
    """Preload of the local workers (``local_cluster``): Ctrl-C is the submitting process's
    to handle (it closes the cluster); a worker process interrupted on its own printed its own
    traceback over the message.  The worker state machine's one warning, a running task
    cancelled, is logged only while the worker closes (distributed/worker_state_machine.py
    ``_finish_async_instruction``): after an interrupt or a failure reported anyway."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("distributed.worker.state_machine").setLevel(logging.ERROR)


def connect(scheduler: str | None, cluster=None):
    """A Dask client of ``scheduler`` (an address) or of a local ``cluster``; an address that
    is malformed or answers nothing within :data:`CONNECT_TIMEOUT_S` is a :class:`DermisError`
    naming it."""
    from dask.distributed import Client
    if scheduler is None:
        return Client(cluster)
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S)
    except ValueError as exc:     # distributed's address parser
        raise DermisError(f"--scheduler {scheduler!r}: not a Dask scheduler address ({exc}); "
                          "give one as tcp://HOST:PORT, or leave --scheduler out to run local "
                          "workers") from None
    except OSError as exc:        # refused, unreachable, or timed out
        raise DermisError(f"--scheduler {scheduler!r}: no Dask scheduler answered within "
                          f"{CONNECT_TIMEOUT_S} s ({exc}); start one (dask scheduler) and its "
                          "workers, or leave --scheduler out to run local workers") from None


def _killed(exc) -> DermisError:
    """The message of a task whose worker process died every time it ran it."""
    task = getattr(exc, "task", "?")
    worker = getattr(getattr(exc, "last_worker", None), "address", None) or "?"
    tries = getattr(exc, "allowed_failures", 0) + 1
    return DermisError(f"node {str(task).rsplit('-', 1)[0]}: the worker process running it "
                       f"died {tries} times (last on {worker}), killed from outside or out of "
                       "memory; finished nodes stay cached: lower the scene's memory needs "
                       "(camera size, bake.resolution, bssrdf.point_density) or use fewer "
                       "--workers, and run again")


@contextlib.contextmanager
def _sigint_deferred():
    """Hold Ctrl-C back while a local cluster starts: delivered (as KeyboardInterrupt) once
    the cluster exists and can be closed.  Interrupted mid-start, a cluster was left half
    made (its exit handler's traceback) and worker processes still importing printed theirs.
    A signal blocked here stays blocked in the processes (and the event-loop thread)
    started meanwhile, so the workers leave Ctrl-C to this process from their first
    instruction (:func:`dask_setup` covers workers started later)."""
    if not hasattr(signal, "pthread_sigmask"):     # not POSIX: nothing to hold back
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def _quiet_dask(quiet: bool):
    """With ``quiet``, silence distributed's loggers in this process (its scheduler, nannies
    and client) for the block, then restore them: closing a cluster whose tasks were
    interrupted or lost logs the cancelled tasks' tracebacks over the message."""
    log = logging.getLogger("distributed")
    level = log.level
    if quiet:
        log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        log.setLevel(level)


def _run_dask(tasks, cache_root, device, workers, scheduler, progress, warm) -> dict:
    from dask.distributed import as_completed
    from distributed.scheduler import KilledWorker

    cluster = client = None
    quiet = False       # closing after an interrupt or a lost worker: no log tracebacks
    try:
        if scheduler is None:
            with _sigint_deferred():
                cluster = local_cluster(workers)
        client = connect(scheduler, cluster)
        futures = {}
        for name, (sub, nid, deps) in tasks.items():   # topological: deps submitted first
            futures[name] = client.submit(_run_task, sub, nid, cache_root, device, warm,
                                          name.rsplit("-", 1)[1],
                                          *(futures[d] for d in deps), key=name,
                                          retries=TASK_RETRIES, pure=False)
        results, failed = {}, 0
        for fut in as_completed(list(futures.values())):
            try:
                results[fut.key] = fut.result()
            except KilledWorker as exc:
                failed += 1
                quiet = True
                raise _killed(exc) from None
            except Exception:
                failed += 1
                raise
            finally:
                if progress:
                    progress(len(results), len(futures) - len(results) - failed, failed,
                             len(futures))
        return results
    except KeyboardInterrupt:
        quiet = True
        raise
    finally:
        with _quiet_dask(quiet):
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
