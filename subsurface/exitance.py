"""Radiant exitance of the BSSRDF at shading points (docs/science.md §4 "Near field").

The far part of the profile is gathered from the irradiance points (``subsurface/gather.py``
over the octree of ``subsurface/octree.py``); the near part (``subsurface/near_field.py``) is
evaluated at each shading point for point and directional lights, from their shadow edges
(``subsurface/shadow_edges.py``), and gathered from the points for the other lights.
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from dermis.pipeline.cl import get_env
from dermis.pipeline.reuse import content_key
from dermis.pipeline.shared import RunCache, Shared
from dermis.subsurface.gather import GatherTuning, gather
from dermis.subsurface.near_field import NEAR_OUTER, SHARP_LIGHTS, near_tables, split_profile
from dermis.subsurface.octree import build_octree, scene_default
from dermis.subsurface.profile_table import BLUR_REACH
from dermis.subsurface.shadow_edges import shadow_edges, sharp_near_field

__all__ = ["ShadingPoints", "ExitanceOptions", "exitance", "SHARED_GATHERS", "OCTREES",
           "SHADOW_EDGES", "NEAR_TABLES", "GATHERS", "POINT_TREES"]

# Gathers kept per run by :func:`exitance` for reuse: the same points, irradiance, profile and
# query positions give the same exitance, and the low mesh's two bump variants of a lighting
# condition shade the same positions (the bump moves normals only) and run together.  Each
# is a (Q, 3) float32 array, ~30 MB at 800 x 800 x 4 spp; 6 hold a condition's far and soft
# parts and its noise for two profiles.
SHARED_GATHERS = 6
# What the BSSRDF images of a run share (pipeline/shared.py): the octrees of a mesh's points
# under a lighting condition, the shadow edges located on them, the near-field tables of a
# profile, and the last gathers (the low mesh's bump variants gather at the same positions)
OCTREES = Shared("octree")
SHADOW_EDGES = Shared("shadow_edges")
NEAR_TABLES = Shared("near_table")
GATHERS = Shared("gather", keep=SHARED_GATHERS)
POINT_TREES = Shared("points_kdtree")   # for the exact near sums where edges bound no region


@dataclass(frozen=True)
class ShadingPoints:
    """The surface points :func:`exitance` shades (the camera samples' hits).

    positions : (Q, 3) float, mm
    shading_normals : (Q, 3) float, the normals the near field is shaded with (bump mapped)
    geo_normals : (Q, 3) float, the geometric normals (shadow-ray offsets, horizon culling)
    visible : (Q, number of point/directional lights) bool, optional
        Which of those lights each shading point sees (``shadow_edges.sharp_visibility`` of
        the shared visibility); None traces a shadow ray per point and light.
    """

    positions: np.ndarray
    shading_normals: np.ndarray
    geo_normals: np.ndarray
    visible: np.ndarray | None = None


@dataclass(frozen=True)
class ExitanceOptions:
    """How :func:`exitance` evaluates the BSSRDF.

    epsilon : float or None
        Solid-angle criterion of the gather (:func:`gather`; the scene's ``[bssrdf]
        epsilon``); None only with ``brute_force``.
    normalisation : {"energy", "thesis"}
        As :func:`gather`; "thesis" gathers the whole profile from the points.
    leaf_size : int
        Octree leaf size (default the scene schema's ``[bssrdf] leaf_size``).
    brute_force : bool
        Sum every point with no clustering (the reference; :func:`gather`).
    near_field : bool
        False: the thesis's method, the whole profile gathered from the points (blurred by
        their reconstruction width); so is the "thesis" normalisation.
    transmittance : callable, optional
        The entry transmittance (``Transmittance``) the irradiance was weighted with.
    indirect : bool
        The irradiance also holds light other than the lights' own (one bounce of indirect
        light, ``lighting/indirect.py``): the point and directional lights' part is then
        recomputed for their shadow edges, and the rest is gathered whole, as a soft light's.
    tuning : GatherTuning
        Research knobs of the gather; the defaults are what the pipeline runs.
    env : pipeline.cl.ClEnv, optional
        OpenCL environment (default ``pipeline.cl.get_env()``).
    progress : callable(float), optional
        Called with the fraction done of each gather (:func:`gather`).
    """

    epsilon: float | None
    normalisation: str = "energy"
    leaf_size: int = scene_default("leaf_size")
    brute_force: bool = False
    near_field: bool = True
    transmittance: object = None
    indirect: bool = False
    tuning: GatherTuning = GatherTuning()
    env: object = None
    progress: object = None


def exitance(points, irradiance: np.ndarray, profile, shading: ShadingPoints, *, lights,
             visibility, options: ExitanceOptions,
             shared: RunCache | None = None,
             keys: tuple[str, str, str] | None = None,
             terms: str = "all", noise: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Radiant exitance of the BSSRDF at shading points: the far part of the profile
    gathered from the points, the near part at each point (module docstring).

    Parameters
    ----------
    points : SurfacePoints (positions, normals, areas, info["kernel_sigma_mm"], info
        ["spacing_mm"]) and ``irradiance`` (N, 3) their entering irradiance for ``lights``
    profile : LayerProfile
    shading : ShadingPoints, the points to shade
    lights : sequence of LightConfig, the lighting condition ``irradiance`` was computed for
    visibility : lighting.visibility.Visibility of the mesh the points lie on
    options : ExitanceOptions
    shared : RunCache, optional
        The run's shared intermediates: octrees, edges and tables are kept per (points,
        irradiance), made once when several nodes ask at the same time, and the gathers of
        the last ``SHARED_GATHERS`` query sets (the low mesh's bump variants shade the same
        positions: only the sharp near field sees their normals) are reused.
    keys : (points, irradiance, profile) content keys, optional
        With ``shared``: the cache keys of the nodes that made them (``ctx.input_keys``); by
        default digests of their arrays.
    terms : {"all", "smooth", "near"}
        "all": the exitance; "smooth": the parts gathered from the points alone (the far part
        of the point and directional lights and the whole profile of the other light where
        the near field is resolved, else everything); "near": the point and directional
        lights' near field alone (zero where it is not resolved).  all = smooth + near.
    noise : (N, 3) float, optional
        The points' irradiance noise (``PointIrradiance.noise``, lighting/irradiance.py
        "Halves"): stats["noise"] is then the exitance's own noise estimate at the shading
        points, (Q, 3) float32, the points' noise gathered through the whole profile with
        the irradiance's clusters (``Octree.carrying``): linear in it, so noise^2 estimates
        M's variance from the irradiance's sampling (the point and directional lights' part,
        the near field included, has none).  None for the "near" terms, without ``noise``
        or where it is zero everywhere.

    Returns
    -------
    M : (Q, 3) float32; stats : dict (the gathers' stats, timings of each part)
    """
    queries, shading_normals, geo_normals, visible = (
        shading.positions, shading.shading_normals, shading.geo_normals, shading.visible)
    epsilon, normalisation, leaf_size = options.epsilon, options.normalisation, options.leaf_size
    brute_force, near_field, transmittance = (options.brute_force, options.near_field,
                                              options.transmittance)
    tuning, env, progress = options.tuning, options.env, options.progress
    t0 = time.perf_counter()
    cache = RunCache() if shared is None else shared    # a private one: nothing is shared
    if keys is None:
        keys = (("points", "irradiance", "profile") if shared is None else
                (content_key(points.positions, points.areas), content_key(irradiance),
                 content_key(*(np.asarray(getattr(profile, f)) for f in
                                        ("r_mm", "R", "T", "Rd", "cutoff_mm")))))
    sigma = float(points.info.get("kernel_sigma_mm") or 0.0)
    spacing = float(points.info.get("spacing_mm") or math.sqrt(
        float(np.sum(points.areas)) / max(len(points.areas), 1)))
    lights = list(lights)
    sharp = [l for l in lights if l.type in SHARP_LIGHTS]
    soft = [l for l in lights if l.type not in SHARP_LIGHTS]
    resolved = (near_field and normalisation == "energy" and sigma > 0 and sharp
                and tuning.kernel_sigma_mm is None)
    E = np.asarray(irradiance, np.float32)
    key, profile_key = tuple(keys[:2]), keys[2]

    def tree(name, e):
        return cache.get(OCTREES, (name, leaf_size, sigma) + key, lambda: build_octree(
            points.positions, points.areas, e(), leaf_size=leaf_size,
            kernel_sigma_mm=sigma or None))

    gkw = dict(epsilon=epsilon, normalisation=normalisation, env=env, brute_force=brute_force,
               progress=progress, tuning=tuning)
    qkey = content_key(queries)

    def gathered(name, make_tree, part):
        """gather() of the octree ``make_tree()`` (kept in the run as ``name``) at the
        queries, or the same gather made earlier in the run (its stats then with no kernel
        seconds of this call; which node made it depends on the run's order, so nothing
        else says so: the artifact stays the same)."""
        gk = ((name, part, qkey, profile_key, epsilon, normalisation, brute_force,
               repr(tuning)) + key)
        (m, st), made = cache.get_made(GATHERS, gk, lambda: gather(
            make_tree(), profile, queries, part=part, **gkw))
        return m, (st if made else {**st, "kernel_seconds": 0.0})

    def lit_near(k, ed):
        """The near part of the profile summed over the points light ``k`` reaches (its
        shadow edges' ``lit``) at the queries ``idx``: the near energy of the lit region from
        the points' own shadow rays, where the located edges bound no region about a shading
        point (``shadow_edges.sharp_near_field``).  A few points of an image: summed exactly
        (brute force) over the points within the blurred near table's reach of them."""
        def near(idx):
            from scipy.spatial import cKDTree
            q = np.asarray(queries, np.float64)[idx]
            pts = cache.get(POINT_TREES, key, lambda: cKDTree(
                np.asarray(points.positions, np.float64)))
            reach = (NEAR_OUTER + BLUR_REACH) * sigma + spacing
            pick = np.unique(np.concatenate(
                [np.asarray(i, np.int64) for i in pts.query_ball_point(q, reach)] + [[0]]))
            lit = np.repeat(ed.lit[pick, None], 3, axis=1).astype(np.float32)
            t = build_octree(np.asarray(points.positions)[pick], np.asarray(points.areas)[pick],
                             lit, leaf_size=leaf_size, kernel_sigma_mm=sigma)
            m, st = gather(t, profile, q, epsilon=None, normalisation=normalisation, env=env,
                           brute_force=True, tuning=tuning, part="near")
            stats["kernel_seconds"] += st["kernel_seconds"]
            return m
        return near

    if terms not in ("all", "smooth", "near"):
        raise ValueError(f"exitance terms {terms!r}: one of 'all', 'smooth', 'near'")
    stats: dict = {"near_field": bool(resolved), "kernel_seconds": 0.0, "noise": None}
    if noise is not None and terms != "near" and np.any(noise):
        # the noise through the irradiance's clusters: the octree "all" of E, as the gathers'
        d = np.asarray(noise, np.float32)
        stats["noise"], st = gathered("noise", lambda: tree("all", lambda: E).carrying(d),
                                      "all")
        stats["kernel_seconds"] += st["kernel_seconds"]
    if not resolved:
        if terms == "near":
            return np.zeros((len(queries), 3), np.float32), {**stats, "seconds": 0.0}
        m, st = gathered("all", lambda: tree("all", lambda: E), "all")
        stats.update(st)
        stats["seconds"] = time.perf_counter() - t0
        return m, stats

    def locate_edges():
        # the shadow edges (host numpy and Embree, one thread each) are located while this
        # thread builds the octree and the device gathers the far part: independent work
        # whose results do not depend on the overlap
        # a condition of one light: E is that light's (unless it holds indirect light too)
        own = E if len(lights) == 1 and not options.indirect else None
        pool = ThreadPoolExecutor(max_workers=len(sharp))
        pending = [pool.submit(shadow_edges, points.positions, points.normals, l, visibility,
                               spacing, transmittance=transmittance, irradiance=own)
                   for l in sharp]
        pool.shutdown(wait=False)
        return pending
    pending = cache.get(SHADOW_EDGES, (spacing, repr(sharp), repr(transmittance)) + key,
                        locate_edges)
    M = np.zeros((len(queries), 3))
    if terms != "near":
        m_far, st = gathered("all", lambda: tree("all", lambda: E), "far")
        stats.update(st)
        M += m_far
    edges = [f.result() for f in pending]
    t_edges = sum(ed.info["seconds"] for ed in edges)
    if terms != "near" and (soft or options.indirect):
        m_soft, st_soft = gathered("soft", lambda: tree("soft", lambda: np.maximum(
            E - sum(ed.irradiance for ed in edges), 0.0).astype(np.float32)), "near")
        M += m_soft
        stats["kernel_seconds"] += st_soft["kernel_seconds"]
    t1 = time.perf_counter()
    if terms == "smooth":
        stats.update({"edges_seconds": t_edges, "seconds": time.perf_counter() - t0})
        return np.nan_to_num(M, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32), stats
    table = cache.get(NEAR_TABLES, (profile_key, sigma, tuning.cutoff_mm), lambda: near_tables(
        split_profile(profile, sigma, cutoff_mm=tuning.cutoff_mm)))
    stats.update({"near_fallback": 0, "near_side_from_visibility": 0})
    for k, (light, ed) in enumerate(zip(sharp, edges)):
        M += sharp_near_field(queries, shading_normals, geo_normals, light, visibility, ed,
                              table, lit_near=lit_near(k, ed), transmittance=transmittance,
                              env=env or get_env(), stats=stats,
                              visible=None if visible is None else visible[:, k])
    stats.update({"edges_seconds": t_edges, "near_seconds": time.perf_counter() - t1,
                  "rd_near": table.rd_near.tolist(), "near_radius_mm": table.r_out,
                  "edge_crossings": [ed.info["crossings"] for ed in edges],
                  "seconds": time.perf_counter() - t0})
    return np.nan_to_num(M, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32), stats
