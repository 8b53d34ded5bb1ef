"""Benchmark of the adaptive BSSRDF (models/bssrdf_adaptive.py, subsurface/adaptive.py)
against the full BSSRDF: per lighting condition and view of a scene (default:
scenes/default.toml at its size, high mesh; a view's conditions are labelled
"<lighting>@<view>"), the adaptive image's relative RMSE against the full BSSRDF's and of
both against the Mitsuba reference, the seconds of each, and the fraction of pixels and
camera samples gathered (and which predictor flagged them); at the shipped target and at
looser ones (--targets).

How it measures.  The pipeline builds the scene's inputs and both images once (reference
included unless --no-reference); then, per lighting condition, each model's node is re-run
in this process on its cached inputs, ``--repeats`` times, interleaved (full, adaptive,
adaptive, full, ...: the 2-core machine is shared, load drifts), medians kept.  Each call
gets a fresh set of run-wide intermediates except those of the mesh, made once here and
handed over as a run shares them between every image of the mesh: its Embree scene (both
models); the gather's query tiles are dropped before each call (each image pays its own sort).  The
intermediates a run shares between the BSSRDF images of one lighting condition (the
points' octree, their shadow edges, the near-field table, the points' kd-tree:
``subsurface/exitance.py``) are excluded for both models: made by a first call of the full
model and handed to every measured call (``--standalone``: each call makes its own, as when
one BSSRDF image is alone in its run).  Times are the node's
own "total" (its work after the shared visibility: gather or local model + predictor +
gather, exit to radiance, surface term, EXR) and its exitance part alone ("gather").
At the shipped target, both models' exitance is also measured against the brute-force gather
(every point summed) at 4000 random camera samples: the full BSSRDF's own approximation error
(its clusters at epsilon, its tile walk) beside the adaptive model's.
Relative RMSE: sqrt(mean (a - b)^2) / sqrt(mean b^2) over the pixels that hit, all
channels (reports/diff.py's); against the reference the model images are averaged over the
reference's pixels first, then over blocks of 1 and 10 x 10 of them, with the share of the
error the reference's own noise explains (its half-buffers; reports/ground_truth.py ranks
the models by face region with it).  PNGs (tone-mapped full / adaptive, blend mask, |difference| at 1 % of the 99th
percentile = white) go to --png-dir.

Usage: python bench/bench_bssrdf_adaptive.py [--scene FILE] [--cache DIR] [--repeats 3]
       [--lights point,area,...] [--targets 0.01,0.02,0.04] [--no-reference]
       [--png-dir DIR] [--out bench/results/bssrdf_adaptive.json] [--label default]
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import math
import os
import re
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from labelled import save_labelled

REPO = Path(__file__).resolve().parents[1]


def variant(scene: Path, out: Path, reference: bool) -> Path:
    """The scene with [render] models = bssrdf and bssrdf_adaptive on the high mesh, its
    relative asset paths made absolute, no causes (and no reference unless asked)."""
    text = scene.read_text()
    base = scene.parent
    text = re.sub(r'"(assets/[^"]+)"', lambda m: f'"{(base / m.group(1)).as_posix()}"', text)
    text = re.sub(r"^models = .*$", 'models = ["bssrdf", "bssrdf_adaptive"]', text, flags=re.M)
    text = re.sub(r"^geometries = .*$", 'geometries = ["high"]', text, flags=re.M)
    text = re.sub(r'^name = "[^"]*"', 'name = "bench_bssrdf_adaptive"', text, count=1,
                  flags=re.M)
    text = re.sub(r'^output_dir = .*$', f'output_dir = "{(out.parent / "out").as_posix()}"',
                  text, flags=re.M)
    text += f"\n[reference]\nenabled = {'true' if reference else 'false'}\n"
    text += "\n[causes]\nenabled = false\n"
    out.write_text(text)
    return out


def rel_rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = (a - b)[mask]
    return float(np.sqrt((d ** 2).mean()) / np.sqrt((b[mask] ** 2).mean()))


def against_reference(image: np.ndarray, mask: np.ndarray, ref, block: int) -> dict:
    """``image`` (H, W, 3) averaged over the reference's pixels, both then over blocks of
    ``block`` x ``block`` reference pixels whose every camera pixel hit: the relative RMSE
    against the reference, the part of it the reference's own noise explains (its half-
    buffer estimate, reports/ground_truth.py) and the rest, sqrt(rmse^2 - noise^2)."""
    from dermis.geometry.regions import block_mean
    h, w = ref.linear.shape[:2]
    m_img, m_ok = block_mean(image, mask, image.shape[0] // h)
    ok = m_ok & np.asarray(ref.mask, bool)
    r_img, b_ok = block_mean(np.asarray(ref.linear, np.float64), ok, block)
    m_blk, _ = block_mean(m_img, ok, block)
    rms = float(np.sqrt((r_img[b_ok] ** 2).mean()))
    err = float(np.sqrt(((m_blk - r_img)[b_ok] ** 2).mean())) / rms
    out = {"block_reference_pixels": block, "blocks": int(b_ok.sum()), "rel_rmse": err}
    if ref.noise is not None:
        n2, _ = block_mean(np.asarray(ref.noise, np.float64) ** 2, ok, block)
        floor = float(np.sqrt((n2[b_ok] / block ** 2).mean())) / rms
        out.update({"reference_noise": floor,
                    "beyond_noise": math.sqrt(max(err * err - floor * floor, 0.0))})
    return out


class Runner:
    """Re-runs BSSRDF nodes of the planned scene on their cached inputs."""

    # the kinds a run shares between the BSSRDF images of one lighting condition
    SHARED_KINDS = ("octree", "shadow_edges", "near_table", "points_kdtree")

    def __init__(self, scene, cache: Path, standalone: bool = False):
        from dermis.pipeline.graph import key_parts, node_key, plan_order
        from dermis.pipeline.plan import build_graph
        from dermis.pipeline.store import Store
        self.nodes, targets = build_graph(scene)
        self.keys = {}
        for nid in plan_order(self.nodes, targets):
            self.keys[nid] = node_key(key_parts(self.nodes[nid], self.keys))
        self.store = Store(cache)
        self._inputs, self._scenes = {}, {}
        self.env = None
        self.standalone = standalone
        self._kept: dict = {}     # lighting label -> {kind: RecentResults}

    def load(self, nid: str):
        from dermis.pipeline.graph import _load
        if nid not in self._inputs:
            self._inputs[nid] = _load(self.store, nid, self.keys[nid])
        return self._inputs[nid]

    def call(self, nid: str):
        from dermis.lighting.visibility import EMBREE_SCENES, Visibility
        from dermis.pipeline.api import RunContext
        from dermis.pipeline.shared import RunCache
        from dermis.subsurface import gather
        node = self.nodes[nid]
        inputs = {d: self.load(d) for d in node.dep_ids}
        ctx = RunContext(shared=RunCache())
        if not self.standalone:
            from dermis.pipeline.reuse import RecentResults
            label = self.nodes[nid].params["label"]
            if label not in self._kept:
                self._kept = {label: {k: RecentResults(1 << 62) for k in self.SHARED_KINDS}}
            ctx.shared._stores.update(self._kept[label])
        if self.env is not None:
            ctx._env = self.env
        stage = importlib.import_module(node.module)
        ctx.shared = ctx.shared.restricted(tuple(getattr(stage, "SHARES", ())) + node.shares)
        ctx.input_keys = {role: self.keys[d] for role, d in node.deps.items()}
        mesh_key = ctx.input_keys["mesh"]
        mesh = inputs[node.deps["mesh"]]
        if mesh_key not in self._scenes:
            self._scenes[mesh_key] = Visibility(mesh.vertices, mesh.faces)
        ctx.shared.get(EMBREE_SCENES, mesh_key, lambda: self._scenes[mesh_key])
        gather._QUERY_TILES._items.clear()
        ctx.out_dir = Path(tempfile.mkdtemp(prefix="bench-adaptive-"))
        t0, c0 = time.perf_counter(), time.process_time()
        result = node.call(inputs, ctx)
        wall = time.perf_counter() - t0
        # CPU seconds of the process (PoCL's device threads included): less sensitive to
        # other jobs on the machine than wall seconds
        result.artifact.timings["cpu"] = time.process_time() - c0
        self.env = ctx.cl
        return result, wall, ctx.out_dir


def with_target(target: float):
    """Point the registry's bssrdf_adaptive at another target (a bench knob, not a scene
    setting)."""
    from dermis.subsurface.adaptive import AdaptiveOptions, adaptive_exitance
    mod = importlib.import_module("dermis.models.bssrdf_adaptive")
    if not hasattr(mod, "_SHIPPED"):
        mod._SHIPPED = mod.MODEL
    mod.MODEL = dataclasses.replace(mod._SHIPPED, exitance=functools.partial(
        adaptive_exitance, adaptive=AdaptiveOptions(target=target)))


def exitance_inputs(runner, nid: str) -> tuple:
    """((points, irradiance, profile, shading), keywords) the adaptive BSSRDF node ``nid``
    passes to its exitance (the full BSSRDF's are the same but for camera and pixels)."""
    mod = importlib.import_module("dermis.models.bssrdf_adaptive")
    shipped, seen = mod.MODEL, {}

    def spy(points, irradiance, profile, shading, **kw):
        seen.update(args=(points, irradiance, profile, shading), kw=kw)
        return shipped.exitance(points, irradiance, profile, shading, **kw)
    mod.MODEL = dataclasses.replace(shipped, exitance=spy)
    try:
        runner.call(nid)
    finally:
        mod.MODEL = shipped
    return seen["args"], seen["kw"]


def against_brute_force(runner, nid: str, samples: int = 4000, seed: int = 1) -> dict:
    """Both models' exitance at ``samples`` random camera samples of the adaptive image
    ``nid`` against the brute-force gather there (every point summed, no clusters; the full
    BSSRDF's own approximation error, gather epsilon and tile walk, included): relative RMSE
    of each, all channels."""
    from dermis.subsurface.adaptive import adaptive_exitance
    from dermis.subsurface.exitance import ShadingPoints, exitance
    (points, E, profile, sh), kw = exitance_inputs(runner, nid)
    common = dict(lights=kw["lights"], visibility=kw["visibility"])
    full, _ = exitance(points, E, profile, sh, options=kw["options"], shared=kw["shared"],
                       keys=kw["keys"], **common)
    ad, _ = adaptive_exitance(points, E, profile, sh, options=kw["options"],
                              camera=kw["camera"], pixels=kw["pixels"], shared=kw["shared"],
                              keys=kw["keys"], **common)
    pick = np.sort(np.random.default_rng(seed).choice(len(sh.positions),
                                                      min(samples, len(sh.positions)),
                                                      replace=False))
    sub = ShadingPoints(sh.positions[pick], sh.shading_normals[pick], sh.geo_normals[pick],
                        None if sh.visible is None else sh.visible[pick])
    brute, _ = exitance(points, E, profile, sub,
                        options=dataclasses.replace(kw["options"], brute_force=True), **common)
    brute = np.asarray(brute, np.float64)

    def rel(a):
        return float(np.sqrt(((np.asarray(a, np.float64)[pick] - brute) ** 2).mean())
                     / np.sqrt((brute ** 2).mean()))
    return {"samples": int(len(pick)), "bssrdf": rel(full), "bssrdf_adaptive": rel(ad)}


def png(path: Path, image: np.ndarray, scale: float) -> None:
    from PIL import Image
    x = np.clip(image * scale, 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    Image.fromarray((x * 255 + 0.5).astype(np.uint8)).save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(REPO / "scenes" / "default.toml"))
    ap.add_argument("--cache", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lights", default="")
    ap.add_argument("--targets", default="0.01,0.02,0.04")
    ap.add_argument("--no-reference", action="store_true")
    ap.add_argument("--png-dir", default=None)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "bssrdf_adaptive.json"))
    ap.add_argument("--label", default="default")
    ap.add_argument("--standalone", action="store_true",
                    help="each call makes the intermediates a run shares between the BSSRDF "
                         "images of a lighting condition (octree, shadow edges)")
    args = ap.parse_args()
    from dermis.pipeline import api
    from dermis.subsurface.adaptive import TARGET
    work = Path(args.cache or tempfile.mkdtemp(prefix="bench-adaptive-"))
    work.mkdir(parents=True, exist_ok=True)
    scene_file = variant(Path(args.scene), work / "scene.toml", not args.no_reference)
    scene = api.load_scene(scene_file)
    t0 = time.perf_counter()
    api.run(scene, cache=work / "cache", export=False, jobs=1)
    first_run = time.perf_counter() - t0
    runner = Runner(scene, work / "cache", standalone=args.standalone)
    labels = [lab for lab, _ in scene.light_groups()]
    if args.lights:
        labels = [lab for lab in labels if lab in args.lights.split(",")]
    targets = [float(t) for t in args.targets.split(",") if t]
    pngs = Path(args.png_dir) if args.png_dir else None
    if pngs:
        pngs.mkdir(parents=True, exist_ok=True)
    rows = {}
    for lab in labels:
        full_id, ad_id = f"render-bssrdf-{lab}-high", f"render-bssrdf_adaptive-{lab}-high"
        ref_id = f"reference-{lab}"
        ref = runner.load(ref_id) if ref_id in runner.keys else None
        row = {"targets": {}}
        for target in targets:
            with_target(target)
            times = {"bssrdf": [], "bssrdf_adaptive": []}
            outs = {}
            if not args.standalone:
                runner.call(full_id)     # makes the shared intermediates (not measured)
            for r in range(args.repeats):
                order = ("bssrdf", "bssrdf_adaptive") if r % 2 == 0 else ("bssrdf_adaptive",
                                                                         "bssrdf")
                for model in order:
                    res, wall, folder = runner.call(full_id if model == "bssrdf" else ad_id)
                    tm = res.artifact.timings
                    times[model].append({"wall": wall, "cpu": tm["cpu"], "total": tm["total"],
                                         "gather": tm["gather"], **{
                                             k: tm[k] for k in ("local_seconds",
                                                                "predictor_seconds",
                                                                "sample_gather_seconds",
                                                                "adaptive_gather_seconds",
                                                                "surface_reflection")
                                             if k in tm}})
                    outs[model] = (res.artifact, folder)
            full, ad = outs["bssrdf"][0], outs["bssrdf_adaptive"][0]
            mask = np.asarray(full.mask, bool)
            med = {m: {k: statistics.median(t[k] for t in times[m]) for k in times[m][0]}
                   for m in times}
            g = ad.info["gather"]
            entry = {
                "rel_rmse_vs_bssrdf": rel_rmse(ad.linear, full.linear, mask),
                "seconds_median": med, "seconds_all": times,
                "time_ratio_total": med["bssrdf_adaptive"]["total"] / med["bssrdf"]["total"],
                "time_ratio_cpu": med["bssrdf_adaptive"]["cpu"] / med["bssrdf"]["cpu"],
                "time_ratio_exitance": med["bssrdf_adaptive"]["gather"] / med["bssrdf"]["gather"],
                **{k: g[k] for k in g if k.startswith(("gathered", "flagged"))}}
            if target == TARGET:
                entry["exitance_vs_brute_force"] = against_brute_force(runner, ad_id)
            if ref is not None:
                entry["vs_reference"] = {m: [against_reference(img.linear, mask, ref, b)
                                             for b in (1, 10)]
                                         for m, img in (("bssrdf", full),
                                                        ("bssrdf_adaptive", ad))}
            row["targets"][str(target)] = entry
            print(lab, target, {k: (round(v, 4) if isinstance(v, float) else v)
                                for k, v in entry.items() if k not in ("seconds_all",
                                                                       "seconds_median")},
                  {m: round(med[m]["total"], 2) for m in med}, flush=True)
            if pngs and target == TARGET:
                scale = 1.0 / float(np.percentile(full.linear[mask].max(axis=1), 99))
                png(pngs / f"{lab}-full.png", full.linear, scale)
                png(pngs / f"{lab}-adaptive.png", ad.linear, scale)
                diff = np.abs(ad.linear - full.linear).max(axis=2, keepdims=True)
                png(pngs / f"{lab}-diff.png", np.repeat(diff, 3, 2), 100.0 * scale)
                import OpenImageIO as oiio
                blend = next(outs["bssrdf_adaptive"][1].glob("*-blend.exr"))
                w = oiio.ImageBuf(str(blend)).get_pixels(oiio.FLOAT)
                from PIL import Image
                Image.fromarray((np.clip(w[..., 0], 0, 1) * 255 + 0.5).astype(np.uint8)).save(
                    pngs / f"{lab}-blend.png")
        rows[lab] = row
    with_target(TARGET)
    result = {"scene": str(args.scene), "geometry": "high", "repeats": args.repeats,
              "shipped_target": TARGET, "first_run_seconds": first_run,
              "loadavg": os.getloadavg(), "cpus": os.cpu_count(),
              "intermediates": ("made by each image (standalone)" if args.standalone else
                                "shared by both images, excluded: octree, shadow edges, "
                                "near-field table, points' kd-tree, Embree scene"),
              "note": "2-core machine shared with other jobs: times noisy; A/B interleaved, "
                      "medians of the repeats", "lights": rows}
    save_labelled(args.out, args.label, result)
    print("wrote", args.out, "label", args.label)


if __name__ == "__main__":
    main()
