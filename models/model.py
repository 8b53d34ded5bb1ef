"""The local illumination model as one unit: what the pipeline, the renderer and the reports
need to know of a model, declared by the model's own module (``MODEL = Model(...)`` at its
end).  The composition root lists the units (``dermis.MODELS``: name -> module) and
``pipeline.registry.model(name)`` loads one; nothing else dispatches on a model's name.

Two kinds (``stage``):

* ``"render"`` - a BRDF shaded by ``cl/shade.cl`` on the shared visibility
  (``rendering/shade.py``): ``shade`` are the ``-D`` defines that select it there, either
  as a base BRDF (``DERMIS_BASE``) or, with ``bases``, as a term added over one of them
  (the asperity layer, docs/science.md §5);
* ``"bssrdf"`` - an image of the BSSRDF stage (``stages/bssrdf.py``) reading the layer
  profiles of ``profile``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from dermis.pipeline.errors import ConfigError

__all__ = ["Model"]


@dataclass(frozen=True)
class Model:
    """One local illumination model.

    name : its name in scenes (``[render] models``), node ids and file names
    label : how the images, sheets and the report name it
    stage : "render" (a BRDF of ``cl/shade.cl``) or "bssrdf" (the BSSRDF stage)
    doc : the section of docs/science.md that states it
    params : the parameter class (validated on construction, ``pack()`` gives the float32
        block its kernels read); ``params()`` are the defaults.  None for a BSSRDF: its
        parameters are the scene's ``[bssrdf]`` and ``[optics]`` sections
    kernel : the ``.cl`` file with its ``<name>_eval`` kernel (``models/evaluate.py``)
    albedo : the parameter holding its diffuse albedo, which the texture replaces per point
        (its kernels then read a per-point albedo); None: it has none
    shade : ``-D`` (name, value) pairs that select it in ``cl/shade.cl``
    bases : for a term added over a base BRDF, the models it may be added to
    optics : its parameters derive from the scene's ``[optics]`` layer stack
    scene_params : (config slice of the render node, the run's shared intermediates or None)
        -> its parameters
    shade_albedo : (params, per-hit albedo, textured) -> the albedo ``cl/shade.cl`` reads,
        where it is not the linear albedo itself
    profile : for a BSSRDF, the layer-profile model it reads (None: the scene's ``[optics]
        profile``)
    shares : the run-wide intermediates (``pipeline.shared.Shared`` kinds) its
        ``scene_params`` uses; the stage that renders it declares them
    profiles : it reads the layer profiles (of ``profile``, else the scene's)
    check : (validated layer stack, validated scene sections by name, file) -> problems:
        what it needs of the scene, checked when the scene is loaded (the scene is refused
        before any stage runs)
    glossy : its image shows the Lafortune skin fit's lobes (a BSSRDF through its surface
        term, ``[bssrdf] surface_reflection``), so the shared rays sample them
        (``rendering/cast.py`` :func:`glossy_lobes`)
    exitance : for a BSSRDF, what computes its exitance at the shading points in place of
        the full gather (``subsurface.exitance.exitance``): called with the same arguments
        and ``camera`` and ``pixels``, the shading points' flat pixel indices; returns (M,
        stats), stats may hold "blend_image" (H, W), written beside the image
    """

    name: str
    label: str
    stage: str
    doc: str
    params: type | None = None
    kernel: str | None = None
    albedo: str | None = None
    shade: tuple = ()
    bases: tuple = ()
    optics: bool = False
    scene_params: Callable[[dict, Any], Any] | None = None
    shade_albedo: Callable[[Any, Any, bool], Any] | None = None
    profile: str | None = None
    shares: tuple = ()
    profiles: bool = False
    check: Callable[[Any, dict, str], list] | None = None
    glossy: bool = False
    exitance: Callable[..., Any] | None = None

    def checked(self, params, what: str):
        """``params`` (its defaults when None), else ConfigError: ``what`` must be
        ``self.params``."""
        p = params if params is not None else self.params()
        if not isinstance(p, self.params):
            raise ConfigError(f"{what} must be {self.params.__name__}, got {type(p).__name__}")
        return p

    def base(self, name: str) -> "Model":
        """The base model ``name`` of a term model (one of ``bases``)."""
        for m in self.bases:
            if m.name == name:
                return m
        raise ConfigError(f"{self.name}.base = {name!r}: must be one of "
                          f"{tuple(m.name for m in self.bases)}")

    def reads_optics(self, base: str | None = None) -> bool:
        """Whether its parameters, or those of its base ``base``, derive from the scene's
        ``[optics]`` layers."""
        return self.optics or (base is not None and self.base(base).optics)
