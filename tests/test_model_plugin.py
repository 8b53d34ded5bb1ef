"""Local illumination models as plugin units (models/model.py): every registered model declares
itself consistently, and a model defined here, outside the package, registers by name and
renders through rendering/ like the shipped ones.

The toy model is a grey Lambertian with a constant reflectance that ignores the albedo
texture.  It reuses the Lambert branch of cl/shade.cl (``DERMIS_BASE`` 0) and hands the kernel
its constant albedo through ``Model.shade_albedo``, so its image must equal the Lambert
model's image of the same reflectance bit for bit, and the closed form albedo / pi * E cos.
"""
from __future__ import annotations

import math
import re
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import dermis
from dermis.lighting.visibility import Visibility
from dermis.models import asperity, lambert
from dermis.models.evaluate import evaluate
from dermis.models.model import Model
from dermis.pipeline import registry
from dermis.pipeline.cl import CL_DIR
from dermis.pipeline.config import CameraConfig, LightConfig
from dermis.pipeline.errors import ConfigError
from dermis.rendering.options import RenderOptions
from dermis.rendering.shade import render

sys.path.insert(0, str(Path(__file__).parent))
from render_fixtures import icosphere, plane  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class GreyParams:
    """A constant reflectance in [0, 1], the same in every channel."""

    reflectance: float = 0.6

    def __post_init__(self):
        if not 0.0 <= float(self.reflectance) <= 1.0:
            raise ConfigError(f"grey.reflectance = {self.reflectance}: must be in [0, 1]")

    def pack(self) -> np.ndarray:
        """cl/shade.cl's Lambert branch reads no parameter block: 4 unused floats."""
        return np.zeros(4, np.float32)


def _grey_albedo(params: GreyParams, albedo: np.ndarray, textured: bool) -> np.ndarray:
    """The constant reflectance at every hit, whatever the texture says."""
    return np.full(albedo.shape, params.reflectance, np.float32)


GREY = Model(name="grey", label="grey Lambert", stage="render", doc="docs/science.md §5",
             params=GreyParams, shade=(("DERMIS_BASE", 0),),
             scene_params=lambda config, shared: GreyParams(), shade_albedo=_grey_albedo)


@pytest.fixture
def grey_registered(monkeypatch):
    """GREY registered by name as a plugin: a module of its own listed in ``dermis.MODELS``."""
    module = types.ModuleType("grey_model_plugin")
    module.MODEL = GREY
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(dermis, "MODELS", dermis.MODELS + (("grey", module.__name__),))
    return GREY


def _scene(size=48):
    mesh = icosphere(100.0, 4)
    cam = CameraConfig(position=(0.0, 0.0, 600.0), look_at=(0.0, 0.0, 0.0), fov_deg=22.0,
                       width=size, height=size)
    l = np.array([1.0, 1.0, 1.0]) / math.sqrt(3)
    light = LightConfig(name="d", type="directional", direction=tuple(l),
                        intensity=(1.0, 2.0, 0.5))
    return mesh, cam, light, l


def test01_toy_model_registers_and_renders_as_lambert(grey_registered, cl_env):
    model = registry.model("grey")
    assert model is GREY and not model.reads_optics()
    mesh, cam, light, l = _scene()
    vis = Visibility(mesh.vertices, mesh.faces)
    grey = render(mesh, light, model, GreyParams(0.6), cam, RenderOptions(visibility=vis),
                  cl_env=cl_env)
    ref = render(mesh, light, lambert.MODEL, lambert.LambertParams((0.6, 0.6, 0.6)), cam,
                 RenderOptions(visibility=vis), cl_env=cl_env)
    np.testing.assert_array_equal(grey.linear, ref.linear)
    assert grey.info["model"] == "grey" and grey.info["nonfinite_pixels"] == 0
    # closed form at the pixel nearest the sphere's centre: albedo / pi * E * (n . l), n = +z
    c = cam.width // 2
    expected = 0.6 / math.pi * np.array([1.0, 2.0, 0.5]) * l[2]
    np.testing.assert_allclose(grey.linear[c, c], expected, rtol=2e-3)
    # defaults come from the parameter class; a wrong parameter type is refused
    assert np.array_equal(render(mesh, light, model, None, cam, RenderOptions(visibility=vis),
                                 cl_env=cl_env).linear, grey.linear)
    with pytest.raises(ConfigError, match="params for model 'grey' must be GreyParams"):
        render(mesh, light, model, lambert.LambertParams(), cam, RenderOptions(visibility=vis))


def test02_toy_model_ignores_the_texture(grey_registered, cl_env):
    rng = np.random.default_rng(7)
    mesh = plane(size=200.0, n=2, texture_srgb=rng.integers(0, 256, (8, 8, 3), dtype=np.uint8))
    cam = CameraConfig(position=(0.0, 0.0, 400.0), look_at=(0.0, 0.0, 0.0), fov_deg=20.0,
                       width=24, height=24)
    light = LightConfig(name="d", type="directional", direction=(0.0, 0.0, 1.0),
                        intensity=(math.pi,) * 3)
    img = render(mesh, light, registry.model("grey"), GreyParams(0.25), cam,
                 cl_env=cl_env).linear
    lam = render(mesh, light, lambert.MODEL, lambert.LambertParams((0.25,) * 3), cam,
                 RenderOptions(textured=False), cl_env=cl_env).linear
    np.testing.assert_array_equal(img, lam)
    np.testing.assert_allclose(img, 0.25, rtol=1e-6)     # E = pi, f = 0.25 / pi


def test03_registered_models_declare_themselves_consistently():
    science = (REPO / "docs" / "science.md").read_text()
    shade = (CL_DIR / "shade.cl").read_text()
    assert registry.MODEL_NAMES == tuple(name for name, _ in dermis.MODELS)
    for name in registry.MODEL_NAMES:
        m = registry.model(name)
        assert m.name == name and m.stage in ("render", "bssrdf", "cycles"), name
        if m.stage == "cycles":    # Blender's models: their own page (docs/cycles.md)
            assert (REPO / m.doc).is_file() and m.scene_params(None, None).method, name
            continue
        section = re.search(r"§\d+", m.doc).group(0)
        assert re.search(rf"^## {section} ", science, re.M), (name, m.doc)
        if m.stage == "render":
            assert m.params is not None and m.scene_params is not None, name
            # its eval kernel file, or (Lambert) evaluated inline by cl/shade.cl
            assert (CL_DIR / m.kernel).is_file() if m.kernel else m.shade, name
            for define, _ in m.shade:
                assert define in shade, (name, define)
        else:
            assert m.params is None and m.kernel is None and not m.shade, name
    assert tuple(b.name for b in asperity.BASES) == registry.term_bases()
    with pytest.raises(ConfigError, match=r"model = 'phong': must be one of"):
        registry.model("phong")


def test04_evaluate_needs_an_eval_kernel():
    n = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ConfigError, match="has no eval kernel"):
        evaluate(GREY, n, n)


def test05_toy_model_runs_through_the_whole_pipeline(grey_registered, tmp_path, monkeypatch):
    """Registered by one line (``dermis.MODELS``), the toy model is a scene model: the scene
    validates it, the planner gives it render nodes keyed by its own module's code, the render
    stage shades it on the shared visibility, and the images stage makes its PNG.  Two
    reflectances that differ by a factor of two give images that differ by exactly two (the
    kernel's only use of the albedo is one product)."""
    from dermis.pipeline import api
    from dermis.pipeline.config import load_scene
    from dermis.pipeline.plan import build_graph
    from dermis.pipeline.store import Store

    dark = Model(name="grey_dark", label="dark grey Lambert", stage="render",
                 doc="docs/science.md §5", params=GreyParams, shade=(("DERMIS_BASE", 0),),
                 scene_params=lambda config, shared: GreyParams(0.25),
                 shade_albedo=_grey_albedo)
    module = types.ModuleType("grey_dark_model_plugin")
    module.MODEL = dark
    monkeypatch.setitem(sys.modules, module.__name__, module)
    monkeypatch.setattr(dermis, "MODELS", dermis.MODELS + (("grey_dark", module.__name__),))
    bright = Model(**{**GREY.__dict__, "scene_params": lambda config, shared: GreyParams(0.5)})
    monkeypatch.setattr(sys.modules["grey_model_plugin"], "MODEL", bright)

    quick = REPO / "scenes" / "quick.toml"
    scene = load_scene(quick, overrides={
        "render": {"models": ["grey", "grey_dark"], "geometries": ["high"], "lights": ["point"]},
        "camera": {"width": 48, "height": 48},
        "output": {"output_dir": str(tmp_path / "out"), "previews": False}})
    nodes, _ = build_graph(scene)
    grey_id, dark_id = "render-grey-point-high", "render-grey_dark-point-high"
    assert nodes[grey_id].code == ("grey_model_plugin",)
    assert nodes[grey_id].deps["visibility"] == nodes[dark_id].deps["visibility"]
    assert set(nodes["images"].params["renders"]) == {grey_id, dark_id}
    summary = api.run(scene, cache=tmp_path / "cache")
    assert {grey_id, dark_id, "images"} <= set(summary.ran())
    store, keys = Store(tmp_path / "cache"), {r.id: r.key for r in summary.nodes}
    from dermis.pipeline.graph import _load
    grey, dark = (_load(store, nid, keys[nid]).linear for nid in (grey_id, dark_id))
    assert np.isfinite(grey).all() and (grey >= 0).all() and grey.max() > 0
    np.testing.assert_array_equal(grey, 2.0 * dark)
    pngs = {p.name for p in (tmp_path / "out" / "quick").rglob("*.png")}
    assert {"grey-point-high.png", "grey_dark-point-high.png"} <= pngs
