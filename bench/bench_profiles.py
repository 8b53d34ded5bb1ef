"""Benchmark the layer-optics stage: layer-file build time, Monte Carlo photons/s, and the
multipole's error against the Monte Carlo for the skin presets.

Usage: python bench/bench_profiles.py [--out bench/results/profiles.json] [--photons N]
Targets (issue): two-layer RGB layer file <= 2 s; Monte Carlo >= 4 x MCML 1.2.2's ~27,000
photons/s per core on the semi-infinite n = 1.4, mu_a = 0.01/mm, mu_s = 10/mm, g = 0 case.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from dermis.physics.layers import PRESETS, Layer, LayerStack
from dermis.stages import mc_slab, profiles

MCML_PHOTONS_PER_S_PER_CORE = 27000.0  # issue text, MCML 1.2.2 on one core of this machine


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="bench/results/profiles.json")
    ap.add_argument("--photons", type=int, default=400000, help="MC photons per channel")
    args = ap.parse_args()
    out: dict = {"load_average": os.getloadavg()}

    times = []
    for _ in range(3):
        t = time.perf_counter()
        profiles.build_profiles(PRESETS["two_layer"])
        times.append(time.perf_counter() - t)
    out["layer_file_two_layer_s"] = {"min": min(times), "median": float(np.median(times))}
    print(f"two_layer layer file: min {min(times):.2f} s, median {np.median(times):.2f} s")

    mcml = LayerStack((Layer(math.inf, 1.4, (0.01,) * 3, (10.0,) * 3),))
    r = mc_slab.simulate(mcml, photons=20000, r_max_mm=10, bins=50)
    out["mc_mcml_case"] = {"photons_per_second": r.photons_per_second,
                           "interactions_per_second": r.info["interactions_per_second"],
                           "Rd": r.Rd.tolist(), "Rd_err": r.Rd_err.tolist(),
                           "target_photons_per_second": 4 * MCML_PHOTONS_PER_S_PER_CORE,
                           "device": r.info["device"]}
    print(f"MC MCML case: {r.photons_per_second:,.0f} photons/s "
          f"({r.info['interactions_per_second']:.3g} interactions/s), Rd {r.Rd.round(4)}")

    out["errors"] = {}
    for name in ("skin1", "skin2", "two_layer"):
        st = PRESETS[name]
        prof = profiles.build_profiles(st)
        h = prof.r_mm[1]
        n = len(prof.r_mm) - 1
        mc = mc_slab.simulate(st, photons=args.photons, r_max_mm=(2 * n + 1) * h / 2,
                         bins=2 * n + 1, seed=1)
        # rebin MC (width h/2 from 0) onto the layer-file rings [kh - h/2, kh + h/2)
        area_f = np.pi * np.diff(mc.r_edges**2)[:, None]
        e = mc.R * area_f
        v = (mc.R_err * area_f) ** 2
        eb = np.vstack([e[:1], e[1:2 * n:2] + e[2:2 * n + 1:2]])
        vb = np.vstack([v[:1], v[1:2 * n:2] + v[2:2 * n + 1:2]])
        area = np.pi * np.diff(np.concatenate([[0.0], (np.arange(n + 1) + 0.5) * h]) ** 2)
        mcR, mcE = eb / area[:, None], np.sqrt(vb) / area[:, None]
        top = st.layers[0]
        mfp = 1 / (np.array(top.sigma_a) + np.array(top.sigma_s_prime))
        entry = {"Rd_multipole": prof.Rd.tolist(), "Rd_mc": mc.Rd.tolist(),
                 "Rd_mc_err": mc.Rd_err.tolist(),
                 "Rd_rel_error": (prof.Rd / mc.Rd - 1).tolist(),
                 "Tt_multipole": prof.Tt.tolist(), "Tt_mc": mc.Tt.tolist(),
                 "mc_photons_per_second": mc.photons_per_second, "radii": {}}
        for mult in (0.5, 1, 2, 4, 8, 16):
            row = []
            for c in range(3):
                k = int(round(mult * mfp[c] / h))
                if k > n or mcR[k, c] <= 0:
                    row.append(None)
                    continue
                row.append({"r_mm": float(prof.r_mm[k]), "multipole": float(prof.R[k, c]),
                            "mc": float(mcR[k, c]), "mc_err": float(mcE[k, c]),
                            "ratio": float(prof.R[k, c] / mcR[k, c])})
            entry["radii"][f"{mult}_mfp"] = row
        out["errors"][name] = entry
        ratios = {m: [None if x is None else round(x["ratio"], 3) for x in row]
                  for m, row in entry["radii"].items()}
        print(f"{name}: Rd multipole {prof.Rd.round(4)} MC {mc.Rd.round(4)} "
              f"+- {mc.Rd_err.round(4)}; R ratio multipole/MC by radius {ratios}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
