"""Scene files: TOML -> validated, typed dataclasses with defaults.

Every field is declared once, with its type, default, allowed range and unit, in
the dataclasses below; one generic walker (:func:`_build`) validates a TOML
table against them.  Errors name the file, the dotted key, the bad value and
what is allowed; unknown keys are errors with a did-you-mean, and all problems
found in one file are reported together.

Lengths: fields marked ``unit="length"`` are written in the scene's
``[scene] units`` (mm by default, or cm / m) and converted to mm at load.
"""
from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any, get_type_hints

from .errors import ConfigError
from . import registry
from .registry import model
from .scene_rules import (check_camera, check_environment_file, check_reference,
                          direction_problem, fmt, plain_name_problem)

__all__ = ["Scene", "load_scene", "default_scene_path", "LENGTH_UNITS", "GEOMETRIES",
           "scene_warnings"]

LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
GEOMETRIES = ("high", "low", "low_bump", "low_bump_blur")
LIGHT_TYPES = ("point", "disc", "directional", "environment")


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
    # Swept (bench/results/sweep_default.json, default scan at 400x400, area light, vs 64):
    # 4 / 8 / 16 / 32 -> 1.22 / 1.01 / 0.42 / 0.52 % relative RMSE: 16 is the cheapest < 1 %
    samples: int = spec(16, lo=1, hi=4096, doc="shadow samples (thesis: 16)")


@dataclass(frozen=True)
class RenderConfig:
    # default: the thesis's four; bssrdf_mc costs a Monte Carlo table (docs/profiles.md)
    # the registered models (dermis.MODELS), read when a scene is checked: plugins may add some
    models: tuple = spec(registry.default_models(), choices=registry.model_names,
                         doc="models to render (bssrdf is the reference of the difference "
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
    # Swept (bench/results/sweep_default.json, default scan at 400x400, point + area, vs 8):
    # 1 / 2 / 4 -> 2.40 / 2.13 / 1.55 %; 8 costs +20 s of 136 s: kept at 4 (5 % target met;
    # 1 % needs 8, where the sweep has no finer reference to confirm it)
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
    # Swept (bench/results/sweep_default.json, default scan at 400x400, vs 0.04): 0.005 / 0.01
    # / 0.02 -> 3.12 / 1.96 / 1.02 %; 0.04 costs +86 s of 136 s: kept (with spp, the largest
    # error of the defaults)
    point_density: float = spec(0.02, lo=0.0, lo_open=True, hi=100.0,
                                doc="multiplier on one point per pi*mfp^2")
    # Swept (bench/results/sweep_default.json, vs 128): point + area 16 / 32 / 64 -> 0.10 /
    # 0.07 / 0.05 %, but under the sunset 2.63 / 1.58 / 1.06 %: kept at 64 for the sky
    irradiance_samples: int = spec(64, lo=1, hi=4096, doc="thesis: 64 shadow samples")
    # Measured on the LPS head (250k points, 640k pixels; bench/results/gather.json): eps 0.5
    # gives 0.38% relative RMSE vs brute force at 543x its speed (0.18 s kernel); 0.4: 0.27%;
    # 0.2: 0.06%. A scene with sharper irradiance (bumpy sheet, 20x shadow step) needs 0.2.
    # Swept (bench/results/sweep_default.json, default scan at 400x400, vs brute force): 1.0 /
    # 0.5 / 0.25 / 0.1 -> 0.54 (max 1.04) / 0.17 / 0.02 / 0.003 %: kept (1.0 exceeds 1 % on one
    # of the 2 images); the sweep's time of 0.5 carries the first point's one-time costs
    epsilon: float = spec(0.5, lo=0.0, lo_open=True, hi=10.0, doc="solid-angle criterion")
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
    # in progressive passes of two half-buffers over the head's pixels until every face
    # region's mean is known to target_rel_se or budget_s runs out (groundtruth/progressive.py).
    # 1 % everywhere took 0.6-3.8 M paths per lighting condition of the default scene
    # (bench/results/reference_passes.json), ~30 us a path on 2 idle cores: 340 s for the
    # four, so the default budget (40 s each) reaches ~1.5-2 % and keeps a cold default run
    # near 5 minutes; a larger budget_s continues from the cached passes.
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
    budget_s: float = spec(40.0, lo=0.0, hi=1e7, doc="seconds of rendering per lighting condition "
                                                     "(0 = no limit); a larger budget continues "
                                                     "from the cached passes")
    max_passes: int = spec(0, lo=0, hi=1 << 20, doc="stop after this many passes (0 = no limit); "
                                                    "like budget_s, continued from the cache")
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
    # one message.  Noise is measured like the reference's, on blocks of `block` camera
    # pixels (0: one reference pixel, 8 x 8 on the default camera); 2 % on those blocks took
    # 30-36 samples per pixel for Burley under point, disc and directional light, 284 under
    # the sunset, 68 for the random walk (default scan at 400 x 400, bench/results/cycles.json):
    # 5 %, 6 x fewer samples, keeps them near the reference's own noise at the ranking's
    # 4 x 4-pixel blocks (2.5 %), where the report subtracts each image's noise
    mappings: tuple = spec(("matched", "native"), choices=("matched", "native"),
                           doc="inputs from the skin: matched (fitted to the skin's flat-slab "
                               "Rd and mean exit radius), native (radius = mean free path, "
                               "base colour = albedo); images of native end in _native")
    geometries: tuple = spec(("high",), choices=("high", "low"),
                             doc="meshes rendered (those also in render.geometries)")
    target_noise: float = spec(0.05, lo=0.0, lo_open=True, hi=1.0,
                               doc="relative RMSE noise on reference-pixel blocks to reach")
    block: int = spec(0, lo=0, hi=1024, doc="noise block in camera pixels (0: the reference's)")
    pilot_spp: int = spec(4, lo=1, hi=4096, doc="samples per pixel of each half's first pass")
    max_spp: int = spec(256, lo=1, hi=1 << 16, doc="samples per pixel of each half, at most")
    seed: int = spec(1, lo=0, hi=1 << 20, doc="half-images use seeds 2 (seed + k) and 2 (seed + k) + 1")
    threads: int = spec(2, lo=1, hi=1024, doc="Cycles render threads (fixed: same image for any)")


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
    render: RenderConfig = spec(factory=RenderConfig)
    optics: Any = spec(None, doc='layer stack: preset = "two_layer" or [[optics.layers]]')
    bssrdf: BssrdfConfig = spec(factory=BssrdfConfig)
    reference: ReferenceConfig = spec(factory=ReferenceConfig)
    causes: CausesConfig = spec(factory=CausesConfig)
    cycles: CyclesConfig = spec(factory=CyclesConfig)
    output: OutputConfig = spec(factory=OutputConfig)
    path: str = ""

    @property
    def light_by_name(self) -> dict:
        return {l.name: l for l in self.lights}

    def light_groups(self) -> tuple:
        """The lighting conditions to render: (label, tuple of LightConfig) pairs."""
        labels = self.render.lights or tuple(l.name for l in self.lights)
        return tuple((label, tuple(self.light_by_name[n] for n in label.split("+")))
                     for label in labels)

    def mesh_path(self) -> Path | None:
        if self.mesh.source == "procedural":
            return None
        return _resolve(self.mesh.source, self.path)

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
        return _resolve(value, self.path) if value else None


# --------------------------------------------------------------------------- validation
class _Problems(list):
    def add(self, where: str, key: str, msg: str):
        self.append(f"{where}: {key}{msg}")


def _did_you_mean(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


# Largest coordinate or size, in mm, after the unit conversion.  The renderer squares
# distances between points in float32 (a light sample's |q - p|^2, lighting/emitters.py),
# which overflows (3.4e38) beyond |q - p| ~ 1.8e19 mm; two points within 1e18 mm of the
# origin are at most 2 sqrt(3) 1e18 mm apart, 1.2e37 squared (a light-year is 9.5e18 mm).
MAX_LENGTH_MM = 1e18
UNIT_NAMES = {scale: name for name, scale in LENGTH_UNITS.items()}


def _check_number(value, meta, where, key, problems, *, integer: bool, scale: float) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            integer and not isinstance(value, int)):
        kind = "an integer" if integer else "a number"
        problems.add(where, key, f" = {fmt(value)}: must be {kind}")
        return None
    if not math.isfinite(value):
        problems.add(where, key, f" = {fmt(value)}: must be finite")
        return None
    lo, hi = meta.get("lo"), meta.get("hi")
    length = meta.get("unit") == "length"
    unit = f" ({UNIT_NAMES.get(scale, 'mm')})" if length else ""
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        rel = ">" if meta.get("lo_open") else ">="
        problems.add(where, key, f" = {fmt(value)}{unit}: must be {rel} {lo}")
        return None
    if hi is not None and (value > hi or (meta.get("hi_open") and value == hi)):
        rel = "<" if meta.get("hi_open") else "<="
        problems.add(where, key, f" = {fmt(value)}{unit}: must be {rel} {hi}")
        return None
    out = value * scale if scale != 1.0 else value
    if length and not abs(out) <= MAX_LENGTH_MM:
        problems.add(where, key, f" = {fmt(value)}{unit}: is {float(out):g} mm; a length "
                     f"must be at most {MAX_LENGTH_MM:g} mm in magnitude (the renderer squares "
                     "distances in single precision, which overflows beyond)")
        return None
    return out


def _check_value(value, tp, meta, where, key, problems, length_scale):
    scale = length_scale if meta.get("unit") == "length" else 1.0
    choices = _choices(meta)
    if tp is bool:
        if not isinstance(value, bool):
            problems.add(where, key, f" = {fmt(value)}: must be true or false")
            return None
        return value
    if tp is int or tp is float:
        return _check_number(value, meta, where, key, problems, integer=tp is int, scale=scale)
    if tp is str:
        if not isinstance(value, str):
            problems.add(where, key, f" = {fmt(value)}: must be a string")
            return None
        if choices and value not in choices:
            problems.add(where, key, f" = {fmt(value)}: must be one of "
                         + ", ".join(fmt(c) for c in choices) + _did_you_mean(value, choices))
            return None
        return value
    if tp is tuple:  # vectors of 3 numbers, or lists of choices / names
        if not isinstance(value, list):
            problems.add(where, key, f" = {fmt(value)}: must be an array")
            return None
        if choices:
            bad = [v for v in value if v not in choices]
            if bad:
                problems.add(where, key, f" = {fmt(value)}: {fmt(bad[0])} is not one of "
                             + ", ".join(fmt(c) for c in choices)
                             + _did_you_mean(str(bad[0]), choices))
                return None
            return tuple(value)
        if meta.get("names"):
            bad = [v for v in value if not isinstance(v, str)]
            if bad:
                problems.add(where, key, f" = {fmt(value)}: {fmt(bad[0])} is not a string; "
                             "must be an array of names (strings)")
                return None
            return tuple(value)
        if len(value) != 3:
            problems.add(where, key, f" = {fmt(value)}: must have 3 numbers")
            return None
        out = [_check_number(v, meta, where, f"{key}[{i}]", problems, integer=False, scale=scale)
               for i, v in enumerate(value)]
        return None if any(v is None for v in out) else tuple(float(v) for v in out)
    return value


def _build(cls, table, where: str, prefix: str, problems: _Problems, length_scale: float):
    """Validate ``table`` against dataclass ``cls``; collect problems, return instance or None."""
    if not isinstance(table, dict):
        problems.add(where, prefix.rstrip("."), f" = {fmt(table)}: must be a table")
        return None
    hints = get_type_hints(cls)
    known = {f.name: f for f in fields(cls) if f.name != "path"}
    for key in table:
        if key not in known:
            problems.add(where, prefix + key, ": unknown key" + _did_you_mean(key, known)
                         + f"; allowed: {', '.join(known)}")
    values = {}
    for name, f in known.items():
        key = prefix + name
        if name not in table:
            if f.default is MISSING and f.default_factory is MISSING:
                problems.add(where, key, ": required key is missing")
            continue
        tp = hints[name]
        if is_dataclass(tp):
            values[name] = _build(tp, table[name], where, key + ".", problems, length_scale)
        else:
            values[name] = _check_value(table[name], tp, f.metadata, where, key, problems,
                                        length_scale)
    if any(v is None for k, v in values.items() if k in table):
        return None
    try:
        return cls(**values)
    except TypeError:
        return None


def _fmt_default(f) -> str:
    if f.default_factory is not MISSING or f.default is MISSING:
        return ""
    v = f.default
    if isinstance(v, tuple) and all(isinstance(x, str) for x in v):
        return "[" + ", ".join(v) + "]" if v else "[]"
    if isinstance(v, float) and v.is_integer() and abs(v) >= 1e4:
        return f"{int(v):,}"
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 1e4:
        return f"{v:,}"
    return fmt(v).replace("True", "true").replace("False", "false")


def _choices(meta) -> tuple | None:
    """A field's allowed values: a tuple, or a function giving them (the registered models,
    which plugins may extend)."""
    choices = meta.get("choices")
    return choices() if callable(choices) else choices


def _fmt_rule(meta) -> str:
    if _choices(meta):
        return "one of " + ", ".join(str(c) for c in _choices(meta))
    parts = []
    if meta.get("lo") is not None:
        parts.append((">" if meta.get("lo_open") else ">=") + f" {meta['lo']}")
    if meta.get("hi") is not None:
        parts.append(("<" if meta.get("hi_open") else "<=") + f" {meta['hi']}")
    return ", ".join(parts)


SCHEMA_TABLES = (("scene", SceneInfo), ("mesh", MeshConfig), ("bake", BakeConfig),
                 ("camera", CameraConfig), ("[lights]", LightConfig), ("render", RenderConfig),
                 ("bssrdf", BssrdfConfig), ("reference", ReferenceConfig),
                 ("causes", CausesConfig), ("cycles", CyclesConfig), ("output", OutputConfig))


def schema_markdown() -> str:
    """The scene-format reference, generated from the schema's own field docs (README.md holds
    this text between its ``scene-format`` markers; tests/test_config.py keeps them equal)."""
    lines = ["| key | default | allowed | what |", "|---|---|---|---|"]
    for table, cls in SCHEMA_TABLES:
        for f in fields(cls):
            unit = " (length)" if f.metadata.get("unit") == "length" else ""
            doc = f.metadata.get("doc", "").replace("|", "/")
            lines.append(f"| `[{table}] {f.name}` | {_fmt_default(f)} | {_fmt_rule(f.metadata)}"
                         f"{unit} | {doc} |")
    return "\n".join(lines)


def _resolve(path: str, scene_path: str) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute() and scene_path and not scene_path.startswith("<"):
        p = Path(scene_path).parent / p
    return p


def default_scene_path() -> Path:
    """The embedded default scene (the packaged Lee Perry-Smith scan), shipped in the package."""
    return Path(str(resources.files("dermis.scenes"))) / "default.toml"


def load_scene(path: str | Path | None = None, *, overrides: dict | None = None) -> Scene:
    """Load and validate a scene file.

    Parameters
    ----------
    path : str or Path, optional
        TOML scene file; None loads the embedded default (:func:`default_scene_path`).
    overrides : dict, optional
        Nested dict merged over the file's tables before validation (API/tests).

    Raises
    ------
    ConfigError
        On any problem; the message lists every problem with file, key, value and rule.
    """
    path = Path(path) if path is not None else default_scene_path()
    where = str(path)
    if not path.is_file():
        raise ConfigError(f"{where}: scene file does not exist")
    try:
        table = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{where}: not a text (UTF-8) file") from None
    return scene_from_dict(table, where=where, overrides=overrides)


def scene_warnings(scene: Scene) -> list[str]:
    """Settings that validate but make a run useless (it would render nothing, or black)."""
    where = scene.path
    out = []
    r = scene.render
    if not r.models:
        out.append(f"{where}: render.models = []: nothing is rendered (only the meshes are "
                   "prepared)")
    elif not r.geometries:
        out.append(f"{where}: render.geometries = []: nothing is rendered (only the meshes are "
                   "prepared)")
    for label, lights in scene.light_groups():
        dark = [l for l in lights if not any(l.intensity if l.type != "environment"
                                             else (l.scale,))]
        if r.models and r.geometries and len(dark) == len(lights):
            keys = ", ".join(f"lights.{l.name}." + ("scale = 0.0" if l.type == "environment"
                                                    else f"intensity = {fmt(l.intensity)}")
                             for l in dark)
            out.append(f"{where}: lighting condition {fmt(label)} emits no light ({keys}); "
                       "its renders will be black")
    own = getattr(scene.optics, "profile", None)
    readers: dict = {}      # layer-profile model -> the rendered models that read it
    for name in r.models:
        m = model(name)
        if m.profiles:
            readers.setdefault(m.profile or own, []).append(name)
    for profile, names in readers.items():
        if len(names) > 1:
            out.append(f"{where}: render.models has {' and '.join(names)}, but optics.profile = "
                       f"{fmt(profile)} makes them the same image (drop optics.profile to "
                       "compare the multipole with the Monte Carlo profile)")
    return out


def _sections(body: dict, where: str, length_scale: float):
    """The scene's tables that validate on their own (None for the others): the cross-field
    checks then still run when some other table has a problem (all problems listed at once)."""
    from types import SimpleNamespace
    hints = get_type_hints(Scene)
    out = {}
    for f in fields(Scene):
        if not is_dataclass(hints.get(f.name)):
            continue
        cls, table = hints[f.name], body.get(f.name, {})
        if isinstance(table, dict):  # keep the keys that validate on their own (others: default)
            table = {k: v for k, v in table.items() if _build(
                cls, {k: v}, where, f.name + ".", _Problems(), length_scale) is not None}
        out[f.name] = _build(cls, table, where, f.name + ".", _Problems(), length_scale)
    return SimpleNamespace(**out)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def scene_from_dict(table: dict, *, where: str = "<scene>", overrides: dict | None = None) -> Scene:
    """Validate an already-parsed scene table (see :func:`load_scene`)."""
    layers = registry.section("optics")      # the layer optics own their validation
    parse_layer_stack, PRESETS = layers.parse_layer_stack, layers.PRESETS
    split_profile_options, with_profile = layers.split_profile_options, layers.with_profile

    if overrides:
        table = _merge(table, overrides)
    problems = _Problems()
    units = table.get("scene", {}).get("units", "mm") if isinstance(table.get("scene"), dict) else "mm"
    length_scale = LENGTH_UNITS.get(units, 1.0) if isinstance(units, str) else 1.0  # else: refused
    body = {k: v for k, v in table.items() if k not in ("lights", "optics", "sweep")}
    if "sweep" in table and not isinstance(table["sweep"], dict):  # checked by `dermis sweep`
        problems.add(where, "sweep", f" = {fmt(table['sweep'])}: must be a table ([sweep])")
    scene = _build(Scene, body, where, "", problems, length_scale)

    lights, light_index = [], []
    raw_lights = table.get("lights", [])
    if not isinstance(raw_lights, list):
        problems.add(where, "lights", ": must be an array of tables ([[lights]])")
        raw_lights = []
    for i, lt in enumerate(raw_lights):
        light = _build(LightConfig, lt, where, f"lights[{i}].", problems, length_scale)
        if light is not None:
            lights.append(light)
            light_index.append(i)
    for k, light in enumerate(lights):  # map paths are relative to the scene file
        i = light_index[k]
        why = plain_name_problem(light.name, extra="+")
        if why:
            problems.add(where, f"lights[{i}].name", f" = {fmt(light.name)}: {why} (light "
                         "names become parts of output file names; '+' joins lights in "
                         "render.lights)")
        why = direction_problem(light.direction)
        if light.type in ("directional", "disc") and why:
            problems.add(where, f"lights[{i}].direction", f" = {fmt(light.direction)}: {why} "
                         f"(the {light.type} light's "
                         + ("direction towards the light)" if light.type == "directional"
                            else "disc normal)"))
        if light.type == "environment" and light.map != "procedural_sunset":
            p = _resolve(light.map, where)
            if not p.is_file():
                problems.add(where, f"lights[{i}].map", f" = {fmt(light.map)}: file not found "
                             f'({p}); use "procedural_sunset" for the embedded sky')
            else:
                problems += check_environment_file(p, where, f"lights[{i}].map", light.map)
            lights[k] = replace(light, map=str(p.resolve()))
    names = [l.name for l in lights]
    # lights refused above keep their names for render.lights (one problem, not two)
    named = names + [lt["name"] for lt in raw_lights if isinstance(lt, dict)
                     and isinstance(lt.get("name"), str) and lt["name"] not in names]
    for n in {n for n in names if names.count(n) > 1}:
        problems.add(where, "lights", f": name {fmt(n)} is used twice; names must be unique")

    optics = table.get("optics", {"preset": "two_layer"})
    stack = None
    profile = {}
    if isinstance(optics, dict):  # profile / photons / seed: the BSSRDF's profile model
        optics, profile, bad = split_profile_options(optics, where=f"{where}: optics")
        problems.extend(bad)
    if not isinstance(optics, dict):
        problems.add(where, "optics", f" = {fmt(optics)}: must be a table")
    elif "preset" in optics:
        extra = set(optics) - {"preset"}
        if extra:
            problems.add(where, "optics", f": preset and {sorted(extra)} conflict; give either "
                         "preset or an explicit [[optics.layers]] stack")
        elif not isinstance(optics["preset"], str) or optics["preset"] not in PRESETS:
            problems.add(where, "optics.preset", f" = {fmt(optics['preset'])}: must be one of "
                         + ", ".join(fmt(p) for p in PRESETS)
                         + _did_you_mean(str(optics["preset"]), PRESETS))
        else:
            stack = PRESETS[optics["preset"]]
    else:
        try:
            stack = parse_layer_stack(optics, where=f"{where}: optics")
        except ConfigError as exc:
            problems.append(str(exc))
    if stack is not None:
        stack = with_profile(stack, **profile)

    # cross-field checks run on every table that validated, even when another did not
    sc = scene if scene is not None else _sections(body, where, length_scale)
    why = plain_name_problem(sc.scene.name) if sc.scene is not None else None
    if why:
        problems.add(where, "scene.name", f" = {fmt(sc.scene.name)}: {why} (outputs go "
                     "to output_dir/<scene.name>/)")
    render = sc.render
    if render is not None:
        for label in render.lights:
            parts = label.split("+")
            for n in parts:
                if n not in named:
                    problems.add(where, "render.lights", f": {fmt(n)} (in {fmt(label)}) names "
                                 "no [[lights]] entry; defined: "
                                 + (", ".join(fmt(x) for x in named) or "none"))
            for n in sorted({n for n in parts if parts.count(n) > 1}):
                problems.add(where, "render.lights", f": {fmt(label)} names light {fmt(n)} "
                             f"{parts.count(n)} times; each light may appear once in a lighting "
                             "condition (raise its intensity to brighten it)")
        for key in ("lights", "models", "geometries"):
            values = getattr(render, key)
            for v in sorted({v for v in values if values.count(v) > 1}):
                problems.add(where, f"render.{key}", f": {fmt(v)} is listed twice; list each "
                             "once")
        if render.models and not raw_lights:
            problems.add(where, "lights", f": no [[lights]] defined, but render.models = "
                         f"{fmt(list(render.models))} need at least one light (or set "
                         "render.models = [] to prepare the meshes only)")
    if sc.camera is not None:
        problems += check_camera(sc.camera, where)
    if render is not None and stack is not None:   # what each rendered model needs
        for name in render.models:
            check = model(name).check
            found = check(stack, dict(vars(sc)), where) if check is not None else []
            problems += [p for p in found if p not in problems]   # bssrdf_mc shares bssrdf's
    given = table.get("reference")
    if sc.reference is not None and isinstance(given, dict):
        labels = (render.lights or tuple(names)) if render is not None else None
        problems += check_reference(sc.reference, set(given), sc.camera, labels, where)
    if sc.mesh is not None:
        if sc.mesh.source != "procedural":
            p = _resolve(sc.mesh.source, where)
            if not p.is_file():
                problems.add(where, "mesh.source", f" = {fmt(sc.mesh.source)}: file not found "
                             f"({p}); use \"procedural\" for the embedded head")
        for key in ("texture", "displacement"):
            val = getattr(sc.mesh, key)
            if val and not _resolve(val, where).is_file():
                problems.add(where, f"mesh.{key}", f" = {fmt(val)}: file not found "
                             f"({_resolve(val, where)})")
        if sc.mesh.low_triangles >= sc.mesh.high_triangles:
            problems.add(where, "mesh.low_triangles", f" = {sc.mesh.low_triangles}: must be "
                         f"< mesh.high_triangles ({sc.mesh.high_triangles})")
    if problems:
        raise ConfigError("\n".join(problems))
    out = Scene(**{**{f.name: getattr(scene, f.name) for f in fields(Scene)},
                   "lights": tuple(lights), "optics": stack, "path": where})
    from .resources import resource_problems   # resources reads this module's vocabulary
    problems += [f"{where}: {p}" for p in resource_problems(out)]
    if problems:
        raise ConfigError("\n".join(problems))
    return out
