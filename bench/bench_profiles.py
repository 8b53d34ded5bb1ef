"""Benchmark the layer-optics stage: layer-file build time, and every profile model's error
against dermis's own Monte Carlo on the layer files of scenes/layers/ and the skin presets.

Usage: python bench/bench_profiles.py [--out bench/results/profiles.json] [--photons N]
       [--cases a,b,...]

For each case (a preset or scenes/layers/<case>.toml) and channel: Rd and Tt of the Monte
Carlo reference (per photon entering: the specular reflection at entry is not counted) with
their standard errors, and per model (multipole = the default; diffusion = the same
diffusion with its own totals, i.e. the diffusion model's own error; dj2005 = dermis <= 1,
"before") the relative error of Rd and Tt and the R(r) error over [0.05, 5] mm (misplaced
energy, rms and largest relative error on 24 log rings: optics/profile_command.py
``profile_errors``).  The reference runs on the union of the layer file's and the Monte
Carlo table's rings, so every comparison sums whole rings.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dermis.optics.layers import PRESETS, load_layers_toml  # noqa: E402
from dermis.optics.layer_file import RD_CONVENTION  # noqa: E402
from dermis.optics.layer_profiles import MultipoleOptions, build_profiles  # noqa: E402
from dermis.optics.monte_carlo_table import mc_bin_edges, monte_carlo_profiles  # noqa: E402
from dermis.optics.profile_command import profile_errors, ring_edges  # noqa: E402

CASES = ("two_layer", "two_layer_skin", "thin_epidermis", "thin_epidermis_from_below",
         "slab_1mm", "low_albedo", "skin1", "skin2")
MODELS = {"multipole": MultipoleOptions(), "diffusion": MultipoleOptions(totals="diffusion"),
          "dj2005": MultipoleOptions(diffusion="dj2005")}


def load(name: str):
    return PRESETS[name] if name in PRESETS else load_layers_toml(ROOT / "scenes/layers"
                                                                  / f"{name}.toml")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "bench/results/profiles.json"))
    ap.add_argument("--photons", type=int, default=1_000_000, help="MC photons per channel")
    ap.add_argument("--cases", default=",".join(CASES))
    args = ap.parse_args()
    out: dict = {"load_average_start": os.getloadavg(), "photons_per_channel": args.photons,
                 "convention": RD_CONVENTION, "cases": {}}
    times = []
    for _ in range(3):
        t = time.perf_counter()
        build_profiles(PRESETS["two_layer"])
        times.append(time.perf_counter() - t)
    out["layer_file_two_layer_s"] = {"min": min(times), "median": float(np.median(times)),
                                     "load_average": os.getloadavg()}
    print(f"two_layer layer file: min {min(times):.2f} s, median {np.median(times):.2f} s")
    for name in args.cases.split(","):
        st = load(name)
        built = {m: build_profiles(st, options=o) for m, o in MODELS.items()}
        edges = ring_edges(built["multipole"])
        mc_edges = mc_bin_edges(st)
        union = np.unique(np.concatenate([edges, mc_edges]))
        union = union[union <= max(edges[-1], mc_edges[-1])]
        t = time.perf_counter()
        ref = monte_carlo_profiles(st, photons=args.photons, seed=1, edges=union)
        entry = {"mc": {"Rd": ref.Rd.tolist(), "Rd_err": ref.info["Rd_err"],
                        "Tt": ref.Tt.tolist(), "Tt_err": ref.info["Tt_err"],
                        "photons_per_second": ref.info["photons_per_second"],
                        "wall_s": time.perf_counter() - t, "load_average": os.getloadavg()},
                 "models": {}}
        for m, p in built.items():
            err = profile_errors(p, ref)
            entry["models"][m] = {"Rd": p.Rd.tolist(), "Tt": p.Tt.tolist(), **err,
                                  "negative_lobes": len(p.info.get("negative_lobes", []))}
            ch = err["channels"]
            print(f"{name:26s} {m:10s} dRd {_fmt([c['dRd'] for c in ch])} dTt "
                  f"{_fmt([c['dTt'] for c in ch])} R(r) misplaced "
                  f"{_fmt([c['R_misplaced'] for c in ch])} max {_fmt([c['R_max'] for c in ch])}")
        out["cases"][name] = entry
        print(f"{name:26s} MC Rd {np.round(ref.Rd, 4)} +- {np.round(ref.info['Rd_err'], 4)} "
              f"Tt {np.round(ref.Tt, 4)}")
    out["load_average_end"] = os.getloadavg()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


def _fmt(v) -> str:
    return "[" + " ".join("    -" if x is None else f"{100 * x:+5.1f}" for x in v) + "] %"


if __name__ == "__main__":
    main()
