"""Stage ``irradiance``: irradiance at the BSSRDF sample points from one lighting condition.

Jensen-Buhler pass 1: each point's irradiance with shadows, from
:func:`dermis.lighting.irradiance.irradiance` (thesis: 64 shadow samples for area and environment
lights).  One node per mesh and lighting condition.  The irradiance stored is the part that
enters the skin: each light sample is weighted by the entry transmittance
:class:`dermis.optics.transmittance.Transmittance` at its cosine (Fresnel, and with the BSSRDF's
surface term min(Fresnel, 1 - the lobes' albedo); docs/science.md §4), because the
profile's Rd is per entering photon.  With ``[render] indirect`` the points also receive one
bounce of indirect light (stage ``indirect``, interpolated from the mesh's vertices) times the
entry transmittance of diffuse light, the hemispherical mean of T.  The points' light is
estimated as the renderer's is (lighting/irradiance.py "Halves": two independent halves,
the environment's control variate), and the stage keeps the halves' difference, the points'
own noise estimate (``PointIrradiance.noise``) that the BSSRDF images gather into theirs;
the indirect bounce adds none (its noise is not estimated).  Cost per mesh and light (64
samples, ~241k points): ``bench/bench_irradiance.py`` -> ``bench/results/irradiance.json``
(docs/science.md §4).
"""
from __future__ import annotations

import math
import time

import numpy as np

from dermis.pipeline.artifacts import PointIrradiance
from dermis.pipeline.config import LightConfig
from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.registry import stage
from dermis.lighting.emitters import SamplingOptions, light_params
from dermis.lighting.indirect import at_points
from dermis.lighting.irradiance import irradiance
from dermis.lighting.visibility import EMBREE_SCENES, embree_scene
from dermis.optics.transmittance import Transmittance

NAME = "irradiance"
VERSION = 3   # 2: entering irradiance (entry transmittance per light sample); 3: halves, control
KERNELS = ()
SHARES = (EMBREE_SCENES,)


def node_id(mesh_node: str, label: str) -> str:
    return f"{NAME}-{mesh_node}-{label}"


def node(scene, mesh_node: str, label: str, lights: tuple) -> Node:
    """Pass 1 of one mesh's points under one lighting condition (``label``)."""
    params = {"label": label, **light_params(lights), "samples": scene.bssrdf.irradiance_samples,
              "seed": scene.mesh.seed,
              "entry": {"eta": scene.optics.layers[0].eta / scene.optics.eta_above,
                        "surface_reflection": scene.bssrdf.surface_reflection}}
    return Node(node_id(mesh_node, label), NAME, __name__, params,
                {"points": stage("samples").node_id(mesh_node), "mesh": mesh_node,
                 **stage("indirect").inputs(scene, mesh_node, label)}, label=f"irradiance {label}",
                locations=("lights[].map",))


def run(params: dict, inputs: dict, ctx) -> StageResult:
    pts, mesh = inputs["points"], inputs["mesh"]
    t0 = time.perf_counter()
    vis = embree_scene(mesh, ctx.shared, ctx.input_keys.get("mesh"))
    lights = [LightConfig(**d) for d in params["lights"]]
    entry = params["entry"]
    transmit = Transmittance(entry["eta"], entry["surface_reflection"])
    E, noise = irradiance(pts.positions, pts.normals, lights, vis.occluded, seed=params["seed"],
                          options=SamplingOptions(samples=params["samples"]),
                          transmittance=transmit, halves=True)
    if "indirect" in inputs:   # one diffuse bounce (lighting/indirect.py): its entering part
        E += at_points(inputs["indirect"].irradiance, mesh, pts.positions, vis) * transmit.mean
    ms = float(np.mean(np.square(E, dtype=np.float64)))
    info = {"seconds": time.perf_counter() - t0, "points": int(len(E)),
            "samples": params["samples"], "entry_transmittance": repr(transmit),
            # the points' own noise, relative to their RMS (0: no sampling noise)
            "rel_noise": math.sqrt(float(np.mean(np.square(noise, dtype=np.float64))) / ms)
            if ms > 0 else 0.0}
    return StageResult(PointIrradiance(E, info, noise=noise), info=info)
