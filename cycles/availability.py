"""Whether Blender's Cycles can render here: ``bpy`` (Blender as a Python module) is the
optional extra ``pip install dermis[cycles]``, with wheels for one Python version per
Blender release (bpy 4.5: CPython 3.11).  Found without importing it: the pipeline's process
never loads Blender (:mod:`dermis.cycles.job`)."""
from __future__ import annotations

import importlib.util
import sys

__all__ = ["missing_reason", "BPY_PYTHON"]

BPY_PYTHON = (3, 11)   # the Python the bpy 4.5 wheels are built for (pypi.org/project/bpy)


def missing_reason() -> str | None:
    """Why Cycles cannot render here, or None."""
    try:
        found = importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        found = False
    if found:
        return None
    py = f"{sys.version_info[0]}.{sys.version_info[1]}"
    if sys.version_info[:2] != BPY_PYTHON:
        return (f"bpy (Blender as a Python module) is not installed, and has no wheel for "
                f"Python {py} (bpy 4.5 needs Python {BPY_PYTHON[0]}.{BPY_PYTHON[1]})")
    return "bpy (Blender as a Python module) is not installed: pip install 'dermis[cycles]'"
