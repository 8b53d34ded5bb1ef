"""The verdict of the default run: every model's distance to the path-traced reference.

Runs the default scene (``dermis run``, every stage; or reads a finished run's
``metrics.json`` with ``--metrics``) and writes ``bench/results/default_verdict.json``:

* per lighting condition the noise the reference reached (passes, why it stopped, each face
  region's relative standard error) and the ranking with rank ranges;
* per model and region the distance (model / reference - 1, luminance) with its standard
  error and whether it is resolved;
* the thesis's conclusions with their verdicts;
* the causes table's rows for the whole face and the thin parts (ear, nostril): distance,
  interreflection, boundary, profile, geometry parts and the remainder.

    python3 bench/bench_default_verdict.py [--cache DIR] [--metrics out/default/report/metrics.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def summarise(metrics: dict) -> dict:
    gt = metrics.get("ground_truth", {})
    out = {"lights": {}, "thesis": metrics.get("thesis", []), "causes": []}
    for light, g in gt.items():
        rec = {"noise_reached": g.get("noise_reached"),
               "region_rel_se": {r: v.get("ref_rel_se") for r, v in g.get("regions", {}).items()},
               "ranking": g.get("ranking"), "models": {}}
        for model, m in g.get("models", {}).items():
            rec["models"][model] = {
                "distance_4x4": m.get("distance"), "stderr_4x4": m.get("stderr"),
                "rank": m.get("rank"), "rank_range": m.get("rank_range"),
                "seconds": m.get("seconds"),
                "regions": {r: {"rel_diff": v.get("rel_diff"), "stderr": v.get("stderr"),
                                "resolved": v.get("resolved")}
                            for r, v in m.get("regions", {}).items()}}
        out["lights"][light] = rec
    for row in (metrics.get("causes") or {}).get("rows", []):
        if row["geometry"] != "high" or row["region"] not in ("face", "ear", "nostril"):
            continue
        parts = {k: (None if v is None else {"value": v["value"][0], "se": v["se"][0]})
                 for k, v in row["parts"].items()}
        out["causes"].append({"light": row["light"], "model": row["model"],
                              "region": row["region"], "distance": row["distance"][0],
                              "sigma": row["sigma"][0], "parts": parts,
                              "remainder": row["remainder"]["value"][0],
                              "remainder_se": row["remainder"]["se"][0]})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/dermis-bench-default-verdict")
    ap.add_argument("--metrics", default=None, help="a finished default run's metrics.json")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "default_verdict.json"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.metrics:
        path = Path(args.metrics)
    else:
        from dermis.pipeline import api
        from dermis.pipeline.config import load_scene
        summary = api.run(load_scene(None), cache=args.cache, export=False)
        path = Path(next(n for n in summary.nodes if n.id == "report").path) / "metrics.json"
    result = {"scene": "scenes/default.toml", "metrics": str(path),
              "seconds": time.perf_counter() - t0,
              **summarise(json.loads(path.read_text()))}
    Path(args.out).write_text(json.dumps(result, indent=1, sort_keys=True, default=float))
    for light, rec in result["lights"].items():
        print(light, "ranking", rec["ranking"], "worst region rel SE",
              max(v for v in rec["region_rel_se"].values() if v is not None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
