"""Benchmark: the speed-accuracy sweep of the default scan (scenes/sweep_default.toml).

Runs ``dermis sweep scenes/sweep_default.toml`` serially (a warm cache re-scores without
rebuilding: the times are read from the stage metadata of the run that built each node) and
writes a small summary, no images: per knob its points (value, seconds of the nodes the knob
changes, relative RMSE and FLIP against the knob's reference), the Pareto front, the
recommended settings (cheapest point reaching 1 % and 5 %, best within the time budget), and
for each knob whether the scene default is on the front and what the data recommends.

    python3 bench/bench_sweep_default.py [--cache DIR] [--out bench/results/sweep_default.json]
    python3 bench/bench_sweep_default.py --only geometry --out bench/results/sweep_default_geometry.json
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = {"point_area": REPO / "scenes" / "sweep_default.toml",
          "sunset": REPO / "scenes" / "sweep_default_sunset.toml",
          "geometry": REPO / "scenes" / "sweep_default_geometry.toml"}


def summarise(res: dict) -> dict:
    rows = res["points"]
    knobs = {}
    for name, front in res["fronts"].items():
        if name == "joint":
            continue
        sel = [k for k, r in enumerate(rows) if r["knob"] == name]
        pts = [{"value": rows[k]["values"][name], "seconds": rows[k]["seconds"],
                "seconds_shared": rows[k]["seconds_shared"],
                "kernel_seconds": rows[k]["kernel_seconds"],
                "rel_rmse": rows[k].get("rel_rmse"), "rel_rmse_max": rows[k].get("rel_rmse_max"),
                "flip": rows[k].get("flip"), "images": rows[k].get("images"),
                "is_default": rows[k]["is_default"], "on_front": k in front} for k in sel]
        default = [p for p in pts if p["is_default"]]
        knobs[name] = {"reference": res["reference_rules"][name], "points": pts,
                       "front": [rows[k]["values"][name] for k in front],
                       "recommended": res["recommended"][name],
                       "default": default[0]["value"] if default else None,
                       "default_on_front": bool(default and default[0]["on_front"])}
    joint = [{"knob": rows[k]["knob"], "values": rows[k]["values"],
              "seconds_total": rows[k]["seconds_total"], "rel_rmse": rows[k]["rel_rmse"]}
             for k in res["fronts"]["joint"]]
    return {"knobs": knobs, "joint_front_by_total_seconds": joint,
            "recommended_single_knob_by_total_seconds": res["recommended"]["joint"],
            "combined": res.get("combined"), "base_seconds": res.get("base_seconds"),
            "targets": res["targets"], "budget_s": res["budget_s"]}


def validate(scene_path: Path, combined: dict, cache) -> dict:
    """Render the combined recommendations and the defaults as whole scenes and measure them
    against the scene with every knob at its finest swept value (the per-knob references
    together): their real error and total node seconds, next to the quadrature/additive
    prediction."""
    import tomllib
    from dermis.pipeline.distributed import run_graphs
    from dermis.pipeline.plan import build_graph
    from dermis.pipeline.store import Store
    from dermis.reports.sweep import (IMAGE_STAGES, KNOBS, _errors, _images, _scene, _seconds,
                                      _set, parse_sweep)
    table = tomllib.loads(scene_path.read_text())
    spec = parse_sweep(table.pop("sweep"), str(scene_path))
    finest = {k: max(v, key=KNOBS[k].rank) for k, v in spec.knobs.items()}
    variants = {"finest": finest}
    for name in ("defaults", "rel_rmse<=0.01", "rel_rmse<=0.05"):
        if combined.get(name):
            variants[name] = combined[name]["values"]
    graphs, names = [], list(variants)
    for name in names:
        t = table
        for k, v in variants[name].items():
            t = _set(t, k, v)
        nodes, _ = build_graph(_scene(t, str(scene_path), name))
        graphs.append((nodes, [n for n, v in nodes.items() if v.stage in IMAGE_STAGES]))
    summaries, _ = run_graphs(graphs, cache)
    store = Store(cache)
    imgs = [_images(store, s) for s in summaries]
    out = {}
    for i, name in enumerate(names):
        out[name] = {"values": variants[name],
                     "measured_seconds": _seconds(store, summaries[i], set())["total"],
                     **_errors(imgs[i], imgs[0]),
                     "predicted": combined.get(name)}
    return out


def main() -> None:
    from dermis.reports.sweep import run_sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", default=str(REPO / ".dermis-cache"))
    ap.add_argument("--res", default=None, help="sweep output folder (plots, sweep.json)")
    ap.add_argument("--only", choices=sorted(SCENES), help="one of the scenes")
    ap.add_argument("--validate", action="store_true",
                    help="also render the combined recommendations against all-finest")
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
           "time_rule": "seconds = stage-metadata seconds of the nodes the knob changes "
                        "(build seconds excluded), summed over both lights and models; the "
                        "machine was shared (load averages below), so times carry +-30 % noise",
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
        if args.validate and res.get("combined") and len(res["combined"].get("defaults", {})
                                                         .get("values", {})) > 1:
            t0 = time.perf_counter()
            out[name]["validation"] = validate(scene, res["combined"], args.cache)
            out[name]["validation"]["wall_seconds"] = time.perf_counter() - t0
            out[name]["validation"]["loadavg_after"] = os.getloadavg()
    Path(args.out).write_text(json.dumps(out, indent=1, default=str))
    print(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
