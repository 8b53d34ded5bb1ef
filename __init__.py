"""dermis: classic human-skin rendering techniques side by side, measured.

The repository's top-level folders install as one import package:
``dermis.pipeline`` (engine), ``dermis.physics`` (host physics shared by stages),
``dermis.stages`` (one module per stage), ``dermis.reports`` (images, previews,
report), ``dermis.cl`` (OpenCL kernels) and ``dermis.scenes`` (scene presets).
See docs/architecture.md.
"""
__version__ = "0.2.0"
__all__ = ["__version__"]
