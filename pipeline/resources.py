"""The memory a scene needs, estimated at load, against the memory this machine has.

Each stage that grows with a scene setting (the image size and its samples, the bake
resolution, the point density) has an estimated peak: constants fitted to measured peak
resident sets, every one an upper bound of its measurements (the sources are cited by each
constant).  ``load_scene`` refuses a scene whose estimate exceeds the machine's memory
(physical memory or the cgroup limit; ``$DERMIS_MEMORY_MB`` overrides), naming the setting to
lower.  A run executes two nodes at a time by default: the estimates bound each stage, not
the sum of two large stages that happen to run together.
"""
from __future__ import annotations

import os
from pathlib import Path

from .config import LightConfig, Scene
from .errors import ConfigError
from .registry import model, stage

__all__ = ["estimate_memory", "machine_memory", "resource_problems", "head_points",
           "light_samples_per_pixel", "MEMORY_ENV_VAR", "HEAD_AREA_MM2"]

# Peak memory of the stages that grow with a scene setting, fitted to measured peaks.  Bytes.
# Bake and points: docs/hardening.md "Memory estimates" (resident set size of `dermis run
# --until STAGE` on the procedural head, 2-core PoCL machine).
MEMORY_BASE = 300 << 20          # interpreter, numpy, open3d, OpenCL runtime (measured 290 MB)
BAKE_BYTES_PER_TEXEL = 48        # rasterised positions/normals, bake rays, maps, blur
POINT_BYTES = 2800               # sample points: candidates, kd-trees, partition-of-unity areas
# Rendering: bench/bench_memory_estimate.py -> bench/results/memory_estimate.json, the peak
# resident set of `dermis run` of the quick scene (meshes, points and profiles cached) at 64^2
# to 512^2 pixels and, to check the extrapolation, 1024^2; spp 4, under a point light (4
# light samples a pixel), the 70 mm disc and the sunset (16 each), BRDF and BSSRDF models
# alone and together (two nodes at a time), kernels cached and compiling.  Each constant is
# an upper envelope of the measurements with a margin: every peak lies 1.1 to 2.0 times
# below its estimate (1.4 to 1.8 at 1024^2; the least margin is a first run at 64^2).
RENDER_BASE = 500 << 20          # measured 296-335 MB at 64^2; 429-463 MB when kernels compile
MESH_BYTES_PER_TRIANGLE = 160    # the rendered mesh and its ray-casting scene (measured 153)
# Per pixel: per camera sample (hits, surface attributes) and per light sample (directions,
# weights, visibility).  Measured slopes, 64^2-512^2 fit / 512^2 -> 1024^2: BRDF 332 / 503 B
# a pixel (point light), 701 / 622 (disc); BSSRDF 925 (point), 1407 / 782 (disc).
# A requested light sample: the visibility stage keeps every sample drawn above the horizon
# and not shadowed (directions, weights, flags: 25 B; 50-55 B at the peak, while the batches
# are joined: 53.7 B a stored sample in bench/results/env_noise.json "after_nets" "memory").
# Where the head fills a fraction of the frame fewer are stored (0.36 of the requested under
# the sunset at the default framing), but a close-up stores 0.94 of them: measured on the
# quick scene's face filling a 64^2 frame under the sunset, 256 -> 1024 -> 2048 samples a
# pixel, 54 and 33 B a requested sample (BRDF), 11 and 33 (BSSRDF); bench/results/
# memory_estimate.json "light_samples".  64 B bounds both with a margin (24 B, the fit at the
# default framing, left the 2048-sample close-up 27 MB above its estimate).
CAMERA_SAMPLE_BYTES = {"brdf": 110, "bssrdf": 150}
LIGHT_SAMPLE_BYTES = {"brdf": 64, "bssrdf": 64}
BSSRDF_BASE = 150 << 20          # octree, profile tables, points held by the gather
# An environment light: its map, its sampling tables (a fixed part and a part per texel of
# the map; measured with the 2048 x 1024 procedural sunset and the 1024 x 512 Venice HDR:
# BRDF +252 / +176 MB, with the BSSRDF, whose irradiance pass samples the map for every
# point, +936 / +544 MB).  The fixed parts are 650 MB: a fresh process rendering the quick
# scene's face as a 64^2 close-up under the sunset with Lafortune alone peaked at 1062-1210 MB
# at 256 light samples a pixel and 1663-1837 MB at 4096 (4 runs each on 2 cores; the peak
# moves by ~10 % between runs), where a fixed part of 180 MB estimated 869 and 1829 MB: 650
# restores a margin of 1.1 over the largest peak (tests/test_memory_light_samples.py).  A
# first run on a cold OpenCL kernel cache peaks higher while the programs build (1807 MB at
# 256 samples on a clean machine): not counted.  The BSSRDF's irradiance pass draws the map
# as the renderer does (the mixture and its control variate, lighting/irradiance.py
# "Halves"): the small render of tests/test_hardening_config.py test12 (96^2, disc and
# procedural sunset, Lafortune and BSSRDF; the map's tables built once under a lock,
# pipeline/reuse.py built_once) peaked at 1099-1769 MiB over 7 local runs (1555-1587
# before, 2 runs) and at 2242 in a clean-clone CI run, where it depends on which nodes'
# batches meet: 580 B a texel bounds the largest with a margin of 1.1.
ENVIRONMENT_BYTES = {"brdf": (650 << 20, 60), "bssrdf": (650 << 20, 580)}   # (fixed, per texel)
PROCEDURAL_SUNSET_TEXELS = 2048 * 1024   # lighting/environment.py procedural_sunset: 2048 x 1024
# Surface area of the embedded procedural head (mm^2, measured at 2k-60k triangles: 1.55e5
# to 1.59e5); a scan is assumed head-sized, twice that (the LPS head: 3.7e5 mm^2).
HEAD_AREA_MM2 = {"procedural": 1.6e5, "scan": 4.0e5}
MEMORY_ENV_VAR = "DERMIS_MEMORY_MB"   # override the machine memory the check compares with


def machine_memory() -> int:
    """Bytes of memory this process may use: ``$DERMIS_MEMORY_MB``, else the smaller of the
    machine's physical memory and the cgroup limit."""
    env = os.environ.get(MEMORY_ENV_VAR, "").strip()
    if env:
        try:
            return int(float(env) * (1 << 20))
        except ValueError:
            raise ConfigError(f"${MEMORY_ENV_VAR} = {env!r}: must be a number of MiB") from None
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for limit in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(limit).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


def _environment_texels(light: LightConfig) -> int:
    """Texels of an environment light's map (the procedural sunset's, or the file header's)."""
    if light.map == "procedural_sunset":
        return PROCEDURAL_SUNSET_TEXELS
    try:
        import OpenImageIO as oiio   # heavy: imported only for a scene with a map file
    except ImportError:  # pragma: no cover - a dependency
        return PROCEDURAL_SUNSET_TEXELS
    inp = oiio.ImageInput.open(str(light.map))
    if inp is None:
        return PROCEDURAL_SUNSET_TEXELS
    try:
        return inp.spec().width * inp.spec().height
    finally:
        inp.close()


def light_samples_per_pixel(scene: Scene) -> int:
    """The most light samples a pixel draws in one lighting condition: spp x (1 per point or
    directional light, ceil(samples / spp) per disc or environment light; stages/visibility.py
    samples_per_hit)."""
    spp = scene.render.spp
    return max((spp * sum(1 if l.type in ("point", "directional") else -(-l.samples // spp)
                          for l in lights) for _, lights in scene.light_groups()), default=0)


def estimate_memory(scene: Scene) -> list[tuple[str, str, int]]:
    """Estimated peak bytes of the stages that grow with a setting: (what, key, bytes)."""
    out = []
    cam = scene.camera
    r = scene.render
    renders = bool(r.models and scene.lights and r.geometries)
    bssrdf = any(model(m).profiles for m in r.models)   # points and a profile gather
    if renders:
        kind = "bssrdf" if bssrdf else "brdf"
        px = cam.width * cam.height
        lpp = light_samples_per_pixel(scene)
        triangles = max(scene.mesh.high_triangles if g == "high" else scene.mesh.low_triangles
                        for g in r.geometries)
        need = (RENDER_BASE + MESH_BYTES_PER_TRIANGLE * triangles + BSSRDF_BASE * bssrdf
                + px * (CAMERA_SAMPLE_BYTES[kind] * r.spp + LIGHT_SAMPLE_BYTES[kind] * lpp))
        used = {l.name for _, lights in scene.light_groups() for l in lights}
        envs = [l for l in scene.lights if l.type == "environment" and l.name in used]
        if envs:
            fixed, per_texel = ENVIRONMENT_BYTES[kind]
            need += fixed + per_texel * max(_environment_texels(l) for l in envs)
        out.append((f"rendering {cam.width} x {cam.height} pixels ({r.spp} camera and {lpp} "
                    "light samples a pixel)", "camera.width, camera.height", need))
    if set(r.geometries) & {"low_bump", "low_bump_blur"}:
        n = scene.bake.resolution
        out.append((f"baking {n} x {n} texels", "bake.resolution",
                    MEMORY_BASE + BAKE_BYTES_PER_TEXEL * n * n))
    if renders and bssrdf and scene.optics is not None:
        _, points = head_points(scene)
        out.append((f"about {points:.3g} irradiance points", "bssrdf.point_density",
                    MEMORY_BASE + int(POINT_BYTES * points)))
    return out


def head_points(scene: Scene) -> tuple[float, float]:
    """(area, points): a head-sized surface (``HEAD_AREA_MM2``) and the irradiance points
    the ``samples`` stage places on it at the scene's density (its node's spacing)."""
    area = HEAD_AREA_MM2["procedural" if scene.mesh.source == "procedural" else "scan"]
    spacing = stage("samples").node(scene, stage("mesh_high").NAME).params["spacing_mm"]
    return area, area / spacing ** 2


def resource_problems(scene: Scene) -> list[str]:
    """Settings whose estimated peak memory exceeds the machine's (see :func:`estimate_memory`)."""
    have = machine_memory()
    out = []
    for what, key, need in estimate_memory(scene):
        if need > have:
            out.append(f"{key}: {what} needs about {need / 2**30:.1f} GiB at its peak; this "
                       f"machine has {have / 2**30:.1f} GiB (${MEMORY_ENV_VAR} overrides); "
                       f"lower {key}")
    return out
