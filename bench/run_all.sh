#!/usr/bin/env bash
# Run every benchmark one after another (never in parallel: 2 cores) and keep their JSON
# in bench/results/. Each script also prints its numbers. Usage: bash bench/run_all.sh
set -uo pipefail
cd "$(dirname "$0")/.."
mkdir -p bench/results
for b in bench_procedural_head bench_mesh_prep bench_bake bench_samples bench_profiles bench_mc_speed \
         bench_brdf bench_render bench_gather; do
  echo "=== $b ($(cut -d' ' -f1 /proc/loadavg) load)"
  python3 "bench/$b.py" || echo "!!! $b failed"
done
echo "=== bench_pipeline (the default scene: packaged scan; then the procedural preset)"
python3 bench/bench_pipeline.py --out bench/results/pipeline_default.json
python3 bench/bench_pipeline.py scenes/procedural.toml --out bench/results/pipeline_procedural.json
