"""What the default scene requires, and the evidence ``[render] models = ["auto"]`` reads.

Reads a finished default run's ``metrics.json`` (``--metrics``; else runs the default scene,
``dermis run``) and writes ``bench/results/requirements.json``:

* per view and lighting condition: the effects visible in each face region (size, standard
  error, verdict) and the cheapest model within 1, 2 and 5 % of the path-traced reference in
  every region (``views.<view>.requires``);
* per kind of lighting condition (its lights' types, and whether a close-up sees it): each
  model's seconds per image, its worst region bound |error| + 2 s.e. against the reference
  and the RMS of its region errors, over every condition of that kind -- the table
  :mod:`dermis.pipeline.model_choice` holds.

    python3 bench/bench_requirements.py [--cache DIR] [--metrics out/default/report/metrics.json]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def kinds(metrics: dict, scene) -> dict:
    """{kind: {model: {"seconds": worst, "bound": worst}}} over the referenced conditions."""
    from dermis.pipeline.model_choice import condition_kind
    out: dict = {}
    for label, g in metrics.get("ground_truth", {}).items():
        kind = condition_kind([l.type for l in dict(scene.light_groups())[label]],
                              scene.view_of(label) is not None)
        for model, m in g.get("models", {}).items():
            regions = [r for r in m["regions"].values() if r.get("rel_diff") is not None]
            if not regions or m.get("seconds") is None:
                continue
            rec = out.setdefault(kind, {}).setdefault(model, {"seconds": 0.0, "bound": 0.0,
                                                              "errors": [], "conditions": []})
            rec["seconds"] = max(rec["seconds"], float(m["seconds"]))
            rec["bound"] = max(rec["bound"], max(abs(r["rel_diff"]) + 2 * r["stderr"]
                                                 for r in regions))
            rec["errors"] += [r["rel_diff"] for r in regions]
            rec["conditions"].append(label)
    for models in out.values():
        for rec in models.values():
            rec["rms_error"] = math.sqrt(sum(e * e for e in rec["errors"]) / len(rec["errors"]))
    return out


def cheapest(requires: dict, accuracy: float) -> dict:
    out = {}
    for view, lights in requires.items():
        for light, rec in lights.items():
            seen: dict = {}
            for row in rec["regions"].values():
                if row.get("against") != "reference":
                    continue
                for m, v in row["models"].items():
                    ok = abs(v["error"]) + 2 * v["stderr"] <= accuracy
                    good, t = seen.get(m, (True, 0.0))
                    seen[m] = (good and ok, max(t, v["seconds"]))
            fits = sorted((t, m) for m, (good, t) in seen.items() if good)
            out[f"{view}/{light}"] = fits[0][1] if fits else None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=None)
    ap.add_argument("--metrics", default=None, help="a finished default run's metrics.json")
    args = ap.parse_args(argv)
    from dermis.pipeline.config import load_scene
    scene = load_scene()
    t0 = time.perf_counter()
    if args.metrics is None:
        from dermis.pipeline.api import cache_dir_for, run
        run(scene, cache=cache_dir_for(scene, args.cache))
        path = Path(scene.output.output_dir) / scene.scene.name / "report" / "metrics.json"
    else:
        path = Path(args.metrics)
    metrics = json.loads(path.read_text())
    requires = {v: r["requires"] for v, r in metrics.get("views", {}).items()}
    out = {"scene": "default", "metrics": str(path), "seconds": time.perf_counter() - t0,
           "kinds": kinds(metrics, scene),
           "cheapest_everywhere": {f"{100 * a:g}%": cheapest(requires, a)
                                   for a in (0.01, 0.02, 0.05)},
           "requires": requires}
    dest = REPO / "bench" / "results" / "requirements.json"
    dest.write_text(json.dumps(out, indent=1, sort_keys=True))
    for kind, models in sorted(out["kinds"].items()):
        row = ", ".join(f"{m} {100 * v['bound']:.1f}%/{100 * v['rms_error']:.1f}% "
                        f"{v['seconds']:.1f}s"
                        for m, v in sorted(models.items(), key=lambda kv: kv[1]["seconds"]))
        print(f"{kind}: {row}")
    print(json.dumps(out["cheapest_everywhere"], indent=1))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
