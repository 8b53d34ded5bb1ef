"""Running Cycles render processes from the pipeline (:mod:`dermis.cycles.render_job`).

The job's description and arrays go to a temporary folder, a render process of the same
interpreter (where ``bpy`` is installed, :mod:`dermis.cycles.availability`) renders them and
this module reads the result back.  Blender's console output is kept in the folder and
quoted when the job fails.  Two ways:

* ``run_job(job, arrays)``: a process of its own, ``python -m dermis.cycles.render_job
  FOLDER`` (the slab measurements: each starts from an empty Blender anyway);
* ``run_job(job, arrays, serve=True)``: the job goes to a serving process (``--serve``),
  one per thread count, started at the first such job and kept while jobs come (it exits
  after ``IDLE_S`` seconds without one); it keeps the head mesh and its BVH between jobs of
  the same mesh, so a head's images after the first skip Blender's start (~2 s), the mesh
  build (~10 s on the 1.1M-triangle scan) and the BVH (~2 s) (docs/cycles.md "Cost").
  Jobs go to it one at a time (a lock): each renders on all its threads.
"""
from __future__ import annotations

import atexit
import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dermis.pipeline.errors import DermisError

__all__ = ["run_job", "close_servers", "IDLE_S"]

RENDER_PROCESS = "dermis.cycles.render_job"
IDLE_S = 60.0   # a serving process exits after this long without a job (its memory freed)


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


def _env(threads: int) -> dict:
    return {**os.environ, "PYTHONPATH": _pythonpath(), "OMP_NUM_THREADS": str(threads)}


def _failure(folder: Path, returncode) -> DermisError:
    tail = ""
    if (folder / "blender.log").is_file():
        tail = (folder / "blender.log").read_text(errors="replace")[-3000:]
    if (folder / "error.txt").is_file():
        tail += "\n" + (folder / "error.txt").read_text(errors="replace")[-3000:]
    return DermisError(f"cycles: the Blender render process failed (exit {returncode}); its "
                       f"output ends:\n{tail}")


class _Server:
    """A serving render process (``render_job --serve``): jobs by folder name on its stdin,
    each one's folder name back on a pipe of its own when done."""

    def __init__(self, threads: int):
        self.cwd = tempfile.mkdtemp(prefix="dermis-cycles-serve-")
        self.log = open(Path(self.cwd) / "serve.log", "wb")    # its output outside jobs
        r, w = os.pipe()
        # run in a folder of its own: see run_job on dermis's ``cycles`` package
        self.proc = subprocess.Popen(
            [sys.executable, "-m", RENDER_PROCESS, "--serve", str(w), str(IDLE_S)],
            stdin=subprocess.PIPE, stdout=self.log, stderr=subprocess.STDOUT,
            env=_env(threads), cwd=self.cwd, pass_fds=(w,), text=True,
            preexec_fn=_parent_death_signal())
        os.close(w)
        self.done = os.fdopen(r, "r")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def render(self, folder: Path) -> bool:
        """Run the job in ``folder``; False when the process ended before taking it."""
        try:
            self.proc.stdin.write(f"{folder}\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            return False
        line = self.done.readline()
        if not line:
            self.proc.wait()
            if not (folder / "blender.log").is_file():
                return False     # it had exited (idle) before reading the job
            raise _failure(folder, self.proc.returncode)
        return True

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self.done.close()
        self.log.close()
        shutil.rmtree(self.cwd, ignore_errors=True)


_SERVERS: dict = {}
_LOCK = threading.Lock()


def close_servers() -> None:
    """End every serving process (they also end by themselves when idle, or with this
    process)."""
    with _LOCK:
        for s in _SERVERS.values():
            s.close()
        _SERVERS.clear()


atexit.register(close_servers)


def _serve(folder: Path, threads: int) -> float:
    """Run the job in ``folder`` on the serving process of ``threads`` (started if none);
    returns its seconds, from when the process was free for it (another job's wait left
    out)."""
    with _LOCK:
        t0 = time.perf_counter()
        for _ in range(2):
            server = _SERVERS.get(threads)
            if server is None or not server.alive():
                if server is not None:
                    server.close()
                server = _SERVERS[threads] = _Server(threads)
            if server.render(folder):
                return time.perf_counter() - t0
            tail = (Path(server.cwd) / "serve.log").read_text(errors="replace")[-3000:]
            server.close()
            del _SERVERS[threads]
        raise DermisError(f"cycles: the Blender render process ended before taking a job; "
                          f"its output ends:\n{tail}")


def run_job(job: dict, arrays: dict | None = None, *, serve: bool = False
            ) -> tuple[dict, dict]:
    """Render ``job`` (``kind`` "head" or "slab") in a Blender process (``serve``: on the
    serving one, module docstring); returns the result's JSON facts (``wall_seconds`` added:
    the job's time here, a new process's start included, and ``startup_seconds``: the part
    outside the job's own work) and its arrays."""
    folder = Path(tempfile.mkdtemp(prefix="dermis-cycles-"))
    try:
        (folder / "job.json").write_text(json.dumps(job))
        if arrays:
            np.savez(folder / "arrays.npz", **{k: v for k, v in arrays.items() if v is not None})
        threads = int(job.get("threads", 1))
        t0 = time.perf_counter()
        returncode = None
        if serve:
            wall = _serve(folder, threads)
        else:
            # run in the job's folder: ``python -m`` puts the working directory first on the
            # path, and from dermis's own folder its ``cycles`` package would hide Blender's
            # ``cycles`` add-on (Blender then has no Cycles engine)
            with open(folder / "blender.log", "wb") as log:
                proc = subprocess.run([sys.executable, "-m", RENDER_PROCESS, str(folder)],
                                      stdout=log, stderr=subprocess.STDOUT, env=_env(threads),
                                      cwd=folder, preexec_fn=_parent_death_signal())
            returncode = proc.returncode
            wall = time.perf_counter() - t0
        if returncode not in (None, 0) or not (folder / "result.json").is_file():
            raise _failure(folder, returncode)
        result = json.loads((folder / "result.json").read_text())
        result["wall_seconds"] = wall
        # Blender's start (a new process's), the arrays' way there and back
        result["startup_seconds"] = max(wall - result.get("process_seconds", 0.0), 0.0)
        with np.load(folder / "result.npz") as z:
            out = {k: z[k] for k in z.files}
        return result, out
    finally:
        shutil.rmtree(folder, ignore_errors=True)
