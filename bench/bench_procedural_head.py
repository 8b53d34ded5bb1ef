"""Time and memory of the procedural head at the default scene's size (1M triangles, 2048^2 texture).

Run: python bench/bench_procedural_head.py [--triangles 1000000] [--texture 2048] [--repeat 1]
                                           [--out bench/results/procedural_head.json]
Prints wall time (best of --repeat), per-phase times from a profile-free second pass, the
process's peak resident memory (resource.getrusage ru_maxrss, which includes the interpreter and
imports) and the mesh's own size, and writes them as JSON.  Target: <= 10 s on 2 cores.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dermis.geometry import procedural_head as ph  # noqa: E402


def _peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # Linux: KiB


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--texture", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "procedural_head.json"))
    a = ap.parse_args()

    rss_before = _peak_rss_mb()
    times = []
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        mesh = ph.make_head(triangles=a.triangles, texture_size=a.texture, seed=a.seed)
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    ph.make_head(triangles=a.triangles, texture_size=a.texture, seed=a.seed, detail=False)
    t_smooth = time.perf_counter() - t0
    t0 = time.perf_counter()
    ph.make_head(triangles=a.triangles, texture_size=64, seed=a.seed)
    t_geometry = time.perf_counter() - t0
    peak = _peak_rss_mb()
    mesh_mb = sum(x.nbytes for x in (mesh.vertices, mesh.faces, mesh.uv, mesh.uv_faces,
                                     mesh.texture_srgb)) / 2 ** 20
    result = {
        "triangles_requested": a.triangles, "triangles": mesh.n_triangles,
        "vertices": int(len(mesh.vertices)), "texture_size": a.texture,
        "seconds_best": min(times), "seconds_all": times,
        "seconds_detail_false": t_smooth, "seconds_texture_64": t_geometry,
        "peak_rss_mb": peak, "rss_before_mb": rss_before, "mesh_arrays_mb": mesh_mb,
        "info": {k: mesh.info[k] for k in ("grid", "height_mm", "detail_rms_mm",
                                           "rays_rebracketed", "max_residual_mm")},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "numpy": np.__version__, "processor": platform.processor()},
    }
    print(f"procedural head: {mesh.n_triangles:,} triangles, {a.texture}^2 texture: "
          f"{min(times):.2f} s (detail=False {t_smooth:.2f} s, 64^2 texture {t_geometry:.2f} s); "
          f"peak RSS {peak:.0f} MB (before {rss_before:.0f} MB), mesh arrays {mesh_mb:.0f} MB")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
