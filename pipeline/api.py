"""Python API mirroring the CLI: ``load_scene``, ``run``, ``status``, ``clean``, ``devices``.

>>> from pipeline.api import load_scene, run            # doctest: +SKIP
>>> summary = run(load_scene("scenes/quick.toml"))       # doctest: +SKIP
>>> print(summary.table())                               # doctest: +SKIP
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from .config import Scene, load_scene
from .errors import DermisError
from .graph import RunSummary, execute
from .plan import build_graph
from .registry import STAGE_NAMES, stage
from .store import CACHE_ENV_VAR, Store

__all__ = ["load_scene", "run", "status", "clean", "devices", "cache_dir_for", "RunContext"]


@dataclass
class RunContext:
    """What a node function may use besides its inputs: the OpenCL env, its output dir, progress."""

    device: str | None = None
    out_dir: Path | None = None
    progress: object = None
    memo: dict = field(default_factory=dict)   # per-run reuse (e.g. Embree scenes per mesh key)
    _env: object = None

    @property
    def cl(self):
        if self._env is None:
            from .cl import get_env
            self._env = get_env(self.device)
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
        progress=None, export: bool = True, notice=None) -> RunSummary:
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
        Stage names or node ids to recompute even when cached.
    device : str, optional
        OpenCL device spec (see :mod:`pipeline.cl`).
    progress : callable(node, fraction), optional
    notice : callable(str), optional
        One-line notices, e.g. a corrupted cache entry being rebuilt (default: stderr).
    export : bool
        Copy file outputs (previews, images) into ``output_dir/<scene name>/``.
    """
    for f in force:
        if f not in STAGE_NAMES and "-" not in f:
            _check_stage(f, "--force")
    nodes, targets = build_graph(scene)
    targets = _targets(nodes, targets, until)
    store = Store(cache_dir_for(scene, cache))
    ctx = RunContext(device=device)
    if device is not None:
        ctx.cl  # an explicit device is checked before any stage runs
    if notice is None:
        notice = _stderr_notice
    with store.locked():
        summary = execute(nodes, targets, store, ctx, force=tuple(force), progress=progress,
                          notice=notice)
        if export:
            _export(scene, store, summary)
    return summary


def _stderr_notice(text: str) -> None:
    import sys
    print(f"dermis: {text}", file=sys.stderr)


def _export(scene: Scene, store: Store, summary: RunSummary) -> Path:
    """Copy file artifacts to ``output_dir/<scene>/<stage>/`` and write run.json beside them."""
    out = Path(scene.output.output_dir) / scene.scene.name
    out.mkdir(parents=True, exist_ok=True)
    for rep in summary.nodes:
        meta = store.meta(rep.id, rep.key)
        folder = (getattr(stage(rep.stage), "OUTPUT_FOLDER", rep.stage)
                  if rep.stage in STAGE_NAMES else rep.stage)
        for name in meta.get("files", []):
            src = Path(rep.path) / name
            if src.is_file():
                (out / folder).mkdir(exist_ok=True)
                shutil.copy2(src, out / folder / name)
    (out / "run.json").write_text(json.dumps({
        "scene": scene.path, "cache": str(store.root),
        "nodes": [{"id": r.id, "status": r.status, "seconds": r.seconds,
                   "kernel_seconds": r.kernel_seconds, "key": r.key, "reasons": r.reasons}
                  for r in summary.nodes]}, indent=1))
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
