"""The scene schema: every section of a scene file as a frozen dataclass whose fields
declare their type, default, allowed range, unit and doc once (:func:`spec`), and the
:class:`Scene` they make up with its derived views (lighting conditions, views, cameras).
Validation and loading: :mod:`dermis.pipeline.config`."""
from __future__ import annotations

from dataclasses import MISSING, dataclass, field
from pathlib import Path
from typing import Any

from . import registry
from .model_choice import AUTO

__all__ = ["LENGTH_UNITS", "GEOMETRIES", "LIGHT_TYPES", "VIEW_MARK", "MAIN_VIEW", "condition_of", "view_name_of",
           "spec", "SceneInfo", "MeshConfig", "BakeConfig", "CameraConfig", "ViewConfig",
           "LightConfig", "RenderConfig", "BssrdfConfig", "ReferenceConfig", "CausesConfig", "CyclesConfig",
           "ReportConfig", "OutputConfig", "Scene", "choices_of", "SCHEMA_TABLES", "resolve_path"]


LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
GEOMETRIES = ("high", "low", "low_bump", "low_bump_blur")
LIGHT_TYPES = ("point", "disc", "directional", "environment")
# joins a lighting condition and the view that sees it in a label ("point@nose"); the main
# camera's conditions keep their plain labels
VIEW_MARK = "@"
MAIN_VIEW = "main"


def condition_of(label: str) -> str:
    """The lighting condition of a lighting label, without its view ("point@nose" -> "point"):
    what a camera-independent pass (the irradiance of the BSSRDF's points) is keyed by."""
    return label.split(VIEW_MARK)[0]


def view_name_of(label: str) -> str:
    """The view of a lighting label ("point@nose" -> "nose"; a plain label: the main camera's,
    ``MAIN_VIEW``)."""
    return label.partition(VIEW_MARK)[2] or MAIN_VIEW


def spec(default=MISSING, *, lo=None, hi=None, lo_open=False, hi_open=False, choices=None,
         unit=None, doc="", factory=None, names=False):
    """A dataclass field with validation metadata.  A tuple field is a vector of 3 numbers,
    unless it has ``choices`` or ``names`` (a list of strings: names of lights)."""
    meta = dict(lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, choices=choices, unit=unit,
                doc=doc, names=names)
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class SceneInfo:
    name: str = spec("dermis", doc="label used in output paths and reports")
    units: str = spec("mm", choices=tuple(LENGTH_UNITS), doc="units of lengths in this file")


@dataclass(frozen=True)
class MeshConfig:
    source: str = spec("procedural", doc='"procedural" (embedded head) or a mesh file path')
    units: str = spec("mm", choices=tuple(LENGTH_UNITS), doc="units of the mesh file")
    texture: str = spec("", doc="albedo texture path (else the file's material)")
    displacement: str = spec("", doc="grey displacement map for the high mesh (optional)")
    displacement_scale_mm: float = spec(0.0, lo=0.0, hi=100.0, doc="mm per unit map value")
    displacement_mid: float = spec(0.5, lo=0.0, hi=1.0, doc="map value of zero displacement")
    high_triangles: int = spec(1_000_000, lo=1_000, hi=20_000_000,
                               doc="triangles of the high mesh (thesis: ~1M-triangle scan)")
    low_triangles: int = spec(16_750, lo=100, hi=5_000_000, doc="thesis: 16,750 (QSlim)")
    procedural_detail: bool = spec(True, doc="pores and wrinkles on the procedural head")
    procedural_texture_size: int = spec(2048, lo=64, hi=16384,
                                        doc="albedo texture size of the procedural head")
    seed: int = spec(0, lo=0, doc="seed of every random choice (head, points, light samples)")


@dataclass(frozen=True)
class BakeConfig:
    resolution: int = spec(4096, lo=16, hi=16384, doc="thesis: 4096x4096")
    blur_sigma_px: float = spec(8.0, lo=0.0, hi=1000.0,
                                doc="Gaussian sigma of the blurred bump map (thesis 3.2; value ours)")
    max_distance: float = spec(0.0, lo=0.0, unit="length", doc="0 = automatic")
    dilate_px: int = spec(16, lo=0, hi=4096, doc="texels the maps are grown past chart borders")
    reference: str = spec("phong", choices=("phong", "flat"),
                          doc="surface bump heights are measured from: the low mesh's smooth "
                              "Phong surface, or the flat triangles (thesis; facets show)")


@dataclass(frozen=True)
class CameraConfig:
    position: tuple = spec((0.0, 0.0, 900.0), unit="length", doc="eye point")
    look_at: tuple = spec((0.0, 0.0, 0.0), unit="length", doc="point the camera looks at")
    up: tuple = spec((0.0, 1.0, 0.0), doc="up direction (not parallel to the view)")
    fov_deg: float = spec(30.0, lo=0.0, hi=179.0, lo_open=True,
                          doc="full field of view across the shorter image side")
    width: int = spec(800, lo=1, hi=16384, doc="pixels (thesis: 800)")
    height: int = spec(800, lo=1, hi=16384, doc="pixels (thesis: 800)")


@dataclass(frozen=True)
class ViewConfig:
    """A close-up: a camera of its own and the lighting conditions rendered through it (its
    images, references and differences carry the lighting label ``<condition>@<name>``)."""

    name: str = spec(doc="unique name, used in output file names (not \"main\": the "
                         "[camera])")
    camera: CameraConfig = spec(factory=CameraConfig, doc="its camera: a [views.camera] table "
                                "with the keys of [camera]")
    lights: tuple = spec((), names=True, doc='lighting conditions seen in this view (names '
                         'of [[lights]], "a+b" together); empty = those of [render] lights')
    geometries: tuple = spec(("high",), choices=GEOMETRIES,
                             doc="geometries rendered in this view (close-ups: the scan)")


@dataclass(frozen=True)
class LightConfig:
    name: str = spec(doc="unique name, used in output file names")
    type: str = spec(choices=LIGHT_TYPES, doc="kind of light")
    position: tuple = spec((0.0, 0.0, 0.0), unit="length", doc="point / disc centre")
    direction: tuple = spec((0.0, 0.0, 1.0), doc="directional: towards the light; disc: normal")
    # hi: float32 light samples, irradiance and radiance stay finite down to the 1e-6 mm
    # distance floor of point lights (1e20 / 1e-12 = 1e32 < 3.4e38; tests/test_stability.py)
    intensity: tuple = spec((1.0, 1.0, 1.0), lo=0.0, hi=1e20, doc="point/disc: W/sr-like "
                                                                  "units; directional: irradiance")
    radius: float = spec(70.0, lo=0.0, lo_open=True, unit="length", doc="disc radius (thesis 70 mm)")
    map: str = spec("procedural_sunset", doc='environment: "procedural_sunset" or an HDR/EXR path')
    scale: float = spec(1.0, lo=0.0, hi=1e20, doc="environment radiance multiplier")
    rotation_deg: float = spec(0.0, lo=-360.0, hi=360.0, doc="environment: turn about +y")
    # Swept (bench/results/sweep_default.json "point_area": default scan at 400x400, point +
    # area, 3 repeats, errors against the converged value extrapolated from the finest, +-0.1 %):
    # 4 / 8 / 16 / 32 / 64 -> 1.40 / 0.75 / 0.50 / 0.33 / 0.11 %: 8 is the cheapest < 1 % for
    # the disc; 16 kept for the sky (its sweep, "sunset_before_repeats", measured one run each)
    samples: int = spec(16, lo=1, hi=4096, doc="shadow samples (thesis: 16)")


@dataclass(frozen=True)
class RenderConfig:
    # default: the thesis's four; bssrdf_mc costs a Monte Carlo table (docs/profiles.md)
    # the registered models (dermis.MODELS), read when a scene is checked: plugins may add some
    models: tuple = spec(registry.default_models(), choices=lambda: registry.model_names()
                         + (AUTO,),
                         doc='models to render; ["auto"]: per view and lighting condition the '
                             "cheapest measured to meet [report] accuracy "
                             "(bssrdf is the reference of the difference "
                             "images; bssrdf_mc: the BSSRDF with the Monte Carlo profile)")
    lights: tuple = spec((), names=True,
                         doc='lighting conditions to render: names of [[lights]], "a+b" '
                             "lights several together (the thesis's two directional "
                             "lights); empty = each light alone")
    geometries: tuple = spec(("high", "low_bump", "low_bump_blur"), choices=GEOMETRIES,
                             doc="high mesh; low mesh plain, with the sharp or the blurred bump map")
    # Lambert default: in the thesis's timings asperity renders beat Lafortune for every light
    # (docs/science.md §7), so its base cannot have been a costlier model (an inference; see asperity.cl)
    asperity_base: str = spec("lambert", choices=registry.term_bases,
                              doc="model under the asperity term")
    # Measured (bench/bench_render.py --spp, bench/results/render_spp.json; Lafortune, high
    # mesh): point light, error vs 64 spp over the head 0.0196 / 0.0110 / 0.0058 / 0.0039 at
    # spp 1 / 4 / 9 / 16 for 2.9 / 5.0 / 12.7 / 35 s; under the sunset the noise stays 0.162 up
    # to 4 and grows beyond (0.175, 0.251: a pixel's 16 light samples leave < 4 per camera
    # sample for the MIS).  4 halves the aliasing for 1.7x the time and costs no noise.
    # Swept (bench/results/sweep_default.json "point_area": default scan at 400x400, point +
    # area, 3 repeats, against the converged value extrapolated from the finest, +-0.8 %):
    # 1 / 2 / 4 / 8 -> 3.2 / 2.9 / 2.35 / 0.8 %; kept at 4 (the 5 % target met: the defaults
    # together measured 1.7 % from the most refined configuration; 1 % needs 8, twice the
    # camera samples of every image)
    spp: int = spec(4, lo=1, hi=256,
                    doc="camera samples per pixel, stratified (anti-aliasing); a pixel's disc "
                        "and environment light samples are spread over them")
    # the thesis shades with direct light only; true adds one diffuse bounce (lighting/indirect.py)
    indirect: bool = spec(False, doc="add one bounce of indirect light (Lambertian, the skin's "
                                     "albedo) to every model")
    # Measured (bench/bench_indirect.py, bench/results/indirect.json "samples"; default scan,
    # point light, 6000 face vertices vs 4096 rays): RMS noise / mean light over the face
    # 4.5 / 2.8 / 1.8 / 1.3 / 0.67 % at 16 / 32 / 64 / 128 / 256 rays; 256 is the first below
    # the BRDF images' own 1.1 % at the default spp (render_spp.json)
    indirect_samples: int = spec(256, lo=1, hi=4096,
                                 doc="bounce rays per vertex of the indirect light")


@dataclass(frozen=True)
class BssrdfConfig:
    # Jensen-Buhler's rule (one point per pi*mfp^2, smallest mfp of the stack) asks for 12M
    # points on a head with the two-layer skin (mfp 0.1 mm); 0.02 gives ~250k, the size the
    # issue's targets assume, and the gather's cell-averaged profile keeps energy exact.
    # Swept (bench/results/sweep_default.json "point_area": default scan at 400x400, 3
    # repeats, against the converged value, noise model of order 1.14, +-0.4 %): 0.005 / 0.01
    # / 0.02 / 0.04 -> 3.5 / 2.4 / 1.4 / 0.4 % for a median 21 / 36 / 41 / 62 s: kept (with
    # spp, the largest error of the defaults)
    point_density: float = spec(0.02, lo=0.0, lo_open=True, hi=100.0,
                                doc="multiplier on one point per pi*mfp^2")
    # Swept (bench/results/sweep_default.json, against the converged value): point + area
    # 16 / 32 / 64 / 128 -> 0.10 / 0.08 / 0.05 / 0.02 %, but under the sunset
    # ("sunset_before_repeats", vs 128) 2.63 / 1.58 / 1.06 %: kept at 64 for the sky
    irradiance_samples: int = spec(64, lo=1, hi=4096, doc="thesis: 64 shadow samples")
    # Measured on the LPS head (250k points, 640k pixels; bench/results/gather.json): eps 0.5
    # gives 0.38% relative RMSE vs brute force at 543x its speed (0.18 s kernel); 0.4: 0.27%;
    # 0.2: 0.06%. A scene with sharper irradiance (bumpy sheet, 20x shadow step) needs 0.2.
    # Swept (bench/results/sweep_default.json "point_area", default scan at 400x400, vs brute
    # force): 1.0 / 0.5 / 0.25 / 0.1 -> 0.54 / 0.17 / 0.02 / 0.00 %, times within their
    # spread of each other.  Per view of the default scene (bench/results/gather_views.json,
    # exitance vs brute force at 4000 camera samples): 0.5 is 2.79 % off in the lips close-up
    # (8 px/mm, disc light) and 0.40-0.46 % under the disc and the sky; 0.25 is at most
    # 0.12 % on every view, for 3-54 % more kernel time (at most 0.18 s an image): 0.25
    epsilon: float = spec(0.25, lo=0.0, lo_open=True, hi=10.0, doc="solid-angle criterion")
    # Jensen-Buhler used <= 8 points per leaf; 16 measured 8-10% faster at lower error
    leaf_size: int = spec(16, lo=1, hi=256, doc="points per octree leaf")
    normalisation: str = spec("energy", choices=("energy", "thesis"),
                              doc="profile normalisation in the gather (energy: exact Rd)")
    albedo_mode: str = spec("replace", choices=("replace", "modulate", "none"),
                            doc="replace: texture = total diffuse reflectance (profile shapes "
                                "the blur); modulate: texture tints the profile; none: ignore")
    surface_reflection: str = spec("lafortune_lobes", choices=("lafortune_lobes", "none"),
                                   doc="specular surface term added to the subsurface image")
    brute_force: bool = spec(False, doc="reference gather over every point (slow)")


@dataclass(frozen=True)
class ReferenceConfig:
    # Mitsuba 3 path-traced ground truth (stages/reference.py, docs/ground-truth.md), rendered
    # in progressive passes of two half-buffers over the head's pixels: first until every face
    # region's mean is known to required_rel_se whatever the clock (only max_paths stops it
    # short), then toward target_rel_se within budget_s (groundtruth/progressive.py).  A wall
    # budget alone (40 s each) reached 3-26 % in the worst region at load 3-14, 1.3-6 % at
    # load ~2; 2 % everywhere took 0.26-1.6 M paths per reference, aimed at directly (6.9 M
    # for the default eight, 1,010 CPU s at load ~10: bench/results/reference_cost.json);
    # 1 % everywhere takes 4x that (0.6-3.8 M paths per condition, reference_passes.json).
    enabled: bool = spec(True, doc="render Mitsuba 3 references (skipped with one message where "
                                   "Mitsuba cannot run)")
    # 100 reference pixels across the default camera's 800: 8x8-pixel blocks, where the
    # reference's noise resolves the models (bench/results/reference.json)
    width: int = spec(0, lo=0, hi=16384, doc="pixels; must divide camera.width (block-averaged "
                                             "comparison); 0 = about 100 (reference_size)")
    height: int = spec(0, lo=0, hi=16384, doc="pixels; must divide camera.height; 0 = with width")
    target_rel_se: float = spec(0.01, lo=0.0, lo_open=True, hi=1.0,
                                doc="stop when every face region's luminance mean has this "
                                    "relative standard error")
    # after the required 2 % (which alone takes longer than this on the main camera), only the
    # cheap references (the sunset, close-ups) refine toward 1 %
    budget_s: float = spec(20.0, lo=0.0, hi=1e7, doc="seconds of rendering per lighting condition "
                                                     "(0 = no limit); a larger budget continues "
                                                     "from the cached passes")
    max_passes: int = spec(0, lo=0, hi=1 << 20, doc="stop after this many passes (0 = no limit); "
                                                    "like budget_s, continued from the cache")
    # 2 %: the report's accuracy ([report] accuracy), a region's mean the ranking can trust
    required_rel_se: float = spec(0.02, lo=0.0, hi=1.0,
                                  doc="every face region's luminance mean reaches this relative "
                                      "standard error whatever budget_s says (0 = no guarantee)")
    # 16.8 M paths: 10x the most the required 2 % took (1.6 M, reference_cost.json), ~8 min on
    # 2 idle cores at ~30 us a path: a runaway stops, never a reference on a busy machine
    max_paths: int = spec(1 << 24, lo=0, hi=1 << 40,
                          doc="paths (both halves) a reference never exceeds, the required "
                              "error's hard cap (0 = no limit); continued from the cache")
    min_spp: int = spec(32, lo=1, hi=1 << 20, doc="samples per pixel of each half-buffer every "
                                                 "head pixel gets")
    max_spp: int = spec(4096, lo=1, hi=1 << 24, doc="samples per pixel of each half-buffer no "
                                                   "pixel exceeds")
    pass_spp: int = spec(8, lo=1, hi=1 << 20, doc="fewest samples per pixel and half a pass adds")
    seed: int = spec(1, lo=0, hi=30000, doc="seeds every pass, tile and half-buffer")
    lights: tuple = spec((), names=True,
                         doc="lighting conditions to reference (names as in [render] lights); empty = all")
    roughness: float = spec(0.3, lo=0.0, lo_open=True, hi=1.0, doc="GGX alpha of the skin boundary")
    # ground-truth.md trap 7, and rr_depth measured here: Mitsuba's Russian roulette keeps a
    # path with probability <= 0.99 per event, so in skin (hundreds of events) it biases red
    max_depth: int = spec(-1, lo=-1, doc="path events, -1 = unlimited")
    rr_depth: int = spec(1024, lo=1, doc="events before Russian roulette starts")
    env_clamp: float = spec(0.0, lo=0.0, doc="clamp environment radiance (0 = none, as the models)")
    slab_samples: int = spec(1 << 18, lo=1024, doc="paths of the flat-slab Rd that normalises the albedo tint")
    variant: str = spec("auto", choices=("auto", "cuda_ad_rgb", "llvm_ad_rgb"),
                        doc="Mitsuba variant (auto: cuda, else llvm)")


@dataclass(frozen=True)
class CausesConfig:
    # The reference's controlled variants (stages/causes.py, groundtruth/variants.py,
    # docs/ground-truth.md "Causes of the distance"), one node per referenced lighting
    # condition at the reference's size.  Samples are per half-buffer; the default scan,
    # 100x100, 2 cores at load 5-9: the diffuse head 0.009 s/spp, the rough skin 0.8-0.9,
    # the smooth 0.7-0.8 s/spp with 9x the rough one's variance per sample (so 3x its
    # samples); this budget: 9-10 s per lighting condition, 59 s with the boundary variant
    # (bench/results/causes.json)
    enabled: bool = spec(True, doc="measure interreflection and boundary effects on the "
                                   "reference (only when [reference] is enabled)")
    diffuse_spp: int = spec(64, lo=1, hi=1 << 20,
                            doc="samples per pixel of each half of the diffuse head (direct "
                                "and all bounces)")
    rough_spp: int = spec(4, lo=1, hi=1 << 20,
                          doc="samples per pixel of each half of the rough-boundary skin head")
    smooth_spp: int = spec(12, lo=1, hi=1 << 20,
                           doc="samples per pixel of each half of the smooth-boundary skin head")
    smooth_roughness: float = spec(0.0, lo=0.0, hi=1.0,
                                   doc="GGX alpha of the smooth variant (0 = smooth dielectric, "
                                       "the models' Fresnel boundary)")
    boundary_lights: tuple = spec((), names=True,
                                  doc="lighting conditions of the boundary variant (disc or "
                                      "environment lights); empty = those of disc lights only")
    slab_samples: int = spec(1 << 14, lo=1024, hi=1 << 26,
                             doc="paths of each flat-slab Rd normalising a boundary variant")
    seed: int = spec(1, lo=0, hi=30000, doc="half-buffers use seeds 2 seed and 2 seed + 1")


@dataclass(frozen=True)
class CyclesConfig:
    # Blender Cycles' skin models (models/cycles_*.py, dermis/cycles/, docs/cycles.md): run
    # where the optional extra is installed (pip install dermis[cycles]), else skipped with
    # one message.  Rendered on the reference's grid (size), where every distance to the
    # truth is measured, to target_noise on blocks of noise_block reference pixels: the
    # ranking's 4 x 4 blocks (reports/ground_truth.py RANK_FACTOR), where the reference's own
    # noise was 12-27 % in a cold default run (docs/cycles.md "Cost"); 4 %, a third of the
    # smallest, adds at most 5 % to the ranking's error bars, and takes 2.6 x
    # fewer samples than 2.5 % (bench/results/cycles.json)
    mappings: tuple = spec(("matched", "native"), choices=("matched", "native"),
                           doc="inputs from the skin: matched (fitted to the skin's flat-slab "
                               "Rd and mean exit radius), native (radius = mean free path, "
                               "base colour = albedo); images of native end in _native")
    geometries: tuple = spec(("high",), choices=("high", "low"),
                             doc="meshes rendered (those also in render.geometries)")
    size: str = spec("reference", choices=("reference", "camera"),
                     doc="pixels rendered: the reference's grid (shown upsampled, nearest) or "
                         "the camera's")
    target_noise: float = spec(0.04, lo=0.0, lo_open=True, hi=1.0,
                               doc="relative RMSE noise on noise_block blocks to reach")
    noise_block: int = spec(4, lo=1, hi=1024,
                            doc="noise block edge in reference pixels (4: the ranking's)")
    pilot_spp: int = spec(4, lo=1, hi=4096, doc="samples per pixel of each half's first pass")
    max_spp: int = spec(256, lo=1, hi=1 << 16, doc="samples per pixel of each half, at most")
    seed: int = spec(1, lo=0, hi=1 << 20,
                     doc="half-images use seeds 2 (seed + k) and 2 (seed + k) + 1")
    threads: int = spec(2, lo=1, hi=1024, doc="Cycles render threads (fixed: same image for any)")


@dataclass(frozen=True)
class ReportConfig:
    # What a scene requires (reports/requirements.py, docs/science.md): an effect is visible
    # above effect_threshold of a region's mean (1 %: the ground truth's own target,
    # [reference] target_rel_se, so a visible effect is one the truth can resolve); a model
    # is adequate within accuracy of the truth (2 %: twice that, the smallest error the
    # default reference can confirm at RESOLVE_K = 2 standard errors of 1 %)
    accuracy: float = spec(0.02, lo=0.0, hi=10.0, lo_open=True,
                           doc="relative error a model may have in a region to be adequate")
    effect_threshold: float = spec(0.01, lo=0.0, hi=10.0, lo_open=True,
                                   doc="relative size above which an effect is visible")


@dataclass(frozen=True)
class OutputConfig:
    cache_dir: str = spec("", doc="empty: $DERMIS_CACHE or ./.dermis-cache")
    output_dir: str = spec("out", doc="outputs go to output_dir/<scene name>/")
    previews: bool = spec(True, doc="PNG previews of meshes and baked maps")


@dataclass(frozen=True)
class Scene:
    """A whole validated scene; ``path`` is the file it came from (or the embedded default)."""

    scene: SceneInfo = spec(factory=SceneInfo)
    mesh: MeshConfig = spec(factory=MeshConfig)
    bake: BakeConfig = spec(factory=BakeConfig)
    camera: CameraConfig = spec(factory=CameraConfig)
    lights: tuple = spec((), doc="array of [[lights]] tables")
    views: tuple = spec((), doc="array of [[views]] tables: close-ups beside [camera]")
    render: RenderConfig = spec(factory=RenderConfig)
    optics: Any = spec(None, doc='layer stack: preset = "two_layer" or [[optics.layers]]')
    bssrdf: BssrdfConfig = spec(factory=BssrdfConfig)
    reference: ReferenceConfig = spec(factory=ReferenceConfig)
    causes: CausesConfig = spec(factory=CausesConfig)
    cycles: CyclesConfig = spec(factory=CyclesConfig)
    report: ReportConfig = spec(factory=ReportConfig)
    output: OutputConfig = spec(factory=OutputConfig)
    path: str = ""
    # (lighting label, model) of render.models = ["auto"] (pipeline/model_choice.py)
    chosen: tuple = field(default=(), metadata={"internal": True})

    @property
    def light_by_name(self) -> dict:
        return {l.name: l for l in self.lights}

    def light_groups(self, view: str | None = None) -> tuple:
        """The lighting conditions to render: (label, tuple of LightConfig) pairs, those of
        the main camera then each view's (labelled ``<condition>@<view>``); ``view``: only
        that view's ("main": the camera's)."""
        main = self.render.lights or tuple(l.name for l in self.lights)
        labels = [(c, "main") for c in main] + [
            (f"{c}{VIEW_MARK}{v.name}", v.name) for v in self.views for c in v.lights or main]
        return tuple((label, tuple(self.light_by_name[n]
                                   for n in condition_of(label).split("+")))
                     for label, of in labels if view is None or of == view)

    def models_of(self, label: str) -> tuple:
        """The models rendered under lighting condition ``label``."""
        chosen = dict(self.chosen)
        return (chosen[label],) if label in chosen else self.render.models

    def view_of(self, label: str) -> ViewConfig | None:
        """The view a lighting label belongs to (None: the main camera)."""
        name = view_name_of(label)
        return next((v for v in self.views if v.name == name), None)

    def camera_of(self, label: str) -> CameraConfig:
        """The camera that sees lighting condition ``label``."""
        view = self.view_of(label)
        return view.camera if view is not None else self.camera

    def geometries_of(self, label: str) -> tuple:
        """The geometries rendered under lighting condition ``label``."""
        view = self.view_of(label)
        return view.geometries if view is not None else self.render.geometries

    def mesh_path(self) -> Path | None:
        if self.mesh.source == "procedural":
            return None
        return resolve_path(self.mesh.source, self.path)

    def credits(self) -> tuple[str, ...]:
        """Attribution lines of the asset files this scene uses (``ATTRIBUTION.txt`` beside them)."""
        paths = [self.mesh_path(), self.resolve(self.mesh.texture), self.resolve(self.mesh.displacement)]
        paths += [Path(l.map) for l in self.lights if l.type == "environment"
                  and l.map != "procedural_sunset"]
        out = []
        for p in paths:
            note = p.parent / "ATTRIBUTION.txt" if p is not None else None
            if note is not None and note.is_file():
                text = note.read_text().strip()
                if text not in out:
                    out.append(text)
        return tuple(out)

    def resolve(self, value: str) -> Path | None:
        """A path value of this scene resolved against the scene file's folder (None if empty)."""
        return resolve_path(value, self.path) if value else None


def choices_of(meta) -> tuple | None:
    """A field's allowed values: a tuple, or a function giving them (the registered models,
    which plugins may extend)."""
    choices = meta.get("choices")
    return choices() if callable(choices) else choices


SCHEMA_TABLES = (("scene", SceneInfo), ("mesh", MeshConfig), ("bake", BakeConfig),
                 ("camera", CameraConfig), ("[lights]", LightConfig), ("[views]", ViewConfig),
                 ("render", RenderConfig),
                 ("bssrdf", BssrdfConfig), ("reference", ReferenceConfig),
                 ("causes", CausesConfig), ("cycles", CyclesConfig), ("report", ReportConfig), ("output", OutputConfig))


def resolve_path(path: str, scene_path: str) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute() and scene_path and not scene_path.startswith("<"):
        p = Path(scene_path).parent / p
    return p
