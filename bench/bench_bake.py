"""Benchmark of geometry/bake.py: wall time per sub-step and peak memory of a 4096^2 bake.

Cases (each run in its own subprocess so its peak RSS is its own):
  synthetic  high = bumpy lat-long sphere, ~1.1M triangles, 2048x4096 procedural texture;
             low = 64 x 128 lat-long sphere (16,128 triangles, thesis: 16,750).
  lps        low = Lee Perry-Smith OBJ (17,684 triangles, cm -> mm); high = the same mesh
             midpoint-subdivided 3 times (1,131,776 triangles) and displaced along its normals
             by the 4096^2 displacement JPEG (amplitude chosen here: +-1 mm around the median;
             the true scale is lost, see the data README), textured with Map-COL.jpg.
             Skipped when the scan's data folder beside the repository (DATA) is absent.

Target: <= 25 s and <= 3 GB for 4096^2 against ~1.1M triangles, 2 cores.
Usage: python bench/bench_bake.py [--out bench/results/bake.json] [--resolution 4096]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "lps_head"
sys.path.insert(0, str(ROOT / "tests"))
LPS_DISP_AMPLITUDE_MM = 1.0     # displacement: (value - median) / 128 * this, mm (a guess)


def _rss_mb(field: str) -> float:
    """VmRSS / VmHWM of this process in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak() -> bool:
    """Reset VmHWM so the peak measured afterwards is the bake's (Linux clear_refs = 5)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def synthetic_case():
    from bake_fixtures import bumpy_radius, latlong_sphere, latlong_texture

    def field(d):
        """Pore-scale bumps (~5 mm wavelength on a 100 mm sphere) over a smooth swell."""
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        return (0.3 * np.sin(120 * x) * np.sin(120 * y) * np.sin(120 * z)
                + 0.7 * np.sin(9 * x + 3 * z) * np.cos(5 * y))
    low = latlong_sphere(64, 128, 100.0, radial_normals=False)
    high = latlong_sphere(530, 1060, bumpy_radius(100.0, 1.0, field),
                          texture_srgb=latlong_texture(2048, 4096), radial_normals=False)
    return low, high


def _read_obj(path: Path):
    """Minimal OBJ reader: v, vt, triangular f with v/vt[/vn] corners."""
    v, vt, f, ft = [], [], [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            v.append(line.split()[1:4])
        elif line.startswith("vt "):
            vt.append(line.split()[1:3])
        elif line.startswith("f "):
            corners = [c.split("/") for c in line.split()[1:]]
            for k in range(1, len(corners) - 1):          # fan-triangulate
                tri = (corners[0], corners[k], corners[k + 1])
                f.append([int(c[0]) - 1 for c in tri])
                ft.append([int(c[1]) - 1 for c in tri])
    return (np.array(v, float), np.array(f, np.int64), np.array(vt, float), np.array(ft, np.int64))


def _read_image(path: Path) -> np.ndarray:
    import OpenImageIO as oiio
    buf = oiio.ImageBuf(str(path))
    return buf.get_pixels(oiio.UINT8)


def lps_case():
    import igl

    from dermis.pipeline.artifacts import Mesh
    from dermis.geometry.texture_lookup import bilinear
    v_cm, f, vt, ft = _read_obj(DATA / "LeePerrySmith_cm.obj")
    v = v_cm * 10.0                                                 # cm -> mm
    low = Mesh(vertices=v, faces=f.astype(np.int32), uv=vt.astype(np.float32),
               uv_faces=ft.astype(np.int32))
    # Midpoint subdivision of positions and of the UV mesh separately: igl.upsample emits the
    # child faces per parent face in a fixed corner pattern, so both stay face-aligned (the
    # baked albedo preview shows the face texture in place; a misalignment scrambles it).
    vh, fh = igl.upsample(v, f, 3)
    uvh, fth = igl.upsample(vt, ft, 3)
    assert fh.shape == fth.shape
    n = igl.per_vertex_normals(vh, fh, igl.PerVertexNormalsWeightingType.PER_VERTEX_NORMALS_WEIGHTING_TYPE_ANGLE)
    disp = _read_image(DATA / "Infinite-Level_02_Disp_NoSmoothUV-4096.jpg")[..., 0].astype(np.float32)
    corner_uv = np.zeros((len(vh), 2))
    corner_uv[fh.ravel()] = uvh[fth.ravel()]                        # one UV per welded vertex
    h = (bilinear(disp, corner_uv) - np.median(disp)) / 128.0 * LPS_DISP_AMPLITUDE_MM
    tex = _read_image(DATA / "Map-COL.jpg")[..., :3]
    high = Mesh(vertices=vh + h[:, None] * n, faces=fh.astype(np.int32), uv=uvh.astype(np.float32),
                uv_faces=fth.astype(np.int32), texture_srgb=np.ascontiguousarray(tex))
    return low, high


def worker(case: str, resolution: int, preview_dir: str | None) -> dict:
    from dermis.geometry.bake import bake_maps
    t0 = time.perf_counter()
    low, high = synthetic_case() if case == "synthetic" else lps_case()
    build_s = time.perf_counter() - t0
    rss_before = _rss_mb("VmRSS")
    reset = _reset_peak()
    t0 = time.perf_counter()
    maps = bake_maps(low, high, resolution=resolution)
    wall = time.perf_counter() - t0
    peak = _rss_mb("VmHWM")
    if preview_dir:
        from dermis.reports import previews
        out = Path(preview_dir) / case
        previews.save_map_previews(maps, out)
        previews.save_shaded_comparison(high, low, maps, out / "shaded.png", size=800)
    info = {k: v for k, v in maps.info.items()}
    return {"case": case, "resolution": resolution, "low_triangles": len(low.faces),
            "high_triangles": len(high.faces), "case_build_s": round(build_s, 2),
            "bake_wall_s": round(wall, 2), "rss_before_bake_mb": round(rss_before, 1),
            "peak_rss_during_bake_mb": round(peak, 1) if reset else None,
            "peak_rss_process_mb": round(peak, 1), "peak_reset_ok": reset, "bake_info": info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "bake.json"))
    ap.add_argument("--resolution", type=int, default=4096)
    ap.add_argument("--cases", default="synthetic,lps")
    ap.add_argument("--previews", default=None, help="directory for preview PNGs (optional)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.resolution, args.previews)))
        return 0
    results = []
    for case in args.cases.split(","):
        if case == "lps" and not DATA.exists():
            print(f"lps: skipped ({DATA} absent)")
            continue
        cmd = [sys.executable, __file__, "--worker", case, "--resolution", str(args.resolution)]
        if args.previews:
            cmd += ["--previews", args.previews]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        if proc.returncode != 0:
            print(proc.stderr)
            return proc.returncode
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        results.append(r)
        i = r["bake_info"]
        print(f"{case}: {r['high_triangles']:,} high / {r['low_triangles']:,} low tris, "
              f"{r['resolution']}^2: bake {r['bake_wall_s']:.1f} s, peak RSS "
              f"{r['peak_rss_during_bake_mb']} MB (before {r['rss_before_bake_mb']} MB); "
              f"{i['covered_texels']:,} texels, {i['misses']:,} misses")
        print("   " + ", ".join(f"{k} {v:.2f}" for k, v in i["timings"].items()))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                               "results": results}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
