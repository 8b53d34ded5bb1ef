"""Benchmark the layer file at the weakly absorbing extremes (test_stability test10 / test11):
build time of two_layer and of two_layer with sigma_a = 0 on both layers, the image
sums of weakly absorbing finite layers against a 4000-pair reference, and the per-example
build times of test11's strategy (whole property domain, derandomized examples).

Usage: python bench/bench_profiles_extreme.py [--out bench/results/profiles_extreme.json]
       [--label after] [--git REV] [--examples 10]

``--git REV`` measures the layer file of revision REV, where it was one module,
stages/profiles.py (loaded from ``git show``), instead of the working tree's optics/ modules;
each run adds or replaces its ``--label`` entry in the JSON.  The machine is
shared: the load average is recorded with every timing.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def _thin_white():
    from dermis.optics.layers import Layer, LayerStack
    return LayerStack((Layer(0.0001137189970100061, 1.0001,
                             (37.55372038574953, 4.8296701934996, 0.0),
                             (50.38233482866731, 83.10638502091724, 87.93605521441684), 0.99),
                       Layer(math.inf, 2.5, (0.00411810463415155, 41.181005160473696,
                                             20.59052317076002),
                             (41.176928236885885, 4.1181046341520035e-05, 20.59052317076002),
                             -0.07790825929450951)), 1.0, 1.4)


@dataclasses.dataclass(frozen=True)
class _Profiles:
    """The functions measured: the working tree's, or those of a revision's stages/profiles.py."""

    build_profiles: object
    diffusion_constants: object
    beam_sources: object
    image_sum: object


def _profiles_module(rev: str | None) -> _Profiles:
    if rev is None:
        from dermis.optics import multipole
        from dermis.optics.layer_profiles import build_profiles
        return _Profiles(build_profiles, multipole.diffusion_constants, multipole.beam_sources,
                         multipole.image_sum)
    src = subprocess.run(["git", "show", f"{rev}:stages/profiles.py"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    path = Path(f"/tmp/dermis_profiles_{rev}.py")
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("_profiles_at_rev", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["_profiles_at_rev"] = mod       # dataclasses look their module up
    spec.loader.exec_module(mod)
    return _Profiles(mod.build_profiles, mod._chan, mod._sources, mod._image_sum)


def _sigma_a_zero(stack):
    from dermis.optics.layers import Layer, LayerStack
    return LayerStack(tuple(Layer(l.thickness_mm, l.eta, (0.0, 0.0, 0.0), l.sigma_s_prime, l.g)
                            for l in stack.layers), stack.eta_above, stack.eta_below)


def _build(P, stack) -> dict:
    import resource
    t0 = time.perf_counter()
    prof = P.build_profiles(stack)
    took = time.perf_counter() - t0
    return {"seconds": took, "load": os.getloadavg(), "poles": prof.info["poles_used"],
            "grid_h_mm": prof.info["grid_h_mm"], "grid_rmax_mm": prof.info["grid_rmax_mm"],
            "Rd": prof.Rd.tolist(), "cutoff_mm": prof.cutoff_mm.tolist(),
            "energy_beyond_table": [float(x) for x in prof.info["energy_beyond_table"]],
            "negative_lobes": len(prof.info["negative_lobes"]),
            "R_at_mm": {str(x): prof.R[int(round(x / prof.r_mm[1]))].tolist()
                        for x in (0.5, 2.0, 10.0, 40.0) if x < prof.r_mm[-1]},
            "maxrss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def _image_sums(P) -> list:
    """Cumulative energy of weakly absorbing single layers: the measured image sum against
    the working tree's with 4000 pairs and the integral tail (relative to the sources'
    energy, at r = 0 .. 10 L)."""
    from dermis.optics import multipole as W
    from dermis.optics.layers import PRESETS, Layer
    top = PRESETS["two_layer"].layers[0]
    cases = [("two_layer epidermis, sigma_a = 0",
              Layer(top.thickness_mm, 1.4, (0.0,) * 3, top.sigma_s_prime, 0.8), 1.0, 1.0),
             ("0.1 mfp, albedo 1, sigma_t 100/mm",
              Layer(1e-3, 1.4, (0.0,) * 3, (100.0,) * 3, 0.0), 1.0, 1.4),
             ("1 mfp, albedo 0.9999", Layer(1.0, 1.0, (1e-4,) * 3, (1 - 1e-4,) * 3, 0.5),
              1.33, 1.0)]
    out = []
    for name, lay, ea, eb in cases:
        ch = P.diffusion_constants(lay, 0, lay.eta / ea, lay.eta / eb, "pbd", None)
        src = P.beam_sources(ch)
        L = ch.d + ch.zb_t + ch.zb_b
        r = np.array([0.0, 0.1, 0.3, 1.0, 3.0, 10.0]) * L
        ref = W.diffusion_constants(lay, 0, lay.eta / ea, lay.eta / eb, "pbd", None)
        ref = dataclasses.replace(ref, poles=4000, reach=math.inf, tail=True)
        src_ref = src                           # the same beam nodes (4000 pairs would cut them)
        row = {"case": name, "pairs": ch.poles, "L_mm": L}
        for side in ("top", "bot"):
            e = P.image_sum(ch, src, side, "energy", r)
            e_ref = W.image_sum(ref, src_ref, side, "energy", r)
            row[f"max_err_{side}"] = float(np.abs(e - e_ref).max() / src.w.sum())
        out.append(row)
    return out


def _property(P, examples: int) -> dict:
    from hypothesis import HealthCheck, assume, given, settings
    import test_stability as T
    times: list = []

    @settings(max_examples=examples, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(stack=T.profile_stacks(full_domain=True))
    def run(stack):
        assume(not all(a == 0 for l in stack.layers for a in l.sigma_a))
        t0 = time.perf_counter()
        P.build_profiles(stack)
        times.append(time.perf_counter() - t0)

    run()
    return {"examples": len(times), "seconds": times, "max_s": max(times),
            "mean_s": sum(times) / len(times), "load": os.getloadavg()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "profiles_extreme.json"))
    ap.add_argument("--label", default="after")
    ap.add_argument("--git", default=None, help="measure the layer file of this rev "
                    "(stages/profiles.py there)")
    ap.add_argument("--examples", type=int, default=10)
    a = ap.parse_args()
    P = _profiles_module(a.git)
    from dermis.optics.layers import PRESETS
    res = {"rev": a.git or "working tree", "date_utc": time.strftime("%Y-%m-%d %H:%M:%S",
                                                                    time.gmtime())}
    res["two_layer"] = _build(P, PRESETS["two_layer"])
    res["two_layer_sigma_a_0"] = _build(P, _sigma_a_zero(PRESETS["two_layer"]))
    res["ratio"] = res["two_layer_sigma_a_0"]["seconds"] / res["two_layer"]["seconds"]
    # test11's slowest example seen at 7436bab (a 1.1e-4 mm layer, albedo 1 in blue: 2000 pairs)
    res["thin_white_stack"] = _build(P, _thin_white())
    res["image_sums"] = _image_sums(P)
    if a.examples > 0:
        res["test11_strategy"] = _property(P, a.examples)
    print(json.dumps(res, indent=1))
    out = Path(a.out)
    data = json.loads(out.read_text()) if out.exists() else {}
    data.setdefault("about", __doc__.splitlines()[0])
    data.setdefault(a.label, {}).update(res)
    out.write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
