"""Benchmark of the BSSRDF images: seconds per 800x800 image and per lighting
condition (irradiance pass, gather, surface term) on the high and the low mesh, the
gather's error against brute force, peak memory; the knife-edge error; the models'
directional albedo; HK93 against the layer profile's Rd.

Runs the pipeline itself (``python -m dermis.pipeline.cli``) on a variant of a scene
(default: scenes/default.toml, the Lee Perry-Smith scan at 800x800) that renders only the
BSSRDF, in a scratch cache; then re-runs the ``bssrdf`` stage alone (--force bssrdf, the
irradiance cached) in a fresh process whose peak resident memory is recorded.  Times come
from each node's meta.json.  It works with any version of dermis that ``python3 -m
dermis.pipeline.cli`` imports (set PYTHONPATH to benchmark another checkout: the "before"
numbers of bench/results/bssrdf.json came from git 6ec7c04 that way, with
``--label before --scene <that checkout>/scenes/default.toml``).

Usage: python bench/bench_bssrdf.py [--scene FILE] [--geometries high,low_bump]
       [--lights point,area,dir_left+dir_right,sunset] [--cache DIR] [--label after]
       [--out bench/results/bssrdf.json] [--skip-pipeline] [--brute-queries 4000] [--spp N]
       [--skip-energy] [--extra knife,edge,cpu,irradiance [--only-extra]] [--cpu-passes N]
The 2-core machine is shared with other jobs: treat the times as noisy (+-30 %).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from labelled import read_labelled, save_labelled

REPO = Path(__file__).resolve().parents[1]


def variant(scene: Path, out: Path, geometries, lights, spp: int | None = None) -> Path:
    """The scene with [render] models = bssrdf only, the given geometries and lights (and
    ``spp`` camera samples per pixel if given), its relative asset paths made absolute (the
    variant lives elsewhere)."""
    text = scene.read_text()
    base = scene.parent
    text = re.sub(r'"(assets/[^"]+)"', lambda m: f'"{(base / m.group(1)).as_posix()}"', text)
    text = re.sub(r"^models = .*$", 'models = ["bssrdf"]', text, flags=re.M)
    text = re.sub(r"^geometries = .*$", "geometries = [" + ", ".join(f'"{g}"' for g in geometries)
                  + "]", text, flags=re.M)
    text = re.sub(r'^lights = \[".*$', "lights = [" + ", ".join(f'"{l}"' for l in lights) + "]",
                  text, flags=re.M)
    text = re.sub(r'^name = "[^"]*"', 'name = "bench_bssrdf"', text, count=1, flags=re.M)
    if spp is not None:
        text = re.sub(r"^spp = .*$\n?", "", text, flags=re.M)
        text = re.sub(r"^(models = .*)$", rf"\1\nspp = {int(spp)}", text, count=1, flags=re.M)
    out.write_text(text)
    return out


_CHILD = """
import resource, runpy, sys
sys.argv = ["dermis"] + sys.argv[1:]
try:
    runpy.run_module("dermis.pipeline.cli", run_name="__main__")
finally:
    u = resource.getrusage(resource.RUSAGE_SELF)
    print("PEAK_RSS_KIB", u.ru_maxrss, "CPU_S", u.ru_utime + u.ru_stime, flush=True)
"""


def cli(args, cache: Path) -> tuple[float, int, float]:
    """Run the dermis CLI in a child process: (wall seconds, the child's own peak RSS in
    KiB, its CPU seconds over all threads)."""
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _CHILD, *args, "--cache", str(cache), "-q"],
                         check=True, cwd=cache.parent, capture_output=True, text=True)
    sys.stdout.write(out.stdout[-2000:])
    peak, cpu = re.findall(r"PEAK_RSS_KIB (\d+) CPU_S ([0-9.]+)", out.stdout)[-1]
    return time.perf_counter() - t0, int(peak), float(cpu)


def node_meta(cache: Path, prefix: str) -> dict:
    """meta.json of each node; of a node's several keys (runs sharing a cache), the newest."""
    out = {}
    for f in sorted(glob.glob(str(cache / f"{prefix}*" / "*" / "meta.json"))):
        d = json.loads(Path(f).read_text())
        if d["node"] not in out or d.get("finished", "") >= out[d["node"]].get("finished", ""):
            out[d["node"]] = d
    return out


def pipeline(args) -> dict:
    work = Path(args.cache).resolve()
    work.mkdir(parents=True, exist_ok=True)
    toml = variant(Path(args.scene).resolve(), work / "scene.toml", args.geometries, args.lights,
                   args.spp)
    cache = work / "cache"
    first, _, _ = cli(["run", str(toml)], cache)
    again, peak_kib, cpu = cli(["run", str(toml), "--force", "bssrdf"], cache)
    res = {"first_run_seconds": first, "bssrdf_rerun_seconds": again,
           "bssrdf_rerun_cpu_seconds": cpu, "bssrdf_rerun_peak_rss_mib": peak_kib / 1024.0,
           "irradiance": {}, "images": {}}
    for nid, d in node_meta(cache, "irradiance-").items():
        res["irradiance"][nid] = {"seconds": d["seconds"],
                                  "points": d.get("info", {}).get("points")}
    for nid, d in node_meta(cache, "samples-").items():
        res.setdefault("samples", {})[nid] = {"seconds": d["seconds"], **{
            k: d.get("info", {}).get(k) for k in ("points", "spacing_mm")}}
    for nid, d in node_meta(cache, "render-bssrdf-").items():
        t = d.get("info", {}).get("timings", {})
        res["images"][nid] = {"seconds": d["seconds"], **{k: t.get(k) for k in (
            "visibility", "gather", "edges_seconds", "near_seconds", "surface_reflection",
            "total", "kernel_seconds")}}
    return res


# ------------------------------------------------------------------------ accuracy (new code)
def brute_force_error(cache: Path, n_queries: int) -> dict:
    """Relative RMSE of the shipped exitance against the brute-force gather (every point,
    no clustering, no expansion) on random front-facing pixels, per lighting condition
    (the high mesh).  The near field is exact either way; the difference is the far part's
    clustering."""
    from dermis.geometry.normals import vertex_normals
    from dermis.pipeline import artifacts
    from dermis.pipeline.cl import get_env
    from dermis.pipeline.config import BssrdfConfig, load_scene
    from dermis.lighting.visibility import Visibility
    from dermis.rendering.camera import camera_rays
    from dermis.optics.transmittance import Transmittance
    from dermis.subsurface.exitance import ExitanceOptions, ShadingPoints, exitance
    ld = lambda n: artifacts.load(glob.glob(str(cache / n / "*"))[0])  # noqa: E731
    mesh, pts, prof = ld("mesh_high"), ld("samples-mesh_high"), ld("profiles")
    scene = load_scene(str(cache.parent / "scene.toml"))
    vis = Visibility(mesh.vertices, mesh.faces)
    o, d = camera_rays(scene.camera)
    h = vis.intersect(o, d)
    tri, b = h.tri[h.hit], h.bary[h.hit]
    F, V = mesh.faces[tri], mesh.vertices
    w = np.stack([1 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)
    pos = (V[F] * w[..., None]).sum(1)
    ng = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    ns = (vertex_normals(mesh)[F] * w[..., None]).sum(1)
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    wo = -d[h.hit]
    front = ((ng * wo).sum(1) > 0) & ((ns * wo).sum(1) > 0)
    pick = np.random.default_rng(0).choice(np.flatnonzero(front), n_queries, replace=False)
    cfg = BssrdfConfig()
    eta = scene.optics.layers[0].eta / scene.optics.eta_above
    T = Transmittance(eta, cfg.surface_reflection)
    env = get_env()
    out = {}
    for label, lights in scene.light_groups():
        try:
            irr = ld(f"irradiance-mesh_high-{label}")
        except IndexError:
            continue
        shading = ShadingPoints(pos[pick], ns[pick], ng[pick])
        kw = dict(lights=lights, visibility=vis)
        t0 = time.perf_counter()
        m, st = exitance(pts, irr.irradiance, prof, shading, **kw, options=ExitanceOptions(
            epsilon=cfg.epsilon, transmittance=T, env=env))
        t1 = time.perf_counter()
        mb, _ = exitance(pts, irr.irradiance, prof, shading, **kw, options=ExitanceOptions(
            epsilon=None, brute_force=True, transmittance=T, env=env))
        t2 = time.perf_counter()
        rmse = np.sqrt(((m - mb) ** 2).mean(0) / np.maximum((mb ** 2).mean(0), 1e-30))
        out[label] = {"queries": n_queries, "rel_rmse": float(rmse.max()),
                      "max_rel_err": float(np.max(np.abs(m - mb).max(0) / np.maximum(
                          np.abs(mb).max(0), 1e-30))), "seconds": t1 - t0,
                      "brute_seconds": t2 - t1, "near_field": st["near_field"]}
    return out


# ------------------------------------------------------------------------ knife edge, colour
def knife_edge_table() -> dict:
    """Max |error| / (E Rd) per channel of tests/test_knife_edge.py's knife edge per preset, at
    the shipped settings and at the old default (point_density 0.02 with no mean-free-path
    cap, no near field: the thesis's point gather alone)."""
    import math
    sys.path.insert(0, str(REPO / "tests"))
    import test_knife_edge as K
    from dermis.pipeline.cl import get_env
    from dermis.pipeline.config import BssrdfConfig
    from dermis.optics.layers import PRESETS
    from dermis.optics.layer_profiles import build_profiles
    from dermis.subsurface import points as S
    env, out = get_env(), {}
    for preset in ("two_layer", "skin1", "skin2"):
        prof, stack = build_profiles(PRESETS[preset]), PRESETS[preset]
        t0 = time.perf_counter()
        new = np.abs(K.knife_edge(prof, stack, env)[0]).max(0)
        took = time.perf_counter() - t0
        cap, S.MFP_CAP_MM = S.MFP_CAP_MM, math.inf
        try:
            old_spacing = S.spacing_from_mfp(stack, 0.02)
            old = np.abs(K.knife_edge(prof, stack, env, density=0.02, near_field=False)[0]).max(0)
        finally:
            S.MFP_CAP_MM = cap
        out[preset] = {"max_err_rgb": new.round(4).tolist(), "seconds": took,
                       "spacing_mm": S.spacing_from_mfp(stack, BssrdfConfig().point_density),
                       "old_default_max_err_rgb": old.round(4).tolist(),
                       "old_spacing_mm": old_spacing,
                       "half_energy_radius_mm": K.half_energy_radius(prof).round(4).tolist()}
        print(preset, out[preset], flush=True)
    return out


def shadow_edge_colour(cache: Path, exr: Path, light_name: str = "point") -> dict:
    """Mean linear RGB of a BSSRDF image's cast-shadow pixels by their distance (mm, on the
    surface: 3-D distance of the pixel-centre hits) to the nearest lit pixel, and of the lit
    pixels within 1 mm of a shadowed one.  Cast shadow: facing the light (cos > 0.3) but
    occluded (the nose's, the ears' and the eyelids' shadows under the point light)."""
    from scipy.spatial import cKDTree
    from dermis.pipeline import artifacts
    from dermis.pipeline.config import load_scene
    from dermis.pipeline.imageio import read_image
    from dermis.lighting.visibility import Visibility
    from dermis.rendering.camera import camera_rays
    mesh = artifacts.load(glob.glob(str(cache / "mesh_high" / "*"))[0])
    scene = load_scene(str(cache.parent / "scene.toml"))
    light = next(l for l in scene.lights if l.name == light_name)
    vis = Visibility(mesh.vertices, mesh.faces)
    o, d = camera_rays(scene.camera)
    h = vis.intersect(o, d)
    F, V, b = mesh.faces[h.tri[h.hit]], mesh.vertices, h.bary[h.hit]
    w = np.stack([1 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)
    pos = (V[F] * w[..., None]).sum(1)
    ng = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    ng *= np.sign(((-d[h.hit]) * ng).sum(1))[:, None]
    if light.type == "point":
        L = np.asarray(light.position) - pos
        dist = np.linalg.norm(L, axis=1)
        L /= dist[:, None]
    else:
        L = np.tile(np.asarray(light.direction) / np.linalg.norm(light.direction), (len(pos), 1))
        dist = np.full(len(pos), np.inf)
    blocked = vis.occluded(pos, ng, L.astype(np.float32), dist.astype(np.float32))
    img = read_image(exr)[..., :3].reshape(-1, 3)[np.flatnonzero(h.hit)].astype(np.float64)
    facing = (L * ng).sum(1) > 0.3
    lit, shad = facing & ~blocked, facing & blocked
    ds = cKDTree(pos[lit]).query(pos[shad])[0]
    dl = cKDTree(pos[shad]).query(pos[lit])[0]
    ref = img[lit][dl <= 1.0].mean(0)
    out = {"image": str(exr), "lit_0-1mm": {"pixels": int((dl <= 1.0).sum()),
                                             "rgb_over_G": (ref / ref[1]).round(3).tolist()}}
    for lo, hi in ((0.0, 0.5), (0.5, 1.5), (1.5, 3.0)):
        band = (ds > lo) & (ds <= hi)
        m = img[shad][band].mean(0)
        out[f"shadow_{lo}-{hi}mm"] = {"pixels": int(band.sum()),
                                      "rgb_over_G": (m / m[1]).round(3).tolist(),
                                      "relative_to_lit_over_G": ((m / ref) / (m / ref)[1]
                                                                 ).round(3).tolist(),
                                      "luminance_fraction_of_lit": float(
                                          (m @ [0.2126, 0.7152, 0.0722])
                                          / (ref @ [0.2126, 0.7152, 0.0722]))}
    return out


def image_cpu(cache: Path, passes: int = 1) -> dict:
    """Wall and CPU seconds (all threads) of each BSSRDF image re-rendered alone in this
    process (its inputs, the irradiance included, loaded from the cache), ``passes`` times
    over the 8 images: the last pass is recorded per image, earlier ones under
    "pass<k>" (the first pass pays the OpenCL program builds unless the cache was stale,
    and the first image of each mesh what this process keeps across runs)."""
    from dermis.pipeline import api
    scene = api.load_scene(str(cache.parent / "scene.toml"))
    api.run(scene, cache=cache, notice=lambda s: None, export=False)
    out = {}
    for k in range(1, passes + 1):
        rec = out if k == passes else out.setdefault(f"pass{k}", {})
        for label, _ in scene.light_groups():
            for geom in scene.render.geometries:
                nid = f"render-bssrdf-{label}-{geom}"
                la, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
                api.run(scene, cache=cache, force=[nid], notice=lambda s: None, export=False)
                rec[nid] = {"wall_s": time.perf_counter() - t0,
                            "cpu_s": time.process_time() - c0, "loadavg": list(la)}
                print(f"pass {k}", nid, rec[nid], flush=True)
    return out


def irradiance_profile(cache: Path, mesh_node: str = "mesh_low", light_name: str = "sunset",
                       ) -> dict:
    """The irradiance pass of one mesh and light in this process: wall/CPU seconds and noise
    (relative RMS difference of two seeds' point luminance / sqrt 2) per environment strategy,
    and a cProfile of the default one (which part dominates: numpy sampling or Embree)."""
    import cProfile
    import pstats
    from dermis.pipeline import artifacts
    from dermis.pipeline.config import BssrdfConfig, load_scene
    from dermis.lighting.emitters import SamplingOptions
    from dermis.lighting.irradiance import irradiance
    from dermis.rendering.color import LUMINANCE
    from dermis.lighting.visibility import Visibility
    from dermis.optics.transmittance import Transmittance
    ld = lambda n: artifacts.load(glob.glob(str(cache / n / "*"))[0])  # noqa: E731
    mesh, pts = ld(mesh_node), ld(f"samples-{mesh_node}")
    scene = load_scene(str(cache.parent / "scene.toml"))
    lights = [l for l in scene.lights if l.name == light_name]
    vis = Visibility(mesh.vertices, mesh.faces)
    cfg = BssrdfConfig()
    T = Transmittance(scene.optics.layers[0].eta / scene.optics.eta_above, cfg.surface_reflection)
    out = {"mesh": mesh_node, "light": light_name, "points": int(len(pts.positions)),
           "samples": cfg.irradiance_samples}
    for strategy in ("product", "mis"):
        lum = []
        for seed in (0, 1):
            prof = cProfile.Profile() if (strategy, seed) == ("product", 0) else None
            la, t0, c0 = os.getloadavg(), time.perf_counter(), time.process_time()
            if prof:
                prof.enable()
            E = irradiance(pts.positions, pts.normals, lights, vis.occluded, seed=seed,
                           options=SamplingOptions(samples=cfg.irradiance_samples,
                                                   env_strategy=strategy), transmittance=T)
            if prof:
                prof.disable()
                st = pstats.Stats(prof).stats
                cum = {f"{k[0].split('/')[-1]}:{k[2]}": v[3] for k, v in st.items()}
                out["profile_cumulative_s"] = {k: round(v, 2) for k, v in sorted(
                    cum.items(), key=lambda kv: -kv[1])[:14]}
            out[f"{strategy}_seed{seed}"] = {"wall_s": time.perf_counter() - t0,
                                             "cpu_s": time.process_time() - c0, "loadavg": list(la)}
            lum.append(E @ LUMINANCE)
        a, b = lum
        m = 0.5 * (a + b)
        ok = m > 1e-3 * m.max()
        out[f"{strategy}_rel_noise"] = float(np.sqrt(np.mean(((a - b)[ok] / m[ok]) ** 2) / 2))
        print(strategy, {k: v for k, v in out.items() if k.startswith(strategy)}, flush=True)
    return out


# ------------------------------------------------------------------------ energy, HK93
def energy_table() -> dict:
    """Max over texture albedos in [0, 1] of each model's directional albedo (as cl/shade.cl
    composes it) per view angle; HK93's reflectance under uniform light against the layer
    profile's Rd."""
    import pyopencl as cl
    from dermis.pipeline.cl import get_env, to_device
    from dermis.optics.fresnel import diffuse_fresnel_external
    from dermis.optics.layers import PRESETS
    from dermis.models.asperity import AsperityParams
    from dermis.models.hk93 import HK93Params
    from dermis.models.lafortune import LafortuneParams
    from dermis.optics.transmittance import Transmittance
    from dermis.optics.layer_profiles import build_profiles
    env = get_env()
    theta = [0.0, 30.0, 60.0, 80.0, 85.0, 87.0, 89.0, 89.9]
    albedos = np.linspace(0.0, 1.0, 11)
    x, wq = np.polynomial.legendre.leggauss(96)
    mu, wmu = 0.5 * (x + 1), 0.5 * wq
    phi = (np.arange(192) + 0.5) / 192 * 2 * np.pi
    m, p = (a.ravel() for a in np.meshgrid(mu, phi, indexing="ij"))
    s = np.sqrt(1 - m * m)
    wi = np.stack([s * np.cos(p), s * np.sin(p), m], 1).astype(np.float32)
    weight = np.repeat(wmu, 192) * (2 * np.pi / 192)

    def albedo(base, bp, asp, alb, th):
        t = np.radians(th)
        wo = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], 1).astype(np.float32)
        h, n = len(wo), len(wi)
        knl = cl.Kernel(env.program("shade.cl", {"DERMIS_BASE": base,
                                                 "DERMIS_ASPERITY": int(asp is not None)}),
                        "shade_samples")
        pt = np.repeat(np.arange(h, dtype=np.int32), n)
        outb = np.empty((h * n, 3), np.float32)
        d_out = cl.Buffer(env.context, cl.mem_flags.WRITE_ONLY, outb.nbytes)
        bpk = bp.pack() if bp is not None else np.zeros(4, np.float32)
        apk = asp.pack() if asp is not None else np.zeros(8, np.float32)
        knl(env.queue, (h * n,), None, to_device(env, pt), to_device(env, np.tile(wi, (h, 1))),
            to_device(env, np.ones((h * n, 3), np.float32)), np.int32(h * n),
            to_device(env, np.tile(np.float32([0, 0, 1]), (h, 1))), to_device(env, wo),
            to_device(env, np.tile(np.asarray(alb, np.float32), (h, 1))),
            to_device(env, bpk), to_device(env, apk), to_device(env, np.ones(1, np.uint8)),
            np.int32(0), d_out, d_out, np.int32(0))
        cl.enqueue_copy(env.queue, outb, d_out)
        return (outb.reshape(h, n, 3) * weight[None, :, None]).sum(1)

    hk = HK93Params(PRESETS["two_layer"])
    ref = hk.texture_reference()
    laf = LafortuneParams()
    models = {"lambert": (0, None, None), "lafortune": (1, laf, None), "hk93": (2, hk, None),
              "asperity+lambert": (0, None, AsperityParams()),
              "asperity+lafortune": (1, laf, AsperityParams()),
              "asperity+hk93": (2, hk, AsperityParams())}
    table = {}
    for name, (base, bp, asp) in models.items():
        worst = np.zeros(len(theta))
        for a in albedos:
            alb = np.full(3, a) / (ref if base == 2 else 1.0)
            worst = np.maximum(worst, albedo(base, bp, asp, alb, theta).max(axis=1))
        table[name] = dict(zip([str(t) for t in theta], worst.round(4).tolist()))
    # the BSSRDF: lobes (rho_d = 0) + a T(mu), a <= 1
    lobes = albedo(1, LafortuneParams(rho_d=(0, 0, 0)), None, np.zeros(3), theta)
    t = Transmittance(1.4, "lafortune_lobes")(np.cos(np.radians(theta)))
    table["bssrdf (lobes + T a)"] = dict(zip([str(x) for x in theta],
                                             (lobes + t).max(axis=1).round(4).tolist()))
    hk_res = {}
    x12, w12 = np.polynomial.legendre.leggauss(12)
    mu12 = 0.5 * (x12 + 1)
    for preset in ("two_layer", "skin1", "skin2"):
        stack = PRESETS[preset]
        p = HK93Params(stack)
        a = albedo(2, p, None, np.ones(3), np.degrees(np.arccos(mu12)).tolist())  # untinted
        rho_hh = (a * (mu12 * w12)[:, None]).sum(0)
        rd = build_profiles(stack).Rd
        eta = stack.layers[0].eta
        hk_res[preset] = {"hk93_uniform_light": rho_hh.round(4).tolist(),
                          "profile_Rd": np.round(rd, 4).tolist(),
                          "bssrdf_uniform_light_(1-Fdr_ext)Rd": np.round(
                              (1 - diffuse_fresnel_external(eta)) * rd, 4).tolist()}
    return {"albedo_max_over_texture": table, "hk93_vs_profile": hk_res}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(REPO / "scenes" / "default.toml"))
    ap.add_argument("--geometries", default="high,low_bump")
    ap.add_argument("--lights", default="point,area,dir_left+dir_right,sunset")
    ap.add_argument("--cache", default="/tmp/dermis-bench-bssrdf")
    ap.add_argument("--label", default="after")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "bssrdf.json"))
    ap.add_argument("--skip-pipeline", action="store_true")
    ap.add_argument("--brute-queries", type=int, default=4000)
    ap.add_argument("--spp", type=int, default=None,
                    help="[render] spp of the variant (default: the scene's)")
    ap.add_argument("--skip-energy", action="store_true")
    ap.add_argument("--extra", default="",
                    help="comma list of knife,edge,cpu,irradiance: also run these measurements "
                         "(edge/cpu/irradiance read the --cache of an earlier run)")
    ap.add_argument("--cpu-passes", type=int, default=1,
                    help="--extra cpu: render the 8 images this many times in one process")
    ap.add_argument("--only-extra", action="store_true",
                    help="run only the --extra measurements; merge them into the label's entry")
    args = ap.parse_args()
    args.geometries = args.geometries.split(",")
    args.lights = args.lights.split(",")
    import dermis
    extra = [e for e in args.extra.split(",") if e]
    if args.only_extra:
        cache = Path(args.cache).resolve() / "cache"
        out = Path(args.out)
        old = read_labelled(out)
        entry = old.setdefault(args.label, {})
        runs = {"knife": lambda: knife_edge_table(),
                "edge": lambda: shadow_edge_colour(
                    cache, cache.parent / "out" / "bench_bssrdf" / "render" / "bssrdf-point-high.exr"),
                "cpu": lambda: image_cpu(cache, args.cpu_passes), "irradiance": lambda: irradiance_profile(cache)}
        for e in extra:
            la = list(os.getloadavg())
            entry[{"knife": "knife_edge", "edge": "shadow_edge_colour", "cpu": "image_cpu",
                   "irradiance": "irradiance_pass"}[e]] = {"loadavg_start": la, **runs[e]()}
            out.write_text(json.dumps(old, indent=1))
        return
    res = {"label": args.label, "dermis": str(Path(dermis.__file__).parent), "spp": args.spp,
           "loadavg_start": list(os.getloadavg()),
           "note": "2-core shared machine, other jobs running: times noisy (+-30 %)"}
    if not args.skip_pipeline:
        res["pipeline"] = pipeline(args)
        print(json.dumps(res["pipeline"], indent=1))
    res["brute_force"] = brute_force_error(Path(args.cache).resolve() / "cache",
                                           args.brute_queries)
    print(json.dumps(res["brute_force"], indent=1))
    if not args.skip_energy:
        res["energy"] = energy_table()
        print(json.dumps(res["energy"], indent=1))
    res["loadavg_end"] = list(os.getloadavg())
    save_labelled(args.out, args.label, res)


if __name__ == "__main__":
    main()
