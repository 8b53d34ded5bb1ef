"""Python API mirroring the CLI: ``load_scene``, ``run``, ``status``, ``clean``, ``devices``.

>>> from pipeline.api import load_scene, run            # doctest: +SKIP
>>> summary = run(load_scene("scenes/quick.toml"))       # doctest: +SKIP
>>> print(summary.table())                               # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .config import Scene, load_scene
from .scene_rules import scene_warnings
from .errors import DermisError
from .graph import RunSummary, execute, plan_order
from .imageio import ImageRangeWarning
from .outputs import export as export_outputs, output_folder
from .plan import build_graph
from .registry import STAGE_NAMES
from .shared import RunCache
from .store import CACHE_ENV_VAR, Store
from .taskpool import SerialPool

__all__ = ["load_scene", "run", "status", "clean", "devices", "cache_dir_for", "RunContext",
           "dark_renders"]


@dataclass
class RunContext:
    """What a node function may use besides its inputs: the OpenCL env, its output dir,
    progress, the run's shared intermediates (``shared``: a view restricted to the kinds the
    node's stage declares in ``SHARES``, pipeline/shared.py) and the cache keys of its inputs
    by role (``input_keys``: content keys for what it shares), and for a node with
    ``resumable`` params the earlier entry it may continue (``resume_from``)."""

    device: str | None = None
    out_dir: Path | None = None
    progress: object = None
    shared: RunCache = field(default_factory=RunCache)
    input_keys: dict = field(default_factory=dict)
    resume_from: Path | None = None    # an earlier entry of the node to continue (Node.resumable)
    tasks: Any = field(default_factory=SerialPool)   # where a node's own tasks run (taskpool.py)
    _env: object = None
    _shared: dict = field(default_factory=lambda: {"lock": threading.Lock()}, repr=False)

    def for_node(self) -> "RunContext":
        """A copy for one node (its own out_dir and progress) sharing the run's intermediates
        and the OpenCL environment (nodes may run on several threads at once)."""
        return replace(self, out_dir=None, progress=None, input_keys={}, resume_from=None)

    @property
    def cl(self):
        if self._env is None:
            with self._shared["lock"]:     # one OpenCL context however many nodes ask at once
                if "env" not in self._shared:
                    from .cl import get_env
                    self._shared["env"] = get_env(self.device)
            self._env = self._shared["env"]
        return self._env

    @property
    def build_seconds(self) -> float:
        """Seconds this process has spent building OpenCL programs so far."""
        from .cl import build_seconds
        return build_seconds()

    @property
    def device_description(self) -> str:
        return self._env.description if self._env is not None else "host"


def cache_dir_for(scene: Scene | None, cache: str | os.PathLike | None = None) -> Path:
    """Cache directory: ``cache`` argument > $DERMIS_CACHE > scene output.cache_dir > ./.dermis-cache."""
    chosen = cache or os.environ.get(CACHE_ENV_VAR) or (scene.output.cache_dir if scene else "")
    return Path(chosen or ".dermis-cache")


def _check_stage(name: str, what: str) -> None:
    if name not in STAGE_NAMES:
        import difflib
        close = difflib.get_close_matches(name, STAGE_NAMES, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise DermisError(f"{what} {name!r} is not a stage{hint}; stages: {', '.join(STAGE_NAMES)}")


JOBS_ENV_VAR = "DERMIS_JOBS"
# Nodes run at once by default.  Measured on the 2-core machine, cold default matrix
# (bench/results/pipeline_default.json "jobs_comparison"; 3 jobs: no faster, +0.9 GB):
# docs/software.md "Running nodes at once".
DEFAULT_JOBS = 2


def resolve_jobs(jobs=None) -> int:
    """``jobs`` > $DERMIS_JOBS > DEFAULT_JOBS, checked: a whole number from 1 to 64."""
    source, value = "--jobs", jobs
    if value is None and os.environ.get(JOBS_ENV_VAR):
        source, value = f"${JOBS_ENV_VAR}", os.environ[JOBS_ENV_VAR]
    if value is None:
        return DEFAULT_JOBS
    try:
        n = int(str(value).strip())
    except ValueError:
        n = None
    if n is None or not 1 <= n <= 64 or str(value).strip() != str(n):
        raise DermisError(f"{source} = {value!r}: the number of nodes run at once must be a "
                          f"whole number from 1 to 64")
    return n


def _targets(nodes, targets, until):
    if until is None:
        return targets
    _check_stage(until, "--until")
    chosen = [nid for nid, n in nodes.items() if n.stage == until]
    if not chosen:
        raise DermisError(f"--until {until}: this scene needs no {until} stage; its stages: "
                          + ", ".join(sorted({n.stage for n in nodes.values()})))
    return chosen


def run(scene: Scene, *, cache=None, until: str | None = None, force=(), device: str | None = None,
        progress=None, export: bool = True, notice=None, jobs: int | None = None,
        shared: RunCache | None = None, tasks=None) -> RunSummary:
    """Build everything the scene asks for that is not cached; return the per-stage summary.

    Parameters
    ----------
    scene : Scene
        From :func:`load_scene`.
    cache : path, optional
        Cache directory (see :func:`cache_dir_for`).
    until : str, optional
        Build only what the named stage needs (and that stage).
    force : iterable of str
        Stage names or node ids to recompute even when cached; each must be one this run
        runs (in the scene's graph, and needed for ``until``), else :class:`DermisError`.
    device : str, optional
        OpenCL device spec (see :mod:`pipeline.cl`).
    progress : callable(node, fraction), optional
    notice : callable(str), optional
        One-line notices, e.g. a corrupted cache entry being rebuilt (default: stderr).
    export : bool
        Copy file outputs (previews, images) into ``output_dir/<scene name>/``, replacing
        the previous run's outputs whole (:mod:`pipeline.outputs`).
    jobs : int, optional
        Nodes run at once (threads of this process): the argument > $DERMIS_JOBS >
        :data:`DEFAULT_JOBS`.  Any value gives the same artifacts.
    shared : RunCache, optional
        The intermediates nodes share (Embree scenes, surface passes, octrees...), new for
        each run by default; a process that renders several runs one after another may pass
        one to keep them across runs (keys are content: an equal mesh finds its scene).
    tasks : pipeline.taskpool pool, optional
        Where nodes that split their work into tasks run them (the reference's tiles): this
        process by default, Dask workers with a ``DaskPool`` (``dermis run --workers N``).
        Any pool gives the same artifacts.
    """
    jobs = resolve_jobs(jobs)
    for f in force:
        if f not in STAGE_NAMES and "-" not in f:
            _check_stage(f, "--force")
    nodes, targets = build_graph(scene)
    targets = _targets(nodes, targets, until)
    _check_force(nodes, plan_order(nodes, targets), force, until)
    store = Store(cache_dir_for(scene, cache))
    ctx = RunContext(device=device, shared=RunCache() if shared is None else shared,
                     tasks=SerialPool() if tasks is None else tasks)
    from .cl import check_device
    check_device(device)  # --device or $DERMIS_CL_DEVICE: checked before any stage runs
    if notice is None:
        notice = _stderr_notice
    if export:
        output_folder(scene)  # writable, checked before any stage runs
    warnings = scene_warnings(scene)
    for text in warnings:
        notice(f"warning: {text}")
    with store.locked():
        with _image_warnings(notice) as image_warnings:
            summary = execute(nodes, targets, store, ctx, force=tuple(force),
                              progress=progress, notice=notice, jobs=jobs)
        dark = dark_renders(scene, summary)
        for text in dark:
            notice(f"warning: {text}")
        summary.warnings = warnings + image_warnings + dark
        if export:
            export_outputs(scene, store, summary)
    return summary


def _check_force(nodes: dict, planned: list[str], force, until: str | None) -> None:
    """Refuse ``--force`` of a stage or node this run would not run: not in the scene's graph
    (nothing the scene asks for needs it), or not needed for ``--until``."""
    stages = sorted({n.stage for n in nodes.values()})
    planned_stages = {nodes[nid].stage for nid in planned}
    for f in force:
        is_stage = f in STAGE_NAMES
        if (f not in stages) if is_stage else (f not in nodes):
            what = (f"this scene's graph has no {f} stage: nothing the scene asks for (render."
                    f"models, render.lights, render.geometries, output) needs it; its stages: "
                    + ", ".join(stages)) if is_stage else (
                f"this scene's graph has no node {f!r}; its nodes: " + _some(sorted(nodes)))
            raise DermisError(f"--force {f}: {what}")
        if (f not in planned_stages) if is_stage else (f not in planned):
            raise DermisError(f"--force {f}: --until {until} does not run {f} ({until} does not "
                              f"need it), so it would not be recomputed; the stages --until "
                              f"{until} runs: " + ", ".join(sorted(planned_stages)))


def _some(names: list[str], n: int = 8) -> str:
    return ", ".join(names[:n]) + (f", ... ({len(names) - n} more)" if len(names) > n else "")


@contextmanager
def _image_warnings(notice):
    """Route :class:`ImageRangeWarning` (an EXR holding values float32 cannot represent, from
    any node's thread) to ``notice`` as warnings; yield the list of their texts."""
    texts: list[str] = []
    with warnings.catch_warnings():
        warnings.simplefilter("always", ImageRangeWarning)
        shown = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, ImageRangeWarning):
                texts.append(str(message))
                notice(f"warning: {message}")
            else:
                shown(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield texts


def _stderr_notice(text: str) -> None:
    import sys
    print(f"dermis: {text}", file=sys.stderr)


def dark_renders(scene: Scene, summary: RunSummary) -> list[str]:
    """Warnings for renders that came out entirely black, naming the likely cause."""
    out = []
    cam = scene.camera
    for rep in summary.nodes:     # every node whose artifact is an image, whatever its stage
        if rep.status not in ("ran", "cached"):
            continue
        try:
            meta = json.loads((Path(rep.path) / "meta.json").read_text())
            if not isinstance(meta, dict) or meta.get("artifact") != "RenderedImage":
                continue
            with np.load(Path(rep.path) / "data.npz", allow_pickle=False) as data:
                mask, linear = data["mask"], data["linear"]
        except (OSError, KeyError, ValueError):
            continue
        if not mask.any():
            out.append(f"{rep.id}: the image is black: no camera ray hits the mesh (camera at "
                       f"{list(cam.position)} looking at {list(cam.look_at)}, fov_deg "
                       f"{cam.fov_deg}): the camera looks away from the mesh; check "
                       "camera.position, camera.look_at and mesh.units")
        elif not float(np.max(linear)) > 0.0:
            out.append(f"{rep.id}: the image is black although the camera sees the mesh: the "
                       "light emits nothing (zero intensity or scale) or so little that every "
                       "pixel rounds to 0 in float32, the light is inside the "
                       "mesh or behind the visible surface, or the camera is inside the mesh "
                       "(it sees back faces only); check [[lights]] and camera.position")
    return out


def status(scene: Scene, *, cache=None, until: str | None = None) -> RunSummary:
    """What a run would do: each node cached or stale, with named reasons."""
    nodes, targets = build_graph(scene)
    targets = _targets(nodes, targets, until)
    store = Store(cache_dir_for(scene, cache))
    return execute(nodes, targets, store, RunContext(), dry_run=True)


def clean(*, cache=None, scene: Scene | None = None, stage: str | None = None) -> int:
    """Delete cached artifacts (all, or one stage's); returns how many were removed."""
    if stage is not None:
        _check_stage(stage, "--stage")
    return Store(cache_dir_for(scene, cache)).clean(stage)


def devices():
    """OpenCL platforms and devices (see :func:`pipeline.cl.list_devices`)."""
    from .cl import list_devices
    return list_devices()
