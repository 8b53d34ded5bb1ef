"""Time the ``samples`` and ``bake`` nodes of the default scene alone, before and after a change.

The upstream nodes (mesh_source, mesh_high, mesh_low) are built once into a cache and reused
(warm upstream); each timed node then runs in its own subprocess, as the engine runs it (BLAS
on one thread), once with the stage module of a git ref (``--baseline-ref``, default HEAD) and
once with the working tree's.  Per node and version: wall and CPU seconds (all threads), the
load average before and after (the machine may be shared), the stage's own step timings, and
whether the artifacts' arrays are byte-identical (else their max and RMS difference).

    python3 bench/bench_stages.py [--cache DIR] [--out bench/results/stage_speed.json]
        [--baseline-ref HEAD] [--nodes bake,samples-mesh_high,samples-mesh_low] [--no-baseline]
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NODES = ("samples-mesh_high", "samples-mesh_low", "bake")
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "dermis-bench-stages"


def _graph(cache: Path):
    """Nodes, keys and store of the default scene, with the upstream of NODES built."""
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    from dermis.pipeline.graph import key_parts, node_key, plan_order
    from dermis.pipeline.plan import build_graph
    from dermis.pipeline.store import Store
    scene = load_scene(None)
    api.run(scene, cache=cache, until="mesh_low", export=False)
    nodes, _ = build_graph(scene)
    keys: dict[str, str] = {}
    for nid in plan_order(nodes, list(NODES)):
        keys[nid] = node_key(key_parts(nodes[nid], keys))
    return nodes, keys, Store(cache)


def _stage_module(name: str, ref: str | None):
    """The stage module from the working tree (ref None) or from git at ``ref``."""
    if ref is None:
        return importlib.import_module(f"dermis.stages.{name}")
    src = subprocess.run(["git", "show", f"{ref}:stages/{name}.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / f"{name}_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"{name}_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _child(cache: Path, nid: str, ref: str | None, arrays_out: Path) -> dict:
    """Run one node once; return its timings and save its arrays to ``arrays_out``."""
    import importlib
    for preloaded in ("open3d", "scipy.sparse", "scipy.spatial"):
        importlib.import_module(preloaded)   # import cost is not the node's: the engine has it
    from dermis.pipeline.api import RunContext
    from dermis.pipeline.graph import _load, _one_blas_thread
    nodes, keys, store = _graph(cache)
    node = nodes[nid]
    inputs = {role: _load(store, dep, keys[dep]) for role, dep in node.deps.items()}
    mod = _stage_module(node.stage, ref)
    load_before = os.getloadavg()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    with _one_blas_thread():
        result = mod.run(node.params, inputs, RunContext())
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    art = result.artifact
    arrays = {f.name: getattr(art, f.name) for f in dataclasses.fields(art)
              if isinstance(getattr(art, f.name), np.ndarray)}
    np.savez(arrays_out, **arrays)
    info = art.info
    steps = info.get("timings") or {k: v for k, v in info.items() if k.startswith("seconds")}
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
            "loadavg_before": [round(x, 2) for x in load_before],
            "loadavg_after": [round(x, 2) for x in os.getloadavg()],
            "steps_s": {k: round(float(v), 3) for k, v in steps.items()}}


def _compare(a_path: Path, b_path: Path) -> dict:
    """Byte-identical, or per array the max and RMS difference."""
    a, b = np.load(a_path), np.load(b_path)
    out = {}
    for name in a.files:
        x, y = a[name], b[name]
        if x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes():
            out[name] = "identical"
        elif x.shape != y.shape:
            out[name] = f"shape {x.shape} vs {y.shape}"
        else:
            d = x.astype(np.float64) - y.astype(np.float64)
            out[name] = {"max_abs": float(np.abs(d).max()), "rms": float(np.sqrt((d * d).mean()))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(DEFAULT_CACHE))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "stage_speed.json"))
    ap.add_argument("--baseline-ref", default="HEAD")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--nodes", default=",".join(NODES))
    ap.add_argument("--child", nargs=3, metavar=("NODE", "REF", "NPZ"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cache = Path(args.cache)
    if args.child:
        nid, ref, npz = args.child
        print(json.dumps(_child(cache, nid, None if ref == "-" else ref, Path(npz))))
        return 0

    _graph(cache)  # build the upstream once, outside the timed runs
    work = Path(tempfile.mkdtemp(prefix="bench-stages-"))
    versions = ([("before", args.baseline_ref)] if not args.no_baseline else []) + [("after", "-")]
    results: dict = {}
    for nid in args.nodes.split(","):
        rec = results.setdefault(nid, {})
        for label, ref in versions:
            npz = work / f"{nid}-{label}.npz"
            proc = subprocess.run([sys.executable, __file__, "--cache", str(cache),
                                   "--child", nid, ref, str(npz)], cwd=ROOT, check=True,
                                  capture_output=True, text=True)
            rec[label] = json.loads(proc.stdout.strip().splitlines()[-1])
            print(nid, label, rec[label], flush=True)
        if "before" in rec:
            rec["arrays_vs_before"] = _compare(work / f"{nid}-before.npz", work / f"{nid}-after.npz")
            print(nid, rec["arrays_vs_before"], flush=True)
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                         text=True).stdout.strip()
    report = {"command": "python3 bench/bench_stages.py " + " ".join(argv or sys.argv[1:]),
              "scene": "default (scenes/default.toml), upstream cached (warm)",
              "baseline_ref": None if args.no_baseline else args.baseline_ref, "head": git,
              "cpus": os.cpu_count(),
              "note": "wall and CPU seconds of one run each; CPU counts every thread; the "
                      "machine may be shared (see the load averages)",
              "nodes": results}
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
