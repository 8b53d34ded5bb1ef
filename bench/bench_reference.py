"""Benchmark the Mitsuba 3 ground truth: reference cost and noise, every model's distance to it.

Runs the default scene (packaged scan, high mesh, the four lighting conditions) with
``[reference] enabled`` into a cache, then reads the newest artifacts of every model render
and reference from that cache (by node folder, so later code edits do not force a re-render
to analyse) and writes:

* ``bench/results/reference.json``: per light the reference's seconds, seconds per spp, noise
  per block factor and fitted c = noise sqrt(spp); per model and light the relative RMSE with
  the reference's noise beside it, region means, FLIP, SSIM, speed-up at equal error;
  rankings; the thesis's conclusions checked (:mod:`dermis.reports.ground_truth`);
* ``bench/results/reference_slab.json`` (``--slab``): the flat-slab check, Mitsuba's Rd of
  each preset against the multipole and dermis's Monte Carlo;
* ``OUT/ground_truth.pdf`` and ``OUT/gt-error-*.png`` (``--out-dir``, default
  ``out/default/ground_truth``).

    python3 bench/bench_reference.py [--cache DIR] [--size 100] [--spp 64] [--no-run] [--slab]

CPU-heavy: the default (100x100, 2 x 64 spp, four lights) takes ~25 min on 2 cores.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def newest(cache: Path, node_id: str):
    """The newest cached artifact of ``node_id`` (restored timings), or None."""
    from dermis.pipeline import artifacts
    from dermis.pipeline.graph import restore_measurements
    dirs = [d for d in (cache / node_id).glob("*") if (d / "meta.json").is_file()]
    if not dirs:
        return None
    d = max(dirs, key=lambda p: (p / "meta.json").stat().st_mtime)
    meta = json.loads((d / "meta.json").read_text())
    return restore_measurements(artifacts.load(d), meta.get("measurements", {}))


def slab_check(out: Path) -> dict:
    """Mitsuba's flat-slab Rd of each preset vs the multipole (layer file) and the Monte Carlo."""
    import numpy as np
    from dermis.optics.layers import PRESETS
    from dermis.groundtruth.mitsuba import load_mitsuba
    from dermis.groundtruth.slab import slab_reflectance
    from dermis.optics import monte_carlo_slab as mc_slab
    from dermis.optics.layer_profiles import build_profiles
    mi = load_mitsuba()
    res = {}
    for name in ("skin1", "two_layer"):
        st = PRESETS[name]
        rec = {"multipole_Rd": build_profiles(st).Rd.tolist()}
        mc = mc_slab.simulate(st, photons=200_000, r_max_mm=50.0, bins=8)
        rec["mc_Rd"], rec["mc_Rd_err"] = mc.Rd.tolist(), mc.Rd_err.tolist()
        for alpha in (0.3, 0.1):
            t = time.perf_counter()
            r = slab_reflectance(mi, st, roughness=alpha, samples=1 << 17)
            rec[f"mitsuba_alpha{alpha}"] = {
                "Rd_incident": r.Rd.tolist(), "Rd_entered": r.Rd_entered.tolist(),
                "stderr": r.Rd_stderr.tolist(), "specular": r.specular.tolist(),
                "seconds": time.perf_counter() - t,
                "ratio_to_mc": (r.Rd_entered / np.asarray(mc.Rd)).tolist()}
        res[name] = rec
        print(name, json.dumps(rec, indent=None)[:400], flush=True)
    out.write_text(json.dumps(res, indent=1))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-reference")
    ap.add_argument("--size", type=int, default=100)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--no-run", action="store_true", help="analyse what the cache holds")
    ap.add_argument("--slab", action="store_true", help="also the flat-slab check")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "reference.json"))
    ap.add_argument("--out-dir", default=str(REPO / "out" / "default" / "ground_truth"))
    args = ap.parse_args(argv)

    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    from dermis.reports.ground_truth import (ground_truth_metrics, ground_truth_pages,
                                             write_ground_truth)
    over = {"render": {"geometries": ["high"]}, "output": {"previews": False},
            "reference": {"enabled": True, "width": args.size, "height": args.size,
                          "spp": args.spp, "slab_samples": 1 << 17}}
    scene = load_scene(None, overrides=over)
    cache = Path(args.cache)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    if not args.no_run:
        api.run(scene, cache=cache, export=False)
    wall = time.perf_counter() - t0
    mesh = newest(cache, "mesh_high")
    images, refs, extra = {}, {}, {}
    for label, _ in scene.light_groups():
        ref = newest(cache, f"reference-{label}")
        if ref is not None:
            refs[label] = ref
        for model in scene.render.models:
            nid = (f"render-bssrdf-{label}-high" if model == "bssrdf"
                   else f"render-{model}-{label}-high")
            im = newest(cache, nid)
            if im is not None:
                images[nid] = im
        irr = newest(cache, f"irradiance-mesh_high-{label}")
        if irr is not None:
            extra[(label, "mesh_high")] = float(irr.info.get("seconds", 0.0) or 0.0)
    metrics = ground_truth_metrics(images, refs, mesh=mesh, camera=scene.camera,
                                   extra_seconds=extra)
    out_dir = Path(args.out_dir)
    write_ground_truth(metrics, images, refs, out_dir)
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.backends.backend_pdf import PdfPages
    with PdfPages(out_dir / "ground_truth.pdf") as pdf:
        ground_truth_pages(pdf, metrics, images, refs)
    result = {"scene": "scenes/default.toml (high mesh)", "cache": str(cache),
              "wall_seconds": wall, "loadavg_before": load0, "loadavg_after": os.getloadavg(),
              "cpus": os.cpu_count(), **metrics}
    Path(args.out).write_text(json.dumps(result, indent=1, sort_keys=True, default=float))
    for l, r in metrics["references"].items():
        print(f"reference {l}: {r['width']}x{r['height']} {r['spp']} spp {r['seconds']:.0f} s "
              f"({r['seconds_per_spp']:.2f} s/spp), noise px {r['noise'].get('1', {}).get('rel', 0):.3f}"
              f" 4x4 {r['noise'].get('4', {}).get('rel', 0):.3f}")
    for k, r in sorted(metrics["models"].items()):
        s1, s4 = r["scales"].get("1", {}), r["scales"].get("4", {})
        print(f"{k:32s} px {100 * s1.get('rel_rmse', 0):5.1f}% (ref {100 * s1.get('ref_noise', 0):4.1f}%)"
              f" 4x4 {100 * s4.get('rel_rmse', 0):5.1f}% (ref {100 * s4.get('ref_noise', 0):4.1f}%)"
              f" FLIP {r['flip']:.3f} SSIM {r['ssim']:.3f} speed-up {s1.get('speedup', 0):.3g}"
              + "".join(f" {n[:4]} {100 * g['rel_lum']:+.1f}±{100 * g['sigma_lum']:.1f}"
                        for n, g in r["regions"].items()))
    for c in metrics["thesis"]:
        print(f"thesis: {c['claim']}: {c['verdict']}")
    if args.slab:
        slab_check(Path(args.out).with_name("reference_slab.json"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
