"""dermis: classic human-skin rendering techniques side by side, measured.

The repository's top-level folders install as one import package:
``dermis.pipeline`` (engine), ``dermis.physics`` (host physics shared by stages),
``dermis.stages`` (one module per stage), ``dermis.reports`` (images, previews,
report), ``dermis.cl`` (OpenCL kernels) and ``dermis.scenes`` (scene presets).
See docs/software.md in this repository ("Layout").
"""
__version__ = "0.2.0"
__all__ = ["__version__", "STAGES", "MODELS", "COMMANDS"]

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
    ("render", "dermis.stages.render"),
    ("bssrdf", "dermis.stages.bssrdf"),
    ("reference", "dermis.stages.reference"),
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
    ("bssrdf", "dermis.models.bssrdf"),
    ("bssrdf_mc", "dermis.models.bssrdf_mc"),
)

# CLI subcommands provided by the physics packages: (name, module with add_parser and run).
COMMANDS = (("profile", "dermis.optics.profile_command"), ("sweep", "dermis.reports.sweep"))
