"""Stage ``profiles``: the scene's layer stack -> radial profiles R(r), T(r) per channel.

The layer file the BSSRDF gathers with, from the scene's ``[optics]`` profile model
(:func:`dermis.optics.layer_profiles.build_profiles`; docs/profiles.md).
"""
from __future__ import annotations

from dermis.pipeline.graph import Node, StageResult
from dermis.pipeline.registry import model as lookup_model
from dermis.optics.layer_profiles import build_profiles
from dermis.optics.single_layer import single_layer_equivalent
from dermis.optics.layers import (LayerStack, DEFAULT_PROFILE_MODEL, DEFAULT_MC_PHOTONS,
                                   DEFAULT_MC_SEED)

__all__ = ["NAME", "VERSION", "KERNELS", "profile_of", "node_id", "node", "plan", "run"]

NAME = "profiles"

VERSION = 2   # 2: beam-integrated P1 diffusion with real extinction, explicit negative lobes,
              #    Monte Carlo tables

KERNELS = ()  # the Monte Carlo model builds mc_slab.cl through optics/monte_carlo_slab.py


def profile_of(scene, model) -> str:
    """The layer-profile model a BSSRDF ``model`` (a :class:`~dermis.models.model.Model`)
    reads: its own ``profile``, else the scene's ``[optics] profile``."""
    return model.profile or getattr(scene.optics, "profile", DEFAULT_PROFILE_MODEL)


def node_id(scene, profile: str) -> str:
    """``profiles`` for the scene's own ``[optics] profile``, ``profiles-<profile>`` for
    another (the ``bssrdf_mc`` images' Monte Carlo table beside a multipole scene)."""
    own = getattr(scene.optics, "profile", DEFAULT_PROFILE_MODEL)
    return NAME if profile == own else f"{NAME}-{profile}"


# the multipole profiles of the one layer with the stack's total reflectance
# (optics/single_layer.py): what the BSSRDF renders without the stack's layering
SINGLE_LAYER = "single_layer"


def node(scene, model: str | None = None) -> Node:
    """The layer profiles of the scene's stack with ``model`` (None: ``[optics] profile``);
    the model, and for the Monte Carlo ``[optics] photons`` and ``seed``, are in the key.
    ``single_layer``: of the single layer fitted to the scene's own profiles' Rd."""
    optics = scene.optics
    model = model or getattr(optics, "profile", DEFAULT_PROFILE_MODEL)
    params = {"stack": LayerStack.to_dict(optics), "model": model}
    if model == SINGLE_LAYER:
        own = node(scene)
        return Node(node_id(scene, model), NAME, __name__, params, {"stack": own.id},
                    label="layer profiles (single layer, same Rd)")
    if model == "monte_carlo":
        params["photons"] = int(getattr(optics, "photons", DEFAULT_MC_PHOTONS))
        params["seed"] = int(getattr(optics, "seed", DEFAULT_MC_SEED))
    return Node(node_id(scene, model), NAME, __name__, params, (),
                label=f"layer profiles ({model})")


def run(params: dict, inputs: dict, ctx) -> StageResult:
    model = params.get("model", "multipole")
    stack = LayerStack.from_dict(params["stack"])
    if model == SINGLE_LAYER:
        single, fit = single_layer_equivalent(stack, inputs["stack"].Rd)
        prof = build_profiles(single)
        prof.info["single_layer"] = fit
        kernel_seconds = 0.0
    elif model == "monte_carlo":
        prof = build_profiles(stack, model=model, photons=params["photons"],
                              seed=params["seed"], env=ctx.cl, progress=ctx.progress)
        kernel_seconds = prof.info.get("kernel_seconds", 0.0)
    else:
        prof = build_profiles(stack)
        kernel_seconds = 0.0
    return StageResult(prof, info={"model": model, "Rd": list(map(float, prof.Rd)),
                                   "Tt": list(map(float, prof.Tt)),
                                   "negative_lobes": len(prof.info.get("negative_lobes", [])),
                                   "kernel_seconds": kernel_seconds})


def plan(scene, plan) -> None:
    """The profiles every BSSRDF model of the scene reads (outputs of their own: the
    report's profile page and ``dermis profile`` read them)."""
    for name in scene.render.models:
        m = lookup_model(name)
        if m.profiles:
            if profile_of(scene, m) == SINGLE_LAYER:
                plan.add(node(scene), target=True)
            plan.add(node(scene, profile_of(scene, m)), target=True)
