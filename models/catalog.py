"""The registered models as images, sheets and reports name and order them.

Read from the registry (``dermis.MODELS`` through :mod:`dermis.pipeline.registry`): the
order scenes list models in, each model's label, which models are BSSRDFs (images of the
BSSRDF stage, with an irradiance pass), and the thesis's four.  A name that is not
registered (an image of a model a plugin added for one run) keeps its name as its label
and sorts after the registered ones.
"""
from __future__ import annotations

import dermis
from dermis.pipeline import registry

__all__ = ["ordered", "label", "ranked", "is_bssrdf", "THESIS_MODELS"]

# the thesis's four, in its order (measured BRDF, asperity, Hanrahan-Krueger, BSSRDF): the
# default [render] models and the ones its conclusions are about
THESIS_MODELS = dermis.THESIS_MODELS


def ordered(models) -> list[str]:
    """``models`` in the registry's order, unregistered names after them, sorted."""
    models = set(models)
    known = [m for m in registry.model_names() if m in models]
    return known + sorted(models - set(known))


NATIVE = "_native"   # the Cycles models' images of the native mapping (stages/cycles.py)


def _native_base(model: str) -> str | None:
    """The Cycles model whose native-mapping image ``model`` is, else None."""
    base = model[:-len(NATIVE)] if model.endswith(NATIVE) else None
    return base if base in registry.model_names() and registry.model(base).stage == "cycles" \
        else None


def label(model: str) -> str:
    """How images and the report name ``model``."""
    base = _native_base(model)
    if base is not None:
        return registry.model(base).label.removesuffix(" (matched)") + " (native)"
    return registry.model(model).label if model in registry.model_names() else model


def ranked(model: str) -> bool:
    """Whether the report ranks ``model``'s images against the reference: the thesis's four
    and Blender Cycles' models in both mappings (docs/cycles.md)."""
    if model in THESIS_MODELS or _native_base(model) is not None:
        return True
    return model in registry.model_names() and registry.model(model).stage == "cycles"


def is_bssrdf(model: str) -> bool:
    """Whether ``model``'s images come from the BSSRDF stage (and so have an irradiance pass)."""
    return model in registry.model_names() and registry.model(model).profiles
