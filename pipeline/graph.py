"""Stage graph: nodes, cache keys, staleness reasons, and the make-style executor.

A :class:`Node` is one invocation of a stage: its id (``mesh_low``,
``irradiance-high-point``...), the stage module it runs, the exact slice of the
scene config it reads, and the ids of the upstream nodes it consumes.  Its key is
the hash of

* the stage name, the module's ``VERSION`` and the source text of its in-repository
  import closure and of every kernel that closure builds (:mod:`.codehash`), so
  editing any code a node runs invalidates exactly that node's artifacts;
* the canonical JSON of its config slice (sorted keys);
* the keys of its upstream nodes.

Nothing else (progress, verbosity, output paths, the OpenCL device) enters the
key.  The graph itself is built by :mod:`dermis.pipeline.plan` from what the scene asks
for, so nothing that no requested output needs is ever computed.
"""
from __future__ import annotations

import copy
import functools
import hashlib
import importlib
import json
import threading
import time
import traceback
from contextlib import contextmanager
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any, Callable

from . import artifacts
from .cl import DeviceMemoryError, allocation_failure
from .codehash import closure_hash
from .errors import DermisError
from .reuse import KeyedLocks
from .store import META, Store

__all__ = ["Node", "StageResult", "RunSummary", "node_key", "plan_order", "execute", "staleness"]


@dataclass
class StageResult:
    """What a node's function returns: an artifact, and/or files it wrote into ``out_dir``."""

    artifact: Any = None
    files: list = field(default_factory=list)
    info: dict = field(default_factory=dict)   # JSON-able facts for meta.json


@dataclass
class Node:
    """One stage invocation in the graph.

    ``deps`` maps the role an input plays in the stage (``"mesh"``, ``"maps"``...) to the id
    of the upstream node that provides it (a tuple of ids: each id is its own role).  The
    node runs ``module.run(params, inputs, ctx)`` with ``inputs`` keyed by role, or ``fn``
    (same signature without ``params``) when one is given (toy graphs in the tests).
    """

    id: str
    stage: str                       # stage name, e.g. "mesh_low"
    module: str                      # the stage module, e.g. "dermis.stages.mesh_low"
    params: dict                     # config slice (JSON-able): all the stage reads
    deps: dict | tuple = ()
    fn: Callable[..., StageResult] | None = None
    label: str = ""                  # short human description
    # params that only say WHERE an input file is ("file", "lights[].map"): left out of the
    # key, whose file content enters through a digest param instead (same scene, any spelling)
    locations: tuple = ()
    # further modules the node runs that its stage module reaches by name, not by an import
    # statement (the model a render node looks up in the registry): their import closures
    # enter the key like the stage module's own (docs/software.md "Cache keys")
    code: tuple = ()
    # run-wide intermediates (pipeline/shared.py) this node uses beyond its stage's SHARES
    # (those of the model it renders)
    shares: tuple = ()
    # params that only say how far to go (a time budget): an intact entry of this node whose
    # key parts differ from this one's only in them is handed to the run to continue from
    # (``ctx.resume_from``, :func:`resumable_entry`)
    resumable: tuple = ()

    def __post_init__(self):
        if not isinstance(self.deps, dict):
            self.deps = {d: d for d in self.deps}

    @property
    def dep_ids(self) -> tuple[str, ...]:
        return tuple(self.deps.values())

    def code_hash(self) -> str:
        """Hash of the code this node runs (docs/software.md, "Cache keys")."""
        mod = importlib.import_module(self.module)
        text = f"{getattr(mod, 'VERSION', 0)}:{closure_hash(self.module)}"
        for extra in self.code:
            text += f":{extra}:{closure_hash(extra)}"
        return hashlib.sha256(text.encode()).hexdigest()

    def call(self, inputs: dict, ctx) -> StageResult:
        by_role = {role: inputs[nid] for role, nid in self.deps.items()}
        if self.fn is not None:
            return self.fn(by_role, ctx)
        return importlib.import_module(self.module).run(self.params, by_role, ctx)


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def _without(params, paths) -> Any:
    """``params`` with the dotted ``paths`` removed (``a[].b``: key b of every item of list a)."""
    out = json.loads(_canonical(params))
    for path in paths:
        head, _, rest = path.partition(".")
        if head.endswith("[]"):
            for item in out.get(head[:-2], []):
                if isinstance(item, dict):
                    item.pop(rest, None)
        elif rest:
            if isinstance(out.get(head), dict):
                out[head] = _without(out[head], [rest])
        else:
            out.pop(head, None)
    return out


def key_parts(node: Node, upstream_keys: dict[str, str]) -> dict:
    return {
        "stage": node.stage,
        "code": node.code_hash(),
        "params": _without(node.params, node.locations),
        "deps": {d: upstream_keys[d] for d in node.dep_ids},
    }


def resumable_entry(store: Store, node: Node, parts: dict) -> Path | None:
    """The newest intact entry of ``node`` built from the same code, inputs and params up to
    ``node.resumable`` (a smaller or larger budget of the same work), or None."""
    if not node.resumable:
        return None
    def same_work(p):
        return (isinstance(p, dict) and isinstance(p.get("params"), dict)
                and {**p, "params": _without(p["params"], node.resumable)} == want)
    want = json.loads(_canonical({**parts, "params": _without(parts["params"], node.resumable)}))
    best, newest = None, ""
    folder = store.root / node.id
    for d in (sorted(folder.iterdir()) if folder.is_dir() else []):
        try:
            meta = json.loads((d / META).read_text())
        except (OSError, ValueError):
            continue
        if (not isinstance(meta, dict) or not same_work(meta.get("parts"))
                or store.verify(node.id, d.name) is not None):
            continue
        if str(meta.get("finished", "")) >= newest:
            best, newest = d, str(meta.get("finished", ""))
    return best


def node_key(parts: dict) -> str:
    return hashlib.sha256(_canonical(parts).encode()).hexdigest()[:24]


def plan_order(nodes: dict[str, Node], targets: list[str]) -> list[str]:
    """Topological order of ``targets`` and everything they depend on."""
    order, state = [], {}

    def visit(nid, chain):
        if state.get(nid) == "done":
            return
        if state.get(nid) == "visiting":
            raise RuntimeError("cycle in stage graph: " + " -> ".join(chain + [nid]))
        state[nid] = "visiting"
        for d in nodes[nid].dep_ids:
            visit(d, chain + [nid])
        state[nid] = "done"
        order.append(nid)

    for t in targets:
        visit(t, [])
    return order


def _diff_params(old, new, prefix="") -> list[str]:
    """Dotted keys whose values differ between two JSON-able dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _diff_params(old.get(k), new.get(k), f"{prefix}{k}.")
        return out
    return [] if old == new else [prefix.rstrip(".")]


def staleness(store: Store, node: Node, parts: dict, key: str, stale_deps: set[str]) -> list[str]:
    """Named reasons why ``node`` must run (empty list: it is cached), doit-style."""
    problem = store.verify(node.id, key)
    if problem is None:
        return []
    if problem != "not built":
        return [f"corrupted {problem}"]
    old = store.read_index(node.id)
    if old is None:
        return ["never_built"]
    if old.get("key") == key:
        return ["missing_output"]
    reasons = []
    old_parts = old.get("parts", {})
    if old_parts.get("code") != parts["code"]:
        reasons.append(f"code_changed {node.module} or its kernels")
    for k in _diff_params(old_parts.get("params", {}), parts["params"]):
        reasons.append(f"config_changed {k}")
    changed = [d + (" (stale)" if d in stale_deps else "") for d, k in parts["deps"].items()
               if old_parts.get("deps", {}).get(d) != k]
    if len(changed) > 3:  # e.g. the images node: name a few, count the rest
        reasons.append(f"upstream_changed {len(changed)} nodes ({', '.join(changed[:2])}, ...)")
    else:
        reasons += [f"upstream_changed {d}" for d in changed]
    return reasons or ["missing_output"]


@dataclass
class NodeReport:
    id: str
    stage: str
    status: str            # "ran" | "cached" | "stale" (status only) | "failed"
    seconds: float = 0.0
    kernel_seconds: float = 0.0
    key: str = ""
    reasons: list = field(default_factory=list)
    path: str = ""


@dataclass
class RunSummary:
    nodes: list

    def ran(self) -> list[str]:
        return [n.id for n in self.nodes if n.status == "ran"]

    def cached(self) -> list[str]:
        return [n.id for n in self.nodes if n.status == "cached"]

    def table(self) -> str:
        w = max([len(n.id) for n in self.nodes] + [5])
        lines = [f"{'stage':<{w}}  {'status':<7}  {'seconds':>8}  {'kernel s':>8}"]
        for n in self.nodes:
            ks = f"{n.kernel_seconds:8.2f}" if n.kernel_seconds else f"{'':>8}"
            lines.append(f"{n.id:<{w}}  {n.status:<7}  {n.seconds:8.2f}  {ks}")
        total = sum(n.seconds for n in self.nodes)
        lines.append(f"{'total':<{w}}  {'':<7}  {total:8.2f}")
        return "\n".join(lines)


# "cheapest": a choice made on measured times is a measurement too (reports/requirements.py)
MEASUREMENT_KEYS = frozenset({"timings", "seconds", "kernel_seconds", "wall_seconds",
                              "cheapest", "cheapest_everywhere"})


def _is_measurement(key: str, value) -> bool:
    # "seconds_sampling" (samples stage steps) and rates such as "photons_per_second" (the
    # Monte Carlo profile) are timings too: left in the artifact they made its bytes differ
    # between runs (tests/test_sweep.py: serial and Dask runs give the same bytes)
    return key in MEASUREMENT_KEYS or key.endswith("_seconds") or key.startswith("seconds_") \
        or key.endswith("_per_second") or (
            key.endswith("_s") and isinstance(value, float) and not key.startswith("sigma"))


_LIST = "__list__"     # marks the measurements of a list of dicts (one dict per item)


def _split(d: dict) -> tuple[dict, dict]:
    """(d without its time measurements, the measurements), recursively through dicts and
    lists of dicts (e.g. the seconds of each Monte Carlo run)."""
    kept, measured = {}, {}
    for k, v in d.items():
        if _is_measurement(k, v):
            measured[k] = v
        elif isinstance(v, dict):
            kept[k], sub = _split(v)
            if sub:
                measured[k] = sub
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            pairs = [_split(x) for x in v]
            kept[k] = [a for a, _ in pairs]
            if any(b for _, b in pairs):
                measured[k] = {_LIST: [b for _, b in pairs]}
        else:
            kept[k] = v
    return kept, measured


def _merge(d: dict, measured: dict) -> dict:
    out = dict(d)
    for k, v in measured.items():
        if isinstance(v, dict) and _LIST in v and isinstance(out.get(k), list):
            out[k] = [_merge(x, m) for x, m in zip(out[k], v[_LIST])]
        elif isinstance(v, dict) and isinstance(out.get(k), dict) and k not in MEASUREMENT_KEYS:
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def split_measurements(artifact) -> dict:
    """Move the time measurements out of an artifact's ``info`` / ``timings`` (in place) and
    return them: cached data stays byte-identical between runs; the times go to meta.json."""
    measured = {}
    for name in ("info", "timings"):
        value = getattr(artifact, name, None)
        if isinstance(value, dict):
            if name == "timings":
                kept, sub = {}, dict(value)
            else:
                kept, sub = _split(value)
            setattr(artifact, name, kept)
            if sub:
                measured[name] = sub
    return measured


def restore_measurements(artifact, measured: dict):
    for name, sub in measured.items():
        setattr(artifact, name, _merge(getattr(artifact, name, {}) or {}, sub))
    return artifact


def _load(store: Store, node_id: str, key: str):
    problem = store.verify(node_id, key)
    if problem is not None:  # changed since planning: refuse rather than use it
        raise DermisError(f"cache entry {store.artifact_dir(node_id, key)} is corrupted "
                          f"({problem}); run again to rebuild it")
    d = store.artifact_dir(node_id, key)
    if not (d / "fields.json").is_file():
        return d  # file-only artifacts (images): their directory
    try:
        measured = store.meta(node_id, key).get("measurements", {})
        return restore_measurements(artifacts.load(d), measured if isinstance(measured, dict)
                                    else {})
    except (OSError, ValueError, KeyError, TypeError) as exc:
        # intact by its checksums yet unreadable (e.g. written by an incompatible version)
        store.discard(node_id, key)
        raise DermisError(f"cache entry {d} cannot be read ({type(exc).__name__}: {exc}); it "
                          "was removed: run again to rebuild it") from None


@contextmanager
def _one_blas_thread():
    """Run a node with BLAS/LAPACK on one thread.

    OpenBLAS splits a product over its threads and sums the parts in a thread-count-dependent
    order, so the same node gave different last bits in a process with 2 BLAS threads (dermis
    run) and in a Dask worker (which starts with OMP_NUM_THREADS=1): the profiles' adding-
    doubling differed by 1 ulp and everything downstream with it.  One thread on
    every machine and in every process makes the bytes independent of where a node runs; the
    stages' matrices are small (tens of quadrature nodes), so nothing measurable is lost."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:     # declared in pyproject; without it results may vary in the last bit
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def execute(nodes: dict[str, Node], targets: list[str], store: Store, ctx, *,
            force: tuple[str, ...] = (), dry_run: bool = False, progress=None,
            notice=None, jobs: int = 1) -> RunSummary:
    """Run ``targets`` and their upstream nodes, skipping whatever is cached.

    ``force`` lists stage names (or node ids) to recompute even when cached.
    ``dry_run`` computes keys and staleness only (``dermis status``).
    ``progress(node, fraction)`` is called as nodes advance; ``notice(text)`` gets one-line
    notices (a corrupted cache entry being rebuilt).  ``jobs`` > 1 runs up to that many
    independent nodes at once on threads of this process (:func:`_run_concurrently`); the
    artifacts are the same bytes whatever ``jobs`` is.
    """
    order = plan_order(nodes, targets)
    keys: dict[str, str] = {}
    all_parts: dict[str, dict] = {}
    reports: dict[str, NodeReport] = {}
    stale: set[str] = set()
    todo: list[str] = []
    for nid in order:          # keys follow from the code, the config and upstream keys only
        node = nodes[nid]
        parts = all_parts[nid] = key_parts(node, keys)
        key = keys[nid] = node_key(parts)
        reasons = staleness(store, node, parts, key, stale)
        if node.stage in force or nid in force:
            reasons = ["forced"] + reasons
        reports[nid] = NodeReport(nid, node.stage, "cached", key=key, reasons=reasons,
                                  path=str(store.artifact_dir(nid, key)))
        if not reasons:
            continue
        if reasons[0].startswith("corrupted") and notice:
            notice(f"{nid}: cache entry {reasons[0]}; rebuilding it")
        stale.add(nid)
        todo.append(nid)
        if dry_run:
            reports[nid].status = "stale"
    summary = RunSummary([reports[nid] for nid in order])
    if dry_run or not todo:
        return summary
    runner = _NodeRunner(nodes, keys, all_parts, store, ctx, progress, todo)
    with _one_blas_thread():   # for the whole run: per node, threads would undo each other's
        if jobs <= 1 or len(todo) == 1:
            for nid in todo:
                runner.run(nid, reports[nid])
        else:
            _run_concurrently(runner, todo, reports, int(jobs))
    return summary


class _NodeRunner:
    """Runs one stale node: loads its inputs, calls it, checks and stores its artifact."""

    def __init__(self, nodes, keys, parts, store, ctx, progress, todo):
        self.nodes, self.keys, self.parts, self.store, self.ctx = nodes, keys, parts, store, ctx
        self._progress = progress
        self._loaded: dict[str, Any] = {}
        self._loading = KeyedLocks()            # each cached input read once
        self._lock = threading.Lock()
        # how many stale nodes still read each artifact: at 0 it is dropped from memory (the
        # run's images, visibility and irradiance arrays would otherwise all stay resident)
        self._readers: dict[str, int] = {}
        for nid in todo:
            for d in nodes[nid].dep_ids:
                self._readers[d] = self._readers.get(d, 0) + 1

    def readers_left(self, nid: str) -> int:
        """Stale nodes that still have to read ``nid``'s artifact."""
        with self._lock:
            return self._readers.get(nid, 0)

    def progress(self, node, fraction):
        if self._progress:
            with self._lock:   # the callback (progress bars) need not be thread-safe
                self._progress(node, fraction)

    def input(self, nid: str):
        """The artifact of ``nid``: produced in this run, or loaded once from the store."""
        with self._loading(nid):
            with self._lock:
                if nid in self._loaded:
                    return self._loaded[nid]
            value = _load(self.store, nid, self.keys[nid])
            with self._lock:
                self._loaded[nid] = value
            return value

    def _node_ctx(self, node, out_dir):
        """The run's context for one node: its own output folder and progress callback."""
        ctx = self.ctx.for_node() if hasattr(self.ctx, "for_node") else copy.copy(self.ctx)
        ctx.out_dir = out_dir
        ctx.progress = (lambda f, _n=node: self.progress(_n, f)) if self._progress else None
        if node.fn is None and hasattr(ctx, "shared"):
            # the intermediates the stage declares, keyed by its inputs' cache keys
            ctx.shared = ctx.shared.restricted(
                tuple(getattr(importlib.import_module(node.module), "SHARES", ())) + node.shares)
            ctx.input_keys = {role: self.keys[nid] for role, nid in node.deps.items()}
            if node.resumable:
                ctx.resume_from = resumable_entry(self.store, node, self.parts[node.id])
        return ctx

    def run(self, nid: str, rep: NodeReport) -> None:
        node, key, store = self.nodes[nid], self.keys[nid], self.store
        inputs = {d: self.input(d) for d in node.dep_ids}
        self.progress(node, 0.0)
        t0 = time.perf_counter()
        build0 = self.ctx.build_seconds
        with store.writing(nid, key) as tmp:
            ctx = self._node_ctx(node, tmp)
            try:
                result = node.call(inputs, ctx)
            except DermisError:
                raise
            except Exception as exc:
                cause = _exhaustion(exc) or exc   # out of memory: exit 2, not a traceback
                raise StageFailure(nid, cause, traceback.format_exc()) from cause
            seconds = time.perf_counter() - t0
            if result.artifact is not None:
                bad = artifacts.nonfinite_fields(result.artifact)
                if bad:  # a stage's arrays are finite by contract: never cache NaN or Inf
                    raise StageFailure(nid, ValueError(f"non-finite values in {', '.join(bad)}"),
                                       "")
                measured = split_measurements(result.artifact)
                artifacts.save(result.artifact, tmp)
                restore_measurements(result.artifact, measured)
            info = dict(result.info)
            kernel_s = float(info.pop("kernel_seconds", 0.0) or 0.0)
            if result.artifact is not None and isinstance(getattr(result.artifact, "info", None), dict):
                kernel_s = kernel_s or float(result.artifact.info.get("kernel_seconds", 0.0) or 0.0)
            build_s = self.ctx.build_seconds - build0   # OpenCL program builds: once per process
            meta = {"node": nid, "stage": node.stage, "key": key,
                    "parts": self.parts[nid],
                    "artifact": (type(result.artifact).__name__ if result.artifact is not None
                                 else None),
                    "seconds": seconds, "kernel_seconds": kernel_s, "info": info,
                    "build_seconds": build_s,
                    "measurements": measured if result.artifact is not None else {},
                    "files": [str(f) for f in result.files], "device": ctx.device_description,
                    "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
            (tmp / META).write_text(json.dumps(meta, indent=1, sort_keys=True, default=str))
        store.write_index(nid, {"key": key, "parts": meta["parts"]})
        with self._lock:
            if self._readers.get(nid, 0) > 0:
                self._loaded[nid] = (result.artifact if result.artifact is not None
                                     else store.artifact_dir(nid, key))
            released = 0
            for d in node.dep_ids:
                self._readers[d] -= 1
                if self._readers[d] == 0:
                    released += self._loaded.pop(d, None) is not None
        del inputs, result
        if released:
            _return_free_memory()
        rep.status, rep.seconds, rep.kernel_seconds = "ran", seconds, kernel_s
        rep.path = str(store.artifact_dir(nid, key))
        self.progress(node, 1.0)


def _exhaustion(exc: BaseException) -> MemoryError | None:
    """``exc`` as the MemoryError it stands for, or None: an OpenCL allocation failure
    (:func:`pipeline.cl.allocation_failure`), or a thread that could not start (its stack
    did not fit under the address-space limit, ``ulimit -v``)."""
    if isinstance(exc, MemoryError):
        return None
    if allocation_failure(exc):
        mem = DeviceMemoryError(f"{type(exc).__name__}: {exc}")
    elif isinstance(exc, RuntimeError) and "can't start new thread" in str(exc):
        mem = MemoryError(f"no memory for a new thread ({exc})")
    else:
        return None
    mem.__cause__ = exc
    return mem


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None where the C library is not glibc."""
    import ctypes
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def _return_free_memory() -> None:
    """Give the allocator's free pages back to the system (glibc ``malloc_trim``): with nodes
    on several threads, glibc keeps one heap per thread and the arrays a node freed stay in
    its heap, counted as resident, until trimmed."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _priorities(nodes: dict[str, Node], todo: list[str]) -> dict[str, int]:
    """How many stale nodes wait on each stale node (itself included): the scheduler starts
    the node that unblocks the most work first (on a cold run no node's duration is known)."""
    todo_set = set(todo)
    below: dict[str, set] = {nid: {nid} for nid in todo}
    for nid in todo:                       # todo is topological: upstream first
        for d in nodes[nid].dep_ids:
            if d in todo_set:
                below[d].add(nid)
    for nid in reversed(todo):             # close downwards: each node's dependants' dependants
        for d in nodes[nid].dep_ids:
            if d in todo_set:
                below[d] |= below[nid]
    return {nid: len(s) for nid, s in below.items()}


def _run_concurrently(runner: _NodeRunner, todo: list[str], reports: dict, jobs: int) -> None:
    """Run the stale nodes ``todo`` (topological order) on ``jobs`` threads, each node once
    all its stale inputs are done, the one most work waits on first.  The first failure stops
    new starts; running nodes finish (their entries are complete or discarded by the store)
    and the failure is raised."""
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    nodes = runner.nodes
    position = {nid: i for i, nid in enumerate(todo)}
    priority = _priorities(nodes, todo)
    waiting = {nid: {d for d in nodes[nid].dep_ids if d in position} for nid in todo}
    dependants: dict[str, list] = {nid: [] for nid in todo}
    for nid in todo:
        for d in waiting[nid]:
            dependants[d].append(nid)
    ready = [nid for nid in todo if not waiting[nid]]
    running: dict = {}
    failure: BaseException | None = None
    with ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="dermis-node") as pool:
        while (ready and failure is None) or running:
            while ready and failure is None and len(running) < jobs:
                # among equals, the node whose inputs have the fewest readers left: the nodes
                # reading one artifact (the models of one mesh and light) run together and it
                # leaves memory early (a plan-order tie-break kept every light's rays until
                # the last model: +0.4 GB on the default matrix)
                ready.sort(key=lambda n: (-priority[n], min(
                    (runner.readers_left(d) for d in nodes[n].dep_ids), default=0),
                    position[n]))
                nid = ready.pop(0)
                running[pool.submit(runner.run, nid, reports[nid])] = nid
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                nid = running.pop(fut)
                exc = fut.exception()
                if exc is not None:
                    failure = failure or exc
                    continue
                for other in dependants[nid]:
                    waiting[other].discard(nid)
                    if not waiting[other]:
                        ready.append(other)
    if failure is not None:
        raise failure


class StageFailure(Exception):
    """An unexpected (internal) failure inside a stage: exit code 1, with the traceback."""

    def __init__(self, node_id: str, exc: Exception, tb: str):
        super().__init__(f"stage {node_id} failed: {type(exc).__name__}: {exc}")
        self.node_id, self.tb = node_id, tb
