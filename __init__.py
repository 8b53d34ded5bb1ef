"""dermis: classic human-skin rendering techniques side by side, measured.

The repository's top-level folders install as one import package, grouped by concept:
``dermis.pipeline`` (the engine: config, plan, graph, cache, OpenCL runtime, CLI, API),
the libraries ``dermis.geometry`` (meshes, bake), ``dermis.optics`` (layered skin along
depth), ``dermis.subsurface`` (the point-based BSSRDF), ``dermis.lighting`` (emitters,
environment, visibility) and ``dermis.rendering`` (camera to pixels), ``dermis.models``
(one unit per local illumination model), ``dermis.groundtruth`` (the Mitsuba reference),
``dermis.cycles`` (Blender Cycles' skin models, an optional extra),
``dermis.stages`` (thin adapters, one per stage), ``dermis.reports`` (images, differences,
report), ``dermis.cl`` (OpenCL kernels) and ``dermis.scenes`` (scene presets).  This module is
the composition root: the engine imports no stage, model or command module and loads them by
name from the lists below (pipeline/registry.py).  See docs/software.md "Layout".
"""
__version__ = "0.2.0"
__all__ = ["__version__", "STAGES", "MODELS", "THESIS_MODELS", "SECTIONS", "COMMANDS"]

# The stages, in pipeline order: (name, module).  The composition root: the engine
# (dermis.pipeline) imports no stage module; it loads these by name (pipeline/registry.py).
STAGES = (
    ("mesh_source", "dermis.stages.mesh_source"),
    ("mesh_high", "dermis.stages.mesh_high"),
    ("mesh_low", "dermis.stages.mesh_low"),
    ("bake", "dermis.stages.bake"),
    ("mesh_previews", "dermis.stages.mesh_previews"),
    ("profiles", "dermis.stages.profiles"),
    ("samples", "dermis.stages.samples"),
    ("irradiance", "dermis.stages.irradiance"),
    ("visibility", "dermis.stages.visibility"),
    ("indirect", "dermis.stages.indirect"),
    ("render", "dermis.stages.render"),
    ("bssrdf", "dermis.stages.bssrdf"),
    ("cycles", "dermis.stages.cycles"),
    ("reference", "dermis.stages.reference"),
    ("causes", "dermis.stages.causes"),
    ("images", "dermis.stages.images"),
    ("differences", "dermis.stages.differences"),
    ("report", "dermis.stages.report"),
)

# The local illumination models, in the order scenes list them: (name, module declaring
# ``MODEL``, models/model.py).  Loaded by name too (pipeline/registry.py model).
MODELS = (
    ("lafortune", "dermis.models.lafortune"),
    ("asperity", "dermis.models.asperity"),
    ("hk93", "dermis.models.hk93"),
    ("lambert", "dermis.models.lambert"),
    ("bssrdf", "dermis.models.bssrdf"),
    ("bssrdf_mc", "dermis.models.bssrdf_mc"),
    ("bssrdf_single", "dermis.models.bssrdf_single"),
    ("bssrdf_adaptive", "dermis.models.bssrdf_adaptive"),
    ("bssrdf_local", "dermis.models.bssrdf_local"),
    ("cycles_burley", "dermis.models.cycles_burley"),
    ("cycles_random_walk", "dermis.models.cycles_random_walk"),
    ("cycles_random_walk_skin", "dermis.models.cycles_random_walk_skin"),
)

# The thesis's four models, in its order: the default [render] models and the ones the
# report's conclusions are about.
THESIS_MODELS = ("lafortune", "asperity", "hk93", "bssrdf")

# Scene sections whose parsing belongs to a physics package: (section, module).  The layer
# stack's schema (layers, presets, profile options) is the optics package's.
SECTIONS = (("optics", "dermis.optics.layers"),)

# CLI subcommands provided by the physics packages: (name, module with add_parser and run).
COMMANDS = (("report", "dermis.reports.report_command"), ("profile", "dermis.optics.profile_command"),
            ("sweep", "dermis.reports.sweep"))
