"""Benchmark a whole scene: seconds per stage and per image, and the thesis's timing table.

Runs a scene into a fresh (or given) cache and writes JSON with every node's wall and kernel
seconds, the seconds summed per stage (where the time goes), peak memory, the load average,
and a model x lighting x geometry table of seconds per 800x800 image.  For the BSSRDF it
reports the image time alone and with its (cached, shared) irradiance pass, to check the
thesis's headline that with area and environment lights the cached-irradiance BSSRDF is the
fastest model (docs/science.md §7, the thesis's timings, in this repository).  With ``--warm-light NAME`` it then scales that light's
intensity by 1.1 and runs again on the same cache: what one changed light costs (warm).

    python3 bench/bench_pipeline.py [SCENE] [--cache DIR]
        [--out bench/results/pipeline_default.json]
        [--warm-light point]

Peak memory is the process's maximum resident set (``ru_maxrss``), which includes the
OpenCL runtime's threads (PoCL runs in-process).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _per_stage(summary) -> dict:
    """Seconds and node counts summed per stage (ran nodes only)."""
    out: dict = {}
    for n in summary.nodes:
        if n.status != "ran":
            continue
        rec = out.setdefault(n.stage, {"nodes": 0, "seconds": 0.0, "kernel_seconds": 0.0})
        rec["nodes"] += 1
        rec["seconds"] += n.seconds
        rec["kernel_seconds"] += n.kernel_seconds
    return out


class _MemoryWatch:
    """Samples this process's resident memory every 0.1 s and which nodes were running then:
    where the peak comes from (nodes run at once on threads)."""

    def __init__(self):
        import threading
        self.running: set = set()
        self.peak_mb, self.peak_nodes = 0.0, []
        self.t0 = time.perf_counter()
        self.timeline: dict = {}        # node id -> [start, end] seconds since the run began
        self.curve: list = []           # [seconds, MB] once a second
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._page = os.sysconf("SC_PAGE_SIZE")

    def progress(self, node, fraction):
        now = round(time.perf_counter() - self.t0, 3)
        if fraction <= 0.0:
            self.running.add(node.id)
            self.timeline[node.id] = [now, None]
        elif fraction >= 1.0:
            self.running.discard(node.id)
            self.timeline[node.id][1] = now

    def _watch(self):
        while not self._stop.wait(0.1):
            with open("/proc/self/statm") as f:
                rss = int(f.read().split()[1]) * self._page / 2**20
            if rss > self.peak_mb:
                self.peak_mb, self.peak_nodes = rss, sorted(self.running)
            now = time.perf_counter() - self.t0
            if not self.curve or now - self.curve[-1][0] >= 1.0:
                self.curve.append([round(now, 1), round(rss)])

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def _run(api, scene, cache, jobs) -> tuple[float, object, dict]:
    t0 = time.perf_counter()
    with _MemoryWatch() as watch:
        summary = api.run(scene, cache=cache, export=False, jobs=jobs, progress=watch.progress)
    return time.perf_counter() - t0, summary, {"peak_mb": watch.peak_mb,
                                               "running_at_peak": watch.peak_nodes,
                                               "timeline": watch.timeline,
                                               "curve": watch.curve}


def main(argv=None) -> int:
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    from dermis.stages.render import GEOMETRY

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=None)
    ap.add_argument("--cache", default=None, help="default: a fresh temporary directory")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "pipeline.json"))
    ap.add_argument("--jobs", type=int, default=None, help="nodes run at once (default: dermis's)")
    ap.add_argument("--models", default=None,
                    help="comma-separated [render] models instead of the scene's (e.g. the "
                         "thesis's four: lafortune,asperity,hk93,bssrdf)")
    ap.add_argument("--warm-light", default=None,
                    help="then rerun with this light's intensity x 1.1 (warm cost of a change)")
    args = ap.parse_args(argv)

    base_over = {"render": {"models": args.models.split(",")}} if args.models else {}
    scene = load_scene(args.scene, overrides=base_over or None)
    jobs = api.resolve_jobs(args.jobs)
    cache = args.cache or tempfile.mkdtemp(prefix="dermis-bench-")
    load0 = os.getloadavg()
    cpu0 = time.process_time()
    wall, summary, memory = _run(api, scene, cache, jobs)
    cpu = time.process_time() - cpu0
    nodes = {n.id: {"status": n.status, "seconds": n.seconds, "kernel_seconds": n.kernel_seconds}
             for n in summary.nodes}

    table = {}
    for nid, n in nodes.items():
        if not nid.startswith("render-"):
            continue
        _, model, rest = nid.split("-", 2)
        label, geometry = rest.rsplit("-", 1)
        mesh = GEOMETRY[geometry][0]
        row = {"image_s": n["seconds"],
               "visibility_s": nodes.get(f"visibility-{mesh}-{label}", {}).get("seconds", 0.0)}
        if model == "bssrdf":
            irr = nodes.get(f"irradiance-{mesh}-{label}", {})
            row["irradiance_s"] = irr.get("seconds", 0.0)
            row["with_irradiance_s"] = row["image_s"] + row["irradiance_s"]
        table.setdefault(geometry, {}).setdefault(label, {})[model] = row

    result = {
        "scene": scene.path, "cache": cache, "wall_seconds": wall, "cpu_seconds": cpu,
        "spp": scene.render.spp, "jobs": jobs, "models": list(scene.render.models),
        "images": sum(1 for n in summary.nodes if n.stage in ("render", "bssrdf")),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "loadavg_before": load0, "loadavg_after": os.getloadavg(), "cpus": os.cpu_count(),
        "memory_watch": memory,
        "per_stage": _per_stage(summary), "nodes": nodes, "seconds_per_image": table,
    }
    if args.warm_light:
        light = next(l for l in scene.lights if l.name == args.warm_light)
        over = {"lights": [{**_light_table(l), **({"intensity": [1.1 * x for x in l.intensity]}
                                               if l.name == light.name else {})}
                           for l in scene.lights]}
        changed = load_scene(args.scene, overrides={**base_over, **over})
        w2, s2, _ = _run(api, changed, cache, jobs)
        result["warm"] = {"light": args.warm_light, "wall_seconds": w2,
                          "fraction_of_cold": w2 / wall, "ran": s2.ran(),
                          "per_stage": _per_stage(s2)}
        result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))

    print(f"{scene.path}: {result['images']} images, {wall:.1f} s wall ({cpu:.1f} s CPU in this "
          f"process), peak RSS {result['peak_rss_mb']:.0f} MB, load {load0[0]:.2f}, "
          f"spp {scene.render.spp}, jobs {jobs}")
    print(f"\n{'stage':<14}{'nodes':>6}{'seconds':>10}")
    for stage, rec in result["per_stage"].items():
        print(f"{stage:<14}{rec['nodes']:>6}{rec['seconds']:>10.1f}")
    for geometry, rows in table.items():
        models = sorted({m for r in rows.values() for m in r})
        print(f"\n{geometry:<20}" + "".join(f"{m:>16}" for m in models))
        for label, r in rows.items():
            cells = []
            for m in models:
                c = r.get(m)
                if c is None:
                    cells.append(f"{'':>16}")
                elif "with_irradiance_s" in c:
                    cells.append(f"{c['image_s']:7.2f} ({c['with_irradiance_s']:5.1f})")
                else:
                    cells.append(f"{c['image_s']:16.2f}")
            print(f"{label:<20}" + "".join(cells))
    print("\nbssrdf: image seconds (with its irradiance pass, computed once per mesh and light);"
          " the visibility of each mesh and light is shared by its models (per_stage)")
    if "warm" in result:
        w = result["warm"]
        print(f"warm after changing light {w['light']!r}: {w['wall_seconds']:.1f} s = "
              f"{w['fraction_of_cold']:.0%} of cold; ran {len(w['ran'])} nodes")
    print(f"wrote {args.out}")
    return 0


def _light_table(light) -> dict:
    """A LightConfig as its scene table (lengths are already in mm: the scene's units)."""
    from dataclasses import asdict
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(light).items()}


if __name__ == "__main__":
    sys.exit(main())
