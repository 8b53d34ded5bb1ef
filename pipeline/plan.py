"""From a scene to the stage graph: every stage plans its own nodes.

The planner knows no stage and no model by name.  It walks the stages in pipeline order
(``dermis.STAGES``) and calls each stage module's ``plan(scene, plan)`` hook, if it has one;
the hook adds the nodes the scene needs from that stage (and, where a stage's nodes exist
only as inputs of another's, that stage adds them: an image adds its visibility node).
A stage finds what earlier stages planned through :class:`Plan` (:meth:`Plan.of_stage`,
:meth:`Plan.provided`), and names another stage's nodes only through that stage's own
``node``/``node_id`` functions (``registry.stage(name)``), never by formatting an id.
"""
from __future__ import annotations

from .config import Scene
from .errors import DermisError
from .graph import Node
from .registry import STAGE_NAMES, model, stage

__all__ = ["build_graph", "Plan", "STAGE_NAMES"]


class Plan:
    """The graph being planned: nodes by id, the run's targets, and what nodes provide.

    ``provides`` tags a node with what it is for later stages (``"image"``: a rendered image
    the images, differences and report stages read), so that those find it without knowing
    which stage made it."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.nodes: dict[str, Node] = {}
        self.targets: list[str] = []
        self._provided: dict[str, list[str]] = {}
        # why a stage the scene asked for planned nothing (stage name -> reason), for the
        # stages that report on it
        self.skipped: dict[str, str] = {}

    def add(self, node: Node, *, target: bool = False, provides: str | None = None) -> Node:
        """Add ``node`` (a node with the same id is planned once: two stages asking for the
        same shared input get the same node, and its definitions must agree)."""
        have = self.nodes.get(node.id)
        if have is None:
            self.nodes[node.id] = node
        elif (have.stage, have.params, have.deps) != (node.stage, node.params, node.deps):
            raise DermisError(f"node {node.id!r} planned twice with different definitions "
                              f"({have.stage} and {node.stage})")
        if target and node.id not in self.targets:
            self.targets.append(node.id)
        if provides is not None and node.id not in self._provided.setdefault(provides, []):
            self._provided[provides].append(node.id)
        return self.nodes[node.id]

    def of_stage(self, name: str) -> list[Node]:
        """The nodes of stage ``name`` planned so far, in the order they were added."""
        return [n for n in self.nodes.values() if n.stage == name]

    def images_of(self, stage_name: str):
        """(model, lighting label, lights, geometry) of every image the scene asks for whose
        model is rendered by stage ``stage_name`` (``Model.stage``), models outermost."""
        for name in self.scene.render.models:
            if model(name).stage != stage_name:
                continue
            for label, lights in self.scene.light_groups():
                if name not in self.scene.models_of(label):
                    continue
                for geometry in self.scene.geometries_of(label):
                    yield name, label, lights, geometry

    def provided(self, what: str) -> list[Node]:
        """The nodes added with ``provides=what``, in the order they were added."""
        return [self.nodes[nid] for nid in self._provided.get(what, ())]


def build_graph(scene: Scene) -> tuple[dict[str, Node], list[str]]:
    """Nodes needed by the scene's requested outputs, and the target node ids.

    Returns
    -------
    nodes : dict node id -> Node
    targets : the node ids whose artifacts are the run's outputs
    """
    plan = Plan(scene)
    for name in STAGE_NAMES:
        hook = getattr(stage(name), "plan", None)
        if hook is not None:
            hook(scene, plan)
    return plan.nodes, plan.targets
