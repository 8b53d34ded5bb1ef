"""One bounce of indirect light (lighting/indirect.py, stage ``indirect``): its sample counts and
what it changes on the default scene.

Three parts (``--parts``), on the default scan (scenes/default.toml, high mesh, point light):

* ``samples`` - the bounce rays per vertex (``[render] indirect_samples``): E_ind at 6000
  random face-region vertices with S = 16 .. 256 rays (two seeds) against S = 4096; the
  noise (RMS of the error, the reference's own subtracted in quadrature) relative to the
  vertex's light E_dir + E_ind, over lit vertices (E_dir > 0) and shadowed ones, and the
  seconds of the whole pass (every vertex) per S.
* ``directions`` - the BRDF response (rendering/indirect_shading.py): the indirect part of
  each BRDF image (200 x 200, spp 4, E_ind from ``--samples`` rays) from the albedo table,
  against S = 1, 4, 16, 64 cosine-weighted directions per camera hit through the model's
  kernel (two seeds): the per-hit estimate's noise relative to the pixel, over the face
  regions' pixels, and its mean against the table's.
* ``scene`` - the pipeline at 200 x 200 with ``indirect`` false and true (same cache): per
  model and face region (geometry/regions.py) the brightening of the region mean, the
  percentiles of the per-pixel brightening over its lit pixels (>= 5 % of the head's mean)
  and what the term adds to the unlit ones (in units of the head's mean); with ``--reference`` the Mitsuba reference
  (100 x 100, 64 spp per seed) and each model's region distance to it
  (reports/ground_truth.py) without and with the term.

    python bench/bench_indirect.py [--parts samples,directions,scene] [--reference]
                                   [--cache /tmp/dermis-bench-indirect] [--label after]

Writes (merging) bench/results/indirect.json under ``--label``.  Timings on the shared
2-core machine move with the other jobs (``loadavg`` beside them).
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from labelled import read_labelled, save_labelled

REPO = Path(__file__).resolve().parents[1]
SIZE = 200
# "Lit" pixels: at least this fraction of the head's mean luminance without the term.
LIT_FRACTION = 0.05
SAMPLES = tuple(int(s) for s in os.environ.get("BENCH_INDIRECT_SAMPLES", "16,32,64,128,256").split(","))


def _scene(cache, indirect: bool, samples: int, reference: bool):
    from dermis.pipeline.config import load_scene
    over = {"camera": {"width": SIZE, "height": SIZE},
            "render": {"models": ["lafortune", "asperity", "hk93", "bssrdf"],
                       "lights": ["point"], "geometries": ["high"], "indirect": indirect,
                       "indirect_samples": samples},
            "output": {"previews": False, "output_dir": str(Path(cache) / "out")}}
    if reference:
        over["reference"] = {"enabled": True, "width": 100, "height": 100, "spp": 64}
    return load_scene(REPO / "scenes" / "default.toml", overrides=over)


def _artifacts(scene, cache, until=None):
    from dermis.pipeline import api
    from dermis.pipeline.artifacts import load
    from dermis.pipeline.store import Store
    summary = api.run(scene, cache=cache, until=until, export=False)
    store = Store(cache)
    # each node's seconds when it was built (a cached node's from its cache entry)
    seconds = {n.id: float(store.meta(n.id, n.key).get("seconds", 0.0)) for n in summary.nodes}
    return ({n.id: (lambda nid=n.id, key=n.key: load(store.artifact_dir(nid, key)))
             for n in summary.nodes}, seconds, summary)


def _lum(x):
    from dermis.rendering.color import LUMINANCE
    return np.asarray(x, np.float64) @ LUMINANCE


def _setup(cache):
    from dermis.geometry.normals import vertex_normals
    from dermis.geometry.regions import face_regions
    from dermis.lighting.irradiance import irradiance
    from dermis.lighting.visibility import Visibility
    scene = _scene(cache, False, 64, False)
    arts, _, _ = _artifacts(scene, cache, until="mesh_high")
    mesh = arts["mesh_high"]()
    vis = Visibility(mesh.vertices, mesh.faces)
    lights = dict(scene.light_groups())["point"]
    v, n = np.asarray(mesh.vertices, np.float32), vertex_normals(mesh)
    e_dir = irradiance(v, n, lights, vis.occluded, seed=scene.mesh.seed)
    lab = np.zeros(len(v), np.int8)
    lab[np.asarray(mesh.faces).ravel()] = np.repeat(face_regions(mesh.vertices, mesh.faces), 3)
    return scene, mesh, vis, lights, v, n, e_dir, lab


def part_samples(cache, res):
    from dermis.lighting.indirect import bounce_irradiance
    from dermis.models.lafortune import LafortuneParams
    scene, mesh, vis, lights, v, n, e_dir, lab = _setup(cache)
    rng = np.random.default_rng(7)
    sub = rng.choice(np.flatnonzero(lab > 0), 6000, replace=False)
    alb = LafortuneParams().rho_d
    run = lambda s, seed, idx=sub: bounce_irradiance(v[idx], n[idx], mesh, e_dir, vis,  # noqa
                                                     samples=s, seed=seed, fallback_albedo=alb)
    t0 = time.perf_counter()
    ref = _lum(run(4096, 99))
    out = {"vertices": int(len(v)), "subset": int(len(sub)), "reference_samples": 4096,
           "reference_seconds": time.perf_counter() - t0, "per_samples": {}}
    light = _lum(e_dir[sub]) + ref
    lit = _lum(e_dir[sub]) > 0
    for s in SAMPLES:
        errs = np.concatenate([(_lum(run(s, seed)) - ref) for seed in (0, 1)])
        both = np.concatenate([np.arange(len(sub))] * 2)
        rec = {}
        # RMS noise in units of the mean light over each set (per-vertex ratios would blow
        # up at the terminator, where E_dir -> 0); the reference's own variance (s / 4096
        # of an estimate's) subtracted
        for name, sel in (("lit", lit), ("shadowed", ~lit), ("all", np.ones_like(lit))):
            e = errs[sel[both]]
            ms = float(np.mean(e * e)) / (1.0 + s / 4096.0)
            rec[name] = {"noise_vs_light": float(np.sqrt(ms) / light[sel].mean()),
                         "noise_vs_indirect": float(np.sqrt(ms) / ref[sel].mean()),
                         "indirect_share": float(ref[sel].mean() / light[sel].mean()),
                         "vertices": int(sel.sum())}
        t0 = time.perf_counter()
        if s <= 256:   # the whole pass, every vertex (the stage's work after E_dir)
            bounce_irradiance(v, n, mesh, e_dir, vis, samples=s, seed=0, fallback_albedo=alb)
            rec["all_vertices_seconds"] = time.perf_counter() - t0
            rec["loadavg"] = list(os.getloadavg())
        out["per_samples"][str(s)] = rec
        print(s, rec, flush=True)
    res["samples"] = out


def _per_hit_mc(directions: int, seed: int):
    """The alternative to the albedo table: each hit's rho_dh E_ind / pi from ``directions``
    cosine-weighted directions about its shading normal through the model's kernel
    (weights E_ind / (S cos)), with the signature of ``indirect_radiance``."""
    from dermis.lighting.visibility import interpolate
    from dermis.lighting.strata import stratified_2d
    from dermis.lighting.warps import cosine_hemisphere

    def radiance(px, make_shader, faces, vertex_irradiance):
        shader, s = make_shader(px), directions
        e = interpolate(vertex_irradiance, faces, px.samples.tri, px.samples.bary)
        u = stratified_2d(np.random.default_rng(seed), len(e), s)
        d, cos = cosine_hemisphere(u, np.asarray(px.surf["shading_normal"], np.float64))
        w = e[:, None, :] / (s * np.maximum(cos, 1e-12))[..., None]
        gidx = np.repeat(np.arange(len(e), dtype=np.int32), s)
        out, _ = shader(gidx, d.reshape(-1, 3).astype(np.float32),
                        w.reshape(-1, 3).astype(np.float32))
        return px.pixels(out.reshape(len(e), s, 3).sum(axis=1)).astype(np.float64)
    return radiance


def part_directions(cache, res, samples: int):
    import dermis.rendering.shade as shade
    from dermis.lighting.indirect import bounce_irradiance
    from dermis.models.lafortune import LafortuneParams
    from dermis.pipeline import registry
    from dermis.rendering.cast import cast
    from dermis.rendering.options import RenderOptions
    from dermis.reports.ground_truth import region_labels_for
    scene, mesh, vis, lights, v, n, e_dir, lab = _setup(cache)
    e_ind = bounce_irradiance(v, n, mesh, e_dir, vis, samples=samples, seed=0,
                              fallback_albedo=LafortuneParams().rho_d)
    cam = scene.camera
    px_samples = cast(mesh, list(lights), cam, RenderOptions(spp=4, seed=1, visibility=vis))
    regions = region_labels_for(mesh, cam, width=cam.width, height=cam.height) > 0
    out = {"e_ind_samples": samples, "per_model": {}}
    table = shade.indirect_radiance
    try:
        for name in ("lafortune", "asperity", "hk93"):
            m = registry.model(name)
            base_name = scene.render.asperity_base if m.bases else None
            cfg = {"optics": scene.optics.to_dict(), "asperity_base": base_name}
            p = m.scene_params(cfg, None)
            bp = m.base(base_name).scene_params(cfg, None) if base_name else None
            opts = dict(samples=px_samples, base=base_name, base_params=bp)
            direct = shade.render(mesh, [], m, p, cam, RenderOptions(**opts)).linear

            def part(method):
                shade.indirect_radiance = method
                t0 = time.perf_counter()
                img = shade.render(mesh, [], m, p, cam, RenderOptions(indirect=e_ind, **opts))
                return _lum(img.linear - direct), time.perf_counter() - t0
            tab, t_tab = part(table)
            total = _lum(direct) + tab
            sel = regions & (total > 0)
            rec = {"table": {"render_seconds": t_tab, "indirect_share": float(np.mean(
                tab[sel] / total[sel]))}}
            for s in (1, 4, 16, 64):
                (a, t), (b, _) = part(_per_hit_mc(s, 0)), part(_per_hit_mc(s, 1))
                rel = (a - b)[sel] / np.sqrt(2.0) / total[sel]
                rec[f"per_hit_{s}"] = {
                    "rel_noise": float(np.sqrt(np.mean(rel * rel))),
                    # the two estimators' means over the face (the table's bias, if any)
                    "mean_vs_table": float(0.5 * (a + b)[sel].sum() / tab[sel].sum() - 1),
                    "render_seconds": t}
                print(name, s, rec[f"per_hit_{s}"], flush=True)
            out["per_model"][name] = rec
    finally:
        shade.indirect_radiance = table
    res["directions"] = out


def _region_table(images, labels):
    """Per model and region: mean luminance; per-pixel values for percentiles."""
    from dermis.geometry.regions import REGION_LABELS, REGIONS
    out = {}
    for name, img in images.items():
        lum = _lum(img.linear)
        out[name] = {r: lum[labels == REGION_LABELS[r]] for r in REGIONS}
        out[name]["head"] = lum[labels > 0]
    return out


def part_scene(cache, res, samples: int, reference: bool):
    from dermis.reports.ground_truth import ground_truth_metrics, region_labels_for
    out = {"size": SIZE, "indirect_samples": samples, "reference": reference, "models": {}}
    runs = {}
    for on in (False, True):
        scene = _scene(cache, on, samples, reference)
        arts, seconds, _ = _artifacts(scene, cache)
        out[f"node_seconds_{'on' if on else 'off'}"] = sum(seconds.values())
        if on:
            out["node_seconds"] = {k: v for k, v in seconds.items()
                                   if k.startswith(("indirect", "irradiance", "render"))}
        images = {m: arts[f"render-{m}-point-high"]() for m in
                  ("lafortune", "asperity", "hk93", "bssrdf")}
        runs[on] = (scene, arts, images)
    scene, arts, _ = runs[True]
    mesh = arts["mesh_high"]()
    labels = region_labels_for(mesh, scene.camera, width=SIZE, height=SIZE)
    off, on = _region_table(runs[False][2], labels), _region_table(runs[True][2], labels)
    for m in off:
        rec = {}
        # lit pixels: at least LIT_FRACTION of the head's mean without the term (the per-pixel
        # ratio is meaningless where a pixel was ~0: in a BRDF model's point-light shadow)
        lit_level = LIT_FRACTION * off[m]["head"].mean()
        for r in off[m]:
            a, b = off[m][r], on[m][r]
            if not len(a):
                continue
            ok = a >= lit_level
            ratio = b[ok] / a[ok] - 1.0
            rec[r] = {"pixels": int(len(a)), "mean_off": float(a.mean()),
                      "mean_on": float(b.mean()), "brighter": float(b.mean() / a.mean() - 1),
                      "lit_pixels": int(ok.sum()),
                      "lit_mean_brighter": float(b[ok].mean() / a[ok].mean() - 1)
                      if ok.any() else 0.0,
                      "lit_pixel_p50": float(np.percentile(ratio, 50)) if ok.any() else 0.0,
                      "lit_pixel_p90": float(np.percentile(ratio, 90)) if ok.any() else 0.0,
                      "lit_pixel_p99": float(np.percentile(ratio, 99)) if ok.any() else 0.0,
                      "unlit_added_vs_head_mean": float((b[~ok] - a[~ok]).mean()
                                                        / off[m]["head"].mean())
                      if (~ok).any() else 0.0}
        out["models"][m] = {"regions": rec}
    if reference:
        refs = {"point": arts["reference-point"]()}
        for on_ in (False, True):
            gt = ground_truth_metrics({m: im for m, im in runs[on_][2].items()}, refs,
                                      mesh=mesh, camera=scene.camera)
            for key, rec in gt["models"].items():
                m = rec["model"]
                for r, g in rec["regions"].items():
                    d = out["models"][m]["regions"].setdefault(r, {})
                    d[f"vs_reference_{'on' if on_ else 'off'}"] = g["rel_lum"]
                    d["reference_sigma"] = g["sigma_lum"]
        for m in out["models"]:
            for r, d in out["models"][m]["regions"].items():
                if "vs_reference_off" in d and d["vs_reference_off"] != 0:
                    d["darkening_removed"] = 1.0 - d["vs_reference_on"] / d["vs_reference_off"]
    res["scene"] = out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="samples,directions,scene")
    ap.add_argument("--samples", type=int, default=None,
                    help="bounce rays per vertex for directions/scene (default: the scene's)")
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--cache", default="/tmp/dermis-bench-indirect")
    ap.add_argument("--label", default="after")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "indirect.json"))
    args = ap.parse_args()
    import dermis
    from dermis.pipeline.config import RenderConfig
    samples = args.samples or RenderConfig().indirect_samples
    res = read_labelled(args.out).get(args.label, {})
    res.update({"dermis": str(Path(dermis.__file__).parent),
                "loadavg_start": list(os.getloadavg()),
                "note": "default scan, high mesh, point light; 2-core shared machine"})
    cache = Path(args.cache) / "cache"
    for part in args.parts.split(","):
        if part == "samples":
            part_samples(cache, res)
        elif part == "directions":
            part_directions(cache, res, samples)
        elif part == "scene":
            part_scene(cache, res, samples, args.reference)
        save_labelled(args.out, args.label, res)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
