"""Benchmark where a cold default run's references spend their time, and what noise they reach.

Runs ``dermis run --until reference`` on the default scene into an empty cache (unless
``--no-run``: then it reads a cache an earlier run filled, with the wall and CPU seconds of
that run from ``/usr/bin/time -v`` output, ``--time-file``) and records, under ``--label``
in ``bench/results/reference_cost.json``:

* the run's wall seconds, CPU seconds (the run's process and its children) and the load
  average before and after (the machine is shared: CPU seconds are the comparable figure);
* per reference node its seconds (lock waits included: the nodes' Mitsuba work runs one at a
  time, ``groundtruth/mitsuba.py``), the node's own seconds after it got Mitsuba, the
  scene load, the flat-slab calibration, the rendering (wall and CPU), the paths, the passes
  (how many in the guaranteed part), why it stopped and every face region's relative
  standard error;
* with ``--profile-load``: the parts of one head scene's load (unweld, PLY writing, Mitsuba's
  scene build) and of its face-region labels, wall and CPU seconds.

    python3 bench/bench_reference_cost.py --label after [--cache DIR] [--no-run --time-file F]
                                          [--profile-load]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "results" / "reference_cost.json"


def _time_file(path: Path) -> dict:
    """Wall, user and system seconds and peak RSS of a ``/usr/bin/time -v`` report."""
    text = path.read_text()

    def num(pat):
        m = re.search(pat, text)
        return m.group(1) if m else None
    wall = num(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)")
    secs = (sum(float(p) * 60 ** i for i, p in enumerate(reversed(wall.split(":"))))
            if wall else None)
    return {"wall_s": secs, "user_cpu_s": float(num(r"User time \(seconds\): ([\d.]+)") or 0),
            "system_cpu_s": float(num(r"System time \(seconds\): ([\d.]+)") or 0),
            "peak_rss_kb": int(num(r"Maximum resident set size \(kbytes\): (\d+)") or 0)}


def _run(cache: Path) -> dict:
    la, t0 = os.getloadavg(), time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "dermis", "run", "--until", "reference", "--cache",
                    str(cache), "-q"], check=True, cwd="/tmp")
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": time.perf_counter() - t0, "user_cpu_s": r1.ru_utime - r0.ru_utime,
            "system_cpu_s": r1.ru_stime - r0.ru_stime, "peak_rss_kb": r1.ru_maxrss,
            "loadavg_before": list(la), "loadavg_after": list(os.getloadavg())}


def _nodes(cache: Path) -> dict:
    out = {}
    for folder in sorted(cache.glob("reference-*")):
        entries = [d for d in folder.iterdir() if (d / "meta.json").is_file()]
        if not entries:
            continue
        d = max(entries, key=lambda p: (p / "meta.json").stat().st_mtime)
        meta = json.loads((d / "meta.json").read_text())
        info = meta.get("info", {})
        t = info.get("timings", {})
        log = []
        if (d / "passes.npz").is_file():
            import numpy as np
            with np.load(d / "passes.npz") as z:
                log = json.loads(str(z["log"]))
        rel = info.get("region_rel_se", {})
        out[folder.name] = {
            "node_s": meta.get("seconds"), "own_s": t.get("total"),
            "lock_wait_s": (meta.get("seconds") or 0) - (t.get("total") or 0),
            "scene_load_s": t.get("scene_load"), "slab_s": t.get("slab"),
            "render_s": t.get("render"),
            "render_cpu_s": sum(p.get("cpu_seconds", 0.0) for p in log) or None,
            "paths": sum(p["paths"] for p in log), "passes": len(log),
            "guaranteed_passes": sum(1 for p in log if p.get("guaranteed")),
            "stopped": info.get("stopped"), "worst_rel_se": max(rel.values()) if rel else None,
            "region_rel_se": rel}
    return out


def _profile_load(cache: Path) -> dict:
    """The parts of one head scene's load, on the cached high mesh."""
    import numpy as np
    from dermis.geometry.regions import face_regions
    from dermis.groundtruth import mitsuba
    from dermis.groundtruth import scene_export as se
    from dermis.optics.layers import LayerStack
    from dermis.pipeline import api, artifacts
    entry = next(d for d in (cache / "mesh_high").iterdir() if (d / "meta.json").is_file())
    mesh = artifacts.load(entry)
    scene = api.load_scene(None)
    stack = LayerStack.from_dict(scene.optics.to_dict())
    mi = mitsuba.load_mitsuba("auto")
    lights = list(dict(scene.light_groups())["point"])
    res = {}

    def timed(name, fn):
        t0, c0 = time.perf_counter(), time.process_time()
        value = fn()
        res[name] = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
        return value
    normals = se.vertex_normals(mesh)
    parts = timed("unweld", lambda: se.unweld(mesh.vertices, mesh.faces, normals, mesh.uv,
                                              mesh.uv_faces))
    timed("write_ply", lambda: se.write_ply("/tmp/bench-reference-cost.ply", *parts))
    loader = mi.load_dict
    captured = {}

    def capture(d, *a, **k):
        captured["dict"] = d
        return timed("mitsuba_scene_build", lambda: loader(d, *a, **k))
    mi.load_dict = capture
    try:
        head = timed("head_scene_total", lambda: se.head_scene(
            mi, mesh, stack, scene.camera, lights, width=100, height=100,
            options=se.HeadSceneOptions(roughness=0.3, tint_rd=np.array([0.5, 0.4, 0.3]))))
    finally:
        mi.load_dict = loader
    se.release(head)
    timed("face_regions", lambda: face_regions(mesh.vertices, mesh.faces))
    res["faces"] = int(len(mesh.faces))
    res["loadavg"] = list(os.getloadavg())
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--cache", default="/tmp/dermis-bench-reference-cost")
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("--time-file", help="/usr/bin/time -v output of the run (with --no-run)")
    ap.add_argument("--load-file", help="JSON lines of load_before / load_after (with --no-run)")
    ap.add_argument("--profile-load", action="store_true")
    ap.add_argument("--note", default="")
    args = ap.parse_args(argv)
    cache = Path(args.cache)
    if args.no_run:
        run = _time_file(Path(args.time_file)) if args.time_file else {}
        if args.load_file:
            for line in Path(args.load_file).read_text().splitlines():
                for k, v in json.loads(line).items():
                    run[k.replace("load_", "loadavg_")] = v
    else:
        if cache.exists() and any(cache.iterdir()):
            sys.exit(f"{cache} is not empty: a cold run needs an empty cache")
        run = _run(cache)
    rec = {"run": run, "cpus": os.cpu_count(), "nodes": _nodes(cache), "note": args.note}
    if args.profile_load:
        rec["scene_load_parts"] = _profile_load(cache)
    data = json.loads(OUT.read_text()) if OUT.is_file() else {}
    data[args.label] = rec
    OUT.write_text(json.dumps(data, indent=1) + "\n")
    print(json.dumps(rec, indent=1)[:3000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
