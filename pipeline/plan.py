"""From a scene to the stage graph: which nodes the requested outputs need.

The graph holds only what the scene asks for: the low mesh and its bakes exist only when a
``low*`` geometry is asked for, layer profiles only for the BSSRDF, irradiance points and
passes only per mesh and lighting condition the BSSRDF renders.  Each stage module builds its
own node (the exact config slice it reads, its upstream nodes); this module only decides
which nodes exist.
"""
from __future__ import annotations

from .config import BSSRDF_MODELS, Scene
from .graph import Node
from .registry import STAGE_NAMES, stage

__all__ = ["build_graph", "STAGE_NAMES"]

LOW_GEOMETRIES = {"low", "low_bump", "low_bump_blur"}
BUMP_GEOMETRIES = {"low_bump", "low_bump_blur"}
REFERENCE_MODEL = "bssrdf"   # the difference images are measured against it


def build_graph(scene: Scene) -> tuple[dict[str, Node], list[str]]:
    """Nodes needed by the scene's requested outputs, and the target node ids.

    Returns
    -------
    nodes : dict node id -> Node
    targets : the node ids whose artifacts are the run's outputs
    """
    geoms = set(scene.render.geometries)
    needs_low, needs_bake = bool(geoms & LOW_GEOMETRIES), bool(geoms & BUMP_GEOMETRIES)
    models = scene.render.models
    nodes: dict[str, Node] = {}
    targets: list[str] = []

    def add(node: Node, target: bool = False) -> Node:
        nodes[node.id] = node
        if target:
            targets.append(node.id)
        return node

    add(stage("mesh_source").node(scene))
    add(stage("mesh_high").node(scene), target=not needs_low)
    if needs_low:
        add(stage("mesh_low").node(scene), target=not needs_bake)
    if needs_bake:
        add(stage("bake").node(scene), target=True)
    if scene.output.previews:
        add(stage("mesh_previews").node(scene, needs_bake), target=True)
    for model in models:   # each BSSRDF's profile model (bssrdf_mc: the Monte Carlo table)
        if model in BSSRDF_MODELS:
            add(stage("profiles").node(scene, BSSRDF_MODELS[model]), target=True)

    render_ids = []
    for model in models:
        for label, lights in scene.light_groups():
            for geometry in scene.render.geometries:
                mesh_node = stage("render").GEOMETRY[geometry][0]
                # camera and shadow rays: once per mesh x lighting, shared by every model
                add(stage("visibility").node(scene, mesh_node, label, lights))
                if model in BSSRDF_MODELS:   # points and irradiance shared by both BSSRDFs
                    add(stage("samples").node(scene, mesh_node))
                    add(stage("irradiance").node(scene, mesh_node, label, lights))
                    node = stage("bssrdf").node(scene, label, lights, geometry, model)
                else:
                    node = stage("render").node(scene, model, label, lights, geometry)
                render_ids.append(add(node).id)
    reference_ids, reference_skipped = [], None
    if scene.reference.enabled:  # Mitsuba ground truth, one node per lighting condition
        reference_ids, reference_skipped = _add_references(scene, add)
    images_id = None
    if render_ids:
        images_id = add(stage("images").node(scene, render_ids), target=True).id
    if REFERENCE_MODEL in models and len(models) > 1:  # differences need the reference + another
        irradiance_ids = [n for n, node in nodes.items() if node.stage == "irradiance"]
        diff_ids = [add(stage("differences").node(scene, label, [
            r for r in render_ids if nodes[r].params.get("label") == label])).id
            for label, _ in scene.light_groups()]     # one light's comparisons per node
        add(stage("report").node(scene, render_ids, irradiance_ids, diff_ids, images_id,
                                 reference_ids, reference_skipped), target=True)
    return nodes, targets


_SKIP_NOTICES: set = set()


def _add_references(scene: Scene, add) -> tuple[list[str], str | None]:
    """The reference nodes the scene asks for, and why there are none (Mitsuba missing:
    one message)."""
    import sys
    from .errors import ConfigError
    ref = stage("reference")
    groups = dict(scene.light_groups())
    wanted = scene.reference.lights or tuple(groups)
    unknown = [l for l in wanted if l not in groups]
    if unknown:
        raise ConfigError(f"{scene.path}: reference.lights: {unknown[0]!r} is not a lighting "
                          f"condition of [render] lights ({', '.join(groups)})")
    reason = ref.unavailable_reason()
    if reason:
        if reason not in _SKIP_NOTICES:
            _SKIP_NOTICES.add(reason)
            print(f"dermis: reference stage skipped: {reason}", file=sys.stderr)
        return [], f"Reference stage skipped: {reason}"
    return [add(ref.node(scene, label, groups[label]), target=True).id
            for label in wanted], None
