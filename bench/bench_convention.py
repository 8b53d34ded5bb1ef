"""Benchmark the albedo convention: what a flat plate of skin reflects per unit of albedo in
every model and in the path tracer (docs/ground-truth.md, "The albedo convention").

Writes ``bench/results/convention.json``:

* ``models``: per model (lafortune, hk93, asperity on its default Lambert base, bssrdf) and
  light (directional at normal and 60 deg incidence, uniform sky) the exitance per unit
  irradiance at albedo 0 (its surface term) and per unit albedo above it (the albedo part),
  from the models' own code (tests/flat_plate.py);
* ``exact``: the albedo part of the exact plane-parallel transport of the stack behind a
  smooth boundary (adding-doubling) under the convention;
* ``mitsuba``: the untextured slab, rough (the reference's GGX boundary) and smooth
  (Mitsuba's ``dielectric``), total and black-interior readings at each light with
  standard errors, and the albedo part per unit albedo under the convention
  (subsurface reflectance over the normal-incidence reflectance per entered flux);
  ``rough_vs_smooth``: the ratio of the two, the reference boundary's own error
  (tests/test_convention.py states it for the uniform sky);
* ``reciprocity``: the slab at normal incidence measured both ways, a directional light
  with an irradiance meter (two runs: heavy-tailed, trap 10) and the radiance meter under
  the sky (:func:`dermis.groundtruth.slab.slab_reflectance`), with their standard errors
  and times.

    python3 bench/bench_convention.py [--samples 1048576] [--preset two_layer]
                                      [--only-reciprocity]

CPU: ~5 min on 2 idle cores at the default samples.
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
sys.path.insert(0, str(REPO / "tests"))


def mitsuba_slab(mi, stack, roughness, samples, batches) -> dict:
    """Rough and smooth untextured slabs under each light (see the module docstring)."""
    import numpy as np
    from dermis.groundtruth.slab import (irradiance_meter, meter_reading, slab_scene_dict)
    out = {}
    for boundary, alpha in (("rough", roughness), ("smooth", 0.0)):
        rec = {}
        for black in (False, True):
            for light, view in (("normal", 0.0), ("oblique", 60.0), ("sky", None)):
                d = slab_scene_dict(mi, stack, alpha, black=black,
                                    view_deg=view if view is not None else 0.0)
                sensor, scale = "meter", 1.0
                if view is None:
                    d.pop("meter")
                    d["irr_shape"] = irradiance_meter(mi, "irr", (0.0, 0.0, 0.0))
                    sensor, scale = "irr", 1.0 / math.pi
                t0 = time.perf_counter()
                m, se = meter_reading(mi, mi.load_dict(d), sensor, samples=samples,
                                      batches=batches, seed=11 + black)
                rec[f"{light}{'_black' if black else ''}"] = {
                    "mean": (m * scale).tolist(), "stderr": (se * scale).tolist(),
                    "seconds": time.perf_counter() - t0, "samples": samples}
                print(boundary, light, "black" if black else "", m * scale, se / m, flush=True)
        sub = {k: np.asarray(rec[k]["mean"]) - np.asarray(rec[f"{k}_black"]["mean"])
               for k in ("normal", "oblique", "sky")}
        sub_se = {k: np.hypot(rec[k]["stderr"], rec[f"{k}_black"]["stderr"]) for k in sub}
        spec0 = np.asarray(rec["normal_black"]["mean"])
        rd_entered = sub["normal"] / (1.0 - spec0)
        rec["albedo_part"] = {k: (sub[k] / rd_entered).tolist() for k in sub}
        # relative standard error of the albedo part: its reading and the normaliser's
        rec["albedo_part_rel_stderr"] = {
            k: (np.hypot(sub_se[k] / sub[k], sub_se["normal"] / sub["normal"])
                if k != "normal" else sub_se["normal"] * 0).tolist() for k in sub}
        rec["Rd_entered"] = rd_entered.tolist()
        out[boundary] = rec
    ratio, ratio_se = {}, {}
    for k in ("normal", "oblique", "sky"):
        r, s = (np.asarray(out[b]["albedo_part"][k]) for b in ("rough", "smooth"))
        ratio[k] = (r / s).tolist()
        ratio_se[k] = (r / s * np.hypot(out["rough"]["albedo_part_rel_stderr"][k],
                                        out["smooth"]["albedo_part_rel_stderr"][k])).tolist()
    out["rough_vs_smooth"] = ratio
    out["rough_vs_smooth_stderr"] = ratio_se
    return out


def reciprocity(mi, stack, roughness, samples, batches, repeats: int = 2) -> dict:
    """The slab at normal incidence both ways: a directional light with an irradiance meter
    (``repeats`` independent runs of 4 x ``samples`` paths: its estimate is heavy-tailed,
    ground-truth.md trap 10, so its standard error is itself uncertain) and the radiance
    meter under the sky (:func:`dermis.groundtruth.slab.slab_reflectance`)."""
    import numpy as np
    from dermis.groundtruth.scene_export import rgb_spectrum
    from dermis.groundtruth.slab import (irradiance_meter, meter_reading, slab_reflectance,
                                         slab_scene_dict)
    r = slab_reflectance(mi, stack, roughness=roughness, samples=samples, batches=batches,
                         seed=31)
    out = {"radiance_meter_sky": {"Rd": r.Rd.tolist(), "stderr": r.Rd_stderr.tolist(),
                                  "specular": r.specular.tolist(), "seconds": r.seconds,
                                  "samples": samples}, "directional": []}
    for rep in range(repeats):
        run = {}
        for black in (False, True):
            d = slab_scene_dict(mi, stack, roughness, black=black)
            for k in ("sky", "meter"):
                d.pop(k)
            d["light"] = {"type": "directional", "direction": [0.0, 0.0, -1.0],
                          "irradiance": rgb_spectrum((1.0, 1.0, 1.0))}
            d["irr_shape"] = irradiance_meter(mi, "irr", (0.0, 0.0, 0.0), half_mm=10.0)
            t0 = time.perf_counter()
            m, se = meter_reading(mi, mi.load_dict(d), "irr", samples=4 * samples,
                                  batches=4 * batches, seed=21 + black + 100 * rep)
            run["total_black" if black else "total"] = {
                "mean": m.tolist(), "stderr": se.tolist(), "seconds": time.perf_counter() - t0}
        rd = np.asarray(run["total"]["mean"]) - np.asarray(run["total_black"]["mean"])
        se = np.hypot(run["total"]["stderr"], run["total_black"]["stderr"])
        run.update(Rd=rd.tolist(), Rd_stderr=se.tolist(), samples=4 * samples,
                   relative_difference=(rd / r.Rd - 1.0).tolist(),
                   difference_in_sigma=((rd - r.Rd) / np.hypot(se, r.Rd_stderr)).tolist())
        out["directional"].append(run)
        print("reciprocity", rep, run["relative_difference"], run["difference_in_sigma"],
              flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1 << 20)
    ap.add_argument("--batches", type=int, default=16)
    ap.add_argument("--preset", default="two_layer")
    ap.add_argument("--roughness", type=float, default=0.3)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "convention.json"))
    ap.add_argument("--only-reciprocity", action="store_true",
                    help="recompute the reciprocity check alone into the existing --out file")
    a = ap.parse_args()
    import numpy as np
    import flat_plate as fp
    from dermis.groundtruth.mitsuba import load_mitsuba
    from dermis.optics.layers import PRESETS
    from dermis.pipeline.cl import get_env
    stack = PRESETS[a.preset]
    if a.only_reciprocity:
        mi = load_mitsuba()
        out = json.loads(Path(a.out).read_text())
        out["reciprocity"] = reciprocity(mi, stack, a.roughness, a.samples // 2, a.batches)
        Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
        return
    env = get_env()
    t0 = time.perf_counter()
    models = {}
    for name in ("lafortune", "hk93", "asperity"):
        z, o = (fp.brdf_plate(env, name, stack, np.full(3, v)) for v in (0.0, 1.0))
        models[name] = {k: {"surface": z[k].tolist(), "albedo_part": (o[k] - z[k]).tolist()}
                        for k in z}
    b = fp.bssrdf_plate(env, stack, [np.zeros(3), np.ones(3)])
    models["bssrdf"] = {k: {"surface": v[0].tolist(), "albedo_part": (v[1] - v[0]).tolist()}
                        for k, v in b.items()}
    exact = {k: v.tolist() for k, v in fp.exact_albedo_part(stack).items()}
    print(json.dumps(models, indent=1), exact, flush=True)
    mi = load_mitsuba()
    out = {"preset": a.preset, "roughness": a.roughness, "samples": a.samples,
           "batches": a.batches, "variant": mi.variant(), "models": models, "exact": exact}
    out["mitsuba"] = mitsuba_slab(mi, stack, a.roughness, a.samples, a.batches)
    out["reciprocity"] = reciprocity(mi, stack, a.roughness, a.samples // 2, a.batches)
    out["seconds"] = time.perf_counter() - t0
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out["mitsuba"]["rough_vs_smooth"]))


if __name__ == "__main__":
    main()
