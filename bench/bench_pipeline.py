"""Benchmark a whole scene: seconds per stage and per image, and the thesis's timing table.

Runs a scene into a fresh (or given) cache and writes JSON with every node's wall and kernel
seconds, peak memory, the load average, and a model x lighting x geometry table of seconds per
800x800 image. For the BSSRDF it reports the image time alone and with its (cached, shared)
irradiance pass, to check the thesis's headline that with area and environment lights the
cached-irradiance BSSRDF is the fastest model (docs/physics.md §7).

    python3 bench/bench_pipeline.py [SCENE] [--cache DIR] [--out bench/results/pipeline.json]
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
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    from dermis.pipeline.plan import GEOMETRY_MESH

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=None)
    ap.add_argument("--cache", default=None, help="default: a fresh temporary directory")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "pipeline.json"))
    args = ap.parse_args(argv)

    scene = load_scene(args.scene)
    cache = args.cache or tempfile.mkdtemp(prefix="dermis-bench-")
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    summary = api.run(scene, cache=cache, export=False)
    wall = time.perf_counter() - t0
    nodes = {n.id: {"status": n.status, "seconds": n.seconds, "kernel_seconds": n.kernel_seconds}
             for n in summary.nodes}

    table = {}
    for nid, n in nodes.items():
        if not nid.startswith("render-"):
            continue
        _, model, rest = nid.split("-", 2)
        label, geometry = rest.rsplit("-", 1)
        row = {"image_s": n["seconds"]}
        if model == "bssrdf":
            irr = nodes.get(f"irradiance-{GEOMETRY_MESH[geometry]}-{label}", {})
            row["irradiance_s"] = irr.get("seconds", 0.0)
            row["with_irradiance_s"] = row["image_s"] + row["irradiance_s"]
        table.setdefault(geometry, {}).setdefault(label, {})[model] = row

    result = {
        "scene": scene.path, "cache": cache, "wall_seconds": wall,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "loadavg_before": load0, "loadavg_after": os.getloadavg(), "cpus": os.cpu_count(),
        "nodes": nodes, "seconds_per_image": table,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))

    print(f"{scene.path}: {wall:.1f} s wall, peak RSS {result['peak_rss_mb']:.0f} MB, "
          f"load {load0[0]:.2f}")
    for geometry, rows in table.items():
        models = sorted({m for r in rows.values() for m in r})
        print(f"\n{geometry:<14}" + "".join(f"{m:>16}" for m in models))
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
            print(f"{label:<14}" + "".join(cells))
    print("\nbssrdf: image seconds (with its irradiance pass, computed once per mesh and light)")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
