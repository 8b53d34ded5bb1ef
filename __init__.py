"""dermis: classic human-skin rendering techniques side by side, measured.

The repository's top-level folders install as one import package:
``dermis.pipeline`` (engine), ``dermis.physics`` (host physics shared by stages),
``dermis.stages`` (one module per stage), ``dermis.reports`` (images, previews,
report), ``dermis.cl`` (OpenCL kernels) and ``dermis.scenes`` (scene presets).
See docs/software.md in this repository ("Layout").
"""
__version__ = "0.2.0"
__all__ = ["__version__", "STAGES", "COMMANDS"]

# The stages, in pipeline order: (name, module).  The composition root: the engine
# (dermis.pipeline) imports no stage module; it loads these by name (pipeline/registry.py).
STAGES = (
    ("mesh_source", "dermis.stages.mesh_source"),
    ("mesh_high", "dermis.stages.mesh_high"),
    ("mesh_low", "dermis.stages.mesh_low"),
    ("bake", "dermis.stages.bake"),
    ("mesh_previews", "dermis.reports.mesh_previews"),
    ("profiles", "dermis.stages.profiles"),
    ("samples", "dermis.stages.samples"),
    ("irradiance", "dermis.stages.irradiance"),
    ("visibility", "dermis.stages.visibility"),
    ("render", "dermis.stages.render"),
    ("bssrdf", "dermis.stages.bssrdf"),
    ("reference", "dermis.stages.reference"),
    ("images", "dermis.reports.images"),
    ("differences", "dermis.reports.differences"),
    ("report", "dermis.reports.report"),
)

# CLI subcommands provided by the physics packages: (name, module with add_parser and run).
COMMANDS = (("profile", "dermis.stages.profile_cli"), ("sweep", "dermis.reports.sweep"))
