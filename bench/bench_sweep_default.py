"""Benchmark: the speed-accuracy sweeps of the default scan (scenes/sweep_default*.toml) and
of the quick scene (scenes/sweep_quick.toml).

Runs ``dermis sweep`` serially on each and writes a small summary, no images: per knob its
points (value, median seconds of the nodes the knob changes over the [sweep] repeats with
their min-max spread and samples, relative RMSE and FLIP against the converged reference with
its uncertainty and kind), the knob's extrapolation, the Pareto front, the per-knob
recommendations, and the recommended configurations as predicted (first order) and as
rendered and measured (reports/sweep_verify.py), misses included.

    python3 bench/bench_sweep_default.py [--cache DIR] [--out bench/results/sweep_default.json]
    python3 bench/bench_sweep_default.py --only quick --out bench/results/sweep_quick.json
    python3 bench/bench_sweep_default.py --only geometry --out bench/results/sweep_default_geometry.json
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = {"quick": REPO / "scenes" / "sweep_quick.toml",
          "point_area": REPO / "scenes" / "sweep_default.toml",
          "sunset": REPO / "scenes" / "sweep_default_sunset.toml",
          "geometry": REPO / "scenes" / "sweep_default_geometry.toml"}


def summarise(res: dict) -> dict:
    rows = res["points"]
    knobs = {}
    for name, front in res["fronts"].items():
        if name == "joint":
            continue
        sel = [k for k, r in enumerate(rows) if r["knob"] == name]
        keep = ("seconds", "seconds_min", "seconds_max", "seconds_samples", "seconds_shared",
                "kernel_seconds", "rel_rmse", "rel_rmse_vs_finest", "error_uncertainty",
                "error_reference", "rel_rmse_max", "flip", "images", "is_default")
        pts = [{"value": rows[k]["values"][name], **{f: rows[k].get(f) for f in keep},
                "on_front": k in front} for k in sel]
        default = [p for p in pts if p["is_default"]]
        knobs[name] = {"reference": res["reference_rules"][name], "points": pts,
                       "extrapolation": res.get("extrapolation", {}).get(name),
                       "front": [rows[k]["values"][name] for k in front],
                       "recommended": res["per_knob"][name],
                       "default": default[0]["value"] if default else None,
                       "default_on_front": bool(default and default[0]["on_front"])}
    joint = [{"knob": rows[k]["knob"], "values": rows[k]["values"],
              "seconds_total": rows[k]["seconds_total"], "rel_rmse": rows[k]["rel_rmse"]}
             for k in res["fronts"]["joint"]]
    return {"knobs": knobs, "joint_front_by_total_seconds": joint,
            "recommended_single_knob_by_total_seconds": res["per_knob"]["joint"],
            "combined_first_order": res.get("combined"),
            "recommended_rendered": res.get("recommended"),
            "base_seconds": res.get("base_seconds"),
            "base_seconds_spread": res.get("base_seconds_spread"), "repeats": res.get("repeats"),
            "targets": res["targets"], "budget_s": res["budget_s"]}


def main() -> None:
    from dermis.reports.sweep import run_sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", default=str(REPO / ".dermis-cache"))
    ap.add_argument("--res", default=None, help="sweep output folder (plots, sweep.json)")
    ap.add_argument("--only", choices=sorted(SCENES), help="one of the scenes")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "sweep_default.json"))
    ap.add_argument("--first-run", default=None,
                    help="JSON of the run that built the cache (wall, loads), kept in the output")
    args = ap.parse_args()
    out = {"scenes": {k: str(v.relative_to(REPO)) for k, v in SCENES.items()},
           "cut": "the default scan (scenes/default.toml) cut to fit one evening on the shared "
                  "2-core machine: geometry high only, 400x400 instead of 800x800; point_area: "
                  "lights point + area, models lafortune + bssrdf; sunset: the environment "
                  "light, bssrdf only; geometry: point + area, lafortune + bssrdf on the high and the low "
                  "mesh with its baked maps (low_bump), the mesh, bake and optics knobs; "
                  "errors are means over the images the knob changes "
                  "(relative RMSE in linear radiance, FLIP LDR)",
           "time_rule": "seconds = median over [sweep] repeats of the seconds of the nodes the "
                        "knob changes (the first from the stage metadata of the run that built "
                        "them, the others forced recomputations in rotated order; build seconds "
                        "excluded), min-max spread and every sample kept, summed over both "
                        "lights and models; the machine was shared (load averages below)",
           "first_run": json.loads(args.first_run) if args.first_run else None,
           "cpu_count": os.cpu_count()}
    for name, scene in SCENES.items():
        if args.only and name != args.only:
            continue
        load0, t0 = os.getloadavg(), time.perf_counter()
        res = run_sweep(scene, cache=args.cache,
                        out_dir=Path(args.res) / name if args.res else None)
        out[name] = {**summarise(res),
                     "this_run": {"wall_seconds": time.perf_counter() - t0,
                                  "loadavg_before": load0, "loadavg_after": os.getloadavg(),
                                  "distributed": res["distributed"]}}
    Path(args.out).write_text(json.dumps(out, indent=1, default=str))
    print(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
