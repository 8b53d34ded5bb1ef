"""Running a Cycles render process from the pipeline (:mod:`dermis.cycles.render_job`).

The job's description and arrays go to a temporary folder, ``python -m
dermis.cycles.render_job FOLDER`` renders them with the same interpreter (where ``bpy`` is
installed, :mod:`dermis.cycles.availability`) and this module reads the result back.
Blender's console output is kept in the folder and quoted when the process fails.
"""
from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import DermisError

__all__ = ["run_job"]


def _pythonpath() -> str:
    """The folder that makes ``import dermis`` load this package, first on the path."""
    import dermis
    root = str(Path(dermis.__file__).resolve().parent.parent)
    rest = os.environ.get("PYTHONPATH", "")
    return root + (os.pathsep + rest if rest else "")


def _parent_death_signal():
    """A function for the child to call between fork and exec (no imports, no locks): on
    Linux, have the kernel send it SIGTERM when the pipeline's process dies, so that a killed
    run leaves no Blender rendering on; None elsewhere."""
    if sys.platform != "linux":
        return None
    try:
        prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
    except OSError:
        return None
    return lambda: prctl(1, int(signal.SIGTERM))   # PR_SET_PDEATHSIG


def run_job(job: dict, arrays: dict | None = None) -> tuple[dict, dict]:
    """Render ``job`` (``kind`` "head" or "slab") in a Blender process; returns the result's
    JSON facts (``wall_seconds`` added: the whole process, Blender's start included) and its
    arrays."""
    folder = Path(tempfile.mkdtemp(prefix="dermis-cycles-"))
    try:
        (folder / "job.json").write_text(json.dumps(job))
        if arrays:
            np.savez(folder / "arrays.npz", **{k: v for k, v in arrays.items() if v is not None})
        env = {**os.environ, "PYTHONPATH": _pythonpath(),
               "OMP_NUM_THREADS": str(job.get("threads", 1))}
        t0 = time.perf_counter()
        # run in the job's folder: ``python -m`` puts the working directory first on the
        # path, and from dermis's own folder its ``cycles`` package would hide Blender's
        # ``cycles`` add-on (Blender then has no Cycles engine)
        with open(folder / "blender.log", "wb") as log:
            proc = subprocess.run([sys.executable, "-m", "dermis.cycles.render_job", str(folder)],
                                  stdout=log, stderr=subprocess.STDOUT, env=env, cwd=folder,
                                  preexec_fn=_parent_death_signal())
        wall = time.perf_counter() - t0
        if proc.returncode != 0 or not (folder / "result.json").is_file():
            tail = (folder / "blender.log").read_text(errors="replace")[-3000:]
            raise DermisError(f"cycles: the Blender render process failed (exit "
                              f"{proc.returncode}); its output ends:\n{tail}")
        result = json.loads((folder / "result.json").read_text())
        result["wall_seconds"] = wall
        with np.load(folder / "result.npz") as z:
            out = {k: z[k] for k in z.files}
        return result, out
    finally:
        shutil.rmtree(folder, ignore_errors=True)
